"""Transitional: ``sweep``'s page, until they move to
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

__all__ = ["sweep_report_html"]

_TABLE_OVERLAPS = ("overlap.inverse_volume", "overlap.inverse_volume_complexity")


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
