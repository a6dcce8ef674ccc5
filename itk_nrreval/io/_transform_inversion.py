"""Inverting transforms: whole inverse transforms, and inverses evaluated at points.

:func:`invert` inverts a transform or a chain piece by piece: linear pieces exactly, each
displacement field with ITK's fixed-point inversion on its grid grown by its largest
displacement (optionally from a coarser grid, refined by fixed-point steps on the field's
own grid). :class:`PointwiseInverse` is the same numerical inverse evaluated at any points,
without an inverse field; :func:`composed_displacement` uses it for ``T^-1(T(p)) - p``.
The conventions (which way a transform maps, chain order, field layout) are those of
:mod:`itk_nrreval.io.transforms`, which lists every public name here.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass

import numba
import numpy as np
import SimpleITK as sitk

from .._errors import InputError
from ._displacements import displacement_field, points_after
from ._field_kernels import (
    add_voxel_points,
    affine_in_place,
    as_plane,
    fixed_point_at_points,
    fixed_point_step,
    index_map,
    linear_parts,
    voxel_point_map,
)
from ._images import Geometry
from ._transform_io import field_transform, itk_error_reason, transform_pieces

__all__ = ["INVERSION_STOPPING", "invert", "PointwiseInverse", "composed_displacement"]


#: The stopping rule of ITK's field inversion by default (:func:`invert`'s `max_iterations`,
#: `max_error`, `mean_error`), and always in :class:`PointwiseInverse`.
INVERSION_STOPPING = (50, 0.01, 1e-4)


def invert(
    transform: sitk.Transform | str | os.PathLike | Sequence,
    *,
    grid: sitk.Image | Geometry | None = None,
    max_iterations: int = INVERSION_STOPPING[0],
    max_error: float = INVERSION_STOPPING[1],
    mean_error: float = INVERSION_STOPPING[2],
    field_step: int = 1,
    refine_steps: int = 3,
) -> sitk.Transform:
    """The inverse mapping (image points to reference points).

    Linear transforms are inverted exactly. A displacement field is inverted with
    ``sitk.InvertDisplacementField`` (fixed-point iteration; never the slow
    ``InverseDisplacementField``) on its own grid grown by its largest displacement, so
    that the inverse is right wherever the field moves points off its grid. A chain is
    inverted piece by piece in reverse order: ``(t2 o t1)^-1 = t1^-1 o t2^-1``, so each
    field is inverted where it lives. Other smooth pieces (B-splines) are first sampled as
    a displacement field on `grid`.

    Parameters
    ----------
    transform : sitk.Transform, path or chain (ANTs order)
    grid : sitk.Image or Geometry, optional
        Where to sample pieces that are neither linear nor displacement fields (e.g.
        B-splines): the registration's reference grid, on which those pieces act.
    max_iterations : int
        Iterations of the field inversion.
    max_error, mean_error : float
        Stopping tolerances of the field inversion (voxels; the filter's units).
    field_step : int
        Invert each displacement field first on every `field_step`-th node of its grid along
        each axis (its own values there; ``field_step**dim`` times fewer voxels to iterate
        on), then refine that inverse on the field's own grid by `refine_steps` fixed-point
        steps ``v(q) <- -u(q + v(q))`` (:func:`_fixed_point_steps`). 1 (the default) inverts
        on the field's own grid alone.
    refine_steps : int
        Fixed-point steps on the field's own grid after a coarse inversion (`field_step` > 1;
        each halves the coarse inverse's error or better where the field's Jacobian is
        near the identity).

    Returns
    -------
    sitk.Transform
        A transform of the same dimension; a composite when the input was one.

    Raises
    ------
    InputError
        A piece that is neither linear nor a displacement field, and no `grid`.
    """
    parts = transform_pieces(transform)
    inverted = [
        _invert_one(t, grid, (max_iterations, max_error, mean_error), field_step, refine_steps)
        for t in parts
    ]
    # sitk list [a, b] means a(b(p)); its inverse is b^-1(a^-1(q)): list [b^-1, a^-1].
    inverted = list(reversed(inverted))
    return inverted[0] if len(inverted) == 1 else sitk.CompositeTransform(inverted)


def _invert_one(t: sitk.Transform, grid, stopping: tuple, step: int, refine_steps: int):
    t = t.Downcast()
    if not t.IsLinear() and not isinstance(t, sitk.DisplacementFieldTransform):
        if grid is None:
            raise InputError(
                f"{t.GetName()}: cannot invert this transform type without a grid to sample "
                "it on (pass grid=, e.g. the registration's reference)"
            )
        t = field_transform(displacement_field(t, grid))
    if isinstance(t, sitk.DisplacementFieldTransform):
        own = t.GetDisplacementField()
        inverse = _coarse_inverse(own, int(step), stopping)
        if step > 1:
            inverse = _fixed_point_steps(own, inverse, int(refine_steps))
        if inverse.GetPixelID() != sitk.sitkVectorFloat64:
            inverse = sitk.Cast(inverse, sitk.sitkVectorFloat64)
        # `inverse` is this function's own image: the transform may take its buffer, where
        # field_transform would copy it first (~0.1 s per 9 M voxels)
        return sitk.DisplacementFieldTransform(inverse)
    if t.IsLinear():
        try:
            return t.GetInverse().Downcast()
        except RuntimeError as exc:
            raise InputError(f"{t.GetName()}: not invertible ({itk_error_reason(exc)})") from None
    raise AssertionError("unreachable: every piece is linear or a field here")


def _coarse_inverse(field: sitk.Image, step: int, stopping: tuple) -> sitk.Image:
    """ITK's inverse of `field` from every `step`-th node of its grid, grown by its largest
    displacement (:func:`_edge_padded`); `stopping` is ``(iterations, max_error,
    mean_error)``."""
    iterations, max_error, mean_error = stopping
    return sitk.InvertDisplacementField(
        _edge_padded(_every_nth_node(field, step)),
        maximumNumberOfIterations=int(iterations),
        maxErrorToleranceThreshold=float(max_error),
        meanErrorToleranceThreshold=float(mean_error),
        enforceBoundaryCondition=False,
    )


def _every_nth_node(field: sitk.Image, step: int) -> sitk.Image:
    """`field` on every `step`-th node along each axis (from its origin): its own values there."""
    if step == 1:
        return field
    dim = field.GetDimension()
    arr = sitk.GetArrayViewFromImage(field)[(slice(None, None, step),) * dim]
    out = sitk.GetImageFromArray(np.ascontiguousarray(arr), isVector=True)
    out.SetSpacing([s * step for s in field.GetSpacing()])
    out.SetOrigin(field.GetOrigin())
    out.SetDirection(field.GetDirection())
    return out


def _edge_padded(field: sitk.Image) -> sitk.Image:
    """`field` on its grid grown by its largest displacement, extended by its edge values.

    The inverse of ``p -> p + u(p)`` is needed wherever the forward map lands, which reaches
    up to ``max |u|`` beyond the field's own grid: inverted on that grid alone, it would be the
    identity there (a 12 mm shift came back 12 mm out). Beyond the grown grid no point of the
    field's grid can land, so the inverse is the identity there, as ITK gives outside a field.
    The extension by edge values is what lets the fixed-point inversion find preimages inside
    the grid for points that landed outside it.
    """
    arr = sitk.GetArrayFromImage(field)  # (*zyx, dim), mm
    spacing = np.array(field.GetSpacing())
    pad = _padding(arr, spacing)  # voxels per ITK axis
    if not pad.any():
        return field
    dim = field.GetDimension()
    padded = np.pad(arr, [*((k, k) for k in pad[::-1]), (0, 0)], mode="edge")
    out = sitk.GetImageFromArray(padded, isVector=True)
    direction = np.array(field.GetDirection()).reshape(dim, dim)
    out.SetSpacing(field.GetSpacing())
    out.SetDirection(field.GetDirection())
    out.SetOrigin((np.array(field.GetOrigin()) - direction @ (pad * spacing)).tolist())
    return out


def _padding(u: np.ndarray, spacing: np.ndarray) -> np.ndarray:
    """Voxels per ITK axis by which :func:`_edge_padded` grows a field `u` (mm, numpy order,
    components last): its largest displacement and one voxel; 0 for a zero field."""
    reach = math.sqrt(_largest_squared_norm(u.reshape(-1, u.shape[-1]))) if u.size else 0.0
    if reach == 0.0:
        return np.zeros(len(spacing), int)
    return np.ceil(reach / spacing).astype(int) + 1


@numba.njit(cache=True, nogil=True)
def _largest_squared_norm(u):  # pragma: no cover - compiled
    """max_i |u_i|^2 of the rows of `u` (m, d): one pass, no temporaries (0.2 s -> 0.02 s at
    1 mm)."""
    best = 0.0
    for i in range(u.shape[0]):
        s = 0.0
        for c in range(u.shape[1]):
            s += u[i, c] * u[i, c]
        best = max(best, s)
    return best


def _fixed_point_steps(field: sitk.Image, inverse: sitk.Image, steps: int) -> sitk.Image:
    """The inverse of `field` on its grid grown as :func:`_edge_padded` grows it: `inverse`
    (on a coarser grid of the same direction) refined by `steps` fixed-point steps
    ``v(q) <- -u(q + v(q))``.

    This is the iteration ``sitk.InvertDisplacementField`` runs, started from the coarse
    inverse instead of zero, with both fields interpolated linearly and extended by their
    edge values beyond their grids (as :func:`_edge_padded` extends them; `field` itself is
    never padded: sampling it clamped to its grid is the same).
    """
    dim = field.GetDimension()
    u = sitk.GetArrayViewFromImage(field)  # `field` stays named: the view reads its buffer
    spacing = np.asarray(field.GetSpacing())
    direction = np.asarray(field.GetDirection()).reshape(dim, dim)
    pad = _padding(u, spacing)  # voxels per ITK axis
    origin = np.asarray(field.GetOrigin()) - direction @ (pad * spacing)
    v = sitk.GetArrayFromImage(inverse)
    _, to_index = index_map(field)  # mm -> the field's index steps (ITK axis order)
    # the grown grid's node i in the coarse inverse's continuous index: offset + ratio * i
    ratio, offset = np.zeros(3), np.zeros(3)
    ratio[:dim] = spacing / np.asarray(inverse.GetSpacing())
    coarse_to_index = direction.T / np.asarray(inverse.GetSpacing())[:, None]
    offset[:dim] = coarse_to_index @ (origin - np.asarray(inverse.GetOrigin()))
    u_offset = np.zeros(3)
    u_offset[:dim] = -pad
    if dim == 2:  # one plane of 3D with a zero third component: the same numbers, one kernel
        u, v = as_plane(u), as_plane(v)
    grown = np.zeros(3, int)
    grown[:dim] = 2 * pad  # ITK axis order
    shape = (u.shape[0] + grown[2], u.shape[1] + grown[1], u.shape[2] + grown[0], 3)
    buffers = [np.empty(shape), np.empty(shape) if steps > 1 else None]
    on_grid = False
    for n in range(max(int(steps), 1)):
        out = buffers[n % 2]
        fixed_point_step(u, v, out, u_offset, to_index, ratio, offset, on_grid)
        v, on_grid = out, True
    del buffers, out  # the other buffer goes before the image copies `v` (283 MB at 1 mm)
    result = sitk.GetImageFromArray(v[0, ..., :2] if dim == 2 else v, isVector=True)
    result.SetSpacing(field.GetSpacing())
    result.SetDirection(field.GetDirection())
    result.SetOrigin(origin.tolist())
    return result


class PointwiseInverse:
    """A transform's numerical inverse, evaluated at any points without an inverse field.

    The inverse :func:`invert` gives with ``field_step`` and ``refine_steps``, except that
    each displacement field's fixed-point steps ``y <- r - u(y)`` run at the points asked
    about rather than at the nodes of the field's grid (whose results :func:`invert` then
    interpolates). For a round trip ``T^-1(T(p))`` on every second voxel this is an eighth of
    the refinement's work and no full-size inverse field (issue 30: 1.9 s -> 0.3 s at 1 mm).
    The coarse inverse it starts from and the convention beyond the field's grid are
    :func:`invert`'s: the inverse is the identity beyond the field's grid grown by its
    largest displacement, and the field is extended by its edge values.

    Parameters
    ----------
    transform : sitk.Transform, path, chain (ANTs order) or TransformPieces
        Grid points -> image points (mm, LPS).
    grid : sitk.Image or Geometry, optional
        Where pieces that are neither linear nor displacement fields (B-splines) are sampled
        as displacement fields first (as :func:`invert`).
    field_step : int
        Each displacement field is first inverted by ITK on every `field_step`-th node of
        its grid (:func:`invert`).
    refine_steps : int
        Fixed-point steps at each point after the coarse inverse.

    Raises
    ------
    InputError
        A piece that is neither linear nor a displacement field and no `grid`, or a linear
        piece that is not invertible.
    """

    def __init__(
        self,
        transform,
        *,
        grid: sitk.Image | Geometry | None = None,
        field_step: int = 1,
        refine_steps: int = 3,
    ):
        pieces = transform_pieces(transform)  # files read once; no composite is built
        self.dimension = pieces[0].GetDimension()
        self.refine_steps = int(refine_steps)
        # sitk list [a, b] means a(b(p)): its inverse applies a^-1 first
        self._pieces = [_pointwise_piece(t, grid, int(field_step)) for t in pieces]

    def map_points(self, points: np.ndarray) -> np.ndarray:
        """``T^-1`` at `points`.

        Parameters
        ----------
        points : ndarray of shape (m, dim)
            Physical points (mm, LPS, ITK (x, y[, z]) order).

        Returns
        -------
        ndarray of shape (m, dim), float64
            Their images under the numerical inverse.
        """
        y = np.zeros((len(points), 3))
        y[:, : self.dimension] = points
        self._map_in_place(y)
        return y[:, : self.dimension]

    def _map_in_place(self, y: np.ndarray) -> None:
        """:meth:`map_points` on points as 3-vectors (m, 3), in place."""
        for piece in self._pieces:
            if isinstance(piece, _FieldPiece):
                fixed_point_at_points(y, *piece.arrays(), self.refine_steps)
            else:
                affine_in_place(y, *piece)


@dataclass(frozen=True)
class _FieldPiece:
    """A displacement field and its coarse inverse, as :func:`fixed_point_at_points` reads
    them (3D arrays; a 2D field as one plane)."""

    u: np.ndarray  # (nz, ny, nx, 3), mm
    u_origin: np.ndarray  # (3,)
    u_to_index: np.ndarray  # (3, 3): mm -> u's index steps (ITK axis order)
    lower: np.ndarray  # (3,): the grown grid's buffer, in u's continuous index
    upper: np.ndarray
    v: np.ndarray  # the coarse inverse, (vz, vy, vx, 3)
    v_origin: np.ndarray
    v_to_index: np.ndarray
    images: tuple  # the images whose buffers `u` and `v` view (kept alive with them)

    def arrays(self) -> tuple:
        return (
            self.u,
            self.u_origin,
            self.u_to_index,
            self.lower,
            self.upper,
            self.v,
            self.v_origin,
            self.v_to_index,
        )


def _pointwise_piece(t: sitk.Transform, grid, step: int):
    """One piece of :class:`PointwiseInverse`: a :class:`_FieldPiece`, or the inverse of a
    linear piece as ``(matrix (3, 3), offset (3,))`` acting on 3-vectors."""
    t = t.Downcast()
    dim = t.GetDimension()
    if t.IsLinear():
        try:
            inverse = t.GetInverse()
        except RuntimeError as exc:
            raise InputError(f"{t.GetName()}: not invertible ({itk_error_reason(exc)})") from None
        return linear_parts(inverse)
    if not isinstance(t, sitk.DisplacementFieldTransform):
        if grid is None:
            raise InputError(
                f"{t.GetName()}: cannot invert this transform type without a grid to sample "
                "it on (pass grid=, e.g. the registration's reference)"
            )
        t = field_transform(displacement_field(t, grid))
    field = t.GetDisplacementField()
    coarse = _coarse_inverse(field, step, INVERSION_STOPPING)
    # views: the piece keeps `field` and `coarse` alive (a copy of a 1 mm field: 0.1 s)
    u = sitk.GetArrayViewFromImage(field)
    v = sitk.GetArrayViewFromImage(coarse)
    pad = _padding(u, np.asarray(field.GetSpacing()))
    if dim == 2:
        u, v = as_plane(u), as_plane(v)
    lower, upper = np.full(3, -np.inf), np.full(3, np.inf)
    # ITK's inside-buffer test of the grown grid: -0.5 <= index < size - 0.5 there
    lower[:dim] = -pad - 0.5
    upper[:dim] = np.asarray(field.GetSize()) + pad - 0.5
    return _FieldPiece(u, *index_map(field), lower, upper, v, *index_map(coarse), (field, coarse))


def composed_displacement(
    inverse: PointwiseInverse, first: sitk.Transform | Sequence[sitk.Transform], grid: Geometry
) -> np.ndarray:
    """``inverse(first(p)) - p`` on `grid`'s voxels p: `first` sampled at the voxels, then
    the numerical inverse at the points it gives (no inverse field is built).

    Parameters
    ----------
    inverse : PointwiseInverse
        A numerical inverse ``T^-1``.
    first : sitk.Transform or list of sitk.Transform
        Grid points -> points where `inverse` is evaluated (mm, LPS). A transform is
        sampled by ITK (``TransformToDisplacementField``); its pieces (:func:`leaves`), all
        linear or displacement fields (:func:`has_only_fields`), by the compiled kernels of
        :func:`displacement_after`, to about 1e-13 mm of ITK's sampling, faster and without
        ITK's output image and its copy (0.4 GB at 1 mm).
    grid : Geometry
        The points p.

    Returns
    -------
    ndarray of shape (*grid.shape, dim)
        Displacements in mm, numpy axis order for the grid and ITK (x, y[, z]) order last
        (as ``sitk.GetArrayFromImage`` of a displacement field).
    """
    dim = grid.dimension
    origin, matrix, size = voxel_point_map(grid)
    if isinstance(first, (list, tuple)):
        y = points_after(first, grid)  # first(p)
    else:
        # An array view does not keep its image alive: `field` stays named while it is read
        field = displacement_field(first, grid)
        if dim == 3:  # one copy of the field, not a zeroed array filled from it
            y = sitk.GetArrayFromImage(field).reshape(-1, 3).astype(np.float64, copy=False)
        else:
            y = np.zeros((math.prod(grid.size), 3))
            y[:, :dim] = sitk.GetArrayViewFromImage(field).reshape(-1, dim)
        del field
        add_voxel_points(y, origin, matrix, size, 1.0)  # first(p)
    inverse._map_in_place(y)
    add_voxel_points(y, origin, matrix, size, -1.0)
    return (y if dim == 3 else y[:, :dim]).reshape(*grid.shape, dim)
