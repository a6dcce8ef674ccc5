"""Transitional: ``validate``'s and ``sweep``'s pages, until they move to
:mod:`itk_nrreval.report`."""

from __future__ import annotations

import math
from collections.abc import Mapping

from .report._format import format_number
from .report._html import SELF_CONTAINED as _SELF_CONTAINED
from .report._html import escape as _e
from .report._html import figure_html as _figure
from .report._html import flat_items as _flat
from .report._html import legend_list as _legend_list
from .report._html import options_table as _options_table
from .report._html import page_html as _page
from .report._html import slug_ids as _slugs
from .report._html import table_html as _table
from .report._html import value_ci as _value_ci
from .report.evaluation_text import specificity_units

__all__ = ["validation_report_html", "sweep_report_html"]

_TABLE_OVERLAPS = ("overlap.inverse_volume", "overlap.inverse_volume_complexity")


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


def validation_report_html(
    result, *, figures: Mapping[str, bytes], units: str, version: str | None = None
) -> str:
    """The text of ``report.html`` for a :class:`~itk_nrreval.validation.ValidationResult`.

    The verdict in words first (does specificity rise as overlap falls: Pearson r with its
    95% interval per label weighting, the Spearman correlation of the mean specificity with
    the displacement d, the sensitivity), then the table by d (mean and SD over the
    repeats), the figures, every perturbed set, and the parameters.

    Parameters
    ----------
    result : ValidationResult
    figures : mapping of str to bytes
        PNG bytes: ``"fig2_<weighting>"`` (:func:`~itk_nrreval.validation.fig2_figure`) per
        weighting and ``"vs_d"`` (:func:`~itk_nrreval.validation.vs_d_figure`), the same
        bytes as the files written beside the page.
    units : str
        What specificity is measured in, e.g. ``"L1 distance, intensity units"``.
    version : str, optional
        The package version, printed in the header.

    Returns
    -------
    str
        One self-contained HTML5 page, as :func:`report_html`'s.
    """
    s = result.summary
    m = result.means()
    w0 = result.weightings[0]
    fit_from = result.parameters["fit_from"]
    sec = result.parameters.get("section")
    where = f", slice {sec['axis']}:{sec['index']}" if sec else ""
    grid = " × ".join(map(str, result.shape[::-1]))
    r0 = s.pearson_r.get(w0, math.nan)
    ci0 = s.pearson_ci.get(w0, (math.nan, math.nan))
    answer = _r_words(r0, ci0)
    good = math.isfinite(ci0[1]) and ci0[1] < 0
    verdict = [
        f"<p><b>Does specificity rise as the registration is made worse? {_e(answer[0].upper())}"
        f"{_e(answer[1:])}.</b></p>",
        f"<p>Pearson r between specificity and the {_e(w0.replace('_', ' '))} overlap: "
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

    levels = m["displacement"]
    head = ["d (px)", "d (mm)", "Specificity<br>mean &plusmn; SD", "MC s.e.<br>(mean)"]
    head += [f"Overlap, {_e(w.replace('_', ' '))}<br>mean &plusmn; SD" for w in result.weightings]
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
    table = _table(head, rows, text=(), ids=[_d_id(d) for d in levels], wide=True)
    legend = _legend_list(
        [
            (
                "d",
                "the mean displacement of every image's random clamped-plate-spline warp, in "
                "pixels of the grid (and in mm, the mean over the warps); d = 0 is the "
                "registered set itself.",
            ),
            (
                "Specificity",
                f"of the perturbed set's texture model ({_e(units)}; M = "
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
            _e(w.replace("_", " ")),
            format_number(s.pearson_r.get(w, math.nan), 3),
            _fmt_ci(s.pearson_ci.get(w, (math.nan, math.nan))),
            format_number(s.fit.get(w, (math.nan, math.nan))[0]),
            format_number(s.fit.get(w, (math.nan, math.nan))[1]),
        ]
        for w in result.weightings
    ]
    correlations = (
        _table(stats_head, stats_rows)
        + "<p>The line is specificity = a &times; overlap + b, least squares over the sets "
        f"with d &ge; {fit_from:g} px.</p>"
    )
    figs = []
    for w in result.weightings:
        key = f"fig2_{w}"
        if key in figures:
            figs.append(
                _figure(
                    figures[key],
                    f"Fig. 2, {w}",
                    f"The paper's Fig. 2, {_e(w.replace('_', ' '))} weighting: each point one "
                    "perturbed set, coloured by d (legend, in pixels); error bars &plusmn;1 "
                    "Monte-Carlo s.e. of its specificity (the title says when they are "
                    f"smaller than the markers); grey: the line fitted over d &ge; {fit_from:g}"
                    " px; dashed: the unperturbed specificity.",
                    css="half",
                )
            )
    if "vs_d" in figures:
        figs.append(
            _figure(
                figures["vs_d"],
                "specificity and overlap against d",
                "Mean specificity (left) and overlap (right) against d; error bars &plusmn;1 "
                "standard deviation over the repeats (the titles say when they hide behind "
                "the markers).",
            )
        )
    every = _table(
        ["d (px)", "Repeat", "Specificity", "MC s.e."]
        + [f"Overlap, {_e(w.replace('_', ' '))}" for w in result.weightings]
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
        **{f"parameters.{k}": v for k, v in _flat(dict(result.parameters))},
    }
    if version is not None:
        params["version"] = version
    sections = [
        ("verdict", "Verdict", f'<div class="verdict{"" if good else " flagged"}">'
         + "".join(verdict) + "</div>"),
        ("table", "Specificity and overlap by displacement", table + legend + correlations),
        ("figures", "Figures", "".join(figs)),
        (
            "rows",
            "Every perturbed set",
            f"<details><summary>The {len(result.rows)} perturbed sets</summary>{every}"
            "</details>",
        ),
        ("parameters", "Inputs and parameters", _options_table(params)),
    ]  # fmt: skip
    return _page(
        title=f"Validation: {result.source}",
        heading="Validation: specificity under known misregistration",
        subtitle=(
            f"{len(result.rows)} perturbed sets of N = {result.n_images} images of {grid} "
            f"({_e(result.source)}{_e(where)}); specificity: {_e(units)}, M = {result.n_samples:,}"
            + (f"; itk-nrreval {_e(version)}" if version else "")
        ),
        sections=sections,
        footer=f"{_SELF_CONTAINED} The numbers are those of validation.json beside it.",
    )


def sweep_report_html(
    result,
    *,
    figures: Mapping[str, bytes],
    truth_measure: str,
    specificity_figure: str = "sweep.png",
) -> str:
    """The text of ``report.html`` for a :class:`~itk_nrreval.sweep.SweepResult`.

    The verdict in words first (the setting specificity recommends, the settings it cannot
    separate from it, the best by overlap and, when the true transforms were known, by the
    true correspondence error), then the table of every setting, the figures, the
    agreement between measures and the options. The evaluation's own ``report.html``
    (per-setting images and Jacobians) is in ``evaluation/`` beside it.

    Parameters
    ----------
    result : SweepResult
    figures : mapping of str to bytes
        PNG bytes by file name: `specificity_figure` (the sweep's figure) and any of the
        evaluation's summary figures (:func:`itk_nrreval.report.evaluation_figures.figure_pngs`).
    truth_measure : str
        The key of the true correspondence error in ``result.best_by`` and
        ``result.spearman``.
    specificity_figure : str
        Which of `figures` is the sweep's own.

    Returns
    -------
    str
        One self-contained HTML5 page, as :func:`report_html`'s.
    """
    ev = result.evaluation
    names = [st.name for st in result.settings]
    slugs = _slugs(names, prefix="setting-")
    params = list(result.parameters)
    first = ev.scores[names[0]]
    overlaps = [m for m in first.measures() if m.startswith("overlap.")]
    # the table keeps the evaluation table's two weightings; every one is in the verdict
    shown = [m for m in overlaps if m in _TABLE_OVERLAPS] or overlaps
    units = specificity_units(ev)

    def link(name: str) -> str:
        return f'<a href="#{slugs[name]}">{_e(name)}</a>'

    def values(name: str) -> str:
        st = next(x for x in result.settings if x.name == name)
        return ", ".join(f"{_e(k)} = {_e(v)}" for k, v in st.values.items())

    rec = result.recommended
    others = [n for n in result.not_separable if n != rec]
    if result.decided:
        verdict = [
            f"<p><b>The verdict recommends {link(rec)}</b> ({values(rec)}): decided better "
            "than every other setting.</p>"
        ]
    else:
        verdict = [
            "<p><b>The verdict leaves open</b> "
            + ", ".join(link(n) for n in [rec, *others])
            + f": no setting is decided better than these, and the evidence does not order "
            f"them. {link(rec)} ({values(rec)}) has the lowest specificity among them.</p>"
        ]
    candidates = set(result.not_separable)
    open_pairs = result.evaluation.verdict.open_pairs
    among = [p for p in open_pairs if {p.a, p.b} <= candidates]
    verdict += [
        f"<p>{link(p.a)} and {link(p.b)}: not decided: {_e(p.reason)}.</p>" for p in among[:4]
    ]
    by_best: dict[str, list[str]] = {}  # one line per setting overlap prefers
    for m in overlaps:
        if m in result.best_by:
            by_best.setdefault(result.best_by[m], []).append(m.split(".", 1)[1].replace("_", " "))
    for best, weightings in by_best.items():
        verdict.append(
            f"<p>Best by overlap: {link(best)} ({_e(', '.join(weightings))} weighting"
            f"{'s' if len(weightings) > 1 else ''}).</p>"
        )
    truth = result.truth_error_mm
    if truth is not None:
        best = result.best_by[truth_measure]
        where = (
            "the same setting"
            if best == rec
            else "in the open set"
            if best in result.not_separable
            else "a different setting"
        )
        verdict.append(
            f"<p><b>The truth's choice</b> (lowest true correspondence error): {link(best)}, "
            f"{format_number(truth[best], 3)} mm, {where}; the verdict's choice has "
            f"{format_number(truth[rec], 3)} mm. Spearman correlation over the settings "
            "between specificity and the true error: "
            f"{format_number(result.spearman.get(truth_measure, math.nan), 3)} (1: the same "
            "order).</p>"
        )
    else:
        verdict.append("<p>No true transforms were given: the truth's choice is unknown.</p>")

    head = ["Setting", *[_e(p) for p in params], "Specificity<br>[95% CI]", "MC s.e."]
    head += [f"Overlap, {_e(m.split('.', 1)[1].replace('_', ' '))}<br>[95% CI]" for m in shown]
    if truth is not None:
        head.append("True error (mm)")
    head += ["Verdict says", "Flags"]
    rows, classes = [], []
    for st in result.settings:
        sc = ev.scores[st.name]
        row = [_e(st.name), *[_e(st.values[p]) for p in params]]
        row += [
            _value_ci(sc.specificity.value, sc.intervals.get("specificity")),
            format_number(sc.specificity.stderr, 2),
        ]
        row += [_value_ci(sc.measures()[m], sc.intervals.get(m)) for m in shown]
        if truth is not None:
            row.append(format_number(truth[st.name], 3))
        row.append(
            "&#9733; recommended"
            if st.name == rec
            else "not separable"
            if st.name in result.not_separable
            else "separably worse"
        )
        row.append("; ".join(_e(f) for f in sc.flags) if sc.flags else "none")
        rows.append(row)
        classes.append("flagged" if sc.flags else "best" if st.name == rec else "")
    table = _table(
        head,
        rows,
        text=(0, -2, -1),
        classes=classes,
        ids=[slugs[n] for n in names],
        wide=True,
    )
    legend = _legend_list(
        [
            (
                "Specificity",
                f"of each setting's texture model ({_e(units)}; M = {ev.options['n_samples']:,}"
                f" samples, seed {ev.options['seed']}, the same samples for every setting); "
                "<b>lower is better</b>. 95% CI: subject-level (jackknife over the subjects); "
                "MC s.e.: Monte-Carlo error only.",
            ),
            (
                "Overlap",
                "generalized Tanimoto overlap of the labels in the common frame, 0 to 1, "
                "<b>higher is better</b>; every weighting is in results.json and in "
                "<code>evaluation/report.html</code>.",
            ),
            (
                "True error",
                "mean distance in mm between where the registration and the true transforms "
                "put each point (known for generated data only); lower is better.",
            ),
            (
                "Verdict says",
                "the recommended setting (&#9733;), the open set the verdict cannot order "
                "(none decided better than them), and the rest.",
            ),
            ("Flags", "physically implausible deformations: a warning, not a decision."),
        ]
    )
    captions = {
        specificity_figure: (
            "Each measure against the first swept option (other options as lines); error "
            "bars: subject-level 95% intervals where computed (the titles say when they are "
            "smaller than the markers); ringed: the best by each measure; star: "
            "specificity's choice; red cross: flagged implausible."
        ),
        "mean_images.png": (
            "The mean image of every setting in the common frame, one grey scale, with the "
            "label boundaries of subject 0 (colour legend: label values). Sharper is better "
            "aligned."
        ),
        "specificity.png": "Specificity of every setting, as in the evaluation's report.",
    }
    figs = "".join(
        _figure(png, fname, captions.get(fname, _e(fname))) for fname, png in figures.items()
    )
    agree = _table(
        ["Measure", "Best setting", "Spearman with specificity"],
        [
            [
                _e(m),
                link(best),
                "–" if m == "specificity" else format_number(result.spearman.get(m), 3),
            ]
            for m, best in result.best_by.items()
        ],
        text=(0, 1),
    ) + (
        "<p>Spearman rank correlation over the settings between specificity and each other "
        "measure, counted so that 1 means agreement (lower specificity with higher overlap, "
        "or with lower true error).</p>"
    )
    options = {
        "method": result.method,
        **{f"parameters.{k}": ", ".join(map(str, v)) for k, v in result.parameters.items()},
        "manifest": result.manifest,
        "reused settings": ", ".join(st.name for st in result.settings if st.reused) or "none",
        **{f"evaluation.{k}": v for k, v in _flat(dict(ev.options))},
        "version": ev.version,
    }
    sections = [
        ("verdict", "Verdict", '<div class="verdict">' + "".join(verdict) + "</div>"),
        (
            "settings",
            "Every setting",
            "<p>In grid order (the last option varies fastest).</p>" + table + legend,
        ),
        ("figures", "Figures", figs),
        ("agreement", "Agreement between measures", agree),
        (
            "options",
            "Inputs and options",
            _options_table(options)
            + "<p>The evaluation's own report (each setting's images, Jacobian maps and "
            "frame) is <code>evaluation/report.html</code> beside this file.</p>",
        ),
    ]
    n_images = first.specificity.n_images
    return _page(
        title=f"Sweep: {result.method} {', '.join(params)}",
        heading=f"Parameter sweep: {result.method}",
        subtitle=(
            f"{len(names)} settings of {_e(', '.join(params))} on N = {n_images} images; "
            f"specificity: {_e(units)}, M = {ev.options['n_samples']:,}; itk-nrreval "
            f"{_e(ev.version)}"
        ),
        sections=sections,
        footer=f"{_SELF_CONTAINED} The numbers are those of sweep.json beside it.",
    )
