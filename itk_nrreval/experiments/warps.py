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
The Green's function, the spline and its ball on a grid live in
:mod:`itk_nrreval.experiments._clamped_plate_spline`, the fold check in
:mod:`itk_nrreval.experiments._fold_check`; this module draws warps from them and applies them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import SimpleITK as sitk
from scipy import ndimage

from .._errors import readable
from ._clamped_plate_spline import (
    BallFrame,
    ClampedPlateSpline,
    as_points,
    chunks,
    green,
    green_gradient,
    grid_points,
)
from ._fold_check import KNOT_BOX, REFINE, fold_check, safe_scale

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
#: Accepted warps have a Jacobian determinant at least this large at every check point.
MIN_JACOBIAN = 0.05
#: Memberships may leave [0, 1] by this much (rounding); they are clipped. More is an error.
MEMBERSHIP_TOLERANCE = 1e-6


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
    def _frame(self) -> BallFrame:
        return BallFrame.of(self.shape, self.spacing)

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
        points = as_points(points)
        if self.spline is None or self.scale == 0.0:
            return np.zeros_like(points)
        frame = self._frame
        return (self.scale * frame.radius / frame.spacing) * self.spline(frame.unit(points))

    def jacobian(self, points) -> np.ndarray:
        """``d u_i / d p_j`` at `points` (pixel index units), shape (n, dim, dim).

        ``det(I + jacobian)`` is the Jacobian determinant of ``psi`` (the same in pixels
        and in mm: the two differ by a similarity with the spacing matrix).
        """
        points = as_points(points)
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
        points = grid_points(self.shape)
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
    frame = BallFrame.of(shape, spacing)
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
        t, min_det = fold_check(spline, frame, jac, inside, scale, min_jacobian, cap=1.0)
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
        t, _ = fold_check(spline, frame, jac, inside, scale, min_jacobian)
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
        t, _ = fold_check(field.spline, frame, jac, inside, field.scale, min_jacobian)
        return t * field.mean_displacement
    arr = _field_pixels(field)
    dim = arr.shape[-1]
    mean = float(np.linalg.norm(arr, axis=-1).mean())
    if mean == 0.0:
        return float("inf")
    # grad[..., i, j] = d u_i / d x_j, x_j ITK axis j = numpy axis dim - 1 - j
    grads = np.gradient(arr, axis=tuple(range(dim)))
    jac = np.stack([grads[dim - 1 - j] for j in range(dim)], axis=-1).reshape(-1, dim, dim)
    return mean * safe_scale(jac, min_jacobian)


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
    for sl in chunks(n):
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
