"""What ``nrreval diagnose`` writes for a person: the paper's Table 1 as Markdown and CSV, and
the cell-population bars (``appearance_cells.png``).

The functions take :class:`~itk_nrreval.experiments.appearance.model.AppearanceDiagnostics` (one per
registration) and a :class:`~itk_nrreval.experiments.appearance.diagnose.DiagnosticsResult` without
importing their classes (:mod:`itk_nrreval.experiments.appearance.diagnose` calls this module to
write).
"""

from __future__ import annotations

import csv
import io
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from .._output import atomic_path, claim_entries, write_json, write_text

__all__ = ["table1_markdown", "table1_csv", "save_cell_figure", "write_diagnostics"]


def write_diagnostics(result, out_dir: str | os.PathLike) -> list[Path]:
    """Write ``appearance_table1.md``, ``appearance_table1.csv``,
    ``appearance_diagnostics.json`` and ``appearance_cells.png`` into `out_dir`, each under
    a temporary name renamed when complete.

    Parameters
    ----------
    result : DiagnosticsResult
    out_dir : path

    Returns
    -------
    list of Path
        The four files, in that order.
    """
    names = [
        "appearance_table1.md",
        "appearance_table1.csv",
        "appearance_diagnostics.json",
        "appearance_cells.png",
    ]
    out = claim_entries(out_dir, names, command="diagnose")
    paths = [out / names[0], out / names[1]]
    write_text(paths[0], table1_markdown(result.results))
    write_text(paths[1], table1_csv(result.results))
    paths.append(out / names[2])
    write_json(paths[-1], result.to_dict())
    paths.append(save_cell_figure(result.results, out / names[3]))
    return paths


_VARIANTS = ("raw", "projected")


def _pct(v: float) -> str:
    return f"{100 * v:.0f}%"


def table1_markdown(results: Sequence) -> str:
    """The Table 1 layout as Markdown.

    Parameters
    ----------
    results : sequence of AppearanceDiagnostics
        One per registration, all with the same number of images.

    Returns
    -------
    str
        A counts table (raw rows, then projected rows, one column per training image,
        numbered from 1; empty cells as **0**) and a summary table: empty and near-empty
        fractions, full-appearance specificity ± standard error, representation error.
    """
    if not results:
        return ""
    n = results[0].n_images
    m = results[0].n_samples
    head = "| Image | " + " | ".join(str(i + 1) for i in range(n)) + " |"
    rule = "|---|" + "---:|" * n
    lines = [
        f"Voronoi cell populations of the training images for M = {m} samples of each "
        f"registration's full appearance model (N = {n} images; **0** = empty cell).",
        "",
        head,
        rule,
    ]
    for variant in _VARIANTS:
        lines.append(f"| *{variant}* |" + " |" * n)
        for r in results:
            counts = getattr(r, variant).counts
            cells = " | ".join("**0**" if c == 0 else str(int(c)) for c in counts)
            lines.append(f"| {r.registration} | {cells} |")
    threshold = results[0].raw.near_empty_threshold
    lines += [
        "",
        f"Near-empty: fewer than {threshold:g} samples (10% of the uniform share M / N). "
        "Specificity: mean L2 distance (intensity units) from a sample to its nearest "
        "training image. Representation error: |raw - projected| per image (mean, max), "
        "against the mean distance between a raw image and its nearest other image. "
        "Samples reassigned: samples whose nearest raw image differs from their nearest "
        "projected one.",
        "",
        "| registration | variant | empty | near-empty | specificity ± stderr "
        "| representation error (mean, max) | nearest-image distance | samples reassigned |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in results:
        err = f"{r.representation_error.mean():.3g}, {r.representation_error.max():.3g}"
        spacing = f"{r.training_spacing.mean():.3g}"
        for variant in _VARIANTS:
            c = getattr(r, variant)
            lines.append(
                f"| {r.registration} | {variant} | {_pct(c.empty_fraction)} "
                f"| {_pct(c.near_empty_fraction)} | {c.specificity:.4g} ± {c.stderr:.2g} "
                f"| {err} | {spacing} | {_pct(r.reassigned_fraction)} |"
            )
    return "\n".join(lines) + "\n"


def table1_csv(results: Sequence) -> str:
    """One row per registration and variant, one column per training image (CSV text)."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    n = results[0].n_images if results else 0
    writer.writerow(
        [
            "registration",
            "variant",
            *[f"image_{i + 1}" for i in range(n)],
            "empty_fraction",
            "near_empty_fraction",
            "near_empty_threshold",
            "specificity",
            "stderr",
            "n_samples",
        ]
    )
    for variant in _VARIANTS:
        for r in results:
            c = getattr(r, variant)
            writer.writerow(
                [
                    r.registration,
                    variant,
                    *[int(v) for v in c.counts],
                    f"{c.empty_fraction:.6g}",
                    f"{c.near_empty_fraction:.6g}",
                    f"{c.near_empty_threshold:.6g}",
                    f"{c.specificity:.8g}",
                    f"{c.stderr:.6g}",
                    r.n_samples,
                ]
            )
    return buf.getvalue()


def save_cell_figure(results: Sequence, path: str | Path) -> Path:
    """Cell-population bars, raw vs projected, one panel per registration (PNG, atomic)."""
    from matplotlib.figure import Figure  # no pyplot: the process's backend is left alone

    path = Path(path)
    fig = Figure(figsize=(9, 2.2 * len(results) + 0.6))
    axes = fig.subplots(len(results), 1, squeeze=False, sharex=True)
    for ax, r in zip(axes[:, 0], results, strict=True):
        x = np.arange(1, r.n_images + 1)
        ax.bar(x - 0.2, r.raw.counts, width=0.4, color="tab:orange", label="raw")
        ax.bar(x + 0.2, r.projected.counts, width=0.4, color="tab:blue", label="projected")
        ax.axhline(r.n_samples / r.n_images, color="k", lw=0.8, ls="--", label="uniform M/N")
        ax.axhline(r.raw.near_empty_threshold, color="0.4", lw=0.8, ls=":", label="near-empty")
        ax.set_ylabel("samples")
        ax.set_title(
            f"{r.registration}: empty cells raw {_pct(r.raw.empty_fraction)}, projected "
            f"{_pct(r.projected.empty_fraction)}; near-empty raw "
            f"{_pct(r.raw.near_empty_fraction)}, projected {_pct(r.projected.near_empty_fraction)}",
            fontsize=9,
        )
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, fontsize=8, ncol=4, loc="upper center")
    axes[-1, 0].set_xlabel("training image")
    axes[-1, 0].set_xticks(np.arange(1, results[-1].n_images + 1))
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.35 / fig.get_figheight()))
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    return path
