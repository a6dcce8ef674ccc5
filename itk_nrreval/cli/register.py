"""``nrreval register --images IMAGE... --method METHOD --out DIR``: register a group of images.

``--method multimodal`` registers a group mixing modalities
(:func:`itk_nrreval.experiments.registration.register_multimodal`, ``--strategy joint|per-group``);
each image's group comes from ``--groups`` or, when that is not given, from the manifest's
``groups``, and is recorded in the manifest.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from .._errors import InputError
from ._options import add_quiet_option, seed


def add_parser(sub) -> None:
    from ..experiments.registration import ENGINES, STRATEGIES

    engines = sorted({e for es in ENGINES.values() for e in es})
    p = sub.add_parser(
        "register",
        help="register a group of images (affine, fluid, pairwise, groupwise, multimodal)",
        description="Register N images with one of the paper's algorithms; write per-image "
        "transforms (.h5, reference -> image, ITK convention), the reference image and "
        "registration.json to --out, and add the registration to a manifest.",
    )
    p.add_argument("--images", nargs="+", required=True, metavar="IMAGE", help="the images")
    p.add_argument(
        "--method",
        required=True,
        choices=("affine", "fluid", "pairwise", "groupwise", "multimodal"),
        help="multimodal: a group mixing modalities, with --strategy and each image's group",
    )
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
        "(elastix's own groupwise metric on a stack of 2D images; 2D only); multimodal: "
        "elastix (default) or simpleitk",
    )
    mm = p.add_argument_group("multimodal", "options of --method multimodal")
    mm.add_argument(
        "--strategy",
        choices=STRATEGIES,
        help="joint (default): every image to one reference with mutual information; "
        "per-group: each group to its own reference with correlation, linked to the "
        "reference group by one mutual-information registration",
    )
    mm.add_argument(
        "--groups",
        nargs="+",
        metavar="GROUP",
        help="each image's group (e.g. modality), one per image, in --images order "
        "(default: the manifest's groups)",
    )
    mm.add_argument(
        "--reference-group",
        metavar="GROUP",
        help="the group whose near-mean image is the frame (default: the first image's, in "
        "the manifest's order when it exists)",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument(
        "--manifest",
        metavar="PATH",
        help="manifest to add the registration to "
        "(default DIR/../manifest.yaml; created if needed)",
    )
    p.add_argument(
        "--name",
        help="registration name in the manifest (default: the method; multimodal-STRATEGY); "
        "a name the manifest has already is refused, unless --replace",
    )
    p.add_argument(
        "--replace",
        action="store_true",
        help="replace the manifest's registration of that name with this one",
    )
    p.add_argument(
        "--seed", type=seed, default=0, metavar="S", help="random seed (default %(default)s)"
    )
    add_quiet_option(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from .._output import check_output_folder, staged_folder
    from ..experiments.registration import register
    from ..experiments.registration.multimodal import record_groups
    from ..io.manifest import (
        add_registration,
        check_rewritable,
        load_manifest,
        order_as_in_manifest,
    )
    from ..io.transforms import file_stem

    inputs = [*args.images, *(p for p in (args.reference, args.manifest) if p is not None)]
    out = check_output_folder(
        args.out, inputs=inputs, command="register"
    )  # before the (long) registration
    manifest = Path(args.manifest) if args.manifest else out.parent / "manifest.yaml"
    check_rewritable(manifest)  # before the (long) registration
    old = load_manifest(manifest, check_files=False) if manifest.exists() else None
    # --images may come in any order (a shell glob lists s00_t1 s00_t2 s01_t1 ...): they are
    # registered, named and recorded in the manifest's order, which its groups follow.
    order = None if old is None else order_as_in_manifest(args.images, old, what="--images")
    name = _registration_name(args)
    if old is not None and name in old.registrations and not args.replace:
        # the registration it names may be hours of work, its transforms listed nowhere else
        raise InputError(
            f"{manifest}: has a registration named {name!r} already; give another --name, "
            "or --replace to replace it (nothing was written)"
        )
    images = list(args.images) if order is None else [args.images[k] for k in order]
    if args.method == "multimodal":
        result = _register_multimodal(args, manifest, old, images, order)
    else:
        given = [f"--{k.replace('_', '-')}" for k in _MULTIMODAL_ONLY if getattr(args, k)]
        if given:
            raise InputError(f"{given[0]} is an option of --method multimodal only")
        result = register(  # an EngineError becomes one line and exit code 1 (cli.main)
            images,
            method=args.method,
            reference=args.reference,
            reference_choice=args.reference_choice,
            engine=args.engine,
            seed=args.seed,
            progress=not args.quiet,
        )
    names = [file_stem(p) for p in images]
    # Written into a sibling folder swapped in when complete: `out` never mixes two runs.
    with staged_folder(out, keep=(), command="register") as stage:
        staged = result.write(stage, names=names)
    paths = {
        "reference": out / staged["reference"].name,
        "transforms": [out / p.name for p in staged["transforms"]],
    }
    multimodal = args.method == "multimodal"
    add_registration(
        manifest,
        name,
        reference=paths["reference"],
        transforms=[str(p) for p in paths["transforms"]],
        reference_index=result.reference_index,
        images=images,
        parameters=result.manifest_parameters() if multimodal else None,
    )
    if multimodal:
        record_groups(manifest, result.groups)
    what = f"{args.method} {result.strategy}" if multimodal else args.method
    print(
        f"{what} ({result.engine}): {result.n_images} images in {result.seconds:.1f} s; "
        f"reference {_describe_reference(result, images)}"
    )
    print(f"wrote {out}/ and registration {name!r} in {manifest}")
    return 0


_MULTIMODAL_ONLY = ("strategy", "groups", "reference_group")


def _strategy(args: argparse.Namespace) -> str:
    """``--strategy``, or the first of :data:`STRATEGIES` (the default)."""
    from ..experiments.registration import STRATEGIES

    return args.strategy or STRATEGIES[0]


def _registration_name(args: argparse.Namespace) -> str:
    """The registration's name in the manifest: ``--name``, or one from the method."""
    if args.name:
        return args.name
    if args.method == "multimodal":  # the two strategies side by side in one manifest
        return f"multimodal-{_strategy(args)}"
    return f"{args.method}-{args.reference_choice}" if args.reference_choice else args.method


def _register_multimodal(
    args: argparse.Namespace, manifest: Path, old, images: list[str], order: list[int] | None
):
    """:func:`register_multimodal` on `images`, with their groups.

    `images` are ``--images`` in the order of the manifest `old` (``images[j] ==
    args.images[order[j]]``; `order` and `old` are None when there is no manifest yet). The
    groups are ``--groups`` (given in ``--images`` order), else the manifest's; both are
    checked before the registration, and ``--groups`` against the manifest's.
    """
    from ..experiments.registration import register_multimodal
    from ..experiments.registration.multimodal import check_groups

    if args.reference is not None or args.reference_choice is not None:
        raise InputError(
            "--method multimodal chooses its references (each group's near-mean image); "
            "give --reference-group instead of --reference / --reference-choice"
        )
    if args.groups is not None:
        groups = check_groups(args.groups, len(args.images))
        if order is not None:
            groups = tuple(groups[k] for k in order)
        if old is not None and old.groups is not None and tuple(old.groups) != groups:
            raise InputError(f"--groups differ from the groups of {manifest}")
    elif old is not None and old.groups is not None:
        groups = tuple(old.groups)
    else:
        state = "has none" if old is not None else "does not exist"
        raise InputError(
            "--method multimodal needs each image's group: give --groups (one per image) "
            f"or a manifest with groups ({manifest} {state})"
        )
    return register_multimodal(  # an EngineError becomes one line and exit code 1
        images,
        groups,
        strategy=_strategy(args),
        engine=args.engine,
        reference_group=args.reference_group,
        seed=args.seed,
        progress=not args.quiet,
    )


def _describe_reference(result, images) -> str:
    if result.reference_index is not None:
        return f"image {result.reference_index} ({images[result.reference_index]})"
    return "group mean" if result.method == "groupwise" else "given image"
