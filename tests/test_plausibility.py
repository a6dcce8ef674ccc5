"""Deformation plausibility: analytic folding, unclipped Jacobians, inverse consistency, flags,
and Rohlfing's class-matching cheat caught by it."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import SimpleITK as sitk

from data_synth.cheat import class_matching_cheat
from data_synth.population import make_population
from itk_nrreval import InputError
from itk_nrreval.io._images import Geometry
from itk_nrreval.io.plausibility import (
    Plausibility,
    Thresholds,
    combine,
    deformation_plausibility,
    flags,
    smallest_extent_mm,
)
from itk_nrreval.io.transforms import field_transform


def _rotation(dim: int, angles_deg) -> np.ndarray:
    a = np.radians(angles_deg)
    if dim == 2:
        return np.array([[np.cos(a[0]), -np.sin(a[0])], [np.sin(a[0]), np.cos(a[0])]])
    rz = np.array([[np.cos(a[0]), -np.sin(a[0]), 0], [np.sin(a[0]), np.cos(a[0]), 0], [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, np.cos(a[1]), -np.sin(a[1])], [0, np.sin(a[1]), np.cos(a[1])]])
    return rz @ rx


def _grid(size, spacing, origin=None, rotation=None) -> Geometry:
    dim = len(size)
    d = np.eye(dim) if rotation is None else rotation
    origin = (0.0,) * dim if origin is None else origin
    return Geometry(
        tuple(size), tuple(map(float, spacing)), tuple(map(float, origin)), tuple(d.ravel())
    )


def _points(g: Geometry) -> np.ndarray:
    """Physical voxel centres, shape (*g.shape, dim), ITK component order."""
    dim = g.dimension
    index = np.indices(g.shape)[::-1].reshape(dim, -1).astype(float)  # ITK order
    m = np.asarray(g.direction).reshape(dim, dim) @ np.diag(g.spacing)
    p = np.asarray(g.origin)[:, None] + m @ index
    return np.moveaxis(p.reshape(dim, *g.shape), 0, -1)


def _field(g: Geometry, u: np.ndarray) -> sitk.Transform:
    img = sitk.GetImageFromArray(np.ascontiguousarray(u, dtype=np.float64), isVector=True)
    return field_transform(g.apply_to(img))


def _sine(g: Geometry, *, k: float, period: float, axis, phase: float = 0.3):
    """u(p) = a sin(2 pi e.p / L + phase) e with 2 pi a / L = k: det J = 1 + k cos(theta(p))."""
    e = np.asarray(axis, float) / np.linalg.norm(axis)
    theta = 2 * np.pi * (_points(g) @ e) / period + phase
    a = k * period / (2 * np.pi)
    return _field(g, a * np.sin(theta)[..., None] * e), theta


def _interior(shape) -> np.ndarray:
    m = np.zeros(shape, bool)
    m[(slice(1, -1),) * len(shape)] = True
    return m


# ------------------------------------------------------------------------------------------
# folding against analytic fractions


def test_sine_field_folds_on_the_analytic_fraction():
    # det J = 1 + k cos(theta) folds where cos(theta) <= -1/k: a fraction arccos(1/k)/pi = 1/3
    # of a period for k = 2. Central differences over h = 2 pi dx / L see k sin(h)/h instead
    # of k, so the discrete count on the sample points is predicted exactly by that k.
    g = _grid((256, 12), (0.5, 1.0))  # L = 64 mm: 128 samples per period, 2 periods
    k, period = 2.0, 64.0
    t, theta = _sine(g, k=k, period=period, axis=(1, 0))
    mask = _interior(g.shape)  # central differences only (one-sided at the border)
    h = 2 * np.pi * g.spacing[0] / period
    det_discrete = 1 + k * np.sin(h) / h * np.cos(theta[mask])
    assert np.abs(det_discrete).min() > 1e-6  # no sample sits on the fold threshold
    p = deformation_plausibility(t, g, mask=mask, inverse_consistency=False)
    assert p.folded_fraction == pytest.approx(np.mean(det_discrete <= 0), abs=1e-12)
    assert p.folded_max == p.folded_fraction
    # against the continuous fraction: the sampling of the period (1/128) and the sinc factor
    assert p.folded_fraction == pytest.approx(math.acos(1 / k) / math.pi, abs=0.01)
    assert p.jacobian_min == pytest.approx(1 - k * np.sin(h) / h, abs=1e-3)
    assert p.jacobian_max == pytest.approx(1 + k * np.sin(h) / h, abs=1e-3)


@pytest.mark.parametrize("dim", [2, 3])
def test_same_physical_field_on_an_oblique_anisotropic_grid(dim):
    # The same physical field sampled on a rotated, anisotropic grid: the discrete Jacobian
    # folds on the fraction of the (interior) sample points where the continuous det J <= 0,
    # within 0.01 (the sinc factors of the index-axis differences shift it by < 0.005 here).
    # (The grid spans no whole number of periods along the field, so that fraction is not 1/3.)
    k, period = 2.0, 32.0
    axis = (1.0, 0.4, 0.2)[:dim]
    if dim == 2:
        g = _grid((120, 90), (0.5, 0.8), (-20.0, 5.0), _rotation(2, [30]))
    else:
        g = _grid((48, 40, 32), (0.6, 0.9, 1.2), (-10.0, 4.0, 2.0), _rotation(3, [30, 20]))
    t, theta = _sine(g, k=k, period=period, axis=axis)
    mask = _interior(g.shape)
    p = deformation_plausibility(t, g, mask=mask, inverse_consistency=False)
    analytic = np.mean(1 + k * np.cos(theta[mask]) <= 0)
    assert p.folded_fraction == pytest.approx(analytic, abs=0.01)


def test_slabs_give_the_single_shot_result():
    g = _grid((20, 18, 30), (1.0, 1.3, 0.9), (3.0, -2.0, 1.0), _rotation(3, [15, -25]))
    t, _ = _sine(g, k=1.6, period=14.0, axis=(0.3, 0.5, 1.0))
    mask = np.zeros(g.shape, bool)
    mask[3:25, 2:, 4:] = True
    whole = deformation_plausibility(t, g, mask=mask)
    slabbed = deformation_plausibility(t, g, mask=mask, max_slab_voxels=3 * 20 * 18)
    assert whole.nondiffeomorphic_fraction > whole.folded_fraction > 0
    for name in (
        "folded_fraction",
        "sdlogj",
        "jacobian_min",
        "jacobian_max",
        "nondiffeomorphic_fraction",
        "nondiffeomorphic_volume",
    ):
        assert getattr(slabbed, name) == pytest.approx(getattr(whole, name), rel=1e-12, abs=1e-14)
    assert slabbed.inverse_consistency_mm == pytest.approx(whole.inverse_consistency_mm, rel=1e-6)


# ------------------------------------------------------------------------------------------
# linear transforms, inverse consistency, no clipping, masks


@pytest.mark.parametrize("dim", [2, 3])
def test_affine_is_plausible_with_constant_jacobian(dim):
    rng = np.random.default_rng(7)
    matrix = np.eye(dim) + 0.15 * rng.standard_normal((dim, dim))
    a = sitk.AffineTransform(dim)
    a.SetMatrix(matrix.ravel().tolist())
    a.SetTranslation(rng.normal(size=dim).tolist())
    a.SetCenter([5.0] * dim)
    size = (30, 24, 16)[:dim]
    g = _grid(size, (1.2, 0.8, 1.5)[:dim], (-4.0, 2.0, 1.0)[:dim], _rotation(dim, [25, 10]))
    p = deformation_plausibility(a, g)
    det = float(np.linalg.det(matrix))
    assert det > 0
    assert p.folded_fraction == 0.0
    assert p.sdlogj == pytest.approx(0.0, abs=1e-9)
    assert p.jacobian_min == pytest.approx(det, abs=1e-9)
    assert p.jacobian_max == pytest.approx(det, abs=1e-9)
    assert p.inverse_consistency_mm < 1e-6


def test_reflection_is_counted_not_clipped():
    # det = -0.5 everywhere: a clip-to-1e-9-then-count script would report no fold
    a = sitk.AffineTransform(2)
    a.SetMatrix([-0.5, 0.0, 0.0, 1.0])
    p = deformation_plausibility(a, _grid((16, 16), (1.0, 1.0)))
    assert p.folded_fraction == 1.0
    assert p.jacobian_min == pytest.approx(-0.5, abs=1e-9)
    assert math.isnan(p.sdlogj)
    d = p.to_dict()
    assert d["sdlogj"] is None
    json.dumps(d, allow_nan=False)


def _band_field() -> tuple[Geometry, sitk.Transform]:
    # u_x = -1.5 (x - 10) on 10 <= x <= 20 mm, constant outside: det J = 1 - 1.5 = -0.5 on
    # the 9 columns 11..19, 1 - 0.75 = 0.25 on columns 10 and 20, 1 elsewhere
    g = _grid((40, 10), (1.0, 1.0))
    u = np.zeros((*g.shape, 2))
    u[..., 0] = -1.5 * np.clip(np.arange(40) - 10.0, 0, 10)
    return g, _field(g, u)


def test_negative_jacobian_is_reported_as_is():
    g, t = _band_field()
    p = deformation_plausibility(t, g)
    assert p.jacobian_min == pytest.approx(-0.5, abs=1e-9)
    assert p.jacobian_max == pytest.approx(1.0, abs=1e-9)
    assert p.folded_fraction == pytest.approx(9 / 40)
    # SDlogJ over the unfolded voxels only: 2 columns at log 0.25, 29 at log 1 = 0
    logs = np.r_[np.full(2, np.log(0.25)), np.zeros(29)]
    assert p.sdlogj == pytest.approx(logs.std(), rel=1e-9)


def test_mask_restricts_the_count():
    g, t = _band_field()
    left = np.zeros(g.shape, bool)
    left[:, :10] = True
    band = np.zeros(g.shape, bool)
    band[:, 11:20] = True
    assert deformation_plausibility(t, g, mask=left).folded_fraction == 0.0
    inside = deformation_plausibility(t, g, mask=band, inverse_consistency=False)
    assert inside.folded_fraction == 1.0
    assert inside.jacobian_max == pytest.approx(-0.5, abs=1e-9)
    with pytest.raises(InputError, match="shape"):
        deformation_plausibility(t, g, mask=band.T)
    with pytest.raises(InputError, match="empty"):
        deformation_plausibility(t, g, mask=np.zeros(g.shape, bool))


def test_inverse_consistency_small_for_smooth_large_for_folded():
    g = _grid((64, 64), (1.0, 1.0), (-32.0, -32.0))
    # a Gaussian bump: 2 mm peak, sigma 8 mm, det J in [0.85, 1.15], ~0 at the border
    r2 = np.sum(_points(g) ** 2, axis=-1)
    u = 2.0 * np.exp(-r2 / (2 * 8.0**2))[..., None] * np.array([0.8, 0.6])
    smooth = deformation_plausibility(_field(g, u), g)
    assert smooth.folded_fraction == 0.0
    assert smooth.inverse_consistency_mm < 0.05  # voxel = 1 mm
    folded, _ = _sine(g, k=2.0, period=32.0, axis=(1, 0))
    bad = deformation_plausibility(folded, g)
    assert bad.folded_fraction > 0.25
    assert bad.inverse_consistency_mm > 0.2
    assert bad.inverse_consistency_mm > 10 * smooth.inverse_consistency_mm
    off = deformation_plausibility(folded, g, inverse_consistency=False)
    assert off.inverse_consistency_mm is None


# ------------------------------------------------------------------------------------------
# combine and flags


def _p(folded=0.0, sd=0.1, folded_max=None, ic=0.01, jmin=0.5, jmax=1.5) -> Plausibility:
    return Plausibility(folded, folded if folded_max is None else folded_max, sd, jmin, jmax, ic)


def test_combine():
    c = combine([_p(0.01, 0.2, ic=0.1, jmin=-0.3), _p(0.03, 0.4, ic=0.3, jmax=2.0)])
    assert c.folded_fraction == pytest.approx(0.02)
    assert c.folded_max == pytest.approx(0.03)
    assert c.sdlogj == pytest.approx(0.3)
    assert (c.jacobian_min, c.jacobian_max) == (-0.3, 2.0)
    assert c.inverse_consistency_mm == pytest.approx(0.2)
    assert combine([_p(ic=0.1), _p(ic=None)]).inverse_consistency_mm is None
    assert combine([_p(sd=math.nan), _p(sd=0.2)]).sdlogj == pytest.approx(0.2)
    with pytest.raises(InputError):
        combine([])


def test_flags_folding():
    # the demo's B-spline registrations fold 0.1-0.3 % on average, up to 4.6 % in one image
    out = flags(
        {
            "smooth": _p(),
            "folding": _p(0.022, folded_max=0.043),
            "bspline": _p(0.0028, folded_max=0.046),
        }
    )
    assert out["smooth"] == [] and out["bspline"] == []
    (reason,) = out["folding"]
    assert reason == "2.2% of voxels fold (Jacobian determinant <= 0; 4.3% in the worst image)"
    # one image with a quarter of its voxels folded is enough, even with a small mean
    (reason,) = flags({"a": _p(5e-3, folded_max=0.3)})["a"]
    assert "0.5%" in reason and "30% in the worst image" in reason
    assert (
        flags({"a": _p(0.022)}, thresholds=Thresholds(folded_mean=0.05, folded_max=0.05))["a"] == []
    )


def test_flags_sdlogj():
    regs = {"a": _p(sd=0.1), "b": _p(sd=0.2), "c": _p(sd=0.2), "rough": _p(sd=0.8)}
    out = flags(regs)
    assert out["a"] == out["b"] == out["c"] == []
    assert out["rough"] == ["SDlogJ 0.80 is 4.0x the median of the registrations compared (0.20)"]
    # smooth registrations differing by a large ratio stay below the floor
    assert all(
        v == [] for v in flags({"a": _p(sd=0.01), "b": _p(sd=0.02), "c": _p(sd=0.1)}).values()
    )
    # fewer than three: the absolute bound ratio * floor = 0.4
    out = flags({"a": _p(sd=0.5), "b": _p(sd=0.3)})
    assert out["b"] == []
    assert out["a"] and out["a"][0].startswith("SDlogJ 0.50 is above 0.40")


def test_flags_frame_spread():
    assert smallest_extent_mm(_grid((100, 80, 50), (2.0, 2.5, 4.0))) == 200.0
    out = flags({"a": _p(), "b": _p()}, frame_spread_mm={"a": 12.5, "b": 9.0}, extent_mm=200.0)
    assert out["b"] == []
    assert out["a"] == [
        "frame estimates spread 12.5 mm on average (6.2% of the 200 mm field of view)"
    ]
    with pytest.raises(InputError, match="extent_mm"):
        flags({"a": _p()}, frame_spread_mm={"a": 12.5})


# ------------------------------------------------------------------------------------------
# Rohlfing's cheat: images alike, deformation implausible


def test_class_matching_cheat_matches_classes_but_is_implausible():
    pop = make_population("phantom", dim=2, n=4, seed=3, size=64)
    ref = pop.template_labels
    ref_classes = sitk.GetArrayFromImage(ref)
    grid = Geometry.from_image(ref)
    for s in pop.subjects[:2]:
        affine = s.template_to_subject.GetNthTransform(0)  # [A, phi]: the pose A
        aligned = sitk.Resample(s.labels, ref, affine, sitk.sitkNearestNeighbor, 0, sitk.sitkUInt8)
        cheat = class_matching_cheat(ref, aligned, affine)
        moved = sitk.Resample(s.labels, ref, cheat, sitk.sitkNearestNeighbor, 0, sitk.sitkUInt8)
        truth = sitk.Resample(
            s.labels, ref, s.template_to_subject, sitk.sitkNearestNeighbor, 0, sitk.sitkUInt8
        )
        # the cheat's classes match the reference better than the true correspondence does
        agree = np.mean(sitk.GetArrayFromImage(moved) == ref_classes)
        assert agree > 0.99
        assert agree > np.mean(sitk.GetArrayFromImage(truth) == ref_classes)
        # ... while its deformation folds and is rough (measured: 3-8 % folded, SDlogJ 6-9,
        # det J down to -1 and beyond; the true transform: no fold, SDlogJ ~0.15)
        bad = deformation_plausibility(cheat, grid)
        good = deformation_plausibility(s.template_to_subject, grid)
        assert bad.folded_fraction > 0.005
        assert bad.sdlogj > 1.0 and bad.sdlogj > 5 * good.sdlogj
        assert good.folded_fraction == 0.0 and good.jacobian_min > 0
        assert bad.inverse_consistency_mm > 10 * good.inverse_consistency_mm
        out = flags({"cheat": bad, "truth": good})
        assert out["truth"] == [] and len(out["cheat"]) == 2


def full_grid_inverse(field: sitk.Image) -> sitk.Transform:
    """The reference inverse of a 3D field: ITK's on the field's own full grid (grown by its
    largest displacement, edge values beyond)."""
    arr = sitk.GetArrayFromImage(field)
    spacing = np.asarray(field.GetSpacing())
    pad = np.ceil(np.sqrt((arr**2).sum(-1)).max() / spacing).astype(int) + 1
    padded = sitk.GetImageFromArray(
        np.pad(arr, [*((k, k) for k in pad[::-1]), (0, 0)], mode="edge"), isVector=True
    )
    direction = np.asarray(field.GetDirection()).reshape(3, 3)
    padded.SetSpacing(field.GetSpacing())
    padded.SetDirection(field.GetDirection())
    padded.SetOrigin((np.asarray(field.GetOrigin()) - direction @ (pad * spacing)).tolist())
    inverse = sitk.InvertDisplacementField(padded, 50, 0.01, 1e-4, False)
    return sitk.DisplacementFieldTransform(inverse)


def smooth_random_field(g: Geometry, *, max_mm: float, seed: int = 30) -> sitk.Transform:
    """A smooth random 3D displacement field on `g`: Gaussian-smoothed noise (sigma 5 voxels)
    scaled to a largest displacement of `max_mm`."""
    noise = np.random.default_rng(seed).standard_normal((*g.shape, 3))
    u = np.stack(
        [
            sitk.GetArrayFromImage(
                sitk.SmoothingRecursiveGaussian(sitk.GetImageFromArray(noise[..., c]), 5.0)
            )
            for c in range(3)
        ],
        axis=-1,
    )
    return _field(g, u * (max_mm / np.sqrt((u**2).sum(-1)).max()))


#: An oblique, anisotropic 3D grid for the coarse inverses' tests.
OBLIQUE_GRID = _grid((40, 36, 30), (1.2, 0.9, 1.5), (-10.0, 4.0, 2.0), _rotation(3, [30, 20]))


def _full_resolution_round_trip(t: sitk.Transform, field: sitk.Image, g: Geometry) -> float:
    """The reference: mean |T^-1(T(p)) - p| over every voxel, with the field inverted by ITK
    on its own full grid (:func:`full_grid_inverse`)."""
    round_trip = sitk.CompositeTransform([full_grid_inverse(field), t])
    err = sitk.GetArrayFromImage(
        sitk.TransformToDisplacementField(
            round_trip, sitk.sitkVectorFloat64, g.size, g.origin, g.spacing, g.direction
        )
    )
    return float(np.sqrt((err**2).sum(-1)).mean())


def test_inverse_consistency_against_the_full_resolution_one():
    # Issue 30: inverse consistency inverts each field pointwise at the round trip's points
    # (every second voxel), by six fixed-point steps from a coarse inverse (every fourth
    # node), instead of refining a whole inverse field and interpolating it (1.9 s -> 0.6 s
    # at 1 mm). The reference inverts with ITK on every node and interpolates that inverse
    # field, so where the map is invertible it measures mostly the interpolation of the
    # inverse, which the pointwise inverse does not have: a smooth 3 mm field gives 7e-7 mm
    # against the reference's 0.004 mm, and sines of period 14 mm with k = 0.5 and 0.9 (none
    # folded) 0.001 and 0.084 mm against 0.068 and 0.208 mm. Where the map folds it has no
    # inverse, and both grow with the folding: k = 1.1 and 1.6 (12 %, 28 % folded) give
    # 0.43 and 2.99 mm against 0.52 and 2.22 mm.
    g = OBLIQUE_GRID
    t = smooth_random_field(g, max_mm=3.0)
    reference = _full_resolution_round_trip(t, t.GetDisplacementField(), g)
    smooth = deformation_plausibility(t, g).inverse_consistency_mm
    assert smooth < 1e-4 < reference
    measured, references = [], []
    for k in (0.5, 0.9, 1.1, 1.6):
        t, _ = _sine(g, k=k, period=14.0, axis=(0.3, 0.5, 1.0))
        references.append(_full_resolution_round_trip(t, t.GetDisplacementField(), g))
        measured.append(deformation_plausibility(t, g).inverse_consistency_mm)
    assert smooth < measured[0] < measured[1] < measured[2] < measured[3]  # grows with folding
    assert measured[0] < references[0] and measured[1] < references[1]  # invertible
    assert references[3] > 1.0 and measured[2:] == pytest.approx(references[2:], rel=0.4)


def test_refined_inverse_does_not_depend_on_the_number_of_threads():
    # Issue 30: the fixed-point refinement of a coarse inverse runs its slices in parallel
    # (numba prange); every node is computed alone by the same operations, so one thread and
    # every thread give the same bits.
    import numba

    from itk_nrreval.io.transforms import invert

    t = smooth_random_field(OBLIQUE_GRID, max_mm=3.0)
    threads = numba.get_num_threads()
    inverses = []
    try:
        for n in (1, numba.config.NUMBA_NUM_THREADS):
            numba.set_num_threads(n)
            inverse = invert(t, field_step=2, refine_steps=3).GetDisplacementField()
            inverses.append(sitk.GetArrayFromImage(inverse))
    finally:
        numba.set_num_threads(threads)
    np.testing.assert_array_equal(inverses[0], inverses[1])


@pytest.mark.parametrize("masked", [False, True])
def test_affine_fit_from_the_measures_sampling_equals_affine_fit(masked):
    # Issue 30: the per-image task fits the closest affine map to the displacement that the
    # deformation measures sample anyway, instead of sampling the transform once more; on a
    # field behind an affine map on an oblique, anisotropic grid, in slabs and inside a
    # mask, it is affine_fit's fit to rounding, and the measures are unchanged.
    from itk_nrreval.io.plausibility import affine_fit, deformation_measures

    g = OBLIQUE_GRID
    pose = sitk.AffineTransform(3)
    pose.SetMatrix((1.05, 0.02, 0.0, -0.03, 0.97, 0.01, 0.0, 0.02, 1.02))
    pose.SetTranslation((2.0, -1.0, 3.0))
    t = sitk.CompositeTransform([pose, smooth_random_field(g, max_mm=3.0)])
    mask = None
    if masked:
        mask = np.zeros(g.shape, bool)
        mask[3:25, 5:30, 2:33] = True
    slab = 36 * 40 * 7  # seven rows of the last axis per slab
    plain = deformation_measures(t, g, mask=mask, max_slab_voxels=slab)
    with_fit = deformation_measures(t, g, mask=mask, max_slab_voxels=slab, affine=True)
    # the same fields whatever the flag (issue 43): the fit is None when not asked for
    assert type(plain) is type(with_fit) and plain.affine is None
    fit = with_fit.affine
    alone = affine_fit(t, g, mask=mask, max_slab_voxels=slab).to_dict()
    for key, value in fit.to_dict().items():  # its own sampling rounds differently
        assert value == pytest.approx(alone[key], rel=1e-12), key
    assert with_fit.plausibility == plain.plausibility
    assert with_fit.jacobian.histogram() == plain.jacobian.histogram()
    assert_least_squares_fit(fit, t, g, mask)


def assert_least_squares_fit(fit, t: sitk.Transform, g: Geometry, mask=None) -> None:
    """`fit` is numpy's least squares on ITK's sampling of `t` over `g`'s voxels (in `mask`),
    and `t` is not affine there."""
    p = _points(g).reshape(-1, 3)
    u = sitk.GetArrayFromImage(
        sitk.TransformToDisplacementField(
            t, sitk.sitkVectorFloat64, g.size, g.origin, g.spacing, g.direction
        )
    ).reshape(-1, 3)
    if mask is not None:
        p, u = p[mask.reshape(-1)], u[mask.reshape(-1)]
    design = np.hstack([p, np.ones((len(p), 1))])
    coef, *_ = np.linalg.lstsq(design, u, rcond=None)
    residual = u - design @ coef
    assert fit.nonlinear_rms_mm > 0.1
    assert fit.nonlinear_rms_mm == pytest.approx(np.sqrt((residual**2).sum(1).mean()), rel=1e-9)
    assert fit.displacement_rms_mm == pytest.approx(np.sqrt((u**2).sum(1).mean()), rel=1e-12)
    assert fit.linear_det == pytest.approx(np.linalg.det(np.eye(3) + coef[:3].T), rel=1e-12)


def test_affine_fit_of_a_bspline_is_numpys_least_squares():
    # A B-spline is sampled by ITK (linear maps and fields by the compiled kernels, above),
    # slab by slab: numpy's least squares on ITK's sampling of the whole grid.
    from itk_nrreval.io.plausibility import affine_fit

    g = OBLIQUE_GRID
    image = sitk.Image(list(g.size), sitk.sitkFloat32)
    g.apply_to(image)
    t = sitk.BSplineTransformInitializer(image, [3] * 3)
    t.SetParameters(np.random.default_rng(9).normal(scale=2.0, size=len(t.GetParameters())))
    assert_least_squares_fit(affine_fit(t, g, max_slab_voxels=36 * 40 * 7), t, g)


def voxel_points(g: Geometry) -> np.ndarray:
    """The physical points of `g`'s voxels (m, dim), C order (x fastest): ITK's own
    TransformIndexToPhysicalPoint, one voxel at a time."""
    image = sitk.Image(list(g.size), sitk.sitkUInt8)
    g.apply_to(image)
    return np.array(
        [
            image.TransformIndexToPhysicalPoint([int(i) for i in index[::-1]])
            for index in np.ndindex(*g.shape)
        ]
    )


def _sampled(t: sitk.Transform, g: Geometry) -> np.ndarray:
    """``t(p)`` on `g`'s voxels (m, dim): ITK's own sampling."""
    d = sitk.TransformToDisplacementField(
        t, sitk.sitkVectorFloat64, g.size, g.origin, g.spacing, g.direction
    )
    return voxel_points(g) + sitk.GetArrayFromImage(d).reshape(-1, g.dimension)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("step", [2, 4])
def test_pointwise_inverse_at_the_nodes_is_the_refined_inverse(dim, step):
    """At the field's own nodes, where invert()'s refined inverse field holds the values it
    computed (no interpolation), the pointwise inverse gives the same points to rounding;
    beyond the field's grid grown by its largest displacement it is the identity, exactly."""
    from itk_nrreval.io.transforms import PointwiseInverse, invert

    g3 = OBLIQUE_GRID
    if dim == 3:
        g, t = g3, smooth_random_field(g3, max_mm=3.0)
    else:
        g = _grid((40, 36), (1.2, 0.9), (-10.0, 4.0), _rotation(2, [30]))
        u = np.random.default_rng(4).standard_normal((*g.shape, 2))
        u = np.stack([ndimage_smooth(u[..., c]) for c in range(2)], axis=-1)
        t = _field(g, u * (3.0 / np.sqrt((u**2).sum(-1)).max()))
    nodes = voxel_points(g)
    expected = _sampled(invert(t, field_step=step, refine_steps=3), g)
    got = PointwiseInverse(t, field_step=step, refine_steps=3).map_points(nodes)
    assert np.abs(got - expected).max() < 1e-9
    assert np.abs(got - nodes).max() > 0.5  # the field does move points
    far = nodes[:5] - 50.0  # 50 mm beyond the grid: more than 3 mm + a voxel
    np.testing.assert_array_equal(PointwiseInverse(t, field_step=step).map_points(far), far)


def ndimage_smooth(a: np.ndarray) -> np.ndarray:
    return sitk.GetArrayFromImage(sitk.SmoothingRecursiveGaussian(sitk.GetImageFromArray(a), 5.0))


def test_pointwise_inverse_of_a_chain_round_trips():
    """An affine map after a field, and a B-spline sampled on the grid: T^-1(T(p)) = p to
    well under a hundredth of a mm on a smooth field, linear pieces exactly; the same bits on
    one thread and on all."""
    import numba

    from itk_nrreval.io.transforms import PointwiseInverse

    g = OBLIQUE_GRID
    affine = sitk.AffineTransform(3)
    affine.SetMatrix((_rotation(3, [10, 5]) * 1.05).ravel().tolist())
    affine.SetTranslation([2.0, -1.0, 3.0])
    affine.SetCenter([1.0, 2.0, 3.0])
    bspline = sitk.BSplineTransformInitializer(sitk.Image(list(g.size), sitk.sitkFloat32), [3] * 3)
    bspline.SetParameters(
        (np.random.default_rng(8).normal(scale=0.8, size=len(bspline.GetParameters()))).tolist()
    )
    chain = sitk.CompositeTransform([affine, smooth_random_field(g, max_mm=3.0)])
    p = voxel_points(g)
    back = PointwiseInverse(chain, field_step=4).map_points(_sampled(chain, g))
    assert np.linalg.norm(back - p, axis=1).mean() < 0.01
    linear = PointwiseInverse(affine).map_points(_sampled(affine, g))
    np.testing.assert_allclose(linear, p, atol=1e-9)
    with pytest.raises(InputError, match="grid"):
        PointwiseInverse(bspline)
    threads = numba.get_num_threads()
    results = []
    try:
        for n in (1, numba.config.NUMBA_NUM_THREADS):
            numba.set_num_threads(n)
            results.append(PointwiseInverse(chain, field_step=4).map_points(_sampled(chain, g)))
    finally:
        numba.set_num_threads(threads)
    np.testing.assert_array_equal(results[0], results[1])


@pytest.mark.parametrize("dim", [2, 3])
def test_voxel_points_are_itks(dim):
    """composed_displacement's voxel points (_field_kernels.add_voxel_points): ITK's own index
    -> physical point, C order (x fastest)."""
    from itk_nrreval.io._field_kernels import add_voxel_points

    g = OBLIQUE_GRID if dim == 3 else _grid((7, 5), (1.2, 0.9), (-10.0, 4.0), _rotation(2, [30]))
    origin, matrix, size = np.zeros(3), np.zeros((3, 3)), np.ones(3, np.int64)
    origin[:dim] = g.origin
    matrix[:dim, :dim] = np.asarray(g.direction).reshape(dim, dim) * g.spacing
    size[:dim] = g.size
    points = np.zeros((int(np.prod(g.size)), 3))
    add_voxel_points(points, origin, matrix, size, 1.0)
    np.testing.assert_allclose(points[:, :dim], voxel_points(g), rtol=0, atol=1e-12)


def test_measures_from_the_callers_sampling_equal_their_own():
    """deformation_measures(displacement=) -- the transform already sampled on the grid, as
    evaluate shares it with the memberships -- gives what its own slab-by-slab sampling
    gives, slabs and mask included."""
    from itk_nrreval.io.plausibility import deformation_measures
    from itk_nrreval.io.transforms import displacement_field

    g = OBLIQUE_GRID
    t, _ = _sine(g, k=1.1, period=14.0, axis=(0.3, 0.5, 1.0))
    mask = np.zeros(g.shape, bool)
    mask[3:-4, 5:, :-6] = True
    field = displacement_field(t, g)
    sampled = sitk.GetArrayViewFromImage(field)
    kwargs = dict(mask=mask, affine=True, max_slab_voxels=9000)
    own = deformation_measures(t, g, **kwargs)
    given = deformation_measures(t, g, displacement=sampled, **kwargs)
    own_values = own.plausibility.to_dict().values()
    for a, b in zip(own_values, given.plausibility.to_dict().values(), strict=True):
        assert a == pytest.approx(b, rel=1e-9, abs=1e-12)
    np.testing.assert_allclose(
        own.jacobian.middle, given.jacobian.middle, rtol=1e-9, equal_nan=True
    )
    np.testing.assert_array_equal(own.jacobian.counts, given.jacobian.counts)
    assert own.affine.to_dict() == pytest.approx(given.affine.to_dict(), rel=1e-9)
    with pytest.raises(InputError, match="displacement"):
        deformation_measures(t, g, displacement=sampled[1:])


# ------------------------------------------------------------------------------------------
# Issue 42 (item 5): folds that central differences miss -- Liu et al.'s digital
# diffeomorphism (IJCV 2024), the non-diffeomorphic voxels and volume


def _liu_reference(u: np.ndarray, g: Geometry, mask=None) -> tuple[float, float, float]:
    """Liu et al.'s stencils by brute force, written after their code
    (github.com/yihao6/digital_diffeomorphism): the deformation in index units
    ``psi(q) = q + D^-1 u / spacing``, padded by one voxel with the displacement's edge
    values; ``det`` of forward / backward differences (``psi(p + e) - psi(p)``,
    ``psi(p) - psi(p - e)``) for every combination of axes, and in 3D their ``j1*`` and
    ``j2*`` (differences to p - (1,1,0), p - (1,0,1), p - (0,1,1) and to p + (1,1,0),
    p + (0,1,1), p + (1,0,1)). Returns the fraction of (masked) voxels with some det <= 0,
    their non-diffeomorphic volume over the (masked) voxels -- ``sum -0.5 min(J, 0) / 2``
    over the triangles in 2D, ``/ 6`` over the ten tetrahedra in 3D -- and the smallest
    ``|det|`` (how far the count is from a rounding tie)."""
    dim = g.dimension
    m = np.linalg.inv(np.asarray(g.direction).reshape(dim, dim) @ np.diag(g.spacing))
    xyz = np.transpose(u, (*range(dim)[::-1], dim))  # spatial axes in ITK order (x, y[, z])
    padded = np.pad(xyz @ m.T, [(1, 1)] * dim + [(0, 0)], mode="edge")
    grid = np.meshgrid(*[np.arange(-1.0, n + 1) for n in g.size], indexing="ij")
    psi = np.stack(grid, axis=-1) + padded

    def at(offset) -> np.ndarray:
        return psi[tuple(slice(1 + o, 1 + o + n) for o, n in zip(offset, g.size, strict=True))]

    p0 = at((0,) * dim)
    axes = np.eye(dim, dtype=int)
    dets = []
    for signs in np.ndindex(*(2,) * dim):  # 0: forward, 1: backward, per axis
        columns = [at(axes[a]) - p0 if s == 0 else p0 - at(-axes[a]) for a, s in enumerate(signs)]
        dets.append(np.linalg.det(np.stack(columns, axis=-1)))
    if dim == 3:
        for offsets in ([(-1, -1, 0), (-1, 0, -1), (0, -1, -1)], [(1, 1, 0), (0, 1, 1), (1, 0, 1)]):
            dets.append(np.linalg.det(np.stack([at(o) - p0 for o in offsets], axis=-1)))
    dets = np.stack(dets)
    bad = np.any(dets <= 0, axis=0)
    volume = np.sum(-0.5 * np.minimum(dets, 0) / (2 if dim == 2 else 6), axis=0)
    sel = np.ones(g.size, bool) if mask is None else np.transpose(mask)
    return float(bad[sel].mean()), float(volume[sel].mean()), float(np.abs(dets).min())


def _rough_field(g: Geometry, *, sigma: float, max_mm: float, seed: int) -> np.ndarray:
    """Gaussian-smoothed noise (sigma in voxels) scaled to a largest displacement of
    `max_mm`: ``u`` of shape ``(*g.shape, dim)`` (mm, ITK component order)."""
    from scipy import ndimage

    noise = np.random.default_rng(seed).standard_normal((*g.shape, g.dimension))
    u = np.stack(
        [ndimage.gaussian_filter(noise[..., c], sigma) for c in range(g.dimension)], axis=-1
    )
    return u * (max_mm / np.sqrt((u**2).sum(-1)).max())


#: Oblique, anisotropic grids; the 3D one's direction a rotation times a flipped axis
#: (det -1, as a RAS image read in LPS has), so that no orientation is assumed.
_FLIP = np.diag([1.0, -1.0, 1.0])
NONDIFF_GRIDS = {
    2: _grid((34, 27), (0.8, 1.3), (-10.0, 4.0), _rotation(2, [25])),
    3: _grid((22, 19, 15), (1.2, 0.9, 1.5), (-10.0, 4.0, 2.0), _rotation(3, [30, 20]) @ _FLIP),
}


@pytest.mark.parametrize("dim", [2, 3])
def test_nondiffeomorphic_fraction_and_volume_against_liu_et_al(dim):
    # A rough random field on an oblique anisotropic grid, in slabs and inside a mask: the
    # non-diffeomorphic voxels and volume are those of the brute-force reference, and the
    # stencils see more than central differences do.
    g = NONDIFF_GRIDS[dim]
    u = _rough_field(g, sigma=1.0, max_mm=4.0, seed=11 + dim)
    mask = np.zeros(g.shape, bool)
    mask[(slice(1, -2),) * dim] = True
    mask[(slice(3, 6),) * dim] = False
    fraction, volume, margin = _liu_reference(u, g, mask)
    assert margin > 1e-9  # no det J sits on 0: the count is not a rounding tie
    slab = int(np.prod(g.shape[1:])) * 4  # four rows of the last axis per slab
    p = deformation_plausibility(
        _field(g, u), g, mask=mask, inverse_consistency=False, max_slab_voxels=slab
    )
    assert 0.05 < fraction < 0.9
    assert p.nondiffeomorphic_fraction == pytest.approx(fraction, abs=1e-15)
    assert p.nondiffeomorphic_volume == pytest.approx(volume, rel=1e-9)
    assert p.nondiffeomorphic_max == p.nondiffeomorphic_fraction
    assert p.folded_fraction < p.nondiffeomorphic_fraction
    whole = deformation_plausibility(_field(g, u), g, inverse_consistency=False)
    fraction, volume, _ = _liu_reference(u, g)
    assert whole.nondiffeomorphic_fraction == pytest.approx(fraction, abs=1e-15)
    assert whole.nondiffeomorphic_volume == pytest.approx(volume, rel=1e-9)


def _checkerboard(dim: int) -> tuple[Geometry, np.ndarray]:
    """u_x = +-0.75 voxel alternating like a checkerboard on an inner block, 0 around it:
    central differences skip every other voxel, so they see u_x constant inside the block
    (det J = 1) and +-0.375 voxel per voxel at its edges (det J 0.625, 1.375), while each
    voxel of the block moves 1.5 voxels past a neighbour (one-sided det J = -0.5)."""
    g = _grid((14, 12, 10)[:dim], (1.0, 0.8, 1.25)[:dim])
    u = np.zeros((*g.shape, dim))
    block = (slice(3, -3),) * dim
    parity = np.indices(g.shape).sum(axis=0) % 2
    u[(*block, 0)] = (0.75 * g.spacing[0] * (1 - 2 * parity))[block]
    return g, u


@pytest.mark.parametrize("dim", [2, 3])
def test_a_field_that_folds_between_grid_points_folds_by_some_stencil(dim):
    g, u = _checkerboard(dim)
    p = deformation_plausibility(_field(g, u), g, inverse_consistency=False)
    assert p.folded_fraction == 0.0 and p.jacobian_min == pytest.approx(0.625)
    fraction, volume, _ = _liu_reference(u, g)
    assert p.nondiffeomorphic_fraction == pytest.approx(fraction, abs=1e-15)
    assert p.nondiffeomorphic_volume == pytest.approx(volume, rel=1e-12)
    # by hand: a voxel of the block moving +0.75 towards a neighbour moving -0.75 folds
    # (one-sided det J = 1 - 1.5 = -0.5 on the 2 triangles or 4 corner tetrahedra on that
    # side); so does every voxel of each row of the block along x but one of its two ends
    # (0 or 2 of them, as the row starts with -0.75 or +0.75: 1 a row on average)
    rows = np.prod([n - 6 for n in g.shape[:-1]])  # the block's rows along x
    folded = rows * (g.shape[-1] - 6 - 1)
    assert p.nondiffeomorphic_fraction == folded / u[..., 0].size > 0.09
    share = 2 * 0.25 if dim == 2 else 4 / 12  # each simplex's share of a voxel, / 2
    assert p.nondiffeomorphic_volume == pytest.approx(folded * share * 0.5 / u[..., 0].size)
    # the folding flag says so, where central differences alone would flag nothing
    (reason,) = flags({"checkerboard": p})["checkerboard"]
    assert "by some finite-difference stencil" in reason
    assert reason.endswith("where central differences see 0%")


@pytest.mark.parametrize("dim", [2, 3])
def test_a_smooth_invertible_field_is_digitally_diffeomorphic(dim):
    g = NONDIFF_GRIDS[dim]
    u = _rough_field(g, sigma=4.0, max_mm=1.5, seed=5)
    p = deformation_plausibility(_field(g, u), g, inverse_consistency=False)
    assert p.jacobian_min > 0.5  # far from folding
    assert p.folded_fraction == p.nondiffeomorphic_fraction == p.nondiffeomorphic_volume == 0.0
    assert _liu_reference(u, g)[:2] == (0.0, 0.0)
    assert flags({"smooth": p})["smooth"] == []


def test_stencils_leave_the_central_jacobian_as_it_was_and_the_threads_do_not_matter():
    # The stencils share the central differences' pass (one compiled kernel): det J is
    # transforms.jacobian_determinant's to the bit, and one thread and every thread give
    # the same numbers.
    import numba

    from itk_nrreval.io.plausibility import deformation_measures
    from itk_nrreval.io.transforms import jacobian_determinant

    g = NONDIFF_GRIDS[3]
    u = _rough_field(g, sigma=1.0, max_mm=4.0, seed=3)
    t = _field(g, u)
    det = jacobian_determinant(u, spacing=g.spacing, direction=g.direction)
    threads = numba.get_num_threads()
    results = []
    try:
        for n in (1, numba.config.NUMBA_NUM_THREADS):
            numba.set_num_threads(n)
            results.append(deformation_measures(t, g, inverse_consistency=False, displacement=u))
    finally:
        numba.set_num_threads(threads)
    (p, summary), (p_all, summary_all) = ((m.plausibility, m.jacobian) for m in results)
    np.testing.assert_array_equal(summary.middle, det[g.shape[0] // 2].astype(np.float32))
    assert p.folded_fraction == np.mean(det <= 0) > 0.01
    assert (p.jacobian_min, p.jacobian_max) == (det.min(), det.max())
    logs = np.log(det[det > 0])
    assert p.sdlogj == pytest.approx(np.sqrt(np.mean((logs - logs.mean()) ** 2)), rel=1e-14)
    assert p == p_all
    np.testing.assert_array_equal(summary.middle, summary_all.middle)


def test_nondiffeomorphic_measures_combine_and_round_trip():
    a = Plausibility(0.0, 0.0, 0.1, 0.5, 1.5, 0.01, 0.02, 0.02, 0.001)
    b = Plausibility(0.001, 0.001, 0.1, -0.1, 1.5, 0.01, 0.04, 0.04, 0.003)
    c = combine([a, b])
    assert c.nondiffeomorphic_fraction == pytest.approx(0.03)
    assert c.nondiffeomorphic_max == 0.04
    assert c.nondiffeomorphic_volume == pytest.approx(0.002)
    assert Plausibility.from_dict(json.loads(json.dumps(c.to_dict()))) == c
    # results written before the measure existed: not measured (NaN), and never flagged
    old = {k: v for k, v in a.to_dict().items() if not k.startswith("nondiffeomorphic")}
    read = Plausibility.from_dict(old)
    assert math.isnan(read.nondiffeomorphic_fraction) and math.isnan(read.nondiffeomorphic_max)
    assert math.isnan(combine([read, b]).nondiffeomorphic_fraction)
    assert flags({"old": read})["old"] == []
    # stencil folding crosses the folding bounds: 1% on average, 25% in one image
    stencil = Plausibility(0.0001, 0.0002, 0.1, 0.2, 1.5, 0.01, 0.011, 0.014, 0.0001)
    (reason,) = flags({"demons": stencil})["demons"]
    assert reason == (
        "1.1% of voxels fold by some finite-difference stencil (Jacobian determinant <= 0 "
        "on a one-sided or tetrahedral stencil; 1.4% in the worst image), where central "
        "differences see 0.01%"
    )
    worst = Plausibility(0.0001, 0.0002, 0.1, 0.2, 1.5, 0.01, 0.005, 0.3, 0.0001)
    assert "30% in the worst image" in flags({"w": worst})["w"][0]
    # central folding above the bounds is said as before, once
    both = Plausibility(0.02, 0.04, 0.1, -0.2, 1.5, 0.01, 0.03, 0.05, 0.001)
    assert flags({"b": both})["b"] == [
        "2% of voxels fold (Jacobian determinant <= 0; 4% in the worst image)"
    ]
