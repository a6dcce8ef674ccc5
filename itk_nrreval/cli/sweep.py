"""``nrreval sweep --images IMAGE... --method M --param NAME=v1,v2,... --out DIR``."""

from __future__ import annotations

import argparse

from ._options import add_quiet_option, samples, seed


def _parameter(text: str):
    from .._errors import InputError
    from ..experiments.sweep import parse_parameter

    try:
        return parse_parameter(text)
    except InputError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix(f"--param {text!r}: ")) from None


def add_parser(sub) -> None:
    p = sub.add_parser(
        "sweep",
        help="register once per setting of a method's options; which setting is best?",
        description="Tune a registration without ground truth: register the images once per "
        "setting of a grid over the method's options (--param, repeatable), evaluate every "
        "setting side by side, and name the setting specificity prefers with those it cannot "
        "separate from it. With --from a generated population's manifest and --truth, the "
        "true correspondence error is reported beside it. Writes registrations/, "
        "manifest.yaml, cache/, evaluation/ and sweep.json/.csv/.png into --out; a rerun "
        "with more values registers and evaluates only the new settings.",
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--images", nargs="+", metavar="IMAGE", help="the images")
    src.add_argument(
        "--from",
        dest="source",
        metavar="MANIFEST",
        help="take the images, label maps and mask from this manifest",
    )
    p.add_argument("--labels", nargs="+", metavar="LABEL", help="label maps of --images")
    p.add_argument("--mask", metavar="MASK", help="evaluate inside this mask")
    p.add_argument(
        "--truth",
        metavar="NAME",
        help="with --from: the registration of that manifest holding the true transforms",
    )
    p.add_argument("--method", required=True, choices=("fluid", "pairwise", "groupwise", "affine"))
    p.add_argument(
        "--param",
        action="append",
        type=_parameter,
        required=True,
        metavar="NAME=V1,V2",
        help="an option of the method and its values (repeat for a grid); a value with ':' "
        "is a per-level tuple, e.g. iterations=100:60:40,50:30:20",
    )
    p.add_argument("--engine", help="the method's engine (see nrreval register --help)")
    p.add_argument(
        "--reference-choice",
        choices=("near-mean", "far-from-mean"),
        default="near-mean",
        help="the reference of fluid/pairwise/affine (default near-mean)",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument(
        "--samples",
        type=samples,
        default=20_000,
        metavar="M",
        help="specificity samples (default %(default)s)",
    )
    p.add_argument(
        "--seed", type=seed, default=0, metavar="S", help="random seed (default %(default)s)"
    )
    add_quiet_option(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from .._errors import InputError
    from .._output import check_output_folder
    from ..experiments.sweep import sweep
    from ..io.manifest import load_manifest
    from ..io.transforms import chain_transform

    out = check_output_folder(args.out, command="sweep")
    truth = truth_reference = None
    if args.source is not None:
        if args.labels is not None or args.mask is not None:
            raise InputError("--labels/--mask: taken from --from's manifest; do not give them")
        m = load_manifest(args.source)
        images, labels = list(m.images), list(m.labels) if m.labels is not None else None
        mask = m.mask
        if args.truth is not None:
            if args.truth not in m.registrations:
                raise InputError(
                    f"--truth {args.truth!r}: not a registration of {args.source} "
                    f"(have: {', '.join(m.registrations)})"
                )
            reg = m.registrations[args.truth]
            truth = [chain_transform(t) for t in reg.transforms]
            truth_reference = reg.reference
    else:
        if args.truth is not None:
            raise InputError("--truth: only with --from (a manifest holding the true transforms)")
        images, labels, mask = args.images, args.labels, args.mask
    if args.source is not None:  # its every file, not only the images
        check_output_folder(args.out, inputs=m.files, command="sweep")
    parameters: dict = {}
    for name, values in args.param:
        if name in parameters:
            raise InputError(f"--param {name}: given twice")
        parameters[name] = values
    result = sweep(
        images,
        method=args.method,
        parameters=parameters,
        out=out,
        labels=labels,
        mask=mask,
        engine=args.engine,
        reference_choice=args.reference_choice,
        truth=truth,
        truth_reference=truth_reference,
        n_samples=args.samples,
        seed=args.seed,
        progress=not args.quiet,
    )
    reused = sum(s.reused for s in result.settings)
    head = f"{len(result.settings)} settings ({reused} already registered); "
    if result.recommended is not None:
        print(f"{head}the verdict recommends {result.recommended} (decided better than the rest)")
    else:
        print(f"{head}no setting is recommended: {result.reason}")
    for measure, best in result.best_by.items():
        flagged = " (flagged implausible)" if result.evaluation.scores[best].flags else ""
        print(f"  best by {measure}: {best}{flagged}")
    print(f"wrote {out}/sweep.json, sweep.csv, sweep.png, report.html and evaluation/")
    return 0
