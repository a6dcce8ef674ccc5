"""Writing a population to disk in the layout of ``nrreval synth``.

Layout of the output folder::

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

import os
from pathlib import Path

import SimpleITK as sitk

from itk_nrreval._output import atomic_path, write_json
from itk_nrreval._progress import progress
from itk_nrreval.manifest import write_manifest
from itk_nrreval.transforms import write_transform

from .population import Population

__all__ = ["write_population"]


def write_population(
    pop: Population, out: str | os.PathLike, *, montage: bool = True, show_progress: bool = True
) -> Path:
    """Write `pop` into the folder `out` (layout in the module docstring).

    Returns
    -------
    Path
        The manifest, whose one registration ``truth`` is the true correspondence.
    """
    out = Path(out)
    names = [f"s{i:02d}" if len(pop) <= 100 else f"s{i:03d}" for i in range(len(pop))]

    def write_image(image: sitk.Image, rel: str) -> Path:
        with atomic_path(out / rel) as tmp:
            sitk.WriteImage(image, str(tmp), useCompression=True)
        return (out / rel).absolute()

    images, labels, transforms = [], [], []
    subjects = zip(names, pop.subjects, strict=True)
    for name, s in progress(subjects, desc="writing", total=len(pop), enabled=show_progress):
        images.append(write_image(s.image, f"img/{name}.nii.gz"))
        labels.append(write_image(s.labels, f"lab/{name}.nii.gz"))
        transforms.append(
            write_transform(s.template_to_subject, out / f"truth/{name}.h5").absolute()
        )
    reference = write_image(pop.template, "truth/template.nii.gz")
    write_image(pop.template_labels, "truth/template_labels.nii.gz")
    write_json(out / "truth/label_names.json", {str(k): v for k, v in pop.label_names.items()})
    if montage:
        from .montage import save_montage

        save_montage(
            [s.image for s in pop.subjects],
            [s.labels for s in pop.subjects],
            path=out / "montage.png",
            titles=names,
        )
    manifest = {
        "images": [str(p) for p in images],
        "labels": [str(p) for p in labels],
        "registrations": {
            "truth": {"reference": str(reference), "transforms": [str(p) for p in transforms]}
        },
    }
    return write_manifest(manifest, out / "manifest.yaml")
