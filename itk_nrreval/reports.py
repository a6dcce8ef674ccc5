"""Writing an :class:`~itk_nrreval.evaluation.EvaluationResult`: JSON, CSV, Markdown, figures.

``summary.md`` is laid out like the paper's Table 3: per registration, the generalized
overlap (inverse-volume, and inverse-volume & complexity weighting) and the specificity with
its standard error, each with its rank and quantitative relative rank. Every file is written
under a temporary name and renamed when complete; figures are written first and the
``results.*`` files last, so an interrupted run leaves no partial ``results.*``.

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
from pathlib import Path

import numpy as np

from ._output import atomic_path, write_text

__all__ = ["summary_table", "results_csv", "write_reports", "format_number", "format_percent"]

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
                str(result.ranks[m][name]),
                format_percent(result.relative_ranks[m][name]),
            ]
        row += [
            format_number(s.specificity.value),
            _ci(s, "specificity"),
            format_number(s.specificity.stderr, 2),
            str(result.ranks["specificity"][name]),
            format_percent(result.relative_ranks["specificity"][name]),
        ]
        row += [
            format_number(s.generalization.value),
            _ci(s, "generalization"),
            str(result.ranks["generalization"][name]),
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
        f"Rows in the verdict's order (by specificity, flagged registrations last). Common "
        f"frame: {result.common_frame}. Specificity and generalization: lower is better "
        f"({o['distance'].upper()} distance in the model's parameter space, in the images' "
        f"intensity units; M = {o['n_samples']} samples, seed {o['seed']}); overlap: higher "
        "is better. 95% CI: subject-level interval (jackknife over the subjects: would the "
        "score hold for other subjects?). MC s.e.: Monte-Carlo standard error of the "
        "specificity estimate only (it shrinks as M grows). Rank: 1 is best. Rel. rank: "
        "100% for the best score, 0% for the worst, linear between, (worst - x) / "
        "(worst - best).",
        "",
        "| Registration | Frame from | Spread mean (mm) | Spread max (mm) | Folded (mean) | "
        "Folded (worst image) | SDlogJ | det J min | det J max | Inverse consistency (mm) |",
        "|---|---|--:|--:|--:|--:|--:|--:|--:|--:|",
    ]
    for name in order:
        s = result.scores[name]
        pl = s.plausibility
        notes.append(
            f"| {name} | {s.frame.method} | {format_number(s.frame.spread_mean_mm, 3)} | "
            f"{format_number(s.frame.spread_max_mm, 3)} | {pl.folded_fraction:.2%} | "
            f"{pl.folded_max:.2%} | {format_number(pl.sdlogj, 3)} | "
            f"{format_number(pl.jacobian_min, 3)} | {format_number(pl.jacobian_max, 3)} | "
            f"{format_number(pl.inverse_consistency_mm, 3)} |"
        )
    return "\n".join(lines + notes) + "\n"


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


def _save_figure(fig, path: Path) -> None:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120, bbox_inches="tight")


def _middle_slice(img: np.ndarray) -> np.ndarray:
    return img if img.ndim == 2 else img[img.shape[0] // 2]


def _figures(result, out: Path) -> list[Path]:
    # Figure objects without pyplot: no process-wide backend is chosen or changed
    from matplotlib.figure import Figure

    written = []
    names = list(result.verdict.ranking) if result.verdict is not None else list(result.names)
    spec = [result.scores[n].specificity for n in names]
    values = np.array([s.value for s in spec])
    ivs = [result.scores[n].intervals.get("specificity") for n in names]
    has_ci = all(iv is not None and math.isfinite(iv.lo) for iv in ivs)
    fig = Figure(figsize=(max(4.5, 1.3 * len(names)), 3.8))
    ax = fig.subplots()
    colors = ["tab:red" if result.scores[n].flags else "tab:blue" for n in names]
    if has_ci:
        err = np.array([[v - iv.lo, iv.hi - v] for v, iv in zip(values, ivs, strict=True)]).T
    else:
        err = np.array([[s.stderr for s in spec]] * 2)
    for x, (v, c) in enumerate(zip(values, colors, strict=True)):
        ax.errorbar(x, v, yerr=err[:, x : x + 1], fmt="o", capsize=5, color=c)
    labels = [f"{n}\n(flagged)" if result.scores[n].flags else n for n in names]
    ax.set_xticks(range(len(names)), labels, rotation=30, ha="right")
    o = result.options
    ax.set_ylabel(f"specificity ({o['distance'].upper()}; lower is better)")
    mc = max(s.stderr for s in spec)
    what = (
        "bars: 95% subject-level interval (jackknife over subjects)"
        if has_ci
        else "bars: Monte-Carlo standard error"
    )
    ax.set_title(
        f"Specificity, M = {o['n_samples']:,} samples; {what}\n"
        f"Monte-Carlo s.e. at most {mc:.2g}"
        + (" (too small to draw)" if has_ci else "")
        + "; red: flagged as implausible",
        fontsize=8,
    )
    _save_figure(fig, out / "specificity.png")
    written.append(out / "specificity.png")

    overlap = next((m for m, _ in _TABLE_OVERLAPS if m in result.ranks), None)
    overlap = overlap or next((m for m in result.measures if m.startswith("overlap.")), None)
    if overlap is not None:
        fig = Figure(figsize=(4.5, 3.5))
        ax = fig.subplots()
        xs = [result.scores[n].measures()[overlap] for n in names]
        ax.errorbar(xs, [s.value for s in spec], yerr=[s.stderr for s in spec], fmt="o", capsize=3)
        for x, s, n in zip(xs, spec, names, strict=True):
            ax.annotate(n, (x, s.value), textcoords="offset points", xytext=(4, 4), fontsize=8)
        ax.set_xlabel(f"generalized overlap ({overlap.split('.', 1)[1]}), higher is better")
        ax.set_ylabel("specificity, lower is better")
        _save_figure(fig, out / "specificity_vs_overlap.png")
        written.append(out / "specificity_vs_overlap.png")

    fig = Figure(figsize=(2.6 * len(names), 2.8))
    axes = fig.subplots(1, len(names), squeeze=False)
    lo = min(float(np.min(result.mean_images[n])) for n in names)
    hi = max(float(np.max(result.mean_images[n])) for n in names)
    for ax, n in zip(axes[0], names, strict=True):
        ax.imshow(
            _middle_slice(result.mean_images[n]), cmap="gray", vmin=lo, vmax=hi, origin="lower"
        )
        ax.set_title(n, fontsize=9)
        ax.axis("off")
    fig.suptitle("Mean image in the common frame")
    _save_figure(fig, out / "mean_images.png")
    written.append(out / "mean_images.png")
    return written


def write_reports(result, out: str | os.PathLike, *, figures: bool = True) -> list[Path]:
    """Write figures, then ``results.json``, ``results.csv`` and ``summary.md`` into `out`.

    Returns
    -------
    list of Path
        The files written.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written = _figures(result, out) if figures else []
    # build everything before writing any results.* file
    texts = {
        "results.json": json.dumps(result.to_dict(), indent=2, default=_json_default) + "\n",
        "results.csv": results_csv(result),
        "summary.md": summary_table(result),
    }
    for fname, text in texts.items():
        write_text(out / fname, text)
        written.append(out / fname)
    return written
