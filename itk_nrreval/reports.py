"""Writing an :class:`~itk_nrreval.evaluation.EvaluationResult`: JSON, CSV, Markdown, figures.

``summary.md`` is laid out like the paper's Table 3: per registration, the generalized
overlap (inverse-volume, and inverse-volume & complexity weighting) and the specificity with
its standard error, each with its rank and quantitative relative rank. Every file is written
under a temporary name and renamed when complete; figures are written first, then
``report.html`` (:mod:`itk_nrreval.html_report`, given as text), and the ``results.*`` files
last, so an interrupted run leaves no partial ``results.*``.

Every figure is rendered once to PNG bytes (:func:`figure_pngs`, :func:`png_bytes`): the same
bytes are written as files and embedded in the HTML report. The figures say what they show:
units, M, the distance, what the error bars are (subject-level 95% intervals when computed;
otherwise Monte-Carlo intervals, with a note when they are smaller than the markers), and a
colour legend for label contours. The drawing helpers the HTML report shares
(:func:`thumbnail`, :func:`middle_slice`, :func:`draw_label_contours`) live here.

:meth:`EvaluationResult.write <itk_nrreval.evaluation.EvaluationResult.write>` calls
:func:`write_reports`; the functions here take the result without importing its class
(that import would be a cycle).
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from ._output import atomic_path, write_text

__all__ = [
    "summary_table",
    "results_csv",
    "subjects_csv",
    "subjects_summary",
    "write_reports",
    "figure_pngs",
    "format_number",
    "format_percent",
    "format_rank",
    "frame_spread_words",
    "frame_spread_flagged",
    "TIES_WORDS",
    "png_bytes",
    "middle_slice",
    "thumbnail",
    "draw_label_contours",
    "specificity_units",
    "bars_hidden",
    "HIDDEN_BARS",
    "wrap_name",
    "FLAGGED_SUBJECTS_SHOWN",
]

#: How many flagged subjects per registration the HTML report shows with pictures (in
#: manifest order; how many more there are is said): the pipeline keeps a resampled slice of
#: these only, so the report stays light whatever the number of subjects.
FLAGGED_SUBJECTS_SHOWN = 6

_TABLE_OVERLAPS = (
    ("overlap.inverse_volume", "Overlap (inverse volume)"),
    ("overlap.inverse_volume_complexity", "Overlap (inverse volume & complexity)"),
)


def format_number(v, digits: int = 4) -> str:
    """`v` to `digits` significant digits; an en dash for None or NaN."""
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "–"
    return f"{v:.{digits}g}"


def format_percent(v) -> str:
    """A percentage with one decimal; an en dash for None."""
    return "–" if v is None else f"{v:.1f}%"


def format_rank(result, measure: str, name: str) -> str:
    """The rank of `name` by `measure` for a reader: ``"2"``, ``"1 (tied)"``, or a dash."""
    rank = result.ranks[measure][name]
    if rank is None:
        return "–"
    return f"{rank} (tied)" if result.tied_with(measure, name) else str(rank)


#: How the reports explain the relative rank and its ties (summary.md and report.html).
TIES_WORDS = (
    "Scores not told apart from noise are tied: in score order, neighbours whose difference "
    "is within 1.96 combined standard errors (the Monte-Carlo s.e. for specificity; the "
    "s.e. for generalization when no subject-level interval was computed) or whose "
    "subject-level 95% interval of the difference includes 0 (not separable, as in the "
    "verdict). Tied scores share the better rank, marked (tied), and one relative rank, "
    "that of their mean, so a spread within the noise is never shown as the whole 0-100% "
    "range; when every score is tied, all are 100%."
)


def frame_spread_words(result) -> tuple[float | None, str]:
    """The mean frame spread (mm) that is flagged, and the reports' sentence saying so.

    The limit is :func:`itk_nrreval.plausibility.frame_spread_limit_mm` of the run's
    thresholds and field of view, the number :func:`~itk_nrreval.plausibility.flags` used;
    None (and a sentence without a number) for a result that does not record them.
    """
    from .plausibility import Thresholds, frame_spread_limit_mm

    o = result.options
    fov = o.get("field_of_view_mm")
    fraction = o.get("thresholds", {}).get("frame_spread_fraction")
    if fov is None or fraction is None:
        return None, (
            "A mean spread above the flag threshold (frame_spread_fraction of the field "
            "of view) is flagged: comparing that registration in the common frame is doubtful."
        )
    limit = frame_spread_limit_mm(fov, Thresholds(frame_spread_fraction=fraction))
    return limit, (
        f"A mean spread above {format_number(limit, 3)} mm ({format_number(100 * fraction, 3)}% "
        f"of the {format_number(fov, 4)} mm field of view, the flag threshold) is flagged: the "
        "images do not agree where that registration's frame sits, and comparing it in the "
        "common frame is doubtful. Below it the spread is not judged. The max spread, the "
        "farthest estimate at a single voxel of a single image, is shown for context and "
        "not judged."
    )


def frame_spread_flagged(result, name: str) -> bool:
    """Whether `name`'s mean frame spread is above the limit of :func:`frame_spread_words`."""
    limit, _ = frame_spread_words(result)
    spread = result.scores[name].frame.spread_mean_mm
    return limit is not None and math.isfinite(spread) and spread > limit


def _ci(s, measure: str) -> str:
    iv = s.intervals.get(measure)
    if iv is None or not math.isfinite(iv.lo):
        return "–"
    return f"[{format_number(iv.lo)}, {format_number(iv.hi)}]"


def summary_table(result) -> str:
    """The verdict in words, then a Markdown table like the paper's Table 3.

    Columns: for each overlap weighting present among inverse volume and inverse volume &
    complexity, then specificity and generalization: score, subject-level 95% interval,
    rank and relative rank (specificity also its Monte-Carlo standard error); then the
    plausibility flags. Lower is better for specificity and generalization, higher for
    overlap. A second table gives each registration's frame and deformation plausibility.
    """
    cols = [(m, title) for m, title in _TABLE_OVERLAPS if m in result.ranks]
    header = ["Registration"]
    for _, title in cols:
        header += [f"{title}", "95% CI", "Rank", "Rel. rank"]
    header += ["Specificity", "95% CI", "MC s.e.", "Rank", "Rel. rank"]
    header += ["Generalization", "95% CI", "Rank", "Rel. rank", "Flags"]
    order = list(result.verdict.ranking) if result.verdict is not None else list(result.scores)
    rows = []
    for name in order:
        s = result.scores[name]
        row = [name]
        for m, _ in cols:
            row += [
                format_number(s.measures()[m]),
                _ci(s, m),
                format_rank(result, m, name),
                format_percent(result.relative_ranks[m][name]),
            ]
        row += [
            format_number(s.specificity.value),
            _ci(s, "specificity"),
            format_number(s.specificity.stderr, 2),
            format_rank(result, "specificity", name),
            format_percent(result.relative_ranks["specificity"][name]),
        ]
        row += [
            format_number(s.generalization.value),
            _ci(s, "generalization"),
            format_rank(result, "generalization", name),
            format_percent(result.relative_ranks["generalization"][name]),
            "; ".join(s.flags) if s.flags else "–",
        ]
        rows.append(row)
    head = []
    if result.verdict is not None:
        head = [*result.verdict.text, ""]
    lines = head + [
        "| " + " | ".join(header) + " |",
        "|" + "|".join("---" if i == 0 else "--:" for i in range(len(header))) + "|",
    ]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    o = result.options
    notes = [
        "",
        f"Rows in the verdict's order (by level of its decisions, by specificity within a "
        f"level: only the decided pairs listed in results.json are claims). Common "
        f"frame: {result.common_frame}. Specificity and generalization: lower is better "
        f"({o['distance'].upper()} distance in the model's parameter space, in the images' "
        f"intensity units; M = {o['n_samples']} samples, seed {o['seed']}); overlap: higher "
        "is better. 95% CI: subject-level interval (jackknife over the subjects: would the "
        "score hold for other subjects?). MC s.e.: Monte-Carlo standard error of the "
        "specificity estimate only (it shrinks as M grows). Rank: 1 is best. Rel. rank: "
        "100% for the best score, 0% for the worst, linear between, (worst - x) / "
        f"(worst - best). {TIES_WORDS}",
        "",
        "| Registration | Frame from | Spread mean (mm) | Spread flagged | Spread max (mm) | "
        "Folded (mean) | Folded (worst image) | SDlogJ | det J min | det J max | "
        "Inverse consistency (mm) |",
        "|---|---|--:|--:|--:|--:|--:|--:|--:|--:|--:|",
    ]
    for name in order:
        s = result.scores[name]
        pl = s.plausibility
        notes.append(
            f"| {name} | {s.frame.method} | {format_number(s.frame.spread_mean_mm, 3)} | "
            f"{'yes' if frame_spread_flagged(result, name) else 'no'} | "
            f"{format_number(s.frame.spread_max_mm, 3)} | {pl.folded_fraction:.2%} | "
            f"{pl.folded_max:.2%} | {format_number(pl.sdlogj, 3)} | "
            f"{format_number(pl.jacobian_min, 3)} | {format_number(pl.jacobian_max, 3)} | "
            f"{format_number(pl.inverse_consistency_mm, 3)} |"
        )
    notes += [
        "",
        "Frame spread: how far the per-image estimates of the transform into the common "
        "frame lie from it. " + frame_spread_words(result)[1],
    ]
    return "\n".join(lines + notes + subjects_summary(result)) + "\n"


def subjects_summary(result) -> list[str]:
    """The lines of ``summary.md`` that name the flagged subjects of every registration.

    Per registration, each flagged subject (manifest index and image) with its diagnosis
    and flags, or that none is flagged; and the subjects left out of every score.
    """
    if not any(s.subjects for s in result.scores.values()):
        return []
    lines = [
        "",
        "## Flagged subjects",
        "",
        "Each subject compared with the rest of its cohort under the same registration "
        "(robust z-scores, z = (x - median) / (1.4826 MAD)): its distance to the texture "
        "model of the others, its deformation, its label overlap with the others, its "
        "coverage of the common grid (per-subject values in subjects.csv).",
        "",
    ]
    left_out = result.options.get("left_out_of_scores") or []
    if left_out:
        first = next(iter(result.scores.values()))
        names = ", ".join(f"{i} ({first.subjects[i].image})" for i in left_out)
        lines += [
            f"Left out of every registration's scores (off the common grid): subject {names}.",
            "",
        ]
    for name, s in result.scores.items():
        flagged = [q for q in s.subjects if q.flags]
        if not flagged:
            lines.append(f"- {name}: none of the {len(s.subjects)} subjects is flagged.")
            continue
        lines.append(f"- {name}: {len(flagged)} of the {len(s.subjects)} subjects flagged:")
        for q in flagged:
            cause = q.diagnosis if q.diagnosis is not None else "no common cause recognised"
            lines.append(f"  - subject {q.index} ({q.image}): {cause}. {'; '.join(q.flags)}.")
    return lines


def _missing(v) -> bool:
    return v is None or (isinstance(v, float) and math.isnan(v))


#: The columns of ``subjects.csv`` taken from a subject's deformation, in order.
_SUBJECT_DEFORMATION = (
    "folded_fraction",
    "sdlogj",
    "sdlogj_z",
    "jacobian_min",
    "jacobian_max",
    "inverse_consistency_mm",
    "inverse_consistency_z",
    "linear_det",
    "nonlinear_rms_mm",
    "nonlinear_rms_z",
    "displacement_rms_mm",
)


def subjects_csv(result) -> str:
    """One row per registration and subject (manifest order): the subject's quality control.

    Columns: registration, index, image, in_scores, score (distance to the model of the
    others, intensity units), z, overlap, overlap_z, coverage, the deformation measures
    (mm where a length) and their z, flags (joined by "; "), diagnosis. Empty cells: not
    computed.
    """
    fields = ["registration", "index", "image", "in_scores", "score", "z"]
    fields += ["overlap", "overlap_z", "coverage", *_SUBJECT_DEFORMATION, "flags", "diagnosis"]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n")
    w.writeheader()
    for name, s in result.scores.items():
        for q in s.subjects:
            row = {
                "registration": name,
                "index": q.index,
                "image": q.image,
                "in_scores": q.in_scores,
                "score": q.score,
                "z": q.z,
                "overlap": q.overlap,
                "overlap_z": q.overlap_z,
                "coverage": q.coverage,
                **{k: q.deformation.get(k) for k in _SUBJECT_DEFORMATION},
                "flags": "; ".join(q.flags),
                "diagnosis": q.diagnosis or "",
            }
            w.writerow({k: "" if _missing(v) else v for k, v in row.items()})
    return buf.getvalue()


def results_csv(result) -> str:
    """One row per registration: scores, standard errors, ranks, relative ranks, frame."""
    fields = ["registration", "specificity", "specificity_stderr"]
    fields += ["specificity_ci95_lo", "specificity_ci95_hi"]
    fields += ["generalization", "generalization_stderr"]
    fields += ["generalization_ci95_lo", "generalization_ci95_hi"]
    overlaps = [m for m in result.measures if m.startswith("overlap.")]
    fields += overlaps
    fields += [f"{m}_ci95_{e}" for m in overlaps for e in ("lo", "hi")]
    fields += [f"rank.{m}" for m in result.measures]
    fields += [f"relative_rank.{m}" for m in result.measures]
    fields += [f"tied_with.{m}" for m in result.measures]
    fields += ["frame_method", "frame_spread_mean_mm", "frame_spread_max_mm"]
    fields += ["folded_fraction", "folded_max", "sdlogj", "jacobian_min", "jacobian_max"]
    fields += ["inverse_consistency_mm", "flags"]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n")
    w.writeheader()
    for name, s in result.scores.items():
        row = {
            "registration": name,
            "specificity": s.specificity.value,
            "specificity_stderr": s.specificity.stderr,
            "generalization": s.generalization.value,
            "generalization_stderr": s.generalization.stderr,
            "frame_method": s.frame.method,
            "frame_spread_mean_mm": s.frame.spread_mean_mm,
            "frame_spread_max_mm": s.frame.spread_max_mm,
            "folded_fraction": s.folded_fraction,
            "folded_max": s.folded_max,
            "sdlogj": s.plausibility.sdlogj,
            "jacobian_min": s.plausibility.jacobian_min,
            "jacobian_max": s.plausibility.jacobian_max,
            "inverse_consistency_mm": s.plausibility.inverse_consistency_mm,
            "flags": "; ".join(s.flags),
        }
        for m in ["specificity", "generalization", *overlaps]:
            iv = s.intervals.get(m)
            row[f"{m}_ci95_lo"] = iv.lo if iv is not None else None
            row[f"{m}_ci95_hi"] = iv.hi if iv is not None else None
        row.update({m: s.measures()[m] for m in overlaps})
        row.update({f"rank.{m}": result.ranks[m][name] for m in result.measures})
        row.update({f"relative_rank.{m}": result.relative_ranks[m][name] for m in result.measures})
        row.update({f"tied_with.{m}": ";".join(result.tied_with(m, name)) for m in result.measures})
        w.writerow(row)
    return buf.getvalue()


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serializable: {type(o).__name__}")


def png_bytes(fig, *, dpi: int = 120) -> bytes:
    """Render a ``matplotlib.figure.Figure`` to compact PNG bytes (tight bounding box).

    Every figure is rendered once: the bytes are written to a file and embedded in the HTML
    report alike. The PNG is stored with a palette when that loses nothing visible: exactly
    when the picture has at most 256 colours, else with an adaptive palette of 256 colours
    only if no channel of any pixel moves by more than 2 of 255 (grey images over a few
    coloured contours); otherwise as true colour. About 3-5 times smaller than matplotlib's
    RGBA output for the report's figures.
    """
    from PIL import Image

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    buf.seek(0)
    with Image.open(buf) as im:
        rgb = im.convert("RGB")
    arr = np.asarray(rgb)
    packed = (arr[..., 0].astype(np.uint32) << 16) | (arr[..., 1].astype(np.uint32) << 8)
    packed |= arr[..., 2]
    colours, index = np.unique(packed, return_inverse=True)
    if colours.size <= 256:
        out = Image.fromarray(index.reshape(packed.shape).astype(np.uint8))
        palette = np.stack([colours >> 16, (colours >> 8) & 255, colours & 255], axis=1)
        out.putpalette(palette.astype(np.uint8).ravel().tolist())
    else:
        out = rgb.quantize(256, method=Image.Quantize.MAXCOVERAGE, dither=Image.Dither.NONE)
        error = np.abs(np.asarray(out.convert("RGB"), np.int16) - arr).max()
        if error > 2:
            out = rgb
    res = io.BytesIO()
    out.save(res, format="PNG", optimize=True)
    return res.getvalue()


def middle_slice(img: np.ndarray) -> np.ndarray:
    """The middle slice (numpy index ``shape[0] // 2``) of a 3D array; a 2D array as is."""
    return img if img.ndim == 2 else img[img.shape[0] // 2]


def thumbnail(a: np.ndarray, *, max_size: int = 256, mode: str = "mean") -> np.ndarray:
    """A 2D array shrunk by a whole factor until no side exceeds `max_size` pixels.

    Parameters
    ----------
    a : ndarray, 2D
    max_size : int
    mode : {"mean", "nearest", "any"}
        ``"mean"``: the mean of each block of pixels, NaN ignored (NaN where a block is all
        NaN); ``"nearest"``: the centre pixel of each block (for label maps); ``"any"``:
        whether any pixel of the block is true (for masks: a folded voxel stays visible).

    Returns
    -------
    ndarray
        `a` itself when it already fits; else of shape ``(rows // f, columns // f)`` in
        every mode (the last rows and columns short of a whole block are dropped), so that
        thumbnails of the same slice overlay pixel for pixel.
    """
    a = np.asarray(a)
    f = math.ceil(max(a.shape) / max_size)
    if f <= 1:
        return a
    h, w = a.shape[0] // f * f, a.shape[1] // f * f  # every mode drops the same remainder
    if mode == "nearest":
        return a[f // 2 : h : f, f // 2 : w : f]
    blocks = a[:h, :w].reshape(h // f, f, w // f, f)
    if mode == "any":
        return blocks.any(axis=(1, 3))
    if mode != "mean":
        raise ValueError(f"mode: {mode!r} is not one of ('mean', 'nearest', 'any')")
    valid = ~np.isnan(blocks)
    count = valid.sum(axis=(1, 3))
    total = np.where(valid, blocks, 0.0).sum(axis=(1, 3))
    return np.divide(total, count, out=np.full(count.shape, np.nan), where=count > 0)


#: Label maps with at most this many label values get one colour and a legend entry each
#: (tab20's colours without its two greys, which would vanish on a grey image).
LEGEND_LABELS = 18


def draw_label_contours(
    ax,
    labels: np.ndarray,
    *,
    aspect: float = 1.0,
    fontsize: int = 6,
    legend: bool = True,
    values: Sequence[int] | None = None,
) -> tuple[list, str]:
    """Draw the boundaries of every nonzero label of `labels` over an image in `ax`.

    Boundary pixels (a nonzero label with a 4-neighbour of another value) are drawn in the
    label's colour, with a legend naming every label value present in `labels`; with more
    than :data:`LEGEND_LABELS` values, all in one colour and one legend entry that says so.

    Parameters
    ----------
    ax : matplotlib Axes
        Already showing the image (``origin="lower"``), on the same pixel grid.
    labels : ndarray of int, 2D
    aspect : float
        Pixel aspect (row spacing / column spacing), as the image's.
    fontsize : int
        Legend font size.
    legend : bool
        Draw the legend beside `ax`; False leaves it to the caller (e.g. one legend for a
        row of panels).
    values : sequence of int, optional
        Every label value of the figure (or the report), present here or not: a value gets
        the same colour in every panel drawn with the same `values`. Default: the values
        present in `labels`.

    Returns
    -------
    handles : list of matplotlib Patch
        The legend's entries, one per nonzero value present in `labels`, in increasing
        order (empty without labels).
    title : str
        The legend's title.
    """
    from matplotlib import colormaps
    from matplotlib.patches import Patch

    lab = np.asarray(labels)
    edge = np.zeros(lab.shape, bool)
    edge[1:, :] |= lab[1:, :] != lab[:-1, :]
    edge[:-1, :] |= lab[:-1, :] != lab[1:, :]
    edge[:, 1:] |= lab[:, 1:] != lab[:, :-1]
    edge[:, :-1] |= lab[:, :-1] != lab[:, 1:]
    edge &= lab != 0
    present = [int(v) for v in np.unique(lab) if v != 0]
    # colours are keyed by the position of a value among all of the figure's values, so that
    # a label keeps its colour in every panel even where another label is missing
    palette = sorted({int(v) for v in values if v != 0} | set(present)) if values else present
    overlay = np.zeros((*lab.shape, 4))
    if len(palette) <= LEGEND_LABELS:
        if len(palette) <= 9:  # tab10 without its grey
            colors = [c for i, c in enumerate(colormaps["tab10"].colors) if i != 7]
        else:
            colors = [c for i, c in enumerate(colormaps["tab20"].colors) if i not in (14, 15)]
        handles = []
        for v in present:
            color = (*colors[palette.index(v)], 1.0)
            overlay[edge & (lab == v)] = color
            handles.append(Patch(color=color, label=str(v)))
        title = "label value"
    else:
        overlay[edge] = (1.0, 0.85, 0.0, 1.0)
        handles = [Patch(color=(1.0, 0.85, 0.0), label=f"{len(present)} labels")] if present else []
        title = f"labels {present[0]}..{present[-1]}" if present else "label value"
    ax.imshow(overlay, origin="lower", aspect=aspect, interpolation="nearest")
    if handles and legend:
        ax.legend(
            handles=handles,
            title=title,
            fontsize=fontsize,
            title_fontsize=fontsize,
            loc="upper left",
            bbox_to_anchor=(1.01, 1.0),
            borderaxespad=0.0,
            handlelength=1.0,
            ncol=1 if len(handles) <= 10 else 2,
        )
    return handles, title


def bars_hidden(ax, half_lengths, *, markersize: float = 6.0, axis: str = "y") -> bool:
    """Whether error bars of these half-lengths would all hide behind their markers.

    Call once everything is drawn (the axis limits are final). A bar shows only where it
    reaches past the marker, whose radius is ``markersize / 2`` points.

    Parameters
    ----------
    ax : matplotlib Axes
    half_lengths : array_like
        Each bar's half-length, in data units of `axis` (for an asymmetric bar, the longer
        side); NaN is ignored.
    markersize : float
        Marker diameter in points (matplotlib's ``markersize``).
    axis : {"y", "x"}

    Returns
    -------
    bool
        True when no bar reaches past its marker (also when there is no bar).
    """
    lengths = np.asarray(half_lengths, float)
    lengths = lengths[np.isfinite(lengths)]
    if not lengths.size:
        return True
    lo, hi = ax.get_ylim() if axis == "y" else ax.get_xlim()
    box = ax.get_position()
    fig_in = ax.figure.get_figheight() if axis == "y" else ax.figure.get_figwidth()
    points = (box.height if axis == "y" else box.width) * fig_in * 72.0
    if ax.get_yscale() == "log" if axis == "y" else ax.get_xscale() == "log":
        return False  # no single data-per-point scale; do not claim the bars are hidden
    radius = 0.5 * markersize * abs(hi - lo) / points  # in data units
    return bool(lengths.max() < radius)


#: The words a figure uses for Monte-Carlo error bars that do not show.
HIDDEN_BARS = "smaller than the markers"


def wrap_name(name: str, width: int = 24) -> str:
    """`name` broken into lines of at most about `width` characters after ``_``, so that
    long registration names (a sweep's settings) do not run into their neighbours."""
    lines, line = [], ""
    for part in name.split("_"):
        piece = part if not line else "_" + part
        if line and len(line) + len(piece) > width:
            lines.append(line + "_")
            line = part
        else:
            line += piece
    return "\n".join([*lines, line])


def specificity_units(result) -> str:
    """The unit of specificity and generalization, e.g. ``"L1 distance, intensity units"``."""
    o = result.options
    exponent = next(iter(result.scores.values())).specificity.exponent
    unit = "intensity units" if exponent == 1 else f"(intensity units)^{exponent:g}"
    return f"{o['distance'].upper()} distance, {unit}"


def _intervals(result, names, measure) -> list | None:
    """Per registration the (lo, hi) of `measure`'s subject-level 95% interval, or None."""
    ivs = [result.scores[n].intervals.get(measure) for n in names]
    if all(iv is not None and math.isfinite(iv.lo) and math.isfinite(iv.hi) for iv in ivs):
        return [(iv.lo, iv.hi) for iv in ivs]
    return None


def _specificity_figure(result, names):
    from matplotlib.figure import Figure

    spec = [result.scores[n].specificity for n in names]
    values = np.array([s.value for s in spec])
    mc = np.array([s.stderr for s in spec])
    ci = _intervals(result, names, "specificity")
    fig = Figure(figsize=(max(5.0, 1.0 * len(names)), 4.0))  # about 560 px in the page
    ax = fig.subplots()
    colors = ["tab:red" if result.scores[n].flags else "tab:blue" for n in names]
    if ci is not None:
        err = np.array([[v - lo, hi - v] for v, (lo, hi) in zip(values, ci, strict=True)]).T
    else:
        err = np.array([1.96 * mc] * 2)
    for x, (v, c) in enumerate(zip(values, colors, strict=True)):
        ax.errorbar(x, v, yerr=err[:, x : x + 1], fmt="o", markersize=6, capsize=5, color=c)
    labels = [f"{n}\n(flagged)" if result.scores[n].flags else n for n in names]
    ax.set_xticks(range(len(names)), labels, rotation=30, ha="right")
    ax.set_xlim(-0.6, len(names) - 0.4)
    o = result.options
    ax.set_ylabel(f"specificity ({specificity_units(result)})\nlower is better")
    n_images = spec[0].n_images
    mc_hidden = bars_hidden(ax, 1.96 * mc, markersize=6)
    if ci is not None:
        what = f"bars: subject-level 95% interval (jackknife over the N = {n_images} subjects)"
        if bars_hidden(ax, err.max(axis=0), markersize=6):
            what += f", {HIDDEN_BARS}"
        mc_note = f"Monte-Carlo s.e. at most {mc.max():.2g}" + (
            f" (±1.96 s.e. is {HIDDEN_BARS}; not drawn)" if mc_hidden else " (not drawn)"
        )
    else:
        what = "bars: 95% Monte-Carlo interval (±1.96 s.e.; model sampling only)"
        mc_note = (
            f"the Monte-Carlo error bars are {HIDDEN_BARS} (s.e. at most {mc.max():.2g}); "
            "no subject-level interval (confidence off or N < 4)"
            if mc_hidden
            else "no subject-level interval (confidence off or N < 4)"
        )
    ax.set_title(
        f"Specificity, M = {o['n_samples']:,} model samples, {o['distance'].upper()} distance\n"
        f"{what}\n{mc_note}"
        + ("; red: flagged as implausible" if any(result.scores[n].flags for n in names) else ""),
        fontsize=8,
    )
    return fig


def _overlap_figure(result, names, overlap: str):
    from matplotlib.figure import Figure

    spec = [result.scores[n].specificity for n in names]
    ys = np.array([s.value for s in spec])
    xs = np.array([result.scores[n].measures()[overlap] for n in names])
    ci_y = _intervals(result, names, "specificity")
    ci_x = _intervals(result, names, overlap)
    fig = Figure(figsize=(5.0, 4.0))
    ax = fig.subplots()
    if ci_y is not None:
        yerr = np.array([[y - lo, hi - y] for y, (lo, hi) in zip(ys, ci_y, strict=True)]).T
    else:
        yerr = 1.96 * np.array([s.stderr for s in spec])
    xerr = None
    if ci_x is not None:
        xerr = np.array([[x - lo, hi - x] for x, (lo, hi) in zip(xs, ci_x, strict=True)]).T
    colors = ["tab:red" if result.scores[n].flags else "tab:blue" for n in names]
    for i in range(len(names)):
        ax.errorbar(
            xs[i],
            ys[i],
            yerr=yerr[:, i : i + 1] if yerr.ndim == 2 else yerr[i],
            xerr=xerr[:, i : i + 1] if xerr is not None else None,
            fmt="o",
            capsize=3,
            color=colors[i],
        )
    for x, y, n in zip(xs, ys, names, strict=True):
        ax.annotate(n, (x, y), textcoords="offset points", xytext=(4, 4), fontsize=8)
    weighting = overlap.split(".", 1)[1].replace("_", " ")
    ax.set_xlabel(f"generalized overlap (Tanimoto, {weighting} weighting, 0..1)\nhigher is better")
    ax.set_ylabel(f"specificity ({specificity_units(result)})\nlower is better")
    ybar = yerr.max(axis=0) if yerr.ndim == 2 else yerr
    if ci_y is not None:
        what = "bars: subject-level 95% intervals of both scores (jackknife over subjects)"
        hidden = bars_hidden(ax, ybar, markersize=6) and (
            xerr is None or bars_hidden(ax, xerr.max(axis=0), markersize=6, axis="x")
        )
    else:
        what = (
            "bars: 95% Monte-Carlo interval of specificity only (±1.96 s.e.; no "
            "subject-level intervals computed)"
        )
        hidden = bars_hidden(ax, ybar, markersize=6)
    if hidden:
        what += f"\nthe bars are {HIDDEN_BARS}"
    o = result.options
    ax.set_title(
        f"Specificity against overlap; M = {o['n_samples']:,}, {o['distance'].upper()}\n{what}",
        fontsize=8,
    )
    return fig


def _mean_images_figure(result, names):
    from matplotlib.figure import Figure

    slices = {n: middle_slice(result.mean_images[n]) for n in names}
    lo = min(float(np.nanmin(slices[n])) for n in names)
    hi = max(float(np.nanmax(slices[n])) for n in names)
    thumbs = getattr(result, "thumbnails", {}) or {}
    contours = any("labels_0" in thumbs.get(n, {}) for n in names)
    # every label value shown in any panel: one colour per value across the row, one legend
    values: set[int] = set()
    for n in names:
        if "labels_0" in thumbs.get(n, {}):
            values |= {int(v) for v in np.unique(thumbnail(thumbs[n]["labels_0"], mode="nearest"))}
    values.discard(0)
    fig = Figure(
        figsize=(max(2.6 * len(names), 5.2), 3.4 if contours else 3.0), layout="constrained"
    )
    axes = fig.subplots(1, len(names), squeeze=False)
    handles: dict[str, object] = {}  # legend entry by label, over all panels
    legend_title = ""
    for ax, n in zip(axes[0], names, strict=True):
        t = thumbs.get(n, {})
        sp = t.get("common_spacing")
        aspect = float(sp[0] / sp[1]) if sp is not None else 1.0
        ax.imshow(
            thumbnail(slices[n]), cmap="gray", vmin=lo, vmax=hi, origin="lower", aspect=aspect
        )
        if "labels_0" in t:
            found, legend_title = draw_label_contours(
                ax,
                thumbnail(t["labels_0"], mode="nearest"),
                aspect=aspect,
                legend=False,
                values=sorted(values),
            )
            for h in found:
                handles.setdefault(h.get_label(), h)
        ax.set_title(wrap_name(n), fontsize=9 if len(n) <= 24 else 7)
        ax.axis("off")
    dim = next(iter(result.mean_images.values())).ndim
    where = "middle slice, " if dim == 3 else ""
    title = (
        f"Mean of the N images in the common frame ({where}grey scale shared: "
        f"{format_number(lo, 3)} to {format_number(hi, 3)} intensity units)"
    )
    if contours:
        title += "\ncontours: the labels of subject 0 resampled into the same frame"
    if handles:
        # numerically ordered: labels found in a later panel only still sort into place
        order = sorted(handles, key=lambda k: (not k.isdigit(), int(k) if k.isdigit() else 0))
        fig.legend(
            handles=[handles[k] for k in order],
            title=legend_title,
            loc="outside lower center",
            ncol=min(len(handles), 10),
            fontsize=7,
            title_fontsize=7,
        )
    fig.suptitle(title, fontsize=9)
    return fig


def _subjects_figure(result, names):
    """Every scored subject's model-distance z-score per registration, a strip plot.

    One column per registration (`names`, in order), one point per subject in the scores at
    its robust z-score of the log distance to the texture model of the others
    (:attr:`SubjectQC.z <itk_nrreval.subject_qc.SubjectQC.z>`), spread sideways so that
    points do not hide one another; red: flagged for any reason, numbered by the subject's
    index for those the report shows; dashed: the threshold above which the distance alone
    flags a subject. The axis is linear within the threshold and logarithmic beyond
    (symlog), where the failures lie.

    Returns
    -------
    matplotlib.figure.Figure
    """
    from matplotlib.figure import Figure
    from matplotlib.ticker import FuncFormatter

    threshold = float(result.options.get("subject_thresholds", {}).get("outlier_z", math.nan))
    fig = Figure(figsize=(max(5.0, 1.3 * len(names)), 4.0))
    ax = fig.subplots()
    # the same spread every time: the figure's bytes are compared with the file's
    jitter = np.random.default_rng(0)
    xs: dict[bool, list[float]] = {False: [], True: []}
    ys: dict[bool, list[float]] = {False: [], True: []}
    infinite = 0
    for k, name in enumerate(names):
        scored = [q for q in result.scores[name].subjects if q.z is not None]
        spread = jitter.uniform(-0.28, 0.28, len(scored))
        shown = {q.index for q in result.scores[name].flagged_subjects[:FLAGGED_SUBJECTS_SHOWN]}
        for q, dx in zip(scored, spread, strict=True):
            z = q.z
            if math.isinf(z):  # no spread in the cohort (MAD 0): drawn at the edge
                infinite += 1
                z = math.copysign(1e3, z)
            xs[q.flagged].append(k + dx)
            ys[q.flagged].append(z)
            if q.index in shown:
                ax.annotate(
                    str(q.index),
                    (k + dx, z),
                    textcoords="offset points",
                    xytext=(4, 2),
                    fontsize=7,
                    color="tab:red",
                )
    if xs[False]:
        ax.scatter(xs[False], ys[False], s=12, color="tab:blue", alpha=0.6, label="not flagged")
    if xs[True]:
        ax.scatter(
            xs[True],
            ys[True],
            s=30,
            color="tab:red",
            edgecolors="k",
            linewidths=0.5,
            label="flagged (any reason)",
        )
    ylabel = "z of log distance to the model of the others"
    if math.isfinite(threshold):
        ax.axhline(
            threshold, color="tab:red", ls="--", lw=1, label=f"flag threshold z = {threshold:g}"
        )
        # the cohort within the threshold, read linearly; the failures, often far beyond it
        ax.set_yscale("symlog", linthresh=threshold)
        ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))  # not 10^1
        ylabel += f"\n(linear within ±{threshold:g}, logarithmic beyond)"
    ax.set_xticks(range(len(names)), [wrap_name(n) for n in names], rotation=30, ha="right")
    ax.set_xlim(-0.6, len(names) - 0.4)
    ax.margins(y=0.08)  # the farthest points whole, clear of the frame
    ax.set_ylabel(ylabel)
    ax.legend(fontsize=7, loc="best")
    left_out = len(result.options.get("left_out_of_scores") or [])
    notes = [
        "Each subject against its cohort: robust z = (x - median) / (1.4826 MAD) "
        "of its log distance",
        "to the texture model of the other subjects; numbers: flagged subjects shown in the report",
    ]
    if left_out:
        notes.append(
            f"{left_out} subject{'s' if left_out > 1 else ''} left out of the scores (off the "
            "common grid): not drawn"
        )
    if infinite:
        notes.append(f"{infinite} z = ±inf (no spread in the cohort) drawn at ±1000")
    ax.set_title("\n".join(notes), fontsize=8)
    return fig


def figure_pngs(result) -> dict[str, bytes]:
    """The summary figures, each rendered once to PNG bytes, by file name.

    ``specificity.png`` (scores with their subject-level 95% intervals, or Monte-Carlo
    error bars and a note when those are all there is), ``specificity_vs_overlap.png``
    (with labels) and ``mean_images.png`` (middle slice of each registration's mean image,
    with the label contours of subject 0 and their legend when labels were given) and,
    when subjects were scored against their cohort, ``subjects.png`` (every subject's
    model-distance z-score per registration, the flag threshold, the flagged subjects:
    :func:`_subjects_figure`).
    """
    names = list(result.verdict.ranking) if result.verdict is not None else list(result.names)
    out = {"specificity.png": png_bytes(_specificity_figure(result, names))}
    overlap = next((m for m, _ in _TABLE_OVERLAPS if m in result.ranks), None)
    overlap = overlap or next((m for m in result.measures if m.startswith("overlap.")), None)
    if overlap is not None:
        out["specificity_vs_overlap.png"] = png_bytes(_overlap_figure(result, names, overlap))
    out["mean_images.png"] = png_bytes(_mean_images_figure(result, names))
    if any(q.z is not None for n in names for q in result.scores[n].subjects):
        out["subjects.png"] = png_bytes(_subjects_figure(result, names))
    return out


def write_reports(
    result,
    out: str | os.PathLike,
    *,
    figures: bool | Mapping[str, bytes] = True,
    html: str | None = None,
) -> list[Path]:
    """Write figures, then ``report.html``, then ``results.json``, ``results.csv``,
    ``summary.md`` and ``subjects.csv`` (per-subject quality control, :func:`subjects_csv`)
    into `out`.

    Parameters
    ----------
    result : EvaluationResult
    out : path
        Created if needed.
    figures : bool or mapping of str to bytes
        True: render and write the PNG figures (:func:`figure_pngs`); a mapping: write these
        already rendered figures (file name to PNG bytes); False: no figures.
    html : str, optional
        The text of ``report.html`` (:func:`itk_nrreval.html_report.report_html`), written
        after the figures and before the ``results.*`` files.

    Returns
    -------
    list of Path
        The files written.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if figures is True:
        figures = figure_pngs(result)
    written = []
    for fname, data in (figures or {}).items():
        with atomic_path(out / fname) as tmp:
            tmp.write_bytes(data)
        written.append(out / fname)
    if html is not None:
        write_text(out / "report.html", html)
        written.append(out / "report.html")
    # build everything before writing any results.* file
    texts = {
        "results.json": json.dumps(result.to_dict(), indent=2, default=_json_default) + "\n",
        "results.csv": results_csv(result),
        "summary.md": summary_table(result),
    }
    if any(s.subjects for s in result.scores.values()):
        texts["subjects.csv"] = subjects_csv(result)
    for fname, text in texts.items():
        write_text(out / fname, text)
        written.append(out / fname)
    return written
