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
* Central differences do not see every fold: a voxel that moves past its neighbours leaves
  its own central-difference Jacobian unchanged (the "checkerboard" case of Liu et al.,
  "On finite difference Jacobian computation in deformable image registration", IJCV 2024).
  The same pass over the field also takes ``det J`` on the one-sided stencils (the triangles
  and tetrahedra of the voxel grid) that their *digital diffeomorphism* requires positive,
  and reports the non-diffeomorphic voxels and volume beside the folded fraction.
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
    transform_pieces,
)

__all__ = [
    "Plausibility",
    "Thresholds",
    "SubjectThresholds",
    "AffineFit",
    "JacobianSummary",
    "DeformationMeasures",
    "deformation_plausibility",
    "deformation_measures",
    "affine_fit",
    "combine",
    "flags",
    "frame_spread_limit_mm",
    "smallest_extent_mm",
    "SLAB_VOXELS",
    "LOG_JACOBIAN_BINS",
    "LOG_JACOBIAN_RANGE",
    "INVERSE_FIELD_STEP",
    "INVERSE_CONSISTENCY_STEP",
    "INVERSE_REFINE_STEPS",
    "INNER_TETRAHEDRA",
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
    nondiffeomorphic_fraction : float
        Fraction of the evaluated voxels where ``det J <= 0`` on at least one of the
        finite-difference stencils of :func:`deformation_measures` (the central one, the
        ``2**d`` one-sided ones and, in 3D, the two inner tetrahedra of the voxel cubes): the
        voxels that are not *digitally diffeomorphic* (Liu et al., IJCV 2024); in [0, 1], at
        least `folded_fraction`. NaN when not measured (results written before it was). For a
        registration: the mean over its images.
    nondiffeomorphic_max : float
        The largest `nondiffeomorphic_fraction` of a single image.
    nondiffeomorphic_volume : float
        Liu et al.'s non-diffeomorphic volume (area in 2D) as a fraction of the evaluated
        volume: the volume the deformed triangles or tetrahedra of the evaluated voxels
        cover inside out (``det J < 0``), averaged over the two ways of cutting the voxel
        cubes (squares) into them, over the evaluated volume; what Learn2Reg's LUMIR reports
        as "NDV" in percent, divided by 100. Multiply by the evaluated volume for mm^3. At
        least 0 (0 where every stencil has ``det J >= 0``), and not bounded by 1 (a simplex
        turned inside out may also grow); NaN when not measured. For a registration: the
        mean over its images.
    """

    folded_fraction: float
    folded_max: float
    sdlogj: float
    jacobian_min: float
    jacobian_max: float
    inverse_consistency_mm: float | None = None
    # last, with defaults: measures added later (issue 42), absent from older results
    nondiffeomorphic_fraction: float = math.nan
    nondiffeomorphic_max: float = math.nan
    nondiffeomorphic_volume: float = math.nan

    def to_dict(self) -> dict:
        """The fields as a JSON-safe dict: NaN and infinities become None."""
        return {k: json_number(v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, data: Mapping) -> Plausibility:
        """Inverse of :meth:`to_dict` (None back to NaN, except the inverse consistency; a
        measure the dict does not have, as in results written before it existed, NaN)."""

        def number(key: str) -> float:
            value = data.get(key)
            return math.nan if value is None else float(value)

        return cls(
            folded_fraction=float(data["folded_fraction"]),
            folded_max=float(data["folded_max"]),
            sdlogj=number("sdlogj"),
            jacobian_min=number("jacobian_min"),
            jacobian_max=number("jacobian_max"),
            inverse_consistency_mm=data["inverse_consistency_mm"],
            nondiffeomorphic_fraction=number("nondiffeomorphic_fraction"),
            nondiffeomorphic_max=number("nondiffeomorphic_max"),
            nondiffeomorphic_volume=number("nondiffeomorphic_volume"),
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


@dataclass(frozen=True)
class DeformationMeasures:
    """What :func:`deformation_measures` returns: the same fields whatever its flags.

    Attributes
    ----------
    plausibility : Plausibility
        ``folded_max`` equals ``folded_fraction``, ``nondiffeomorphic_max``
        ``nondiffeomorphic_fraction`` (one image).
    jacobian : JacobianSummary
        Over the same evaluated voxels.
    affine : AffineFit or None
        :func:`affine_fit`'s fit over the evaluated voxels, from the same sampling of the
        transform; None unless asked for (``affine=True``).
    """

    plausibility: Plausibility
    jacobian: JacobianSummary
    affine: AffineFit | None = None


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
        ``folded_max`` equals ``folded_fraction``, ``nondiffeomorphic_max``
        ``nondiffeomorphic_fraction`` (one image).
    """
    return deformation_measures(
        transform,
        grid,
        mask=mask,
        inverse_consistency=inverse_consistency,
        max_slab_voxels=max_slab_voxels,
    ).plausibility


def deformation_measures(
    transform: sitk.Transform,
    grid: Geometry | sitk.Image,
    *,
    mask: np.ndarray | None = None,
    inverse_consistency: bool = True,
    max_slab_voxels: int = SLAB_VOXELS,
    affine: bool = False,
    displacement: np.ndarray | None = None,
) -> DeformationMeasures:
    """Plausibility of a transform on a grid, and its Jacobian's histogram and middle slice.

    One pass over the grid gives both: folding, SDlogJ, Jacobian range and inverse
    consistency (:class:`Plausibility`), and the histogram of ``log det J`` on fixed bins
    with ``det J`` on the middle slice (:class:`JacobianSummary`, for reports); with
    `affine`, also the closest affine map (:func:`affine_fit`) from the same sampling of the
    transform. The result has the same fields whatever the flags
    (:class:`DeformationMeasures`).

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
        Also compute :func:`affine_fit`'s fit over the evaluated voxels, from the
        displacement sampled here (its numbers to rounding, without sampling the transform
        a second time); without it the result's ``affine`` is None.

    Returns
    -------
    DeformationMeasures
        ``plausibility`` (:class:`Plausibility`; ``folded_max`` equals ``folded_fraction``,
        ``nondiffeomorphic_max`` ``nondiffeomorphic_fraction``: one image), ``jacobian``
        (:class:`JacobianSummary`, over the same evaluated voxels) and ``affine``
        (:class:`AffineFit`; None without `affine`).

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
    * ``nondiffeomorphic_fraction = #{p : det J_s(p) <= 0 for some stencil s} / #p``, the
      stencils of Liu et al.'s digital diffeomorphism (IJCV 2024; their code,
      github.com/yihao6/digital_diffeomorphism, is what Learn2Reg's LUMIR evaluation
      runs): with forward or backward differences along each axis, the ``2**d`` one-sided
      Jacobians ``det(I + [h_x h_y (h_z)] du/dx)`` -- det J of the affine map on each
      triangle (2D) or corner tetrahedron (3D) of the voxel squares (cubes) around p --, in
      3D the two inner tetrahedra of the cubes below and above p
      (:data:`INNER_TETRAHEDRA`), and the central ``det J(p)`` (which, inside the grid, is
      the mean of the one-sided ones, so it adds nothing there but rounding); the
      displacement extended beyond the grid by its edge values, as their code pads it.
      Liu et al. show that all of these positive at every voxel is what keeps the map free
      of folding at the voxel level; central differences alone miss, for instance, a voxel
      moved past its neighbours, which leaves its own central difference unchanged;
    * ``nondiffeomorphic_volume = (1/#p) sum_p sum_s w_s max(-det J_s(p), 0)``, Liu et
      al.'s non-diffeomorphic volume (area) over the evaluated volume: ``w_s`` is the
      simplex's share of a voxel (1/2 for a triangle, 1/6 for a corner tetrahedron, 1/3 for
      an inner one) times 1/2 (either way of cutting a square or cube covers it once), so
      the sum is the volume the deformed simplices cover inside out, in voxel volumes;
    * ``inverse_consistency_mm = mean_p |T^-1(T(p)) - p|`` over the evaluated voxels whose
      every index is even (all evaluated voxels when none is), ``T(p)`` sampled by ITK and
      ``T^-1`` evaluated at those points. For linear transforms this is rounding error; for
      a displacement field it is the error of the numerical inverse (six fixed-point steps
      from an inverse computed on a grid four times as coarse as the field's): near 0 where
      the field is invertible, growing where it folds (a folded map has no inverse).

    The sums run over the evaluated voxels (the mask), all at once on grids of at most
    `max_slab_voxels` voxels and otherwise slab by slab, each slab with one row of halo so
    that its central differences and stencils are the whole grid's. Central differences and
    stencils come from one compiled pass over the slab (:func:`_slab_jacobians`): at 1 mm
    (182 x 218 x 182 voxels, one thread) the stencils add 0.03-0.04 s to it.
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

    count = folded = nondiffeomorphic = 0
    nondiffeomorphic_volume = 0.0
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
        sel = None if mask is None else mask[rows]
        # det J (central differences) and, in the same pass, the other stencils' verdicts
        det, bad, bad_volume = _slab_jacobians(u, g, inner, sel)
        nondiffeomorphic += bad
        nondiffeomorphic_volume += bad_volume
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
        nondiffeomorphic_fraction=nondiffeomorphic / count,
        nondiffeomorphic_max=nondiffeomorphic / count,
        nondiffeomorphic_volume=nondiffeomorphic_volume / count,
    )
    summary = JacobianSummary(hist, below, above, folded, middle)
    return DeformationMeasures(plausibility, summary, None if fit is None else fit.fit())


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


#: The two inner tetrahedra of the voxel cubes that every voxel takes ``det J`` on besides its
#: eight corner ones (3D): each row an edge from the voxel p to a vertex, as an index offset
#: in ITK order (i, j, k). Cutting a cube into five tetrahedra leaves one inside, in one of
#: two ways; ``T1`` (p - (1, 1, 0), p - (1, 0, 1), p - (0, 1, 1)) is that of the cube below p
#: (p its highest corner) and ``T2`` (p + (1, 1, 0), p + (0, 1, 1), p + (1, 0, 1)) the other
#: one of the cube above p (p its lowest corner), so that each cube's two are taken once.
INNER_TETRAHEDRA = np.array(
    [
        [[-1, -1, 0], [-1, 0, -1], [0, -1, -1]],
        [[1, 1, 0], [0, 1, 1], [1, 0, 1]],
    ],
    np.float64,
)


def _slab_jacobians(
    u: np.ndarray, g: Geometry, inner: slice, sel: np.ndarray | None
) -> tuple[np.ndarray, int, float]:
    """det J of one slab and its digital-diffeomorphism counts, in one compiled pass.

    Parameters
    ----------
    u : ndarray, shape ``(*halo.shape, d)``
        The displacement (mm, ITK component order) on the slab with its halo rows (numpy
        axis 0).
    g : Geometry
        The whole grid (its spacing and direction; the slab shares them).
    inner : slice
        The slab's own rows of `u` (numpy axis 0).
    sel : ndarray of bool, shape of the inner rows, or None
        The evaluated voxels of those rows (None: all).

    Returns
    -------
    det : ndarray of float64, shape of the inner rows
        ``det J`` by central differences (one-sided at the grid's border): the numbers of
        :func:`~itk_nrreval.transforms.jacobian_determinant`, bit for bit.
    nondiffeomorphic : int
        Evaluated voxels where ``det J <= 0`` on any stencil (:func:`_jacobians`).
    volume : float
        Their non-diffeomorphic volume, in voxel volumes, summed over the evaluated voxels.
    """
    dim = g.dimension
    # physical x = origin + D diag(spacing) index: an index step along axis a moves by
    # steps[:, a] mm; m is computed as jacobian_determinant computes it (the same bits)
    direction = np.asarray(g.direction, np.float64).reshape(dim, dim)
    steps = direction @ np.diag(np.asarray(g.spacing, dtype=np.float64))
    m = np.linalg.inv(steps)
    # a simplex's det J is the volume of its deformed edges over that of its edges
    # (negative: inside out), a ratio the kernel takes as one determinant times these
    scales = np.array([1.0 / np.linalg.det(steps), 0.0, 0.0])
    edges = np.zeros((2, 3, 3))
    if dim == 3:
        for t, offsets in enumerate(INNER_TETRAHEDRA):
            edges[t] = offsets @ steps.T  # the edges' physical vectors, one a row
            scales[1 + t] = 1.0 / np.linalg.det(edges[t])
    evaluate = np.zeros(u.shape[:-1], bool)
    evaluate[inner] = True if sel is None else sel
    det = np.empty(u.shape[:-1])
    # the components apart, each contiguous along x: the kernel's loops along x then run in
    # SIMD lanes (twice as fast at 1 mm as on the interleaved vectors, this copy included)
    v = np.ascontiguousarray(np.moveaxis(u, -1, 0), dtype=np.float64)
    view = (v, evaluate, det) if dim == 3 else (v[:, None], evaluate[None], det[None])
    counts = np.zeros(view[1].shape[0], np.int64)
    volumes = np.zeros(view[1].shape[0])
    _jacobians(view[0], m, steps, edges, scales, view[1], view[2], counts, volumes)
    # per slice, then added up in slice order: the numbers do not depend on the threads
    return det[inner], int(counts.sum()), float(volumes.sum())


@numba.njit(cache=True, inline="always")
def _difference_ends(at, n):  # pragma: no cover - compiled
    """np.gradient's nodes and factor at node `at` of an axis of `n` nodes (central, 1/2,
    inside; one-sided, 1, at the border; 0 on an axis of one node): those of
    :func:`~itk_nrreval.transforms.jacobian_determinant`'s kernel."""
    if n == 1:
        return 0, 0, 0.0
    if at == 0:
        return 0, 1, 1.0
    if at == n - 1:
        return n - 2, n - 1, 1.0
    return at - 1, at + 1, 0.5


@numba.njit(cache=True, inline="always")
def _scaled(diff, factor):  # pragma: no cover - compiled
    """`diff` times a factor of :func:`_difference_ends` (a halving as a division, so that
    it rounds as np.gradient's does)."""
    if factor == 0.5:
        return diff / 2.0
    return diff if factor == 1.0 else 0.0


@numba.njit(cache=True, inline="always")
def _central2(v, k, j, i, x, y, m):  # pragma: no cover - compiled
    """``det(I + G m)`` at voxel (k, j, i) of the 2D field `v` (2, 1, ny, nx), G by the
    differences ``x`` and ``y`` of :func:`_difference_ends`: the operations of
    :func:`~itk_nrreval.transforms.jacobian_determinant`'s kernel, in its order."""
    xl, xh, xf = x
    yl, yh, yf = y
    g00 = _scaled(v[0, k, j, xh] - v[0, k, j, xl], xf)
    g10 = _scaled(v[1, k, j, xh] - v[1, k, j, xl], xf)
    g01 = _scaled(v[0, k, yh, i] - v[0, k, yl, i], yf)
    g11 = _scaled(v[1, k, yh, i] - v[1, k, yl, i], yf)
    j00 = (0.0 + g00 * m[0, 0] + g01 * m[1, 0]) + 1.0
    j01 = 0.0 + g00 * m[0, 1] + g01 * m[1, 1]
    j10 = 0.0 + g10 * m[0, 0] + g11 * m[1, 0]
    j11 = (0.0 + g10 * m[0, 1] + g11 * m[1, 1]) + 1.0
    return j00 * j11 - j01 * j10


@numba.njit(cache=True, inline="always")
def _central3(v, k, j, i, x, y, z, m):  # pragma: no cover - compiled
    """:func:`_central2` of a 3D field `v` (3, nz, ny, nx)."""
    xl, xh, xf = x
    yl, yh, yf = y
    zl, zh, zf = z
    g00 = _scaled(v[0, k, j, xh] - v[0, k, j, xl], xf)
    g10 = _scaled(v[1, k, j, xh] - v[1, k, j, xl], xf)
    g01 = _scaled(v[0, k, yh, i] - v[0, k, yl, i], yf)
    g11 = _scaled(v[1, k, yh, i] - v[1, k, yl, i], yf)
    g20 = _scaled(v[2, k, j, xh] - v[2, k, j, xl], xf)
    g21 = _scaled(v[2, k, yh, i] - v[2, k, yl, i], yf)
    g02 = _scaled(v[0, zh, j, i] - v[0, zl, j, i], zf)
    g12 = _scaled(v[1, zh, j, i] - v[1, zl, j, i], zf)
    g22 = _scaled(v[2, zh, j, i] - v[2, zl, j, i], zf)
    # J = I + G m, each entry summed from 0 in the order a = x, y, z
    j00 = (0.0 + g00 * m[0, 0] + g01 * m[1, 0] + g02 * m[2, 0]) + 1.0
    j01 = 0.0 + g00 * m[0, 1] + g01 * m[1, 1] + g02 * m[2, 1]
    j02 = 0.0 + g00 * m[0, 2] + g01 * m[1, 2] + g02 * m[2, 2]
    j10 = 0.0 + g10 * m[0, 0] + g11 * m[1, 0] + g12 * m[2, 0]
    j11 = (0.0 + g10 * m[0, 1] + g11 * m[1, 1] + g12 * m[2, 1]) + 1.0
    j12 = 0.0 + g10 * m[0, 2] + g11 * m[1, 2] + g12 * m[2, 2]
    j20 = 0.0 + g20 * m[0, 0] + g21 * m[1, 0] + g22 * m[2, 0]
    j21 = 0.0 + g20 * m[0, 1] + g21 * m[1, 1] + g22 * m[2, 1]
    j22 = (0.0 + g20 * m[0, 2] + g21 * m[1, 2] + g22 * m[2, 2]) + 1.0
    return (
        j00 * (j11 * j22 - j12 * j21)
        - j01 * (j10 * j22 - j12 * j20)
        + j02 * (j10 * j21 - j11 * j20)
    )


@numba.njit(cache=True, inline="always")
def _stencils2(v, k, j, i, ip, im, jp, jm, steps, scale):  # pragma: no cover - compiled
    """The least ``det J`` of the four triangles at voxel (k, j, i) of a 2D field `v`, and
    their non-diffeomorphic area (voxel areas): see :func:`_jacobians`. (ip, im), (jp, jm):
    the voxel's neighbours along x and y, itself beyond the grid's border."""
    u0, u1 = v[0, k, j, i], v[1, k, j, i]
    # the deformed index steps: steps[:, a] plus the forward (f) or backward (b) difference
    fx0 = steps[0, 0] + (v[0, k, j, ip] - u0)
    fx1 = steps[1, 0] + (v[1, k, j, ip] - u1)
    bx0 = steps[0, 0] + (u0 - v[0, k, j, im])
    bx1 = steps[1, 0] + (u1 - v[1, k, j, im])
    fy0 = steps[0, 1] + (v[0, k, jp, i] - u0)
    fy1 = steps[1, 1] + (v[1, k, jp, i] - u1)
    by0 = steps[0, 1] + (u0 - v[0, k, jm, i])
    by1 = steps[1, 1] + (u1 - v[1, k, jm, i])
    t0 = (fx0 * fy1 - fx1 * fy0) * scale
    t1 = (fx0 * by1 - fx1 * by0) * scale
    t2 = (bx0 * fy1 - bx1 * fy0) * scale
    t3 = (bx0 * by1 - bx1 * by0) * scale
    low = min(min(t0, t1), min(t2, t3))
    # 1/2 (a triangle's share of the square) x 1/2 (two ways of cutting it)
    negative = -0.25 * (min(t0, 0.0) + min(t1, 0.0) + min(t2, 0.0) + min(t3, 0.0))
    return low, negative


@numba.njit(cache=True, inline="always")
def _triple(a0, a1, a2, b0, b1, b2, c0, c1, c2):  # pragma: no cover - compiled
    """``det [a b c]`` (columns), as ``a . (b x c)``."""
    return a0 * (b1 * c2 - b2 * c1) + a1 * (b2 * c0 - b0 * c2) + a2 * (b0 * c1 - b1 * c0)


@numba.njit(cache=True, inline="always")
def _stencils3(v, k, j, i, ip, im, jp, jm, kp, km, steps, edges, scales):  # pragma: no cover
    """:func:`_stencils2` of a 3D field `v`: the eight corner tetrahedra and the two inner
    ones at voxel (k, j, i); (kp, km) its neighbours along z."""
    u0, u1, u2 = v[0, k, j, i], v[1, k, j, i], v[2, k, j, i]
    fx0 = steps[0, 0] + (v[0, k, j, ip] - u0)
    fx1 = steps[1, 0] + (v[1, k, j, ip] - u1)
    fx2 = steps[2, 0] + (v[2, k, j, ip] - u2)
    bx0 = steps[0, 0] + (u0 - v[0, k, j, im])
    bx1 = steps[1, 0] + (u1 - v[1, k, j, im])
    bx2 = steps[2, 0] + (u2 - v[2, k, j, im])
    fy0 = steps[0, 1] + (v[0, k, jp, i] - u0)
    fy1 = steps[1, 1] + (v[1, k, jp, i] - u1)
    fy2 = steps[2, 1] + (v[2, k, jp, i] - u2)
    by0 = steps[0, 1] + (u0 - v[0, k, jm, i])
    by1 = steps[1, 1] + (u1 - v[1, k, jm, i])
    by2 = steps[2, 1] + (u2 - v[2, k, jm, i])
    fz0 = steps[0, 2] + (v[0, kp, j, i] - u0)
    fz1 = steps[1, 2] + (v[1, kp, j, i] - u1)
    fz2 = steps[2, 2] + (v[2, kp, j, i] - u2)
    bz0 = steps[0, 2] + (u0 - v[0, km, j, i])
    bz1 = steps[1, 2] + (u1 - v[1, km, j, i])
    bz2 = steps[2, 2] + (u2 - v[2, km, j, i])
    # the eight determinants are multilinear in the columns: y x z for the four (y, z)
    # pairs, each dotted with the forward and the backward x
    yz0, yz1, yz2 = fy1 * fz2 - fy2 * fz1, fy2 * fz0 - fy0 * fz2, fy0 * fz1 - fy1 * fz0
    c0 = fx0 * yz0 + fx1 * yz1 + fx2 * yz2
    c1 = bx0 * yz0 + bx1 * yz1 + bx2 * yz2
    yz0, yz1, yz2 = fy1 * bz2 - fy2 * bz1, fy2 * bz0 - fy0 * bz2, fy0 * bz1 - fy1 * bz0
    c2 = fx0 * yz0 + fx1 * yz1 + fx2 * yz2
    c3 = bx0 * yz0 + bx1 * yz1 + bx2 * yz2
    yz0, yz1, yz2 = by1 * fz2 - by2 * fz1, by2 * fz0 - by0 * fz2, by0 * fz1 - by1 * fz0
    c4 = fx0 * yz0 + fx1 * yz1 + fx2 * yz2
    c5 = bx0 * yz0 + bx1 * yz1 + bx2 * yz2
    yz0, yz1, yz2 = by1 * bz2 - by2 * bz1, by2 * bz0 - by0 * bz2, by0 * bz1 - by1 * bz0
    c6 = fx0 * yz0 + fx1 * yz1 + fx2 * yz2
    c7 = bx0 * yz0 + bx1 * yz1 + bx2 * yz2
    s = scales[0]
    c0, c1, c2, c3, c4, c5, c6, c7 = c0 * s, c1 * s, c2 * s, c3 * s, c4 * s, c5 * s, c6 * s, c7 * s
    # the inner tetrahedra, INNER_TETRAHEDRA: T1 (p - (1, 1, 0), p - (1, 0, 1), p - (0, 1, 1))
    # and T2 (p + (1, 1, 0), p + (0, 1, 1), p + (1, 0, 1)); e: their physical edges, rows
    e = edges[0]
    t1 = scales[1] * _triple(
        e[0, 0] + (v[0, k, jm, im] - u0),
        e[0, 1] + (v[1, k, jm, im] - u1),
        e[0, 2] + (v[2, k, jm, im] - u2),
        e[1, 0] + (v[0, km, j, im] - u0),
        e[1, 1] + (v[1, km, j, im] - u1),
        e[1, 2] + (v[2, km, j, im] - u2),
        e[2, 0] + (v[0, km, jm, i] - u0),
        e[2, 1] + (v[1, km, jm, i] - u1),
        e[2, 2] + (v[2, km, jm, i] - u2),
    )
    e = edges[1]
    t2 = scales[2] * _triple(
        e[0, 0] + (v[0, k, jp, ip] - u0),
        e[0, 1] + (v[1, k, jp, ip] - u1),
        e[0, 2] + (v[2, k, jp, ip] - u2),
        e[1, 0] + (v[0, kp, jp, i] - u0),
        e[1, 1] + (v[1, kp, jp, i] - u1),
        e[1, 2] + (v[2, kp, jp, i] - u2),
        e[2, 0] + (v[0, kp, j, ip] - u0),
        e[2, 1] + (v[1, kp, j, ip] - u1),
        e[2, 2] + (v[2, kp, j, ip] - u2),
    )
    low = min(min(min(c0, c1), min(c2, c3)), min(min(c4, c5), min(c6, c7)))
    low = min(low, min(t1, t2))
    corners = min(c0, 0.0) + min(c1, 0.0) + min(c2, 0.0) + min(c3, 0.0)
    corners += min(c4, 0.0) + min(c5, 0.0) + min(c6, 0.0) + min(c7, 0.0)
    # 1/6 (a corner tetrahedron's share of the cube), 1/3 (an inner one's), x 1/2 (two cuts)
    negative = -(corners / 12.0 + (min(t1, 0.0) + min(t2, 0.0)) / 6.0)
    return low, negative


@numba.njit(cache=True, parallel=True)
def _jacobians(v, m, steps, edges, scales, evaluate, det, counts, volumes):  # pragma: no cover
    """``det = det(I + G m)`` by central differences, by the operations of
    :func:`~itk_nrreval.transforms.jacobian_determinant`'s kernel, and at the voxels where
    `evaluate`, ``det J`` on the stencils of Liu et al.'s digital diffeomorphism.

    `v` (d, nz, ny, nx): the displacement's components apart (mm), d 2 or 3 (a 2D field as
    nz = 1), so that the loops along x run in SIMD lanes; `m` (d, d) index steps per mm and
    `steps` its inverse (column a: one index step along axis a, in mm); `edges` (2, 3, 3) the
    physical edges of :data:`INNER_TETRAHEDRA` (one a row; 3D); `scales`: ``1 / det steps``
    and ``1 / det edges[t]``.

    With ``f_a``, ``b_a`` the forward and backward differences of u along index axis a (0
    beyond the grid's border: the displacement extended by its edge values, as Liu et al.'s
    code pads it), the one-sided stencils are the ``2**d`` matrices ``I + [h_x h_y (h_z)] m``,
    each ``h_a`` one of ``f_a``, ``b_a``: the Jacobians of the affine maps on the triangles
    (2D; the four of the pixel squares around the voxel, both ways of cutting each) or corner
    tetrahedra (3D; one per cube around it) at the voxel. Their determinants are
    ``det[steps_a + h_a] / det steps`` (the deformed edges' volume over the edges'),
    multilinear in the columns: four 2 x 2 determinants in 2D, in 3D eight dot products with
    four cross products. In 3D the two inner tetrahedra add ``det[e_c + du_c] / det[e_c]``,
    ``e_c`` an edge and ``du_c`` the displacement's difference along it.

    ``counts[k]``: the evaluated voxels of slice k with ``det J <= 0`` on any of them or by
    central differences; ``volumes[k]``: their non-diffeomorphic volume in voxel volumes,
    each negative ``det J`` times its simplex's share of a voxel (1/2 for a triangle, 1/6
    for a corner tetrahedron, 1/3 for an inner one) times 1/2 (each of the two ways of
    cutting covers every square or cube once). Slices run in parallel, each into its own
    entries; every voxel is computed alone, so the numbers do not depend on the threads."""
    d, nz, ny, nx = v.shape
    for slice_ in numba.prange(nz):
        k = np.int64(slice_)  # prange's index is unsigned
        z = _difference_ends(k, nz)
        kp, km = min(k + 1, nz - 1), max(k - 1, 0)  # the neighbours, edge-padded
        low = np.empty(nx)
        negative = np.empty(nx)
        count = 0
        volume = 0.0
        for j in range(ny):
            y = _difference_ends(j, ny)
            jp, jm = min(j + 1, ny - 1), max(j - 1, 0)
            # the row's inner voxels in loops without a branch (SIMD lanes; central
            # differences and stencils apart: together, they do not vectorise), then its ends
            if d == 2:
                for i in range(1, nx - 1):
                    det[k, j, i] = _central2(v, k, j, i, (i - 1, i + 1, 0.5), y, m)
                for i in range(1, nx - 1):
                    low[i], negative[i] = _stencils2(
                        v, k, j, i, i + 1, i - 1, jp, jm, steps, scales[0]
                    )
            else:
                for i in range(1, nx - 1):
                    det[k, j, i] = _central3(v, k, j, i, (i - 1, i + 1, 0.5), y, z, m)
                for i in range(1, nx - 1):
                    low[i], negative[i] = _stencils3(
                        v, k, j, i, i + 1, i - 1, jp, jm, kp, km, steps, edges, scales
                    )
            for i in (0, nx - 1):
                x = _difference_ends(i, nx)
                ip, im = min(i + 1, nx - 1), max(i - 1, 0)
                if d == 2:
                    det[k, j, i] = _central2(v, k, j, i, x, y, m)
                    low[i], negative[i] = _stencils2(v, k, j, i, ip, im, jp, jm, steps, scales[0])
                else:
                    det[k, j, i] = _central3(v, k, j, i, x, y, z, m)
                    low[i], negative[i] = _stencils3(
                        v, k, j, i, ip, im, jp, jm, kp, km, steps, edges, scales
                    )
            # counted where evaluated (the stencils are taken everywhere: no branch above)
            for i in range(nx):
                if evaluate[k, j, i]:
                    if det[k, j, i] <= 0.0 or low[i] <= 0.0:
                        count += 1
                    volume += negative[i]
        counts[k] = count
        volumes[k] = volume


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
        return cls(**{k: math.nan if data[k] is None else float(data[k]) for k in asdict(_NAN_FIT)})


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
            return _NAN_FIT
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
_NAN_FIT = AffineFit(math.nan, math.nan, math.nan)


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
        None if any image has None; ``nondiffeomorphic_fraction`` and
        ``nondiffeomorphic_volume``: mean, ``nondiffeomorphic_max``: max, each NaN if any
        image has NaN (not measured).
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
        # NaN (not measured) in any image leaves the registration's NaN
        nondiffeomorphic_fraction=float(np.mean([p.nondiffeomorphic_fraction for p in items])),
        nondiffeomorphic_max=float(np.max([p.nondiffeomorphic_max for p in items])),
        nondiffeomorphic_volume=float(np.mean([p.nondiffeomorphic_volume for p in items])),
    )


@dataclass(frozen=True)
class Thresholds:
    """When :func:`flags` calls a registration implausible.

    Attributes
    ----------
    folded_mean : float
        Flag a mean folded fraction above this (default 0.01: 1 % of the voxels), or else a
        mean non-diffeomorphic fraction (folded by some stencil) above it.
    folded_max : float
        ... or a single image's folded (non-diffeomorphic) fraction above this (default
        0.25: 25 %).
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
    * **Folding by some stencil** (the digital diffeomorphism of Liu et al., IJCV 2024) is
      the same physical fault, counted where central differences cannot see it: a voxel
      moved past its neighbours. It is judged by the same bounds. On the genuine
      registrations of the verdict benchmark (``benchmarks/bench_verdict.py``, every image,
      whole reference grids) the stencils see the B-splines' folds 1.2-1.6 times as often as
      central differences (1.9x on the 3D 10 mm grid), and add folds that central
      differences all but miss to demons and fluid registrations with little smoothing:
      1.2-2.8 % of the voxels in 2D and 28 % in 3D at 0.5 mm (central differences:
      0.04-0.25 %), 1.2 % in 3D at 1 mm (0.002 %). Those are the registrations these bounds
      newly flag, with one B-spline (8 mm grid: 0.998 % by central differences, 1.34 % by
      some stencil); each has a larger true error than its case's affine registration or,
      in a sweep without one, than most of its settings.
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
        in the worst image)"``, ``"1.1% of voxels fold by some finite-difference stencil
        (Jacobian determinant <= 0 on a one-sided or tetrahedral stencil; 1.4% in the worst
        image), where central differences see 0.00093%"``, ``"SDlogJ 0.83 is 4.1x the
        median of the registrations compared (0.20)"``, ``"frame estimates spread 12.5 mm on
        average (6.2% of the 200 mm field of view)"``.

    Raises
    ------
    InputError
        `frame_spread_mm` without a positive `extent_mm`.

    Notes
    -----
    A registration is flagged for folding when ``folded_fraction > folded_mean`` or
    ``folded_max > thresholds.folded_max``, and otherwise for folding by some stencil when
    its non-diffeomorphic fraction (at least the folded one; :class:`Plausibility`) crosses
    the same bounds: ``nondiffeomorphic_fraction > folded_mean`` or
    ``nondiffeomorphic_max > thresholds.folded_max`` (never when not measured); for
    roughness, with ``m`` the median SDlogJ over
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
        elif (  # folds that central differences do not see (NaN, not measured: False)
            p.nondiffeomorphic_fraction > th.folded_mean or p.nondiffeomorphic_max > th.folded_max
        ):
            reasons.append(
                f"{_percent(p.nondiffeomorphic_fraction)} of voxels fold by some "
                f"finite-difference stencil (Jacobian determinant <= 0 on a one-sided or "
                f"tetrahedral stencil; {_percent(p.nondiffeomorphic_max)} in the worst "
                f"image), where central differences see {_percent(p.folded_fraction)}"
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
