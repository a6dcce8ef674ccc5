"""The compiled kernels of the sparse label memberships (:mod:`itk_nrreval.io._memberships`):
grid points to continuous indices in a label map, ITK's inside-buffer test, each point's
``2**dim`` interpolation weights added to the labels of their corners, and an image on the
label map's grid interpolated with the same weights.

The module docstring of :mod:`itk_nrreval.io._memberships` says what ITK does and how these
reproduce it (the half-open buffer test, the clamped multilinear weights, the snap to voxel
centres).
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = [
    "by_label",
    "continuous_indices",
    "covered_from",
    "inside_at",
    "inside_flags",
    "linear_values",
    "mark_present",
    "near_border_points",
    "point_entries",
    "point_indices",
    "voxel_base",
]


@numba.njit(cache=True, parallel=True)
def covered_from(
    points, size, g_origin, g_matrix, l_origin, l_inverse, l_size, eps, out
):  # pragma: no cover - compiled
    """Into `out` (flat bool): whether ``p + points[f]`` of each grid voxel p (the grid of
    ITK size `size`, C order) lies in the image's buffer, ITK's IsInsideBuffer by the
    arithmetic of :func:`continuous_indices` and :func:`inside_at`. Returns the number of
    points within `eps` voxels of the border (ITK decides those)."""
    d = points.shape[1]
    nx = size[0]
    ny = size[1]
    n_planes = size[d - 1]
    per_plane = nx * ny if d == 3 else nx
    near = 0
    for z in numba.prange(n_planes):
        idx = np.zeros(d)
        q = np.empty(d)
        idx[d - 1] = z
        n_mid = ny if d == 3 else 1
        for y in range(n_mid):
            if d == 3:
                idx[1] = y
            for x in range(nx):
                idx[0] = x
                f = z * per_plane + y * nx + x if d == 3 else z * nx + x
                for i in range(d):
                    p = g_origin[i]
                    for j in range(d):
                        p += g_matrix[i, j] * idx[j]
                    q[i] = (points[f, i] + p) - l_origin[i]
                ok = True
                for i in range(d):
                    c = 0.0
                    for j in range(d):
                        c += l_inverse[i, j] * q[j]
                    if abs(c + 0.5) <= eps or abs(c - (l_size[i] - 0.5)) <= eps:
                        near += 1
                    ok = ok and (c >= -0.5 and c < l_size[i] - 0.5)
                out[f] = ok
    return near


@numba.njit(cache=True)
def inside_flags(cidx, nz, ny, nx, out):  # pragma: no cover - compiled
    """ITK's IsInsideBuffer of each continuous index (:func:`inside_at`), into `out`."""
    none = np.empty(0, np.uint8)
    for f in range(cidx.shape[0]):
        out[f] = inside_at(cidx, f, none, nz, ny, nx)[0]


@numba.njit(cache=True)
def mark_present(labels, vmin, seen):  # pragma: no cover - compiled
    flat = labels.ravel()
    for i in range(flat.size):
        seen[np.int64(flat[i]) - vmin] = True


@numba.njit(cache=True)
def continuous_indices(
    points, size, z0, g_origin, g_matrix, l_origin, l_inverse, l_size, eps, out
):  # pragma: no cover - compiled
    """``T(p) - p`` (mm, `points` (m, dim)) of the slab's voxels -> their continuous indices
    in the label map, into `out` (m, dim) (which may be `points` itself).

    `size` is the slab's ITK size, `z0` its first plane in the grid (the last ITK axis).
    Returns the number of points within `eps` voxels of the buffer border on some axis.
    """
    d = points.shape[1]
    n_mid = size[1] if d == 3 else 1
    idx = np.zeros(d)
    q = np.empty(d)
    near = 0
    f = 0
    for z in range(size[d - 1]):
        idx[d - 1] = z0 + z
        for y in range(n_mid):
            if d == 3:
                idx[1] = y
            for x in range(size[0]):
                idx[0] = x
                for i in range(d):
                    p = g_origin[i]
                    for j in range(d):
                        p += g_matrix[i, j] * idx[j]
                    q[i] = (points[f, i] + p) - l_origin[i]
                near += _index_into(q, l_inverse, l_size, eps, out, f)
                f += 1
    return near


@numba.njit(cache=True)
def point_indices(points, l_origin, l_inverse, l_size, eps, out):  # pragma: no cover
    """Physical points (`points` (m, 3), mm; a 2D point's third coordinate 0) -> their
    continuous indices in the label map, ITK's ``(D diag(spacing))^-1 (q - origin)``, into
    `out` (m, dim). Returns the number within `eps` voxels of the buffer border on some
    axis (the test of :func:`continuous_indices`)."""
    d = out.shape[1]
    q = np.empty(d)
    near = 0
    for f in range(out.shape[0]):
        for i in range(d):
            q[i] = points[f, i] - l_origin[i]
        near += _index_into(q, l_inverse, l_size, eps, out, f)
    return near


@numba.njit(cache=True, inline="always")
def _index_into(q, l_inverse, l_size, eps, out, f):  # pragma: no cover - compiled
    """Row f of `out` = ``l_inverse @ q`` (q: a point less the label map's origin, mm): its
    continuous index. Returns on how many axes it lies within `eps` of the buffer border."""
    near = 0
    for i in range(q.shape[0]):
        c = 0.0
        for j in range(q.shape[0]):
            c += l_inverse[i, j] * q[j]
        out[f, i] = c
        if abs(c + 0.5) <= eps or abs(c - (l_size[i] - 0.5)) <= eps:
            near += 1
    return near


@numba.njit(cache=True)
def point_entries(
    cidx, labels, vmin, lut, inside, snap, f, n, out_code, out_index, out_weight
):  # pragma: no cover - compiled
    """Nonzero memberships of the slab's points from point `f` on, appended at entry `n`.

    cidx : (m, dim) continuous indices (x, y[, z]) of the points in the label map.
    labels : (nz, ny, nx) label values (a 2D map as one plane); channel = lut[value - vmin].
    inside : (m,) uint8 ITK's inside-buffer decision, or empty to decide here.
    Stops early when fewer than 8 entries of room are left. Returns (next point, entries).
    """
    m = cidx.shape[0]
    nz, ny, nx = labels.shape
    cap = out_code.size
    val = np.empty(8, np.int64)
    wgt = np.empty(8)
    loc_code = np.empty(8, np.int64)
    loc_w = np.empty(8)
    while f < m:
        if n + 8 > cap:
            break
        ok, cx, cy, cz = inside_at(cidx, f, inside, nz, ny, nx)
        if not ok:
            f += 1
            continue
        bx, tx = voxel_base(cx, nx, snap)
        by, ty = voxel_base(cy, ny, snap)
        bz, tz = voxel_base(cz, nz, snap)
        # The upper neighbour exists whenever its weight t is nonzero (c was clamped to the
        # outer voxel centres); with t == 0 the base voxel is read again at weight 0.
        ux = bx + 1 if tx > 0.0 else bx
        uy = by + 1 if ty > 0.0 else by
        uz = bz + 1 if tz > 0.0 else bz
        val[0] = labels[bz, by, bx]
        val[1] = labels[bz, by, ux]
        val[2] = labels[bz, uy, bx]
        val[3] = labels[bz, uy, ux]
        val[4] = labels[uz, by, bx]
        val[5] = labels[uz, by, ux]
        val[6] = labels[uz, uy, bx]
        val[7] = labels[uz, uy, ux]
        same = True
        for j in range(1, 8):
            if val[j] != val[0]:
                same = False
                break
        if same:
            # One label all around: exactly 1, as ITK's nested interpolation gives.
            k = lut[val[0] - vmin]
            if k >= 0:
                out_code[n] = k
                out_index[n] = f
                out_weight[n] = 1.0
                n += 1
            f += 1
            continue
        wx0, wy0, wz0 = 1.0 - tx, 1.0 - ty, 1.0 - tz
        wgt[0] = wx0 * wy0 * wz0
        wgt[1] = tx * wy0 * wz0
        wgt[2] = wx0 * ty * wz0
        wgt[3] = tx * ty * wz0
        wgt[4] = wx0 * wy0 * tz
        wgt[5] = tx * wy0 * tz
        wgt[6] = wx0 * ty * tz
        wgt[7] = tx * ty * tz
        nloc = 0
        for j in range(8):
            if wgt[j] == 0.0:
                continue
            k = lut[val[j] - vmin]
            if k < 0:  # a value without a channel
                continue
            i = 0
            while i < nloc and loc_code[i] != k:
                i += 1
            if i == nloc:
                loc_code[i] = k
                loc_w[i] = wgt[j]
                nloc += 1
            else:
                loc_w[i] += wgt[j]
        for i in range(nloc):
            w = np.float32(loc_w[i])
            if w > 0:
                out_code[n] = loc_code[i]
                out_index[n] = f
                out_weight[n] = w
                n += 1
        f += 1
    return f, n


@numba.njit(cache=True, inline="always")
def inside_at(cidx, f, inside, nz, ny, nx):  # pragma: no cover - compiled
    """Whether point `f` (continuous index ``cidx[f]``, x, y[, z]) is inside a buffer of
    shape (nz, ny, nx), and its index (z 0 in 2D): ITK's decision ``inside[f]`` where given
    (non-empty), else ITK's IsInsideBuffer, ``-0.5 <= c < size - 0.5`` on every axis
    (half-open; NaN is outside)."""
    cx = cidx[f, 0]
    cy = cidx[f, 1]
    cz = cidx[f, 2] if cidx.shape[1] == 3 else 0.0
    if inside.size > 0:
        return inside[f] != 0, cx, cy, cz
    ok = (cx >= -0.5 and cx < nx - 0.5) and (cy >= -0.5 and cy < ny - 0.5)
    return ok and (cz >= -0.5 and cz < nz - 0.5), cx, cy, cz


@numba.njit(cache=True, inline="always")
def voxel_base(c, size, snap):  # pragma: no cover - compiled
    """Lower interpolation neighbour and weight of the upper one along an axis of `size`."""
    c = min(max(c, 0.0), size - 1.0)  # ITK's interpolator clamps to the outer voxel centres
    r = np.floor(c + 0.5)
    if abs(c - r) <= snap:
        c = r
    b = np.floor(c)
    return np.int64(b), c - b


@numba.njit(cache=True)
def by_label(code, index, weight, n_labels):  # pragma: no cover - compiled
    """Stable counting sort of voxel-major entries by label (voxel order kept per label)."""
    starts = np.zeros(n_labels + 1, np.int64)
    for j in range(code.size):
        starts[code[j] + 1] += 1
    for k in range(n_labels):
        starts[k + 1] += starts[k]
    cursor = starts[:-1].copy()
    out_index = np.empty(code.size, np.int32)
    out_weight = np.empty(code.size, np.float32)
    for j in range(code.size):
        k = code[j]
        out_index[cursor[k]] = index[j]
        out_weight[cursor[k]] = weight[j]
        cursor[k] += 1
    return starts, out_index, out_weight


@numba.njit(cache=True)
def near_border_points(cidx, l_size, eps, capacity):  # pragma: no cover - compiled
    """The rows of `cidx` within `eps` voxels of the buffer border on some axis (the test of
    :func:`continuous_indices`); at most `capacity` of them."""
    out = np.empty(capacity, np.int64)
    n = 0
    for f in range(cidx.shape[0]):
        for i in range(cidx.shape[1]):
            c = cidx[f, i]
            if abs(c + 0.5) <= eps or abs(c - (l_size[i] - 0.5)) <= eps:
                out[n] = f
                n += 1
                break
    return out[:n]


@numba.njit(cache=True, parallel=True)
def linear_values(cidx, image, inside, out):  # pragma: no cover - compiled
    """``out[f]``: `image` (nz, ny, nx) linearly interpolated at continuous index ``cidx[f]``
    (x, y[, z]) as ITK's linear interpolator does (clamped to the outer voxel centres), NaN
    outside the buffer. `inside` as in :func:`point_entries` (empty: decide here). Each
    point alone, by the same operations: the numbers do not depend on the threads."""
    nz, ny, nx = image.shape
    for f in numba.prange(cidx.shape[0]):
        ok, cx, cy, cz = inside_at(cidx, f, inside, nz, ny, nx)
        if not ok:
            out[f] = np.nan
            continue
        bx, tx = voxel_base(cx, nx, 0.0)
        by, ty = voxel_base(cy, ny, 0.0)
        bz, tz = voxel_base(cz, nz, 0.0)
        ux = bx + 1 if tx > 0.0 else bx
        uy = by + 1 if ty > 0.0 else by
        uz = bz + 1 if tz > 0.0 else bz
        # ITK's order: along x, then y, then z, each as a + (b - a) t
        a = image[bz, by, bx] + (image[bz, by, ux] - image[bz, by, bx]) * tx
        b = image[bz, uy, bx] + (image[bz, uy, ux] - image[bz, uy, bx]) * tx
        c = image[uz, by, bx] + (image[uz, by, ux] - image[uz, by, bx]) * tx
        e = image[uz, uy, bx] + (image[uz, uy, ux] - image[uz, uy, bx]) * tx
        lo = a + (b - a) * ty
        hi = c + (e - c) * ty
        out[f] = lo + (hi - lo) * tz
