"""``report.html``: one self-contained page that reads an evaluation, as MRIQC and fMRIPrep
reports are read.

The page opens from disk with no network and no JavaScript (:mod:`._html`). It gives, in
order: the verdict in words, with the subjects left off the common grid and how many subjects
each registration flags; the scores with their legend, units and intervals; the summary
figures (the same PNG bytes as the files beside it, ``subjects.png`` among them: every
subject's model-distance z-score); the numbers registration papers report (Dice and HD95 with
their worst 30%, SDlogJ, folding: :mod:`itk_nrreval.label_metrics`); per registration first
its subjects
(:mod:`itk_nrreval.subject_qc`: its registration flags, said once; its reference when that is
one of the subjects; its flagged subjects worst first, each with its name, concern, diagnosis
and subject flags in words, the subject in the common frame beside the mean image and a
checkerboard of the two; every subject ranked worst first by concern), then its mean image, a
checkerboard of two subjects, the label contours of one subject with a colour legend, a
log-Jacobian-determinant map and the histogram of log det J over all subjects; deformation
plausibility and coverage; the frame-estimate spread; the inputs and the options.

It stays light whatever the number of images N: every picture is a middle slice shrunk to at
most 256 pixels a side (:attr:`EvaluationResult.thumbnails
<itk_nrreval.evaluation.EvaluationResult.thumbnails>`, gathered by the pipeline: of subjects
0 and 1, and of the flagged subjects shown, at most
:data:`~itk_nrreval.report.evaluation_text.FLAGGED_SUBJECTS_SHOWN` per registration), and
there is a bounded number of pictures per registration; only the list of input files and
the closed list of each registration's subjects past the worst :data:`RANKED_SHOWN` grow
with N.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

from ..label_names import label_text
from ..subject_qc import ranked, registration_flags
from ._format import format_number, format_percent
from ._html import (
    SELF_CONTAINED,
    escape,
    figure_html,
    interval_text,
    item_text,
    key_value_table,
    legend_list,
    options_table,
    page_html,
    slug_ids,
    table_html,
    value_ci,
)
from ._plot import png_bytes
from .evaluation_figures import figure_pngs, images_figure, jacobian_figure, subject_figure
from .evaluation_text import (
    CONCERN_WORDS,
    FLAGGED_SUBJECTS_SHOWN,
    ORDER_WORDS,
    TABLE_OVERLAPS,
    TIES_WORDS,
    concern_text,
    deformation_metrics,
    format_rank,
    frame_spread_flagged,
    frame_spread_words,
    specificity_units,
)

__all__ = ["report_html", "RANKED_SHOWN"]

#: The overlap weightings the tables show (every one further down): each label counts the same.
_TABLE_OVERLAPS = tuple(m for m, _ in TABLE_OVERLAPS)


_DPI = 100  # pixels per inch of the per-registration figures

_WEIGHTING_WORDS = {
    "volume": "label weight 1: every voxel counts the same, so large labels dominate",
    "inverse_volume": "label weight 1 / volume: every label counts the same, whatever its size",
    "inverse_volume_squared": "label weight 1 / volume²: small labels count most",
    "complexity": "label weight = boundary complexity: intricate labels count more",
    "inverse_volume_complexity": "label weight = complexity / volume",
}

_FRAME_WORDS = {
    "common": "this is the common frame",
    "frame_transform": "the frame transform given in the manifest",
    "reference_index": "its reference is one of the images (the common registration's "
    "transform of that image)",
    "mean": "the mean of the per-image estimates (a displacement field)",
}


def _subject(result, i: int) -> str:
    """How subject i is named: its image file's name, or its index for objects in memory."""
    images = result.inputs.get("images") or []
    if i < len(images) and isinstance(images[i], str):
        return f"subject {i} ({Path(images[i]).name})"
    return f"subject {i}"


def _rel(result, measure: str, name: str) -> str:
    rel = result.relative_ranks[measure][name]
    # the rank on a line of its own: "100.0% (1 (tied))" on one line widened the table past
    # the page
    return f"{format_percent(rel)}<br><small>rank {format_rank(result, measure, name)}</small>"


def _scores_table(result, names: Sequence[str], slugs: Mapping[str, str]) -> str:
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


def _legend(result) -> str:
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


def _overlap_table(result, names: Sequence[str]) -> str:
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


def _comparisons(result) -> str:
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


def _plausibility_table(result, names: Sequence[str]) -> str:
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


def _mean_sd(summary, digits: int = 3) -> str:
    """A summary's mean ± s.d. for a cell; a dash when it has no case."""
    if not summary.n_cases:
        return "–"
    return f"{format_number(summary.mean, digits)} ± {format_number(summary.std, 2)}"


def _fraction_cell(v) -> str:
    return "–" if v is None else f"{v:.2%}"


def _paper_metrics(result, names: Sequence[str]) -> str:
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


def _frames_table(result, names: Sequence[str]) -> str:
    rows = []
    for n in names:
        f = result.scores[n].frame
        rows.append(
            [
                escape(n),
                escape(_FRAME_WORDS.get(f.method, f.method)),
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


def _flagged_subjects(result, name: str) -> str:
    """The subjects of a registration: its registration flags, said once; its reference
    when that is one of the subjects; how many subjects are flagged, then for each of the
    first :data:`~.evaluation_text.FLAGGED_SUBJECTS_SHOWN` (worst first, by concern) its
    name, diagnosis and subject flags in words and its picture beside the mean image, and a
    line for the rest; then every subject ranked by concern (:func:`_ranked_subjects`)."""
    s = result.scores[name]
    if not s.subjects:
        return ""  # not assessed (a result of an earlier version)
    flagged = ranked(s.flagged_subjects)
    judged = sum(not q.reference for q in s.subjects)
    of = f"of the {judged} subjects" + (
        " other than its reference" if judged < len(s.subjects) else ""
    )
    shared = registration_flags(s.subjects)
    parts = [
        f"<h3>Flagged subjects: {len(flagged)} {of} flagged</h3>"
        if flagged
        else f"<h3>Flagged subjects</h3><p>None {of} is flagged.</p>"
    ]
    if shared:
        parts.append(
            f'<p class="flag"><b>Registration flag{"s" if len(shared) > 1 else ""}</b> (a '
            "kind of flag at least half of the subjects carry: a property of this "
            "registration, said once, not a flag of each subject): "
            + "; ".join(escape(f) for f in shared)
            + ".</p>"
        )
    for q in s.subjects:
        if q.reference:
            parts.append(
                f"<p><b>{escape(_subject(result, q.index))}</b> is the reference of this "
                "registration (registered to itself): not judged.</p>"
            )
    if flagged:
        where = "the middle slice of " if result.mean_images[name].ndim == 3 else ""
        parts.append(
            "<p>Each subject compared with the rest of the cohort under this registration "
            "(robust z-scores, z = (x &minus; median) / (1.4826 MAD)): its distance to the "
            "texture model of the others, its deformation, its label overlap with the "
            "others, its coverage of the common grid. Worst first, by concern (below). "
            "Every subject's values are in <code>subjects.csv</code>; every z-score in "
            f'<a href="#figures">subjects.png</a>. The pictures: {where}the subject resampled '
            "into the common frame, the mean of the N images, and a checkerboard of the two "
            "(the subject on the first tile): where the subject is aligned, edges run on "
            "across the tile borders. One grey scale per picture; pale blue: outside the "
            "subject's field of view.</p>"
        )
    t = result.thumbnails.get(name, {})
    for q in flagged[:FLAGGED_SUBJECTS_SHOWN]:
        cause = q.diagnosis if q.diagnosis is not None else "no common cause recognised"
        words = (
            f"<b>{escape(_subject(result, q.index))}</b>, concern "
            f"{concern_text(q.concern)}<br><b>Diagnosis:</b> {escape(cause)}.<br>"
            "<b>Subject flags:</b> " + "; ".join(escape(f) for f in q.flags) + "."
        )
        if f"image_{q.index}" in t:
            png = png_bytes(subject_figure(result, name, q.index), dpi=_DPI)
            parts.append(figure_html(png, f"{name}: subject {q.index}", words))
        else:  # thumbnails of an earlier version, or a result put together in memory
            parts.append(f"<p>{words}<br>(No picture: its resampled slice was not kept.)</p>")
    rest = len(flagged) - FLAGGED_SUBJECTS_SHOWN
    if rest > 0:
        parts.append(
            f"<p>{rest} more flagged subject{'s' if rest > 1 else ''}, not shown: "
            "<code>subjects.csv</code> and <code>summary.md</code> list every one.</p>"
        )
    parts.append(_ranked_subjects(result, name))
    return "\n".join(parts)


#: How many subjects of a registration the ranked table shows open; the others follow in a
#: closed list, so the page stays short whatever N.
RANKED_SHOWN = 10


def _ranked_subjects(result, name: str) -> str:
    """Every subject of a registration worst first, by concern: rank, subject, concern,
    the z-score it came from, and what is flagged (the first :data:`RANKED_SHOWN` open,
    the others in a closed list)."""
    s = result.scores[name]
    rows = []
    for rank, q in enumerate(ranked(s.subjects), start=1):
        marks = []
        if q.reference:
            marks.append("reference of this registration")
        if q.flags:
            marks.append(f"{len(q.flags)} subject flag{'s' if len(q.flags) > 1 else ''}")
        if q.registration_flags:
            plural = "s" if len(q.registration_flags) > 1 else ""
            marks.append(f"shares the registration flag{plural}")
        rows.append(
            [
                str(rank),
                escape(_subject(result, q.index)),
                concern_text(q.concern),
                escape(q.concern_from or "–"),
                escape("; ".join(marks) or "–"),
            ]
        )
    head = ["Rank", "Subject", "Concern", "From", "Flagged"]
    classes = ["flagged" if q.flags else "" for q in ranked(s.subjects)]
    out = [
        "<h3>Every subject, worst first</h3><p>"
        + escape(CONCERN_WORDS)
        + " From: the term that contributes most to the concern.</p>",
        table_html(head, rows[:RANKED_SHOWN], text=(1, 3, 4), classes=classes[:RANKED_SHOWN]),
    ]
    if len(rows) > RANKED_SHOWN:
        out.append(
            f"<details><summary>The other {len(rows) - RANKED_SHOWN} subjects</summary>"
            + table_html(head, rows[RANKED_SHOWN:], text=(1, 3, 4), classes=classes[RANKED_SHOWN:])
            + "</details>"
        )
    return "".join(out)


def _registration_section(result, name: str) -> str:
    """The body of a registration's section: its flagged subjects, its scores in a line,
    its two figures."""
    s = result.scores[name]
    t = result.thumbnails.get(name, {})
    parts = [_flagged_subjects(result, name), "<h3>Scores, images and deformation</h3>"]
    summary = (
        f"Specificity {format_number(s.specificity.value)} "
        f"{interval_text(s.intervals.get('specificity'))}, generalization "
        f"{format_number(s.generalization.value)}"
    )
    if s.overlap:
        w = "inverse_volume" if "inverse_volume" in s.overlap else next(iter(s.overlap))
        summary += f", overlap ({w.replace('_', ' ')}) {format_number(s.overlap[w])}"
    summary += (
        f"; frame: {escape(_FRAME_WORDS.get(s.frame.method, s.frame.method))}, spread "
        f"{format_number(s.frame.spread_mean_mm, 3)} mm on average."
    )
    parts.append(f"<p>{summary}</p>")
    if s.flags:
        parts.append('<p class="flag">Flagged: ' + "; ".join(escape(f) for f in s.flags) + ".</p>")
    dim = result.mean_images[name].ndim
    where = "the middle slice of " if dim == 3 else ""
    if t:
        s0, s1 = _subject(result, 0), _subject(result, 1)
        cap = (
            f"Left: {where}the mean of the N resampled images in the common frame: sharp "
            "where the images agree. Middle: checkerboard of two subjects resampled into the "
            f"common frame ({escape(s0)} on the first tile, {escape(s1)} on the next): when they "
            "are aligned, edges run on across the tile borders. Right: "
            f"{escape(s0)} with the boundaries of its labels, resampled into the common frame "
            "(colour legend: label values). Common grey scale in the images' intensity units; "
            "pale blue: outside that image's field of view."
        )
        if "image_1" not in t:
            cap = f"Left: {where}the mean image. Right: {escape(s0)}."
    else:
        cap = f"{where.capitalize()}the mean of the N resampled images in the common frame."
    images = png_bytes(images_figure(result, name), dpi=_DPI)
    parts.append(figure_html(images, f"{name}: images", cap))
    jac = jacobian_figure(result, name)
    if jac is not None:
        parts.append(
            figure_html(
                png_bytes(jac, dpi=_DPI),
                f"{name}: Jacobian determinant",
                f"Left: log of the Jacobian determinant of {escape(_subject(result, 0))}'s "
                f"transform on {where}the registration's own reference grid (blue: local "
                "shrinking, red: growth, black: folding, grey: outside the mask). Right: "
                "histogram of log det J over every voxel of every subject (inside the mask), "
                "64 bins over [-2, 2]; the share beyond the bins and folded is printed.",
            )
        )
    return "\n".join(parts)


def _subjects_in_verdict(result, names: Sequence[str], slugs: Mapping[str, str]) -> str:
    """The verdict area's lines on the subjects: those left off the common grid (in no
    registration's scores), and how many subjects each registration flags (and how many
    registration flags its subjects share), linked to its section."""
    out = []
    left_out = result.options.get("left_out_of_scores") or []
    if left_out:
        who = ", ".join(escape(_subject(result, i)) for i in left_out)
        out.append(
            f"<p><b>Left out of every registration's scores</b> (off the common grid: its "
            f"transform maps the image (almost) outside it): {who}.</p>"
        )
    counts = []
    for n in names:
        subjects = result.scores[n].subjects
        if subjects:
            k = len(result.scores[n].flagged_subjects)
            judged = sum(not q.reference for q in subjects)
            what = f"{k} of {judged} subjects flagged" if k else "no subject flagged"
            if judged < len(subjects):
                what += " (its reference, one of the subjects, is not judged)"
            shared = len(registration_flags(subjects))
            if shared:
                what += f", {shared} registration flag{'s' if shared > 1 else ''}"
            counts.append(f'<a href="#{slugs[n]}">{escape(n)}</a>: {what}')
    if counts:
        out.append(
            "<p>Flagged subjects (each registration's section names them): "
            + "; ".join(counts)
            + ".</p>"
        )
    return "".join(out)


def _inputs_section(result) -> str:
    inp = dict(result.inputs)

    def item(v) -> str:
        if v is None:
            return "–"
        if isinstance(v, Mapping):
            return escape(", ".join(f"{k}: {val}" for k, val in v.items()))
        return f"<code>{escape(v)}</code>"

    images = inp.get("images") or []
    labels = inp.get("labels")
    rows = [
        ("Manifest", item(inp.get("manifest"))),
        ("Images (N)", str(inp.get("n_images", len(images)))),
        ("Label maps", "none" if not labels else f"{len(labels)} (one per image)"),
        ("Mask", item(inp.get("mask"))),
        ("Common frame", escape(inp.get("common_frame", result.common_frame))),
    ]
    out = [key_value_table(rows)]
    regs = inp.get("registrations") or {}
    if regs:
        head = ["Registration", "Reference", "Reference index", "Frame transform"]
        head.append("Transforms (first image)")
        cells = []
        for name, r in regs.items():
            first = (r.get("transforms") or [[]])[0]
            cells.append(
                [
                    escape(name),
                    item(r.get("reference")),
                    item_text(r.get("reference_index")),
                    item(r.get("frame_transform")),
                    ", ".join(item(x) for x in first),
                ]
            )
        out.append(table_html(head, cells, text=(0, 1, 3, 4), wide=True))
    listing = "".join(
        f"<li>{item(p)}" + (f" &mdash; labels {item(labels[i])}" if labels else "") + "</li>"
        for i, p in enumerate(images)
    )
    out.append(
        f"<details><summary>The {len(images)} images (subject i is the i-th)</summary>"
        f"<ol start='0'>{listing}</ol></details>"
    )
    return "\n".join(out)


def _options_section(result) -> str:
    run = {f"run.{k}": v for k, v in dict(result.run).items()}
    return options_table({**dict(result.options), **run, "version": result.version})


def _summary_figures(result, names: Sequence[str], figures: Mapping[str, bytes]) -> str:
    """The summary figures, embedded with their captions (the half-width ones beside each
    other)."""
    o = result.options
    flagged = any(result.scores[n].flags for n in names)
    fig_parts = []
    captions = {
        "specificity.png": (
            "Specificity of each registration (lower is better; "
            f"{escape(specificity_units(result))}; M = {o['n_samples']:,} model samples). "
            + (
                "Bars: subject-level 95% intervals (jackknife over the subjects); the "
                "Monte-Carlo error is smaller still."
                if any(result.scores[n].intervals.get("specificity") for n in names)
                else "Bars: 95% Monte-Carlo intervals only (no subject-level interval); "
                "the title says whether they are smaller than the markers."
            )
            + (" Red: flagged as implausible." if flagged else "")
        ),
        "specificity_vs_overlap.png": (
            "Specificity (lower is better) against the generalized overlap of the labels "
            "(higher is better): registrations that do well sit at the lower right. Bars as "
            "stated in the title."
        ),
        "mean_images.png": (
            "The mean image of each registration in the common frame, on one grey scale"
            + (
                ", with the boundaries of subject 0's labels (colour legend: label values)"
                if any("labels_0" in result.thumbnails.get(n, {}) for n in names)
                else ""
            )
            + ". A sharp mean means the images are well aligned."
        ),
        "subjects.png": (
            "Every subject in the scores, per registration: the robust z-score of its log "
            "distance to the texture model of the other subjects (0: a typical subject; "
            "above the dashed line the distance alone flags it). Red: a subject flag for any "
            "reason (a duplicated image lies far below: too close to another; a registration "
            "flag its subjects share is not a subject's), numbered by subject "
            "for those each registration's section shows. Subjects left off the common grid "
            "have no score and are not drawn."
        ),
        "rank_stability.png": (
            "How firmly each registration holds its rank (challengeR's blob plot): the "
            "subjects' contributions to each score (their jackknife pseudo-values) are "
            "resampled with replacement, the same draw for every registration, and the "
            "registrations ranked in every draw. Dot area: the share of the draws in which "
            "the registration (row) takes the rank (column); a single large dot is a rank "
            "that holds whichever subjects are drawn, dots spread over several ranks one "
            "that does not. Black cross: the rank on all subjects by the score alone (the "
            "scores table also ties scores within their noise). The shares are in "
            "results.json, rank_stability."
        ),
        "significance.png": (
            "Which registration is told apart from which: per measure, the row's "
            "registration against the column's, dark green where the row's is separably "
            "better (the subject-level 95% interval of the difference excludes 0), orange "
            "where it is separably worse, grey where they are not separable; the last panel "
            "is the verdict's decisions (grey: open). In results.json, significance."
        ),
    }
    full_width = ("mean_images.png", "rank_stability.png", "significance.png")
    for fname, png in figures.items():
        css = "" if fname in full_width else "half"
        fig_parts.append(figure_html(png, fname, captions.get(fname, escape(fname)), css=css))
    return "".join(fig_parts)


def report_html(result, *, figures: Mapping[str, bytes] | None = None) -> str:
    """The text of ``report.html`` for an :class:`~itk_nrreval.evaluation.EvaluationResult`.

    Parameters
    ----------
    result : EvaluationResult
    figures : mapping of str to bytes, optional
        The summary figures already rendered (:func:`~.evaluation_figures.figure_pngs`), to
        embed the same bytes as the files; rendered here when None.

    Returns
    -------
    str
        One self-contained HTML5 page: figures as ``data:image/png;base64`` URIs, inline
        CSS, no script, no external reference; every link targets a section of the page.
    """
    if figures is None:
        figures = figure_pngs(result)
    names = list(result.verdict.ranking) if result.verdict is not None else list(result.names)
    slugs = slug_ids(list(result.scores))
    n_images = next(iter(result.scores.values())).specificity.n_images
    flagged = any(result.scores[n].flags for n in names)
    verdict = (
        "".join(f"<p>{escape(line)}</p>" for line in result.verdict.text)
        if result.verdict is not None
        else "<p>No verdict was computed.</p>"
    )
    ranking = " &rarr; ".join(f'<a href="#{slugs[n]}">{escape(n)}</a>' for n in names)
    subjects = _subjects_in_verdict(result, names, slugs)

    subtitle = (
        f"{len(names)} registrations of N = {n_images} images, compared in the frame of "
        f"<b>{escape(result.common_frame)}</b>; itk-nrreval {escape(result.version)}"
    )
    sections = [
        (
            "verdict",
            "Verdict",
            f'<div class="verdict{" flagged" if flagged else ""}">{verdict}</div>'
            "<p>The verdict's order (the better of every decided pair first; where the "
            f"decisions leave a choice, the lower specificity first): {ranking}</p>" + subjects,
        ),
        (
            "scores",
            "Scores, with their legend",
            f"<p>{escape(ORDER_WORDS)} Each registration's name links to its section.</p>"
            + _scores_table(result, names, slugs)
            + _legend(result),
        ),
        ("figures", "Summary figures", _summary_figures(result, names, figures)),
        (
            "paper-metrics",
            "The numbers registration papers report",
            _paper_metrics(result, names),
        ),
        *[(slugs[n], f"Registration: {n}", _registration_section(result, n)) for n in names],
        (
            "details",
            "Every overlap weighting and pairwise difference",
            _overlap_table(result, names) + _comparisons(result),
        ),
        (
            "plausibility",
            "Deformation plausibility and coverage",
            _plausibility_table(result, names),
        ),
        ("frames", "Frame-estimate spread", _frames_table(result, names)),
        ("inputs", "Inputs", _inputs_section(result)),
        ("options", "Options", _options_section(result)),
    ]
    return page_html(
        title=f"Registration evaluation: {', '.join(names)}",
        heading="Registration evaluation",
        subtitle=subtitle,
        sections=sections,
        footer=f"{SELF_CONTAINED} The numbers are those of results.json beside it.",
    )
