"""``report.html``: one self-contained page that reads an evaluation, as MRIQC and fMRIPrep
reports are read.

The page opens from disk with no network and no JavaScript (:mod:`._html`). It gives, in
order: the verdict in words, with the subjects left off the common grid and how many subjects
each registration flags; the scores with their legend, units and intervals; the summary
figures (the same PNG bytes as the files beside it, ``subjects.png`` among them: every
subject's model-distance z-score); the numbers registration papers report (Dice and HD95 with
their worst 30%, SDlogJ, folding: :mod:`itk_nrreval.measures.label_metrics`); per registration first
its subjects
(:mod:`itk_nrreval.measures.subject_qc`: its registration flags, said once; its reference when that
is one of the subjects; its flagged subjects worst first, each with its name, concern, diagnosis
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

The tables (scores, the papers' numbers, overlaps, plausibility, frames) are built in
:mod:`._evaluation_tables`; this module lays the page out and builds the subjects' sections,
each registration's section and the captions of its figures.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

from ..measures.subject_qc import ranked, registration_flags
from ._evaluation_tables import (
    FRAME_WORDS,
    frames_table,
    overlap_table,
    pairwise_differences,
    paper_metrics_table,
    plausibility_table,
    scores_legend,
    scores_table,
)
from ._format import format_number
from ._html import (
    SELF_CONTAINED,
    escape,
    figure_html,
    interval_text,
    item_text,
    key_value_table,
    options_table,
    page_html,
    slug_ids,
    table_html,
)
from ._plot import png_bytes
from .evaluation_figures import figure_pngs, images_figure, jacobian_figure, subject_figure
from .evaluation_text import (
    CONCERN_WORDS,
    FLAGGED_SUBJECTS_SHOWN,
    ORDER_WORDS,
    concern_text,
    specificity_units,
)

__all__ = ["report_html", "RANKED_SHOWN"]

_DPI = 100  # pixels per inch of the per-registration figures


def _subject(result, i: int) -> str:
    """How subject i is named: its image file's name, or its index for objects in memory."""
    images = result.inputs.get("images") or []
    if i < len(images) and isinstance(images[i], str):
        return f"subject {i} ({Path(images[i]).name})"
    return f"subject {i}"


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
        f"; frame: {escape(FRAME_WORDS.get(s.frame.method, s.frame.method))}, spread "
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
            + scores_table(result, names, slugs)
            + scores_legend(result),
        ),
        ("figures", "Summary figures", _summary_figures(result, names, figures)),
        (
            "paper-metrics",
            "The numbers registration papers report",
            paper_metrics_table(result, names),
        ),
        *[(slugs[n], f"Registration: {n}", _registration_section(result, n)) for n in names],
        (
            "details",
            "Every overlap weighting and pairwise difference",
            overlap_table(result, names) + pairwise_differences(result),
        ),
        (
            "plausibility",
            "Deformation plausibility and coverage",
            plausibility_table(result, names),
        ),
        ("frames", "Frame-estimate spread", frames_table(result, names)),
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
