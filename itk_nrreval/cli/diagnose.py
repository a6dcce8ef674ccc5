"""``nrreval diagnose MANIFEST --registration NAME --out DIR``: the paper's Table 1.

For each named registration, sample its full appearance model and count the samples in the
Voronoi cells of the raw affinely aligned training images and of their projections onto the
model (:func:`itk_nrreval.appearance.appearance_diagnostics`). Writes into ``DIR``:

    appearance_table1.md     Table 1 layout (raw rows, then projected rows; **0** = empty
                             cell), then empty / near-empty fractions, specificity and
                             representation error per registration and variant
    appearance_table1.csv    one row per registration and variant, one column per image
    appearance_diagnostics.json   every number, the settings and the image paths
    appearance_cells.png     cell-population bars, raw vs projected, one panel per registration

Every file is written under a temporary name and renamed when complete.
"""

from __future__ import annotations

import argparse
import csv
import io
from collections.abc import Sequence
from pathlib import Path

from .._errors import InputError
from .._output import check_output_folder
from ._options import samples, seed

__all__ = ["add_parser", "run", "table1_markdown", "table1_csv", "save_cell_figure"]

_VARIANTS = ("raw", "projected")


def add_parser(sub) -> None:
    p = sub.add_parser(
        "diagnose",
        help="Voronoi cell populations of full appearance-model samples (paper, Table 1)",
        description="Build the full (shape + texture) appearance model of each named "
        "registration, draw M samples in the affinely aligned image space, and count how many "
        "fall in each training image's Voronoi cell, for the raw aligned images and for their "
        "projections onto the model (the paper's Table 1).",
    )
    p.add_argument("manifest", metavar="MANIFEST", help="manifest (YAML or JSON)")
    p.add_argument(
        "--registration",
        action="append",
        required=True,
        metavar="NAME",
        help="a registration of the manifest (repeat for several)",
    )
    p.add_argument(
        "--samples",
        type=samples,
        default=1000,
        metavar="M",
        help="model samples (default 1000, as the paper)",
    )
    p.add_argument("--seed", type=seed, default=0, metavar="S", help="sample seed (default 0)")
    p.add_argument("--out", required=True, metavar="DIR", help="folder for the table and figure")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..appearance import appearance_diagnostics
    from ..manifest import load_manifest

    n_samples = args.samples
    out = Path(args.out)
    check_output_folder(out)
    manifest = load_manifest(args.manifest)  # every problem, before any work
    names = list(dict.fromkeys(args.registration))
    unknown = [n for n in names if n not in manifest.registrations]
    if unknown:
        raise InputError(
            f"--registration {', '.join(unknown)}: not in {args.manifest} "
            f"(have: {', '.join(manifest.names)})"
        )
    results = [
        appearance_diagnostics(
            manifest,
            registration=name,
            n_samples=n_samples,
            seed=args.seed,
            progress=not args.no_progress,
        )
        for name in names
    ]
    paths = write_reports(results, out, images=[str(p) for p in manifest.images])
    print(table1_markdown(results), end="")
    print(f"results written to {out}/ ({', '.join(p.name for p in paths)})")
    return 0


# ----------------------------------------------------------------------------- reports


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
    import numpy as np
    from matplotlib.figure import Figure  # no pyplot: the process's backend is left alone

    from .._output import atomic_path

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


def write_reports(results: Sequence, out: str | Path, *, images: Sequence[str] = ()) -> list[Path]:
    """Write the Markdown and CSV tables, the JSON and the figure into `out` (atomically)."""
    from .._output import write_json, write_text
    from .._version import __version__

    out = Path(out)
    paths = [out / "appearance_table1.md", out / "appearance_table1.csv"]
    write_text(paths[0], table1_markdown(results))
    write_text(paths[1], table1_csv(results))
    paths.append(out / "appearance_diagnostics.json")
    write_json(
        paths[-1],
        {
            "version": __version__,
            "images": list(images),
            "registrations": [r.to_dict() for r in results],
        },
    )
    paths.append(save_cell_figure(results, out / "appearance_cells.png"))
    return paths
