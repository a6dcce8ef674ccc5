"""``nrreval diagnose MANIFEST --registration NAME --out DIR``: the paper's Table 1.

For each named registration, sample its full appearance model and count the samples in the
Voronoi cells of the raw affinely aligned training images and of their projections onto the
model (:func:`itk_nrreval.experiments.appearance.diagnose.diagnose`), and write the reports
:meth:`~itk_nrreval.experiments.appearance.diagnose.DiagnosticsResult.write` writes into ``DIR``
(``appearance_table1.md`` / ``.csv``, ``appearance_diagnostics.json``,
``appearance_cells.png``; see :mod:`itk_nrreval.experiments.appearance.diagnose`).
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

from .._errors import InputError
from .._output import check_output_folder, staged_folder
from ..experiments.appearance.diagnose import DiagnosticsResult
from ..report.diagnostics import save_cell_figure, table1_csv, table1_markdown
from ._options import add_quiet_option, samples, seed

__all__ = [
    "add_parser",
    "run",
    "write_reports",
    "table1_markdown",
    "table1_csv",
    "save_cell_figure",
]


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
    add_quiet_option(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..experiments.appearance.diagnose import diagnose
    from ..io.manifest import load_manifest

    manifest = load_manifest(args.manifest)  # every problem, before any work
    out = check_output_folder(args.out, inputs=manifest.files, command="diagnose")
    _warn_label_like_images(manifest)
    names = list(dict.fromkeys(args.registration))
    unknown = [n for n in names if n not in manifest.registrations]
    if unknown:
        raise InputError(
            f"--registration {', '.join(unknown)}: not in {args.manifest} "
            f"(have: {', '.join(manifest.names)})"
        )
    result = diagnose(
        manifest,
        registrations=names,
        n_samples=args.samples,
        seed=args.seed,
        progress=not args.quiet,
    )
    with staged_folder(out, keep=(), command="diagnose") as stage:
        paths = [out / p.name for p in result.write(stage)]
    print(result.table_markdown(), end="")
    print(f"results written to {out}/ ({', '.join(p.name for p in paths)})")
    return 0


def _warn_label_like_images(manifest) -> None:
    """Warn about each image that looks like a label map, as ``evaluate`` does."""
    from ..io._images import label_like_values, read_image, warn_label_like

    for item in manifest.scored_images:
        if (n_values := label_like_values(read_image(item))) is not None:
            warn_label_like(str(item), n_values)


def write_reports(results: Sequence, out: str | Path, *, images: Sequence[str] = ()) -> list[Path]:
    """Write the reports of `results` (AppearanceDiagnostics) into `out`; see
    :meth:`itk_nrreval.experiments.appearance.diagnose.DiagnosticsResult.write`."""
    from .._version import __version__

    inputs = {"images": [str(p) for p in images]}
    return DiagnosticsResult(tuple(results), inputs, __version__).write(out)
