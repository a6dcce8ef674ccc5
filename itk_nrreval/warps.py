"""Random clamped-plate-spline (CPS) warps: the paper's perturbations (Section IV-B).

A clamped-plate spline (Twining & Marsland) deforms only the interior of the unit disk (2D)
or ball (3D); the displacement and its first derivatives vanish on the boundary, so the
warp is exactly the identity outside. On an image the unit ball is the inscribed circle /
sphere *in mm*: centred on the grid, radius half the grid's smallest physical extent, so an
anisotropic volume gets a ball, not an ellipsoid.

* 2D: the biharmonic clamped-plate spline, as in the paper. ``G`` is C^1 at the knots:
  the warp's Jacobian is continuous, its derivatives grow like ``log r`` near a knot.
* 3D: the *triharmonic* clamped-plate spline. The biharmonic 3D Green's function,
  ``r (A + 1/A - 2)``, has a cone point (``-2 r``) at every knot: its warps are only C^0
  there, the Jacobian jumps across each knot and folds hide between pixel centres. The
  triharmonic one, ``r^3 (A^3/3 - 2 A - 1/A + 8/3)`` (Boggio's formula), differs from a
  smooth function by ``8 r^3 / 3``: its warps are C^2 everywhere.

Conventions
-----------
* Points and displacement components are in ITK order ``(x, y[, z])``, in pixel index
  units unless stated, while grids are numpy arrays of shape ``(*spatial)`` in numpy order
  (``(z, y, x)``); a displacement array is ``(*spatial, dim)`` like
  ``sitk.GetArrayFromImage`` of a vector image. "mm" components are along the grid's axes
  (index displacement times spacing); the physical (LPS) vector is that rotated by the
  grid's direction matrix.
* A warp is the map ``psi(p) = p + u(p)``. The paper's perturbed image is defined by
  ``I~(psi(p)) = I(p)``, i.e. ``I~ = I o psi^-1``: the image content moves *with* ``u``.
* ITK resamples *pulling*: ``sitk.Resample`` with a ``DisplacementFieldTransform`` of
  field ``v`` gives ``out(p) = in(p + v(p))``. To make the paper's ``I~`` with ITK, give it
  the displacement of ``psi^-1`` (``cps_warp(..., inverse=True)``); :func:`warp_stack`
  does exactly that, with the inverse solved by Newton's method on the analytic spline.
* The mean displacement ``d`` is the mean over *all* pixels (inside and outside the ball)
  of ``|u|`` in pixel index units (the paper's "mean pixel displacement"); the same in mm
  is reported alongside.

Folding
-------
A warp is accepted when ``det(I + t grad u) >= min_jacobian`` for every ``t`` in
``[0, 1]`` (the whole family ``p + t u(p)`` up to the warp itself) at every check point:
all pixel centres, a sub-grid :data:`REFINE` times finer in every pixel cell around each
knot, and the same sub-grid in every cell whose corner determinants come near the threshold
(``2 min - max < min_jacobian``). The Jacobian is continuous (3D: continuously
differentiable), so within a cell the determinant moves little from its sampled values
except near a knot, which the sub-grid samples; a fold between pixel centres needs a dip
that the sub-grid sees. This is dense sampling, not a proof: the tests check accepted warps
on denser grids. :func:`max_safe_displacement` of a :class:`CPSWarp` uses exactly these
points.

Pure numpy numerics; SimpleITK only in :func:`cps_warp` and :func:`max_safe_displacement`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
import SimpleITK as sitk
from scipy import ndimage

from ._errors import readable

__all__ = [
    "ClampedPlateSpline",
    "CPSWarp",
    "FoldingError",
    "green",
    "green_gradient",
    "knot_positions",
    "random_cps",
    "cps_warp",
    "max_safe_displacement",
    "warp_stack",
    "MEMBERSHIP_TOLERANCE",
    "KNOT_RADIUS",
    "MIN_JACOBIAN",
    "REFINE",
    "KNOT_BOX",
]

#: Knots are placed within this fraction of the unit radius, away from the clamped boundary.
KNOT_RADIUS = 0.7
#: Pixels evaluated at once (bounds the (pixels x knots x dim) temporaries to ~40 MB).
_CHUNK = 65_536
#: Accepted warps have a Jacobian determinant at least this large at every check point.
MIN_JACOBIAN = 0.05
#: The fold check's sub-grid is this many times finer than the image (per axis).
REFINE = 4
#: ... and covers every pixel cell within this many pixels (per axis) of a knot.
KNOT_BOX = 0.5
#: Memberships may leave [0, 1] by this much (rounding); they are clipped. More is an error.
MEMBERSHIP_TOLERANCE = 1e-6
#: Below this, ``z - log1p(z)`` and ``log1p(z) - z / (1 + z)`` are summed as series.
_SERIES_Z = 1e-3
_SERIES_TERMS = 8
#: Sub-grid cells evaluated at once in the fold check (bounds its temporaries).
_CELL_CHUNK = 2048


class FoldingError(RuntimeError):
    """No random warp of the requested size stayed a diffeomorphism within ``max_tries``.

    Attributes
    ----------
    largest_safe, largest_safe_mm : float
        The largest mean displacement (pixels, mm) at which the best of the rejected draws
        would have been accepted (NaN when unknown).
    """

    def __init__(self, message: str, *, largest_safe: float = math.nan, largest_safe_mm=math.nan):
        super().__init__(message)
        self.largest_safe = float(largest_safe)
        self.largest_safe_mm = float(largest_safe_mm)


# ----------------------------------------------------------------------------------------
# Green's function
# ----------------------------------------------------------------------------------------


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
    x, y = _as_points(x), _as_points(y)
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


def _as_points(p) -> np.ndarray:
    p = np.asarray(p, dtype=np.float64)
    if p.ndim != 2:
        raise ValueError(f"points must be an array of shape (n, dim), got shape {p.shape}")
    return p


# ----------------------------------------------------------------------------------------
# The spline
# ----------------------------------------------------------------------------------------


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
        knots = _as_points(knots)
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
        for sl in _chunks(len(inside)):
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
        for sl in _chunks(len(inside)):
            rows = inside[sl]
            x = points[rows]
            g, cq, cd = _kernel(x, y, gradient=True)
            val[rows] = g @ w
            # sum_k w_ki [cq (-2 x_j (1 - |y_k|^2)) + cd (x_j - y_kj)]
            a = cd @ w - 2.0 * ((cq * oy) @ w)
            out[rows] = a[:, :, None] * x[:, None, :] - (cd @ wy).reshape(-1, dim, dim)
        return val, out

    def _check(self, points) -> np.ndarray:
        points = _as_points(points)
        if points.shape[1] != self.dim:
            raise ValueError(f"points must have {self.dim} columns, got shape {points.shape}")
        return points


def _chunks(n: int):
    for start in range(0, n, _CHUNK):
        yield slice(start, min(start + _CHUNK, n))


# ----------------------------------------------------------------------------------------
# Knots and random warps on an image grid
# ----------------------------------------------------------------------------------------


def knot_positions(n_knots: int, dim: int, *, radius: float = KNOT_RADIUS) -> np.ndarray:
    """Deterministic, evenly spread knot positions inside the unit disk / ball.

    Farthest-point sampling from a fine grid of candidates within `radius`, starting at the
    centre: every new knot is as far as possible from those already placed, so knots keep
    away from each other and (by `radius`) from the clamped boundary.

    Returns
    -------
    ndarray of shape (n_knots, dim)
        Unit-ball coordinates (multiply by the ball's radius for mm from its centre).
    """
    if not (isinstance(n_knots, (int, np.integer)) and n_knots >= 1):
        raise ValueError(f"n_knots must be a positive integer, got {readable(n_knots)}")
    if dim not in (2, 3):
        raise ValueError(f"dim must be 2 or 3, got {readable(dim)}")
    if not 0 < radius < 1:
        raise ValueError(f"radius must lie in (0, 1), got {readable(radius)}")
    per_axis = 81 if dim == 2 else 31
    axis = np.linspace(-radius, radius, per_axis)
    cand = np.stack(np.meshgrid(*([axis] * dim), indexing="ij"), axis=-1).reshape(-1, dim)
    cand = cand[np.einsum("nd,nd->n", cand, cand) <= radius**2 + 1e-12]
    if n_knots > len(cand) // 4:
        raise ValueError(
            f"n_knots={n_knots} is too many for a {dim}D ball (at most {len(cand) // 4})"
        )
    chosen = [int(np.argmin(np.einsum("nd,nd->n", cand, cand)))]
    dist = np.linalg.norm(cand - cand[chosen[0]], axis=1)
    for _ in range(n_knots - 1):
        k = int(np.argmax(dist))
        chosen.append(k)
        dist = np.minimum(dist, np.linalg.norm(cand - cand[k], axis=1))
    return cand[chosen].copy()


def _check_shape(shape) -> tuple[int, ...]:
    shape = tuple(int(s) for s in shape)
    if len(shape) not in (2, 3) or min(shape) < 3:
        raise ValueError(f"shape must be 2D or 3D with at least 3 pixels per axis, got {shape}")
    return shape


def _check_spacing(spacing, dim: int) -> tuple[float, ...]:
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
class _Frame:
    """The inscribed ball of a grid: pixel index <-> unit-ball coordinates (via mm)."""

    shape: tuple[int, ...]  # numpy order
    spacing: np.ndarray  # mm, ITK order
    centre: np.ndarray  # pixel index, ITK order
    radius: float  # mm

    @classmethod
    def of(cls, shape, spacing=None) -> _Frame:
        shape = _check_shape(shape)
        sp = np.array(_check_spacing(spacing, len(shape)))
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
        unit = self.unit(_grid_points(self.shape))
        inside = np.flatnonzero(np.einsum("nd,nd->n", unit, unit) < 1.0)
        return unit[inside], inside


def _grid_points(shape: tuple[int, ...]) -> np.ndarray:
    """Pixel centres in ITK order ``(x, y[, z])``, flattened in numpy (C) order: (n, dim)."""
    axes = [np.arange(n, dtype=np.float64) for n in shape]
    grids = np.meshgrid(*axes, indexing="ij")
    return np.stack(grids[::-1], axis=-1).reshape(-1, len(shape))


@dataclass(frozen=True)
class CPSWarp:
    """A CPS warp on a pixel grid: ``psi(p) = p + u(p)``.

    With ``c`` the grid centre (pixels), ``S`` the spacing (mm, ITK order) and ``R`` the
    radius (mm) of the inscribed ball, ``u(p) = scale * R * spline(S (p - c) / R) / S``
    (pixels, componentwise division): the spline acts in mm, so the ball and the knots are
    round in physical space whatever the spacing.

    Attributes
    ----------
    spline : ClampedPlateSpline or None
        The unscaled spline in unit-ball coordinates (None for the identity).
    shape : tuple of int
        Numpy shape of the grid, ``(ny, nx)`` or ``(nz, ny, nx)``.
    scale : float
        Factor applied to every displacement (the paper's ``d / d_hat``).
    mean_displacement : float
        ``d``: mean over all pixels of ``|psi(p) - p|`` in pixel index units.
    min_jacobian : float
        Smallest Jacobian determinant of ``psi`` over the fold check's points.
    spacing : tuple of float
        Voxel size in mm, ITK order (all ones when the grid had none).
    mean_displacement_mm : float
        The same mean in mm.
    """

    spline: ClampedPlateSpline | None
    shape: tuple[int, ...]
    scale: float
    mean_displacement: float
    min_jacobian: float
    spacing: tuple[float, ...] | None = None
    mean_displacement_mm: float | None = None
    # unscaled pixel displacements and unit-ball spline Jacobians at the pixels inside the
    # ball, kept from the draw so that field() and inverse_field() need no new evaluation
    _u: np.ndarray | None = field(default=None, repr=False, compare=False)
    _jac: np.ndarray | None = field(default=None, repr=False, compare=False)

    @property
    def dim(self) -> int:
        return len(self.shape)

    @property
    def _frame(self) -> _Frame:
        return _Frame.of(self.shape, self.spacing)

    @property
    def radius_mm(self) -> float:
        """Radius of the inscribed ball, mm."""
        return self._frame.radius

    @property
    def centre(self) -> np.ndarray:
        """Centre of the ball, pixel index, ITK order, shape (dim,)."""
        return self._frame.centre.copy()

    @property
    def knots(self) -> np.ndarray:
        """Knot positions in pixel index coordinates, ITK order, shape (K, dim)."""
        if self.spline is None:
            return np.zeros((0, self.dim))
        return self._frame.to_pixels(self.spline.knots)

    def _grid_values(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Inside flat indices (n_in,), scaled pixel displacements (n_in, dim), and scaled
        pixel Jacobians ``d u_i / d p_j`` (n_in, dim, dim) there."""
        frame = self._frame
        unit, inside = frame.grid()
        if self._u is None:
            u, jac = self.spline.value_and_jacobian(unit)
            u = u * (frame.radius / frame.spacing)
        else:
            u, jac = self._u, self._jac
        return inside, self.scale * u, self.scale * _pixel_jacobian(jac, frame.spacing)

    def displacement(self, points) -> np.ndarray:
        """``u(p) = psi(p) - p`` at `points` (n, dim), ITK order, pixels."""
        points = _as_points(points)
        if self.spline is None or self.scale == 0.0:
            return np.zeros_like(points)
        frame = self._frame
        return (self.scale * frame.radius / frame.spacing) * self.spline(frame.unit(points))

    def jacobian(self, points) -> np.ndarray:
        """``d u_i / d p_j`` at `points` (pixel index units), shape (n, dim, dim).

        ``det(I + jacobian)`` is the Jacobian determinant of ``psi`` (the same in pixels
        and in mm: the two differ by a similarity with the spacing matrix).
        """
        points = _as_points(points)
        if self.spline is None or self.scale == 0.0:
            return np.zeros((len(points), self.dim, self.dim))
        frame = self._frame
        jac = self.spline.jacobian(frame.unit(points))
        return self.scale * _pixel_jacobian(jac, frame.spacing)

    def field(self) -> np.ndarray:
        """The displacement of ``psi`` at every pixel: shape (*shape, dim), ITK order, pixels."""
        out = np.zeros((int(np.prod(self.shape)), self.dim))
        if self.spline is not None and self.scale != 0.0:
            inside, u, _ = self._grid_values()
            out[inside] = u
        return out.reshape(*self.shape, self.dim)

    def inverse_field(self, *, tol: float = 1e-5, max_iter: int = 50) -> np.ndarray:
        """The displacement ``v`` of ``psi^-1`` at every pixel: ``psi(p + v(p)) = p``.

        Damped Newton iterations on the sampled field and Jacobian (cubic and linear
        interpolation), then Newton steps with the exact spline residual until
        ``|psi(p + v) - p| < tol`` pixels. Outside the inscribed circle / sphere ``v = 0``
        exactly. This is the field ITK resampling needs to produce the paper's
        ``I~ = I o psi^-1``.

        Returns
        -------
        ndarray of shape (*shape, dim)
            ITK component order, pixels.

        Raises
        ------
        FoldingError
            If the iterations do not converge (the warp folds).
        """
        dim = self.dim
        out = np.zeros((int(np.prod(self.shape)), dim))
        if self.spline is None or self.scale == 0.0:
            return out.reshape(*self.shape, dim)
        points = _grid_points(self.shape)
        inside, u_in, jac_in = self._grid_values()
        u = np.zeros_like(points)
        u[inside] = u_in
        jac = np.zeros((len(points), dim, dim))
        jac[inside] = jac_in
        jac += np.eye(dim)
        # cubic B-spline coefficients of u (interpolation error ~1e-6 px for smooth warps)
        grid_u = [
            ndimage.spline_filter(g, order=3, mode="nearest")
            for g in np.moveaxis(u.reshape(*self.shape, dim), -1, 0)
        ]
        grid_j = np.moveaxis(jac.reshape(*self.shape, dim * dim), -1, 0)
        del jac
        target = points[inside]

        def sample(grid, p, order=1):
            coords = p[:, ::-1].T  # ITK (x, y, z) -> numpy axes
            return np.stack(
                [
                    ndimage.map_coordinates(g, coords, order=order, mode="nearest", prefilter=False)
                    for g in grid
                ],
                -1,
            )

        def resid_interp(p, t):
            return p + sample(grid_u, p, order=3) - t

        def resid_exact(p, t):
            return p + self.displacement(p) - t

        p = target - u[inside]
        for exact in (False, True):
            residual = resid_exact if exact else resid_interp
            goal = tol if exact else 0.1 * tol
            res = residual(p, target)
            norm = np.linalg.norm(res, axis=1)
            for _ in range(max_iter):
                act = np.flatnonzero(norm >= goal)  # iterate only where not yet converged
                if act.size == 0:
                    break
                pa, ta, ra, na = p[act], target[act], res[act], norm[act]
                step = _solve_small(sample(grid_j, pa).reshape(-1, dim, dim), ra)
                new = pa - step
                new_res = residual(new, ta)
                for _ in range(6):  # halve the step where the residual grew
                    worse = np.flatnonzero(np.linalg.norm(new_res, axis=1) > na)
                    if worse.size == 0:
                        break
                    step[worse] *= 0.5
                    new[worse] = pa[worse] - step[worse]
                    new_res[worse] = residual(new[worse], ta[worse])
                p[act], res[act], norm[act] = new, new_res, np.linalg.norm(new_res, axis=1)
            else:
                if exact or norm.max() > 1.0:
                    raise FoldingError(
                        f"inverting the warp did not converge (residual {norm.max():.3g} px): "
                        "does it fold?"
                    )
        out[inside] = p - target
        return out.reshape(*self.shape, dim)


def _pixel_jacobian(jac: np.ndarray, spacing: np.ndarray) -> np.ndarray:
    """Unit-ball spline Jacobians (n, dim, dim) -> ``d u_pix_i / d p_j = J_ij S_j / S_i``."""
    if np.all(spacing == spacing[0]):
        return jac
    return jac * (spacing[None, None, :] / spacing[None, :, None])


def _det(a: np.ndarray) -> np.ndarray:
    """Determinants of a stack of 2x2 or 3x3 matrices (n, dim, dim)."""
    if a.shape[-1] == 2:
        return a[:, 0, 0] * a[:, 1, 1] - a[:, 0, 1] * a[:, 1, 0]
    return np.einsum("nj,nj->n", a[:, 0, :], np.cross(a[:, 1, :], a[:, 2, :]))


def _solve_small(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Solve ``a[n] x[n] = b[n]`` for 2x2 or 3x3 matrices by Cramer's rule (n, dim)."""
    if a.shape[-1] == 2:
        det = a[:, 0, 0] * a[:, 1, 1] - a[:, 0, 1] * a[:, 1, 0]
        x0 = a[:, 1, 1] * b[:, 0] - a[:, 0, 1] * b[:, 1]
        x1 = a[:, 0, 0] * b[:, 1] - a[:, 1, 0] * b[:, 0]
        return np.stack([x0, x1], axis=1) / det[:, None]
    cof = np.cross(a[:, [1, 2, 0], :], a[:, [2, 0, 1], :])  # rows: cofactors of a's rows
    det = np.einsum("nj,nj->n", a[:, 0, :], cof[:, 0, :])
    return np.einsum("nij,ni->nj", cof, b) / det[:, None]


def _as_rng(seed) -> np.random.Generator:
    if isinstance(seed, np.random.Generator):
        return seed
    return np.random.default_rng(seed)


# ----------------------------------------------------------------------------------------
# The fold check
# ----------------------------------------------------------------------------------------


def _coefficients(jac: np.ndarray) -> list[np.ndarray]:
    """``c1 .. c_dim`` of ``det(I + t A) = 1 + c1 t + ... + c_dim t^dim`` per matrix:
    the trace, (3D) the sum of the principal 2x2 minors, and the determinant."""
    c1 = np.trace(jac, axis1=1, axis2=2)
    if jac.shape[-1] == 2:
        return [c1, _det(jac)]
    minors = (
        jac[:, 0, 0] * jac[:, 1, 1]
        - jac[:, 0, 1] * jac[:, 1, 0]
        + jac[:, 0, 0] * jac[:, 2, 2]
        - jac[:, 0, 2] * jac[:, 2, 0]
        + jac[:, 1, 1] * jac[:, 2, 2]
        - jac[:, 1, 2] * jac[:, 2, 1]
    )
    return [c1, minors, _det(jac)]


def _first_crossing(jac: np.ndarray, min_jacobian: float) -> np.ndarray:
    """Per matrix ``A`` of `jac` (n, dim, dim): the smallest ``t > 0`` with
    ``det(I + t A) = min_jacobian`` (inf when there is none).

    With ``w = 1 / t``: ``(1 - m) w^dim + c1 w^(dim-1) + ... + c_dim = 0`` (see
    :func:`_coefficients`), whose leading coefficient never vanishes; the smallest positive
    ``t`` is one over the largest positive real root ``w`` (companion-matrix eigenvalues).
    Near-double roots (the determinant only touching the threshold) count as crossings.
    """
    n, dim = len(jac), jac.shape[-1]
    if n == 0:
        return np.zeros(0)
    lead = 1.0 - min_jacobian
    comp = np.zeros((n, dim, dim))
    for k, c in enumerate(_coefficients(jac)):
        comp[:, 0, k] = -c / lead
    for k in range(1, dim):
        comp[:, k, k - 1] = 1.0
    w = np.linalg.eigvals(comp)
    real = np.abs(w.imag) <= 1e-6 * np.maximum(np.abs(w.real), 1e-300)
    pos = np.where(real & (w.real > 0), w.real, 0.0).max(axis=1)
    with np.errstate(divide="ignore"):
        return np.where(pos > 0, 1.0 / pos, np.inf)


def _dips_below(jac: np.ndarray, min_jacobian: float, span: float) -> np.ndarray:
    """Whether ``det(I + t A) < min_jacobian`` for some ``t`` in ``[0, span]``, per matrix:
    the polynomial's minimum over the interval, at its ends and its real critical points
    (closed form, no eigenvalues)."""
    coef = _coefficients(jac)

    def p(t):
        out = (1.0 - min_jacobian) + coef[0] * t
        for k, c in enumerate(coef[1:], start=2):
            out = out + c * t**k
        return out

    low = np.minimum(1.0 - min_jacobian, p(np.full(len(jac), span)))  # p(0) = 1 - m
    with np.errstate(divide="ignore", invalid="ignore"):
        if len(coef) == 2:  # p' = c1 + 2 c2 t
            crit = [-coef[0] / (2.0 * coef[1])]
        else:  # p' = c1 + 2 c2 t + 3 c3 t^2, roots by the stable quadratic formula
            c1, c2, c3 = coef
            disc = np.sqrt(np.maximum(c2 * c2 - 3.0 * c3 * c1, 0.0))
            qq = -(c2 + np.copysign(disc, c2))
            crit = [qq / (3.0 * c3), c1 / qq]
        for t in crit:
            ok = np.isfinite(t) & (t > 0) & (t < span)
            low = np.where(ok, np.minimum(low, p(np.where(ok, t, 0.0))), low)
    return low < 0.0


def _safe_scale(jac: np.ndarray, min_jacobian: float = 0.0, *, cap: float = np.inf) -> float:
    """``min(cap, largest t)`` with ``det(I + s A) >= min_jacobian`` for every ``s`` in
    ``[0, t]`` and every ``A`` in `jac` (n, dim, dim).

    Exact below `cap`. With a finite `cap`, only the matrices whose determinant dips below
    the threshold within ``[0, cap]`` (:func:`_dips_below`) are solved exactly. Otherwise
    matrices are visited in order of the lower bound ``(1 - m^(1/dim)) / |A|_F`` on their
    own ``t`` (every eigenvalue has modulus at most ``|A|_F``, so
    ``det(I + s A) >= (1 - s |A|_F)^dim``), and the search stops once that bound reaches
    the smallest ``t`` found.
    """
    if len(jac) == 0:
        return float(cap)
    if np.isfinite(cap):
        dips = np.flatnonzero(_dips_below(jac, min_jacobian, cap))
        if dips.size == 0:
            return float(cap)
        return min(float(cap), float(_first_crossing(jac[dips], min_jacobian).min()))
    dim = jac.shape[-1]
    norm = np.sqrt(np.einsum("nij,nij->n", jac, jac))
    with np.errstate(divide="ignore"):
        bound = (1.0 - min_jacobian ** (1.0 / dim)) / norm
    order = np.argsort(bound, kind="stable")
    best = float(cap)
    for start in range(0, len(order), 8192):
        idx = order[start : start + 8192]
        if bound[idx[0]] >= best:
            break
        best = min(best, float(_first_crossing(jac[idx], min_jacobian).min()))
    return best


def _cells_near_knots(frame: _Frame, knots_px: np.ndarray) -> np.ndarray:
    """Boolean mask over pixel cells (numpy shape ``n - 1`` per axis, a cell named by its
    lowest corner) of the cells within :data:`KNOT_BOX` pixels of a knot."""
    cells = np.zeros(tuple(n - 1 for n in frame.shape), dtype=bool)
    for p in knots_px[:, ::-1]:  # numpy axis order
        lo = np.clip(np.floor(p - KNOT_BOX).astype(int), 0, np.array(cells.shape) - 1)
        hi = np.clip(np.floor(p + KNOT_BOX).astype(int), 0, np.array(cells.shape) - 1)
        cells[tuple(slice(a, b + 1) for a, b in zip(lo, hi, strict=True))] = True
    return cells


def _cells_near_threshold(det_grid: np.ndarray, min_jacobian: float) -> np.ndarray:
    """Cells whose corner determinants satisfy ``2 min - max < min_jacobian``: the linear
    trend across the cell, continued for one more cell, would cross the threshold."""
    dim = det_grid.ndim
    lo = hi = None
    for corner in np.ndindex(*([2] * dim)):
        v = det_grid[
            tuple(slice(b, n - 1 + b) for b, n in zip(corner, det_grid.shape, strict=True))
        ]
        lo = v if lo is None else np.minimum(lo, v)
        hi = v if hi is None else np.maximum(hi, v)
    return 2.0 * lo - hi < min_jacobian


def _subgrid_offsets(dim: int) -> np.ndarray:
    """Offsets (numpy order) of the sub-grid points of one cell, corners (pixel centres,
    checked already) left out: ``(REFINE + 1)^dim - 2^dim`` points."""
    a = np.arange(REFINE + 1) / REFINE
    offs = np.stack(np.meshgrid(*([a] * dim), indexing="ij"), -1).reshape(-1, dim)
    corner = np.all((offs == 0) | (offs == 1), axis=1)
    return offs[~corner]


def _subgrid_safety(
    spline: ClampedPlateSpline,
    frame: _Frame,
    cells: np.ndarray,
    scale: float,
    min_jacobian: float,
    *,
    cap: float,
) -> tuple[float, float]:
    """Over the sub-grid of the masked `cells`: ``_safe_scale`` of ``scale * J`` (capped)
    and the smallest ``det(I + scale J)``. Chunked over cells."""
    corners = np.argwhere(cells).astype(np.float64)
    offs = _subgrid_offsets(frame.dim)
    t, min_det = float(cap), np.inf
    for start in range(0, len(corners), _CELL_CHUNK):
        pts = (corners[start : start + _CELL_CHUNK, None, :] + offs[None]).reshape(-1, frame.dim)
        unit = frame.unit(pts[:, ::-1])
        unit = unit[np.einsum("nd,nd->n", unit, unit) < 1.0]
        if not len(unit):
            continue
        jac = scale * spline.jacobian(unit)
        min_det = min(min_det, float(_det(jac + np.eye(frame.dim)).min()))
        t = min(t, _safe_scale(jac, min_jacobian, cap=t))
    return t, min_det


def _safety(
    spline: ClampedPlateSpline,
    frame: _Frame,
    jac_in: np.ndarray,
    inside: np.ndarray,
    scale: float,
    min_jacobian: float,
    *,
    cap: float = np.inf,
) -> tuple[float, float]:
    """The fold check of a spline scaled by `scale`: ``(t, min_det)``.

    ``t`` is ``min(cap, largest multiplier)`` such that ``det(I + s scale J) >= min_jacobian``
    for every ``s <= t`` at every check point (pixel centres, the sub-grid around the knots,
    the sub-grid of the cells near the threshold at ``scale`` and at ``t scale``); the warp
    is acceptable when ``t >= 1``. ``min_det`` is the smallest ``det(I + scale J)`` over the
    points checked at ``scale`` (pixel centres, knot and threshold cells).

    `jac_in` are the unscaled unit-ball Jacobians at the pixel centres inside the ball
    (flat indices `inside`); the determinant is the same in unit-ball, mm and pixel units.
    """
    eye = np.eye(frame.dim)
    accept_only = cap <= 1.0  # only whether t >= 1 matters: stop at the first failure
    t = _safe_scale(scale * jac_in, min_jacobian, cap=cap)
    det_in = _det(scale * jac_in + eye)
    min_det = float(det_in.min()) if len(det_in) else 1.0
    if accept_only and t < 1.0:  # fails at the pixel centres already
        return t, min_det
    checked = _cells_near_knots(frame, frame.to_pixels(spline.knots))
    tk, dk = _subgrid_safety(spline, frame, checked, scale, min_jacobian, cap=t)
    t, min_det = min(t, tk), min(min_det, dk)
    # the multiplier at which the cells near the threshold are chosen: the warp itself,
    # unless it folds already (then where it would start to fold)
    level = min(1.0, t)
    for _ in range(6):
        if accept_only and t < 1.0:
            break
        det_grid = np.ones(frame.shape)
        det_grid.flat[inside] = _det(level * scale * jac_in + eye)
        cells = _cells_near_threshold(det_grid, min_jacobian) & ~checked
        if cells.any():
            ts, ds = _subgrid_safety(spline, frame, cells, scale, min_jacobian, cap=t)
            if level == 1.0:
                min_det = min(min_det, ds)
            checked |= cells
            t = min(t, ts)
        if not np.isfinite(t) or abs(t - level) <= 1e-9 * t:
            break
        level = t  # where the warp would fold: look at the cells near the threshold there
    return t, min_det


def random_cps(
    shape: Sequence[int],
    mean_displacement: float,
    *,
    spacing: Sequence[float] | None = None,
    n_knots: int = 25,
    seed: int | np.random.Generator | None = None,
    max_tries: int = 50,
    min_jacobian: float = MIN_JACOBIAN,
) -> CPSWarp:
    """Draw a random CPS warp of exactly the given mean pixel displacement.

    Knots (:func:`knot_positions`, in the inscribed ball in mm) are moved by independent
    isotropic normal steps, the spline is evaluated at every pixel and all displacements
    are scaled by ``d / d_hat`` so that the mean of ``|psi(p) - p|`` (pixel index units)
    over *all* pixels (inside and outside the ball) is exactly `mean_displacement`. A
    draw that fails the fold check (module docstring: ``det(I + t grad u) >=
    min_jacobian`` for all ``t`` in [0, 1] at the pixel centres and on a sub-grid
    :data:`REFINE` times finer near the knots and wherever the determinant comes near the
    threshold) is redrawn.

    Parameters
    ----------
    shape : sequence of int
        Numpy shape of the grid, ``(ny, nx)`` or ``(nz, ny, nx)``.
    mean_displacement : float
        ``d`` in pixels, ``>= 0``. ``0`` gives the identity.
    spacing : sequence of float, optional
        Voxel size in mm, ITK order ``(x, y[, z])``; default 1 along every axis. The ball
        and the knots are placed in mm.
    n_knots : int
        Number of knots.
    seed : int, numpy.random.Generator or None
        Randomness; the same seed gives the same warp.
    max_tries : int
        Draws before giving up.
    min_jacobian : float
        Acceptance threshold on ``det(I + du/dp)`` in ``[0, 1)``.

    Returns
    -------
    CPSWarp

    Raises
    ------
    FoldingError
        When all `max_tries` draws fold; the message (and the exception's
        ``largest_safe`` / ``largest_safe_mm``) gives the largest ``d`` at which the best
        draw would have been accepted.

    Notes
    -----
    How large ``d`` can be is a matter of geometry more than of the kernel: a single
    knot at the centre gives in 3D a bump ``(1 - rho)^3 (1 + 3 rho)`` that folds when its
    amplitude reaches ``9/16`` of the radius, at a mean displacement inside the ball of
    ``0.064 R``; times the fraction of the grid inside the ball (0.39 for 40 x 44 x 36),
    ``d <= 0.45`` px for ``R = 18`` px. (2D biharmonic: ``0.17 R`` inside the disk,
    ``d <= 9.4`` px on 141 x 141.) Random knot steps fold sooner.
    """
    frame = _Frame.of(shape, spacing)
    shape = frame.shape
    d = float(mean_displacement)
    if not (np.isfinite(d) and d >= 0):
        raise ValueError(
            f"mean_displacement must be a finite number >= 0, got {readable(mean_displacement)}"
        )
    if not (isinstance(max_tries, (int, np.integer)) and max_tries >= 1):
        raise ValueError(f"max_tries must be a positive integer, got {readable(max_tries)}")
    if not 0 <= min_jacobian < 1:
        raise ValueError(f"min_jacobian must lie in [0, 1), got {readable(min_jacobian)}")
    dim = len(shape)
    knots = knot_positions(n_knots, dim)
    rng = _as_rng(seed)
    sp = tuple(float(s) for s in frame.spacing)
    if d == 0.0:
        return CPSWarp(None, shape, 0.0, 0.0, 1.0, sp, 0.0)
    unit, inside = frame.grid()
    n_pix = int(np.prod(shape))
    to_px = frame.radius / frame.spacing
    best = (-1.0, None)
    for _ in range(max_tries):
        spline = ClampedPlateSpline.from_knots(knots, rng.normal(size=knots.shape))
        u, jac = spline.value_and_jacobian(unit)
        d_hat = np.linalg.norm(u * to_px, axis=1).sum() / n_pix
        if d_hat == 0.0:
            continue
        scale = d / d_hat  # pixel displacement = scale * R * spline(unit) / S
        t, min_det = _safety(spline, frame, jac, inside, scale, min_jacobian, cap=1.0)
        if t >= 1.0:
            d_mm = scale * frame.radius * np.linalg.norm(u, axis=1).sum() / n_pix
            return CPSWarp(
                spline, shape, scale, d, min(min_det, 1.0), sp, float(d_mm),
                _u=u * to_px, _jac=jac,
            )  # fmt: skip
        if t * d > best[0]:
            best = (t * d, (spline, jac, scale, d_hat, u))
    largest, largest_mm = math.nan, math.nan
    if best[1] is not None:  # the best draw's exact safe d (cap lifted)
        spline, jac, scale, d_hat, u = best[1]
        t, _ = _safety(spline, frame, jac, inside, scale, min_jacobian)
        largest = t * d
        largest_mm = largest * np.linalg.norm(u, axis=1).sum() * frame.radius / (n_pix * d_hat)
    raise FoldingError(
        f"all {max_tries} random CPS warps of mean displacement {d:g} px fold on a "
        f"{'x'.join(map(str, shape[::-1]))} grid (the best would be accepted up to "
        f"d = {largest:.3g} px = {largest_mm:.3g} mm); lower mean_displacement, use fewer "
        "knots, or raise max_tries",
        largest_safe=largest,
        largest_safe_mm=largest_mm,
    )


# ----------------------------------------------------------------------------------------
# SimpleITK edge
# ----------------------------------------------------------------------------------------


def _reference_grid(reference) -> tuple[tuple[int, ...], sitk.Image | None]:
    if isinstance(reference, sitk.Image):
        return tuple(reversed(reference.GetSize())), reference
    try:
        shape = tuple(int(s) for s in reference)
    except TypeError:
        raise ValueError(
            "reference must be a SimpleITK image or a numpy shape tuple, "
            f"got {type(reference).__name__}"
        ) from None
    return shape, None


def _to_sitk_field(arr: np.ndarray, reference: sitk.Image | None) -> sitk.Image:
    """Pixel-unit displacements (ITK order) -> physical VectorFloat64 image on `reference`."""
    if reference is not None:
        dim = reference.GetDimension()
        m = np.array(reference.GetDirection()).reshape(dim, dim) * np.array(reference.GetSpacing())
        arr = arr @ m.T
    img = sitk.GetImageFromArray(np.ascontiguousarray(arr, dtype=np.float64), isVector=True)
    if reference is not None:
        img.CopyInformation(reference)
    return img


def cps_warp(
    reference,
    mean_displacement: float,
    *,
    n_knots: int = 25,
    seed: int | np.random.Generator | None = None,
    max_tries: int = 50,
    inverse: bool = False,
) -> sitk.Image:
    """A random CPS displacement field of exact mean displacement, as a SimpleITK image.

    Parameters
    ----------
    reference : sitk.Image or tuple of int
        The grid: an image (its size, spacing, origin and direction are used; the ball is
        round in mm) or a numpy shape ``(ny, nx)`` / ``(nz, ny, nx)`` (unit spacing, zero
        origin).
    mean_displacement : float
        ``d``: mean over all pixels of ``|psi(p) - p|``, in pixels (index units).
    n_knots, seed, max_tries
        As :func:`random_cps`.
    inverse : bool
        False: the displacement ``u`` of ``psi`` itself (mean exactly ``d`` pixels).
        True: the displacement of ``psi^-1``, the field to resample with, so that
        ``sitk.Resample(image, sitk.DisplacementFieldTransform(sitk.Image(field)))`` gives
        the paper's perturbed image ``I~(psi(p)) = I(p)``.

    Returns
    -------
    sitk.Image
        ``sitkVectorFloat64`` on `reference`'s grid, physical displacements (pixel
        displacement times spacing, rotated by the direction; equal to pixels at unit
        spacing). ``sitk.DisplacementFieldTransform`` consumes its input: pass a copy.

    Examples
    --------
    >>> import SimpleITK as sitk
    >>> f = cps_warp((64, 64), 1.5, seed=0)
    >>> f.GetPixelIDTypeAsString(), f.GetSize()
    ('vector of 64-bit float', (64, 64))
    >>> tx = sitk.DisplacementFieldTransform(sitk.Image(f))
    """
    shape, ref = _reference_grid(reference)
    spacing = None if ref is None else ref.GetSpacing()
    warp = random_cps(
        shape, mean_displacement, spacing=spacing, n_knots=n_knots, seed=seed, max_tries=max_tries
    )
    arr = warp.inverse_field() if inverse else warp.field()
    return _to_sitk_field(arr, ref)


def _field_pixels(field) -> np.ndarray:
    """A displacement field as (*shape, dim) pixel units, ITK component order."""
    if isinstance(field, sitk.Image):
        dim = field.GetDimension()
        if field.GetNumberOfComponentsPerPixel() != dim:
            raise ValueError(
                f"field must have {dim} components per pixel, "
                f"got {field.GetNumberOfComponentsPerPixel()}"
            )
        arr = sitk.GetArrayFromImage(field).astype(np.float64)
        m = np.array(field.GetDirection()).reshape(dim, dim) * np.array(field.GetSpacing())
        return arr @ np.linalg.inv(m).T
    arr = np.asarray(field, dtype=np.float64)
    if arr.ndim not in (3, 4) or arr.shape[-1] != arr.ndim - 1:
        raise ValueError(f"field must be an array of shape (*spatial, dim), got {arr.shape}")
    return arr


def max_safe_displacement(field, *, min_jacobian: float = 0.0) -> float:
    """The largest mean displacement for which this warp's shape passes the fold check.

    The displacement ``u`` is scaled by ``t``; ``psi_t(p) = p + t u(p)`` is acceptable
    while ``det(I + s grad u) >= min_jacobian`` for every ``s <= t`` at every check point.
    Returns ``t* * mean |u|`` in pixels (index units), or ``inf`` when no scaling folds.

    Parameters
    ----------
    field : CPSWarp, sitk.Image or array_like of shape (*spatial, dim)
        A :class:`CPSWarp`: its analytic Jacobian at the fold check's points (pixel centres,
        the sub-grid around the knots and near the threshold), so that a warp drawn by
        :func:`random_cps` with the same `min_jacobian` has ``max_safe_displacement >= d``.
        A displacement field (physical units for an image, pixels for an array; ITK
        component order): central differences at the pixel centres only.
    min_jacobian : float
        The threshold in ``[0, 1)``; 0 asks when the warp would fold.

    Returns
    -------
    float
        Pixels (mean over all pixels of ``|u|`` times ``t*``). For a :class:`CPSWarp`
        multiply by ``warp.mean_displacement_mm / warp.mean_displacement`` for mm.
    """
    if not 0 <= min_jacobian < 1:
        raise ValueError(f"min_jacobian must lie in [0, 1), got {readable(min_jacobian)}")
    if isinstance(field, CPSWarp):
        if field.spline is None or field.scale == 0.0:
            return float("inf")
        frame = field._frame
        unit, inside = frame.grid()
        jac = field._jac if field._jac is not None else field.spline.jacobian(unit)
        t, _ = _safety(field.spline, frame, jac, inside, field.scale, min_jacobian)
        return t * field.mean_displacement
    arr = _field_pixels(field)
    dim = arr.shape[-1]
    mean = float(np.linalg.norm(arr, axis=-1).mean())
    if mean == 0.0:
        return float("inf")
    # grad[..., i, j] = d u_i / d x_j, x_j ITK axis j = numpy axis dim - 1 - j
    grads = np.gradient(arr, axis=tuple(range(dim)))
    jac = np.stack([grads[dim - 1 - j] for j in range(dim)], axis=-1).reshape(-1, dim, dim)
    return mean * _safe_scale(jac, min_jacobian)


# ----------------------------------------------------------------------------------------
# Warping images and labels
# ----------------------------------------------------------------------------------------


def warp_stack(images, warps, *, labels=None, n_labels: int | None = None, label_values=None):
    """Perturb N images (and their labels) with one warp each, the paper's way.

    Output ``I~_i(p) = I_i(psi_i^-1(p))`` (so that ``I~_i(psi_i(p)) = I_i(p)``), by
    bilinear / trilinear interpolation; outside the grid the nearest edge value is used
    (the warps are the identity near the edge anyway). Labels are warped as one-hot
    memberships, each channel interpolated linearly (memberships still sum to 1).

    Parameters
    ----------
    images : ndarray of shape (n_images, *spatial)
        Numpy order, any real dtype (computed in float64).
    warps : sequence of CPSWarp, or ndarray of shape (n_images, *spatial, dim)
        One per image. Arrays are *resampling* fields ``v`` (ITK convention: the output at
        ``p`` is read at ``p + v(p)``; pixels, ITK component order), e.g. the
        ``inverse_field()`` of a warp.
    labels : ndarray, optional
        Integer label maps of shape (n_images, *spatial), or floating memberships of shape
        (n_images, n_labels, *spatial) in [0, 1] (values up to
        :data:`MEMBERSHIP_TOLERANCE` outside are rounding and are clipped).
    n_labels : int, optional
        Integer maps hold ``0 .. n_labels - 1``; channel k is label value k (default
        ``labels.max() + 1``).
    label_values : sequence of int, optional
        Instead of `n_labels`: channel k is label value ``label_values[k]`` (distinct), so
        that large, sparse values (FreeSurfer's up to 14175) need one channel each, not
        ``max + 1``. Every value in `labels` must be listed.

    Returns
    -------
    images : ndarray of shape (n_images, *spatial), float64
    memberships : ndarray of shape (n_images, n_labels, *spatial), float64, or None
        In [0, 1] exactly (interpolation rounding clipped).
    """
    images = np.asarray(images, dtype=np.float64)
    n, spatial = images.shape[0], images.shape[1:]
    dim = len(spatial)
    if dim not in (2, 3):
        raise ValueError(
            f"images must be (n_images, *spatial) with 2 or 3 spatial axes, got {images.shape}"
        )
    if len(warps) != n:
        raise ValueError(f"need one warp per image: {n} images, {len(warps)} warps")
    if n_labels is not None and label_values is not None:
        raise ValueError("give n_labels or label_values, not both")
    fuzzy = labels is not None and np.issubdtype(np.asarray(labels).dtype, np.floating)
    codes = None
    if fuzzy:
        labels = np.asarray(labels)
        if labels.ndim != images.ndim + 1 or labels.shape[2:] != spatial or len(labels) != n:
            raise ValueError(
                f"memberships must have shape (n_images, n_labels, *spatial) = "
                f"({n}, L, {', '.join(map(str, spatial))}), got {labels.shape}"
            )
        lo, hi = float(labels.min()), float(labels.max())
        if lo < -MEMBERSHIP_TOLERANCE or hi > 1.0 + MEMBERSHIP_TOLERANCE:
            raise ValueError(
                f"memberships must lie in [0, 1], got values from {lo:.9g} to {hi:.9g}"
            )
        n_labels = labels.shape[1]
    elif labels is not None:
        labels = np.asarray(labels)
        if labels.shape != images.shape:
            raise ValueError(
                f"labels shape {labels.shape} differs from images shape {images.shape}"
            )
        if not np.issubdtype(labels.dtype, np.integer) or labels.min() < 0:
            raise ValueError("labels must be non-negative integers")
        if label_values is not None:
            values = np.asarray(label_values, dtype=np.int64).ravel()
            if values.size == 0 or np.unique(values).size != values.size:
                raise ValueError(
                    f"label_values must be distinct integers, got {readable(label_values)}"
                )
            order = np.argsort(values)
            pos = np.clip(np.searchsorted(values[order], labels), 0, values.size - 1)
            found = values[order][pos] == labels
            if not found.all():
                bad = int(labels[~found].flat[0])
                raise ValueError(f"labels has value {bad}, which is not in label_values")
            codes = order[pos]  # channel index of every voxel
            n_labels = values.size
        else:
            n_labels = int(labels.max()) + 1 if n_labels is None else int(n_labels)
            if labels.max() >= n_labels:
                raise ValueError(f"labels has value {int(labels.max())} >= n_labels={n_labels}")
            codes = labels
    index = np.stack(np.meshgrid(*[np.arange(s, dtype=np.float64) for s in spatial], indexing="ij"))
    out = np.empty_like(images)
    members = None if labels is None else np.empty((n, n_labels, *spatial))
    for i, w in enumerate(warps):
        v = w.inverse_field() if isinstance(w, CPSWarp) else np.asarray(w, dtype=np.float64)
        if v.shape != (*spatial, dim):
            raise ValueError(f"warp {i}: field shape {v.shape} differs from {(*spatial, dim)}")
        coords = (index + np.moveaxis(v[..., ::-1], -1, 0)).reshape(dim, -1)  # ITK -> numpy
        del v
        if labels is None:
            channels = images[i][None]
        elif fuzzy:
            channels = np.concatenate([images[i][None], np.clip(labels[i], 0.0, 1.0)])
        else:
            onehot = codes[i][None] == np.arange(n_labels).reshape(-1, *([1] * dim))
            channels = np.concatenate([images[i][None], onehot.astype(np.float64)])
        sampled = _linear_sample(channels, coords).reshape(-1, *spatial)
        out[i] = sampled[0]
        if labels is not None:
            # convex combinations of values in [0, 1]: only rounding can leave the range
            np.clip(sampled[1:], 0.0, 1.0, out=members[i])
    return out, members


def _linear_sample(channels: np.ndarray, coords: np.ndarray) -> np.ndarray:
    """Bilinear / trilinear interpolation of every channel at the same points.

    Equivalent to ``ndimage.map_coordinates(c, coords, order=1, mode="nearest")`` per
    channel, with the weights computed once. `channels` (C, *spatial); `coords` (dim, n) in
    numpy axis order; returns (C, n), float64. Chunked over the points.
    """
    spatial = channels.shape[1:]
    flat = channels.reshape(len(channels), -1)
    strides = []
    stride = 1
    for a in reversed(range(len(spatial))):
        strides.insert(0, stride)
        stride *= spatial[a]
    n = coords.shape[1]
    out = np.empty((len(channels), n))
    for sl in _chunks(n):
        base, frac = [], []
        for a, size in enumerate(spatial):
            c = np.clip(coords[a, sl], 0.0, size - 1.0)
            i0 = np.minimum(np.floor(c).astype(np.intp), max(size - 2, 0))
            base.append(i0)
            frac.append(c - i0)
        acc = np.zeros((len(channels), sl.stop - sl.start))
        for corner in np.ndindex(*([2] * len(spatial))):
            w = np.ones(sl.stop - sl.start)
            idx = np.zeros(sl.stop - sl.start, dtype=np.intp)
            for a, bit in enumerate(corner):
                w *= frac[a] if bit else 1.0 - frac[a]
                idx += (base[a] + bit) * strides[a]
            acc += flat[:, idx] * w
        out[:, sl] = acc
    return out
