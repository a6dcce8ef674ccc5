"""What ``validate`` writes for a person: the paper's Fig. 2, specificity and overlap against
the displacement d, and ``report.html``.

The page gives the verdict in words first (does specificity rise as the registration is made
worse: Pearson r with its 95% interval, Spearman with d, the sensitivity), then the table by
d, the figures (the same PNG bytes as the files beside it), every perturbed set and the
parameters. The functions take a :class:`~itk_nrreval.experiments.perturbation.ValidationResult`
without importing its class (:mod:`itk_nrreval.experiments.perturbation` calls this module to
write).
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from .._output import atomic_path, write_text
from ._format import format_number
from ._html import (
    SELF_CONTAINED,
    escape,
    figure_html,
    flat_items,
    legend_list,
    options_table,
    page_html,
    table_html,
)
from ._plot import HIDDEN_BARS, bars_hidden, png_bytes

__all__ = [
    "OUTPUT_FILES",
    "SPECIFICITY_UNITS",
    "fig2_figure",
    "vs_d_figure",
    "plot_fig2",
    "plot_vs_d",
    "validation_report_html",
    "write_validation",
]

#: The files :meth:`ValidationResult.write` writes, in order.
OUTPUT_FILES = (
    "validation.csv",
    "validation.json",
    "validation_fig2.png",
    "validation_vs_d.png",
    "report.html",
)


def write_validation(result, out_dir: str | os.PathLike, *, version: str) -> list[Path]:
    """Write the figures and ``report.html`` of a validation run into `out_dir`.

    ``validation_fig2.png`` (:func:`fig2_figure`, the first weighting),
    ``validation_vs_d.png`` (:func:`vs_d_figure`) and ``report.html``
    (:func:`validation_report_html`: Fig. 2 for every weighting), each written under a
    temporary name and renamed into place.

    Parameters
    ----------
    result : ValidationResult
    out_dir : path
        An existing folder.
    version : str
        The package version, printed in the page's header.

    Returns
    -------
    list of Path
        The three files written, in :data:`OUTPUT_FILES` order.
    """
    out = Path(out_dir)
    paths = [out / name for name in OUTPUT_FILES[2:]]
    # every figure rendered once: the files and the page hold the same bytes
    figures = {f"fig2_{w}": png_bytes(fig2_figure(result, weighting=w)) for w in result.weightings}
    figures["vs_d"] = png_bytes(vs_d_figure(result))
    for path, key in ((paths[0], f"fig2_{result.weightings[0]}"), (paths[1], "vs_d")):
        with atomic_path(path) as tmp:
            tmp.write_bytes(figures[key])
    html = validation_report_html(result, figures=figures, units=SPECIFICITY_UNITS, version=version)
    write_text(paths[2], html)
    return paths


# ----------------------------------------------------------------------------- figures


def _d_label(result) -> str:
    sp = result.spacing
    if sp is not None and np.allclose(sp, sp[0]) and sp[0] != 1.0:
        return f"mean displacement d (pixels; 1 px = {sp[0]:g} mm)"
    return "mean displacement d (pixels)"


SPECIFICITY_UNITS = (
    "L1 distance, intensity units"  # validate's specificity: the paper's L1, lambda 1
)


def fig2_figure(result, *, weighting: str | None = None):
    """The paper's Fig. 2: specificity against overlap, coloured by d.

    Error bars: one Monte-Carlo standard error of each specificity (model sampling only),
    with a note in the title when they are smaller than the markers. The grey line is the
    least-squares fit over ``d >= 0.375`` (with Pearson r and its 95 % interval); the
    dashed line is the unperturbed specificity (d = 0). 2D and 3D runs alike.

    Parameters
    ----------
    result : ValidationResult
    weighting : str, optional
        The overlap's label weighting (default: the first of the run).

    Returns
    -------
    matplotlib.figure.Figure
    """
    import matplotlib
    from matplotlib.figure import Figure  # no pyplot: the process's backend is left alone

    w = weighting or result.weightings[0]
    fit_from = result.parameters["fit_from"]
    d = result.column("displacement")
    s = result.column("specificity")
    se = result.column("specificity_stderr")
    o = result.column(f"overlap_{w}")
    fig = Figure(figsize=(6.4, 4.8), dpi=120)
    ax = fig.subplots()
    levels = np.unique(d)
    cmap = matplotlib.colormaps["viridis"].resampled(max(len(levels), 1))
    for k, v in enumerate(levels):
        sel = d == v
        ax.errorbar(o[sel], s[sel], yerr=se[sel], fmt="o", ms=5, color=cmap(k), label=f"{v:g}")
    fit = d >= fit_from
    a, b = result.summary.fit.get(w, (math.nan, math.nan))
    if math.isfinite(a) and math.isfinite(b) and fit.any():
        xs = np.linspace(np.nanmin(o[fit]), np.nanmax(o[fit]), 2)
        r = result.summary.pearson_r[w]
        lo, hi = result.summary.pearson_ci.get(w, (math.nan, math.nan))
        ci = f", 95% CI {lo:.3f} to {hi:.3f}" if math.isfinite(lo) else ""
        ax.plot(
            xs,
            a * xs + b,
            color="0.5",
            lw=2,
            zorder=0,
            label=f"fit d>={fit_from:g} (r={r:.3f}{ci})",
        )
    if result.summary.unperturbed is not None:
        ax.axhline(result.summary.unperturbed, ls="--", color="k", lw=1, label="d = 0")
    ax.set_xlabel(
        f"generalized Tanimoto overlap ({w.replace('_', '-')} weighted, 0..1; higher: "
        "better aligned)",
        fontsize=9,
    )
    ax.set_ylabel(f"specificity ({SPECIFICITY_UNITS})\nlower is better", fontsize=9)
    grid = " x ".join(map(str, result.shape[::-1]))
    bars = "error bars: ±1 Monte-Carlo s.e. (model sampling only)"
    if bars_hidden(ax, se, markersize=5):
        bars += f", {HIDDEN_BARS}"
    ax.set_title(
        f"N = {result.n_images} images of {grid}, {len(result.rows)} perturbed sets; "
        f"M = {result.n_samples:,} samples\n{bars}",
        fontsize=9,
    )
    ax.legend(title="d (pixels)", fontsize=7, title_fontsize=8, ncol=2, loc="best")
    fig.tight_layout()
    return fig


def vs_d_figure(result):
    """Specificity and overlap against d: mean over repeats, error bars one SD over repeats.

    A note in each title when the bars are smaller than the markers (or when one repeat
    leaves no spread to show).

    Returns
    -------
    matplotlib.figure.Figure
    """
    from matplotlib.figure import Figure

    m = result.means()
    repeats = result.parameters.get("repeats")
    fig = Figure(figsize=(10, 4), dpi=120)
    a1, a2 = fig.subplots(1, 2)

    def bars(ax, sds) -> str:
        if repeats == 1:
            return "one repeat per d: no spread to show"
        note = f"error bars: ±1 SD over the {f'{repeats} ' if repeats else ''}repeats"
        return note + (f", {HIDDEN_BARS}" if bars_hidden(ax, sds, markersize=6) else "")

    a1.errorbar(m["displacement"], m["specificity"], yerr=m["specificity_sd"], fmt="o-", capsize=3)
    a1.set_xlabel(_d_label(result))
    a1.set_ylabel(f"specificity ({SPECIFICITY_UNITS})\nlower is better")
    sens = result.summary.sensitivity_mm
    extra = f"\n{sens:.3g} Monte-Carlo s.e. per mm of d" if math.isfinite(sens) else ""
    a1.set_title(
        f"Specificity, M = {result.n_samples:,}; {bars(a1, m['specificity_sd'])}{extra}",
        fontsize=9,
    )
    for w in result.weightings:
        a2.errorbar(
            m["displacement"],
            m[f"overlap_{w}"],
            yerr=m[f"overlap_{w}_sd"],
            fmt="o-",
            capsize=3,
            label=w.replace("_", " "),
        )
    a2.set_xlabel(_d_label(result))
    a2.set_ylabel("generalized Tanimoto overlap (0..1)\nhigher is better")
    sds = np.concatenate([m[f"overlap_{w}_sd"] for w in result.weightings])
    a2.set_title(f"Overlap; {bars(a2, sds)}", fontsize=9)
    a2.legend(title="label weighting", fontsize=8, title_fontsize=8)
    fig.tight_layout()
    return fig


def plot_fig2(result, path, *, weighting: str | None = None) -> None:
    """Write :func:`fig2_figure` to `path` (PNG)."""
    Path(path).write_bytes(png_bytes(fig2_figure(result, weighting=weighting)))


def plot_vs_d(result, path) -> None:
    """Write :func:`vs_d_figure` to `path` (PNG)."""
    Path(path).write_bytes(png_bytes(vs_d_figure(result)))


# ----------------------------------------------------------------------------- report.html


def _r_words(r: float, ci: tuple[float, float]) -> str:
    """Whether specificity rises as overlap falls, from Pearson r and its 95% interval."""
    lo, hi = ci
    if not math.isfinite(r):
        return "undefined (fewer than two values of d in the fit, or no spread)"
    if math.isfinite(hi) and hi < 0:
        return "yes: specificity rises as overlap falls"
    if r < 0:
        return "only weakly: r is negative but its 95% interval reaches 0"
    return "no: specificity does not rise as overlap falls"


def _fmt_ci(ci: tuple[float, float]) -> str:
    lo, hi = ci
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return "–"
    return f"[{lo:.3f}, {hi:.3f}]"


def _d_id(d: float) -> str:
    return "d-" + f"{d:g}".replace(".", "_")


def _verdict(result) -> str:
    """The verdict in words, in its box: does specificity rise as overlap falls (Pearson r
    with its interval, for the first weighting), Spearman with d, the sensitivity."""
    s = result.summary
    w0 = result.weightings[0]
    fit_from = result.parameters["fit_from"]
    r0 = s.pearson_r.get(w0, math.nan)
    ci0 = s.pearson_ci.get(w0, (math.nan, math.nan))
    answer = _r_words(r0, ci0)
    good = math.isfinite(ci0[1]) and ci0[1] < 0
    verdict = [
        "<p><b>Does specificity rise as the registration is made worse? "
        f"{escape(answer[0].upper())}{escape(answer[1:])}.</b></p>",
        f"<p>Pearson r between specificity and the {escape(w0.replace('_', ' '))} overlap: "
        f"<b>{format_number(r0, 3)}</b>, 95% interval {_fmt_ci(ci0)} (Fisher's z), over the "
        f"{s.n_fit} perturbed sets with d &ge; {fit_from:g} px (strongly negative is good: "
        "the paper's Fig. 2 line).</p>",
        f"<p>Spearman correlation of the mean specificity with d (d &ge; {fit_from:g} px): "
        f"<b>{format_number(s.spearman, 3)}</b>; the mean rises strictly with d: "
        f"<b>{'yes' if s.monotonic else 'no'}</b>. Sensitivity: "
        f"{format_number(s.sensitivity, 3)} Monte-Carlo standard errors per pixel of d"
        + (
            f" ({format_number(s.sensitivity_mm, 3)} per mm)"
            if math.isfinite(s.sensitivity_mm)
            else ""
        )
        + ".</p>",
    ]
    if s.unperturbed is not None:
        verdict.append(
            f"<p>Unperturbed specificity (d = 0): {format_number(s.unperturbed)}. Below "
            f"d = {fit_from:g} px the paper finds a dip under it (interpolation smooths the "
            "images), which is why the fit starts there.</p>"
        )

    return f'<div class="verdict{"" if good else " flagged"}">' + "".join(verdict) + "</div>"


def _by_displacement(result, units: str) -> str:
    """The table by d (mean and SD over the repeats) with its legend, then Pearson r and the
    fitted line per label weighting."""
    s = result.summary
    m = result.means()
    fit_from = result.parameters["fit_from"]
    levels = m["displacement"]
    head = ["d (px)", "d (mm)", "Specificity<br>mean &plusmn; SD", "MC s.e.<br>(mean)"]
    head += [
        f"Overlap, {escape(w.replace('_', ' '))}<br>mean &plusmn; SD" for w in result.weightings
    ]
    head += ["In the fit"]
    rows = []
    for k, d in enumerate(levels):
        row = [
            f"{d:g}",
            format_number(m["displacement_mm"][k], 3),
            f"{format_number(m['specificity'][k])} &plusmn; "
            f"{format_number(m['specificity_sd'][k], 2)}",
            format_number(m["specificity_stderr"][k], 2),
        ]
        row += [
            f"{format_number(m[f'overlap_{w}'][k])} &plusmn; "
            f"{format_number(m[f'overlap_{w}_sd'][k], 2)}"
            for w in result.weightings
        ]
        row.append("yes" if d >= fit_from else "no")
        rows.append(row)
    table = table_html(head, rows, text=(), ids=[_d_id(d) for d in levels], wide=True)
    legend = legend_list(
        [
            (
                "d",
                "the mean displacement of every image's random clamped-plate-spline warp, in "
                "pixels of the grid (and in mm, the mean over the warps); d = 0 is the "
                "registered set itself.",
            ),
            (
                "Specificity",
                f"of the perturbed set's texture model ({escape(units)}; M = "
                f"{result.n_samples:,} samples, seed {result.seed}); <b>lower is better</b>. "
                f"Mean and standard deviation over the {result.parameters.get('repeats', '')} "
                "repeats at each d.",
            ),
            (
                "MC s.e.",
                "Monte-Carlo standard error of one specificity estimate (finite M only), "
                "mean over the repeats.",
            ),
            (
                "Overlap",
                "generalized Tanimoto overlap of the perturbed label memberships, 0 to 1, "
                "<b>higher is better</b>, per label weighting.",
            ),
            ("In the fit", f"whether d &ge; {fit_from:g} px: the rows the line and r use."),
        ]
    )
    stats_head = ["Label weighting", "Pearson r", "95% CI", "Fit: slope a", "Fit: intercept b"]
    stats_rows = [
        [
            escape(w.replace("_", " ")),
            format_number(s.pearson_r.get(w, math.nan), 3),
            _fmt_ci(s.pearson_ci.get(w, (math.nan, math.nan))),
            format_number(s.fit.get(w, (math.nan, math.nan))[0]),
            format_number(s.fit.get(w, (math.nan, math.nan))[1]),
        ]
        for w in result.weightings
    ]
    correlations = (
        table_html(stats_head, stats_rows)
        + "<p>The line is specificity = a &times; overlap + b, least squares over the sets "
        f"with d &ge; {fit_from:g} px.</p>"
    )
    return table + legend + correlations


def _figures(result, figures: Mapping[str, bytes]) -> str:
    """Fig. 2 per label weighting, and specificity and overlap against d, with captions."""
    fit_from = result.parameters["fit_from"]
    figs = []
    for w in result.weightings:
        key = f"fig2_{w}"
        if key in figures:
            figs.append(
                figure_html(
                    figures[key],
                    f"Fig. 2, {w}",
                    f"The paper's Fig. 2, {escape(w.replace('_', ' '))} weighting: each point one "
                    "perturbed set, coloured by d (legend, in pixels); error bars &plusmn;1 "
                    "Monte-Carlo s.e. of its specificity (the title says when they are "
                    f"smaller than the markers); grey: the line fitted over d &ge; {fit_from:g}"
                    " px; dashed: the unperturbed specificity.",
                    css="half",
                )
            )
    if "vs_d" in figures:
        figs.append(
            figure_html(
                figures["vs_d"],
                "specificity and overlap against d",
                "Mean specificity (left) and overlap (right) against d; error bars &plusmn;1 "
                "standard deviation over the repeats (the titles say when they hide behind "
                "the markers).",
            )
        )
    return "".join(figs)


def _every_set(result) -> str:
    """Every perturbed set, one row each, folded away."""
    every = table_html(
        ["d (px)", "Repeat", "Specificity", "MC s.e."]
        + [f"Overlap, {escape(w.replace('_', ' '))}" for w in result.weightings]
        + ["min det J", "d (mm)"],
        [
            [
                f"{r.displacement:g}",
                str(r.repeat),
                format_number(r.specificity),
                format_number(r.specificity_stderr, 2),
                *[format_number(r.overlap.get(w, math.nan)) for w in result.weightings],
                format_number(r.min_jacobian, 3),
                format_number(r.displacement_mm, 3),
            ]
            for r in result.rows
        ],
        text=(),
    )
    return f"<details><summary>The {len(result.rows)} perturbed sets</summary>{every}</details>"


def _parameters(result, units: str, version: str | None) -> str:
    """The inputs and parameters of the run, as a table."""
    params = {
        "source": result.source,
        "n_images": result.n_images,
        "shape (x, y[, z])": " × ".join(map(str, result.shape[::-1])),
        "spacing (mm)": result.spacing,
        "n_samples (M)": result.n_samples,
        "specificity in": units,
        "n_knots": result.n_knots,
        "seed": result.seed,
        "weightings": ", ".join(result.weightings),
        **{f"parameters.{k}": v for k, v in flat_items(dict(result.parameters))},
    }
    if version is not None:
        params["version"] = version
    return options_table(params)


def validation_report_html(
    result, *, figures: Mapping[str, bytes], units: str, version: str | None = None
) -> str:
    """The text of ``report.html`` for a
    :class:`~itk_nrreval.experiments.perturbation.ValidationResult`.

    The verdict in words first (does specificity rise as overlap falls: Pearson r with its
    95% interval per label weighting, the Spearman correlation of the mean specificity with
    the displacement d, the sensitivity), then the table by d (mean and SD over the
    repeats), the figures, every perturbed set, and the parameters.

    Parameters
    ----------
    result : ValidationResult
    figures : mapping of str to bytes
        PNG bytes: ``"fig2_<weighting>"`` (:func:`fig2_figure`) per
        weighting and ``"vs_d"`` (:func:`vs_d_figure`), the same
        bytes as the files written beside the page.
    units : str
        What specificity is measured in, e.g. ``"L1 distance, intensity units"``.
    version : str, optional
        The package version, printed in the header.

    Returns
    -------
    str
        One self-contained HTML5 page, as :func:`~.evaluation_page.report_html`'s.
    """
    sec = result.parameters.get("section")
    where = f", slice {sec['axis']}:{sec['index']}" if sec else ""
    grid = " × ".join(map(str, result.shape[::-1]))
    sections = [
        ("verdict", "Verdict", _verdict(result)),
        ("table", "Specificity and overlap by displacement", _by_displacement(result, units)),
        ("figures", "Figures", _figures(result, figures)),
        ("rows", "Every perturbed set", _every_set(result)),
        ("parameters", "Inputs and parameters", _parameters(result, units, version)),
    ]
    return page_html(
        title=f"Validation: {result.source}",
        heading="Validation: specificity under known misregistration",
        subtitle=(
            f"{len(result.rows)} perturbed sets of N = {result.n_images} images of {grid} "
            f"({escape(result.source)}{escape(where)}); specificity: {escape(units)}, "
            f"M = {result.n_samples:,}" + (f"; itk-nrreval {escape(version)}" if version else "")
        ),
        sections=sections,
        footer=f"{SELF_CONTAINED} The numbers are those of validation.json beside it.",
    )
