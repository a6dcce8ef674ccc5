"""The figures of an evaluation: the summary figures (``specificity.png``,
``specificity_vs_overlap.png``, ``mean_images.png``, ``subjects.png``) and the pictures of each
registration's section of ``report.html`` (its images, a flagged subject, its Jacobian).

Every figure is rendered once to PNG bytes (:func:`figure_pngs`,
:func:`~itk_nrreval.report._plot.png_bytes`): the same bytes are written as files and embedded
in the HTML report. The figures say what they show: units, M, the distance, what the error
bars are (subject-level 95% intervals when computed; otherwise Monte-Carlo intervals, with a
note when they are smaller than the markers), and a colour legend for label contours.

The pictures are drawn from :attr:`EvaluationResult.thumbnails
<itk_nrreval.evaluation.EvaluationResult.thumbnails>`, the small arrays the pipeline keeps:
every picture is a middle slice shrunk to at most 256 pixels a side, so the report stays light
whatever the number of images.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from ..measures.subject_qc import ranked
from ._format import format_number
from ._plot import (
    HIDDEN_BARS,
    bars_hidden,
    draw_label_contours,
    middle_slice,
    png_bytes,
    thumbnail,
    wrap_name,
)
from .evaluation_text import FLAGGED_SUBJECTS_SHOWN, TABLE_OVERLAPS, specificity_units

__all__ = ["figure_pngs", "images_figure", "subject_figure", "jacobian_figure"]


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
                names=_label_names(result),
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
        order = sorted(handles, key=_label_order)
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
    (:attr:`SubjectQC.z <itk_nrreval.measures.subject_qc.SubjectQC.z>`), spread sideways so that
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
        flagged = ranked(result.scores[name].flagged_subjects)  # as the report shows them
        shown = {q.index for q in flagged[:FLAGGED_SUBJECTS_SHOWN]}
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


def _stability_measures(result) -> list[str]:
    """The measures the rank-stability figures show: specificity, then every overlap
    weighting, where their bootstraps were computed."""
    shown = ["specificity", *(m for m in result.measures if m.startswith("overlap."))]
    return [m for m in shown if m in getattr(result, "rank_stability", {})]


def _measure_title(measure: str) -> str:
    if measure.startswith("overlap."):
        return "overlap, " + measure.split(".", 1)[1].replace("_", " ")
    return measure


def _panels(n: int, *, width: float, height: float):
    """A figure of n panels, at most three a row; the figure and its axes (flat)."""
    from matplotlib.figure import Figure

    cols = min(3, n)
    rows = math.ceil(n / cols)
    fig = Figure(figsize=(width * cols, height * rows), layout="constrained")
    axes = np.atleast_1d(fig.subplots(rows, cols, squeeze=False)).reshape(-1)
    for ax in axes[n:]:
        ax.set_visible(False)
    return fig, axes[:n]


def _rank_stability_figure(result, names):
    """challengeR's blob plot: per measure, registration against rank, each dot's area the
    share of the subject bootstraps in which the registration takes that rank; a black
    cross at its rank on all subjects by its score alone (:attr:`EvaluationResult.rank_stability
    <itk_nrreval.evaluation.EvaluationResult.rank_stability>`).

    Returns
    -------
    matplotlib.figure.Figure
    """
    measures = _stability_measures(result)
    n = len(names)
    fig, axes = _panels(len(measures), width=max(2.8, 0.5 * n + 1.6), height=0.42 * n + 1.5)
    for ax, measure in zip(axes, measures, strict=True):
        rs = result.rank_stability[measure]
        for row, name in enumerate(names):
            freq = rs.frequencies[rs.names.index(name)]
            ranks = np.flatnonzero(freq > 0) + 1
            ax.scatter(
                ranks,
                [row] * ranks.size,
                s=320 * freq[ranks - 1],
                color="tab:blue",
                alpha=0.75,
                edgecolors="none",
            )
            if rs.ranks:  # its rank on all subjects, where the draws are centred
                rank = rs.ranks[rs.names.index(name)]
                ax.plot(rank, row, marker="x", color="k", markersize=6, mew=1.2)
        ax.set_yticks(range(n), [wrap_name(x, 18) for x in names], fontsize=7)
        ax.set_xticks(range(1, n + 1))
        ax.set_xlim(0.4, n + 0.6)
        ax.set_ylim(n - 0.5, -0.5)  # the verdict's best on top
        ax.set_xlabel("rank (1 = best)", fontsize=8)
        ax.grid(True, color="0.9", lw=0.6)
        ax.set_axisbelow(True)
        ax.set_title(_measure_title(measure), fontsize=8)
    first = result.rank_stability[measures[0]]
    fig.suptitle(
        f"Rank stability: dot area = share of B = {first.n_bootstrap} bootstraps of the "
        "subjects at that rank; x = rank on all subjects",
        fontsize=9,
    )
    return fig


#: The colours of the significance map's cells: what the row's registration is against the
#: column's.
_SIGNIFICANCE_COLOURS = {
    "better": (0.18, 0.49, 0.20),
    "decided better": (0.18, 0.49, 0.20),
    "worse": (0.96, 0.76, 0.56),
    "decided worse": (0.96, 0.76, 0.56),
    "not separable": (0.87, 0.87, 0.87),
    "open": (0.87, 0.87, 0.87),
    "not compared": (1.0, 1.0, 1.0),
}


def _significance_figure(result, names):
    """Per measure with paired comparisons (specificity, every overlap weighting) and for
    the verdict: a matrix of registration (row) against registration (column), dark green
    where the row's is separably better (the subject-level 95% interval of the difference
    excludes 0) or decided better by the verdict, orange where it is worse, grey where not
    separable or open (:meth:`EvaluationResult.significance
    <itk_nrreval.evaluation.EvaluationResult.significance>`).

    Returns
    -------
    matplotlib.figure.Figure
    """
    from matplotlib.patches import Patch

    maps = result.significance()
    keys = [m for m in ("specificity", *result.measures) if m in maps and m != "generalization"]
    keys = list(dict.fromkeys(keys)) + (["verdict"] if "verdict" in maps else [])
    n = len(names)
    fig, axes = _panels(len(keys), width=max(2.8, 0.42 * n + 1.6), height=0.42 * n + 1.7)
    for ax, key in zip(axes, keys, strict=True):
        cells = np.ones((n, n, 3))
        for i, a in enumerate(names):
            for j, b in enumerate(names):
                if a != b:
                    cells[i, j] = _SIGNIFICANCE_COLOURS[maps[key][a][b]]
        ax.imshow(cells, interpolation="nearest")
        labels = [wrap_name(x, 14) for x in names]
        ax.set_xticks(range(n), labels, rotation=45, ha="right", fontsize=7)
        ax.set_yticks(range(n), [wrap_name(x, 18) for x in names], fontsize=7)
        ax.set_xticks(np.arange(n + 1) - 0.5, minor=True)
        ax.set_yticks(np.arange(n + 1) - 0.5, minor=True)
        ax.grid(which="minor", color="white", lw=1.5)
        ax.tick_params(which="minor", length=0)
        ax.set_title("verdict" if key == "verdict" else _measure_title(key), fontsize=8)
    handles = [
        Patch(color=_SIGNIFICANCE_COLOURS["better"], label="row better (separable / decided)"),
        Patch(color=_SIGNIFICANCE_COLOURS["worse"], label="row worse"),
        Patch(color=_SIGNIFICANCE_COLOURS["not separable"], label="not separable / open"),
    ]
    fig.legend(handles=handles, loc="outside lower center", ncol=3, fontsize=7)
    fig.suptitle(
        "Significance map: the row's registration against the column's (subject-level 95% "
        "interval of the difference; the verdict's decisions)",
        fontsize=9,
    )
    return fig


def figure_pngs(result) -> dict[str, bytes]:
    """The summary figures, each rendered once to PNG bytes, by file name.

    ``specificity.png`` (scores with their subject-level 95% intervals, or Monte-Carlo
    error bars and a note when those are all there is), ``specificity_vs_overlap.png``
    (with labels) and ``mean_images.png`` (middle slice of each registration's mean image,
    with the label contours of subject 0 and their legend when labels were given) and,
    when subjects were scored against their cohort, ``subjects.png`` (every subject's
    model-distance z-score per registration, the flag threshold, the flagged subjects:
    :func:`_subjects_figure`) and, with subject-level confidence, ``rank_stability.png``
    (the blob plot of every registration's rank over subject bootstraps,
    :func:`_rank_stability_figure`) and ``significance.png`` (which registration is told
    apart from which, per measure and by the verdict: :func:`_significance_figure`).
    """
    names = list(result.verdict.ranking) if result.verdict is not None else list(result.names)
    out = {"specificity.png": png_bytes(_specificity_figure(result, names))}
    overlap = next((m for m, _ in TABLE_OVERLAPS if m in result.ranks), None)
    overlap = overlap or next((m for m in result.measures if m.startswith("overlap.")), None)
    if overlap is not None:
        out["specificity_vs_overlap.png"] = png_bytes(_overlap_figure(result, names, overlap))
    out["mean_images.png"] = png_bytes(_mean_images_figure(result, names))
    if any(q.z is not None for n in names for q in result.scores[n].subjects):
        out["subjects.png"] = png_bytes(_subjects_figure(result, names))
    if _stability_measures(result) and len(names) > 1:
        out["rank_stability.png"] = png_bytes(_rank_stability_figure(result, names))
        out["significance.png"] = png_bytes(_significance_figure(result, names))
    return out


# ----------------------------------------------------------------------------- report.html


_OUTSIDE = (0.72, 0.83, 1.0)  # pale blue: no value there (outside the field of view)


def _grey_limits(*arrays: np.ndarray) -> tuple[float, float]:
    vals = np.concatenate([np.asarray(a, float).ravel() for a in arrays])
    vals = vals[np.isfinite(vals)]
    if not vals.size:
        return 0.0, 1.0
    lo, hi = np.percentile(vals, [0.5, 99.5])
    return (float(lo), float(hi)) if hi > lo else (float(lo), float(lo) + 1.0)


def _aspect(spacing) -> float:
    return 1.0 if spacing is None else float(spacing[0] / spacing[1])


def _checkerboard(a: np.ndarray, b: np.ndarray, tiles: int = 8) -> np.ndarray:
    """`a` on the even tiles, `b` on the odd ones; `tiles` tiles along the longer side."""
    size = max(1, round(max(a.shape) / tiles))
    r, c = np.indices(a.shape)
    return np.where((r // size + c // size) % 2 == 0, a, b)


def _label_values(result) -> list[int]:
    """Every nonzero label value of subject 0's thumbnails, over all registrations: one
    colour per value in every figure of the report."""
    values: set[int] = set()
    for t in result.thumbnails.values():
        if "labels_0" in t:
            values |= {int(v) for v in np.unique(thumbnail(t["labels_0"], mode="nearest"))}
    values.discard(0)
    return sorted(values)


def _grey_panels(
    panels: Sequence[tuple[str, np.ndarray]], *, aspect: float, legend: bool, inches: float = 2.7
):
    """A row of images on one grey scale, titled, without ticks.

    Parameters
    ----------
    panels : sequence of (str, ndarray)
        Each panel's title and 2D image (intensity units; NaN outside a field of view,
        drawn pale blue).
    aspect : float
        Pixel height over width (:func:`_aspect`).
    legend : bool
        Leave room on the right for a legend.
    inches : float
        Width of a panel (inches; 100 pixels each in the page).

    Returns
    -------
    (matplotlib.figure.Figure, sequence of Axes)
    """
    from matplotlib import colormaps
    from matplotlib.figure import Figure

    fig = Figure(figsize=(inches * len(panels) + (0.9 if legend else 0.0), inches * 3.0 / 2.7))
    axes = fig.subplots(1, len(panels), squeeze=False)[0]
    lo, hi = _grey_limits(*[p for _, p in panels])
    # outside an image's field of view (NaN) in a colour no image or contour has
    grey = colormaps["gray"].with_extremes(bad=_OUTSIDE)
    for ax, (title, arr) in zip(axes, panels, strict=True):
        ax.imshow(arr, cmap=grey, vmin=lo, vmax=hi, origin="lower", aspect=aspect)
        ax.set_title(title, fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.subplots_adjust(wspace=0.05)
    return fig, axes


def images_figure(result, name: str):
    """Mean image, checkerboard of subjects 0 and 1, subject 0 with its label contours.

    Returns
    -------
    matplotlib.figure.Figure
    """
    t = result.thumbnails.get(name, {})
    mean = thumbnail(middle_slice(result.mean_images[name]))
    aspect = _aspect(t.get("common_spacing"))
    panels = [("mean", mean)]
    if "image_0" in t and "image_1" in t:
        panels.append(("checker", _checkerboard(thumbnail(t["image_0"]), thumbnail(t["image_1"]))))
    if "image_0" in t:
        panels.append(("subject", thumbnail(t["image_0"])))
    legend = "labels_0" in t
    titles = {
        "mean": f"mean of the {result.scores[name].specificity.n_images} images",
        "checker": "checkerboard: subjects 0 | 1",
        "subject": "subject 0" + (" and its labels" if legend else ""),
    }
    fig, axes = _grey_panels(
        [(titles[kind], arr) for kind, arr in panels], aspect=aspect, legend=legend
    )
    if legend:
        draw_label_contours(
            axes[-1],
            thumbnail(t["labels_0"], mode="nearest"),
            aspect=aspect,
            values=_label_values(result),
            names=_label_names(result),
        )
    return fig


def _label_names(result) -> Mapping[int, str] | None:
    """The labels' names (the manifest's ``label_names``), or None."""
    for s in result.scores.values():
        if s.label_metrics is not None and s.label_metrics.names:
            return s.label_metrics.names
    return None


def _label_order(entry: str) -> tuple[bool, int]:
    """A legend entry's place: numerically by its value (``"3"``, ``"3 (csf)"``)."""
    value = entry.split(" ", 1)[0]
    return (not value.isdigit(), int(value) if value.isdigit() else 0)


def subject_figure(result, name: str, index: int):
    """A subject in the common frame, the registration's mean image, and a checkerboard of
    the two (the subject on the first tile), on one grey scale.

    Parameters
    ----------
    result : EvaluationResult
    name : str
        The registration.
    index : int
        The subject (manifest index); its slice must be among the thumbnails
        (``image_<index>``: the pipeline keeps those of the flagged subjects the report
        shows).

    Returns
    -------
    matplotlib.figure.Figure
    """
    t = result.thumbnails[name]
    subject = thumbnail(t[f"image_{index}"])
    mean = thumbnail(middle_slice(result.mean_images[name]))
    fig, _ = _grey_panels(
        [
            (f"subject {index}", subject),
            ("mean image", mean),
            ("checkerboard of the two", _checkerboard(subject, mean)),
        ],
        aspect=_aspect(t.get("common_spacing")),
        legend=False,
        inches=1.9,  # two subjects side by side in the page
    )
    return fig


def jacobian_figure(result, name: str):
    """log det J of subject 0 (map, colour bar, folded voxels) and the histogram of all.

    Returns
    -------
    matplotlib.figure.Figure or None
        None without a Jacobian summary (no thumbnails).
    """
    from matplotlib import colormaps
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch

    t = result.thumbnails.get(name, {})
    if "detj_0" not in t or "log_jacobian_counts" not in t:
        return None
    det = np.asarray(t["detj_0"], float)
    folded = thumbnail(det <= 0, mode="any")
    with np.errstate(divide="ignore", invalid="ignore"):
        logj = thumbnail(np.where(det > 0, np.log(np.where(det > 0, det, 1.0)), np.nan))
    finite = np.abs(logj[np.isfinite(logj)])
    limit = float(np.clip(np.percentile(finite, 99) if finite.size else 0.1, 0.1, 2.0))
    fig = Figure(figsize=(7.6, 3.0), layout="constrained")
    ax, hx = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1.0, 1.35]})
    # 32 colours: a map read against its colour bar (and a PNG with a palette)
    cmap = colormaps["RdBu_r"].resampled(32).with_extremes(bad=(0.85, 0.85, 0.85))
    aspect = _aspect(t.get("reference_spacing"))
    im = ax.imshow(
        logj,
        cmap=cmap,
        vmin=-limit,
        vmax=limit,
        origin="lower",
        aspect=aspect,
        interpolation="nearest",
    )
    if folded.any():
        overlay = np.zeros((*folded.shape, 4))
        overlay[folded] = (0.0, 0.0, 0.0, 1.0)
        ax.imshow(overlay, origin="lower", aspect=aspect, interpolation="nearest")
        ax.legend(
            handles=[Patch(color="black", label="det J <= 0 (folds)")],
            fontsize=6,
            loc="lower left",
            bbox_to_anchor=(0.0, -0.16),
            borderaxespad=0.0,
        )
    cb = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.03, extend="both")
    cb.set_label("log det J  (<0 shrinks, >0 grows)", fontsize=7)
    cb.ax.tick_params(labelsize=7)
    ax.set_title("log det J, subject 0 (reference grid)", fontsize=8)
    ax.set_xticks([])
    ax.set_yticks([])

    counts = np.asarray(t["log_jacobian_counts"], float)
    edges = np.asarray(t["log_jacobian_edges"], float)
    below, above, n_folded = (int(v) for v in t["log_jacobian_outside"])
    total = counts.sum() + below + above + n_folded
    hx.stairs(counts / total if total else counts, edges, fill=True, color="tab:blue")
    hx.axvline(0.0, color="k", lw=0.8, ls="--")
    hx.set_yscale("log")
    bottom, top = hx.get_ylim()
    hx.set_ylim(bottom, top * 30)  # room for the note above the bars
    hx.set_xlim(edges[0], edges[-1])
    hx.set_xlabel("log det J", fontsize=8)
    hx.set_ylabel("fraction of voxels (log scale)", fontsize=8)
    hx.tick_params(labelsize=7)
    n = result.scores[name].specificity.n_images
    hx.set_title(f"log det J of all {n} subjects ({total:,.0f} voxels)", fontsize=8)
    share = (lambda k: f"{k / total:.2%}") if total else (lambda k: "–")
    hx.text(
        0.02,
        0.97,
        f"below {edges[0]:g}: {share(below)}\nabove {edges[-1]:g}: {share(above)}\n"
        f"folded (det J <= 0): {share(n_folded)}",
        transform=hx.transAxes,
        va="top",
        fontsize=7,
        bbox={"facecolor": "white", "alpha": 0.8, "edgecolor": "none"},
    )
    return fig
