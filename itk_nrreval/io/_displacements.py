"""A transform's displacement on a grid: ``T(p) - p``, or ``T(p + d(p)) - p``, at its voxels.

:func:`displacement_field` samples any transform with ITK; :func:`displacement_array`,
:func:`displacement_after` and :class:`PointMap` sample transforms made of linear maps and
displacement fields only (:func:`has_only_fields`) with the compiled kernels of
:mod:`itk_nrreval.io._field_kernels`, to about 1e-13 mm of ITK's sampling, without ITK's
output image, its copy, or a composite transform built for the purpose.

The conventions (which way a transform maps, chain order, field layout) are those of
:mod:`itk_nrreval.io.transforms`, which lists every public name here.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import SimpleITK as sitk

from ._field_kernels import (
    add_voxel_points,
    affine_in_place,
    as_plane,
    field_in_place,
    index_map,
    linear_parts,
    voxel_point_map,
    voxel_points,
    voxel_points_plus,
)
from ._images import Geometry
from ._transform_io import TransformPieces, flatten, leaves

__all__ = [
    "displacement_field",
    "displacement_array",
    "displacement_after",
    "PointMap",
    "points_after",
    "has_only_fields",
    "is_linear",
]


def _grid(reference: sitk.Image | Geometry) -> Geometry:
    """The grid of `reference`: itself when a Geometry, else the image's."""
    return reference if isinstance(reference, Geometry) else Geometry.from_image(reference)


def displacement_field(transform: sitk.Transform, reference: sitk.Image | Geometry) -> sitk.Image:
    """Sample ``T(p) - p`` on the grid of `reference`.

    Parameters
    ----------
    transform : sitk.Transform
        Any transform of the grid's dimension.
    reference : sitk.Image or Geometry
        The grid of points p (voxel centres, mm, LPS).

    Returns
    -------
    sitk.Image
        ``sitkVectorFloat64`` image on that grid; vectors in mm, ITK (x, y[, z]) order.
    """
    g = _grid(reference)
    return sitk.TransformToDisplacementField(
        transform,
        sitk.sitkVectorFloat64,
        list(g.size),
        list(g.origin),
        list(g.spacing),
        list(g.direction),
    )


def displacement_array(
    transform: sitk.Transform | Sequence[sitk.Transform], grid: Geometry
) -> np.ndarray:
    """``T(p) - p`` on `grid`'s voxels p, as an array: by the compiled kernels of
    :func:`displacement_after` when T is linear maps and displacement fields only (to about
    1e-13 mm of ITK's sampling, without its output image and the copy of it), otherwise by
    ITK (:func:`displacement_field`).

    Parameters
    ----------
    transform : sitk.Transform or list of sitk.Transform
        T, or its pieces (:func:`leaves`, :func:`transform_pieces`): grid points -> image
        points (mm, LPS).
    grid : Geometry
        The points p.

    Returns
    -------
    ndarray of shape (*grid.shape, dim), float64
        Displacements in mm, ITK (x, y[, z]) order last (as ``sitk.GetArrayFromImage`` of
        :func:`displacement_field`).
    """
    pieces = leaves(transform)  # once: taking a composite apart copies its fields
    if not has_only_fields(pieces):
        t = transform if isinstance(transform, sitk.Transform) else flatten(pieces)
        return sitk.GetArrayFromImage(displacement_field(t, grid))
    return _minus_voxel_points(points_after(pieces, grid), grid)


def displacement_after(
    transform: sitk.Transform | Sequence[sitk.Transform], displacement: np.ndarray, grid: Geometry
) -> np.ndarray:
    """``T(p + d(p)) - p`` on `grid`'s voxels p: the displacement of ``T o D``, where D is
    ``p -> p + d(p)`` given at the voxels (a frame F on the common grid).

    What ``displacement_field(sitk.CompositeTransform([T, D]), grid)`` gives, D as a
    displacement-field transform on `grid`, to about 1e-13 mm (the same interpolation in
    another order of operations), without building that composite, which copies every
    field of T and D (at 1 mm, 0.1 s and 215 MB each).

    Parameters
    ----------
    transform : sitk.Transform or list of sitk.Transform
        T, of linear pieces and displacement fields only (:func:`has_only_fields`); each
        field by ITK's rules: linear interpolation, the edge values in the half-voxel
        border of its buffer, the identity beyond. Or T's pieces, :func:`leaves`.
    displacement : ndarray of shape (*grid.shape, dim)
        d(p) in mm, ITK (x, y[, z]) order last; any float dtype.
    grid : Geometry
        The points p.

    Returns
    -------
    ndarray of shape (*grid.shape, dim), float64
        Displacements in mm, as ``sitk.GetArrayFromImage`` of a displacement field.

    Raises
    ------
    ValueError
        A piece of T is neither linear nor a displacement field, or `displacement` is not
        shaped as the grid.
    """
    dim = grid.dimension
    if displacement.shape != (*grid.shape, dim):
        raise ValueError(f"displacement: shape {displacement.shape}, not the grid's")
    return _minus_voxel_points(points_after(transform, grid, displacement), grid)


@dataclass(frozen=True, eq=False)
class PointMap:
    """The map ``p -> T(p + d(p))`` at a grid's voxels p, for the compiled kernels to
    evaluate a slab of the grid at a time (:meth:`points`): no array of the whole grid's
    points is built, where a caller needs each slab's points once.

    Attributes
    ----------
    pieces : TransformPieces
        T's pieces (:func:`transform_pieces`), linear maps and displacement fields only
        (:func:`has_only_fields`): grid points -> image points (mm, LPS). Sampled as
        :func:`displacement_after` samples them (to about 1e-13 mm of ITK's).
    displacement : ndarray of shape ``(*grid.shape, dim)`` or None
        d in mm on the whole grid, ITK (x, y[, z]) order last (a frame F's ``F(p) - p``), or
        None for d = 0.
    """

    pieces: TransformPieces
    displacement: np.ndarray | None = None

    def __post_init__(self):
        if not has_only_fields(self.pieces):
            raise ValueError("transform: a piece is neither linear nor a displacement field")

    def points(self, slab: Geometry, first: int, *, out: np.ndarray | None = None) -> np.ndarray:
        """``T(p + d(p))`` at the voxels of `slab`, the whole grid's planes (numpy axis 0)
        from `first` on: (m, 3) float64, mm, C order, a 2D point's third coordinate 0.
        `out`, if given, is a float64 C-ordered array of at least m rows of 3 that the
        points are written into (its first m rows are returned)."""
        d = self.displacement
        if d is not None:
            d = d[first : first + slab.shape[0]]
        return points_after(self.pieces, slab, d, out=out)


def points_after(
    transform: sitk.Transform | Sequence[sitk.Transform],
    grid: Geometry,
    displacement: np.ndarray | None = None,
    *,
    out: np.ndarray | None = None,
) -> np.ndarray:
    """``T(p + d(p))`` (d = 0 when None) at `grid`'s voxels p: (n_voxels, 3) float64, mm,
    C order, a 2D point's third coordinate 0 (:func:`displacement_after`); into the first
    rows of `out` when given."""
    dim = grid.dimension
    pieces = leaves(transform)  # once: taking a composite apart copies its fields
    if not all(_is_linear_or_field(t) for t in pieces):
        raise ValueError("transform: a piece is neither linear nor a displacement field")
    origin, matrix, size = voxel_point_map(grid)
    m = math.prod(grid.size)
    y = np.empty((m, 3)) if out is None else out[:m]
    if displacement is None:
        voxel_points(origin, matrix, size, y)  # p
    else:
        voxel_points_plus(displacement.reshape(-1, dim), origin, matrix, size, y)  # D(p)
    # SimpleITK's list [a, b] is a(b(p)): the last piece acts first
    for piece in reversed(pieces):
        if piece.IsLinear():
            affine_in_place(y, *linear_parts(piece))
            continue
        field = piece.GetDisplacementField()
        u = sitk.GetArrayViewFromImage(field)  # `field` stays named while `u` is read
        # ITK's IsInsideBuffer, -0.5 <= index < size - 0.5, in the kernel's 3D axes
        lower, upper = np.full(3, -0.5), np.full(3, 0.5)
        upper[:dim] = np.asarray(field.GetSize()) - 0.5
        field_in_place(y, as_plane(u) if dim == 2 else u, *index_map(field), lower, upper)
        del u, field
    return y


def _minus_voxel_points(y: np.ndarray, grid: Geometry) -> np.ndarray:
    """Points ``q(p)`` at `grid`'s voxels (n_voxels, 3), as :func:`points_after` gives
    them, less the voxels' points p, in place: ``(*grid.shape, dim)``, ITK order last."""
    dim = grid.dimension
    add_voxel_points(y, *voxel_point_map(grid), -1.0)
    return (y if dim == 3 else y[:, :dim]).reshape(*grid.shape, dim)


def has_only_fields(transform: sitk.Transform | Sequence[sitk.Transform]) -> bool:
    """Whether every piece of `transform` (or every one of its pieces, :func:`leaves`) is
    linear or a displacement field."""
    return all(_is_linear_or_field(t) for t in leaves(transform))


def is_linear(transform: sitk.Transform | TransformPieces) -> bool:
    """Whether `transform` is linear; given as its pieces, whether every piece is (what
    their composite's ``IsLinear`` says), without building the composite."""
    if isinstance(transform, TransformPieces):
        return all(piece.IsLinear() for piece in transform)
    return transform.IsLinear()


def _is_linear_or_field(t: sitk.Transform) -> bool:
    return t.IsLinear() or isinstance(t, sitk.DisplacementFieldTransform)
