"""Clamped-plate-spline warps: the Green's function, the spline, random warps, resampling.

References are kept here, independent of the module: the textbook ``A``-form of the Green's
function, finite differences, Jacobians from ``np.gradient``, SimpleITK's own resampler.
"""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk

from itk_nrreval.experiments import warps as W


def green_reference(x, y):
    """The textbook form: r^2 (A^2 - 1 - ln A^2) in 2D (biharmonic), and in 3D the
    triharmonic r^3 (A^3/3 - 2 A - 1/A + 8/3) (Boggio; see tests/test_warps3d.py)."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    r = np.linalg.norm(x - y)
    a2 = (x @ x * (y @ y) - 2 * x @ y + 1) / r**2
    if len(x) == 2:
        return r**2 * (a2 - 1 - np.log(a2))
    a = np.sqrt(a2)
    return r**3 * (a**3 / 3 - 2 * a - 1 / a + 8 / 3)


def random_inside(rng, n, dim, rmax=0.9):
    v = rng.normal(size=(n, dim))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    return v * rmax * rng.uniform(0.05, 1, size=(n, 1)) ** (1 / dim)


DIMS = pytest.mark.parametrize("dim", [2, 3])


@DIMS
def test_green_matches_textbook_form_and_is_symmetric(dim):
    rng = np.random.default_rng(1)
    x, y = random_inside(rng, 20, dim), random_inside(rng, 7, dim)
    g = W.green(x, y)
    ref = np.array([[green_reference(a, b) for b in y] for a in x])
    # the textbook 3D form cancels (G ~ (A - 1)^3): it is the reference that loses digits
    np.testing.assert_allclose(g, ref, rtol=1e-10 if dim == 2 else 1e-8)
    np.testing.assert_allclose(W.green(y, x), g.T, rtol=1e-13)
    assert np.all(g > 0)


@DIMS
def test_green_exact_limit_on_the_diagonal(dim):
    x = random_inside(np.random.default_rng(2), 10, dim)
    # 2D: (1 - |x|^2)^2; 3D (triharmonic): (1 - |x|^2)^3 / 3
    expected = (1 - np.sum(x**2, 1)) ** 2 if dim == 2 else (1 - np.sum(x**2, 1)) ** 3 / 3
    np.testing.assert_allclose(np.diag(W.green(x, x)), expected, rtol=1e-14)
    # continuous through the diagonal: a point 1e-7 away gives nearly the same value
    near = np.diag(W.green(x + 1e-7, x))
    np.testing.assert_allclose(near, expected, rtol=1e-5)


@DIMS
def test_knot_matrix_is_positive_definite(dim):
    knots = W.knot_positions(30, dim)
    assert np.linalg.eigvalsh(W.green(knots, knots)).min() > 0


@DIMS
def test_green_and_gradient_vanish_on_the_boundary(dim):
    rng = np.random.default_rng(3)
    y = random_inside(rng, 5, dim, rmax=0.8)
    n = rng.normal(size=(40, dim))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    # |n| = 1 up to rounding: G ~ (1 - |n|^2)^order and grad G ~ (1 - |n|^2)^(order - 1)
    # vanish with it (order 2 for the biharmonic 2D kernel, 3 for the triharmonic 3D one)
    assert np.abs(W.green(n, y)).max() < 1e-28
    assert np.abs(W.green_gradient(n, y)).max() < 1e-13
    # independently: moving in by h, G falls like h^2 in 2D (zero value and normal slope),
    # like h^3 in 3D (zero second normal derivative too)
    g1, g2 = W.green(n * (1 - 1e-3), y), W.green(n * (1 - 2e-3), y)
    np.testing.assert_allclose(g2 / g1, 4.0 if dim == 2 else 8.0, rtol=0.01)
    # and is exactly zero outside
    assert np.all(W.green(n * 1.3, y) == 0)


@DIMS
def test_gradient_matches_finite_differences(dim):
    rng = np.random.default_rng(4)
    x, y = random_inside(rng, 15, dim), random_inside(rng, 4, dim)
    h = 1e-6
    fd = np.stack(
        [(W.green(x + h * e, y) - W.green(x - h * e, y)) / (2 * h) for e in np.eye(dim)], -1
    )
    np.testing.assert_allclose(W.green_gradient(x, y), fd, rtol=1e-6, atol=1e-9)


def _bilaplacian(f, x, h):
    """Laplacian of the Laplacian by nested central differences."""
    dim = len(x)

    def lap(fun, p):
        return sum((fun(p + h * e) - 2 * fun(p) + fun(p - h * e)) / h**2 for e in np.eye(dim))

    return lap(lambda p: lap(f, p), x)


@pytest.mark.parametrize("dim", [2])
def test_green_is_biharmonic_away_from_the_knot(dim):
    # 2D only: the 3D kernel is triharmonic (tests/test_warps3d.py)
    y = np.array([0.2, -0.1, 0.15][:dim])
    h = 0.01
    for x in (np.array([-0.3, 0.35, 0.1][:dim]), np.array([0.5, 0.2, -0.3][:dim])):

        def f(p):
            return W.green(p[None], y[None])[0, 0]

        bilap = _bilaplacian(f, x, h)
        fourth = (
            f(x + 2 * h * np.eye(dim)[0])
            - 4 * f(x + h * np.eye(dim)[0])
            + 6 * f(x)
            - 4 * f(x - h * np.eye(dim)[0])
            + f(x - 2 * h * np.eye(dim)[0])
        ) / h**4
        assert abs(bilap) < 1e-2 * max(abs(fourth), 1.0), (bilap, fourth)

    # the test can fail: a smooth non-biharmonic function of similar size does not pass
    def not_biharmonic(p):
        return float(np.sum(p**2) ** 2)

    assert abs(_bilaplacian(not_biharmonic, np.array([-0.3, 0.35, 0.1][:dim]), h)) > 10


@DIMS
def test_spline_interpolates_knots_and_is_zero_outside(dim):
    rng = np.random.default_rng(5)
    knots = W.knot_positions(12, dim)
    moves = rng.normal(size=knots.shape) * 0.05
    cps = W.ClampedPlateSpline.from_knots(knots, moves)
    np.testing.assert_allclose(cps(knots), moves, atol=1e-12)
    outside = rng.normal(size=(30, dim))
    outside *= (1 + rng.uniform(0, 1, (30, 1))) / np.linalg.norm(outside, axis=1, keepdims=True)
    assert np.all(cps(outside) == 0)


def test_spline_rejects_bad_knots():
    with pytest.raises(ValueError, match="inside the unit ball"):
        W.ClampedPlateSpline.from_knots([[0.0, 0.0], [1.0, 0.0]], np.zeros((2, 2)))
    with pytest.raises(ValueError, match="coincident"):
        W.ClampedPlateSpline.from_knots([[0.1, 0.0], [0.1, 0.0]], np.zeros((2, 2)))
    with pytest.raises(ValueError, match="displacements must have"):
        W.ClampedPlateSpline.from_knots([[0.1, 0.0]], np.zeros((2, 2)))


def test_knots_spread_inside_the_circle():
    k = W.knot_positions(25, 2)
    assert k.shape == (25, 2)
    assert np.linalg.norm(k, axis=1).max() <= W.KNOT_RADIUS + 1e-12
    dist = np.linalg.norm(k[:, None] - k[None], axis=-1) + np.eye(25)
    assert dist.min() > 0.15


def numpy_jacobian_det(field):
    """det(I + grad u) from np.gradient; field (*shape, dim) in ITK component order."""
    dim = field.shape[-1]
    grads = np.gradient(field, axis=tuple(range(dim)))  # d/d numpy axis a
    jac = np.stack([grads[dim - 1 - j] for j in range(dim)], -1)  # d u_i / d x_j
    return np.linalg.det(np.eye(dim) + jac)


def inside_mask(shape):
    idx = np.indices(shape).astype(float)
    centre = (np.array(shape) - 1) / 2
    rad2 = sum((idx[a] - centre[a]) ** 2 for a in range(len(shape)))
    return rad2 < (min(shape) / 2) ** 2


@pytest.mark.parametrize(
    "shape,d,knots", [((141, 141), 3.0, 25), ((64, 80), 1.25, 9), ((40, 44, 42), 0.5, 9)]
)
def test_random_warp_mean_support_and_no_folding(shape, d, knots):
    warp = W.random_cps(shape, d, n_knots=knots, seed=7)
    field = warp.field()
    assert field.shape == (*shape, len(shape))
    assert abs(np.linalg.norm(field, axis=-1).mean() - d) < 1e-9
    assert np.all(field[~inside_mask(shape)] == 0)
    assert np.abs(field[inside_mask(shape)]).max() > 0
    assert numpy_jacobian_det(field).min() > 0
    assert W.max_safe_displacement(field) > d


def test_paper_d3_warps_on_141_are_diffeomorphic():
    for seed in range(3):
        field = W.random_cps((141, 141), 3.0, seed=seed).field()
        assert numpy_jacobian_det(field).min() > 0


def test_same_seed_same_warp():
    a = W.random_cps((50, 60), 2.0, n_knots=9, seed=11).field()
    b = W.random_cps((50, 60), 2.0, n_knots=9, seed=np.random.default_rng(11)).field()
    c = W.random_cps((50, 60), 2.0, n_knots=9, seed=12).field()
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)


def test_zero_displacement_is_identity():
    warp = W.random_cps((20, 20), 0.0, seed=0)
    assert np.all(warp.field() == 0) and np.all(warp.inverse_field() == 0)


def test_impossible_displacement_raises_folding_error():
    with pytest.raises(W.FoldingError, match="fold"):
        W.random_cps((41, 41), 15.0, seed=0, max_tries=3)


def test_bad_arguments():
    with pytest.raises(ValueError, match="mean_displacement must be"):
        W.random_cps((20, 20), -1.0)
    with pytest.raises(ValueError, match="shape must be 2D or 3D"):
        W.random_cps((20,), 1.0)
    with pytest.raises(ValueError, match="n_knots must be"):
        W.knot_positions(0, 2)


@pytest.mark.parametrize("shape,d", [((60, 70), 1.5), ((40, 44, 42), 0.4)])
def test_inverse_field_inverts_the_warp(shape, d):
    warp = W.random_cps(shape, d, n_knots=9, seed=3)
    v = warp.inverse_field().reshape(-1, len(shape))
    grid = np.stack(np.indices(shape)[::-1], -1).reshape(-1, len(shape)).astype(float)
    back = grid + v + warp.displacement(grid + v)  # psi(p + v(p)) = p
    np.testing.assert_allclose(back, grid, atol=1e-4)


def test_max_safe_displacement_of_a_linear_field():
    # u(x, y) = (-a (x - cx), 0): det(I + t grad u) = 1 - a t, folds at t = 1 / a
    shape, a = (30, 40), 0.2
    x = np.indices(shape)[1].astype(float)
    field = np.zeros((*shape, 2))
    field[..., 0] = -a * (x - x.mean())
    mean = np.abs(field[..., 0]).mean()
    assert W.max_safe_displacement(field) == pytest.approx(mean / a, rel=1e-9)
    field[..., 0] *= -1  # expansion never folds
    assert W.max_safe_displacement(field) == np.inf


def test_cps_warp_is_a_physical_sitk_field():
    # 48 x 40 pixels of 0.5 x 2 mm: 24 x 80 mm, so the ball (in mm) has radius 12 mm,
    # 24 pixels along x but only 6 along y
    ref = sitk.Image(48, 40, sitk.sitkFloat32)
    ref.SetSpacing((0.5, 2.0))
    ref.SetOrigin((3.0, -1.0))
    field = W.cps_warp(ref, 0.3, n_knots=9, seed=2)
    assert field.GetPixelID() == sitk.sitkVectorFloat64
    assert field.GetSize() == (48, 40) and field.GetSpacing() == (0.5, 2.0)
    assert field.GetOrigin() == (3.0, -1.0)
    pix = W.random_cps((40, 48), 0.3, spacing=(0.5, 2.0), n_knots=9, seed=2).field()
    np.testing.assert_allclose(sitk.GetArrayFromImage(field), pix * [0.5, 2.0], atol=1e-12)
    yy, xx = np.indices((40, 48)).astype(float)
    in_ball = ((xx - 23.5) * 0.5) ** 2 + ((yy - 19.5) * 2.0) ** 2 < 12.0**2
    moved = np.linalg.norm(pix, axis=-1) > 0
    assert moved[in_ball].mean() > 0.99 and not moved[~in_ball].any()
    tx = sitk.DisplacementFieldTransform(sitk.Image(field))
    assert field.GetSize() == (48, 40)  # our image survived the transform taking its copy
    p = ref.TransformIndexToPhysicalPoint((20, 21))
    assert np.abs(pix[21, 20]).max() > 0.01
    np.testing.assert_allclose(np.subtract(tx.TransformPoint(p), p), pix[21, 20] * [0.5, 2.0])
    assert W.max_safe_displacement(field) == pytest.approx(W.max_safe_displacement(pix))


def test_warp_stack_follows_the_paper_convention_and_matches_sitk():
    shape = (64, 64)
    yy, xx = np.indices(shape).astype(float)
    image = np.sin(xx / 6.0) + np.cos(yy / 9.0)
    warp = W.random_cps(shape, 2.0, n_knots=9, seed=5)
    out, _ = W.warp_stack(image[None], [warp])
    # I~(psi(p)) = I(p): for pixels q, solve psi(p) = q independently (scipy root finding)
    # and compare the output at q with the input interpolated at p
    from scipy.ndimage import map_coordinates
    from scipy.optimize import fsolve

    rng = np.random.default_rng(0)
    for qx, qy in rng.integers(8, 56, size=(25, 2)).astype(float):
        q = np.array([qx, qy])
        p = fsolve(lambda p, q=q: p + warp.displacement(p[None])[0] - q, q, xtol=1e-12)
        expected = map_coordinates(image, [[p[1]], [p[0]]], order=1)[0]
        assert out[0][int(qy), int(qx)] == pytest.approx(expected, abs=1e-5)  # tol 1e-5 px
    inner = inside_mask(shape)
    assert np.abs(image - out[0])[inner].max() > 0.1  # it did move
    # SimpleITK with the inverse field gives the same image
    img = sitk.GetImageFromArray(image)
    inv = W.cps_warp(shape, 2.0, n_knots=9, seed=5, inverse=True)
    res = sitk.Resample(img, img, sitk.DisplacementFieldTransform(sitk.Image(inv)), sitk.sitkLinear)
    np.testing.assert_allclose(sitk.GetArrayFromImage(res)[inner], out[0][inner], atol=1e-6)


def test_warp_stack_labels_are_memberships():
    rng = np.random.default_rng(0)
    labels = np.zeros((2, 40, 40), int)
    labels[:, 10:30, 12:25] = 1
    labels[:, 15:20, 15:35] = 2
    warps = [W.random_cps((40, 40), 1.5, n_knots=9, seed=s) for s in (1, 2)]
    images = rng.normal(size=labels.shape)
    _, m = W.warp_stack(images, warps, labels=labels)
    assert m.shape == (2, 3, 40, 40)
    np.testing.assert_allclose(m.sum(axis=1), 1.0, atol=1e-12)
    assert m.min() >= 0 and 0 < np.mean((m > 0) & (m < 1))
    # a one-pixel shift (resampling field v = +1 in x) moves every label left by one pixel
    v = np.zeros((1, 40, 40, 2))
    v[..., 0] = 1.0
    _, m1 = W.warp_stack(images[:1], v, labels=labels[:1])
    np.testing.assert_array_equal(m1[0, 1, :, :-1], (labels[0, :, 1:] == 1))
    with pytest.raises(ValueError, match="one warp per image"):
        W.warp_stack(images, warps[:1])
