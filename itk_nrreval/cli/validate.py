"""``nrreval validate (MANIFEST | --synthetic KIND) --out DIR``: the paper's Section IV."""

from __future__ import annotations

import argparse
import math

from .._errors import InputError
from ._options import add_quiet_option, seed


def _floats(text: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated numbers such as 0,0.5,1, got {text!r}"
        ) from None
    if not values or any(not (v >= 0) for v in values):
        raise argparse.ArgumentTypeError(f"displacements must be numbers >= 0, got {text!r}")
    return values


def add_parser(sub) -> None:
    from ..experiments.perturbation import DEFAULT_DISPLACEMENTS
    from ..measures.overlap import WEIGHTINGS

    p = sub.add_parser(
        "validate",
        help="perturb a registered set with random CPS warps; specificity vs overlap",
        description="The validation experiment of the paper (Section IV): every image of a "
        "registered, labelled set is perturbed by its own random clamped-plate-spline warp of "
        "mean displacement d pixels; the specificity and generalized overlap of each perturbed "
        "set are recorded. 2D warps are biharmonic (the paper's), 3D warps triharmonic; the "
        "ball is round in mm. Writes validation.csv/.json, validation_fig2.png (specificity "
        "vs overlap) and validation_vs_d.png into --out. A d that no warp reaches without "
        "folding is refused, naming the largest that is reachable.",
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument(
        "manifest", nargs="?", metavar="MANIFEST", help="manifest with labels (common frame)"
    )
    src.add_argument(
        "--synthetic",
        choices=("phantom", "mni"),
        metavar="KIND",
        help="generated brain-like data, perfectly registered: phantom or mni",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--n-images", type=int, default=10, metavar="N", help="synthetic N (default 10)")
    p.add_argument(
        "--dim",
        type=int,
        choices=(2, 3),
        default=None,
        help="synthetic data in 2D (141 x 141, the default) or 3D (2 mm voxels)",
    )
    p.add_argument(
        "--slice",
        type=_section,
        default=None,
        metavar="AXIS[:INDEX]",
        help="validate on the 2D slice of the 3D common frame at INDEX along AXIS (x, y or z; "
        "default the middle slice), as the paper's slices; without it, full 3D",
    )
    p.add_argument(
        "--displacements",
        type=_floats,
        default=list(DEFAULT_DISPLACEMENTS),
        metavar="D,D,...",
        help="mean displacements in pixels (default "
        + ",".join(f"{d:g}" for d in DEFAULT_DISPLACEMENTS)
        + ")",
    )
    p.add_argument(
        "--repeats", type=int, default=5, metavar="R", help="perturbations per d (default 5)"
    )
    p.add_argument(
        "--samples",
        type=int,
        default=50_000,
        metavar="M",
        help="specificity samples (default 50000)",
    )
    p.add_argument(
        "--weighting",
        action="append",
        choices=WEIGHTINGS,
        metavar="W",
        help="overlap weighting, repeatable; the first is plotted "
        "(default complexity, inverse_volume)",
    )
    p.add_argument(
        "--knots", type=int, default=25, metavar="K", help="CPS knots per warp (default 25)"
    )
    p.add_argument(
        "--seed", type=seed, default=0, metavar="S", help="random seed (default %(default)s)"
    )
    p.add_argument("--jobs", type=int, default=2, metavar="J", help="threads (default 2)")
    add_quiet_option(p)
    p.set_defaults(func=run)


def _section(text: str):
    from .._errors import InputError
    from ..experiments.perturbation import parse_section

    try:
        return parse_section(text)
    except InputError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix("slice: ")) from None


def run(args: argparse.Namespace) -> int:
    from .._output import check_output_folder, staged_folder
    from ..experiments.perturbation import FIT_FROM, validate, validate_manifest
    from ..io.manifest import load_manifest

    if args.n_images < 3:
        raise InputError(f"--n-images must be at least 3, got {args.n_images}")
    if args.repeats < 1 or args.samples < 2 or args.knots < 1:
        raise InputError("--repeats and --knots must be >= 1 and --samples >= 2")
    if args.jobs < 1:
        raise InputError(f"--jobs must be at least 1, got {args.jobs}")
    if args.synthetic and args.slice and args.dim != 3:
        raise InputError("--slice needs 3D data: add --dim 3 to --synthetic")
    if args.manifest and args.dim is not None:
        raise InputError("--dim applies to --synthetic only (a manifest has its own)")
    manifest = load_manifest(args.manifest) if args.manifest else None
    inputs = manifest.files if manifest is not None else ()
    out = check_output_folder(args.out, inputs=inputs, command="validate")
    weightings = tuple(args.weighting) if args.weighting else ("complexity", "inverse_volume")
    options = dict(
        displacements=args.displacements,
        repeats=args.repeats,
        n_samples=args.samples,
        weightings=weightings,
        n_knots=args.knots,
        seed=args.seed,
        n_jobs=args.jobs,
        progress=not args.quiet,
    )
    if args.synthetic:
        from data_synth import perfectly_registered_arrays

        images, labels, spacing = perfectly_registered_arrays(
            args.synthetic, n=args.n_images, seed=args.seed, dim=args.dim or 2,
            with_spacing=True,
        )  # fmt: skip
        source = f"synthetic:{args.synthetic}" + (":3d" if args.dim == 3 else "")
        result = validate(
            images, labels, spacing=spacing, section=args.slice, source=source, **options
        )
    else:
        source = str(args.manifest)
        # a manifest may list several registrations: the one whose registered images are
        # perturbed is the common frame's, said before the (long) run
        perturbed = manifest.common_frame
        print(f"perturbing registration {perturbed!r} (the common frame) of {source}", flush=True)
        # the manifest loaded above, not its file again: its check reads every image
        result = validate_manifest(manifest, section=args.slice, source=source, **options)
    with staged_folder(out, keep=(), command="validate") as stage:
        paths = [out / p.name for p in result.write(stage)]
    s = result.summary
    taken = result.parameters.get("section")
    where = f", slice {taken['axis']}:{taken['index']}" if taken else ""
    grid = " x ".join(map(str, result.shape[::-1]))
    print(
        f"{len(result.rows)} perturbed sets of {result.n_images} images of {grid} ({source}{where})"
    )
    for w in weightings:
        lo, hi = s.pearson_ci[w]
        print(
            f"Pearson r (specificity vs {w} overlap, d >= {FIT_FROM:g}) = {_num(s.pearson_r[w])} "
            f"(95% CI {_num(lo)} to {_num(hi)}, n = {s.n_fit})"
        )
    print(f"Spearman (mean specificity vs d, d >= {FIT_FROM:g}) = {_num(s.spearman)}")
    print(
        f"sensitivity = {_num(s.sensitivity, '.3g')} standard errors per pixel of d, "
        f"{_num(s.sensitivity_mm, '.3g')} per mm"
    )
    print("wrote " + ", ".join([str(paths[0]), *(p.name for p in paths[1:])]))
    return 0


def _num(value, spec: str = ".4f") -> str:
    """A summary figure for the terminal: 'undefined' for NaN."""
    return "undefined" if value is None or not math.isfinite(value) else format(value, spec)


def plot_fig2(result, path, *, weighting: str | None = None) -> None:
    """:func:`itk_nrreval.report.validation.plot_fig2`."""
    from ..report.validation import plot_fig2 as draw

    draw(result, path, weighting=weighting)


def plot_vs_d(result, path) -> None:
    """:func:`itk_nrreval.report.validation.plot_vs_d`."""
    from ..report.validation import plot_vs_d as draw

    draw(result, path)
