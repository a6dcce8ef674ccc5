"""A measurement grid taken slab by slab along its last ITK axis (z in 3D), so that memory stays
bounded on large grids: the grid from an image, its slabs (each with one row of halo, so that
central differences inside a slab are the whole grid's), and a transform's displacement
sampled on each slab.

Used by the deformation measures and the affine fit (:mod:`itk_nrreval.io.plausibility`); the
results do not depend on the slab size.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence

import numpy as np
import SimpleITK as sitk

from .._errors import InputError
from ._images import Geometry
from .transforms import displacement_array, displacement_field

__all__ = ["SLAB_VOXELS", "as_geometry", "slabs", "slab_displacements"]


#: Voxels per slab (with its halo) above which the grid is processed in slabs along its last
#: ITK axis (z in 3D): the Jacobian of one slab takes about 200 bytes per voxel.
SLAB_VOXELS = 1 << 20


def as_geometry(grid: Geometry | sitk.Image) -> Geometry:
    if isinstance(grid, Geometry):
        return grid
    if isinstance(grid, sitk.Image):
        return Geometry.from_image(grid)
    raise InputError(f"grid: expected a Geometry or a SimpleITK image, got {type(grid).__name__}")


def slabs(g: Geometry, max_voxels: int) -> Iterator[tuple[slice, Geometry, Geometry, slice]]:
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


def slab_displacements(
    t: sitk.Transform | Sequence[sitk.Transform],
    g: Geometry,
    displacement: np.ndarray | None,
    max_slab_voxels: int,
) -> Iterator[tuple[slice, Geometry, slice, np.ndarray]]:
    """Per slab of `g` (:func:`slabs`): ``(rows, slab_grid, inner, u)``, `u` the displacement
    on the slab with its halo rows (mm, shape ``(*halo.shape, d)``): sampled by the compiled
    kernels, or by ITK, or cut from `displacement` when the caller sampled it already.

    `u` may be a view of an image this generator holds: use it before asking for the next
    slab, and do not keep it.
    """
    for rows, halo_grid, slab_grid, inner in slabs(g, max_slab_voxels):
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
        yield rows, slab_grid, inner, u
        del u, field
