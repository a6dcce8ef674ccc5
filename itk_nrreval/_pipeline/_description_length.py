"""The description length of a registration, from its resampled images in the cache.

Run by the driver for one registration while the cache holds its resampled images (before
they go), when ``evaluate(description_length=True)``. The texture is each scored image's
``resampled`` entry; the shape is its transform from the common frame (``T_i o F``)
sampled on the common grid, minus its affine part over the evaluated region. Two passes
over the images: the first adds up the spectra (:class:`SpectrumSums`), the second
recomputes each subject's to leave it out (the jackknife); one image and its field are in
memory at a time, besides the sums (two full-grid arrays per signal: the texture and each
displacement component).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import SimpleITK as sitk

from ..io._cache import DiskCache
from ..io._images import Geometry, read_image
from ..io.frame import points_minus_grid, resampling_transform
from ..io.manifest import Manifest
from ..io.transforms import flatten, transform_pieces
from ..measures.description_length import (
    DescriptionLength,
    SpectrumSums,
    group_bits,
    left_out_bits,
    noise_and_gradient,
    non_linear_part,
)
from ._common_frame import frame_transform

__all__ = ["image_statistics", "registration_description_length"]


def image_statistics(m: Manifest, scored: Sequence[int]) -> tuple[float, float]:
    """``(sigma, g2)``: the medians over the scored images, each in its own space, of
    :func:`~itk_nrreval.measures.description_length.noise_and_gradient`."""
    stats = []
    for i in scored:
        image = read_image(m.scored_images[i], what="image")
        array = sitk.GetArrayFromImage(image).astype(float)
        stats.append(noise_and_gradient(array, image.GetSpacing()[::-1]))
    return float(np.median([s for s, _ in stats])), float(np.median([g for _, g in stats]))


def registration_description_length(
    disk: DiskCache,
    m: Manifest,
    name: str,
    *,
    keys: Sequence[str],
    frame_spec: tuple,
    grid: Geometry,
    region: np.ndarray | None,
    scored: Sequence[int],
    statistics: tuple[float, float],
) -> DescriptionLength:
    """Registration `name`'s description length over the scored images.

    Parameters
    ----------
    keys : sequence of str
        Every image's ``resampled`` cache entry, in image order.
    frame_spec : tuple
        The registration's frame (:func:`~itk_nrreval._pipeline._common_frame.frame_transform`).
    grid : Geometry
        The common grid.
    region : ndarray of bool, shape grid.shape, or None
        The evaluated region (None: the whole grid).
    scored : sequence of int
        The images in the scores.
    statistics : (float, float)
        ``(sigma, g2)`` from :func:`image_statistics`.
    """
    shape = grid.shape
    mask = np.ones(shape, bool) if region is None else np.asarray(region, bool).reshape(shape)
    weights = mask.astype(float)
    mask_spectrum = np.fft.fftn(weights)
    spacing = grid.spacing[::-1]
    frame = frame_transform(frame_spec, grid, disk)
    items = m.registrations[name].transforms
    dim = len(shape)

    def spectra(i: int) -> list[np.ndarray]:
        image = disk.open("resampled", keys[i]).array("image").reshape(shape)
        transform = flatten(resampling_transform(transform_pieces(items[i]), frame))
        field = non_linear_part(points_minus_grid(transform, grid), mask, spacing)
        signals = [image.astype(float)] + [field[..., c] for c in range(dim)]
        return [np.fft.fftn(weights * s) for s in signals]

    sums = [SpectrumSums(shape) for _ in range(dim + 1)]
    for i in scored:
        for s, x in zip(sums, spectra(i), strict=True):
            s.add(x)
    sigma, g2 = statistics
    distortions = [sigma**2] + [sigma**2 / g2] * dim
    parts = [group_bits(s, mask_spectrum, d) for s, d in zip(sums, distortions, strict=True)]
    n = len(scored)
    jackknife = []
    for i in scored:
        left = [
            left_out_bits(s, x, mask_spectrum, d)
            for s, x, d in zip(sums, spectra(i), distortions, strict=True)
        ]
        jackknife.append(sum(left) / (n - 1))
    return DescriptionLength(
        bits=sum(parts) / n,
        texture=parts[0] / n,
        shape=sum(parts[1:]) / n,
        jackknife=tuple(jackknife),
        noise_sd=sigma,
        displacement_precision_mm=float(np.sqrt(sigma**2 / g2)),
    )
