"""``nrreval register --images IMAGE... --method METHOD --out DIR``: register a group of images."""

from __future__ import annotations

import argparse
from pathlib import Path

from ._options import seed


def add_parser(sub) -> None:
    from ..registration import ENGINES

    engines = sorted({e for es in ENGINES.values() for e in es})
    p = sub.add_parser(
        "register",
        help="register a group of images (affine, fluid, pairwise, groupwise)",
        description="Register N images with one of the paper's algorithms; write per-image "
        "transforms (.h5, reference -> image, ITK convention), the reference image and "
        "registration.json to --out, and add the registration to a manifest.",
    )
    p.add_argument("--images", nargs="+", required=True, metavar="IMAGE", help="the images")
    p.add_argument("--method", required=True, choices=("affine", "fluid", "pairwise", "groupwise"))
    ref = p.add_mutually_exclusive_group()
    ref.add_argument("--reference", metavar="REF", help="reference image (default: near-mean)")
    ref.add_argument(
        "--reference-choice",
        choices=("near-mean", "far-from-mean"),
        help="pick the training image nearest to / farthest from the affinely aligned mean",
    )
    p.add_argument(
        "--engine",
        choices=engines,
        help="affine: simpleitk; fluid: simpleitk (default) or ants; pairwise: elastix "
        "(default) or simpleitk; groupwise: elastix (default), simpleitk or elastix-stack "
        "(elastix's own groupwise metric on a stack of 2D images; 2D only)",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument(
        "--manifest",
        metavar="PATH",
        help="manifest to add the registration to "
        "(default DIR/../manifest.yaml; created if needed)",
    )
    p.add_argument("--name", help="registration name in the manifest (default: the method)")
    p.add_argument("--seed", type=seed, default=0, metavar="S")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from .._output import check_output_folder, staged_folder
    from ..manifest import add_registration
    from ..registration import register

    out = check_output_folder(args.out)  # before the (long) registration
    reference = args.reference
    result = register(  # an EngineError becomes one line and exit code 1 (cli.main)
        args.images,
        method=args.method,
        reference=reference,
        reference_choice=args.reference_choice,
        engine=args.engine,
        seed=args.seed,
        progress=not args.no_progress,
    )
    names = [_stem(p) for p in args.images]
    # Written into a sibling folder swapped in when complete: `out` never mixes two runs.
    with staged_folder(out, keep=()) as stage:
        staged = result.write(stage, names=names)
    paths = {
        "reference": out / staged["reference"].name,
        "transforms": [out / p.name for p in staged["transforms"]],
    }
    manifest = Path(args.manifest) if args.manifest else out.parent / "manifest.yaml"
    name = args.name or (
        f"{args.method}-{args.reference_choice}" if args.reference_choice else args.method
    )
    add_registration(
        manifest,
        name,
        reference=paths["reference"],
        transforms=[str(p) for p in paths["transforms"]],
        reference_index=result.reference_index,
        images=list(args.images),
    )
    print(
        f"{args.method} ({result.engine}): {result.n_images} images in {result.seconds:.1f} s; "
        f"reference {_describe_reference(result, args.images)}"
    )
    print(f"wrote {out}/ and registration {name!r} in {manifest}")
    return 0


def _stem(path: str) -> str:
    name = Path(path).name
    for suffix in (".nii.gz", ".nii", ".mha", ".mhd", ".nrrd", ".nhdr"):
        if name.endswith(suffix):
            return name[: -len(suffix)]
    return Path(name).stem


def _describe_reference(result, images) -> str:
    if result.reference_index is not None:
        return f"image {result.reference_index} ({images[result.reference_index]})"
    return "group mean" if result.method == "groupwise" else "given image"
