"""The clamped-plate spline in unit-ball coordinates, and the ball it lives in on an image.

:func:`green` is the clamped-plate Green's function on the unit disk (2D, biharmonic) or
ball (3D, triharmonic; Boggio's formula), :class:`ClampedPlateSpline` the spline that
interpolates knot displacements with it, exactly zero outside the ball. :class:`BallFrame`
is that ball on a pixel grid: the inscribed circle / sphere *in mm*, with the maps between
pixel index and unit-ball coordinates. The random warps built from them, and the module's
conventions (ITK component order, pixels), are in :mod:`itk_nrreval.experiments.warps`. Pure numpy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg

from .._errors import readable

__all__ = [
    "CHUNK",
    "ClampedPlateSpline",
    "BallFrame",
    "green",
    "green_gradient",
    "as_points",
    "chunks",
    "check_shape",
    "check_spacing",
    "grid_points",
]

#: Pixels evaluated at once (bounds the (pixels x knots x dim) temporaries to ~40 MB).
CHUNK = 65_536
#: Below this, ``z - log1p(z)`` and ``log1p(z) - z / (1 + z)`` are summed as series.
_SERIES_Z = 1e-3
_SERIES_TERMS = 8


def _series(z: np.ndarray, coef) -> np.ndarray:
    """``sum_{k>=2} coef(k) (-z)^k`` by Horner, for small ``z``."""
    out = np.zeros_like(z)
    for k in range(_SERIES_TERMS, 1, -1):
        out = out * (-z) + coef(k)
    return out * z * z


def _kernel(x: np.ndarray, y: np.ndarray, *, gradient: bool):
    """Green's function and, optionally, the coefficients of its gradient.

    Returns ``G (n, K)`` and, with `gradient`, ``cq, cd (n, K)`` such that
    ``grad_x G = cq * (-2 x (1 - |y|^2)) + cd * (x - y)``. Rows of `x` must lie inside the
    unit ball (callers drop the others); `y` likewise.
    """
    xx = np.einsum("nd,nd->n", x, x)
    yy = np.einsum("kd,kd->k", y, y)
    r2 = np.maximum(xx[:, None] + yy[None, :] - 2.0 * (x @ y.T), 0.0)
    near = r2 < 1e-6  # the expansion loses digits near coincidence: recompute directly
    if near.any():
        i, k = np.nonzero(near)
        r2[i, k] = np.sum((x[i] - y[k]) ** 2, axis=1)
    q = (1.0 - xx)[:, None] * (1.0 - yy)[None, :]
    if x.shape[1] == 2:
        with np.errstate(divide="ignore", invalid="ignore"):
            z = q / r2
            log_a2 = np.log1p(z)  # ln A^2
            g = q - r2 * log_a2
            cq = z / (1.0 + z) if gradient else None  # dG/dq
        small = np.nonzero(z < _SERIES_Z)  # near the boundary: series, no cancellation
        if small[0].size:
            zs = z[small]
            g[small] = r2[small] * _series(zs, lambda k: 1.0 / k)
        coincident = np.nonzero(r2 == 0.0) if r2.size and r2.min() == 0.0 else (np.array([], int),)
        if coincident[0].size:  # exact limit (1 - |x|^2)^2 = q
            g[coincident] = q[coincident]
        if not gradient:
            return g, None, None
        cd = -2.0 * (log_a2 - cq)  # 2 dG/dR
        if small[0].size:
            cd[small] = -2.0 * _series(zs, lambda k: (k - 1.0) / k)
        if coincident[0].size:
            cq[coincident] = np.where(q[coincident] > 0, 1.0, 0.0)
            cd[coincident] = 0.0
        return g, cq, cd
    # 3D triharmonic: with s = sqrt(r^2 + q) = r A, A - 1 = q / (r (s + r)), and
    # A^3/3 - 2A - 1/A + 8/3 = (A - 1)^3 (A + 3) / (3 A):
    #   G = q^3 (s + 3 r) / (3 s (s + r)^3)          (no cancellation; s > 0 inside)
    #   dG/dq = q^2 / (2 s^3),   dG/dR = -q^3 (3 s + r) / (2 s^3 (s + r)^3),  R = r^2
    # (callers keep x and y strictly inside, so q > 0 and s > 0: no division by zero)
    r = np.sqrt(r2)
    s = np.sqrt(r2 + q)
    sr = s + r
    sr3 = sr * sr * sr
    q2 = q * q
    g = q2 * q * (s + 3.0 * r) / (3.0 * s * sr3)
    if not gradient:
        return g, None, None
    s3 = s * s * s
    cq = q2 / (2.0 * s3)
    cd = -(q2 * q) * (3.0 * s + r) / (s3 * sr3)  # 2 dG/dR
    return g, cq, cd


def _split(x, y):
    x, y = as_points(x), as_points(y)
    if x.shape[1] != y.shape[1] or x.shape[1] not in (2, 3):
        raise ValueError(
            f"x and y must be (n, 2) or (n, 3) with the same dim, got {x.shape} and {y.shape}"
        )
    xin = np.einsum("nd,nd->n", x, x) < 1.0
    yin = np.einsum("kd,kd->k", y, y) < 1.0
    return x, y, xin, yin


def green(x, y) -> np.ndarray:
    """The clamped-plate Green's function ``G(x, y)`` on the unit disk or ball.

    Parameters
    ----------
    x : array_like of shape (n, dim)
    y : array_like of shape (K, dim)
        Points in unit-ball coordinates, ``dim`` 2 or 3.

    Returns
    -------
    ndarray of shape (n, K)
        Zero where ``x`` or ``y`` lies on or outside the unit sphere.

    Notes
    -----
    With ``r = |x - y|``, ``A^2 = (|x|^2 |y|^2 - 2 x.y + 1) / r^2`` and
    ``q = (1 - |x|^2)(1 - |y|^2)`` (so that ``A^2 = 1 + q / r^2``), Boggio's Green's function
    of ``(-Delta)^m`` on the unit ball of R^n with clamped boundary conditions is, up to a
    positive constant, ``r^(2m - n) int_1^A (v^2 - 1)^(m - 1) v^(1 - n) dv``:

    * 2D, biharmonic (m = 2, the paper's): ``G = r^2 (A^2 - 1 - ln A^2)``
      ``= q - r^2 log1p(q / r^2)``, exact limit ``(1 - |x|^2)^2`` at ``x = y``;
      ``z - log1p(z)`` is summed as a series for small ``z = q / r^2`` (near the boundary).
      ``G = dG/dn = 0`` on the circle.
    * 3D, triharmonic (m = 3): ``G = r^3 (A^3/3 - 2 A - 1/A + 8/3)``, evaluated as the
      identical ``q^3 (s + 3 r) / (3 s (s + r)^3)`` with ``s = sqrt(r^2 + q)``, free of
      cancellation; exact limit ``(1 - |x|^2)^3 / 3`` at ``x = y``.
      ``G = dG/dn = d^2G/dn^2 = 0`` on the sphere (``G`` vanishes like the cube of the
      distance to it), ``Delta^3 G = 0`` away from ``y``, and ``G - 8 r^3 / 3`` is smooth,
      so ``G`` is C^2 (its third derivatives jump at ``x = y``).

    Both are symmetric and strictly positive definite as kernels (Green's functions of
    positive self-adjoint operators), so knot matrices are SPD.
    """
    x, y, xin, yin = _split(x, y)
    out = np.zeros((len(x), len(y)))
    out[np.ix_(xin, yin)] = _kernel(x[xin], y[yin], gradient=False)[0]
    return out


def green_gradient(x, y) -> np.ndarray:
    """Gradient of :func:`green` with respect to its first argument.

    Parameters
    ----------
    x : array_like of shape (n, dim)
    y : array_like of shape (K, dim)

    Returns
    -------
    ndarray of shape (n, K, dim)
        ``d G(x_i, y_k) / d x_i``; zero on and outside the unit sphere. Continuous
        everywhere, through ``x = y`` included.

    Notes
    -----
    With ``G = G(q, R)``, ``R = r^2``: ``dq/dx = -2 x (1 - |y|^2)``, ``dR/dx = 2 (x - y)``.
    2D: ``dG/dq = q / (R + q)``, ``dG/dR = -(log1p(z) - z / (1 + z))``.
    3D: ``dG/dq = q^2 / (2 s^3)``, ``dG/dR = -q^3 (3 s + r) / (2 s^3 (s + r)^3)``.
    """
    x, y, xin, yin = _split(x, y)
    out = np.zeros((len(x), len(y), x.shape[1]))
    xi, yi = x[xin], y[yin]
    _, cq, cd = _kernel(xi, yi, gradient=True)
    grad = cq[..., None] * (-2.0 * xi[:, None, :] * (1.0 - np.sum(yi * yi, 1))[None, :, None])
    grad += cd[..., None] * (xi[:, None, :] - yi[None, :, :])
    out[np.ix_(xin, yin)] = grad
    return out


def as_points(p) -> np.ndarray:
    """`p` as a float64 array of points (n, dim); ValueError for another shape."""
    p = np.asarray(p, dtype=np.float64)
    if p.ndim != 2:
        raise ValueError(f"points must be an array of shape (n, dim), got shape {p.shape}")
    return p


@dataclass(frozen=True)
class ClampedPlateSpline:
    """A clamped-plate spline interpolating knot displacements inside the unit ball.

    ``u(x) = sum_k w_k G(x, y_k)`` with ``G`` the clamped-plate Green's function
    (:func:`green`) and weights solving ``G(y_j, y_k) w = d`` (Cholesky).

    Attributes
    ----------
    knots : ndarray of shape (K, dim)
        Knot positions in unit-ball coordinates, strictly inside the unit sphere.
    weights : ndarray of shape (K, dim)
        Spline coefficients.

    Examples
    --------
    >>> import numpy as np
    >>> knots = np.array([[0.0, 0.0], [0.5, 0.0], [0.0, -0.5]])
    >>> moves = np.array([[0.1, 0.0], [0.0, 0.05], [0.0, 0.0]])
    >>> cps = ClampedPlateSpline.from_knots(knots, moves)
    >>> np.allclose(cps(knots), moves), cps(np.array([[1.0, 0.0], [2.0, 2.0]])).tolist()
    (True, [[0.0, 0.0], [0.0, 0.0]])
    """

    knots: np.ndarray = field(repr=False)
    weights: np.ndarray = field(repr=False)

    @classmethod
    def from_knots(cls, knots, displacements) -> ClampedPlateSpline:
        """Fit the spline taking each knot ``knots[k]`` to ``knots[k] + displacements[k]``.

        Parameters
        ----------
        knots : array_like of shape (K, dim)
            Distinct points with ``|knot| < 1``, ``dim`` 2 or 3.
        displacements : array_like of shape (K, dim)

        Raises
        ------
        ValueError
            Bad shapes, knots on or outside the unit sphere, or coincident knots (the knot
            matrix is then singular: the message says so).
        """
        knots = as_points(knots)
        disp = np.asarray(displacements, dtype=np.float64)
        if knots.shape[1] not in (2, 3):
            raise ValueError(f"knots must have 2 or 3 columns, got shape {knots.shape}")
        if disp.shape != knots.shape:
            raise ValueError(
                f"displacements must have the knots' shape {knots.shape}, got {disp.shape}"
            )
        radius = np.linalg.norm(knots, axis=1)
        if np.any(radius >= 1.0):
            k = int(np.argmax(radius))
            raise ValueError(
                f"knot {k} lies at radius {radius[k]:.4g}; knots must be inside the unit ball"
            )
        gram = green(knots, knots)
        try:
            factor = scipy.linalg.cho_factor(gram, lower=True)
        except np.linalg.LinAlgError:
            raise ValueError(
                "knot matrix is not positive definite: are two knots coincident?"
            ) from None
        weights = scipy.linalg.cho_solve(factor, disp)
        return cls(knots=knots, weights=weights)

    @property
    def dim(self) -> int:
        return int(self.knots.shape[1])

    def __call__(self, points) -> np.ndarray:
        """Displacements ``u(points)``, shape (n, dim); exactly zero outside the unit ball."""
        points = self._check(points)
        out = np.zeros_like(points)
        inside = np.flatnonzero(np.einsum("nd,nd->n", points, points) < 1.0)
        for sl in chunks(len(inside)):
            rows = inside[sl]
            out[rows] = _kernel(points[rows], self.knots, gradient=False)[0] @ self.weights
        return out

    def jacobian(self, points) -> np.ndarray:
        """Displacement gradient ``J[n, i, j] = d u_i / d x_j`` at `points`, (n, dim, dim)."""
        return self.value_and_jacobian(points)[1]

    def value_and_jacobian(self, points) -> tuple[np.ndarray, np.ndarray]:
        """``u(points)`` (n, dim) and its gradient (n, dim, dim) from one kernel pass."""
        points = self._check(points)
        dim = self.dim
        val = np.zeros_like(points)
        out = np.zeros((len(points), dim, dim))
        inside = np.flatnonzero(np.einsum("nd,nd->n", points, points) < 1.0)
        w, y = self.weights, self.knots
        wy = (w[:, :, None] * y[:, None, :]).reshape(len(y), dim * dim)
        oy = 1.0 - np.einsum("kd,kd->k", y, y)
        for sl in chunks(len(inside)):
            rows = inside[sl]
            x = points[rows]
            g, cq, cd = _kernel(x, y, gradient=True)
            val[rows] = g @ w
            # sum_k w_ki [cq (-2 x_j (1 - |y_k|^2)) + cd (x_j - y_kj)]
            a = cd @ w - 2.0 * ((cq * oy) @ w)
            out[rows] = a[:, :, None] * x[:, None, :] - (cd @ wy).reshape(-1, dim, dim)
        return val, out

    def _check(self, points) -> np.ndarray:
        points = as_points(points)
        if points.shape[1] != self.dim:
            raise ValueError(f"points must have {self.dim} columns, got shape {points.shape}")
        return points


def chunks(n: int):
    """Slices of ``range(n)`` of at most :data:`CHUNK` items, in order."""
    for start in range(0, n, CHUNK):
        yield slice(start, min(start + CHUNK, n))


def check_shape(shape) -> tuple[int, ...]:
    """A grid's numpy shape as ints; ValueError unless 2D or 3D with 3 pixels per axis."""
    shape = tuple(int(s) for s in shape)
    if len(shape) not in (2, 3) or min(shape) < 3:
        raise ValueError(f"shape must be 2D or 3D with at least 3 pixels per axis, got {shape}")
    return shape


def check_spacing(spacing, dim: int) -> tuple[float, ...]:
    """`dim` positive voxel sizes (mm, ITK order), all 1 for None; ValueError otherwise."""
    if spacing is None:
        return (1.0,) * dim
    try:
        out = tuple(float(s) for s in spacing)
    except TypeError:
        raise ValueError(
            f"spacing must be {dim} numbers (mm, ITK order), got {readable(spacing)}"
        ) from None
    if len(out) != dim or not all(math.isfinite(s) and s > 0 for s in out):
        raise ValueError(
            f"spacing must be {dim} positive numbers (mm, ITK order), got {readable(spacing)}"
        )
    return out


@dataclass(frozen=True)
class BallFrame:
    """The inscribed ball of a grid: pixel index <-> unit-ball coordinates (via mm)."""

    shape: tuple[int, ...]  # numpy order
    spacing: np.ndarray  # mm, ITK order
    centre: np.ndarray  # pixel index, ITK order
    radius: float  # mm

    @classmethod
    def of(cls, shape, spacing=None) -> BallFrame:
        shape = check_shape(shape)
        sp = np.array(check_spacing(spacing, len(shape)))
        size = np.array(shape[::-1], dtype=np.float64)
        return cls(shape, sp, (size - 1.0) / 2.0, float((size * sp).min()) / 2.0)

    @property
    def dim(self) -> int:
        return len(self.shape)

    def unit(self, points: np.ndarray) -> np.ndarray:
        """Pixel index points (n, dim) -> unit-ball coordinates."""
        return (points - self.centre) * (self.spacing / self.radius)

    def to_pixels(self, unit: np.ndarray) -> np.ndarray:
        """Unit-ball coordinates (n, dim) -> pixel index points."""
        return self.centre + unit * (self.radius / self.spacing)

    def grid(self) -> tuple[np.ndarray, np.ndarray]:
        """Unit coordinates of the pixel centres inside the ball (n_in, dim), and the flat
        indices (numpy C order) of those pixels."""
        unit = self.unit(grid_points(self.shape))
        inside = np.flatnonzero(np.einsum("nd,nd->n", unit, unit) < 1.0)
        return unit[inside], inside


def grid_points(shape: tuple[int, ...]) -> np.ndarray:
    """Pixel centres in ITK order ``(x, y[, z])``, flattened in numpy (C) order: (n, dim)."""
    axes = [np.arange(n, dtype=np.float64) for n in shape]
    grids = np.meshgrid(*axes, indexing="ij")
    return np.stack(grids[::-1], axis=-1).reshape(-1, len(shape))
