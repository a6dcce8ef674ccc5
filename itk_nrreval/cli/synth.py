"""``nrreval synth``: write a synthetic population with its true correspondence and a manifest.

The folder layout (images, labels, true transforms, template, montage, manifest) is
described in :mod:`data_synth.writing`; every file is written under a temporary name and
renamed when complete.
"""

from __future__ import annotations

import argparse

from .._errors import InputError
from .._output import check_output_folder, staged_folder
from ._options import integer, seed


def add_parser(sub) -> None:
    p = sub.add_parser(
        "synth",
        help="write a synthetic brain-like population with known true transforms",
        description="Make N subjects from a template (analytic phantom or the MNI152 2009a "
        "template) by known random diffeomorphisms, poses and intensity changes, and write "
        "images, labels, the true transforms and a manifest for `nrreval evaluate`.",
    )
    p.add_argument(
        "--kind", default="phantom", metavar="{phantom,mni}", help="template (default phantom)"
    )
    p.add_argument(
        "--dim", type=int, default=2, metavar="{2,3}", help="2D slice or 3D volume (default 2)"
    )
    # evaluate, specificity and validate need at least 3 images (a texture model of 2 has one
    # mode): a population they cannot use is refused when parsed
    p.add_argument(
        "--n",
        type=integer(3),
        default=36,
        metavar="N",
        help="number of subjects (default 36; at least 3)",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="output directory")
    p.add_argument("--seed", type=seed, default=0, metavar="S", help="random seed (default 0)")
    p.add_argument("--spacing", type=float, default=None, metavar="MM", help="voxel size in mm")
    p.add_argument(
        "--warp",
        type=float,
        default=4.0,
        metavar="MM",
        help="RMS velocity of the warps (default 4)",
    )
    p.add_argument(
        "--smoothness", type=float, default=20.0, metavar="MM", help="warp smoothness (default 20)"
    )
    p.add_argument(
        "--contrasts",
        default="t1",
        metavar="C1,C2",
        help="contrasts to image every subject in, comma-separated, from t1 and t2 (default t1): "
        "with more than one, the files are named after the contrast and the manifest records "
        "each image's contrast under `groups`",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from data_synth.phantom import CONTRASTS
    from data_synth.population import make_population
    from data_synth.writing import write_population

    out = check_output_folder(args.out, command="synth")
    if args.kind not in ("phantom", "mni"):
        raise InputError(f"--kind must be 'phantom' or 'mni', got {args.kind!r}")
    if args.dim not in (2, 3):
        raise InputError(f"--dim must be 2 or 3, got {args.dim}")
    if args.seed < 0:
        raise InputError(f"--seed must be >= 0, got {args.seed}")
    contrasts = tuple(c.strip() for c in args.contrasts.split(","))
    if not all(c in CONTRASTS for c in contrasts) or len(set(contrasts)) != len(contrasts):
        raise InputError(
            f"--contrasts must be distinct names from {', '.join(CONTRASTS)}, "
            f"comma-separated, got {args.contrasts!r}"
        )
    try:
        pop = make_population(
            args.kind,
            dim=args.dim,
            n=args.n,
            seed=args.seed,
            spacing=args.spacing,
            warp_mm=args.warp,
            smoothness_mm=args.smoothness,
            contrasts=contrasts,
        )
    except (ValueError, FileNotFoundError) as exc:
        raise InputError(str(exc).splitlines()[0]) from None
    with staged_folder(out, keep=(), command="synth") as stage:
        manifest = out / write_population(pop, stage).name
    what = f"{args.kind}, {args.dim}D" + (
        "" if contrasts == ("t1",) else f", {'+'.join(contrasts)}"
    )
    print(f"wrote {len(pop)} subjects ({what}) and {manifest}")
    return 0
