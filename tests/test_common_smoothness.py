"""Specificity at a common smoothness (benchmarks/bench_common_smoothness.py, the measure
issue 41 tried and did not keep): its smoothed fields against independent references, so
that the numbers docs/verdict.md reports from it are those of the smoothing it describes.

The reference smoothing is scipy's Gaussian filter on displacements sampled point by point
with ``TransformPoint`` (no ITK field filter, no recursive Gaussian), on grids with oblique
direction cosines and strongly anisotropic voxels, so that a sigma taken in voxels rather
than mm, or components mixed with axes, shows as a large error.
"""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
from _benchmarks import benchmark_module
from scipy import ndimage

smoothed_field_transform = benchmark_module("bench_common_smoothness").smoothed_field_transform


def _rotation(dim: int, degrees: float) -> np.ndarray:
    t = np.deg2rad(degrees)
    r = np.eye(dim)
    r[:2, :2] = [[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]]
    if dim == 3:  # a second rotation, about x, so that no axis stays put
        s = np.deg2rad(degrees / 2)
        r = r @ np.array([[1, 0, 0], [0, np.cos(s), -np.sin(s)], [0, np.sin(s), np.cos(s)]])
    return r


def _grid(size, spacing, origin, direction) -> sitk.Image:
    image = sitk.Image([int(s) for s in size], sitk.sitkFloat32)
    image.SetSpacing([float(s) for s in spacing])
    image.SetOrigin([float(o) for o in origin])
    image.SetDirection([float(d) for d in np.asarray(direction).ravel()])
    return image


def _points(image: sitk.Image) -> np.ndarray:
    """Physical points of every voxel, shape (*numpy shape, dim)."""
    idx = np.stack(np.meshgrid(*[np.arange(s) for s in image.GetSize()], indexing="ij"), -1)
    idx = idx.reshape(-1, image.GetDimension()).astype(float)
    d = np.asarray(image.GetDirection()).reshape(image.GetDimension(), -1)
    pts = np.asarray(image.GetOrigin()) + (idx * image.GetSpacing()) @ d.T
    # back to numpy order (z, y, x) for the array axes
    return pts.reshape(*image.GetSize(), -1).transpose(*reversed(range(image.GetDimension())), -1)


def _displacements(transform: sitk.Transform, points: np.ndarray) -> np.ndarray:
    flat = points.reshape(-1, points.shape[-1])
    moved = np.array([transform.TransformPoint(tuple(p)) for p in flat])
    return (moved - flat).reshape(points.shape)


def _random_field_transform(reference: sitk.Image, seed: int, amplitude_mm: float):
    """A displacement field with fine and coarse structure on a grid larger than `reference`
    (so that its displacement is defined wherever the smoothing looks)."""
    rng = np.random.default_rng(seed)
    dim = reference.GetDimension()
    big = _grid(
        np.asarray(reference.GetSize()) + 40,
        reference.GetSpacing(),
        np.asarray(reference.GetOrigin())
        - np.asarray(reference.GetDirection()).reshape(dim, dim)
        @ (20 * np.asarray(reference.GetSpacing())),
        reference.GetDirection(),
    )
    shape = tuple(reversed(big.GetSize()))
    noise = rng.normal(size=(*shape, dim))
    coarse = ndimage.gaussian_filter(rng.normal(size=(*shape, dim)), (6,) * dim + (0,))
    u = amplitude_mm * (0.3 * noise + coarse / coarse.std())
    field = sitk.GetImageFromArray(u, isVector=True)
    field.CopyInformation(big)
    return sitk.DisplacementFieldTransform(sitk.Cast(field, sitk.sitkVectorFloat64))


@pytest.mark.parametrize("dim", [2, 3])
def test_a_linear_map_is_left_as_it_is(dim):
    """G * (A p + t - p) = A p + t - p: an affine registration's images do not change
    (to 0.01 mm: the recursive Gaussian approximates the true one)."""
    rng = np.random.default_rng(dim)
    spacing = [1.0, 3.0, 2.0][:dim]
    size = [24, 10, 12][:dim]
    reference = _grid(size, spacing, rng.normal(scale=20, size=dim), _rotation(dim, 30))
    affine = sitk.AffineTransform(dim)
    affine.SetMatrix((np.eye(dim) + rng.normal(scale=0.05, size=(dim, dim))).ravel().tolist())
    affine.SetTranslation(rng.normal(scale=5, size=dim).tolist())
    affine.SetCenter(rng.normal(scale=10, size=dim).tolist())
    smoothed = smoothed_field_transform(affine, reference, sigma_mm=4.0)
    points = _points(reference).reshape(-1, dim)
    for p in points[:: max(1, len(points) // 200)]:
        np.testing.assert_allclose(
            smoothed.TransformPoint(tuple(p)), affine.TransformPoint(tuple(p)), atol=0.01
        )


@pytest.mark.parametrize("dim", [2, 3])
def test_the_smoothing_is_a_gaussian_in_mm(dim):
    """Against scipy's Gaussian (sigma in voxels = sigma_mm / spacing per axis) of the
    displacements sampled point by point on a padded grid, at the reference's voxels."""
    sigma = 6.0
    spacing = np.array([1.0, 3.0, 2.0][:dim])
    size = [30, 12, 14][:dim]
    reference = _grid(size, spacing, [7.0, -4.0, 2.0][:dim], _rotation(dim, 25))
    transform = _random_field_transform(reference, seed=dim, amplitude_mm=2.0)
    # the reference's grid padded by 4 sigma (in voxels of each axis), sampled point by point
    pad = np.ceil(4 * sigma / spacing).astype(int)
    d = np.asarray(reference.GetDirection()).reshape(dim, dim)
    padded = _grid(
        np.asarray(size) + 2 * pad,
        spacing,
        np.asarray(reference.GetOrigin()) - d @ (pad * spacing),
        d,
    )
    u = _displacements(transform, _points(padded))
    sigmas_numpy_order = tuple(sigma / spacing[::-1]) + (0.0,)
    expected = ndimage.gaussian_filter(u, sigmas_numpy_order, mode="nearest", truncate=6.0)
    inner = tuple(slice(p, p + s) for p, s in zip(pad[::-1], size[::-1], strict=True))
    expected = expected[inner]

    smoothed = smoothed_field_transform(transform, reference, sigma_mm=sigma)
    got = _displacements(smoothed, _points(reference))
    raw = _displacements(transform, _points(reference))
    error = np.sqrt(np.mean(np.sum((got - expected) ** 2, axis=-1)))
    removed = np.sqrt(np.mean(np.sum((raw - expected) ** 2, axis=-1)))
    # what the smoothing removes is large; the disagreement with scipy (the recursive
    # Gaussian's approximation and the sigma/2 storage grid) is a small part of it
    assert removed > 0.5
    assert error < 0.08 * removed, (error, removed)


def test_a_sigma_taken_in_voxels_would_be_seen():
    """The check above can fail: smoothing by sigma voxels instead of mm is far off."""
    sigma = 6.0
    spacing = np.array([1.0, 3.0])
    reference = _grid([30, 12], spacing, [0.0, 0.0], _rotation(2, 25))
    transform = _random_field_transform(reference, seed=5, amplitude_mm=2.0)
    in_mm = _displacements(
        smoothed_field_transform(transform, reference, sigma_mm=sigma), _points(reference)
    )
    wrong = _displacements(
        smoothed_field_transform(transform, reference, sigma_mm=sigma * 3.0), _points(reference)
    )
    raw = _displacements(transform, _points(reference))
    removed = np.sqrt(np.mean(np.sum((raw - in_mm) ** 2, axis=-1)))
    assert np.sqrt(np.mean(np.sum((wrong - in_mm) ** 2, axis=-1))) > 0.08 * removed


def test_sigma_must_be_positive():
    reference = _grid([8, 8], [1.0, 1.0], [0.0, 0.0], np.eye(2))
    with pytest.raises(ValueError, match="sigma_mm"):
        smoothed_field_transform(sitk.Transform(2, sitk.sitkIdentity), reference, sigma_mm=0.0)
