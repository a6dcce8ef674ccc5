"""The fold check of a clamped-plate-spline warp: is ``p + t u(p)`` one-to-one for all t <= 1?

A warp is accepted when ``det(I + t grad u) >= min_jacobian`` for every ``t`` in ``[0, 1]``
at every check point: all pixel centres, a sub-grid :data:`REFINE` times finer in every
pixel cell near a knot (:data:`KNOT_BOX`), and the same sub-grid in every cell whose corner
determinants come near the threshold (module docstring of :mod:`itk_nrreval.experiments.warps`,
"Folding"). :func:`fold_check` runs it for a spline at a scale; :func:`safe_scale` is its
core: the largest multiplier of a set of displacement gradients before any determinant
drops below the threshold, solved exactly as a polynomial root. Pure numpy.
"""

from __future__ import annotations

import numpy as np

from ._clamped_plate_spline import BallFrame, ClampedPlateSpline

__all__ = ["REFINE", "KNOT_BOX", "fold_check", "safe_scale"]

#: The fold check's sub-grid is this many times finer than the image (per axis).
REFINE = 4
#: ... and covers every pixel cell within this many pixels (per axis) of a knot.
KNOT_BOX = 0.5
#: Sub-grid cells evaluated at once in the fold check (bounds its temporaries).
_CELL_CHUNK = 2048


def _det(a: np.ndarray) -> np.ndarray:
    """Determinants of a stack of 2x2 or 3x3 matrices (n, dim, dim)."""
    if a.shape[-1] == 2:
        return a[:, 0, 0] * a[:, 1, 1] - a[:, 0, 1] * a[:, 1, 0]
    return np.einsum("nj,nj->n", a[:, 0, :], np.cross(a[:, 1, :], a[:, 2, :]))


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


def safe_scale(jac: np.ndarray, min_jacobian: float = 0.0, *, cap: float = np.inf) -> float:
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


def _cells_near_knots(frame: BallFrame, knots_px: np.ndarray) -> np.ndarray:
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
    frame: BallFrame,
    cells: np.ndarray,
    scale: float,
    min_jacobian: float,
    *,
    cap: float,
) -> tuple[float, float]:
    """Over the sub-grid of the masked `cells`: ``safe_scale`` of ``scale * J`` (capped)
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
        t = min(t, safe_scale(jac, min_jacobian, cap=t))
    return t, min_det


def fold_check(
    spline: ClampedPlateSpline,
    frame: BallFrame,
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
    t = safe_scale(scale * jac_in, min_jacobian, cap=cap)
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
