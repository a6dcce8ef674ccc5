"""Specificity at a common smoothness: every registration's fields smoothed alike.

Rougher fields fit more of what they should not (noise, bias, structure that does not
correspond), so a lower specificity does not by itself say a registration corresponds
better. This measure takes that advantage away at its source: each registration's
displacement fields ``u(p) = T(p) - p`` are convolved with the same isotropic Gaussian of
``sigma_mm`` (8 mm by default, :data:`COMMON_SMOOTHNESS_MM`) on its reference grid, the
images are resampled through ``p + (G * u)(p)`` instead of ``T(p)``, and specificity is
computed as usual (same M, same seed). A registration whose advantage came from fine-scale
fitting loses it; one whose correspondence is right at coarse scale keeps it. Smoothing a
linear map leaves it unchanged, so an affine registration's images are those it already had.

How the verdict uses it (:mod:`itk_nrreval.verdict`) and what the known-truth benchmark
measured are in ``docs/verdict.md``.

The smoothing is done on the registration's reference grid padded by ``4 sigma`` (so the
Gaussian sees the true displacement beyond the edges, not a boundary condition), and the
smoothed field is kept on a grid of spacing ``sigma / 2`` (or the reference's spacing where
that is coarser): a field smoothed at ``sigma`` varies little between nodes ``sigma / 2``
apart, and 8 mm smoothing of a 1 mm brain then stores 64 times fewer vectors.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from ._images import Geometry, read_image
from .manifest import Manifest
from .transforms import InMemoryTransform, chain_transform, displacement_field, field_transform

__all__ = [
    "COMMON_SMOOTHNESS_MM",
    "smoothed_field_transform",
    "smoothed_manifest",
]

COMMON_SMOOTHNESS_MM = 8.0
"""The Gaussian's standard deviation (mm) of specificity at a common smoothness. 4 mm and
8 mm gave the same decisions on the tuning split of the verdict benchmark; 8 mm is below
the scale of the anatomy's variation in brains (and the phantom) and above the field
smoothing of the demons and the grid spacing of the fine B-splines there."""


def smoothed_field_transform(
    transform: sitk.Transform, reference: sitk.Image | Geometry, *, sigma_mm: float
) -> sitk.DisplacementFieldTransform:
    """The transform ``p -> p + (G_sigma * u)(p)``, with ``u(p) = T(p) - p``.

    Parameters
    ----------
    transform : sitk.Transform
        T: reference points -> image points (mm, LPS), of any kind (a chain, a field).
    reference : sitk.Image or Geometry
        The registration's reference grid, where ``u`` is smoothed.
    sigma_mm : float
        Standard deviation of the isotropic Gaussian, in mm (physical units, so anisotropic
        voxels and oblique direction cosines are smoothed alike in every direction).

    Returns
    -------
    sitk.DisplacementFieldTransform
        On the reference grid's extent padded by ``4 sigma_mm`` on every side, with spacing
        ``max(sigma_mm / 2, the reference's spacing)`` along each axis and the reference's
        direction cosines; zero displacement outside it.
    """
    if not sigma_mm > 0:
        raise ValueError(f"sigma_mm must be positive, got {sigma_mm!r}")
    g = reference if isinstance(reference, Geometry) else Geometry.from_image(reference)
    padded = _padded(g, 4.0 * sigma_mm, spacing=g.spacing)
    field = displacement_field(transform, padded)
    smooth = [
        sitk.SmoothingRecursiveGaussian(sitk.VectorIndexSelectionCast(field, k), sigma_mm)
        for k in range(field.GetNumberOfComponentsPerPixel())
    ]
    coarse = _padded(g, 4.0 * sigma_mm, spacing=np.maximum(g.spacing, sigma_mm / 2.0))
    resampled = [
        sitk.Resample(c, _image_of(coarse), sitk.Transform(), sitk.sitkLinear, 0.0) for c in smooth
    ]
    return field_transform(sitk.Compose(resampled))


def smoothed_manifest(
    m: Manifest,
    *,
    sigma_mm: float,
    folder: str | os.PathLike,
    frames: Mapping[str, sitk.Transform] | None = None,
) -> Manifest:
    """The manifest of the same images with every registration's fields smoothed alike.

    Parameters
    ----------
    m : Manifest
        A checked manifest.
    sigma_mm : float
        See :func:`smoothed_field_transform`.
    folder : path
        Where the smoothed fields are written (one ``.h5`` transform per registration and
        image; the folder is created).
    frames : dict of str to sitk.Transform, optional
        Each registration's F, common-frame points -> its reference-frame points
        (:attr:`itk_nrreval.frame.FrameMapping.transform`), as the unsmoothed registrations
        were brought into the common frame; given, they are kept as the registrations'
        frame transforms (the common registration's is not needed), so that the smoothed
        fields are scored in the same frame rather than one estimated from smoothed fields.

    Returns
    -------
    Manifest
        Labels, per-subject masks and label names dropped (only specificity is asked of
        it); each registration's transforms replaced by its smoothed fields, one per image.
    """
    folder = Path(folder)
    registrations = {}
    for k, (name, r) in enumerate(m.registrations.items()):
        reference = Geometry.from_image(read_image(r.reference, what="reference"))
        chains = []
        for i, chain in enumerate(r.transforms):
            path = folder / f"{k:03d}" / f"{i:05d}.h5"
            path.parent.mkdir(parents=True, exist_ok=True)
            smoothed = smoothed_field_transform(
                chain_transform(chain), reference, sigma_mm=sigma_mm
            )
            sitk.WriteTransform(smoothed, str(path))
            chains.append((path,))
        frame = r.frame_transform
        if frames is not None and name != m.common_frame:
            frame = InMemoryTransform.from_object(frames[name], name=f"{name} frame")
        registrations[name] = dataclasses.replace(
            r, transforms=tuple(chains), frame_transform=frame
        )
    return dataclasses.replace(
        m, labels=None, masks=None, label_names=None, registrations=registrations
    )


def _padded(g: Geometry, margin_mm: float, *, spacing) -> Geometry:
    """`g`'s extent grown by `margin_mm` on every side, sampled at `spacing` (mm)."""
    spacing = np.asarray(spacing, dtype=float)
    direction = np.asarray(g.direction, dtype=float).reshape(g.dimension, g.dimension)
    lengths = (np.asarray(g.size) - 1) * np.asarray(g.spacing) + 2.0 * margin_mm
    size = np.floor(lengths / spacing + 1e-9).astype(int) + 1
    # centred on g's centre: the same physical box whatever the spacing
    centre = np.asarray(g.origin) + direction @ ((np.asarray(g.size) - 1) * g.spacing / 2.0)
    origin = centre - direction @ ((size - 1) * spacing / 2.0)
    return Geometry(
        size=tuple(int(s) for s in size),
        spacing=tuple(float(s) for s in spacing),
        origin=tuple(float(o) for o in origin),
        direction=tuple(float(d) for d in direction.ravel()),
    )


def _image_of(g: Geometry) -> sitk.Image:
    """An empty image on grid `g` (a resampling target)."""
    image = sitk.Image([int(s) for s in g.size], sitk.sitkFloat64)
    image.SetSpacing(g.spacing)
    image.SetOrigin(g.origin)
    image.SetDirection(g.direction)
    return image
