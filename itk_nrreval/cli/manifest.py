"""``nrreval manifest``: write the manifest of what pipelines wrote, to read, edit or keep.

From BIDS derivatives folders (fMRIPrep, sMRIPrep: one registration each), or from ANTs
output prefixes, elastix output folders, FSL and NiftyReg transform files with the images they
belong to; the files found are described in :mod:`itk_nrreval.io.pipeline_outputs`.
"""

from __future__ import annotations

import argparse
import os
import string


def add_parser(sub) -> None:
    p = sub.add_parser(
        "manifest",
        help="write the manifest of BIDS derivatives, ANTs prefixes, elastix folders, FSL or "
        "NiftyReg files",
        description="Find the images, labels and transforms pipelines wrote and write the "
        "manifest `nrreval evaluate` would use. Either BIDS derivatives folders (one "
        "registration each, named after dataset_description.json's GeneratedBy), or --images "
        "and --reference with --ants / --elastix / --fsl / --niftyreg patterns, where what the "
        "* stands for is the subject's label. Quote the patterns so the shell leaves them to "
        "nrreval.",
    )
    p.add_argument(
        "derivatives",
        nargs="*",
        metavar="DERIV",
        help="BIDS derivatives folders (sub-<label>/[ses-<label>/]anat/)",
    )
    p.add_argument(
        "--space",
        metavar="SPACE",
        help="with DERIV: the template space (e.g. MNI152NLin2009cAsym, or MNI152NLin6Asym:res-2); "
        "default: the one space the transforms go into",
    )
    p.add_argument(
        "--ants",
        action="append",
        default=[],
        metavar="[NAME=]PREFIX",
        help="ANTs output prefix pattern, e.g. 'out/sub-*_' (its *1Warp.nii.gz and "
        "*0GenericAffine.mat, or *Composite.h5); repeat for more registrations "
        "(default names ants, ants-2, ...)",
    )
    p.add_argument(
        "--elastix",
        action="append",
        default=[],
        metavar="[NAME=]FOLDER",
        help="elastix output folder pattern, e.g. 'out/sub-*/' (its last "
        "TransformParameters.<k>.txt); repeat for more (default names elastix, elastix-2, ...)",
    )
    p.add_argument(
        "--fsl",
        action="append",
        default=[],
        metavar="[NAME=]PATTERN",
        help="FSL transform file pattern, one file per subject: FLIRT matrices computed with "
        "-ref the --reference and -in the subject's image, e.g. 'flirt/sub-*.mat', or FNIRT "
        "coefficient / displacement files; repeat for more (default names fsl, fsl-2, ...)",
    )
    p.add_argument(
        "--niftyreg",
        action="append",
        default=[],
        metavar="[NAME=]PATTERN",
        help="NiftyReg file pattern, one per subject: reg_aladin's -aff text, e.g. "
        "'nr/sub-*_aff.txt', or reg_transform -def/-disp fields (convert reg_f3d's control-"
        "point grids with reg_transform -def); repeat for more (default names niftyreg, ...)",
    )
    p.add_argument(
        "--images",
        metavar="PATTERN",
        help="with --ants/--elastix/--fsl/--niftyreg: the images (moving), e.g. "
        "'img/sub-*_T1w.nii.gz'",
    )
    p.add_argument(
        "--labels",
        metavar="PATTERN",
        help="with --ants/--elastix/--fsl/--niftyreg: their label maps (optional)",
    )
    p.add_argument(
        "--reference",
        metavar="FILE",
        help="with --ants/--elastix/--fsl/--niftyreg: the fixed image every subject was "
        "registered to",
    )
    p.add_argument(
        "--method",
        action="append",
        metavar="NAME=METHOD",
        help="with --ants/--elastix/--fsl/--niftyreg: the method of the registration NAME "
        "(e.g. syn=SyN), where its files do not say it (ANTs warps, NiftyReg fields); "
        "recorded with its engine, so the verdict can weigh roughness between settings of one "
        "method; repeat for more",
    )
    p.add_argument("--mask", metavar="FILE", help="a mask on the template's (reference's) grid")
    p.add_argument("--out", required=True, metavar="FILE", help="the manifest to write (YAML)")
    p.set_defaults(func=run)


def _named(values: list[str]) -> list[tuple[str | None, str]]:
    """``NAME=PATTERN`` or ``PATTERN`` -> (name or None, pattern)."""
    out = []
    for value in values:
        name, eq, pattern = value.partition("=")
        if eq and name and "/" not in name and "*" not in name:
            out.append((name, pattern))
        else:
            out.append((None, value))
    return out


def manifest_of(args: argparse.Namespace):
    """The manifest the arguments describe (shared with ``nrreval evaluate DERIV ...``)."""
    from .._errors import InputError
    from ..io.pipeline_outputs import manifest_from_derivatives, manifest_from_transforms

    kinds = ("ants", "elastix", "fsl", "niftyreg")
    layouts = "/".join(f"--{k}" for k in kinds)
    pipelines = any(getattr(args, kind, None) for kind in kinds)
    if args.derivatives and pipelines:
        raise InputError(
            _shell_expanded(args)
            or f"give derivatives folders, or {layouts} with --images, not both"
        )
    if args.derivatives:
        given = [o for o in ("images", "labels", "reference") if getattr(args, o, None) is not None]
        given += ["method"] * bool(getattr(args, "method", None))
        if given:
            raise InputError(f"--{given[0]} goes with {layouts}, not derivatives folders")
        return manifest_from_derivatives(args.derivatives, space=args.space, mask=args.mask)
    if not pipelines:
        raise InputError(f"nothing to read: give derivatives folders, or {layouts}")
    if args.space is not None:
        raise InputError("--space goes with derivatives folders")
    for option in ("images", "reference"):
        if getattr(args, option) is None:
            raise InputError(f"{layouts} need --{option}")
    patterns: dict[str, dict[str, str]] = {}
    for kind in kinds:
        patterns[kind] = {}
        for k, (name, pattern) in enumerate(_named(getattr(args, kind, None) or [])):
            name = name or (kind if k == 0 else f"{kind}-{k + 1}")
            if any(name in named for named in patterns.values()):
                raise InputError(f"--{kind} {pattern}: a second registration named {name!r}")
            patterns[kind][name] = pattern
    return manifest_from_transforms(
        images=args.images,
        reference=args.reference,
        **patterns,
        labels=args.labels,
        mask=args.mask,
        methods=_methods(args.method or []),
    )


def _methods(values: list[str]) -> dict[str, str]:
    """``NAME=METHOD`` values -> {name: method}."""
    from .._errors import InputError

    out: dict[str, str] = {}
    for value in values:
        name, eq, method = value.partition("=")
        if not (eq and name and method):
            raise InputError(f"--method {value}: give NAME=METHOD, e.g. --method syn=SyN")
        if name in out:
            raise InputError(f"--method {value}: a second method for {name!r}")
        out[name] = method
    return out


#: The options given as patterns, with an example of each for the messages.
_PATTERNS = {
    "images": "img/sub-*_T1w.nii.gz",
    "labels": "lab/sub-*_dseg.nii.gz",
    "ants": "out/sub-*_",
    "elastix": "out/sub-*/",
    "fsl": "flirt/sub-*.mat",
    "niftyreg": "nr/sub-*_aff.txt",
}


def _shell_expanded(args: argparse.Namespace) -> str | None:
    """The message for a pattern the shell expanded, or None.

    An unquoted ``--images img/sub-*_T1w.nii.gz`` reaches nrreval as the files it matches:
    the first is the option's value, the others are taken for derivatives folders. Such a
    value has no wildcard (a pattern needs one), and the arguments after it lie in its
    folder.
    """
    after = args.derivatives

    def folder(path: str) -> str:
        return os.path.dirname(os.path.normpath(path))

    for option, example in _PATTERNS.items():
        values = getattr(args, option, None) or []
        for value in [values] if isinstance(values, str) else values:
            name, pattern = _named([value])[0]
            if any(c in pattern for c in "*?[") or folder(pattern) != folder(after[0]):
                continue
            paths = [pattern, *(p for p in after if folder(p) == folder(pattern))]
            shown = f"{'' if name is None else name + '='}{_as_pattern(paths) or example}"
            return (
                f"--{option} {value} {after[0]} ...: looks like a pattern your shell expanded "
                f"into {len(paths)} paths; quote it, e.g. --{option} '{shown}'"
            )
    return None


_WORD = string.ascii_letters + string.digits


def _as_pattern(paths: list[str]) -> str | None:
    """The pattern `paths` (two or more) probably came from: their common start and end,
    cut back to a word's boundary, around a ``*`` (``img/sub-01_T1w.nii.gz``,
    ``img/sub-02_T1w.nii.gz`` -> ``img/sub-*_T1w.nii.gz``); None when they overlap."""
    start = os.path.commonprefix(paths).rstrip(_WORD)
    end = os.path.commonprefix([p[::-1] for p in paths])[::-1].lstrip(_WORD)
    if len(start) + len(end) >= min(len(p) for p in paths):
        return None
    return f"{start}*{end}"


def run(args: argparse.Namespace) -> int:
    from .._output import check_output_file
    from ..io.manifest import write_manifest, written_by_nrreval

    manifest = manifest_of(args)
    out = check_output_file(
        args.out, inputs=manifest.files, option="--out", ours=written_by_nrreval
    )
    write_manifest(manifest, out)
    print(
        f"manifest of {manifest.n_images} images and {len(manifest.names)} registrations "
        f"({', '.join(manifest.names)}) written to {args.out}"
    )
    unknown = [
        name
        for name, reg in manifest.registrations.items()
        if "engine" in (reg.parameters or {}) and "method" not in reg.parameters
    ]
    if unknown and len(manifest.names) > 1:
        print(
            f"the files of {', '.join(unknown)} do not say which method wrote them: give "
            f"--method {unknown[0]}=METHOD (e.g. SyN) to let the verdict weigh roughness "
            "between settings of one method"
        )
    return 0
