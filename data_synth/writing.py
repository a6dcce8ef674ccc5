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

A population in other contrasts than T1 alone (``contrasts=("t1", "t2")``) names its images
and templates after the contrast -- ``img/s00_t1.nii.gz``, ``img/s00_t2.nii.gz``,
``truth/template_t1.nii.gz``, ... -- and lists the images contrast by contrast (every subject
in the first contrast, then in the second); each image's label map and true transform are its
subject's (listed once per image), and the `truth` reference is the first contrast's
template. With more than one contrast the manifest also records each image's contrast,
in image order, under ``groups`` (``[t1, t1, ..., t2, t2, ...]``: the ``groups`` of
:func:`itk_nrreval.specificity`), and each image's subject under ``subjects``
(``[s00, s01, ..., s00, s01, ...]``: the subject-level jackknife leaves a subject out with
all its contrasts).

Every file is written under a temporary name and renamed when complete.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import SimpleITK as sitk

from itk_nrreval._output import atomic_path, write_json
from itk_nrreval._progress import progress_bar
from itk_nrreval.io.manifest import write_manifest
from itk_nrreval.io.transforms import write_transform

from .population import Population

__all__ = ["write_population"]


def write_population(
    pop: Population, out: str | os.PathLike, *, montage: bool = True, progress: bool = True
) -> Path:
    """Write `pop` into the folder `out` (layout in the module docstring).

    Returns
    -------
    Path
        The manifest, whose one registration ``truth`` is the true correspondence.
    """
    out = Path(out)
    names = [f"s{i:02d}" if len(pop) <= 100 else f"s{i:03d}" for i in range(len(pop))]
    contrasts = tuple(pop.contrasts)
    # The T1-only layout is the original one; any other names the contrast in every image.
    suffix = {c: "" if contrasts == ("t1",) else f"_{c}" for c in contrasts}

    def write_image(image: sitk.Image, rel: str) -> Path:
        with atomic_path(out / rel) as tmp:
            sitk.WriteImage(image, str(tmp), useCompression=True)
        return (out / rel).absolute()

    images = {c: [] for c in contrasts}
    labels, transforms = [], []
    subjects = zip(names, pop.subjects, strict=True)
    for name, s in progress_bar(subjects, desc="writing", total=len(pop), enabled=progress):
        for c in contrasts:
            images[c].append(write_image(s.images[c], f"img/{name}{suffix[c]}.nii.gz"))
        labels.append(write_image(s.labels, f"lab/{name}.nii.gz"))
        transforms.append(
            write_transform(s.template_to_subject, out / f"truth/{name}.h5").absolute()
        )
    templates = {
        c: write_image(pop.templates[c], f"truth/template{suffix[c]}.nii.gz") for c in contrasts
    }
    write_image(pop.template_labels, "truth/template_labels.nii.gz")
    write_json(out / "truth/label_names.json", {str(k): v for k, v in pop.label_names.items()})
    if montage:
        from .montage import save_montage

        # A subject's contrasts side by side (the montage shows its first 36 panels).
        k = len(contrasts)
        shown = min(k * len(pop), 36)
        save_montage(
            [s.images[c] for s in pop.subjects for c in contrasts],
            [s.labels for s in pop.subjects for _ in contrasts],
            path=out / "montage.png",
            titles=[f"{name}{suffix[c]}" for name in names for c in contrasts],
            ncols=None if k == 1 else k * math.ceil(math.sqrt(shown / k)),
        )
    manifest = {
        "images": [str(p) for c in contrasts for p in images[c]],
        "labels": [str(p) for _ in contrasts for p in labels],
        **({"groups": [c for c in contrasts for _ in names]} if len(contrasts) > 1 else {}),
        # a subject's contrasts are one subject: the jackknife leaves them out together
        **({"subjects": [n for _ in contrasts for n in names]} if len(contrasts) > 1 else {}),
        "registrations": {
            "truth": {
                "reference": str(templates[contrasts[0]]),
                "transforms": [str(p) for _ in contrasts for p in transforms],
            }
        },
    }
    return write_manifest(manifest, out / "manifest.yaml")
