"""What ``sweep`` writes for a person: ``sweep.png`` (each measure against the swept options)
and ``report.html`` (the verdict in words, every setting, the figures, the agreement between
measures, the options).

The functions take a :class:`~itk_nrreval.experiments.sweep.SweepResult` without importing its class
(:mod:`itk_nrreval.experiments.sweep` calls this module to write); the key of the true
correspondence error in ``result.best_by`` and ``result.spearman`` is passed as `truth_measure`.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping
from pathlib import Path

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
    slug_ids,
    table_html,
    value_ci,
)
from ._plot import HIDDEN_BARS, bars_hidden, png_bytes
from .evaluation_text import TABLE_OVERLAPS, specificity_units

__all__ = ["sweep_figure", "sweep_report_html", "write_sweep"]

#: The overlap weightings the table shows (the evaluation table's two).
_TABLE_OVERLAPS = tuple(m for m, _ in TABLE_OVERLAPS)


def write_sweep(result, out: Path, *, truth_measure: str) -> list[Path]:
    """Write ``sweep.png`` then ``report.html`` into `out`, each under a temporary name
    renamed when complete; the evaluation's ``mean_images.png`` (already written in
    ``out/evaluation/``) is embedded in the page as it is.

    Parameters
    ----------
    result : SweepResult
    out : Path
        The sweep's folder (existing).
    truth_measure : str
        The key of the true correspondence error in ``result.best_by`` and
        ``result.spearman``.

    Returns
    -------
    list of Path
        The two files written.
    """
    figures = {"sweep.png": png_bytes(sweep_figure(result, truth_measure=truth_measure), dpi=110)}
    with atomic_path(out / "sweep.png") as tmp:
        tmp.write_bytes(figures["sweep.png"])
    means = out / "evaluation" / "mean_images.png"
    if means.is_file():
        figures["mean_images.png"] = means.read_bytes()
    html = sweep_report_html(result, figures=figures, truth_measure=truth_measure)
    write_text(out / "report.html", html)
    return [out / "sweep.png", out / "report.html"]


# ----------------------------------------------------------------------------- sweep.png


def sweep_figure(result, *, truth_measure: str):
    """One panel per measure against the first swept option; other options as lines.

    Subject-level 95% intervals as error bars (when computed; each title says when they are
    smaller than the markers or missing), flagged settings as red crosses, each measure's
    best setting ringed, the verdict's recommendation (when there is one) starred.

    Returns
    -------
    matplotlib.figure.Figure
    """
    from matplotlib.figure import Figure

    first, *others = list(result.parameters)
    xs = list(result.parameters[first])
    numeric = all(isinstance(x, numbers.Real) and not isinstance(x, bool) for x in xs)
    position = {repr(x): (float(x) if numeric else k) for k, x in enumerate(xs)}
    found = list(result.evaluation.scores[result.settings[0].name].measures())
    overlaps = [m for m in found if m.startswith("overlap.")]
    # one overlap weighting is enough to read: inverse volume (every label counts alike)
    overlap = "overlap.inverse_volume" if "overlap.inverse_volume" in overlaps else overlaps[:1]
    measures = ["specificity", *([overlap] if isinstance(overlap, str) else overlap)]
    if result.truth_error_mm is not None:
        measures.append(truth_measure)
    fig = Figure(figsize=(4.2 * len(measures), 3.6), layout="constrained")
    titles = {**_TITLES, truth_measure: "true correspondence error (lower is better)"}
    axes = fig.subplots(1, len(measures), squeeze=False)[0]
    lines: dict[tuple, list] = {}  # settings by the values of the other options
    for s in result.settings:
        lines.setdefault(tuple(repr(s.values[o]) for o in others), []).append(s)
    for ax, measure in zip(axes, measures, strict=True):
        halves = []  # every bar's longer side, to say whether any shows
        for key, group in lines.items():
            x = [position[repr(s.values[first])] for s in group]
            y, err = [], [[], []]
            for s in group:
                v, iv = _value(result, s.name, measure, truth_measure)
                y.append(v)
                err[0].append(v - iv[0] if iv else 0.0)
                err[1].append(iv[1] - v if iv else 0.0)
                halves.append(max(err[0][-1], err[1][-1]) if iv else math.nan)
            label = ", ".join(f"{o}={s}" for o, s in zip(others, key, strict=True)) or None
            ax.errorbar(x, y, yerr=err, marker="o", ms=4, capsize=3, label=label)
            for s, xv, yv in zip(group, x, y, strict=True):
                if result.evaluation.scores[s.name].flags:
                    ax.plot(xv, yv, "x", color="red", ms=10, mew=2)
                if result.best_by.get(measure) == s.name:
                    ax.plot(xv, yv, "o", mfc="none", mec="black", ms=13, mew=1.5)
                if measure == "specificity" and s.name == result.recommended:  # None: no star
                    ax.plot(xv, yv, "*", color="gold", mec="black", ms=15)
        ax.set_xlabel(first)
        if numeric and min(xs) > 0 and max(xs) / min(xs) >= 8:
            ax.set_xscale("log")
            ax.minorticks_off()
        if numeric:
            ax.set_xticks([float(x) for x in xs], [f"{x:g}" for x in xs])
        else:
            ax.set_xticks(range(len(xs)), [str(x) for x in xs])
        if measure == "specificity":
            unit = f"\n{specificity_units(result.evaluation)}"
        else:
            unit = _unit(measure, truth_measure)
        if all(math.isnan(h) for h in halves):
            bars = "no interval" if measure == truth_measure else "no interval computed"
        elif bars_hidden(ax, halves, markersize=4):
            bars = f"95% CI bars {HIDDEN_BARS}"
        else:
            bars = "bars: subject-level 95% CI"
        ax.set_title(f"{titles.get(measure.split('.')[0], measure)}{unit}\n{bars}", fontsize=8)
        if len(lines) > 1 and ax is axes[0]:
            ax.legend(fontsize=7)
    o = result.evaluation.options
    fig.suptitle(
        f"{result.method} sweep (M = {o['n_samples']:,} specificity samples, N = "
        f"{result.evaluation.scores[result.settings[0].name].specificity.n_images} images): "
        "ringed = best by each measure, star = the verdict's recommendation "
        f"({result.recommended or 'none'}), red x = flagged implausible",
        fontsize=8,
    )
    return fig


_TITLES = {
    "specificity": "specificity (lower is better)",
    "overlap": "overlap (higher is better)",
}


def _unit(measure: str, truth_measure: str) -> str:
    if measure == truth_measure:
        return ", mm"
    if measure.startswith("overlap."):
        return f"\n{measure.split('.', 1)[1].replace('_', ' ')} weighting, 0..1"
    return ", intensity units"


def _value(result, name: str, measure: str, truth_measure: str):
    if measure == truth_measure:
        return result.truth_error_mm[name], None
    sc = result.evaluation.scores[name]
    iv = sc.intervals.get(measure)
    ok = iv is not None and math.isfinite(iv.lo) and math.isfinite(iv.hi)
    return sc.measures()[measure], ((iv.lo, iv.hi) if ok else None)


# ----------------------------------------------------------------------------- report.html


def _link(slugs: Mapping[str, str], name: str) -> str:
    """A setting's name, linked to its row of the table."""
    return f'<a href="#{slugs[name]}">{escape(name)}</a>'


def _values(result, name: str) -> str:
    """A setting's option values, ``name = value`` separated by commas."""
    st = next(x for x in result.settings if x.name == name)
    return ", ".join(f"{escape(k)} = {escape(v)}" for k, v in st.values.items())


def _overlaps(result) -> list[str]:
    """The overlap measures of the evaluation (every label weighting), in its order."""
    first = result.evaluation.scores[result.settings[0].name]
    return [m for m in first.measures() if m.startswith("overlap.")]


def _verdict(result, slugs: Mapping[str, str], truth_measure: str) -> str:
    """The verdict in words, in its box: the setting recommended, or why none is and the
    open set; the open pairs among them, the best by overlap and, with the truth, the
    truth's choice."""
    overlaps = _overlaps(result)
    rec = result.recommended
    if rec is not None:
        verdict = [
            f"<p><b>The verdict recommends {_link(slugs, rec)}</b> ({_values(result, rec)}): "
            "decided better than every other setting.</p>"
        ]
    else:
        # never a star for a setting the verdict did not decide for (issue 44): say why
        verdict = [f"<p><b>No setting is recommended</b>: {escape(result.reason)}.</p>"]
        if len(result.not_separable) > 1:
            low = result.lowest_specificity
            verdict.append(
                "<p>The verdict leaves open "
                + ", ".join(_link(slugs, n) for n in result.not_separable)
                + f": no setting is decided better than these. {_link(slugs, low)} "
                f"({_values(result, low)}) has the lowest specificity among them, which "
                "alone decides nothing.</p>"
            )
    candidates = set(result.not_separable)
    open_pairs = result.evaluation.verdict.open_pairs
    among = [p for p in open_pairs if {p.a, p.b} <= candidates]
    verdict += [
        f"<p>{_link(slugs, p.a)} and {_link(slugs, p.b)}: not decided: {escape(p.reason)}.</p>"
        for p in among[:4]
    ]
    by_best: dict[str, list[str]] = {}  # one line per setting overlap prefers
    for m in overlaps:
        if m in result.best_by:
            by_best.setdefault(result.best_by[m], []).append(m.split(".", 1)[1].replace("_", " "))
    for best, weightings in by_best.items():
        verdict.append(
            f"<p>Best by overlap: {_link(slugs, best)} ({escape(', '.join(weightings))} weighting"
            f"{'s' if len(weightings) > 1 else ''}).</p>"
        )
    truth = result.truth_error_mm
    if truth is not None:
        best = result.best_by[truth_measure]
        if rec is not None:
            where = "the same setting" if best == rec else "a different setting"
            chosen = f"the verdict's choice has {format_number(truth[rec], 3)} mm"
        else:
            where = "in the open set" if best in result.not_separable else "not in the open set"
            chosen = "the verdict recommends none"
        verdict.append(
            "<p><b>The truth's choice</b> (lowest true correspondence error): "
            f"{_link(slugs, best)}, "
            f"{format_number(truth[best], 3)} mm, {where}; {chosen}. "
            "Spearman correlation over the settings "
            "between specificity and the true error: "
            f"{format_number(result.spearman.get(truth_measure, math.nan), 3)} (1: the same "
            "order).</p>"
        )
    else:
        verdict.append("<p>No true transforms were given: the truth's choice is unknown.</p>")
    return '<div class="verdict">' + "".join(verdict) + "</div>"


def _settings_table(result, slugs: Mapping[str, str], units: str) -> str:
    """Every setting in grid order: its values, scores, true error, what the verdict says
    and its flags; then the legend."""
    ev = result.evaluation
    params = list(result.parameters)
    names = [st.name for st in result.settings]
    overlaps = _overlaps(result)
    # the table keeps the evaluation table's two weightings; every one is in the verdict
    shown = [m for m in overlaps if m in _TABLE_OVERLAPS] or overlaps
    rec = result.recommended
    truth = result.truth_error_mm
    head = ["Setting", *[escape(p) for p in params], "Specificity<br>[95% CI]", "MC s.e."]
    head += [f"Overlap, {escape(m.split('.', 1)[1].replace('_', ' '))}<br>[95% CI]" for m in shown]
    if truth is not None:
        head.append("True error (mm)")
    head += ["Verdict says", "Flags"]
    rows, classes = [], []
    for st in result.settings:
        sc = ev.scores[st.name]
        row = [escape(st.name), *[escape(st.values[p]) for p in params]]
        row += [
            value_ci(sc.specificity.value, sc.intervals.get("specificity")),
            format_number(sc.specificity.stderr, 2),
        ]
        row += [value_ci(sc.measures()[m], sc.intervals.get(m)) for m in shown]
        if truth is not None:
            row.append(format_number(truth[st.name], 3))
        row.append(_verdict_says(result, st.name))
        row.append("; ".join(escape(f) for f in sc.flags) if sc.flags else "none")
        rows.append(row)
        classes.append("flagged" if sc.flags else "best" if st.name == rec else "")
    table = table_html(
        head,
        rows,
        text=(0, -2, -1),
        classes=classes,
        ids=[slugs[n] for n in names],
        wide=True,
    )
    legend = legend_list(
        [
            (
                "Specificity",
                f"of each setting's texture model ({escape(units)}; M = {ev.options['n_samples']:,}"
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
                "&#9733; recommended: decided better than every other setting, and not "
                "flagged (at most one, often none); open: no setting is decided better than "
                "it; decided worse than: the settings the verdict decides better than it.",
            ),
            ("Flags", "physically implausible deformations: a warning, not a decision."),
        ]
    )
    return table + legend


def _verdict_says(result, name: str) -> str:
    """What the verdict says about one setting, for its row of the table."""
    if name == result.recommended:
        return "&#9733; recommended"
    if name in result.not_separable:
        return "open: none decided better"
    better = [d.better for d in result.evaluation.verdict.decisions if d.worse == name]
    return "decided worse than " + ", ".join(escape(b) for b in better)


def _figures(figures: Mapping[str, bytes], specificity_figure: str) -> str:
    """The sweep's figure and the evaluation's, with captions."""
    captions = {
        specificity_figure: (
            "Each measure against the first swept option (other options as lines); error "
            "bars: subject-level 95% intervals where computed (the titles say when they are "
            "smaller than the markers); ringed: the best by each measure; star: the "
            "verdict's recommendation (none when it decides no setting better than every "
            "other); red cross: flagged implausible."
        ),
        "mean_images.png": (
            "The mean image of every setting in the common frame, one grey scale, with the "
            "label boundaries of subject 0 (colour legend: label values). Sharper is better "
            "aligned."
        ),
        "specificity.png": "Specificity of every setting, as in the evaluation's report.",
    }
    figs = "".join(
        figure_html(png, fname, captions.get(fname, escape(fname)))
        for fname, png in figures.items()
    )
    return figs


def _agreement(result, slugs: Mapping[str, str]) -> str:
    """Each measure's best setting and its Spearman correlation with specificity."""
    agree = table_html(
        ["Measure", "Best setting", "Spearman with specificity"],
        [
            [
                escape(m),
                _link(slugs, best),
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
    return agree


def _options(result) -> str:
    """The sweep's inputs and options, and the evaluation's."""
    ev = result.evaluation
    options = {
        "method": result.method,
        **{f"parameters.{k}": ", ".join(map(str, v)) for k, v in result.parameters.items()},
        "manifest": result.manifest,
        "reused settings": ", ".join(st.name for st in result.settings if st.reused) or "none",
        **{f"evaluation.{k}": v for k, v in flat_items(dict(ev.options))},
        "version": ev.version,
    }
    return (
        options_table(options)
        + "<p>The evaluation's own report (each setting's images, Jacobian maps and "
        "frame) is <code>evaluation/report.html</code> beside this file.</p>"
    )


def sweep_report_html(
    result,
    *,
    figures: Mapping[str, bytes],
    truth_measure: str,
    specificity_figure: str = "sweep.png",
) -> str:
    """The text of ``report.html`` for a :class:`~itk_nrreval.experiments.sweep.SweepResult`.

    The verdict in words first (the setting it recommends, or why none, and the settings it
    leaves open, the best by overlap and, when the true transforms were known, by the true
    correspondence error), then the table of every setting, the figures, the
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
    slugs = slug_ids(names, prefix="setting-")
    params = list(result.parameters)
    first = ev.scores[names[0]]
    units = specificity_units(ev)
    sections = [
        ("verdict", "Verdict", _verdict(result, slugs, truth_measure)),
        (
            "settings",
            "Every setting",
            "<p>In grid order (the last option varies fastest).</p>"
            + _settings_table(result, slugs, units),
        ),
        ("figures", "Figures", _figures(figures, specificity_figure)),
        ("agreement", "Agreement between measures", _agreement(result, slugs)),
        ("options", "Inputs and options", _options(result)),
    ]
    n_images = first.specificity.n_images
    return page_html(
        title=f"Sweep: {result.method} {', '.join(params)}",
        heading=f"Parameter sweep: {result.method}",
        subtitle=(
            f"{len(names)} settings of {escape(', '.join(params))} on N = {n_images} images; "
            f"specificity: {escape(units)}, M = {ev.options['n_samples']:,}; itk-nrreval "
            f"{escape(ev.version)}"
        ),
        sections=sections,
        footer=f"{SELF_CONTAINED} The numbers are those of sweep.json beside it.",
    )
