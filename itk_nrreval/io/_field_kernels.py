"""Compiled kernels that move points through linear maps and displacement fields.

Each displacement field is sampled as ITK's ``DisplacementFieldTransform`` samples it
(linear interpolation, clamped to its nodes; the identity beyond its buffer), so that the
points these kernels give agree with ITK's to about 1e-13 mm. Everything is in a 3D form: a
point is a row of 3 coordinates (mm, ITK (x, y, z) order), a 2D grid or field one plane of a
3D one (:func:`as_plane`, :func:`voxel_point_map`, :func:`index_map`). The kernels run in
parallel over points or slices, each computed alone by the same operations, so the numbers
do not depend on the number of threads. Used by :mod:`itk_nrreval.io._displacements` and
:mod:`itk_nrreval.io._transform_inversion` (whose fixed-point steps, :func:`fixed_point_step`
and :func:`fixed_point_at_points`, are here too).

Kernels that inline one another stay in this one module: numba's cache (``cache=True``)
checks only the file of the kernel it compiled, so a kernel inlining an edited kernel of
another file would keep its stale compiled code.
"""

from __future__ import annotations

import numba
import numpy as np
import SimpleITK as sitk

from ._images import Geometry

__all__ = [
    "voxel_point_map",
    "index_map",
    "linear_parts",
    "as_plane",
    "add_voxel_points",
    "voxel_points",
    "voxel_points_plus",
    "affine_in_place",
    "field_in_place",
    "continuous_index",
    "in_box",
    "corner",
    "trilinear",
    "linear_at_index",
    "linear_at",
    "fixed_point_step",
    "fixed_point_at_points",
]


def voxel_point_map(grid: Geometry) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`grid`'s voxel -> point map in the kernels' 3D form: (origin (3,), index -> point
    matrix (3, 3), ITK size (3,), int64), a 2D grid in the upper-left block."""
    dim = grid.dimension
    origin, matrix = np.zeros(3), np.zeros((3, 3))
    origin[:dim] = grid.origin
    matrix[:dim, :dim] = np.asarray(grid.direction, float).reshape(dim, dim) * grid.spacing
    size = np.ones(3, np.int64)
    size[:dim] = grid.size
    return origin, matrix, size


def index_map(image: sitk.Image) -> tuple[np.ndarray, np.ndarray]:
    """`image`'s origin (3,) and its mm -> continuous index map (3, 3), ITK axis order, as
    3D (a 2D image's third row and column zero)."""
    dim = image.GetDimension()
    origin, to_index = np.zeros(3), np.zeros((3, 3))
    origin[:dim] = image.GetOrigin()
    direction = np.asarray(image.GetDirection()).reshape(dim, dim)
    to_index[:dim, :dim] = direction.T / np.asarray(image.GetSpacing())[:, None]
    return origin, to_index


def linear_parts(t: sitk.Transform) -> tuple[np.ndarray, np.ndarray]:
    """A linear transform as ``(matrix (3, 3), offset (3,))`` acting on 3-vectors (a 2D
    one in the upper-left block), from the images of the origin and the unit vectors."""
    dim = t.GetDimension()
    origin = np.asarray(t.TransformPoint((0.0,) * dim))
    matrix, offset = np.eye(3), np.zeros(3)
    for j in range(dim):
        unit = np.zeros(dim)
        unit[j] = 1.0
        matrix[:dim, j] = np.asarray(t.TransformPoint(unit.tolist())) - origin
    offset[:dim] = origin
    return matrix, offset


def as_plane(a: np.ndarray) -> np.ndarray:
    """A 2D field (ny, nx, 2) as one plane of a 3D one, (1, ny, nx, 3), third component 0."""
    plane = np.zeros((1, *a.shape[:2], 3))
    plane[0, ..., :2] = a
    return plane


@numba.njit(cache=True, parallel=True)
def add_voxel_points(y, origin, matrix, size, sign):  # pragma: no cover - compiled
    """In place, row f of `y` (m, 3) += `sign` * the physical point of voxel f of a grid of
    ITK `size` (3,) (C order: x fastest): ``origin + matrix @ index``."""
    nx, ny = size[0], size[1]
    for f in numba.prange(y.shape[0]):
        i = f % nx
        j = (f // nx) % ny
        k = f // (nx * ny)
        for a in range(3):
            y[f, a] += sign * (origin[a] + matrix[a, 0] * i + matrix[a, 1] * j + matrix[a, 2] * k)


@numba.njit(cache=True, parallel=True)
def voxel_points(origin, matrix, size, y):  # pragma: no cover - compiled
    """Row f of `y` (m, 3) = the physical point of voxel f (:func:`add_voxel_points`'s
    arithmetic on a zeroed `y`: the same bits), in one pass over `y`'s pages."""
    nx, ny = size[0], size[1]
    for f in numba.prange(y.shape[0]):
        i = f % nx
        j = (f // nx) % ny
        k = f // (nx * ny)
        for a in range(3):
            point = origin[a] + matrix[a, 0] * i + matrix[a, 1] * j + matrix[a, 2] * k
            y[f, a] = 0.0 + 1.0 * point


@numba.njit(cache=True, parallel=True)
def voxel_points_plus(d, origin, matrix, size, y):  # pragma: no cover - compiled
    """Row f of `y` (m, 3) = row f of `d` (m, dim; 0 beyond dim) + the physical point of
    voxel f (:func:`add_voxel_points`'s arithmetic: the same bits as adding it to a zeroed
    copy of `d`), in one pass."""
    nx, ny = size[0], size[1]
    dim = d.shape[1]
    for f in numba.prange(y.shape[0]):
        i = f % nx
        j = (f // nx) % ny
        k = f // (nx * ny)
        for a in range(3):
            v = np.float64(d[f, a]) if a < dim else 0.0
            y[f, a] = v + 1.0 * (origin[a] + matrix[a, 0] * i + matrix[a, 1] * j + matrix[a, 2] * k)


@numba.njit(cache=True, parallel=True)
def affine_in_place(y, matrix, offset):  # pragma: no cover - compiled
    """In place, each row of `y` (m, 3) -> ``matrix @ row + offset``."""
    for f in numba.prange(y.shape[0]):
        a0, a1, a2 = y[f, 0], y[f, 1], y[f, 2]
        for r in range(3):
            y[f, r] = matrix[r, 0] * a0 + matrix[r, 1] * a1 + matrix[r, 2] * a2 + offset[r]


@numba.njit(cache=True, parallel=True)
def field_in_place(y, u, origin, to_index, lower, upper):  # pragma: no cover - compiled
    """In place, each point p (row of `y` (m, 3)) -> ``p + u(p)`` where p's continuous index
    in u's grid lies in ``[lower, upper)`` on every axis (ITK's DisplacementFieldTransform:
    the buffer's -0.5 to size - 0.5), `u` (nz, ny, nx, 3) sampled linearly, clamped to its
    nodes; unchanged elsewhere. `origin`, `to_index`: u's grid (:func:`index_map`)."""
    for f in numba.prange(y.shape[0]):
        p0, p1, p2 = y[f, 0], y[f, 1], y[f, 2]
        c0, c1, c2 = continuous_index(p0, p1, p2, origin, to_index)
        if not in_box(c0, c1, c2, lower, upper):
            continue
        w0, w1, w2 = linear_at_index(u, c0, c1, c2)
        y[f, 0], y[f, 1], y[f, 2] = p0 + w0, p1 + w1, p2 + w2


@numba.njit(cache=True, inline="always")
def continuous_index(p0, p1, p2, origin, to_index):  # pragma: no cover - compiled
    """Physical point p's continuous index (ITK axis order) in a grid of `origin` (3,) and
    `to_index` (3, 3): mm -> index (:func:`index_map`)."""
    d0, d1, d2 = p0 - origin[0], p1 - origin[1], p2 - origin[2]
    return (
        to_index[0, 0] * d0 + to_index[0, 1] * d1 + to_index[0, 2] * d2,
        to_index[1, 0] * d0 + to_index[1, 1] * d1 + to_index[1, 2] * d2,
        to_index[2, 0] * d0 + to_index[2, 1] * d1 + to_index[2, 2] * d2,
    )


@numba.njit(cache=True, inline="always")
def in_box(c0, c1, c2, lower, upper):  # pragma: no cover - compiled
    """Whether a continuous index lies in ``[lower, upper)`` on every axis (NaN: no)."""
    return lower[0] <= c0 < upper[0] and lower[1] <= c1 < upper[1] and lower[2] <= c2 < upper[2]


@numba.njit(cache=True, inline="always")
def corner(x, n):  # pragma: no cover - compiled
    """Lower and upper node and weight of continuous index `x` on an axis of `n` nodes,
    clamped to the axis (the edge value beyond it)."""
    x = min(max(x, 0.0), n - 1.0)
    x0 = min(int(x), max(n - 2, 0))
    return x0, min(x0 + 1, n - 1), x - x0


@numba.njit(cache=True, inline="always")
def trilinear(a, z0, z1, fz, y0, y1, fy, x0, x1, fx, c):  # pragma: no cover - compiled
    """Component `c` of `a` (nz, ny, nx, 3) interpolated between the given nodes."""
    return (1 - fz) * (
        (1 - fy) * ((1 - fx) * a[z0, y0, x0, c] + fx * a[z0, y0, x1, c])
        + fy * ((1 - fx) * a[z0, y1, x0, c] + fx * a[z0, y1, x1, c])
    ) + fz * (
        (1 - fy) * ((1 - fx) * a[z1, y0, x0, c] + fx * a[z1, y0, x1, c])
        + fy * ((1 - fx) * a[z1, y1, x0, c] + fx * a[z1, y1, x1, c])
    )


@numba.njit(cache=True, inline="always")
def linear_at_index(a, c0, c1, c2):  # pragma: no cover - compiled
    """The three components of `a` (nz, ny, nx, 3) at continuous index (c0, c1, c2) (ITK
    axis order), sampled linearly and clamped to its grid."""
    nz, ny, nx, _ = a.shape
    x0, x1, fx = corner(c0, nx)
    y0, y1, fy = corner(c1, ny)
    z0, z1, fz = corner(c2, nz)
    return (
        trilinear(a, z0, z1, fz, y0, y1, fy, x0, x1, fx, 0),
        trilinear(a, z0, z1, fz, y0, y1, fy, x0, x1, fx, 1),
        trilinear(a, z0, z1, fz, y0, y1, fy, x0, x1, fx, 2),
    )


@numba.njit(cache=True, inline="always")
def linear_at(a, p0, p1, p2, origin, to_index):  # pragma: no cover - compiled
    """The three components of `a` (nz, ny, nx, 3) at physical point p, sampled linearly and
    clamped to its grid (`origin` (3,), `to_index` (3, 3): mm -> index, ITK axis order)."""
    c0, c1, c2 = continuous_index(p0, p1, p2, origin, to_index)
    return linear_at_index(a, c0, c1, c2)


@numba.njit(cache=True, parallel=True)
def fixed_point_step(u, v, out, u_offset, to_index, ratio, offset, v_on_grid):  # pragma: no cover
    """``out(q) = -u(q + v(q))`` on out's grid (nz, ny, nx, 3), whose node i is u's
    continuous index ``i + u_offset`` and v's ``offset + ratio * i`` (ITK axis order; with
    `v_on_grid`, v is on out's own grid and read at its nodes); `to_index` (3, 3) maps mm to
    u's index steps. u and v are sampled linearly, clamped to their grids.

    Slices run in parallel; each node is computed alone by the same operations, so the
    numbers do not depend on the number of threads."""
    nz, ny, nx, _ = out.shape
    uz, uy, ux, _ = u.shape
    vz, vy, vx, _ = v.shape
    t00, t01, t02 = to_index[0, 0], to_index[0, 1], to_index[0, 2]
    t10, t11, t12 = to_index[1, 0], to_index[1, 1], to_index[1, 2]
    t20, t21, t22 = to_index[2, 0], to_index[2, 1], to_index[2, 2]
    for k in numba.prange(nz):
        for j in range(ny):
            for i in range(nx):
                if v_on_grid:
                    a0, a1, a2 = v[k, j, i, 0], v[k, j, i, 1], v[k, j, i, 2]
                else:
                    x0, x1, fx = corner(offset[0] + i * ratio[0], vx)
                    y0, y1, fy = corner(offset[1] + j * ratio[1], vy)
                    z0, z1, fz = corner(offset[2] + k * ratio[2], vz)
                    a0 = trilinear(v, z0, z1, fz, y0, y1, fy, x0, x1, fx, 0)
                    a1 = trilinear(v, z0, z1, fz, y0, y1, fy, x0, x1, fx, 1)
                    a2 = trilinear(v, z0, z1, fz, y0, y1, fy, x0, x1, fx, 2)
                x0, x1, fx = corner(i + u_offset[0] + (t00 * a0 + t01 * a1 + t02 * a2), ux)
                y0, y1, fy = corner(j + u_offset[1] + (t10 * a0 + t11 * a1 + t12 * a2), uy)
                z0, z1, fz = corner(k + u_offset[2] + (t20 * a0 + t21 * a1 + t22 * a2), uz)
                out[k, j, i, 0] = -trilinear(u, z0, z1, fz, y0, y1, fy, x0, x1, fx, 0)
                out[k, j, i, 1] = -trilinear(u, z0, z1, fz, y0, y1, fy, x0, x1, fx, 1)
                out[k, j, i, 2] = -trilinear(u, z0, z1, fz, y0, y1, fy, x0, x1, fx, 2)


@numba.njit(cache=True, parallel=True)
def fixed_point_at_points(
    y, u, u_origin, u_to_index, lower, upper, v, v_origin, v_to_index, steps
):  # pragma: no cover - compiled
    """In place, each point r of `y` (m, 3) -> the inverse of ``p -> p + u(p)`` at r: the
    coarse inverse `v` interpolated there, then `steps` steps ``y <- r - u(y)``; r itself
    where it lies beyond the grown grid (`lower`, `upper`: its buffer in u's continuous
    index). Fields are sampled linearly, clamped to their grids (:func:`fixed_point_step`'s
    rules). Each point alone, by the same operations: the numbers do not depend on the
    threads."""
    for f in numba.prange(y.shape[0]):
        r0, r1, r2 = y[f, 0], y[f, 1], y[f, 2]
        c0, c1, c2 = continuous_index(r0, r1, r2, u_origin, u_to_index)
        if not in_box(c0, c1, c2, lower, upper):
            continue
        w0, w1, w2 = linear_at(v, r0, r1, r2, v_origin, v_to_index)
        a0, a1, a2 = r0 + w0, r1 + w1, r2 + w2
        for _ in range(steps):
            w0, w1, w2 = linear_at(u, a0, a1, a2, u_origin, u_to_index)
            a0, a1, a2 = r0 - w0, r1 - w1, r2 - w2
        y[f, 0], y[f, 1], y[f, 2] = a0, a1, a2
