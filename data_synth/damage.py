"""Registrations of a population with some subjects' registrations broken in known ways.

For per-subject quality control (:mod:`itk_nrreval.measures.subject_qc`): a cohort whose true
registration is known (:func:`data_synth.make_population`), with chosen subjects damaged
the way registration pipelines fail. Each damage acts on the subject's true transform
``T = A o phi`` (template points to subject points; ``A`` the pose, ``phi`` the warp):

* ``"mirrored"``: ``F o T``, F mirroring the x axis about the grid's centre (axes flipped);
* ``"affine_only"``: ``A`` alone (the registration stopped after its affine step);
* ``"scaled"``: ``A o phi_s``, the warp's displacement multiplied by `scale`;
* ``"duplicated"``: the subject's image and labels are a copy of another subject's (the
  one before it), with that subject's transform; the image's copy differs by a faint seeded
  noise (standard deviation 1e-3 of its intensity range), as a re-exported or re-saved copy
  does (a byte-identical copy is refused by the manifest's check, before any work);
* ``"off_grid"``: ``Shift o T``, shifted 10 fields of view away: the image lands outside
  the common grid;
* ``"inverted"``: ``T^-1 = phi^-1 o A^-1`` (the population's own ``subject_to_template``),
  the transform of the wrong direction (subject points to template points);
* ``"swapped"``: the subject and the one before it exchange their true transforms (a mix-up
  of two subjects' files): both are registered with the other's transform.
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from itk_nrreval.io.manifest import write_manifest
from itk_nrreval.io.transforms import write_transform

from .population import Population
from .writing import write_population

__all__ = ["DAMAGES", "DIAGNOSES", "damaged_transform", "write_damaged"]

DAMAGES = ("mirrored", "affine_only", "scaled", "duplicated", "off_grid", "inverted", "swapped")
#: The damages that need a subject before the damaged one (its copy, its swap partner).
_PAIRED = ("duplicated", "swapped")

#: The words each damage's diagnosis holds
#: (:func:`itk_nrreval.measures.subject_qc.assess_subjects`): what the tests and the benchmark count
#: as a right diagnosis.
DIAGNOSES = {
    "mirrored": "mirrored",
    "affine_only": "affine only",
    "scaled": "displacements scaled",
    "duplicated": "duplicated image",
    "off_grid": "off the common grid",
    "inverted": "inverted transform",
    "swapped": "looks like another subject's",
}


def _centre(image: sitk.Image) -> np.ndarray:
    return np.asarray(
        image.TransformContinuousIndexToPhysicalPoint([(s - 1) / 2 for s in image.GetSize()])
    )


def _near_copy(source: Path, target: Path, *, seed: int) -> None:
    """`source` written to `target` with seeded Gaussian noise of 1e-3 of its intensity
    range: the same image to any measure that matters, not the same voxels."""
    image = sitk.ReadImage(str(source), sitk.sitkFloat32)
    values = sitk.GetArrayFromImage(image)
    spread = float(values.max() - values.min()) or 1.0
    noise = np.random.default_rng(seed).normal(0.0, 1e-3 * spread, values.shape)
    copy = sitk.GetImageFromArray((values + noise).astype(np.float32))
    copy.CopyInformation(image)
    sitk.WriteImage(copy, str(target))


def damaged_transform(
    pop: Population, index: int, damage: str, *, scale: float = 3.0
) -> sitk.Transform:
    """Subject `index`'s true transform, damaged (module docstring); not a paired damage
    (``"duplicated"``, ``"swapped"``: :func:`write_damaged` makes those)."""
    true = pop.subjects[index].template_to_subject
    dim = pop.template.GetDimension()
    pose, warp = true.GetNthTransform(0), true.GetNthTransform(1)
    if damage == "mirrored":
        flip = sitk.AffineTransform(dim)
        flip.SetCenter(_centre(pop.template).tolist())
        flip.SetMatrix(np.diag([-1.0] + [1.0] * (dim - 1)).ravel().tolist())
        return sitk.CompositeTransform([flip, true])
    if damage == "affine_only":
        return sitk.CompositeTransform([pose])
    if damage == "scaled":
        field = sitk.DisplacementFieldTransform(warp).GetDisplacementField()
        scaled = sitk.GetImageFromArray(sitk.GetArrayFromImage(field) * scale, isVector=True)
        scaled.CopyInformation(field)
        return sitk.CompositeTransform([pose, sitk.DisplacementFieldTransform(scaled)])
    if damage == "off_grid":
        size = np.asarray(pop.template.GetSize()) * np.asarray(pop.template.GetSpacing())
        shift = sitk.TranslationTransform(dim, (10 * size).tolist())
        return sitk.CompositeTransform([shift, true])
    if damage == "inverted":
        return pop.subjects[index].subject_to_template
    single = tuple(d for d in DAMAGES if d not in _PAIRED)
    raise ValueError(f"damage: {damage!r} is not one of {single}")


def write_damaged(
    pop: Population,
    out: str | os.PathLike,
    damages: Mapping[int, str],
    *,
    scale: float = 3.0,
) -> tuple[Path, Path]:
    """Write `pop` (:func:`write_population`) and two manifests in `out`.

    ``manifest.yaml`` has the true registration ``truth`` alone; ``damaged.yaml`` has one
    registration ``damaged``: every subject's true transform except those in `damages`
    (subject index -> damage, one of :data:`DAMAGES`), damaged as the module docstring says.
    A ``"duplicated"`` or ``"swapped"`` subject cannot be subject 0; the subject before a
    ``"swapped"`` one gets its true transform (the subject before it must not be damaged).

    Returns
    -------
    (Path, Path)
        ``manifest.yaml`` and ``damaged.yaml``.
    """
    out = Path(out)
    clean = write_population(pop, out, montage=False, progress=False)
    (out / "damaged").mkdir(exist_ok=True)
    names = [f"s{i:02d}" if len(pop) <= 100 else f"s{i:03d}" for i in range(len(pop))]
    images = [(out / f"img/{n}.nii.gz").absolute() for n in names]
    labels = [(out / f"lab/{n}.nii.gz").absolute() for n in names]
    transforms = [(out / f"truth/{n}.h5").absolute() for n in names]
    for i, damage in damages.items():
        if damage in _PAIRED and (i == 0 or i - 1 in damages):
            raise ValueError(
                f"damages: subject {i} ({damage}) needs an undamaged subject before it"
            )
        if damage == "duplicated":
            images[i] = out / f"damaged/{names[i]}_copy.nii.gz"
            labels[i] = out / f"damaged/{names[i]}_copy_labels.nii.gz"
            _near_copy(out / f"img/{names[i - 1]}.nii.gz", images[i], seed=i)
            shutil.copyfile(out / f"lab/{names[i - 1]}.nii.gz", labels[i])
            transforms[i] = transforms[i - 1]
        elif damage == "swapped":
            # copies, so that each file's name says what it holds in this registration
            for mine, theirs in ((i, i - 1), (i - 1, i)):
                transforms[mine] = out / f"damaged/{names[mine]}_swapped_with_{names[theirs]}.h5"
                shutil.copyfile(out / f"truth/{names[theirs]}.h5", transforms[mine])
        else:
            t = damaged_transform(pop, i, damage, scale=scale)
            transforms[i] = write_transform(t, out / f"damaged/{names[i]}_{damage}.h5")
    manifest = {
        "images": [str(p) for p in images],
        "labels": [str(p) for p in labels],
        "registrations": {
            "damaged": {
                "reference": str((out / "truth/template.nii.gz").absolute()),
                "transforms": [str(p) for p in transforms],
            }
        },
    }
    return clean, write_manifest(manifest, out / "damaged.yaml")
