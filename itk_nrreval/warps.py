"""Random clamped-plate-spline (CPS) warps: the paper's perturbations (Section IV-B).

The biharmonic clamped-plate spline (Twining & Marsland) deforms only the interior of the
unit disk (2D) or ball (3D); the displacement and its gradient vanish on the boundary, so
the warp is C^1 and is exactly the identity outside. On an image the unit disk is the
inscribed circle / sphere: centred on the image, radius half its smallest side, in pixels.

Conventions
-----------
* Points and displacement components are in ITK order ``(x, y[, z])`` (pixel index units
  unless stated), while grids are numpy arrays of shape ``(*spatial)`` in numpy order
  (``(z, y, x)``); a displacement array is ``(*spatial, dim)`` like
  ``sitk.GetArrayFromImage`` of a vector image.
* A warp is the map ``psi(p) = p + u(p)``. The paper's perturbed image is defined by
  ``I~(psi(p)) = I(p)``, i.e. ``I~ = I o psi^-1``: the image content moves *with* ``u``.
* ITK resamples *pulling*: ``sitk.Resample`` with a ``DisplacementFieldTransform`` of
  field ``v`` gives ``out(p) = in(p + v(p))``. To make the paper's ``I~`` with ITK, give it
  the displacement of ``psi^-1`` (``cps_warp(..., inverse=True)``); :func:`warp_stack`
  does exactly that, with the inverse solved by Newton's method on the analytic spline.

Pure numpy numerics; SimpleITK only in :func:`cps_warp` and :func:`max_safe_displacement`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
import SimpleITK as sitk
from scipy import ndimage

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
]

#: Knots are placed within this fraction of the unit radius, away from the clamped boundary.
KNOT_RADIUS = 0.7
#: Pixels evaluated at once (bounds the (pixels x knots x dim) temporaries to ~40 MB).
CHUNK = 65_536
#: Accepted warps have a Jacobian determinant at least this large at every pixel centre.
MIN_JACOBIAN = 0.05
#: Below this, ``z - log1p(z)`` and ``log1p(z) - z / (1 + z)`` are summed as series.
_SERIES_Z = 1e-3
_SERIES_TERMS = 8


class FoldingError(RuntimeError):
    """No random warp of the requested size stayed a diffeomorphism within ``max_tries``."""


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
    r = np.sqrt(r2)
    s = np.sqrt(r2 + q)
    sr2 = (s + r) ** 2
    q2 = q * q
    den = s * sr2
    g = np.divide(q2, den, out=np.zeros_like(q), where=den > 0)
    if not gradient:
        return g, None, None
    s3 = s**3
    cq = np.divide(q, 2.0 * s3, out=np.zeros_like(q), where=s3 > 0)
    # d G / d R * 2 (x - y) = -(x - y) / r * q^2 (r + 2 s) / (s^3 (s + r)^2)
    den = s3 * sr2 * r
    cd = -np.divide(q2 * (r + 2.0 * s), den, out=np.zeros_like(q), where=den > 0)
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
    ``q = (1 - |x|^2)(1 - |y|^2)`` (so that ``A^2 = 1 + q / r^2``):

    * 2D: ``G = r^2 (A^2 - 1 - ln A^2) = q - r^2 log1p(q / r^2)``, exact limit
      ``(1 - |x|^2)^2`` at ``x = y``; ``z - log1p(z)`` is summed as a series for small
      ``z = q / r^2`` (near the boundary).
    * 3D: ``G = r (A + 1/A - 2) = s + r^2 / s - 2 r`` with ``s = sqrt(r^2 + q)``, evaluated
      as the identical ``q^2 / (s (s + r)^2)``, free of cancellation; exact limit
      ``1 - |x|^2`` at ``x = y``.

    Both are proportional to the Green's function of the biharmonic operator with clamped
    boundary conditions (``G = dG/dn = 0`` on the sphere; Twining & Marsland): symmetric,
    and strictly positive definite as a kernel, so knot matrices are SPD.
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
        ``d G(x_i, y_k) / d x_i``; zero on and outside the unit sphere. In 3D the gradient
        is discontinuous at ``x = y`` (``G`` has a cone point there, like ``r``); there the
        radial part is dropped.

    Notes
    -----
    With ``G = G(q, R)``, ``R = r^2``: ``dq/dx = -2 x (1 - |y|^2)``, ``dR/dx = 2 (x - y)``.
    2D: ``dG/dq = q / (R + q)``, ``dG/dR = -(log1p(z) - z / (1 + z))``.
    3D: ``dG/dq = q / (2 s^3)``, ``dG/dR = -q^2 (r + 2 s) / (2 r s^3 (s + r)^2)``.
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
    for start in range(0, n, CHUNK):
        yield slice(start, min(start + CHUNK, n))


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
        Unit-ball coordinates.
    """
    if not (isinstance(n_knots, (int, np.integer)) and n_knots >= 1):
        raise ValueError(f"n_knots must be a positive integer, got {n_knots!r}")
    if dim not in (2, 3):
        raise ValueError(f"dim must be 2 or 3, got {dim!r}")
    if not 0 < radius < 1:
        raise ValueError(f"radius must lie in (0, 1), got {radius!r}")
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


def _grid_frame(shape: tuple[int, ...]) -> tuple[np.ndarray, float]:
    """Centre (ITK order, pixels) and radius (pixels) of the inscribed circle / sphere."""
    size = np.array(shape[::-1], dtype=np.float64)
    return (size - 1.0) / 2.0, float(size.min()) / 2.0


def _grid_points(shape: tuple[int, ...]) -> np.ndarray:
    """Pixel centres in ITK order ``(x, y[, z])``, flattened in numpy (C) order: (n, dim)."""
    axes = [np.arange(n, dtype=np.float64) for n in shape]
    grids = np.meshgrid(*axes, indexing="ij")
    return np.stack(grids[::-1], axis=-1).reshape(-1, len(shape))


@dataclass(frozen=True)
class CPSWarp:
    """A CPS warp ``psi(p) = p + scale * R * spline((p - c) / R)`` on a pixel grid.

    ``c`` and ``R`` are the centre and radius (pixels) of the grid's inscribed circle/sphere.

    Attributes
    ----------
    spline : ClampedPlateSpline
        The unscaled spline in unit-ball coordinates.
    shape : tuple of int
        Numpy shape of the grid, ``(ny, nx)`` or ``(nz, ny, nx)``.
    scale : float
        Factor applied to every pixel displacement (the paper's ``d / d_hat``).
    mean_displacement : float
        Mean over all pixels of ``|psi(p) - p|`` in pixels (the paper's ``d``).
    min_jacobian : float
        Smallest Jacobian determinant of ``psi`` over the pixel centres.
    """

    spline: ClampedPlateSpline | None
    shape: tuple[int, ...]
    scale: float
    mean_displacement: float
    min_jacobian: float
    # unscaled pixel displacements and gradients at the pixels inside the circle, kept
    # from the draw so that field() and inverse_field() need no new spline evaluation
    _u: np.ndarray | None = field(default=None, repr=False, compare=False)
    _jac: np.ndarray | None = field(default=None, repr=False, compare=False)

    def _grid_values(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Inside mask (n,), scaled pixel displacements (n_in, dim) and gradients there."""
        c, r = _grid_frame(self.shape)
        unit = (_grid_points(self.shape) - c) / r
        inside = np.einsum("nd,nd->n", unit, unit) < 1.0
        if self._u is None:
            u, jac = self.spline.value_and_jacobian(unit[inside])
            u = u * r
        else:
            u, jac = self._u, self._jac
        return inside, self.scale * u, self.scale * jac

    @property
    def dim(self) -> int:
        return len(self.shape)

    def displacement(self, points) -> np.ndarray:
        """``u(p) = psi(p) - p`` at `points` (n, dim), ITK order, pixels."""
        points = _as_points(points)
        if self.spline is None or self.scale == 0.0:
            return np.zeros_like(points)
        c, r = _grid_frame(self.shape)
        return (self.scale * r) * self.spline((points - c) / r)

    def jacobian(self, points) -> np.ndarray:
        """``d u_i / d p_j`` at `points`, shape (n, dim, dim)."""
        points = _as_points(points)
        if self.spline is None or self.scale == 0.0:
            return np.zeros((len(points), self.dim, self.dim))
        c, r = _grid_frame(self.shape)
        return self.scale * self.spline.jacobian((points - c) / r)

    def field(self) -> np.ndarray:
        """The displacement of ``psi`` at every pixel: shape (*shape, dim), ITK order, pixels."""
        out = np.zeros((int(np.prod(self.shape)), self.dim))
        if self.spline is not None and self.scale != 0.0:
            inside, u, _ = self._grid_values()
            out[inside] = u
        return out.reshape(*self.shape, self.dim)

    def inverse_field(self, *, tol: float = 1e-5, max_iter: int = 50) -> np.ndarray:
        """The displacement ``v`` of ``psi^-1`` at every pixel: ``psi(p + v(p)) = p``.

        Damped Newton iterations on the sampled field and Jacobian (linear interpolation),
        then Newton steps with the exact spline residual until ``|psi(p + v) - p| < tol``
        pixels. Outside the inscribed circle / sphere ``v = 0`` exactly. This is the field
        ITK resampling needs to produce the paper's ``I~ = I o psi^-1``.

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


def random_cps(
    shape: Sequence[int],
    mean_displacement: float,
    *,
    n_knots: int = 25,
    seed: int | np.random.Generator | None = None,
    max_tries: int = 50,
    min_jacobian: float = MIN_JACOBIAN,
) -> CPSWarp:
    """Draw a random CPS warp of exactly the given mean pixel displacement.

    Knots (:func:`knot_positions`) are moved by independent isotropic normal steps, the
    spline is evaluated at every pixel and all displacements are scaled by ``d / d_hat``
    so that the mean of ``|psi(p) - p|`` over *all* pixels (inside and outside the circle)
    is exactly `mean_displacement`. A warp whose Jacobian determinant falls below
    `min_jacobian` at some pixel centre (it folds, or nearly) is redrawn.

    Parameters
    ----------
    shape : sequence of int
        Numpy shape of the grid, ``(ny, nx)`` or ``(nz, ny, nx)``.
    mean_displacement : float
        ``d`` in pixels, ``>= 0``. ``0`` gives the identity.
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
        When all `max_tries` draws fold; the message gives the largest safe ``d`` seen.
    """
    shape = tuple(int(s) for s in shape)
    if len(shape) not in (2, 3) or min(shape) < 3:
        raise ValueError(f"shape must be 2D or 3D with at least 3 pixels per axis, got {shape}")
    d = float(mean_displacement)
    if not (np.isfinite(d) and d >= 0):
        raise ValueError(
            f"mean_displacement must be a finite number >= 0, got {mean_displacement!r}"
        )
    if not (isinstance(max_tries, (int, np.integer)) and max_tries >= 1):
        raise ValueError(f"max_tries must be a positive integer, got {max_tries!r}")
    if not 0 <= min_jacobian < 1:
        raise ValueError(f"min_jacobian must lie in [0, 1), got {min_jacobian!r}")
    dim = len(shape)
    knots = knot_positions(n_knots, dim)
    rng = _as_rng(seed)
    if d == 0.0:
        return CPSWarp(None, shape, 0.0, 0.0, 1.0)
    c, r = _grid_frame(shape)
    points = _grid_points(shape)
    unit = (points - c) / r
    inside = np.einsum("nd,nd->n", unit, unit) < 1.0
    last = (0.0, np.zeros((1, dim, dim)))
    for _ in range(max_tries):
        spline = ClampedPlateSpline.from_knots(knots, rng.normal(size=knots.shape))
        u, jac = spline.value_and_jacobian(unit[inside])
        u *= r  # pixels; jac = d u_pix / d p needs no factor
        d_hat = np.linalg.norm(u, axis=1).sum() / len(points)
        if d_hat == 0.0:
            continue
        scale = d / d_hat  # pixel displacement = scale * r * spline(unit)
        min_det = float(_det(np.eye(dim) + scale * jac).min())
        if min_det >= min_jacobian:
            return CPSWarp(spline, shape, scale, d, min(min_det, 1.0), _u=u, _jac=jac)
        last = (d_hat, jac)
    best = last[0] * _safe_scale(last[1])
    raise FoldingError(
        f"all {max_tries} random CPS warps of mean displacement {d:g} px fold "
        f"(the last would be safe up to d = {best:.3g} px); lower mean_displacement, "
        "use fewer knots, "
        f"or raise max_tries"
    )


def _safe_scale(jac: np.ndarray) -> float:
    """Largest ``t`` with ``det(I + t A) > 0`` for every ``A`` in `jac` (n, dim, dim).

    ``det(I + t A) = prod(1 + t lambda)`` vanishes first at ``t = -1 / lambda`` for the most
    negative real eigenvalue ``lambda`` over all pixels; complex pairs never vanish.
    """
    lam = np.linalg.eigvals(jac)
    real = np.abs(lam.imag) <= 1e-12 * np.maximum(1.0, np.abs(lam.real))
    neg = lam.real[real & (lam.real < 0)]
    return float(np.inf if neg.size == 0 else -1.0 / neg.min())


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
        The grid: an image (its size, spacing, origin and direction are used) or a numpy
        shape ``(ny, nx)`` / ``(nz, ny, nx)`` (unit spacing, zero origin).
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
    warp = random_cps(shape, mean_displacement, n_knots=n_knots, seed=seed, max_tries=max_tries)
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


def max_safe_displacement(field) -> float:
    """The largest mean displacement for which this warp's shape stays a diffeomorphism.

    The field ``u`` is scaled by ``t``; ``psi_t(p) = p + t u(p)`` folds first where
    ``det(I + t grad u)`` reaches zero, at ``t* = -1 / lambda_min`` for the most negative
    real eigenvalue of ``grad u`` over the grid (central differences). Returns
    ``t* * mean |u|`` in pixels, or ``inf`` when no scaling folds.

    Parameters
    ----------
    field : sitk.Image or array_like of shape (*spatial, dim)
        A displacement field (physical units for an image, pixels for an array; ITK
        component order).

    Returns
    -------
    float
        Pixels (mean over all pixels of ``|u|`` times ``t*``).
    """
    arr = _field_pixels(field)
    dim = arr.shape[-1]
    mean = float(np.linalg.norm(arr, axis=-1).mean())
    if mean == 0.0:
        return float("inf")
    # grad[..., i, j] = d u_i / d x_j, x_j ITK axis j = numpy axis dim - 1 - j
    grads = np.gradient(arr, axis=tuple(range(dim)))
    jac = np.stack([grads[dim - 1 - j] for j in range(dim)], axis=-1).reshape(-1, dim, dim)
    return mean * _safe_scale(jac)


# ----------------------------------------------------------------------------------------
# Warping images and labels
# ----------------------------------------------------------------------------------------


def warp_stack(images, warps, *, labels=None, n_labels: int | None = None):
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
        Integer label maps of shape (n_images, *spatial) with values ``0 .. n_labels - 1``
        (made one-hot), or floating memberships of shape (n_images, n_labels, *spatial).
    n_labels : int, optional
        Number of label values for integer maps (default ``labels.max() + 1``).

    Returns
    -------
    images : ndarray of shape (n_images, *spatial), float64
    memberships : ndarray of shape (n_images, n_labels, *spatial), float64, or None
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
    fuzzy = labels is not None and np.issubdtype(np.asarray(labels).dtype, np.floating)
    if fuzzy:
        labels = np.asarray(labels, dtype=np.float64)
        if labels.ndim != images.ndim + 1 or labels.shape[2:] != spatial or len(labels) != n:
            raise ValueError(
                f"memberships must have shape (n_images, n_labels, *spatial) = "
                f"({n}, L, {', '.join(map(str, spatial))}), got {labels.shape}"
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
        n_labels = int(labels.max()) + 1 if n_labels is None else int(n_labels)
        if labels.max() >= n_labels:
            raise ValueError(f"labels has value {int(labels.max())} >= n_labels={n_labels}")
    index = np.stack(np.meshgrid(*[np.arange(s, dtype=np.float64) for s in spatial], indexing="ij"))
    out = np.empty_like(images)
    members = None if labels is None else np.empty((n, n_labels, *spatial))
    for i, w in enumerate(warps):
        v = w.inverse_field() if isinstance(w, CPSWarp) else np.asarray(w, dtype=np.float64)
        if v.shape != (*spatial, dim):
            raise ValueError(f"warp {i}: field shape {v.shape} differs from {(*spatial, dim)}")
        coords = index + np.moveaxis(v[..., ::-1], -1, 0)  # ITK (x, y, z) -> numpy axes
        if labels is None:
            channels = images[i][None]
        elif fuzzy:
            channels = np.concatenate([images[i][None], labels[i]])
        else:
            onehot = labels[i][None] == np.arange(n_labels).reshape(-1, *([1] * dim))
            channels = np.concatenate([images[i][None], onehot.astype(np.float64)])
        sampled = _linear_sample(channels, coords.reshape(dim, -1)).reshape(-1, *spatial)
        out[i] = sampled[0]
        if labels is not None:
            members[i] = sampled[1:]
    return out, members


def _linear_sample(channels: np.ndarray, coords: np.ndarray) -> np.ndarray:
    """Bilinear / trilinear interpolation of every channel at the same points.

    Equivalent to ``ndimage.map_coordinates(c, coords, order=1, mode="nearest")`` per
    channel, with the weights computed once. `channels` (C, *spatial); `coords` (dim, n) in
    numpy axis order; returns (C, n).
    """
    spatial = channels.shape[1:]
    flat = channels.reshape(len(channels), -1)
    base, frac, strides = [], [], []
    stride = 1
    for a in reversed(range(len(spatial))):
        strides.insert(0, stride)
        stride *= spatial[a]
    for a, size in enumerate(spatial):
        c = np.clip(coords[a], 0.0, size - 1.0)
        i0 = np.minimum(np.floor(c).astype(np.intp), max(size - 2, 0))
        base.append(i0)
        frac.append(c - i0)
    out = np.zeros((len(channels), coords.shape[1]))
    for corner in np.ndindex(*([2] * len(spatial))):
        w = np.ones(coords.shape[1])
        idx = np.zeros(coords.shape[1], dtype=np.intp)
        for a, bit in enumerate(corner):
            w *= frac[a] if bit else 1.0 - frac[a]
            idx += (base[a] + bit) * strides[a]
        out += flat[:, idx] * w
    return out
