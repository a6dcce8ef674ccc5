"""Deformation plausibility: folding, Jacobian roughness and inverse consistency of a transform.

An evaluation without ground truth scores how well a registration makes the images *look*
alike; a registration can game that by tearing and folding space (Rohlfing, IEEE TMI 31(2),
2012). This module measures the deformation itself, so that such registrations are flagged
whatever their image scores.

Conventions
-----------
* Every transform maps **reference (fixed) points to image (moving) points**, in physical
  coordinates (mm, LPS), as ITK writes them. The plausibility of one image's transform is
  measured on a grid -- the registration's own reference grid, on which the transform acts.
* Jacobians are taken in physical units with the grid's direction cosines honoured
  (:func:`itk_nrreval.transforms.jacobian_determinant`), on the transform **as given**: nothing
  is clipped before folds are counted. (A widespread evaluation script clips ``det J`` to
  ``1e-9`` before counting ``det J <= 0`` and so never reports a fold.)
* Masks are boolean arrays in numpy order (``(z, y, x)``) of the grid.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass

import numba
import numpy as np
import SimpleITK as sitk

from ._errors import InputError
from ._images import Geometry
from ._output import json_number
from .transforms import (
    PointwiseInverse,
    composed_displacement,
    displacement_array,
    displacement_field,
    flatten,
    has_only_fields,
    jacobian_determinant,
    transform_pieces,
)

__all__ = [
    "Plausibility",
    "Thresholds",
    "SubjectThresholds",
    "AffineFit",
    "JacobianSummary",
    "deformation_plausibility",
    "deformation_measures",
    "affine_fit",
    "combine",
    "flags",
    "frame_spread_limit_mm",
    "smallest_extent_mm",
]

#: Voxels per slab (with its halo) above which the grid is processed in slabs along its last
#: ITK axis (z in 3D): the Jacobian of one slab takes about 200 bytes per voxel.
SLAB_VOXELS = 1 << 20

#: Bins of the log det J histogram of :class:`JacobianSummary`: fixed, so that histograms of
#: different images (and processes) add up. [-2, 2] spans volume changes by a factor e^2 = 7.4
#: either way; values beyond are counted apart (``below``, ``above``).
LOG_JACOBIAN_BINS = 64
LOG_JACOBIAN_RANGE = (-2.0, 2.0)

#: Inverse consistency is measured on every ``INVERSE_CONSISTENCY_STEP``-th voxel of the
#: grid along each axis: each displacement field of ``T`` is inverted by ITK on every
#: ``INVERSE_FIELD_STEP``-th node of its grid, and that coarse inverse refined by
#: ``INVERSE_REFINE_STEPS`` fixed-point steps at the round trip's own points
#: (:class:`itk_nrreval.transforms.PointwiseInverse`), not on the field's grid. At 1 mm this
#: takes about 0.6 s of one core (1.9 s refining a whole inverse field, 12 s inverting on
#: the full grid). Without the interpolation of an inverse field, what is left is the
#: iteration's own error: near 0 where the map is invertible (7e-7 mm on a smooth 3 mm
#: field, where ITK's full-grid inverse field gives 0.004 mm), large where it folds (no
#: inverse). Six steps rather than three: with three, the error of clean cohorts' smooth
#: fields spread from 1e-4 to 0.02 mm, enough for their subjects' z-scores to flag
#: (``tests/test_plausibility.py`` and ``tests/test_subject_qc.py`` state the bounds;
#: ``benchmarks/bench_image_task.py`` the times; issue 30).
INVERSE_FIELD_STEP = 4
INVERSE_CONSISTENCY_STEP = 2
INVERSE_REFINE_STEPS = 6


@dataclass(frozen=True)
class Plausibility:
    """How physically plausible a deformation is (one image's transform, or a registration).

    Attributes
    ----------
    folded_fraction : float
        Fraction of the evaluated voxels where the Jacobian determinant is <= 0 (the map
        folds space there); in [0, 1]. For a registration: the mean over its images.
    folded_max : float
        The largest folded fraction of a single image (one image: equal to
        `folded_fraction`).
    sdlogj : float
        Standard deviation (population, ``ddof=0``) of ``log det J`` over the evaluated
        voxels that do not fold; NaN when every voxel folds. 0 for a linear transform. For a
        registration: the mean over its images.
    jacobian_min, jacobian_max : float
        Extreme Jacobian determinants over the evaluated voxels (unclipped; negative where
        the map folds). For a registration: over all its images.
    inverse_consistency_mm : float or None
        Mean round-trip error ``|T^-1(T(p)) - p|`` (mm) over the evaluated voxels, with
        ``T^-1`` from :func:`itk_nrreval.transforms.invert`; about 0 for linear transforms.
        None when not computed or when the inverse could not be computed. For a
        registration: the mean over its images (None if any image has None).
    """

    folded_fraction: float
    folded_max: float
    sdlogj: float
    jacobian_min: float
    jacobian_max: float
    inverse_consistency_mm: float | None = None

    def to_dict(self) -> dict:
        """The fields as a JSON-safe dict: NaN and infinities become None."""
        return {k: json_number(v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, data: Mapping) -> Plausibility:
        """Inverse of :meth:`to_dict` (None back to NaN, except the inverse consistency)."""
        nan = math.nan
        return cls(
            folded_fraction=float(data["folded_fraction"]),
            folded_max=float(data["folded_max"]),
            sdlogj=nan if data["sdlogj"] is None else float(data["sdlogj"]),
            jacobian_min=nan if data["jacobian_min"] is None else float(data["jacobian_min"]),
            jacobian_max=nan if data["jacobian_max"] is None else float(data["jacobian_max"]),
            inverse_consistency_mm=data["inverse_consistency_mm"],
        )


@dataclass(frozen=True)
class JacobianSummary:
    """The distribution of ``log det J`` of one transform, and ``det J`` on one slice.

    Attributes
    ----------
    counts : ndarray of int64, shape (LOG_JACOBIAN_BINS,)
        Histogram of ``log det J`` over the evaluated voxels that do not fold, on the fixed
        bins :attr:`edges` (``LOG_JACOBIAN_BINS`` equal bins over ``LOG_JACOBIAN_RANGE``;
        the last bin is closed on the right, as in ``np.histogram``).
    below, above : int
        Evaluated voxels with ``0 < det J`` and ``log det J`` below / above that range.
    folded : int
        Evaluated voxels with ``det J <= 0`` (no logarithm).
    middle : ndarray of float32
        ``det J`` on the middle slice of the grid (numpy index ``shape[0] // 2`` of a 3D
        grid, shape ``grid.shape[1:]``; the whole grid in 2D), NaN outside the mask.
        Unclipped: negative where the map folds.

    Notes
    -----
    ``counts.sum() + below + above + folded`` is the number of evaluated voxels with a
    finite ``det J``. Histograms of several transforms on the same bins add up
    (:meth:`add`).
    """

    counts: np.ndarray
    below: int
    above: int
    folded: int
    middle: np.ndarray

    @property
    def edges(self) -> np.ndarray:
        """The bin edges of :attr:`counts`, shape (LOG_JACOBIAN_BINS + 1,)."""
        return np.linspace(*LOG_JACOBIAN_RANGE, LOG_JACOBIAN_BINS + 1)

    def histogram(self) -> dict:
        """The histogram alone, JSON-ready: ``counts`` (list), ``below``, ``above``,
        ``folded``."""
        return {
            "counts": [int(c) for c in self.counts],
            "below": int(self.below),
            "above": int(self.above),
            "folded": int(self.folded),
        }


def _geometry(grid: Geometry | sitk.Image) -> Geometry:
    if isinstance(grid, Geometry):
        return grid
    if isinstance(grid, sitk.Image):
        return Geometry.from_image(grid)
    raise InputError(f"grid: expected a Geometry or a SimpleITK image, got {type(grid).__name__}")


def smallest_extent_mm(grid: Geometry | sitk.Image) -> float:
    """The grid's smallest physical extent (mm): ``min_k size_k * spacing_k``.

    The field of view that :func:`flags` relates a frame spread to (``extent_mm``).
    """
    g = _geometry(grid)
    return float(min(n * s for n, s in zip(g.size, g.spacing, strict=True)))


def _slabs(g: Geometry, max_voxels: int) -> Iterator[tuple[slice, Geometry, Geometry, slice]]:
    """Split `g` along its last ITK axis (numpy axis 0) into slabs.

    Yields ``(rows, halo_grid, slab_grid, inner)``: the numpy rows of the slab, the grid of the
    slab with one row of halo on each side (inside the grid), the grid of the slab alone,
    and the slab's rows inside the halo grid's array. Central differences inside a slab
    extended by its halo are those of the whole grid, so the Jacobians agree exactly.
    """
    n = g.size[-1]
    per_row = max(1, math.prod(g.size[:-1]))
    rows_per_slab = n if n * per_row <= max_voxels else max(1, max_voxels // per_row - 2)
    step = np.asarray(g.direction, np.float64).reshape(g.dimension, g.dimension)[:, -1]
    step = step * g.spacing[-1]  # physical offset of one row along the last axis

    def sub(start: int, stop: int) -> Geometry:
        origin = tuple(float(o) for o in np.asarray(g.origin) + start * step)
        return Geometry((*g.size[:-1], stop - start), g.spacing, origin, g.direction)

    for start in range(0, n, rows_per_slab):
        stop = min(start + rows_per_slab, n)
        lo, hi = max(start - 1, 0), min(stop + 1, n)
        yield slice(start, stop), sub(lo, hi), sub(start, stop), slice(start - lo, stop - lo)


def deformation_plausibility(
    transform: sitk.Transform,
    grid: Geometry | sitk.Image,
    *,
    mask: np.ndarray | None = None,
    inverse_consistency: bool = True,
    max_slab_voxels: int = SLAB_VOXELS,
) -> Plausibility:
    """Folding, SDlogJ, Jacobian range and inverse consistency of a transform on a grid.

    :func:`deformation_measures` without its :class:`JacobianSummary`; the parameters,
    exceptions and notes are its.

    Returns
    -------
    Plausibility
        ``folded_max`` equals ``folded_fraction`` (one image).
    """
    return deformation_measures(
        transform,
        grid,
        mask=mask,
        inverse_consistency=inverse_consistency,
        max_slab_voxels=max_slab_voxels,
    )[0]


def deformation_measures(
    transform: sitk.Transform,
    grid: Geometry | sitk.Image,
    *,
    mask: np.ndarray | None = None,
    inverse_consistency: bool = True,
    max_slab_voxels: int = SLAB_VOXELS,
    affine: bool = False,
    displacement: np.ndarray | None = None,
) -> tuple[Plausibility, JacobianSummary] | tuple[Plausibility, JacobianSummary, AffineFit]:
    """Plausibility of a transform on a grid, and its Jacobian's histogram and middle slice.

    One pass over the grid gives both: folding, SDlogJ, Jacobian range and inverse
    consistency (:class:`Plausibility`), and the histogram of ``log det J`` on fixed bins
    with ``det J`` on the middle slice (:class:`JacobianSummary`, for reports); with
    `affine`, also the closest affine map (:func:`affine_fit`) from the same sampling of the
    transform.

    Parameters
    ----------
    transform : sitk.Transform (or a path / chain in ANTs order, or its TransformPieces)
        Maps reference points to image points (mm, LPS); measured as given, never clipped.
        Linear maps and displacement fields are sampled by the compiled kernels (to about
        1e-13 mm of ITK's sampling), other pieces by ITK.
    grid : Geometry or sitk.Image
        The grid of points p (voxel centres) on which the transform is evaluated: the
        registration's reference grid. Size ``(x, y[, z])``, numpy shape ``grid.shape``.
    mask : ndarray of bool, shape ``grid.shape`` (numpy order), optional
        Evaluate only these voxels (the Jacobian still uses their neighbours).
    inverse_consistency : bool
        Invert the transform at the points it maps every second voxel to
        (:data:`INVERSE_CONSISTENCY_STEP`) with
        :class:`itk_nrreval.transforms.PointwiseInverse` (linear parts exactly,
        displacement fields from a coarse inverse on every fourth node of their own grid,
        :data:`INVERSE_FIELD_STEP`, refined at those points; other non-linear pieces after
        sampling them on `grid`) and measure the round trip. False leaves
        ``inverse_consistency_mm`` None (and saves a field inversion).
    max_slab_voxels : int
        Grids larger than this are processed in slabs along the last axis (z in 3D) so that
        memory stays bounded; the result does not depend on it.
    displacement : ndarray of shape ``(*grid.shape, dim)``, optional
        ``T(p) - p`` already sampled on `grid` (mm, ITK (x, y[, z]) order last, as
        ``sitk.GetArrayViewFromImage`` of :func:`~itk_nrreval.transforms.displacement_field`
        gives it), when the caller needs that sampling too; default: sampled here, slab by
        slab.
    affine : bool
        Also return :func:`affine_fit`'s fit over the evaluated voxels, from the
        displacement sampled here (its numbers to rounding, without sampling the transform
        a second time).

    Returns
    -------
    Plausibility
        ``folded_max`` equals ``folded_fraction`` (one image).
    JacobianSummary
        Over the same evaluated voxels.
    AffineFit
        Only with `affine`.

    Raises
    ------
    InputError
        A grid of another dimension than the transform, a mask of the wrong shape, or an
        empty mask.

    Notes
    -----
    With ``u(p) = T(p) - p`` sampled on the grid (:func:`displacement_field`), the Jacobian
    determinant is ``det J(p) = det(I + du/dx)`` with derivatives in physical coordinates
    (central differences inside the grid, one-sided at its border), and

    * ``folded_fraction = #{p : det J(p) <= 0} / #p``;
    * ``sdlogj = std{log det J(p) : det J(p) > 0}`` (Leow et al., IEEE TMI 26(6), 2007;
      the Learn2Reg challenges' smoothness measure), accumulated slab by slab with the
      parallel-variance formula of Chan et al.;
    * ``inverse_consistency_mm = mean_p |T^-1(T(p)) - p|`` over the evaluated voxels whose
      every index is even (all evaluated voxels when none is), ``T(p)`` sampled by ITK and
      ``T^-1`` evaluated at those points. For linear transforms this is rounding error; for
      a displacement field it is the error of the numerical inverse (six fixed-point steps
      from an inverse computed on a grid four times as coarse as the field's): near 0 where
      the field is invertible, growing where it folds (a folded map has no inverse).

    The sums run over the evaluated voxels (the mask), all at once on grids of at most
    `max_slab_voxels` voxels and otherwise slab by slab, each slab with one row of halo so
    that its central differences are the whole grid's.
    """
    g = _geometry(grid)
    pieces = transform_pieces(transform)  # read and taken apart once, for every use below
    if displacement is not None and displacement.shape != (*g.shape, g.dimension):
        raise InputError(
            f"displacement: shape {displacement.shape} is not the grid's {(*g.shape, g.dimension)}"
        )
    dim = pieces[0].GetDimension()
    if dim != g.dimension:
        raise InputError(f"transform: {dim}D transform on a {g.dimension}D grid {g.size}")
    # linear maps and fields are sampled by the compiled kernels; anything else by ITK
    t = pieces if has_only_fields(pieces) else flatten(pieces)
    if mask is not None:
        mask = np.asarray(mask)
        if mask.shape != g.shape:
            raise InputError(f"mask: shape {mask.shape} differs from the grid's {g.shape}")
        mask = mask.astype(bool, copy=False)
        if not mask.any():
            raise InputError("mask: empty (no voxel to evaluate)")

    inverse = None
    if inverse_consistency:
        try:
            inverse = PointwiseInverse(
                pieces, grid=g, field_step=INVERSE_FIELD_STEP, refine_steps=INVERSE_REFINE_STEPS
            )
        except (InputError, RuntimeError):
            inverse = None

    count = folded = 0
    n_log, mean_log, m2_log = 0, 0.0, 0.0
    jmin, jmax = math.inf, -math.inf
    hist = np.zeros(LOG_JACOBIAN_BINS, np.int64)
    below = above = 0
    mid = g.shape[0] // 2  # the middle slice of a 3D grid (numpy axis 0: the slab axis)
    middle = np.full(g.shape[1:] if g.dimension == 3 else g.shape, np.nan, np.float32)
    fit = _AffineSums(g) if affine else None
    for rows, halo_grid, slab_grid, inner in _slabs(g, max(int(max_slab_voxels), 1)):
        if displacement is None and not isinstance(t, sitk.Transform):
            field = None
            u = displacement_array(t, halo_grid)
        elif displacement is None:
            # An array view does not keep its image alive: `field` stays named while `u` is
            # used.
            field = displacement_field(t, halo_grid)
            u = sitk.GetArrayViewFromImage(field)
        else:
            field = None
            first = rows.start - inner.start
            u = displacement[first : first + halo_grid.size[-1]]
        det = jacobian_determinant(u, spacing=g.spacing, direction=g.direction)[inner]
        sel = None if mask is None else mask[rows]
        if fit is not None:
            fit.add(u[inner], slab_grid, sel)
        del u, field
        if g.dimension != 3:
            middle[rows] = np.where(sel, det, np.nan) if sel is not None else det
        elif rows.start <= mid < rows.stop:
            row = det[mid - rows.start]
            middle[:] = np.where(sel[mid - rows.start], row, np.nan) if sel is not None else row
        if sel is not None:
            if not sel.any():
                continue
            det = det[sel]
        det = det.ravel()
        count += det.size
        folded += int(np.count_nonzero(det <= 0))
        jmin = min(jmin, float(det.min()))
        jmax = max(jmax, float(det.max()))
        logs = np.log(det[det > 0])
        hist += np.histogram(logs, bins=LOG_JACOBIAN_BINS, range=LOG_JACOBIAN_RANGE)[0]
        below += int(np.count_nonzero(logs < LOG_JACOBIAN_RANGE[0]))
        above += int(np.count_nonzero(logs > LOG_JACOBIAN_RANGE[1]))
        if logs.size:  # Chan et al.: merge (n, mean, M2) of this slab into the running ones
            m = float(logs.mean())
            m2 = float(np.sum((logs - m) ** 2))
            total = n_log + logs.size
            delta = m - mean_log
            mean_log += delta * logs.size / total
            m2_log += m2 + delta * delta * n_log * logs.size / total
            n_log = total

    consistency = None
    if inverse is not None:
        consistency = _mean_round_trip(t, inverse, g, mask, max(int(max_slab_voxels), 1))
    fraction = folded / count
    plausibility = Plausibility(
        folded_fraction=fraction,
        folded_max=fraction,
        sdlogj=math.sqrt(m2_log / n_log) if n_log else math.nan,
        jacobian_min=jmin,
        jacobian_max=jmax,
        inverse_consistency_mm=consistency,
    )
    summary = JacobianSummary(hist, below, above, folded, middle)
    return (plausibility, summary) if fit is None else (plausibility, summary, fit.fit())


def _mean_round_trip(
    t: sitk.Transform | Sequence[sitk.Transform],
    inverse: PointwiseInverse,
    g: Geometry,
    mask: np.ndarray | None,
    max_slab_voxels: int,
) -> float | None:
    """Mean ``|T^-1(T(p)) - p|`` (mm) over the evaluated voxels of `g` whose every index is
    a multiple of :data:`INVERSE_CONSISTENCY_STEP` (over all of them when none is)
    (:func:`~itk_nrreval.transforms.composed_displacement`); None when not finite."""
    step = INVERSE_CONSISTENCY_STEP
    every = (slice(None, None, step),) * g.dimension
    if mask is not None and not mask[every].any():
        step, every = 1, (slice(None),) * g.dimension
    sub = Geometry(
        tuple(-(-n // step) for n in g.size),
        tuple(s * step for s in g.spacing),
        g.origin,
        g.direction,
    )
    sub_mask = None if mask is None else mask[every]
    err_sum, count = 0.0, 0
    for rows, _halo, slab_grid, _inner in _slabs(sub, max_slab_voxels):
        # An array view does not keep its image alive: name the image, or the view reads
        # freed memory (zeros on a Dask worker, issue 25).
        err = composed_displacement(inverse, t, slab_grid).reshape(-1, g.dimension)
        norms = np.sqrt(np.sum(err * err, axis=-1))
        if sub_mask is not None:
            norms = norms[sub_mask[rows].ravel()]
        err_sum += float(norms.sum())
        count += norms.size
    return err_sum / count if count and math.isfinite(err_sum) else None


@dataclass(frozen=True)
class AffineFit:
    """The affine map closest to a transform on a grid (least squares over its voxels).

    Attributes
    ----------
    linear_det : float
        Determinant of the fitted map's linear part (unitless): about 1 for a pose, negative
        for a map that mirrors space (axes flipped).
    displacement_rms_mm : float
        Root mean square of ``|T(p) - p|`` over the evaluated voxels, mm.
    nonlinear_rms_mm : float
        Root mean square of ``|T(p) - (A p + b)|``, mm, with ``A p + b`` the fitted affine
        map: the part of the displacement no affine map explains; 0 (to round-off) for a
        linear transform.
    """

    linear_det: float
    displacement_rms_mm: float
    nonlinear_rms_mm: float

    def to_dict(self) -> dict:
        return {k: json_number(v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, data: Mapping) -> AffineFit:
        """Inverse of :meth:`to_dict` (None back to NaN)."""
        return cls(**{k: math.nan if data[k] is None else float(data[k]) for k in asdict(NAN_FIT)})


def affine_fit(
    transform: sitk.Transform,
    grid: Geometry | sitk.Image,
    *,
    mask: np.ndarray | None = None,
    max_slab_voxels: int = SLAB_VOXELS,
) -> AffineFit:
    """Fit an affine map to a transform over a grid's voxels, by least squares.

    Parameters
    ----------
    transform : sitk.Transform (or a path / chain in ANTs order, or its TransformPieces)
        Maps reference points to image points (mm, LPS). Linear maps and displacement
        fields are sampled by the compiled kernels (to about 1e-13 mm of ITK's sampling),
        other pieces by ITK.
    grid : Geometry or sitk.Image
        The points p (voxel centres): the registration's reference grid.
    mask : ndarray of bool, shape ``grid.shape`` (numpy order), optional
        Fit over these voxels only (at least ``dimension + 1`` of them, not all on one plane).
    max_slab_voxels : int
        Sample the displacement slab by slab along the last axis above this many voxels, so
        that memory stays bounded; the result does not depend on it.

    Returns
    -------
    AffineFit
        All NaN when the voxels do not determine an affine map (too few, or on one plane).

    Notes
    -----
    With ``u(p) = T(p) - p`` and ``q = p - c`` (c the grid's centre, so that the sums do not
    lose the millimetres to the coordinates' size), the fit ``u ~ B^T [q, 1]`` solves the
    normal equations ``S_qq B = S_qu`` with ``S_qq = sum [q, 1][q, 1]^T`` and
    ``S_qu = sum [q, 1] u^T``, accumulated slab by slab; the linear part is ``I + B[:d]^T``
    and the residual sum of squares ``sum |u|^2 - <B, S_qu>``.
    """
    g = _geometry(grid)
    pieces = transform_pieces(transform)  # read and taken apart once, for every slab
    dim = pieces[0].GetDimension()
    if dim != g.dimension:
        raise InputError(f"transform: {dim}D transform on a {g.dimension}D grid {g.size}")
    # linear maps and fields are sampled by the compiled kernels; anything else by ITK
    t = pieces if has_only_fields(pieces) else flatten(pieces)
    sums = _AffineSums(g)
    for rows, _halo, slab_grid, _inner in _slabs(g, max(int(max_slab_voxels), 1)):
        sums.add(displacement_array(t, slab_grid), slab_grid, None if mask is None else mask[rows])
    return sums.fit()


class _AffineSums:
    """The normal equations of :func:`affine_fit` (see its notes), accumulated slab by slab
    over the grid `g`: ``S_qq``, ``S_qu``, ``sum |u|^2`` and the voxel count."""

    def __init__(self, g: Geometry):
        d = g.dimension
        self.direction = np.asarray(g.direction, np.float64).reshape(d, d)
        self.spacing = np.asarray(g.spacing, np.float64)
        size = np.asarray(g.size)
        self.centre = np.asarray(g.origin) + self.direction @ (self.spacing * (size - 1) / 2)
        self.s_qq = np.zeros((d + 1, d + 1))
        self.s_qu = np.zeros((d + 1, d))
        self.s_uu = 0.0
        self.count = 0

    def add(self, u: np.ndarray, slab_grid: Geometry, sel: np.ndarray | None) -> None:
        """Add one slab: `u` its displacement (mm, shape ``(*slab_grid.shape, d)``), `sel` its
        evaluated voxels (bool, ``slab_grid.shape``) or None for all."""
        d = len(self.spacing)
        u = np.asarray(u, np.float64)
        # q of voxel index x (ITK order): (origin - centre) + step @ x
        step = self.direction * self.spacing
        start = np.asarray(slab_grid.origin) - self.centre
        if d == 2:  # one plane of 3D
            u, sel = u[None], None if sel is None else np.asarray(sel)[None]
        every = sel is None
        sel = np.ones((1, 1, 1), bool) if every else np.asarray(sel, bool)
        # per slice of the slab (compiled, in parallel), then added up in slice order: the
        # numbers do not depend on the number of threads
        parts = np.zeros((u.shape[0], d + 1, 2 * d + 2))  # [S_qq | S_qu | sum |u|^2]
        _affine_sums(u, sel, every, start, step, parts)
        total = parts.sum(axis=0)
        self.s_qq += total[:, : d + 1]
        self.s_qu += total[:, d + 1 : 2 * d + 1]
        self.s_uu += float(total[0, 2 * d + 1])
        self.count += int(round(total[d, d]))  # the sum of 1 * 1 over the voxels

    def fit(self) -> AffineFit:
        d = len(self.spacing)
        if self.count <= d or np.linalg.matrix_rank(self.s_qq) < d + 1:
            return NAN_FIT
        b = np.linalg.solve(self.s_qq, self.s_qu)
        residual = max(self.s_uu - float(np.sum(b * self.s_qu)), 0.0)
        return AffineFit(
            linear_det=float(np.linalg.det(np.eye(d) + b[:d].T)),
            displacement_rms_mm=math.sqrt(self.s_uu / self.count),
            nonlinear_rms_mm=math.sqrt(residual / self.count),
        )


@numba.njit(cache=True, parallel=True)
def _affine_sums(u, sel, every, start, step, parts):  # pragma: no cover - compiled
    """For each slice k of `u` (nz, ny, nx, d; d 2 or 3, a 2D slab as nz = 1): with
    ``q1 = [start + step @ (i, j[, k]), 1]`` at every voxel selected by `sel` (all when
    `every`), ``parts[k, :, :d+1] = sum q1 q1^T``, ``parts[k, :, d+1:2d+1] = sum q1 u^T`` and
    ``parts[k, 0, 2d+1] = sum |u|^2``.

    Along a row (j, k fixed) ``q1 = a + i s`` with ``a = q1`` at i = 0 and ``s = [step[:, 0],
    0]``, so a row adds ``n a a^T + (a s^T + s a^T) sum i + s s^T sum i^2`` and
    ``a (sum u)^T + s (sum i u)^T``: a voxel costs its sums, not the outer products."""
    nz, ny, nx, d = u.shape
    for slice_ in numba.prange(nz):
        k = np.int64(slice_)  # prange's index is unsigned
        a = np.ones(d + 1)
        s = np.zeros(d + 1)
        for r in range(d):
            s[r] = step[r, 0]
        su = np.empty(d)
        siu = np.empty(d)
        acc = parts[k]
        for j in range(ny):
            for r in range(d):
                q = start[r] + step[r, 1] * j
                if d == 3:
                    q += step[r, 2] * k
                a[r] = q
            n = si = sii = suu = 0.0
            su[:] = 0.0
            siu[:] = 0.0
            for i in range(nx):
                if not every and not sel[k, j, i]:
                    continue
                x = np.float64(i)
                n += 1.0
                si += x
                sii += x * x
                for c in range(d):
                    v = u[k, j, i, c]
                    su[c] += v
                    siu[c] += x * v
                    suu += v * v
            if n == 0.0:
                continue
            for r in range(d + 1):
                for c in range(d + 1):
                    acc[r, c] += (
                        n * a[r] * a[c] + (a[r] * s[c] + s[r] * a[c]) * si + s[r] * s[c] * sii
                    )
                for c in range(d):
                    acc[r, d + 1 + c] += a[r] * su[c] + s[r] * siu[c]
            acc[0, 2 * d + 1] += suu


#: The fit of a transform whose voxels determine no affine map.
NAN_FIT = AffineFit(math.nan, math.nan, math.nan)


def combine(per_image: Sequence[Plausibility]) -> Plausibility:
    """One registration's plausibility from its images' (every image weighs the same).

    Parameters
    ----------
    per_image : sequence of Plausibility
        One per image of the registration (at least one).

    Returns
    -------
    Plausibility
        ``folded_fraction``: mean over images; ``folded_max``: max; ``sdlogj``: mean over
        the images where it is defined (NaN if none: every voxel of every image folds);
        ``jacobian_min`` / ``jacobian_max``: min / max; ``inverse_consistency_mm``: mean,
        None if any image has None.
    """
    items = list(per_image)
    if not items:
        raise InputError("combine: no per-image plausibility given")
    sd = [p.sdlogj for p in items if math.isfinite(p.sdlogj)]
    ic = [p.inverse_consistency_mm for p in items]
    return Plausibility(
        folded_fraction=float(np.mean([p.folded_fraction for p in items])),
        folded_max=float(max(p.folded_max for p in items)),
        sdlogj=float(np.mean(sd)) if sd else math.nan,
        jacobian_min=float(min(p.jacobian_min for p in items)),
        jacobian_max=float(max(p.jacobian_max for p in items)),
        inverse_consistency_mm=None if any(v is None for v in ic) else float(np.mean(ic)),
    )


@dataclass(frozen=True)
class Thresholds:
    """When :func:`flags` calls a registration implausible.

    Attributes
    ----------
    folded_mean : float
        Flag a mean folded fraction above this (default 0.01: 1 % of the voxels).
    folded_max : float
        ... or a single image's folded fraction above this (default 0.25: 25 %).
    sdlogj_ratio : float
        Flag an SDlogJ more than this many times the median over the registrations
        compared (default 2) ...
    sdlogj_floor : float
        ... and above this absolute value (default 0.2). With fewer than 3 registrations
        compared (no meaningful median) the bound is ``sdlogj_ratio * sdlogj_floor``
        (default 0.4) alone.
    frame_spread_fraction : float
        Flag a mean spread of the frame estimates above this fraction of the common grid's
        smallest physical extent (default 0.05: 5 %).

    Notes
    -----
    Rationale for the defaults:

    * **Folding** (``det J <= 0``) is physically implausible for anatomy: tissue does not
      pass through itself. Diffeomorphic registrations (SyN, fluid, stationary-velocity
      demons) fold nowhere up to discretisation; B-spline registrations fold a little
      where their regularisation is weak -- the demo's elastix registrations (N = 36) fold
      0.1-0.3 % of the brain's voxels on average and up to 4.6 % in one image. A mean
      above 1 % is beyond that, and is what registrations that tear look like: Rohlfing's
      class-matching cheat, which games image similarity (Rohlfing 2012), folds 2-3 % on a
      real-anatomy case and 22 % on the demo's phantom. One image folding on more than a
      quarter of its voxels is a failed registration whatever the mean.
    * **SDlogJ** measures the roughness of the deformation: the spread of local log volume
      changes (Leow et al. 2007; reported by the Learn2Reg challenges). Its scale depends on
      the anatomy and the population, so it is judged relative to the registrations being
      compared: more than twice their median. The absolute floor of 0.2 (local volume
      changes of about +-20 % at one standard deviation) keeps small differences among
      smooth registrations from ever flagging. With fewer than three registrations a median
      says little, so only SDlogJ above ``ratio * floor`` = 0.4 (volume changes by a factor
      of about 1.5 at one standard deviation) is flagged.
    * **Frame spread**: a registration whose reference is not the common frame is brought in
      by a transform F estimated from each of its images; when those estimates disagree by
      more than 5 % of the field of view on average, the registrations do not agree about
      where the common frame is, and comparing them in it is doubtful.
    """

    folded_mean: float = 0.01
    folded_max: float = 0.25
    sdlogj_ratio: float = 2.0
    sdlogj_floor: float = 0.2
    frame_spread_fraction: float = 0.05


@dataclass(frozen=True, kw_only=True)
class SubjectThresholds:
    """When :func:`itk_nrreval.subject_qc.assess_subjects` flags one subject of a cohort.

    Each subject is compared with the rest of its cohort (the same registration's other
    subjects) by robust z-scores, ``z = (x - median) / (1.4826 MAD)`` over the cohort; see
    :mod:`itk_nrreval.subject_qc` for the measures. The defaults aim at flagging at most 2 %
    of the subjects of a cohort of 36 that registered well (measured on generated cohorts:
    ``benchmarks/bench_subject_qc.py``, ``docs/subject-qc.md``).

    Attributes
    ----------
    outlier_z : float
        Flag a subject whose log distance to the texture model of the others has z above
        this (default 3.5).
    deformation_z : float
        Flag a subject whose log SDlogJ, log non-linear displacement (RMS beyond the best
        affine map) or log inverse-consistency error has z above this (default 3.5) ...
    deformation_ratio : float
        ... and is more than this many times the cohort's median (default 1.5; the median
        taken no lower than the measure's floor: 0.001 for SDlogJ and mm of displacement,
        0.1 mm of inverse consistency): in a cohort whose deformations are much alike (a
        small MAD), a z-score alone would flag differences too small to mean a failure.
    overlap_z : float
        Flag a subject whose label overlap with the others has z below minus this (default
        3.5) ...
    overlap_ratio : float
        ... and whose label mismatch with the others (1 - overlap) is more than this many
        times the cohort's median mismatch (default 1.5): as for the deformation, a cohort
        whose overlaps are much alike (clean 3D cohorts of 12 at 2 mm: within 0.01 of each
        other) would otherwise flag differences too small to mean a failure.
    folded : float
        Flag a subject whose transform folds more than this fraction of its voxels (default
        0.01, as :attr:`Thresholds.folded_mean` for a registration).
    off_grid_coverage : float
        A subject covering less of the common grid than this fraction of the cohort's median
        coverage (under any registration) is flagged and left out of every registration's
        scores, so that it cannot empty the region they are taken on (default 0.5).
    duplicate_distance : float
        Two subjects whose resampled images lie closer than this fraction of the cohort's
        median pairwise distance are flagged as duplicates (default 0.01).
    affine_only_ratio : float
        Flag a subject whose non-linear displacement is below this fraction of the cohort's
        median, when that median is above 0.001 mm (default 0.1): its registration stopped
        early, or did only the affine step.
    scaled_ratio : float
        Diagnose scaled displacements when a subject flagged for its deformation moves
        more than this many times the cohort's median non-linear displacement (default
        1.5).
    better_fit_ratio : float
        Diagnose an inverted transform, or another subject's transform, when a flagged
        subject's image resampled through the inverse of its transform, or another flagged
        subject's image resampled through its transform, is this many times closer to the
        model of the others than its own resampled image (default 1.3;
        :func:`itk_nrreval.subject_qc.transform_mixups`). Set from generated cohorts
        (``benchmarks/bench_subject_qc.py``): an inverted transform's inverse fit 1.42x
        better or more, a swapped subject's partner's image 2.7x or more; a flagged subject
        with neither fit 1.00x at most (an affine-only or scaled transform up to 1.54x,
        which is diagnosed before). The distance keeps the subject's own anatomy and noise,
        which no transform removes, so even the right transform seldom fits 10x better.
    """

    outlier_z: float = 3.5
    deformation_z: float = 3.5
    deformation_ratio: float = 1.5
    overlap_z: float = 3.5
    overlap_ratio: float = 1.5
    folded: float = 0.01
    off_grid_coverage: float = 0.5
    duplicate_distance: float = 0.01
    affine_only_ratio: float = 0.1
    scaled_ratio: float = 1.5
    better_fit_ratio: float = 1.3


def frame_spread_limit_mm(extent_mm: float, thresholds: Thresholds = Thresholds()) -> float:  # noqa: B008
    """The mean frame-estimate spread (mm) above which :func:`flags` flags a registration.

    ``thresholds.frame_spread_fraction * extent_mm``; the reports state the same number, so
    a spread the page calls doubtful is exactly a flagged one. Only the *mean* spread is
    judged: the maximum is one voxel of one image (often at the edge of the field of view,
    where an estimate extrapolates), shown for context.
    """
    return thresholds.frame_spread_fraction * extent_mm


def _percent(fraction: float) -> str:
    v = 100.0 * fraction
    return f"{v:.0f}%" if v >= 10 else f"{v:.2g}%"


def flags(
    plausibility: Mapping[str, Plausibility],
    *,
    frame_spread_mm: Mapping[str, float] | None = None,
    extent_mm: float | None = None,
    thresholds: Thresholds = Thresholds(),  # noqa: B008 - frozen, immutable default
) -> dict[str, list[str]]:
    """Short human-readable reasons why each registration's deformation is implausible.

    Parameters
    ----------
    plausibility : mapping of str to Plausibility
        Per registration (normally from :func:`combine`), all those being compared.
    frame_spread_mm : mapping of str to float, optional
        Per registration, the mean spread (mm) of its frame estimates (missing, None or NaN:
        not judged). Needs `extent_mm`.
    extent_mm : float, optional
        The common grid's smallest physical extent (mm), e.g. :func:`smallest_extent_mm`.
    thresholds : Thresholds

    Returns
    -------
    dict of str to list of str
        For every registration named in `plausibility` or `frame_spread_mm`, its reasons,
        empty when plausible, e.g. ``"2.2% of voxels fold (Jacobian determinant <= 0; 4.3%
        in the worst image)"``, ``"SDlogJ 0.83 is 4.1x the median of the registrations
        compared (0.20)"``, ``"frame estimates spread 12.5 mm on average (6.2% of the 200
        mm field of view)"``.

    Raises
    ------
    InputError
        `frame_spread_mm` without a positive `extent_mm`.

    Notes
    -----
    A registration is flagged for folding when ``folded_fraction > folded_mean`` or
    ``folded_max > thresholds.folded_max``; for roughness, with ``m`` the median SDlogJ over
    the registrations compared (itself included; those with an undefined SDlogJ left out),
    when at least three are compared and ``sdlogj > sdlogj_ratio * m`` and
    ``sdlogj > sdlogj_floor``, or, with fewer than three, when
    ``sdlogj > sdlogj_ratio * sdlogj_floor``; for the frame when
    ``spread > frame_spread_fraction * extent_mm``. See :class:`Thresholds` for why.
    """
    th = thresholds
    spreads = dict(frame_spread_mm or {})
    if spreads and not (extent_mm is not None and extent_mm > 0):
        raise InputError("flags: frame_spread_mm needs the common grid's extent_mm (> 0)")
    out: dict[str, list[str]] = {name: [] for name in plausibility}
    for name in spreads:
        out.setdefault(name, [])

    sds = [p.sdlogj for p in plausibility.values() if math.isfinite(p.sdlogj)]
    median = float(np.median(sds)) if len(sds) >= 3 else None
    for name, p in plausibility.items():
        reasons = out[name]
        if p.folded_fraction > th.folded_mean or p.folded_max > th.folded_max:
            reasons.append(
                f"{_percent(p.folded_fraction)} of voxels fold (Jacobian determinant <= 0; "
                f"{_percent(p.folded_max)} in the worst image)"
            )
        if not math.isfinite(p.sdlogj):  # every voxel folds: the folding reason says it
            continue
        if median is not None:
            if p.sdlogj > th.sdlogj_ratio * median and p.sdlogj > th.sdlogj_floor:
                times = f"{p.sdlogj / median:.1f}x" if median > 0 else "far above"
                reasons.append(
                    f"SDlogJ {p.sdlogj:.2f} is {times} the median of the registrations "
                    f"compared ({median:.2f})"
                )
        elif p.sdlogj > th.sdlogj_ratio * th.sdlogj_floor:
            reasons.append(
                f"SDlogJ {p.sdlogj:.2f} is above {th.sdlogj_ratio * th.sdlogj_floor:.2f} "
                f"(too few registrations compared for a median)"
            )
    for name, spread in spreads.items():
        if spread is None or not math.isfinite(spread):
            continue
        if spread > frame_spread_limit_mm(extent_mm, th):
            out[name].append(
                f"frame estimates spread {spread:.1f} mm on average ({_percent(spread / extent_mm)}"
                f" of the {extent_mm:.0f} mm field of view)"
            )
    return out
