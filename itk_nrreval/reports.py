"""Writing an :class:`~itk_nrreval.evaluation.EvaluationResult`: JSON, CSV, Markdown, figures.

``summary.md`` is laid out like the paper's Table 3: per registration, the generalized
overlap (inverse-volume, and inverse-volume & complexity weighting) and the specificity with
its standard error, each with its rank and quantitative relative rank. Every file is written
under a temporary name and renamed when complete; figures are written first and the
``results.*`` files last, so an interrupted run leaves no partial ``results.*``.
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
from .evaluation import EvaluationResult

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


def summary_table(result: EvaluationResult) -> str:
    """A Markdown table like the paper's Table 3 (scores, ranks, relative ranks).

    Columns: for each overlap weighting present among inverse volume and inverse volume &
    complexity, then specificity and generalization: score (and standard error), rank and
    relative rank. Lower is better for specificity and generalization, higher for overlap.
    """
    cols = [(m, title) for m, title in _TABLE_OVERLAPS if m in result.ranks]
    header = ["Registration"]
    for _, title in cols:
        header += [f"{title}", "Rank", "Rel. rank"]
    header += ["Specificity", "Std. error", "Rank", "Rel. rank"]
    header += ["Generalization", "Std. error", "Rank", "Rel. rank"]
    rows = []
    for name, s in result.scores.items():
        row = [name]
        for m, _ in cols:
            row += [
                format_number(s.measures()[m]),
                str(result.ranks[m][name]),
                format_percent(result.relative_ranks[m][name]),
            ]
        for m, r in (("specificity", s.specificity), ("generalization", s.generalization)):
            row += [
                format_number(r.value),
                format_number(r.stderr, 2),
                str(result.ranks[m][name]),
                format_percent(result.relative_ranks[m][name]),
            ]
        rows.append(row)
    lines = [
        "| " + " | ".join(header) + " |",
        "|" + "|".join("---" if i == 0 else "--:" for i in range(len(header))) + "|",
    ]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    o = result.options
    notes = [
        "",
        f"Common frame: {result.common_frame}. Specificity and generalization: lower is better "
        f"({o['distance'].upper()} distance, {o['n_samples']} samples, seed {o['seed']}); "
        "overlap: higher is better. Relative rank: best 100%, worst 0%.",
        "",
        "| Registration | Frame from | Spread mean (mm) | Spread max (mm) | Folded (mean) |",
        "|---|---|--:|--:|--:|",
    ]
    for name, s in result.scores.items():
        notes.append(
            f"| {name} | {s.frame.method} | {format_number(s.frame.spread_mean_mm, 3)} | "
            f"{format_number(s.frame.spread_max_mm, 3)} | {s.folded_fraction:.2%} |"
        )
    return "\n".join(lines + notes) + "\n"


def results_csv(result: EvaluationResult) -> str:
    """One row per registration: scores, standard errors, ranks, relative ranks, frame."""
    fields = ["registration", "specificity", "specificity_stderr"]
    fields += ["generalization", "generalization_stderr"]
    overlaps = [m for m in result.measures if m.startswith("overlap.")]
    fields += overlaps
    fields += [f"rank.{m}" for m in result.measures]
    fields += [f"relative_rank.{m}" for m in result.measures]
    fields += ["frame_method", "frame_spread_mean_mm", "frame_spread_max_mm"]
    fields += ["folded_fraction", "folded_max"]
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
        }
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
    import matplotlib.pyplot as plt

    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120, bbox_inches="tight")
    plt.close(fig)


def _middle_slice(img: np.ndarray) -> np.ndarray:
    return img if img.ndim == 2 else img[img.shape[0] // 2]


def _figures(result: EvaluationResult, out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    written = []
    names = list(result.names)
    spec = [result.scores[n].specificity for n in names]
    fig, ax = plt.subplots(figsize=(max(4, 1.2 * len(names)), 3.5))
    ax.errorbar(
        range(len(names)),
        [s.value for s in spec],
        yerr=[s.stderr for s in spec],
        fmt="o",
        capsize=4,
    )
    ax.set_xticks(range(len(names)), names, rotation=30, ha="right")
    ax.set_ylabel("specificity (lower is better)")
    ax.set_title("Specificity ± standard error")
    _save_figure(fig, out / "specificity.png")
    written.append(out / "specificity.png")

    overlap = next((m for m, _ in _TABLE_OVERLAPS if m in result.ranks), None)
    overlap = overlap or next((m for m in result.measures if m.startswith("overlap.")), None)
    if overlap is not None:
        fig, ax = plt.subplots(figsize=(4.5, 3.5))
        xs = [result.scores[n].measures()[overlap] for n in names]
        ax.errorbar(xs, [s.value for s in spec], yerr=[s.stderr for s in spec], fmt="o", capsize=3)
        for x, s, n in zip(xs, spec, names, strict=True):
            ax.annotate(n, (x, s.value), textcoords="offset points", xytext=(4, 4), fontsize=8)
        ax.set_xlabel(f"generalized overlap ({overlap.split('.', 1)[1]}), higher is better")
        ax.set_ylabel("specificity, lower is better")
        _save_figure(fig, out / "specificity_vs_overlap.png")
        written.append(out / "specificity_vs_overlap.png")

    fig, axes = plt.subplots(1, len(names), figsize=(2.6 * len(names), 2.8), squeeze=False)
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


def write_reports(
    result: EvaluationResult, out: str | os.PathLike, *, figures: bool = True
) -> list[Path]:
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
