"""Displacement fields that look like RAS given as LPS: a check on the images' own content.

A displacement field given as a plain image is read as ITK's: LPS components. nibabel, FSL,
NiftyReg and SPM write RAS components; such a field read as LPS moves every point by twice
its x and y displacements the wrong way. Nothing in an ITK-style file says which was meant
(the headers that do say so are checked by
:func:`itk_nrreval.io._foreign_transforms.plain_field_problem`), so :func:`orientation_notes`
asks the images: the registration aligned each image with the reference, so the field as
meant aligns it better than its negation.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from .._errors import InputError
from ._images import read_image
from .transforms import FIELD_SUFFIXES, InMemoryTransform, file_suffix, read_transform

__all__ = [
    "orientation_notes",
    "ORIENTATION_SUBJECTS",
    "ORIENTATION_GRID",
    "ORIENTATION_MARGIN",
    "ORIENTATION_MIN_MOVE",
]

ORIENTATION_SUBJECTS = 3
"""How many subjects of each registration the RAS-as-LPS check of :func:`orientation_notes`
looks at (the first ones whose transforms hold a displacement field given as a plain image):
a tool that writes RAS fields writes every subject's so, and each look costs a field and two
images read (about a second at 1 mm)."""

ORIENTATION_GRID = 48
"""Voxels per axis (at most) of the coarse reference grid the check resamples on."""

ORIENTATION_MARGIN = 0.02
"""How much better (normalised mutual information, which is 1 for independent intensities and
2 for identical ones) the negated field must align its image with the reference than the
field as given for the check to warn. On the 2D population of
``tests/test_foreign_transforms.py`` a correct field moved by half a voxel loses about 0.1,
and negating fields of 3-5 mm costs about 0.5: 0.02 asks for a clear preference, not a tie
decided by noise."""

ORIENTATION_MIN_MOVE = 1.0
"""Negating x and y must move the field's points by at least this many voxels (median over
the field) for the check to say anything: below that both align their image alike, and the
difference would not matter."""


def orientation_notes(manifest) -> list[str]:
    """Warnings for displacement fields that look like RAS given as LPS, one per registration.

    For the first :data:`ORIENTATION_SUBJECTS` subjects of each registration whose transform
    chain holds a displacement field given as a plain image (a file without a format, or an
    image object), the image is resampled onto a coarse copy of the reference's grid through
    the chain as given, through the same chain with that field's x and y components negated,
    and through the chain without that field; each is compared with the reference by
    normalised mutual information (so it holds across contrasts). The registration aligned
    the image with the reference, so the chain as given should align it best; where the
    negated one aligns it better than both others by :data:`ORIENTATION_MARGIN` (and negating
    moves points by at least :data:`ORIENTATION_MIN_MOVE` voxels), the field was most likely
    written in RAS (nibabel, FSL, NiftyReg, SPM) and read as ITK's LPS. Beating the chain
    without the field is what tells a field meant in RAS from a merely wrong one (a failed or
    deliberately perturbed registration), which its negation may happen to improve; and a
    registration is named only when more than half of the subjects checked look so (a tool
    writes every subject's field in one convention; a lone subject that fits better negated
    is taken for such an accident: on ``tests/test_evaluate.py``'s registration of random
    fields one subject of five does, by 0.08).

    What this cannot see: a field whose displacements are too small to tell (then reading it
    either way barely matters), a registration that failed either way, a field negated in
    other components, absolute positions stored as displacements (both readings are then far
    off), one subject's field negated among correct ones, and subjects after the first
    :data:`ORIENTATION_SUBJECTS`.

    Returns
    -------
    list of str
        One line per registration with such a subject, naming the manifest item and file.
    """
    notes = []
    for name, reg in manifest.registrations.items():
        flagged, looked = [], 0
        for i, chain in enumerate(reg.transforms):
            if looked >= ORIENTATION_SUBJECTS:
                break
            plain = [
                j
                for j, t in enumerate(chain)
                if (isinstance(t, Path) and _is_field_file(t))
                or (isinstance(t, InMemoryTransform) and isinstance(t.value, sitk.Image))
            ]
            if not plain:
                continue
            looked += 1
            found = []  # each field of the chain (mostly one); the one negating helps most
            for j in plain:
                try:
                    scores = _negated_fits_better(reg.reference, manifest.images[i], chain, j)
                except (InputError, RuntimeError, ValueError, MemoryError):
                    break  # the reading and checking elsewhere report unreadable files
                if scores is not None:
                    found.append((scores[1] - scores[0], j, scores))
            if found:
                _, j, scores = max(found)
                flagged.append((i, chain[j], scores))
        # a tool that writes RAS fields writes every subject's so; one subject whose field
        # happens to fit better negated is a failed registration's accident, not a convention
        if flagged and 2 * len(flagged) > looked:
            i, item, (given, negated) = flagged[0]
            others = (
                f" (and {len(flagged) - 1} more of the {looked} checked)"
                if len(flagged) > 1
                else ""
            )
            notes.append(
                f"registrations.{name}.transforms[{i}]: {Path(str(item)).name} aligns "
                f"{Path(str(manifest.images[i])).name} with the reference better with its x "
                f"and y displacements negated (normalised mutual information {negated:.3f} "
                f"against {given:.3f}){others}: a field written in RAS (nibabel, FSL, "
                "NiftyReg) read as ITK's LPS? Write it in LPS, or give its format"
            )
    return notes


def _is_field_file(path: Path) -> bool:
    return file_suffix(path) in FIELD_SUFFIXES


def _negated_fits_better(reference, image, chain: Sequence, j: int) -> tuple[float, float] | None:
    """(NMI as given, NMI negated) when negating piece `j`'s x and y fits clearly better."""
    ref = read_image(reference, what="reference")
    img = read_image(image)
    pieces = [read_transform(t) for t in chain]
    field = sitk.DisplacementFieldTransform(pieces[j]).GetDisplacementField()
    values = sitk.GetArrayFromImage(field)
    dim = field.GetDimension()
    move = 2 * np.linalg.norm(values[..., :2], axis=-1)
    if np.median(move) < ORIENTATION_MIN_MOVE * min(img.GetSpacing()):
        return None
    values[..., :2] *= -1.0
    negated = sitk.GetImageFromArray(values, isVector=True)
    negated.CopyInformation(field)
    flipped = list(pieces)
    flipped[j] = sitk.DisplacementFieldTransform(sitk.Cast(negated, sitk.sitkVectorFloat64))
    grid = _coarse(ref, ORIENTATION_GRID)
    fixed = sitk.GetArrayFromImage(
        sitk.Resample(
            sitk.Cast(ref, sitk.sitkFloat64),
            grid,
            sitk.Transform(dim, sitk.sitkIdentity),
            sitk.sitkLinear,
            math.nan,
        )
    )
    without = pieces[:j] + pieces[j + 1 :]
    scores = []
    for chosen in (pieces, flipped, without):
        composite = sitk.CompositeTransform(dim)
        for t in reversed(chosen):  # ANTs order: the first listed acts first
            composite.AddTransform(t)
        if not chosen:
            composite.AddTransform(sitk.Transform(dim, sitk.sitkIdentity))
        moved = sitk.GetArrayFromImage(
            sitk.Resample(
                sitk.Cast(img, sitk.sitkFloat64), grid, composite, sitk.sitkLinear, math.nan
            )
        )
        scores.append(_nmi(fixed, moved))
    given, flipped_score, dropped = scores
    # a field meant as RAS aligns the image once negated, better than the chain without it;
    # a field that is merely wrong (a failed or perturbed registration) may do better negated
    # than as given, but not better than leaving it out
    if flipped_score > max(given, dropped) + ORIENTATION_MARGIN:
        return given, flipped_score
    return None


def _coarse(image: sitk.Image, n: int) -> sitk.Image:
    """An empty image on `image`'s grid subsampled to at most `n` voxels per axis."""
    size = np.asarray(image.GetSize())
    step = np.maximum(1, np.ceil(size / n)).astype(int)
    out = sitk.Image([int(s) for s in np.ceil(size / step)], sitk.sitkFloat64)
    out.SetSpacing((np.asarray(image.GetSpacing()) * step).tolist())
    out.SetOrigin(image.GetOrigin())
    out.SetDirection(image.GetDirection())
    return out


def _nmi(a: np.ndarray, b: np.ndarray, bins: int = 32) -> float:
    """Normalised mutual information ``(H(A) + H(B)) / H(A, B)`` over the voxels both hold."""
    keep = np.isfinite(a) & np.isfinite(b)
    if keep.sum() < 64:
        return math.nan
    joint, _, _ = np.histogram2d(a[keep], b[keep], bins=bins)
    p = joint / joint.sum()

    def entropy(q):
        q = q[q > 0]
        return float(-(q * np.log(q)).sum())

    return (entropy(p.sum(0)) + entropy(p.sum(1))) / max(entropy(p), 1e-12)
