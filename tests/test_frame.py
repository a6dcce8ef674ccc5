"""The common frame: the three ways of getting F agree; resampling order; memberships."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
from test_plausibility import OBLIQUE_GRID, full_grid_inverse, smooth_random_field, voxel_points

from itk_nrreval.io.frame import (
    frame_estimates,
    frame_mapping,
    resample_images,
    resample_memberships,
    resampling_transform,
)
from itk_nrreval.io.manifest import load_manifest
from itk_nrreval.io.transforms import field_transform


def grid(dim: int, n: int) -> sitk.Image:
    img = sitk.Image([n + 2 * k for k in range(dim)], sitk.sitkFloat32)
    img.SetSpacing([1.0 + 0.2 * k for k in range(dim)])
    img.SetOrigin([2.0 - k for k in range(dim)])
    return img


def physical_points(img: sitk.Image) -> np.ndarray:
    """Voxel centres, numpy (*spatial_zyx, dim), (x, y, z) last (identity direction)."""
    idx = np.moveaxis(np.indices(img.GetSize()[::-1])[::-1], 0, -1)
    return idx * np.array(img.GetSpacing()) + np.array(img.GetOrigin())


def smooth_field(img: sitk.Image, seed: int, amplitude: float = 1.2) -> sitk.Image:
    dim = img.GetDimension()
    rel = (physical_points(img) - np.array(img.GetOrigin())) / (
        (np.array(img.GetSize()) - 1) * np.array(img.GetSpacing())
    )
    bump = np.prod(np.sin(np.pi * rel), axis=-1)
    phase = np.random.default_rng(seed).uniform(0, 2 * np.pi, dim)
    u = np.stack(
        [amplitude * bump * np.sin(2 * np.pi * rel[..., c] + phase[c]) for c in range(dim)], -1
    )
    f = sitk.GetImageFromArray(u, isVector=True)
    f.CopyInformation(img)
    return f


def affine(dim: int, seed: int) -> sitk.AffineTransform:
    rng = np.random.default_rng(seed)
    a = sitk.AffineTransform(dim)
    a.SetMatrix((np.eye(dim) + 0.05 * rng.standard_normal((dim, dim))).ravel().tolist())
    a.SetTranslation((1.5 * rng.standard_normal(dim)).tolist())
    a.SetCenter((np.array(grid(dim, 10).GetOrigin()) + 8).tolist())
    return a


@pytest.mark.parametrize("dim", [2, 3])
def test_three_ways_of_getting_the_frame_agree(tmp_path, dim):
    """R's reference is image 1 (T_1^C = A1), so F = A1 by all three routes."""
    common = grid(dim, 20 if dim == 2 else 12)
    a1 = affine(dim, 1)
    t_common = [
        field_transform(smooth_field(common, 0)),
        a1,
        sitk.CompositeTransform([affine(dim, 2), field_transform(smooth_field(common, 2))]),
    ]
    a1_inv = a1.GetInverse()
    # T_i^R = T_i^C o A1^-1  (ANTs order: A1^-1 acts first)
    t_r = [[a1_inv, t] for t in t_common]
    rng = np.random.default_rng(dim)
    for name in ("img0", "img1", "img2", "ref"):  # distinct, not constant: the manifest's check
        noise = sitk.GetImageFromArray(rng.normal(size=common.GetSize()[::-1]).astype(np.float32))
        noise.CopyInformation(common)
        sitk.WriteImage(noise, str(tmp_path / f"{name}.nii.gz"))
    sitk.WriteTransform(a1, str(tmp_path / "common_to_r.tfm"))
    data = {
        "images": ["img0.nii.gz", "img1.nii.gz", "img2.nii.gz"],
        "registrations": {
            "C": {"reference": "ref.nii.gz", "transforms": t_common},
            "R": {
                "reference": "img1.nii.gz",
                "reference_index": 1,
                "frame_transform": "common_to_r.tfm",
                "transforms": t_r,
            },
        },
    }
    m = load_manifest(data, base_dir=tmp_path)
    p = physical_points(common)
    mm = np.array(a1.GetMatrix()).reshape(dim, dim)
    c, t = np.array(a1.GetCenter()), np.array(a1.GetTranslation())
    expected = (p - c) @ mm.T + c + t  # A1(p), independently of SimpleITK
    # the mean route carries the field inversions' residual: < 0.1 voxel (spacing >= 1 mm)
    by_default = frame_mapping(m, "R", grid=common)
    assert by_default.method == "frame_transform"
    for method, tol in [("frame_transform", 1e-9), ("reference_index", 1e-9), ("mean", 0.1)]:
        f = frame_mapping(m, "R", grid=common, method=method)
        assert f.method == method
        got = np.array([f.transform.TransformPoint(q.tolist()) for q in p.reshape(-1, dim)])
        err = np.abs(got - expected.reshape(-1, dim))
        inner = err.reshape(*p.shape)[(slice(2, -2),) * dim]  # inversion is loosest at the rim
        assert inner.max() < tol, (method, inner.max())
        assert 0 <= f.spread_mean_mm < 0.05
        assert f.spread_mean_mm <= f.spread_max_mm
    assert frame_mapping(m, "C", grid=common).method == "common"
    with pytest.raises(ValueError, match="method: 'best' is not one of"):
        frame_mapping(m, "R", grid=common, method="best")


def test_spread_reports_inconsistent_estimates():
    """Per-image estimates that disagree by known shifts give that spread."""
    common = grid(2, 16)
    t_common = [sitk.TranslationTransform(2, (0.0, 0.0)) for _ in range(3)]
    shifts = [(1.0, 0.0), (-1.0, 0.0), (0.0, 0.0)]
    # T_i^R = T_i^C o S_i^-1, so F_i = S_i: translations by the shifts; mean shift 0
    t_r = [sitk.TranslationTransform(2, (-sx, -sy)) for sx, sy in shifts]
    m = load_manifest(
        {
            "images": ["a.nii", "b.nii", "c.nii"],
            "registrations": {
                "C": {"reference": "a.nii", "transforms": t_common},
                "R": {"reference": "a.nii", "transforms": t_r},
            },
        },
        check_files=False,
    )
    f = frame_mapping(m, "R", grid=common)
    assert f.method == "mean"
    assert f.spread_mean_mm == pytest.approx(2 / 3, abs=1e-6)  # |1|, |-1|, |0| mm
    assert f.spread_max_mm == pytest.approx(1.0, abs=1e-6)


def test_resampling_transform_applies_frame_first():
    scale = sitk.ScaleTransform(2, (2.0, 3.0))
    shift = sitk.TranslationTransform(2, (1.0, -1.0))
    t = resampling_transform(scale, shift)  # T o F: F = shift acts first
    assert t.TransformPoint((1.0, 1.0)) == pytest.approx((4.0, 0.0))


def test_resample_images_options():
    img = grid(2, 8)
    with pytest.raises(ValueError, match="interpolation: 'cubic' is not one of"):
        resample_images([img], [sitk.Transform(2, sitk.sitkIdentity)], img, interpolation="cubic")


def test_memberships_one_hot_and_fuzzy():
    arr = np.zeros((6, 8), np.int16)
    arr[:, 4:] = 3
    arr[2:4, 1:3] = 1
    lab = sitk.GetImageFromArray(arr)
    ident = sitk.TranslationTransform(2, (0.0, 0.0))
    half = sitk.TranslationTransform(2, (0.5, 0.0))
    m = resample_memberships([lab, lab], [ident, half], lab, values=[0, 1, 3], progress=False)
    assert m.shape == (2, 3, 6, 8)
    expected = np.stack([(arr == v) for v in (0, 1, 3)]).astype(np.float32)
    np.testing.assert_array_equal(m[0], expected)
    # half a voxel to the right: each membership averages two neighbours
    shifted = 0.5 * (expected[:, :, :-1] + expected[:, :, 1:])
    np.testing.assert_allclose(m[1][:, :, :-1], shifted, atol=1e-6)
    np.testing.assert_allclose(m[1][:, :, :-1].sum(axis=0), 1.0, atol=1e-6)


@pytest.mark.parametrize("dim", [2, 3])
def test_frame_estimates_when_the_reference_is_not_co_located_with_the_images(dim):
    """R's reference grid lies 10 mm off the common grid (and the images), oblique.

    ``T_i^R(r) = T_i^C(r - s)`` as displacement fields on R's own grid, so ``F(p) = p + s``
    exactly. Each estimate ``(T_i^R)^-1(T_i^C(p))`` needs the inverse of a field at points
    that lie off that field's grid; inverted on its own grid, it was the identity there and
    the estimates were off by up to 10 mm (issue 15, item 5).
    """
    common = grid(dim, 18 if dim == 2 else 10)
    theta = 0.35
    rot = np.eye(dim)
    rot[:2, :2] = [[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]]
    common.SetDirection(rot.ravel().tolist())
    s = 10.0 * rot[:, 0] + (0.0 if dim == 2 else np.array([0.0, 0.0, 1.5]))
    reg = sitk.Image(common)
    reg.SetOrigin((np.array(common.GetOrigin()) + s).tolist())
    t_common, t_reg = [], []
    for i in range(3):
        w = smooth_field(common, seed=i, amplitude=0.5)  # T_i^C(p) = p + w(p), common grid
        tc = field_transform(w)
        t_common.append(tc)
        # T_i^R(r) = T_i^C(r - s): sample r -> T_i^C(r - s) - r on R's grid.
        shift = sitk.TranslationTransform(dim, (-s).tolist())
        t_reg.append(
            field_transform(
                sitk.TransformToDisplacementField(
                    sitk.CompositeTransform([tc, shift]),
                    sitk.sitkVectorFloat64,
                    reg.GetSize(),
                    reg.GetOrigin(),
                    reg.GetSpacing(),
                    reg.GetDirection(),
                )
            )
        )
    est = frame_estimates(t_common, t_reg, common)  # F_i(p) - p, (n, *zyx, dim)
    err = np.linalg.norm(est - s, axis=-1)
    # Linear interpolation of the inverse field on a 10-voxel grid: ~0.1 mm at worst.
    assert err.max() < 0.15 and np.percentile(err, 90) < 0.05, err.max()


def test_frame_estimates_invert_the_registration_to_a_hundredth_of_a_mm():
    # Issue 30: each estimate F_i = (T_i^R)^-1 o T_i^C inverts T_i^R's displacement field
    # from a coarse inverse on every second node of its grid, refined by three fixed-point
    # steps at the points where it is evaluated (transforms.PointwiseInverse), not on the
    # field's grid and then interpolated. On a smooth field of up to 3 mm on an oblique,
    # anisotropic 3D grid, behind an affine map: wherever the preimage lies inside the
    # field's grid, T^R(F(p)) = T^C(p) to 0.01 mm at every voxel (measured 0.0098 mm at
    # worst, 1e-5 mm on average), where ITK's inverse on the full grid, interpolated as a
    # field, leaves 0.10 mm at worst and 0.0014 mm on average (the inverse's kinks near the
    # grid's edge fall between its nodes); the two estimates differ by 0.002 mm on average.
    g = OBLIQUE_GRID
    field = smooth_random_field(g, max_mm=3.0)
    pose = sitk.AffineTransform(3)
    pose.SetMatrix((1.05, 0.02, 0.0, -0.03, 0.97, 0.01, 0.0, 0.02, 1.02))
    pose.SetTranslation((2.0, -1.0, 3.0))
    pose.SetCenter((0.0, 10.0, 10.0))
    common = sitk.TranslationTransform(3, (1.5, -0.5, 2.0))
    other = sitk.CompositeTransform([pose, field])  # the field acts first, then the pose
    est = frame_estimates([common], [other], g)[0]
    # F(p) = field^-1(pose^-1(common(p))), with ITK's full-grid inverse of the field
    full_grid = sitk.CompositeTransform(
        [full_grid_inverse(field.GetDisplacementField()), pose.GetInverse(), common]
    )
    itk_est = sitk.GetArrayFromImage(
        sitk.TransformToDisplacementField(
            full_grid, sitk.sitkVectorFloat64, g.size, g.origin, g.spacing, g.direction
        )
    )
    assert np.linalg.norm(est - itk_est, axis=-1).mean() < 0.005
    points = voxel_points(g)
    targets = np.array([common.TransformPoint(p) for p in points])
    grid_of_field = field.GetDisplacementField()
    last = np.array(grid_of_field.GetSize()) - 1

    def forward_residuals(estimate):
        """|T^R(F(p)) - T^C(p)| where F(p) lies inside the field's grid (ITK's forward)."""
        preimages = estimate.reshape(-1, 3) + points
        index = np.array(
            [grid_of_field.TransformPhysicalPointToContinuousIndex(y) for y in preimages]
        )
        inside = np.all((index >= 0) & (index <= last), axis=1)
        moved = np.array([other.TransformPoint(y) for y in preimages[inside]])
        return np.linalg.norm(moved - targets[inside], axis=1), inside.mean()

    mine, share = forward_residuals(est)
    assert share > 0.8 and mine.max() < 0.01 and mine.mean() < 1e-4, (mine.max(), mine.mean())
    theirs, _ = forward_residuals(itk_est)
    assert theirs.max() > 5 * mine.max()  # the interpolated inverse field is the coarser one


@pytest.mark.parametrize("masked", [False, True])
def test_distance_sums_equal_numpys_norm(masked):
    # The frame spread's per-estimate sums (issue 30: one compiled pass instead of two
    # full-size temporaries) against np.linalg.norm over the same voxels.
    from itk_nrreval.io.frame import distance_sums

    rng = np.random.default_rng(7)
    a = rng.normal(0.0, 2.0, (9, 11, 13, 3)).astype(np.float32)
    b = rng.normal(0.0, 2.0, (9, 11, 13, 3))
    mask = rng.random((9, 11, 13)) > 0.4 if masked else None
    dist = np.linalg.norm(a.astype(np.float64) - b, axis=-1)
    if mask is not None:
        dist = dist[mask]
    total, largest, count = distance_sums(a, b, mask)
    assert count == dist.size
    assert largest == dist.max()
    assert total == pytest.approx(dist.sum(), rel=1e-13)
