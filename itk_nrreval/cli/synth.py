"""``nrreval synth``: write a synthetic population with its true correspondence and a manifest.

Layout of ``--out DIR``::

    img/s00.nii.gz ...            subject images (float32)
    lab/s00.nii.gz ...            subject label maps (uint8)
    truth/s00.h5 ...              true transform template -> subject (ITK: maps template
                                  points to subject points; affine o displacement field)
    truth/template.nii.gz         the template (the frame of the `truth` registration)
    truth/template_labels.nii.gz  its labels
    truth/label_names.json        label value -> name
    montage.png                   the subjects with their label contours
    manifest.yaml                 images, labels and the registration `truth`

Every file is written under a temporary name and renamed when complete.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from .._errors import InputError


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
    p.add_argument("--n", type=int, default=36, metavar="N", help="number of subjects (default 36)")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory")
    p.add_argument("--seed", type=int, default=0, metavar="S", help="random seed (default 0)")
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
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from data_synth.population import make_population

    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out}: exists and is not a directory")
    if args.kind not in ("phantom", "mni"):
        raise InputError(f"--kind must be 'phantom' or 'mni', got {args.kind!r}")
    if args.dim not in (2, 3):
        raise InputError(f"--dim must be 2 or 3, got {args.dim}")
    if args.n < 1:
        raise InputError(f"--n must be at least 1, got {args.n}")
    if args.seed < 0:
        raise InputError(f"--seed must be >= 0, got {args.seed}")
    try:
        pop = make_population(
            args.kind,
            dim=args.dim,
            n=args.n,
            seed=args.seed,
            spacing=args.spacing,
            warp_mm=args.warp,
            smoothness_mm=args.smoothness,
        )
    except (ValueError, FileNotFoundError) as exc:
        raise InputError(str(exc).splitlines()[0]) from None
    manifest = write_population(pop, out)
    print(f"wrote {len(pop)} subjects ({args.kind}, {args.dim}D) and {manifest}")
    return 0


def write_population(pop, out: str | os.PathLike, *, montage: bool = True) -> Path:
    """Write a :class:`data_synth.Population` into `out` (layout in the module docstring).

    Returns the path of the manifest.
    """
    import SimpleITK as sitk

    from .._output import atomic_path, write_json
    from .._progress import progress

    out = Path(out)
    names = [f"s{i:02d}" if len(pop) <= 100 else f"s{i:03d}" for i in range(len(pop))]

    def write_image(image, rel: str) -> str:
        with atomic_path(out / rel) as tmp:
            sitk.WriteImage(image, str(tmp), useCompression=True)
        return rel

    def write_transform(transform, rel: str) -> str:
        flat = sitk.CompositeTransform(transform)
        flat.FlattenTransform()
        with atomic_path(out / rel) as tmp:
            sitk.WriteTransform(flat, str(tmp))
        return rel

    images, labels, transforms = [], [], []
    for name, s in progress(zip(names, pop.subjects, strict=True), desc="writing", total=len(pop)):
        images.append(write_image(s.image, f"img/{name}.nii.gz"))
        labels.append(write_image(s.labels, f"lab/{name}.nii.gz"))
        transforms.append(write_transform(s.template_to_subject, f"truth/{name}.h5"))
    reference = write_image(pop.template, "truth/template.nii.gz")
    write_image(pop.template_labels, "truth/template_labels.nii.gz")
    write_json(out / "truth/label_names.json", {str(k): v for k, v in pop.label_names.items()})
    if montage:
        from data_synth.montage import save_montage

        save_montage(
            [s.image for s in pop.subjects],
            [s.labels for s in pop.subjects],
            path=out / "montage.png",
            titles=names,
        )
    return _write_manifest(
        out / "manifest.yaml",
        images=images,
        labels=labels,
        registrations={"truth": {"reference": reference, "transforms": transforms}},
    )


def _write_manifest(path: Path, *, images, labels, registrations) -> Path:
    """Write the `nrreval evaluate` manifest (paths given relative to its folder)."""
    from ..manifest import write_manifest

    base = path.absolute().parent

    def absolute(rel):
        return str(base / rel) if isinstance(rel, str) else [absolute(r) for r in rel]

    data = {
        "images": absolute(images),
        "labels": absolute(labels),
        "registrations": {
            name: {k: absolute(v) for k, v in reg.items()} for name, reg in registrations.items()
        },
    }
    return write_manifest(data, path)
