"""The 3D clamped-plate spline: the triharmonic kernel, warps that do not fold, the ball in mm.

Every check here is against something independent of the module: Boggio's integral by
quadrature, finite differences of the kernel's values, brute-force scans of determinants,
the closed-form single-knot bump, and dense sampling of accepted warps.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from scipy import integrate, ndimage, optimize

from itk_nrreval.experiments import warps as W
from itk_nrreval.experiments._fold_check import safe_scale


def random_inside(rng, n, dim, rmax=0.9):
    v = rng.normal(size=(n, dim))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return v * rmax * rng.uniform(0.05, 1, size=(n, 1)) ** (1 / dim)


def boggio(x, y, m, n):
    """Boggio's clamped Green's function of (-Delta)^m on the unit ball of R^n, without its
    constant: r^(2m - n) int_1^A (v^2 - 1)^(m - 1) v^(1 - n) dv, by quadrature."""
    r = np.linalg.norm(x - y)
    a = np.sqrt(x @ x * (y @ y) - 2 * x @ y + 1) / r
    val, _ = integrate.quad(lambda v: (v * v - 1) ** (m - 1) * v ** (1 - n), 1.0, a, epsabs=0)
    return r ** (2 * m - n) * val


def biharmonic_3d(x, y):
    """The former 3D kernel, r (A + 1/A - 2): the cone point the triharmonic one removes."""
    r = np.linalg.norm(x - y)
    a = np.sqrt(x @ x * (y @ y) - 2 * x @ y + 1) / r
    return r * (a + 1 / a - 2)


# ----------------------------------------------------------------------------------------
# The kernel
# ----------------------------------------------------------------------------------------


def test_green_is_boggios_integral():
    rng = np.random.default_rng(0)
    for dim, m, const in ((2, 2, 2.0), (3, 3, 1.0)):  # 2D: the module's r^2 (A^2-1-ln A^2)
        x, y = random_inside(rng, 12, dim), random_inside(rng, 5, dim)
        ref = np.array([[const * boggio(a, b, m, dim) for b in y] for a in x])
        np.testing.assert_allclose(W.green(x, y), ref, rtol=1e-7)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(2, 20))
def test_green_3d_symmetric_and_positive_definite(seed, n):
    rng = np.random.default_rng(seed)
    pts = random_inside(rng, n, 3, rmax=0.95)
    dist = np.linalg.norm(pts[:, None] - pts[None], axis=-1) + np.eye(n)
    assume(dist.min() > 0.05)
    g = W.green(pts, pts)
    np.testing.assert_allclose(g, g.T, rtol=1e-12, atol=0)
    assert np.linalg.eigvalsh(g).min() > 0
    # and the Cholesky solve of from_knots accepts them
    W.ClampedPlateSpline.from_knots(pts * 0.99, np.zeros_like(pts))


def test_green_3d_clamped_to_third_order_on_the_sphere():
    """G = dG/dn = d2G/dn2 = 0 on the sphere (the triharmonic Dirichlet conditions):
    G(n (1 - h)) ~ c h^3 with c > 0; the biharmonic kernel only vanishes like h^2."""
    rng = np.random.default_rng(3)
    y = random_inside(rng, 6, 3, rmax=0.8)
    n = rng.normal(size=(30, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    hs = np.array([4e-3, 2e-3, 1e-3])
    g = np.stack([W.green(n * (1 - h), y) for h in hs])  # (3, 30, 6)
    c = g / hs[:, None, None] ** 3
    assert c.min() > 0
    np.testing.assert_allclose(c[1:], c[:-1], rtol=0.02)  # G / h^3 converges
    # normal derivatives by differences along the normal, at the sphere itself
    h = 1e-3

    def along(f, t):
        return np.array([[f(a * (1 - t), b) for b in y] for a in n[:8]])

    for f, order in ((lambda a, b: W.green(a[None], b[None])[0, 0], 3), (biharmonic_3d, 2)):
        d2 = (along(f, 2 * h) - 2 * along(f, h) + along(f, 0)) / h**2  # d2G/dn2 at h
        d2_half = (along(f, h) - 2 * along(f, h / 2) + along(f, 0)) / (h / 2) ** 2
        if order == 3:  # second derivative -> 0 linearly in h
            np.testing.assert_allclose(d2 / d2_half, 2.0, rtol=0.05)
        else:  # the biharmonic kernel keeps a nonzero second normal derivative: not clamped
            np.testing.assert_allclose(d2 / d2_half, 1.0, rtol=0.05)
    # the gradient on the sphere itself (|n| = 1 to rounding) vanishes
    assert np.abs(W.green_gradient(n, y)).max() < 1e-20


def _tri_laplacian_stencil(power: int) -> np.ndarray:
    """Coefficients (times h^(2 power)) of the discrete Laplacian to the given power."""
    size = 2 * power + 1
    k = np.zeros((size,) * 3)
    k[(power,) * 3] = 1.0
    lap = np.zeros((3, 3, 3))
    lap[1, 1, 1] = -6.0
    for a in range(3):
        idx = [1, 1, 1]
        for s in (0, 2):
            idx[a] = s
            lap[tuple(idx)] = 1.0
        idx[a] = 1
    for _ in range(power):
        k = ndimage.convolve(k, lap, mode="constant")
    return k


def _discrete(f, x, h, power):
    k = _tri_laplacian_stencil(power)
    offs = np.argwhere(k != 0) - power
    return float(k[tuple((offs + power).T)] @ f(x + h * offs)) / h ** (2 * power)


def test_green_3d_is_triharmonic_not_biharmonic_away_from_the_knot():
    rng = np.random.default_rng(5)
    y = np.array([0.2, -0.1, 0.15])
    xs = [np.array([-0.3, 0.35, 0.1]), np.array([0.5, 0.2, -0.3])]
    while len(xs) < 8:  # and random points at distance >= 0.4 from the knot, inside 0.8
        x = random_inside(rng, 1, 3, rmax=0.8)[0]
        if np.linalg.norm(x - y) > 0.4:
            xs.append(x)

    def g(p):
        return W.green(p, y[None])[:, 0]

    def g_plus(p):  # a non-triharmonic comparison: Delta^3 |x|^6 = 5040
        return g(p) + 1e-3 * np.sum(p * p, axis=1) ** 3

    for x in xs:
        # Richardson on h = 0.02, 0.01 cancels the h^2 error of the 6th-order stencil
        tri = [_discrete(g, x, h, 3) for h in (0.02, 0.01)]
        extrap = (4 * tri[1] - tri[0]) / 3
        assert abs(extrap) < 0.05, (x, tri)
        cmp = [_discrete(g_plus, x, h, 3) for h in (0.02, 0.01)]
        assert (4 * cmp[1] - cmp[0]) / 3 == pytest.approx(5.04, abs=0.05)
    # it is not merely biharmonic (a biharmonic kernel is triharmonic too)
    bi = [_discrete(g, xs[1], h, 2) for h in (0.02, 0.01)]
    assert abs((4 * bi[1] - bi[0]) / 3) > 1.0


def test_3d_kernel_is_smooth_through_the_knot_unlike_the_biharmonic():
    """The gradient (so the warp's Jacobian) is continuous at the knot; the biharmonic
    kernel's jumps by 2 (its cone point -2 r)."""
    y = np.array([0.25, -0.1, 0.3])
    e = np.array([0.6, 0.0, 0.8])
    h, eps = 1e-6, 1e-4

    def fd_grad(f, p):
        return np.array([(f(p + h * a) - f(p - h * a)) / (2 * h) for a in np.eye(3)])

    def tri(p):
        return W.green(p[None], y[None])[0, 0]

    jump_tri = fd_grad(tri, y + eps * e) - fd_grad(tri, y - eps * e)
    jump_bi = fd_grad(lambda p: biharmonic_3d(p, y), y + eps * e) - fd_grad(
        lambda p: biharmonic_3d(p, y), y - eps * e
    )
    assert np.linalg.norm(jump_tri) < 1e-3
    # grad(-2 r) flips from -2 e to +2 e across the knot: a jump of length 4
    assert np.linalg.norm(jump_bi) == pytest.approx(4.0, rel=0.01)
    # second derivatives (of the analytic gradient) agree on both sides of the knot too
    hess = [
        (W.green_gradient((y + s * 2 * eps * e)[None], y[None])[0, 0]
         - W.green_gradient((y + s * eps * e)[None], y[None])[0, 0]) / (s * eps)
        for s in (1, -1)
    ]  # fmt: skip
    np.testing.assert_allclose(hess[0], hess[1], atol=2e-3 * max(1.0, np.abs(hess[0]).max()))


def test_spline_jacobian_matches_finite_differences_near_knots():
    knots = W.knot_positions(9, 3)
    rng = np.random.default_rng(2)
    cps = W.ClampedPlateSpline.from_knots(knots, rng.normal(size=knots.shape) * 0.05)
    pts = np.concatenate([knots + 1e-3 * rng.normal(size=knots.shape), random_inside(rng, 20, 3)])
    h = 1e-6
    fd = np.stack([(cps(pts + h * e) - cps(pts - h * e)) / (2 * h) for e in np.eye(3)], -1)
    np.testing.assert_allclose(cps.jacobian(pts), fd, atol=1e-7)


# ----------------------------------------------------------------------------------------
# The fold check's arithmetic, through the public API
# ----------------------------------------------------------------------------------------


def brute_first_crossing(a, m):
    """Smallest t > 0 with det(I + t A) = m, by scanning then bisection (inf if none < 1e3)."""
    ts = np.concatenate([np.linspace(0, 1, 20001)[1:], np.geomspace(1, 1e3, 20000)])
    det = np.linalg.det(np.eye(len(a)) + ts[:, None, None] * a) - m
    neg = np.flatnonzero(det <= 0)
    if neg.size == 0:
        return np.inf
    k = neg[0]
    lo = 0.0 if k == 0 else ts[k - 1]
    return optimize.brentq(lambda t: np.linalg.det(np.eye(len(a)) + t * a) - m, lo, ts[k])


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("m", [0.0, 0.05, 0.5])
def test_max_safe_displacement_of_linear_fields_matches_a_brute_force_scan(dim, m):
    rng = np.random.default_rng(int(10 * m) + dim)
    shape = (5,) * dim
    grid = np.stack(np.indices(shape)[::-1], -1).astype(float) - 2.0  # ITK order, centred
    for _ in range(25):
        a = rng.normal(size=(dim, dim)) * rng.uniform(0.05, 2)
        field = grid @ a.T  # u(p) = A (p - c): central differences give A exactly
        mean = np.linalg.norm(field, axis=-1).mean()
        expected = mean * brute_first_crossing(a, m)
        got = W.max_safe_displacement(field, min_jacobian=m)
        if np.isinf(expected):
            assert got > mean * 999
        else:
            assert got == pytest.approx(expected, rel=1e-6)


def test_single_knot_bump_folds_where_the_closed_form_says():
    """One knot at the centre: u = a e (1 - rho)^3 (1 + 3 rho) (the kernel at y = 0, scaled
    to 1 at the knot). det(I + grad u) = 1 + a dP/de >= 0 while a <= R / max|P'| = 9 R / 16,
    so the largest safe d is 9 R / 16 times the grid mean of P -- independent of the module."""
    shape = (36, 44, 40)  # numpy order: 40 x 44 x 36 in ITK order
    warp = W.random_cps(shape, 0.1, n_knots=1, seed=0)
    r = min(shape) / 2
    idx = np.indices(shape).astype(float)
    rho = np.sqrt(sum((idx[a] - (shape[a] - 1) / 2) ** 2 for a in range(3))) / r
    bump = np.where(rho < 1, (1 - rho) ** 3 * (1 + 3 * rho), 0.0)
    expected = 9 * r / 16 * bump.mean()
    assert W.max_safe_displacement(warp) == pytest.approx(expected, rel=2e-3)
    assert expected < 0.45  # the "2 px on 40 x 44 x 36" is beyond any single bump


# ----------------------------------------------------------------------------------------
# Random 3D warps
# ----------------------------------------------------------------------------------------


def fd_det(warp, pts, h=1e-4):
    """det(I + grad u) from central differences of the displacement (not its Jacobian)."""
    cols = [(warp.displacement(pts + h * e) - warp.displacement(pts - h * e)) / (2 * h)
            for e in np.eye(3)]  # fmt: skip
    return np.linalg.det(np.eye(3) + np.stack(cols, -1))


def near_knot_points(warp, half=0.75, step=0.25):
    """A grid 1/step times finer than the image in a box of +-half pixels around each knot."""
    a = np.arange(-half, half + 1e-9, step)
    box = np.stack(np.meshgrid(a, a, a, indexing="ij"), -1).reshape(-1, 3)
    return (warp.knots[:, None, :] + box[None]).reshape(-1, 3)


def ball_mask(shape, spacing=(1.0, 1.0, 1.0)):
    idx = np.indices(shape).astype(float)
    sp = np.asarray(spacing)[::-1]  # numpy order
    radius = min(n * s for n, s in zip(shape, sp, strict=True)) / 2
    rad2 = sum(((idx[a] - (shape[a] - 1) / 2) * sp[a]) ** 2 for a in range(3))
    return rad2 < radius**2


@pytest.mark.parametrize(
    "shape,d,seeds", [((36, 44, 40), 0.25, range(20)), ((64, 64, 64), 0.6, range(3))]
)
def test_3d_warps_exact_mean_zero_outside_and_no_fold_near_knots(shape, d, seeds):
    inside = ball_mask(shape)
    worst = np.inf
    for seed in seeds:
        warp = W.random_cps(shape, d, seed=seed)
        field = warp.field()
        assert abs(np.linalg.norm(field, axis=-1).mean() - d) < 1e-9
        assert np.all(field[~inside] == 0) and np.abs(field[inside]).max() > 0
        det = fd_det(warp, near_knot_points(warp))
        worst = min(worst, det.min())
        assert warp.min_jacobian >= W.MIN_JACOBIAN
        if seed < 2:  # consistent with the acceptance (test_max_safe_displacement_is_tight)
            assert W.max_safe_displacement(warp, min_jacobian=W.MIN_JACOBIAN) >= d
    assert worst > 0


def test_accepted_warps_have_no_fold_anywhere_on_a_dense_grid():
    """Brute force: the analytic det on a grid 2x finer than the image over the whole ball
    (and 4x finer near knots) never falls below the acceptance threshold by more than the
    determinant changes over a quarter pixel."""
    shape = (24, 24, 24)
    a = np.arange(0, 23 + 1e-9, 0.5)
    dense = np.stack(np.meshgrid(a, a, a, indexing="ij"), -1).reshape(-1, 3)
    for seed in range(3):
        warp = W.random_cps(shape, 0.3, n_knots=9, seed=seed)
        dets = np.linalg.det(np.eye(3) + warp.jacobian(dense))
        assert dets.min() > W.MIN_JACOBIAN - 0.02, (seed, dets.min())
        near = np.linalg.det(np.eye(3) + warp.jacobian(near_knot_points(warp)))
        assert near.min() > W.MIN_JACOBIAN - 0.02


def test_max_safe_displacement_is_tight():
    """Scaled up to just below the reported safe d the warp stays above the threshold on a
    dense grid; 10 % beyond it, it does not."""
    shape = (24, 24, 24)
    a = np.arange(0, 23 + 1e-9, 0.25)
    dense = np.stack(np.meshgrid(a, a, a, indexing="ij"), -1).reshape(-1, 3)
    warp = W.random_cps(shape, 0.2, n_knots=9, seed=4)
    safe = W.max_safe_displacement(warp, min_jacobian=W.MIN_JACOBIAN)
    assert safe > 0.2
    jac = warp.jacobian(dense) / warp.scale  # unscaled: scale is linear in d
    scale_at = warp.scale * safe / warp.mean_displacement
    below = np.linalg.det(np.eye(3) + 0.98 * scale_at * jac).min()
    beyond = np.linalg.det(np.eye(3) + 1.10 * scale_at * jac).min()
    assert below > W.MIN_JACOBIAN - 0.01
    assert beyond < W.MIN_JACOBIAN


def test_impossible_3d_request_reports_a_reachable_safe_d():
    shape = (36, 44, 40)
    with pytest.raises(W.FoldingError, match="px") as info:
        W.random_cps(shape, 2.0, seed=1, max_tries=3)  # the request
    safe = info.value.largest_safe
    assert 0 < safe < 0.6 and info.value.largest_safe_mm == pytest.approx(safe, rel=1e-9)
    # the best of the same three draws is accepted just below it
    warp = W.random_cps(shape, 0.999 * safe, seed=1, max_tries=3)
    assert warp.min_jacobian >= W.MIN_JACOBIAN


def test_anisotropic_voxels_get_a_ball_in_mm():
    shape, spacing = (20, 24, 28), (1.0, 1.0, 2.5)  # x, y 1 mm; z 2.5 mm: 28 x 24 x 50 mm
    warp = W.random_cps(shape, 0.05, spacing=spacing, n_knots=9, seed=0)
    field = warp.field()
    inside = ball_mask(shape, spacing)
    moved = np.linalg.norm(field, axis=-1) > 0
    assert not moved[~inside].any() and moved[inside].mean() > 0.99
    assert warp.radius_mm == 12.0
    assert abs(np.linalg.norm(field, axis=-1).mean() - 0.05) < 1e-9
    mm = np.linalg.norm(field * np.array(spacing), axis=-1).mean()  # ITK components x spacing
    assert warp.mean_displacement_mm == pytest.approx(mm, rel=1e-12)
    k_mm = (warp.knots - warp.centre) * np.array(spacing)
    assert np.linalg.norm(k_mm, axis=1).max() <= W.KNOT_RADIUS * 12.0 + 1e-9
    # the inverse still inverts, on the anisotropic grid
    v = warp.inverse_field().reshape(-1, 3)
    grid = np.stack(np.indices(shape)[::-1], -1).reshape(-1, 3).astype(float)
    np.testing.assert_allclose(grid + v + warp.displacement(grid + v), grid, atol=1e-4)


def test_max_safe_of_the_identity_and_bad_threshold():
    assert W.max_safe_displacement(W.random_cps((10, 10, 10), 0.0)) == np.inf
    with pytest.raises(ValueError, match="min_jacobian"):
        W.max_safe_displacement(np.zeros((5, 5, 2)), min_jacobian=1.0)
    warp = W.random_cps((16, 16, 16), 0.1, n_knots=5, seed=0)
    stripped = dataclasses.replace(warp, _u=None, _jac=None)  # recomputed from the spline
    assert W.max_safe_displacement(stripped) == pytest.approx(W.max_safe_displacement(warp))


# ----------------------------------------------------------------------------------------
# Warping labels
# ----------------------------------------------------------------------------------------


def test_warp_stack_maps_sparse_label_values_to_compact_channels():
    rng = np.random.default_rng(0)
    shape = (12, 14, 16)
    small = rng.integers(0, 3, size=(2, *shape))
    big = np.choose(small, [0, 17, 14175])
    warps = [W.random_cps(shape, 0.1, n_knots=3, seed=s) for s in (0, 1)]
    images = rng.normal(size=(2, *shape))
    _, m_small = W.warp_stack(images, warps, labels=small)
    _, m_big = W.warp_stack(images, warps, labels=big, label_values=[0, 17, 14175])
    assert m_big.shape == (2, 3, *shape)
    np.testing.assert_array_equal(m_big, m_small)
    # channel order follows label_values, not sorted values
    _, m_perm = W.warp_stack(images, warps, labels=big, label_values=[14175, 0, 17])
    np.testing.assert_array_equal(m_perm[:, [1, 2, 0]], m_small)
    with pytest.raises(ValueError, match="not in label_values"):
        W.warp_stack(images, warps, labels=big, label_values=[0, 17])
    with pytest.raises(ValueError, match="not both"):
        W.warp_stack(images, warps, labels=big, label_values=[0, 17, 14175], n_labels=3)


def test_warp_stack_memberships_rounding_is_clipped_real_violations_refused():
    rng = np.random.default_rng(1)
    shape = (10, 12, 14)
    lab = rng.integers(0, 2, size=(1, *shape))
    m = np.stack([lab == 0, lab == 1], axis=1).astype(np.float64)
    m[0, 1, 0, 0, 0] = 1.0 + 5e-7  # rounding in an upstream resampler
    m[0, 0, 0, 0, 1] = -5e-7
    warp = W.random_cps(shape, 0.05, n_knots=3, seed=0)
    _, out = W.warp_stack(rng.normal(size=(1, *shape)), [warp], labels=m)
    assert out.min() >= 0.0 and out.max() <= 1.0
    m[0, 1, 0, 0, 0] = 1.01
    with pytest.raises(ValueError, match=r"memberships must lie in \[0, 1\]"):
        W.warp_stack(rng.normal(size=(1, *shape)), [warp], labels=m)


@pytest.mark.parametrize("dim", [2, 3])
def test_capped_fold_search_agrees_with_the_exact_one(dim):
    """The acceptance test (is the first crossing beyond 1?) is done in closed form; it must
    agree with the exact crossing and with a brute-force scan."""
    rng = np.random.default_rng(dim)
    jac = rng.normal(size=(400, dim, dim)) * rng.uniform(0.05, 1.5, size=(400, 1, 1))
    for m in (0.0, 0.05):
        exact = np.array([safe_scale(a[None], m) for a in jac])
        capped = np.array([safe_scale(a[None], m, cap=1.0) for a in jac])
        np.testing.assert_allclose(capped, np.minimum(exact, 1.0), rtol=1e-9)
        for a, t in zip(jac[:40], exact[:40], strict=True):
            assert t == pytest.approx(brute_first_crossing(a, m), rel=1e-6) or (
                np.isinf(t) and np.isinf(brute_first_crossing(a, m))
            )
