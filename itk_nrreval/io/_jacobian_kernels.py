"""The Jacobian determinants of a displacement on a grid, compiled: by central differences, and
on the one-sided stencils (the triangles and tetrahedra of the voxel grid) of Liu et al.'s
digital diffeomorphism (IJCV 2024), in one pass over a slab.

:func:`slab_jacobians` is what :func:`itk_nrreval.io.plausibility.deformation_measures` calls
slab by slab; that function's notes give the formulas. The kernels' central differences are those of
:func:`itk_nrreval.io.transforms.jacobian_determinant`, bit for bit.
"""

from __future__ import annotations

import numba
import numpy as np

from ._images import Geometry

__all__ = ["INNER_TETRAHEDRA", "slab_jacobians"]


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


def slab_jacobians(
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
        :func:`~itk_nrreval.io.transforms.jacobian_determinant`, bit for bit.
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
    :func:`~itk_nrreval.io.transforms.jacobian_determinant`'s kernel."""
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
    :func:`~itk_nrreval.io.transforms.jacobian_determinant`'s kernel, in its order."""
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
    :func:`~itk_nrreval.io.transforms.jacobian_determinant`'s kernel, and at the voxels where
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
