"""Per-subject brain masks in the common frame: each subject's Dice against the common mask.

Where the inputs have a brain mask per image (a manifest's ``masks``, or the
``desc-brain_mask`` images of BIDS derivatives: :mod:`itk_nrreval.io.pipeline_outputs`), each mask
is brought into the common frame through its image's transform, as label maps are
(:func:`resample_mask`), and compared with the common mask (:func:`subject_mask_dice`):

* the manifest's ``mask`` (one image on the common grid), where it has one;
* else the majority vote of the subjects' resampled masks: the voxels inside more than half
  of them (:func:`majority_mask`). Every subject votes, its own mask included, so the
  common mask is one image for the whole cohort.

A subject whose mask lands elsewhere than the others' (a failed skull-strip, or a failed
registration carrying a good mask to the wrong place) has a low Dice; below
:data:`BRAIN_MASK_DICE_MIN` it is to be flagged. Everything here is numpy and SimpleITK on
arrays already in memory; the pipeline (:mod:`itk_nrreval._pipeline`) runs
:func:`resample_mask` per image and caches its result.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import SimpleITK as sitk

from .._output import json_number
from ._images import Geometry
from .frame import resample_onto

__all__ = [
    "BRAIN_MASK_DICE_MIN",
    "MASK_METHODS",
    "BrainMaskDice",
    "resample_mask",
    "majority_mask",
    "dice",
    "subject_mask_dice",
]

#: A subject whose brain mask, in the common frame, has a Dice below this with the common
#: mask is flagged. nipreps/fmriprep#3472 proposes 0.8 for this check of fMRIPrep's
#: spatial normalisation (the subject's brain mask in template space against the
#: template's); the same check is applied here to any registration.
BRAIN_MASK_DICE_MIN = 0.8

#: How a mask is resampled: ``"nearest"`` (ITK's nearest neighbour) or ``"linear"`` (ITK's
#: linear interpolation of the 0/1 mask, inside where it is at least 0.5).
MASK_METHODS = ("nearest", "linear")

#: Where a mask is at least this after linear interpolation, the voxel is inside: at least
#: half of its interpolated neighbourhood lies in the mask, as a label's membership of at
#: least 0.5 makes it the voxel's most likely label.
_LINEAR_INSIDE = 0.5


@dataclass(frozen=True)
class BrainMaskDice:
    """Every subject's brain-mask Dice against the common mask, under one registration.

    Attributes
    ----------
    dice : tuple of float, length n_images
        Per subject (manifest order), ``2 |A ∩ B| / (|A| + |B|)`` of its resampled mask A
        and the common mask B, voxels counted on the common grid; NaN when both are empty.
    common : {"mask", "majority"}
        Which common mask: the manifest's ``mask``, or the majority vote of the subjects'
        resampled masks (:func:`majority_mask`).
    common_voxels : int
        The common mask's voxels (0: an empty majority, every Dice then 0 or NaN).
    threshold : float
        The Dice below which a subject is flagged (:data:`BRAIN_MASK_DICE_MIN`).
    """

    dice: tuple[float, ...]
    common: str
    common_voxels: int
    threshold: float = BRAIN_MASK_DICE_MIN

    @property
    def below(self) -> tuple[int, ...]:
        """The subjects (manifest indices) whose Dice is below `threshold` (NaN: not)."""
        return tuple(i for i, d in enumerate(self.dice) if d < self.threshold)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: the Dice values (NaN as None), the common mask, the threshold."""
        return {
            "dice": [json_number(d) for d in self.dice],
            "common": self.common,
            "common_voxels": int(self.common_voxels),
            "threshold": float(self.threshold),
        }


def resample_mask(
    mask: sitk.Image,
    transform: sitk.Transform,
    grid: Geometry | sitk.Image,
    *,
    method: str = "nearest",
) -> np.ndarray:
    """A binary mask brought onto `grid` through `transform`, as label maps are.

    Parameters
    ----------
    mask : sitk.Image
        Scalar mask in its image's space (any origin, spacing and direction); nonzero is
        inside.
    transform : sitk.Transform
        Grid (reference) points -> mask points, physical mm, LPS (the manifest's
        convention: the image's transform from the common frame, ``T_i o F``).
    grid : Geometry or sitk.Image
        Where the mask is sampled (voxel centres); an image gives its grid.
    method : {"nearest", "linear"}, keyword-only
        ``"nearest"``: the voxel nearest to the mapped point (ITK's nearest neighbour);
        ``"linear"``: the 0/1 mask linearly interpolated at the mapped point, inside where
        at least 0.5. Points mapped outside the mask's field of view are outside.

    Returns
    -------
    ndarray of bool, shape grid's numpy shape ``(z, y, x)`` (``(y, x)`` in 2D)

    Raises
    ------
    ValueError
        `method` not one of :data:`MASK_METHODS`.
    """
    if method not in MASK_METHODS:
        raise ValueError(f"method: {method!r} is not one of {MASK_METHODS}")
    g = grid if isinstance(grid, Geometry) else Geometry.from_image(grid)
    if method == "nearest":
        inside = sitk.Cast(mask != 0, sitk.sitkUInt8)
        out = resample_onto(inside, transform, g, sitk.sitkNearestNeighbor, outside=0.0)
        return sitk.GetArrayFromImage(out) != 0
    # float32 holds 0 and 1 exactly; the interpolated values are compared with 0.5
    inside = sitk.Cast(mask != 0, sitk.sitkFloat32)
    out = resample_onto(inside, transform, g, sitk.sitkLinear, outside=0.0)
    return sitk.GetArrayFromImage(out) >= _LINEAR_INSIDE


def majority_mask(masks: Iterable[np.ndarray]) -> np.ndarray:
    """The voxels inside more than half of `masks` (a tie is outside).

    Parameters
    ----------
    masks : iterable of ndarray of bool, each of one shape
        Read one at a time (a lazy sequence holds one in memory).

    Returns
    -------
    ndarray of bool, that shape

    Raises
    ------
    ValueError
        No mask, or masks of different shapes.
    """
    counts, n = None, 0
    for mask in masks:
        mask = np.asarray(mask, bool)
        if counts is None:
            counts = np.zeros(mask.shape, np.int32)
        elif mask.shape != counts.shape:
            raise ValueError(f"masks: shape {mask.shape} differs from {counts.shape}")
        counts += mask
        n += 1
    if counts is None:
        raise ValueError("masks: none given")
    return 2 * counts > n


def dice(a: np.ndarray, b: np.ndarray) -> float:
    """Dice of two masks of one shape: ``2 |a ∩ b| / (|a| + |b|)`` in voxels; NaN when both
    are empty (nothing to agree on)."""
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    if a.shape != b.shape:
        raise ValueError(f"masks: shape {a.shape} differs from {b.shape}")
    total = int(np.count_nonzero(a)) + int(np.count_nonzero(b))
    if total == 0:
        return math.nan
    return 2.0 * int(np.count_nonzero(a & b)) / total


def subject_mask_dice(
    masks: Sequence[np.ndarray],
    *,
    common: np.ndarray | None = None,
    threshold: float = BRAIN_MASK_DICE_MIN,
) -> BrainMaskDice:
    """Every subject's Dice of its mask in the common frame against the common mask.

    Parameters
    ----------
    masks : sequence of ndarray of bool, length n_images
        Each subject's mask on the common grid (:func:`resample_mask`), numpy order; read
        one at a time (twice without `common`: a lazy sequence holds one in memory).
    common : ndarray of bool, optional, keyword-only
        The common mask on the same grid (the manifest's ``mask``). Default: the majority
        vote of `masks` (:func:`majority_mask`).
    threshold : float, keyword-only
        The Dice below which a subject is flagged.

    Returns
    -------
    BrainMaskDice
    """
    source = "mask" if common is not None else "majority"
    if common is None:
        common = majority_mask(masks)
    common = np.asarray(common, bool)
    values = tuple(dice(masks[i], common) for i in range(len(masks)))
    return BrainMaskDice(values, source, int(np.count_nonzero(common)), float(threshold))
