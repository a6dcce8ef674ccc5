"""Deformation plausibility: folding, Jacobian roughness and inverse consistency of a transform.

An evaluation without ground truth scores how well a registration makes the images *look*
alike; a registration can game that by tearing and folding space (Rohlfing, IEEE TMI 31(2),
2012). This module measures the deformation itself, so that such registrations are flagged
whatever their image scores.

Here: the measures (:func:`deformation_measures`), one registration's from its images'
(:func:`combine`) and the flags (:func:`flags`). Beside it: the compiled Jacobian stencils
(:mod:`itk_nrreval.io._jacobian_kernels`), the affine fit (:mod:`itk_nrreval.io._affine_fit`), the
flags' thresholds (:mod:`itk_nrreval.io._plausibility_thresholds`) and the slabs a large grid is
measured in (:mod:`itk_nrreval.io._grid_slabs`).

Measures
--------
With ``u(p) = T(p) - p`` sampled on the grid
(:func:`~itk_nrreval.io.transforms.displacement_field`), the Jacobian determinant is
``det J(p) = det(I + du/dx)`` with derivatives in physical coordinates (central differences
inside the grid, one-sided at its border), and

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

Conventions
-----------
* Every transform maps **reference (fixed) points to image (moving) points**, in physical
  coordinates (mm, LPS), as ITK writes them. The plausibility of one image's transform is
  measured on a grid -- the registration's own reference grid, on which the transform acts.
* Jacobians are taken in physical units with the grid's direction cosines honoured
  (:func:`itk_nrreval.io.transforms.jacobian_determinant`), on the transform **as given**: nothing
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
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass

import numpy as np
import SimpleITK as sitk

from .._errors import InputError
from .._output import json_number
from ._affine_fit import AffineFit, AffineSums, affine_fit
from ._grid_slabs import SLAB_VOXELS, as_geometry, slab_displacements, slabs
from ._images import Geometry
from ._jacobian_kernels import INNER_TETRAHEDRA, slab_jacobians
from ._plausibility_thresholds import SubjectThresholds, Thresholds, frame_spread_limit_mm
from .transforms import (
    PointwiseInverse,
    composed_displacement,
    flatten,
    has_only_fields,
    transform_pieces,
)

# benchmarks/bench_image_task.py times the affine fit's accumulation through this name
_AffineSums = AffineSums

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


#: Bins of the log det J histogram of :class:`JacobianSummary`: fixed, so that histograms of
#: different images (and processes) add up. [-2, 2] spans volume changes by a factor e^2 = 7.4
#: either way; values beyond are counted apart (``below``, ``above``).
LOG_JACOBIAN_BINS = 64
LOG_JACOBIAN_RANGE = (-2.0, 2.0)

#: Inverse consistency is measured on every ``INVERSE_CONSISTENCY_STEP``-th voxel of the
#: grid along each axis: each displacement field of ``T`` is inverted by ITK on every
#: ``INVERSE_FIELD_STEP``-th node of its grid, and that coarse inverse refined by
#: ``INVERSE_REFINE_STEPS`` fixed-point steps at the round trip's own points
#: (:class:`itk_nrreval.io.transforms.PointwiseInverse`), not on the field's grid. At 1 mm this
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
        ``T^-1`` from :func:`itk_nrreval.io.transforms.invert`; about 0 for linear transforms.
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


def smallest_extent_mm(grid: Geometry | sitk.Image) -> float:
    """The grid's smallest physical extent (mm): ``min_k size_k * spacing_k``.

    The field of view that :func:`flags` relates a frame spread to (``extent_mm``).
    """
    g = as_geometry(grid)
    return float(min(n * s for n, s in zip(g.size, g.spacing, strict=True)))


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
        :class:`itk_nrreval.io.transforms.PointwiseInverse` (linear parts exactly,
        displacement fields from a coarse inverse on every fourth node of their own grid,
        :data:`INVERSE_FIELD_STEP`, refined at those points; other non-linear pieces after
        sampling them on `grid`) and measure the round trip. False leaves
        ``inverse_consistency_mm`` None (and saves a field inversion).
    max_slab_voxels : int
        Grids larger than this are processed in slabs along the last axis (z in 3D) so that
        memory stays bounded; the result does not depend on it.
    displacement : ndarray of shape ``(*grid.shape, dim)``, optional
        ``T(p) - p`` already sampled on `grid` (mm, ITK (x, y[, z]) order last, as
        ``sitk.GetArrayViewFromImage`` of :func:`~itk_nrreval.io.transforms.displacement_field`
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
    The measures' formulas and their references are the module's (Measures).
    The sums run over the evaluated voxels (the mask), all at once on grids of at most
    `max_slab_voxels` voxels and otherwise slab by slab, each slab with one row of halo so
    that its central differences and stencils are the whole grid's. Central differences and
    stencils come from one compiled pass over the slab (:func:`slab_jacobians`): at 1 mm
    (182 x 218 x 182 voxels, one thread) the stencils add 0.03-0.04 s to it.
    """
    g = as_geometry(grid)
    pieces = transform_pieces(transform)  # read and taken apart once, for every use below
    t, mask = _checked_inputs(pieces, g, mask, displacement)
    inverse = _pointwise_inverse(pieces, g) if inverse_consistency else None
    tally = _JacobianTally(g)
    fit = AffineSums(g) if affine else None
    sampled = slab_displacements(t, g, displacement, max(int(max_slab_voxels), 1))
    for rows, slab_grid, inner, u in sampled:
        sel = None if mask is None else mask[rows]
        # det J (central differences) and, in the same pass, the other stencils' verdicts
        det, bad, bad_volume = slab_jacobians(u, g, inner, sel)
        if fit is not None:
            fit.add(u[inner], slab_grid, sel)
        del u
        tally.add(det, rows, sel, bad, bad_volume)
    consistency = None
    if inverse is not None:
        consistency = _mean_round_trip(t, inverse, g, mask, max(int(max_slab_voxels), 1))
    return DeformationMeasures(
        tally.plausibility(consistency), tally.summary(), None if fit is None else fit.fit()
    )


def _checked_inputs(
    pieces: Sequence[sitk.Transform],
    g: Geometry,
    mask: np.ndarray | None,
    displacement: np.ndarray | None,
) -> tuple[sitk.Transform | Sequence[sitk.Transform], np.ndarray | None]:
    """The transform as :func:`deformation_measures` samples it (its pieces when they are
    linear maps and fields, which the compiled kernels sample; else one ITK transform), and
    the mask as booleans, once the displacement's shape, the transform's dimension and the
    mask are checked against the grid.

    Raises
    ------
    InputError
        As :func:`deformation_measures` says.
    """
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
    return t, mask


def _pointwise_inverse(pieces: Sequence[sitk.Transform], g: Geometry) -> PointwiseInverse | None:
    """The inverse whose round trip is the inverse consistency; None when it cannot be
    computed (the measure is then None)."""
    try:
        return PointwiseInverse(
            pieces, grid=g, field_step=INVERSE_FIELD_STEP, refine_steps=INVERSE_REFINE_STEPS
        )
    except (InputError, RuntimeError):
        return None


class _JacobianTally:
    """The evaluated voxels' ``det J``, added up slab by slab into the numbers of
    :class:`Plausibility` and :class:`JacobianSummary`: counts, extremes, the histogram of
    ``log det J``, its mean and variance merged by the parallel-variance formula of Chan et
    al., and the middle slice."""

    def __init__(self, g: Geometry):
        self.count = self.folded = self.nondiffeomorphic = 0
        self.nondiffeomorphic_volume = 0.0
        self.n_log, self.mean_log, self.m2_log = 0, 0.0, 0.0
        self.jmin, self.jmax = math.inf, -math.inf
        self.hist = np.zeros(LOG_JACOBIAN_BINS, np.int64)
        self.below = self.above = 0
        self.dimension = g.dimension
        self.mid = g.shape[0] // 2  # the middle slice of a 3D grid (numpy axis 0: the slab axis)
        self.middle = np.full(g.shape[1:] if g.dimension == 3 else g.shape, np.nan, np.float32)

    def add(
        self,
        det: np.ndarray,
        rows: slice,
        sel: np.ndarray | None,
        nondiffeomorphic: int,
        nondiffeomorphic_volume: float,
    ) -> None:
        """Add one slab: `det` its ``det J`` (central differences), `rows` its numpy rows,
        `sel` its evaluated voxels (None: all), and its stencils' counts
        (:func:`~itk_nrreval.io._jacobian_kernels.slab_jacobians`)."""
        self.nondiffeomorphic += nondiffeomorphic
        self.nondiffeomorphic_volume += nondiffeomorphic_volume
        if self.dimension != 3:
            self.middle[rows] = np.where(sel, det, np.nan) if sel is not None else det
        elif rows.start <= self.mid < rows.stop:
            row = det[self.mid - rows.start]
            self.middle[:] = (
                np.where(sel[self.mid - rows.start], row, np.nan) if sel is not None else row
            )
        if sel is not None:
            if not sel.any():
                return
            det = det[sel]
        det = det.ravel()
        self.count += det.size
        self.folded += int(np.count_nonzero(det <= 0))
        self.jmin = min(self.jmin, float(det.min()))
        self.jmax = max(self.jmax, float(det.max()))
        logs = np.log(det[det > 0])
        self.hist += np.histogram(logs, bins=LOG_JACOBIAN_BINS, range=LOG_JACOBIAN_RANGE)[0]
        self.below += int(np.count_nonzero(logs < LOG_JACOBIAN_RANGE[0]))
        self.above += int(np.count_nonzero(logs > LOG_JACOBIAN_RANGE[1]))
        if logs.size:  # Chan et al.: merge (n, mean, M2) of this slab into the running ones
            m = float(logs.mean())
            m2 = float(np.sum((logs - m) ** 2))
            total = self.n_log + logs.size
            delta = m - self.mean_log
            self.mean_log += delta * logs.size / total
            self.m2_log += m2 + delta * delta * self.n_log * logs.size / total
            self.n_log = total

    def plausibility(self, consistency: float | None) -> Plausibility:
        """One image's :class:`Plausibility`, with its inverse consistency (mm) or None."""
        fraction = self.folded / self.count
        return Plausibility(
            folded_fraction=fraction,
            folded_max=fraction,
            sdlogj=math.sqrt(self.m2_log / self.n_log) if self.n_log else math.nan,
            jacobian_min=self.jmin,
            jacobian_max=self.jmax,
            inverse_consistency_mm=consistency,
            nondiffeomorphic_fraction=self.nondiffeomorphic / self.count,
            nondiffeomorphic_max=self.nondiffeomorphic / self.count,
            nondiffeomorphic_volume=self.nondiffeomorphic_volume / self.count,
        )

    def summary(self) -> JacobianSummary:
        return JacobianSummary(self.hist, self.below, self.above, self.folded, self.middle)


def _mean_round_trip(
    t: sitk.Transform | Sequence[sitk.Transform],
    inverse: PointwiseInverse,
    g: Geometry,
    mask: np.ndarray | None,
    max_slab_voxels: int,
) -> float | None:
    """Mean ``|T^-1(T(p)) - p|`` (mm) over the evaluated voxels of `g` whose every index is
    a multiple of :data:`INVERSE_CONSISTENCY_STEP` (over all of them when none is)
    (:func:`~itk_nrreval.io.transforms.composed_displacement`); None when not finite."""
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
    for rows, _halo, slab_grid, _inner in slabs(sub, max_slab_voxels):
        # An array view does not keep its image alive: name the image, or the view reads
        # freed memory (zeros on a Dask worker, issue 25).
        err = composed_displacement(inverse, t, slab_grid).reshape(-1, g.dimension)
        norms = np.sqrt(np.sum(err * err, axis=-1))
        if sub_mask is not None:
            norms = norms[sub_mask[rows].ravel()]
        err_sum += float(norms.sum())
        count += norms.size
    return err_sum / count if count and math.isfinite(err_sum) else None


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
