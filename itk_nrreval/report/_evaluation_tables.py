"""The tables of an evaluation's HTML report (:mod:`.evaluation_page`): its scores and their
legend, the numbers registration papers report, every overlap weighting, the pairwise
differences, deformation plausibility and coverage, and the frame-estimate spread. Each
function takes the :class:`~itk_nrreval.evaluation.EvaluationResult` and returns HTML.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from ..io.label_names import label_text
from ._format import format_number, format_percent
from ._html import escape, legend_list, table_html, value_ci
from .evaluation_text import (
    TABLE_OVERLAPS,
    TIES_WORDS,
    deformation_metrics,
    format_rank,
    frame_spread_flagged,
    frame_spread_words,
    specificity_units,
)

__all__ = [
    "FRAME_WORDS",
    "scores_table",
    "scores_legend",
    "paper_metrics_table",
    "overlap_table",
    "pairwise_differences",
    "plausibility_table",
    "frames_table",
]

#: The overlap weightings the tables show (every one further down): each label counts the same.
_TABLE_OVERLAPS = tuple(m for m, _ in TABLE_OVERLAPS)

#: What each overlap weighting counts, in words.
_WEIGHTING_WORDS = {
    "volume": "label weight 1: every voxel counts the same, so large labels dominate",
    "inverse_volume": "label weight 1 / volume: every label counts the same, whatever its size",
    "inverse_volume_squared": "label weight 1 / volume²: small labels count most",
    "complexity": "label weight = boundary complexity: intricate labels count more",
    "inverse_volume_complexity": "label weight = complexity / volume",
}


#: How each registration was brought into the common frame, in words (its frame's method).
FRAME_WORDS = {
    "common": "this is the common frame",
    "frame_transform": "the frame transform given in the manifest",
    "reference_index": "its reference is one of the images (the common registration's "
    "transform of that image)",
    "mean": "the mean of the per-image estimates (a displacement field)",
}


def _rel(result, measure: str, name: str) -> str:
    rel = result.relative_ranks[measure][name]
    # the rank on a line of its own: "100.0% (1 (tied))" on one line widened the table past
    # the page
    return f"{format_percent(rel)}<br><small>rank {format_rank(result, measure, name)}</small>"


def scores_table(result, names: Sequence[str], slugs: Mapping[str, str]) -> str:
    """The scores table: per registration its scores with their intervals, relative
    scores and ranks, its coverage and its flags."""
    overlaps = [m for m in _TABLE_OVERLAPS if m in result.ranks]
    head = ["Registration", "Specificity<br>[95% CI]", "MC s.e.", "Rel. (rank)"]
    head += ["Generalization<br>[95% CI]", "s.e.", "Rel. (rank)"]
    for m in overlaps:
        weighting = escape(m.split(".", 1)[1].replace("_", " "))
        head += [f"Overlap, {weighting}<br>[95% CI]", "Rel. (rank)"]
    head += ["Coverage", "Flags"]
    rows = []
    for n in names:
        s = result.scores[n]
        cells = [f'<a href="#{slugs[n]}">{escape(n)}</a>']
        cells += [
            value_ci(s.specificity.value, s.intervals.get("specificity")),
            format_number(s.specificity.stderr, 2),
            _rel(result, "specificity", n),
            value_ci(s.generalization.value, s.intervals.get("generalization")),
            format_number(s.generalization.stderr, 2),
            _rel(result, "generalization", n),
        ]
        for m in overlaps:
            cells += [value_ci(s.measures()[m], s.intervals.get(m)), _rel(result, m, n)]
        cov = s.coverage.fraction if s.coverage is not None else None
        cells.append("–" if cov is None else f"{cov:.1%}")
        cells.append(
            f'<a class="flag" href="#plausibility">{len(s.flags)} flag'
            f"{'s' if len(s.flags) > 1 else ''}</a>"
            if s.flags
            else "none"
        )
        rows.append((n, cells))
    classes = ["flagged" if result.scores[n].flags else "" for n, _ in rows]
    return table_html(head, [c for _, c in rows], text=(0, -1), classes=classes, wide=True)


def scores_legend(result) -> str:
    """The legend of the scores table: what each column measures, in which units, and
    which way is better."""
    o = result.options
    first = next(iter(result.scores.values()))
    n = first.specificity.n_images
    units = specificity_units(result)
    cov = first.coverage
    evaluated = f"{cov.evaluated:.1%}" if cov is not None else "all"
    groups = o.get("resamples")
    jack = (
        f"a grouped jackknife over the subjects ({groups} groups of the N = {n} subjects)"
        if groups
        else "a jackknife over the subjects"
    )
    items = [
        (
            "Specificity",
            "how close images drawn at random from the registration's texture model (a "
            "Gaussian model of the N images resampled into the common frame) come to the "
            f"nearest real image: the mean distance in the model's parameter space ({units}"
            f"; M = {o['n_samples']:,} samples, seed {o['seed']}). <b>Lower is better</b>: a "
            "good registration's model only makes realistic images.",
        ),
        (
            "95% CI",
            f"the subject-level 95% interval, from {jack}: would the score hold for other "
            "subjects? Compare registrations with it (and with the pairwise differences "
            "further down). A dash: not computed (confidence off, or fewer than 4 subjects).",
        ),
        (
            "MC s.e.",
            "Monte-Carlo standard error of the specificity estimate only: the error from "
            "drawing a finite number M of model samples. It shrinks as M grows and says "
            "nothing about other subjects.",
        ),
        (
            "Generalization",
            "the converse: how close each real image comes to the nearest model sample; same "
            "units, <b>lower is better</b>. Its s.e. is the standard deviation over the N "
            "images divided by sqrt(N - 1); its 95% CI is subject-level, as above.",
        ),
        (
            "Overlap",
            "generalized Tanimoto overlap of the label maps resampled into the common frame "
            "(fuzzy memberships, all pairs of images at once), <b>0 to 1, higher is "
            "better</b>, one column per label weighting (every weighting further down). "
            "Even a perfect registration stays below 1: interpolating the labels into the "
            "common frame blurs every boundary over about a voxel.",
        ),
        (
            "Rel. (rank)",
            "the normalised score 100% &times; (worst &minus; x) / (worst &minus; best) among "
            "the registrations compared: 100% for the best, 0% for the worst, linear between; "
            "it is <b>not a rank</b>. The rank (1 = best) is below it. " + escape(TIES_WORDS),
        ),
        (
            "Coverage",
            "the fraction of the common grid (inside the mask) where every image has a value "
            "under this registration (its field of view carried through the transforms). The "
            f"scores are taken on the {evaluated} covered by every image under every "
            "registration, the same voxels for all.",
        ),
        (
            "Flags",
            "why the deformation is physically implausible (voxels that fold, a rough "
            "Jacobian, frame estimates that disagree); thresholds under Options. A flagged "
            "registration keeps its scores; a flag is a warning, not a decision (only severe "
            "folding decides against it: see the verdict).",
        ),
    ]
    return legend_list(items)


def _mean_sd(summary, digits: int = 3) -> str:
    """A summary's mean ± s.d. for a cell; a dash when it has no case."""
    if not summary.n_cases:
        return "–"
    return f"{format_number(summary.mean, digits)} ± {format_number(summary.std, 2)}"


def _fraction_cell(v) -> str:
    return "–" if v is None else f"{v:.2%}"


def paper_metrics_table(result, names: Sequence[str]) -> str:
    """The numbers registration papers report (Learn2Reg's): per registration Dice and HD95
    over its cases with their 30% worst, SDlogJ and the folded (and any non-diffeomorphic)
    fraction; per label in a closed list; and how they differ from the published script."""
    deformation: list[str] = []
    for n in names:
        keys = deformation_metrics(result.scores[n].plausibility)
        deformation += [k for k in keys if k not in deformation]
    words = {
        "sdlogj": "SDlogJ",
        "folded_fraction": "Folded voxels",
        "nondiffeomorphic_fraction": "Non-diffeomorphic voxels",
        "nondiffeomorphic_volume": "Non-diffeomorphic volume",
    }
    head = ["Registration", "Cases", "Dice<br>mean ± s.d.", "Dice<br>worst 30%"]
    head += ["HD95 (mm)<br>mean ± s.d.", "HD95 (mm)<br>worst 30%"]
    head += [escape(words.get(k, k.replace("_", " ").capitalize())) for k in deformation]
    rows, label_rows = [], []
    for n in names:
        s = result.scores[n]
        lm = s.label_metrics
        cells = [escape(n)]
        if lm is None:
            cells += ["–"] * 5
        else:
            dice, hd = lm.overall()
            against = "pairs" if lm.reference is None else f"vs subject {lm.reference}"
            cells += [f"{len(lm.cases)} ({against})", _mean_sd(dice)]
            cells += [format_number(dice.worst30, 3), _mean_sd(hd), format_number(hd.worst30, 3)]
            for value, (ld, lh) in lm.per_label().items():
                label_rows.append(
                    [escape(n), escape(label_text(value, lm.names)), str(ld.n_cases), _mean_sd(ld)]
                    + [format_number(ld.worst30, 3), _mean_sd(lh), format_number(lh.worst30, 3)]
                )
        values = deformation_metrics(s.plausibility)
        for k in deformation:
            v = values.get(k)
            cells.append(format_number(v, 3) if k == "sdlogj" else _fraction_cell(v))
        rows.append(cells)
    out = [table_html(head, rows, text=(0,), wide=True)]
    if label_rows:
        label_head = ["Registration", "Label", "Cases", "Dice<br>mean ± s.d."]
        label_head += ["Dice<br>worst 30%", "HD95 (mm)<br>mean ± s.d.", "HD95 (mm)<br>worst 30%"]
        out.append(
            f"<details><summary>Per label ({len(label_rows)} rows)</summary>"
            + table_html(label_head, label_rows, text=(0,))
            + "</details>"
        )
    out.append(
        legend_list(
            [
                (
                    "Cases",
                    "each subject against the registration's reference subject (vs subject "
                    "i: registered to it) or, without one, every pair of subjects; in the "
                    "common frame, each subject's labels the label of largest resampled "
                    "membership, inside the evaluated region. A label one of the two label "
                    "maps lacks is not compared.",
                ),
                (
                    "Dice",
                    "2 |A ∩ B| / (|A| + |B|) per label and case, voxels counted; the table's "
                    "figure is each case's mean over its labels, then over the cases. "
                    "<b>Higher is better.</b>",
                ),
                (
                    "HD95",
                    "the 95th percentile Hausdorff distance in mm on the common grid's "
                    "physical spacing: the larger of the two directed 95th percentiles of "
                    "the distances between the two labels' boundaries. <b>Lower is "
                    "better.</b>",
                ),
                (
                    "Worst 30%",
                    "the mean over the 30% worst cases (Learn2Reg's robustness): the "
                    "lowest Dice, the <b>largest</b> HD95.",
                ),
                (
                    "SDlogJ, folded",
                    "as in the plausibility table below: the standard deviation of log det J "
                    "(the determinant itself, nothing added) and the fraction of voxels "
                    "with det J &le; 0 counted before any clipping, means over the images.",
                ),
                (
                    "Against the published script",
                    "Learn2Reg's evaluation script takes log(det J + 3), counts folds after "
                    "clipping det J at 1e-9 (always 0), measures HD95 in voxels and takes "
                    "its 30% aggregate on the low side of every measure, the best tail "
                    "for HD95 (MDL-UzL/L2R issues #6, #7, #8); these numbers do not, and "
                    "are not comparable with tables made by it.",
                ),
            ]
        )
    )
    return "".join(out)


def overlap_table(result, names: Sequence[str]) -> str:
    """Every overlap weighting of every registration, with what each weighting counts."""
    ws = [m.split(".", 1)[1] for m in result.measures if m.startswith("overlap.")]
    if not ws:
        return ""
    head = ["Registration"]
    for w in ws:
        head += [f"{escape(w.replace('_', ' '))}<br>[95% CI]", "Rel. (rank)"]
    rows = []
    for n in names:
        s = result.scores[n]
        row = [escape(n)]
        for w in ws:
            row += [
                value_ci(s.overlap[w], s.intervals.get(f"overlap.{w}")),
                _rel(result, f"overlap.{w}", n),
            ]
        rows.append(row)
    words = "".join(
        f"<li><b>{escape(w.replace('_', ' '))}</b>: {escape(_WEIGHTING_WORDS.get(w, w))}</li>"
        for w in ws
    )
    return (
        "<h3>Overlap by label weighting</h3>"
        + table_html(head, rows, wide=True)
        + f"<ul>{words}</ul>"
    )


def pairwise_differences(result) -> str:
    """The pairwise differences with their subject-level 95% intervals, in a closed list."""
    comps = list(result.comparisons)
    if not comps:
        return "<p>No pairwise differences: confidence was not computed.</p>"
    rows = [
        [
            escape(c.measure),
            f"{escape(c.a)} &minus; {escape(c.b)}",
            format_number(c.difference),
            f"[{format_number(c.ci95[0])}, {format_number(c.ci95[1])}]",
            "yes" if c.separable else "no",
        ]
        for c in comps
    ]
    head = ["Measure", "a &minus; b", "Difference", "95% CI", "Separable (CI excludes 0)"]
    return (
        "<details><summary>Pairwise differences with their subject-level 95% intervals "
        f"({len(comps)})</summary>" + table_html(head, rows, text=(0, 1)) + "</details>"
    )


def plausibility_table(result, names: Sequence[str]) -> str:
    """Deformation plausibility and coverage per registration, with its legend."""
    rows = []
    for n in names:
        s = result.scores[n]
        p = s.plausibility
        ic = p.inverse_consistency_mm
        cov = s.coverage
        cells = [
            f"{p.folded_fraction:.2%}",
            f"{p.folded_max:.2%}",
            format_number(p.sdlogj, 3),
            format_number(p.jacobian_min, 3),
            format_number(p.jacobian_max, 3),
            "–" if ic is None else format_number(ic, 3),
            "–" if cov is None else f"{cov.fraction:.1%}",
            "–" if cov is None or not cov.per_image else f"{min(cov.per_image):.1%}",
        ]
        flags = "; ".join(escape(f) for f in s.flags) if s.flags else "plausible"
        rows.append([escape(n), *cells, flags])
    th = result.options.get("thresholds", {})
    head = ["Registration", "Folded voxels (mean)", "Folded (worst image)", "SDlogJ"]
    head += ["det J min", "det J max", "Inverse consistency (mm)", "Coverage, all images"]
    head += ["Coverage, least image", "In words"]
    classes = ["flagged" if result.scores[n].flags else "" for n in names]
    return (
        table_html(head, rows, text=(0, -1), classes=classes, wide=True) + '<dl class="legend">'
        "<dt>Folded voxels</dt><dd>fraction of the voxels of the registration's reference "
        "grid (inside the mask) where the Jacobian determinant det J &le; 0: the map folds "
        "space there. Mean over the images, and the worst single image. Flagged above "
        f"{th.get('folded_mean', float('nan')):.0%} on average or "
        f"{th.get('folded_max', float('nan')):.0%} in one image.</dd>"
        "<dt>SDlogJ</dt><dd>standard deviation of log det J over the voxels that do not "
        "fold (the roughness of the deformation; 0 for a linear transform), mean over the "
        "images.</dd>"
        "<dt>det J min / max</dt><dd>extreme local volume changes over all images, "
        "unclipped (negative where the map folds).</dd>"
        "<dt>Inverse consistency</dt><dd>mean round-trip error |T<sup>-1</sup>(T(p)) "
        "&minus; p| in mm with a numerical inverse; grows where the map folds.</dd>"
        "<dt>Coverage</dt><dd>fraction of the common grid (inside the mask) covered by "
        "every image under this registration, and by the image that covers least.</dd>"
        "</dl>"
    )


def frames_table(result, names: Sequence[str]) -> str:
    """How each registration was brought into the common frame, and how far its per-image
    estimates of that frame spread."""
    rows = []
    for n in names:
        f = result.scores[n].frame
        rows.append(
            [
                escape(n),
                escape(FRAME_WORDS.get(f.method, f.method)),
                format_number(f.spread_mean_mm, 3),
                "flagged" if frame_spread_flagged(result, n) else "no",
                format_number(f.spread_max_mm, 3),
            ]
        )
    head = ["Registration", "Brought into the common frame by"]
    head += ["Spread, mean (mm)", "Mean above the flag threshold", "Spread, max (mm)"]
    return (
        table_html(head, rows, text=(0, 1))
        + "<p>Each registration has its own reference frame and is brought "
        f"into the common frame (<b>{escape(result.common_frame)}</b>'s) by a transform F. Each "
        "image gives its own estimate F<sub>i</sub> of it; the spread is how far those "
        "estimates lie from F (|F<sub>i</sub>(p) &minus; F(p)| over the images and the "
        f"voxels of the common grid, inside the mask). {escape(frame_spread_words(result)[1])}</p>"
    )
