"""``nrreval specificity IMAGE...``: specificity of a set of registered images."""

from __future__ import annotations

import argparse

from .._output import write_json
from ._options import add_quiet_option, positive, samples, seed


def add_parser(sub) -> None:
    p = sub.add_parser(
        "specificity",
        help="specificity of the texture model of registered images",
        description="Specificity (and generalization) of the shape-free texture model of "
        "N registered images on one grid. Lower is better.",
    )
    p.add_argument(
        "images", nargs="+", metavar="IMAGE", help="registered images (NIfTI, MHA, NRRD)"
    )
    p.add_argument("--mask", help="evaluate only voxels where this image is nonzero")
    p.add_argument(
        "--samples",
        type=samples,
        default=100_000,
        metavar="M",
        help="model samples (default 100000)",
    )
    p.add_argument(
        "--distance",
        choices=("l1", "l2"),
        default="l1",
        help="parameter-space distance (default %(default)s)",
    )
    p.add_argument(
        "--exponent",
        type=positive,
        default=1.0,
        metavar="L",
        help="the paper's lambda (default %(default)g)",
    )
    p.add_argument(
        "--seed", type=seed, default=0, metavar="S", help="sample seed (default %(default)s)"
    )
    p.add_argument(
        "--groups",
        type=_group_list,
        metavar="G1,G2,...",
        help="each image's group (e.g. modality), comma-separated in image order: the model "
        "becomes a Gaussian mixture with one Gaussian per group (at least 2 images each)",
    )
    p.add_argument("--json", metavar="OUT", help="also write the numbers to this JSON file")
    add_quiet_option(p)
    p.set_defaults(func=run)


def _group_list(text: str) -> list[str]:
    """``"t1,t1,t2"`` -> ``["t1", "t1", "t2"]``; empty labels are refused."""
    labels = [part.strip() for part in text.split(",")]
    if not all(labels):
        raise argparse.ArgumentTypeError(f"expected comma-separated group labels, got {text!r}")
    return labels


def run(args: argparse.Namespace) -> int:
    from .._output import TOOL, check_output_file, json_written_by_nrreval
    from .._version import __version__
    from ..io.manifest import check_image_contents
    from ..measures.specificity import texture_measures

    if args.json:  # before the work, not after it
        inputs = [*args.images, *(p for p in (args.mask,) if p is not None)]
        check_output_file(args.json, inputs=inputs, option="--json", ours=json_written_by_nrreval)
    # what evaluate's manifest check refuses in its images: a duplicate, a constant image
    check_image_contents(args.images)

    spec, gen = texture_measures(
        args.images,
        n_samples=args.samples,
        distance=args.distance,
        exponent=args.exponent,
        seed=args.seed,
        mask=args.mask,
        groups=args.groups,
        progress=not args.quiet,
    )
    print(
        f"specificity = {spec.value:.6g} ± {spec.stderr:.2g} "
        f"({spec.n_samples} samples, {spec.n_images} images)"
    )
    mix = spec.mixture
    if mix is not None:
        names = [str(g) for g in mix.groups]
        for g, name in enumerate(names):
            nearest = ", ".join(
                f"{h}: {int(c)}" for h, c in zip(names, mix.nearest_counts[g], strict=True)
            )
            print(
                f"  group {name}: {mix.values[g]:.6g} ± {mix.stderrs[g]:.2g} "
                f"({mix.sizes[g]} images, {mix.n_samples[g]} samples; nearest {nearest})"
            )
    print(f"generalization = {gen.value:.6g} ± {gen.stderr:.2g}")
    if args.json:
        record = {
            "tool": TOOL,
            "version": __version__,
            "images": list(args.images),
            "mask": args.mask,
        }
        if args.groups is not None:
            record["groups"] = args.groups
        record["specificity"] = spec.to_dict()
        record["generalization"] = gen.to_dict()
        write_json(args.json, record)
    return 0
