"""Registration under a rigid change of physical coordinates, and on anisotropic voxels.

A rigid change of physical coordinates ``G(p) = R p + t`` (an oblique direction matrix and a
moved origin, applied identically to every image: the voxel arrays are untouched, only
direction and origin change) must not change what a registration says: if ``T`` maps
reference points to image points in the original coordinates and ``T'`` in the new ones,
then ``G^-1(T'(G(p))) = T(p)``. The difference is measured in mm at the reference's voxel
centres inside its brain. A rigid change keeps the spacing, so it reveals direction and
origin errors but not a unit error in the spacing (issue #15 item 6): the same anatomy
sampled on 1.6 x 1.6 mm and on 1.6 x 2.4 / 1.6 x 3.2 mm voxels must also give about the
same transforms in mm.

Engines are not exactly invariant: the affine stage samples its metric at random points
whose jitter ITK draws along the physical axes, and a registration on other voxels sees
other images. Each tolerance is stated with the difference measured when it was set and,
in the comments, what the code before the fixes gave and the spread between two seeds.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import SimpleITK as sitk

from data_synth import make_population
from itk_nrreval import register
from itk_nrreval.experiments.registration import FluidOptions
from itk_nrreval.experiments.registration.fluid import demons_register


def _rotation(dim: int, degrees: float, axis=(1.0, 2.0, 3.0)) -> np.ndarray:
    a = np.deg2rad(degrees)
    if dim == 2:
        return np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(a) * cross + (1 - np.cos(a)) * cross @ cross  # Rodrigues


def _moved(image: sitk.Image, rotation: np.ndarray, shift: np.ndarray) -> sitk.Image:
    """`image` with physical coordinates changed by p -> R p + t (same voxels)."""
    out = sitk.Image(image)
    dim = image.GetDimension()
    direction = np.reshape(image.GetDirection(), (dim, dim))
    out.SetDirection((rotation @ direction).ravel().tolist())
    out.SetOrigin((rotation @ np.asarray(image.GetOrigin()) + shift).tolist())
    return out


def _conjugated(affine: sitk.Transform, rotation: np.ndarray, shift: np.ndarray):
    """The affine p' -> G(A(G^-1(p'))) with G(p) = R p + t."""
    dim = affine.GetDimension()
    matrix = np.reshape(affine.GetMatrix(), (dim, dim))
    at_zero = rotation @ np.asarray(affine.TransformPoint(tuple(-rotation.T @ shift))) + shift
    out = sitk.AffineTransform(dim)
    out.SetMatrix((rotation @ matrix @ rotation.T).ravel().tolist())
    out.SetTranslation(at_zero.tolist())
    return out


def _points(reference: sitk.Image, mask: np.ndarray) -> np.ndarray:
    """Physical points (n, dim) of the reference's voxel centres inside `mask` (numpy order)."""
    idx = np.argwhere(mask)[:, ::-1].astype(float)
    return np.array([reference.TransformContinuousIndexToPhysicalPoint(i.tolist()) for i in idx])


def _differences(
    t0: sitk.Transform,
    t1: sitk.Transform,
    points: np.ndarray,
    rotation: np.ndarray | None = None,
    shift: np.ndarray | None = None,
) -> np.ndarray:
    """|t0(p) - G^-1(t1(G(p)))| (mm) at `points`; G the identity when not given."""
    dim = points.shape[1]
    rotation = np.eye(dim) if rotation is None else rotation
    shift = np.zeros(dim) if shift is None else shift
    out = np.empty(len(points))
    for k, p in enumerate(points):
        a = np.asarray(t0.TransformPoint(p.tolist()))
        b = rotation.T @ (np.asarray(t1.TransformPoint((rotation @ p + shift).tolist())) - shift)
        out[k] = np.linalg.norm(a - b)
    return out


def _summary(d: np.ndarray) -> str:
    return f"mean {d.mean():.3f} p95 {np.percentile(d, 95):.3f} max {d.max():.3f} mm"


# --------------------------------------------------------------------------------------------
# The demons stage alone.


@pytest.fixture(scope="module")
def pair_3d():
    pop = make_population("phantom", dim=3, n=2, seed=4, spacing=6.0)
    fixed, moving = (s.image for s in pop.subjects)
    return fixed, moving, sitk.GetArrayFromImage(pop.subjects[0].labels) > 0


@pytest.mark.parametrize("shrink_factors", [(1,), (2, 1), (4, 2, 1)])
def test_demons_field_is_carried_by_a_rigid_change_of_coordinates(pair_3d, shrink_factors):
    # On one grid the demons field of the moved images is the original field with every
    # vector rotated by R, voxel for voxel. Before the fix, SimpleITK's Shrink (even factors)
    # picked its voxels by rounding a half-integer index whose float error depends on the
    # direction matrix: the coarse images moved by a voxel, and the fields by several mm.
    fixed, moving, mask = pair_3d
    rotation, shift = _rotation(3, 30.0), np.array([40.0, -25.0, 17.0])
    opts = FluidOptions(shrink_factors=shrink_factors, iterations=(20,) * len(shrink_factors))
    a = sitk.GetArrayFromImage(demons_register(fixed, moving, options=opts))
    b = sitk.GetArrayFromImage(
        demons_register(
            _moved(fixed, rotation, shift), _moved(moving, rotation, shift), options=opts
        )
    )
    assert np.linalg.norm(a, axis=-1)[mask].mean() > 1.0  # a real field
    diff = np.linalg.norm(b - a @ rotation.T, axis=-1)[mask]
    # Measured: max 3e-4 mm (float rounding); before the fix mean 1.5 mm, max 17 mm.
    assert diff.max() < 0.01, _summary(diff)


# --------------------------------------------------------------------------------------------
# register, end to end, under a rigid change of physical coordinates.

ROTATION_2D, SHIFT_2D = _rotation(2, 30.0), np.array([40.0, -25.0])
ROTATION_3D, SHIFT_3D = _rotation(3, 30.0), np.array([40.0, -25.0, 17.0])


@pytest.fixture(scope="module")
def population_2d():
    """4 phantom subjects, 94 x 94 voxels of 2.4 mm, and their brain points of subject 0."""
    pop = make_population("phantom", dim=2, n=4, seed=4, spacing=2.4, size=94)
    return [s.image for s in pop.subjects], [s.labels for s in pop.subjects]


def _brain_points(reference: sitk.Image, labels: sitk.Image) -> np.ndarray:
    return _points(reference, sitk.GetArrayFromImage(labels) > 0)


def test_register_affine_and_fluid_under_a_rigid_change_of_coordinates(population_2d):
    images, labels = population_2d
    moved = [_moved(im, ROTATION_2D, SHIFT_2D) for im in images]
    a0 = register(images, method="affine", seed=0, progress=False)
    a1 = register(moved, method="affine", seed=0, progress=False)
    assert a1.reference_index == a0.reference_index  # the same reference is chosen
    k = a0.reference_index
    points = _brain_points(a0.reference, labels[k])
    f0 = register(images, method="fluid", affine=a0, progress=False)
    f1 = register(moved, method="fluid", affine=a1, progress=False)
    for i in range(len(images)):
        if i == k:
            continue
        affine = _differences(a0.transforms[i], a1.transforms[i], points, ROTATION_2D, SHIFT_2D)
        fluid = _differences(f0.transforms[i], f1.transforms[i], points, ROTATION_2D, SHIFT_2D)
        report = f"image {i}: affine {_summary(affine)}; fluid {_summary(fluid)}"
        # Measured: affine mean 0.08-0.35 mm, max 0.59 mm (ITK jitters its random metric
        # samples along the physical axes, so they differ); fluid mean 0.02-0.13 mm, p95
        # 0.06-0.30 mm, max 0.76 mm. For scale, seed 1 instead of 0 moves the affine stage by
        # a mean of 0.9-1.6 mm, and lands image 2 in another minimum (10 mm).
        assert affine.mean() < 0.7 and affine.max() < 1.5, report
        assert fluid.mean() < 0.4 and np.percentile(fluid, 95) < 1.0, report


@pytest.mark.parametrize("dim", [2, 3])
def test_fluid_stage_under_a_rigid_change_of_coordinates(population_2d, pair_3d, dim):
    # The same affine stage, carried exactly by the change (G A G^-1): what remains is the
    # fluid stage itself (resampling, histogram matching, demons), which must follow the
    # change to float rounding.
    if dim == 2:
        images, labels = population_2d
        rotation, shift = ROTATION_2D, SHIFT_2D
    else:
        fixed, moving, mask = pair_3d
        images, labels = [fixed, moving], None
        rotation, shift = ROTATION_3D, SHIFT_3D
    moved = [_moved(im, rotation, shift) for im in images]
    a0 = register(images, method="affine", reference=0, seed=0, progress=False)
    a1 = dataclasses.replace(
        a0,
        transforms=tuple(_conjugated(t, rotation, shift) for t in a0.transforms),
        reference=_moved(a0.reference, rotation, shift),
    )
    f0 = register(images, method="fluid", affine=a0, progress=False)
    f1 = register(moved, method="fluid", affine=a1, progress=False)
    points = _brain_points(images[0], labels[0]) if dim == 2 else _points(images[0], mask)
    for i in range(1, len(images)):
        d = _differences(f0.transforms[i], f1.transforms[i], points, rotation, shift)
        # Measured: max 0.014 mm (float rounding through the iterations); before the fix of
        # the demons pyramid, 2D: mean 2.2 mm, 3D: mean 0.6-0.9 mm, max 3.7-5.9 mm.
        assert d.max() < 0.05, f"image {i}: {_summary(d)}"


# --------------------------------------------------------------------------------------------
# Anisotropic voxels: the same anatomy on 1.6 x 1.6 mm and on 1.6 x 2.4 / 1.6 x 3.2 mm voxels.


def _resampled(image: sitk.Image, spacing) -> sitk.Image:
    """`image` on coarser voxels over the same field of view, anti-aliased per axis."""
    old = image.GetSpacing()
    size = [int(round(n * s / t)) for n, s, t in zip(image.GetSize(), old, spacing, strict=True)]
    grid = sitk.Image(size, sitk.sitkFloat32)
    grid.SetSpacing(list(spacing))
    grid.SetDirection(image.GetDirection())
    first = [(t / s - 1) / 2 for s, t in zip(old, spacing, strict=True)]  # a block's centre
    grid.SetOrigin(image.TransformContinuousIndexToPhysicalPoint(first))
    smooth = image
    for axis, (s, t) in enumerate(zip(old, spacing, strict=True)):
        if t > s:
            smooth = sitk.RecursiveGaussian(smooth, 0.5 * np.sqrt(t * t - s * s), direction=axis)
    return sitk.Resample(smooth, grid, sitk.Transform(), sitk.sitkLinear, 0.0)


@pytest.fixture(scope="module")
def population_iso():
    pop = make_population("phantom", dim=2, n=4, seed=4, spacing=1.6)
    images = [s.image for s in pop.subjects]
    affine = register(images, method="affine", reference=0, seed=0, progress=False)
    fluid = register(images, method="fluid", affine=affine, progress=False)
    return images, sitk.GetArrayFromImage(pop.subjects[0].labels) > 0, affine, fluid


@pytest.mark.parametrize(
    ("y_spacing", "mean_mm", "p95_mm"),
    [
        # Measured: mean over the images 0.54 mm, largest p95 1.36 mm; before the fix
        # 1.45 mm and 4.6 mm (y smoothed by 6 voxels of 2.4 mm, x by 4 of 1.6 mm).
        (2.4, 1.0, 2.0),
        # Measured: 0.82 mm and 3.3 mm; before the fix every field was NaN (ITK's kernel
        # overflowed at the 32-voxel smoothing asked for at the coarsest level).
        (3.2, 1.3, 5.0),
    ],
)
def test_fluid_on_anisotropic_voxels_gives_the_same_transforms_in_mm(
    population_iso, y_spacing, mean_mm, p95_mm
):
    # The affine stage is shared (its transforms are physical), so the differences are the
    # fluid stage's: the same anatomy, registered on coarser voxels along y.
    images, mask, affine, fluid_iso = population_iso
    coarse = [_resampled(im, (1.6, y_spacing)) for im in images]
    shared = dataclasses.replace(affine, reference=coarse[0])
    fluid = register(coarse, method="fluid", affine=shared, progress=False)
    points = _points(images[0], mask)
    means, report = [], []
    for i in range(1, len(images)):
        d = _differences(fluid_iso.transforms[i], fluid.transforms[i], points)
        assert np.isfinite(d).all(), f"image {i}: non-finite transform"
        means.append(d.mean())
        report.append(f"image {i}: {_summary(d)}")
        assert np.percentile(d, 95) < p95_mm, report[-1]
    assert np.mean(means) < mean_mm, "; ".join(report)
