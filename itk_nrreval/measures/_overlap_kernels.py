"""Numba kernels of the generalized overlap: pair sums, volumes and gradient sums.

The public functions below are the whole interface, shared by :mod:`itk_nrreval.measures.overlap`
(one sweep over a group of label maps) and the evaluation pipeline (which adds the sums up
over blocks of voxels and builds the table with :meth:`.OverlapTable.from_sums`):

- fuzzy memberships, one label at a time: :func:`membership_pair_sums`,
  :func:`membership_gradient_sum` (one image), :func:`membership_gradient_sums` (a group of
  images, in parallel) and :func:`membership_stats` (value range and presence);
- crisp label maps, every label in one pass: :func:`label_map_sums` and
  :func:`label_map_gradient_sums`.

Conventions
-----------
Voxels are flattened in C order of the numpy grid shape (z, y, x); a ``shape`` argument is
that numpy shape. ``spacing`` is the voxel size in mm in ITK order (x, y[, z]) -- the reverse
of the numpy axes. A mask has one boolean per voxel (any shape with ``n_voxels`` elements;
nonzero is inside), None meaning every voxel. Every sum is in voxel units: memberships (or
indicator values) summed over voxels; gradient magnitudes, in mm^-1, summed over voxels.
With ``A_i`` image i's membership of the label and the sums over the voxels inside the mask:

- pair_min ``= sum_{i<j} sum_v min(A_i, A_j)``, pair_max the same with max;
- volume[i] ``= sum_v A_i``;
- target_sums[i] ``= sum_v sum_{j != i} min(A_i, A_j)`` (Klein's target overlap numerator
  summed over the other images);
- gradient sums ``sum_v |grad A_i|``, central differences (one-sided at the grid's faces, as
  :func:`numpy.gradient` with ``edge_order=1``; axes of length 1 contribute nothing), taken
  on the whole grid and summed inside the mask.

Every result is independent of the number of numba threads: parallel work is split into
blocks whose partial sums are added in block order (fuzzy pair sums), or into images summed
in voxel order one per thread (gradient sums), or is exact integer arithmetic (crisp counts).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence

import numba
import numba.extending
import numpy as np
from llvmlite import ir as llvm_ir
from numpy.lib.stride_tricks import as_strided

from .._errors import readable

__all__ = [
    "membership_pair_sums",
    "membership_gradient_sum",
    "membership_gradient_sums",
    "membership_stats",
    "label_map_sums",
    "label_map_gradient_sums",
]

_BLOCK = 256  # voxels per block of fuzzy memberships: (N, _BLOCK) float64 scratch fits L2
_INDEX_BITS = 29  # float32 -> float64 leaves 29 zero mantissa bits to carry an image index
_NETWORK_FRACTION = 0.5  # above this share of values strictly in (0, 1), sort by network
_MAX_LUT = 1 << 22  # largest label-value range mapped through a lookup table
_DENSE_RANGE = 1024  # crisp, no label list: count every value of a range this small at once
_COUNT_BYTES = 1 << 17  # crisp count scratch per thread, (labels + 1) x block int32: 128 kB
_COUNT_BLOCK = (64, 2048)  # crisp voxel block bounds


# -- argument checks ---------------------------------------------------------------------------


def _rows(array, what: str, *, floating: bool) -> np.ndarray:
    """`array` as (n_images, n_voxels): float32 / float64 kept (else float64), or integer."""
    a = np.asarray(array)
    if a.ndim != 2:
        raise ValueError(f"{what} must have shape (n_images, n_voxels), got {a.shape}")
    if floating:
        return a if a.dtype in (np.float32, np.float64) else a.astype(np.float64)
    if a.dtype == np.bool_:
        return a.view(np.uint8)
    if not np.issubdtype(a.dtype, np.integer):
        raise ValueError(f"{what} must have an integer dtype, got {a.dtype}")
    return a


def _row_view(rows: np.ndarray) -> tuple[np.ndarray, int]:
    """A C-contiguous 2D view ``base`` and a step such that image i's row is
    ``base[i * step]``: for the kernels, which run much faster on C-contiguous arrays.

    No copy when every row is contiguous and the rows are evenly spaced a whole number of
    rows apart (e.g. one component of an (N, L, n) array: step L); the view then also spans
    the rows in between, which lie inside the same buffer. Anything else is copied.
    """
    n_img, n = rows.shape
    if rows.flags.c_contiguous:
        return rows, 1
    item = rows.itemsize
    s0, s1 = rows.strides
    if n > 0 and n_img > 0 and s1 == item and s0 > 0 and s0 % (n * item) == 0:
        step = s0 // (n * item)
        span = (n_img - 1) * step + 1
        return as_strided(rows, shape=(span, n), strides=(n * item, item)), step
    return np.ascontiguousarray(rows), 1


def _flat_mask(mask, n_voxels: int) -> np.ndarray:
    """The mask as a flat C-contiguous bool array of `n_voxels`, or an empty one for None."""
    if mask is None:
        return np.zeros(0, np.bool_)
    m = np.asarray(mask)
    if m.size != n_voxels:
        raise ValueError(f"mask has {m.size} elements, expected one per voxel ({n_voxels})")
    return np.ascontiguousarray(m.reshape(-1) != 0)


def _grid(shape: Sequence[int], spacing: Sequence[float], n_voxels: int):
    """The numpy shape as int64 and ``1 / spacing`` in numpy axis order."""
    shp = np.asarray(shape, dtype=np.int64).reshape(-1)
    if shp.size == 0 or np.any(shp < 1) or int(np.prod(shp)) != n_voxels:
        raise ValueError(f"shape {tuple(shape)} does not hold {n_voxels} voxels")
    sp = np.asarray(spacing, dtype=np.float64).reshape(-1)
    if sp.shape != shp.shape or not np.all(np.isfinite(sp)) or not np.all(sp > 0):
        raise ValueError(
            f"spacing must be {shp.size} positive numbers in ITK order (x, y[, z]), "
            f"got {readable(spacing)}"
        )
    return shp, 1.0 / sp[::-1]


# -- fuzzy memberships: public ---------------------------------------------------------------


def membership_pair_sums(
    memberships: np.ndarray, *, mask: np.ndarray | None = None
) -> tuple[float, float, np.ndarray, np.ndarray]:
    """Pair sums of one label's memberships over a group of images.

    Parameters
    ----------
    memberships : ndarray of float32 or float64, shape (n_images, n_voxels)
        Image i's membership of the label at each voxel (a block of voxels of a flattened
        grid, or the whole grid), in [0, 1] (not checked). Other dtypes are cast to float64.
        Rows need not be adjacent in memory (a component of an (N, L, n) array is fine).
    mask : ndarray of bool, shape (n_voxels,), optional
        Sum only over the voxels where it is true. Default: every voxel.

    Returns
    -------
    pair_min : float
        ``sum_{i<j} sum_v min(A_i, A_j)``, voxel units.
    pair_max : float
        ``sum_{i<j} sum_v max(A_i, A_j)``, voxel units.
    volume : ndarray of float64, shape (n_images,)
        ``sum_v A_i``, voxel units.
    target_sums : ndarray of float64, shape (n_images,)
        ``sum_v sum_{j != i} min(A_i, A_j)``, voxel units.

    Notes
    -----
    Voxels where every membership is zero (or outside the mask) are skipped. The rest go in
    blocks of 256 to the threads: a block where more than half of the values lie strictly in
    (0, 1) has its columns sorted by Batcher's odd-even merge network (for float32 input with
    the image index packed into the low bits of the float64 sort key), any other block by an
    O(N) pass that sorts only the fractional values. With a_(k) the k-th smallest of a
    voxel's N memberships (k = 0..N-1) the voxel adds ``a_(k) (N - 1 - k)`` to pair_min and
    ``a_(k) k`` to pair_max. Block partial sums are added in block order, so the result does
    not depend on the number of threads.
    """
    rows = _rows(memberships, "memberships", floating=True)
    n_img, n = rows.shape
    mk = _flat_mask(mask, n)
    base, step = _row_view(rows)
    active = np.empty(n, np.bool_)
    _active_voxels(base, step, n_img, mk, active)
    voxels = np.flatnonzero(active)
    net_lo, net_hi = _sorting_network(n_img)
    # float32 memberships carry the image index in the low bits of their float64 sort key
    packed = rows.dtype == np.float32 and n_img <= 1 << _INDEX_BITS
    volume = np.zeros(n_img)
    target = np.zeros(n_img)
    p, q = _pair_sums(base, step, voxels, net_lo, net_hi, _NETWORK_FRACTION, packed, volume, target)
    return float(p), float(q), volume, target


def membership_gradient_sum(
    membership: np.ndarray,
    *,
    shape: Sequence[int],
    spacing: Sequence[float],
    mask: np.ndarray | None = None,
) -> float:
    """``sum_v |grad A|`` over the mask for one image's membership of one label.

    Parameters
    ----------
    membership : ndarray of float, shape (n_voxels,)
        The membership on the whole grid, flat in C order of `shape` (float32 or float64;
        other dtypes are cast to float64).
    shape : sequence of int
        The grid's numpy shape (z, y, x); its product is n_voxels.
    spacing : sequence of float
        Voxel size in mm, ITK order (x, y[, z]).
    mask : ndarray of bool with n_voxels elements, optional
        Sum only over the voxels where it is true (the gradient is still taken on the whole
        grid). Default: every voxel.

    Returns
    -------
    float
        The sum of gradient magnitudes, in mm^-1 x voxels (central differences, one-sided at
        the faces, as :func:`numpy.gradient` with ``edge_order=1``).

    Notes
    -----
    Computed only on the slabs (along the first axis) within two of one holding a nonzero
    membership: farther out the gradient is zero. Line by line along the last axis, summed in
    blocks of 4096 voxels per line.
    """
    row = np.asarray(membership)
    if row.ndim != 1:
        raise ValueError(f"membership must be flat, shape (n_voxels,), got {row.shape}")
    if row.dtype not in (np.float32, np.float64):
        row = row.astype(np.float64)
    shp, inv_h = _grid(shape, spacing, row.size)
    row = np.ascontiguousarray(row)
    return float(_gradient_sum_row(row, _flat_mask(mask, row.size), shp, inv_h))


def membership_gradient_sums(
    memberships: np.ndarray,
    *,
    shape: Sequence[int],
    spacing: Sequence[float],
    mask: np.ndarray | None = None,
) -> np.ndarray:
    """:func:`membership_gradient_sum` of every image of a group, one image per thread.

    Parameters
    ----------
    memberships : ndarray of float, shape (n_images, n_voxels)
        One label's memberships, each row on the whole grid, flat in C order of `shape`.
    shape, spacing, mask
        As for :func:`membership_gradient_sum`.

    Returns
    -------
    ndarray of float64, shape (n_images,)
        ``sum_v |grad A_i|`` over the mask, mm^-1 x voxels; the same numbers as
        :func:`membership_gradient_sum` row by row.
    """
    rows = _rows(memberships, "memberships", floating=True)
    shp, inv_h = _grid(shape, spacing, rows.shape[1])
    out = np.zeros(rows.shape[0])
    base, step = _row_view(rows)
    _gradient_sums(base, step, _flat_mask(mask, rows.shape[1]), shp, inv_h, out)
    return out


def membership_stats(
    memberships: np.ndarray, *, mask: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Value range per image and presence per image and label, in one parallel pass.

    Parameters
    ----------
    memberships : ndarray of float, shape (n_images, n_labels, n_voxels)
        Fuzzy memberships (float32 or float64; other dtypes are cast to float64).
    mask : ndarray of bool with n_voxels elements, optional
        Presence counts only voxels where it is true. Default: every voxel.

    Returns
    -------
    lows, highs : ndarray of float64, shape (n_images,)
        Each image's smallest and largest membership over every label and the whole grid.
    present : ndarray of bool, shape (n_images, n_labels)
        Whether the image has a nonzero membership of the label inside the mask.
    """
    a = np.asarray(memberships)
    if a.ndim != 3:
        raise ValueError(
            f"memberships must have shape (n_images, n_labels, n_voxels), got {a.shape}"
        )
    if a.dtype not in (np.float32, np.float64):
        a = a.astype(np.float64)
    return _membership_stats(a, _flat_mask(mask, a.shape[2]))


# -- crisp label maps: public ----------------------------------------------------------------


def label_map_sums(
    labels: np.ndarray,
    *,
    values: np.ndarray | None = None,
    exclude: Sequence[int] = (),
    mask: np.ndarray | None = None,
    target_overlap: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """Per-label pair counts of a group of crisp label maps, every label in one pass.

    Parameters
    ----------
    labels : ndarray of int (or bool), shape (n_images, n_voxels)
        The label maps, flattened; rows need not be adjacent in memory.
    values : ndarray of int, optional
        The label values to count, distinct. Default: every value present inside the mask in
        some image, less `exclude`.
    exclude : sequence of int
        Values left out of the default set (e.g. background 0); ignored when `values` is
        given.
    mask : ndarray of bool with n_voxels elements, optional
        Count only voxels where it is true. Default: every voxel.
    target_overlap : bool
        Also compute `target_sums` (a second pass over each block's images).

    Returns
    -------
    values : ndarray of int64, shape (n_labels,)
        The label values counted, ascending (those given, including absent ones, or those
        present).
    pair_min : ndarray of int64, shape (n_labels,)
        ``sum_{i<j} sum_v [A_i = l][A_j = l]`` = ``sum_v C(c_v, 2)``, with c_v the number of
        images carrying label l at voxel v. (pair_max follows as ``(N - 1) volume.sum(0) -
        pair_min``: the pair sums of ``a_i + a_j`` are min plus max.)
    volume : ndarray of int64, shape (n_images, n_labels)
        Voxel count of each label in each image.
    target_sums : ndarray of int64, shape (n_images, n_labels), or None
        ``sum over image i's voxels of label l of (c_v - 1)`` = ``sum_{j != i} |A_i ∩ A_j|``;
        None unless `target_overlap`.

    Notes
    -----
    Exact integer arithmetic. Label values map to dense indices through a lookup table when
    their range is below 2^22 (else by binary search). Parallel over blocks of voxels; per
    block, image by image (reading the (N, n) array directly), each voxel's count of its
    label goes up in an (n_labels + 1, block) array whose extra row takes every voxel of an
    uncounted value or outside the mask; then ``sum_v C(c_v, 2)`` is read off the counts
    while they are reset. Without `values`, a small value range (at most 1024 values) is
    counted whole and the absent values dropped afterwards; a larger one is first scanned
    for the values present.
    """
    x = _rows(labels, "labels", floating=False)
    n_img, n = x.shape
    mk = _flat_mask(mask, n)
    if values is not None:
        wanted = np.unique(np.asarray(values, dtype=np.int64).reshape(-1))
        if wanted.size != np.asarray(values).size:
            raise ValueError(f"values must be distinct, got {readable(values)}")
        pm, vol, tgt = _label_counts(x, wanted, mk, target_overlap)
        return (wanted, pm, vol, tgt)
    drop = np.asarray(exclude, dtype=np.int64).reshape(-1)
    if n == 0 or n_img == 0:
        none = np.zeros(0, np.int64)
        return (none, *_label_counts(x, none, mk, target_overlap))
    base, step = _row_view(x)
    lo, hi = _label_range(base, step, n_img)
    if hi - lo < _DENSE_RANGE:  # count every value of the range, then drop the absent ones
        candidates = np.arange(lo, hi + 1, dtype=np.int64)
        candidates = candidates[~np.isin(candidates, drop)]
        pm, vol, tgt = _label_counts(x, candidates, mk, target_overlap)
        keep = vol.sum(axis=0) > 0
        return (
            candidates[keep],
            pm[keep],
            np.ascontiguousarray(vol[:, keep]),
            None if tgt is None else np.ascontiguousarray(tgt[:, keep]),
        )
    if hi - lo < _MAX_LUT:
        n_parts = max(1, min(8, (1 << 24) // (hi - lo + 1)))
        seen = _seen_values(base, step, n_img, lo, hi - lo + 1, mk, n_parts)
        present = np.flatnonzero(seen).astype(np.int64) + lo
    else:
        present = np.unique(
            np.concatenate([np.unique(x[i][mk] if mk.size else x[i]) for i in range(n_img)])
        ).astype(np.int64)
    present = present[~np.isin(present, drop)]
    pm, vol, tgt = _label_counts(x, present, mk, target_overlap)
    return present, pm, vol, tgt


def label_map_gradient_sums(
    labels: np.ndarray,
    values: np.ndarray,
    *,
    shape: Sequence[int],
    spacing: Sequence[float],
    mask: np.ndarray | None = None,
) -> np.ndarray:
    """``sum_v |grad [A_i = l]|`` of every image and label indicator, one image per thread.

    Parameters
    ----------
    labels : ndarray of int (or bool), shape (n_images, n_voxels)
        The label maps, each flat in C order of `shape`.
    values : ndarray of int, shape (n_labels,)
        The label values, distinct and ascending.
    shape : sequence of int
        The grid's numpy shape (z, y, x).
    spacing : sequence of float
        Voxel size in mm, ITK order (x, y[, z]).
    mask : ndarray of bool with n_voxels elements, optional
        Sum only over voxels where it is true (the gradient is still taken on the whole
        grid). Default: every voxel.

    Returns
    -------
    ndarray of float64, shape (n_images, n_labels)
        The gradient magnitude sums of the indicators, mm^-1 x voxels.

    Notes
    -----
    As :func:`numpy.gradient` with ``edge_order=1``: along an axis with neighbours p and m
    (the voxel itself at a face) the indicator of label l changes by ``[p = l] - [m = l]``,
    so only the labels of p and m get a component, of squared size ``f^2`` (f = 1 / (2 h)
    inside, 1 / h at a face). Each image's sums run in voxel order, flushed every 4096
    voxels, whatever the thread count.
    """
    x = _rows(labels, "labels", floating=False)
    vals = np.asarray(values, dtype=np.int64).reshape(-1)
    if vals.size > 1 and np.any(np.diff(vals) <= 0):
        raise ValueError("values must be distinct and ascending")
    shp, inv_h = _grid(shape, spacing, x.shape[1])
    lut, lo = _lookup_table(vals)
    base, step = _row_view(x)
    mk = _flat_mask(mask, x.shape[1])
    return _label_gradient_kernel(base, step, x.shape[0], lut, lo, vals, mk, shp, inv_h)


# -- crisp label maps: private ---------------------------------------------------------------


def _lookup_table(values: np.ndarray) -> tuple[np.ndarray, int]:
    """Dense label index of each value: ``lut[x - lo + 1]`` for x in range, padded at both
    ends with ``len(values)`` (not counted); an empty table means binary search in `values`.
    """
    n_labels = values.size
    if n_labels == 0 or int(values[-1]) - int(values[0]) >= _MAX_LUT:
        return np.zeros(0, np.int32), 0
    lo = int(values[0])
    lut = np.full(int(values[-1]) - lo + 3, n_labels, dtype=np.int32)
    lut[values - lo + 1] = np.arange(n_labels, dtype=np.int32)
    return lut, lo


def _label_counts(x, values, mask, target_overlap: bool):
    """Run :func:`_count_kernel` for the sorted distinct `values`; (pair_min, volume, target)."""
    n_img, n = x.shape
    n_labels = values.size
    rows = n_labels + 1
    if n_labels == 0 or n == 0:
        z = np.zeros((n_img, n_labels), np.int64)
        return np.zeros(n_labels, np.int64), z, (z.copy() if target_overlap else None)
    block = _COUNT_BYTES // (4 * rows)
    block = 1 << max(int(block).bit_length() - 1, 0)  # a power of two
    block = min(max(block, _COUNT_BLOCK[0]), _COUNT_BLOCK[1], max(n, 1))
    n_blocks = (n + block - 1) // block
    n_parts = min(n_blocks, 4 * numba.get_num_threads())
    # few labels: read C(c, 2) off the whole count array while clearing it (vectorized);
    # many labels: revisit each image's voxels instead of sweeping mostly empty rows
    revisit = rows > 2 * n_img
    lut, lo = _lookup_table(values)
    base, step = _row_view(x)
    pm, vol, s = _count_kernel(
        base, step, n_img, lut, lo, values, mask, rows, block, n_parts, target_overlap, revisit
    )
    return pm, vol, (s - vol if target_overlap else None)


@numba.njit(cache=True, nogil=True)
def _lookup_block(row, lut, lo, values, mask, trash, out):  # pragma: no cover - compiled
    """``out[t]``: dense label index of ``row[t]`` (`trash` for a value not counted or a voxel
    outside `mask`, which is empty or aligned with `row`)."""
    m = row.size
    if lut.size > 0:
        top = lut.size - 2
        for t in range(m):
            d = np.int64(row[t]) - lo
            d = min(max(d, -1), top)  # clamped onto the padding: branch-free
            out[t] = lut[d + 1]
    else:
        for t in range(m):
            v = np.int64(row[t])
            pos = np.searchsorted(values, v)
            out[t] = pos if pos < trash and values[pos] == v else trash
    if mask.size > 0:
        for t in range(m):
            out[t] = out[t] if mask[t] else trash


@numba.njit(cache=True, parallel=True)
def _count_kernel(
    x, step, n_img, lut, lo, values, mask, rows, block, n_parts, want_target, revisit
):  # pragma: no cover - compiled
    """Counts of :func:`label_map_sums` over `rows` - 1 labels (row `rows` - 1: not counted);
    image i's labels are ``x[i * step]``.

    Parts of consecutive blocks go to the threads; each part keeps its own integer sums
    (exact, so their order does not matter). Volumes go into four interleaved histograms
    per image (voxel t into ``t % 4``), so runs of one label do not serialize on one counter.
    Returns (pair_min (L,), volume (N, L), sum over each image's voxels of c (N, L)).
    """
    n = x.shape[1]
    n_labels = rows - 1
    trash = n_labels
    has_mask = mask.size > 0
    n_blocks = (n + block - 1) // block
    pm_parts = np.zeros((n_parts, rows), np.int64)
    vol_parts = np.zeros((n_parts, n_img, 4, rows), np.int64)
    s_parts = np.zeros((n_parts if want_target else 0, n_img, 4, rows), np.int64)
    for part in numba.prange(n_parts):
        cnt = np.zeros((rows, block), np.int32)
        kb = np.empty(block, np.int32)
        pm = pm_parts[part]
        for b in range(part * n_blocks // n_parts, (part + 1) * n_blocks // n_parts):
            start = b * block
            stop = min(start + block, n)
            m = stop - start
            mk = mask[start:stop] if has_mask else mask
            for i in range(n_img):
                _lookup_block(x[i * step, start:stop], lut, lo, values, mk, trash, kb)
                h = vol_parts[part, i]
                for t in range(m):
                    k = kb[t]
                    cnt[k, t] += 1
                    h[t & 3, k] += 1
            if want_target:
                for i in range(n_img):
                    _lookup_block(x[i * step, start:stop], lut, lo, values, mk, trash, kb)
                    h = s_parts[part, i]
                    for t in range(m):
                        k = kb[t]
                        h[t & 3, k] += cnt[k, t]
            if revisit:  # clear what the images touched; count each (label, voxel) once
                for i in range(n_img):
                    _lookup_block(x[i * step, start:stop], lut, lo, values, mk, trash, kb)
                    for t in range(m):
                        k = kb[t]
                        c = np.int64(cnt[k, t])
                        pm[k] += c * (c - 1) // 2
                        cnt[k, t] = 0
            else:
                for k in range(rows):
                    ck = cnt[k]
                    acc = 0
                    for t in range(m):
                        c = np.int64(ck[t])
                        acc += c * (c - 1)
                        ck[t] = 0
                    pm[k] += acc // 2
    pair_min = np.zeros(n_labels, np.int64)
    volume = np.zeros((n_img, n_labels), np.int64)
    s = np.zeros((n_img, n_labels), np.int64)
    for part in range(n_parts):
        for k in range(n_labels):
            pair_min[k] += pm_parts[part, k]
        for i in range(n_img):
            for r in range(4):
                for k in range(n_labels):
                    volume[i, k] += vol_parts[part, i, r, k]
                    if want_target:
                        s[i, k] += s_parts[part, i, r, k]
    return pair_min, volume, s


@numba.njit(cache=True, parallel=True)
def _label_range(x, step, n_img):  # pragma: no cover - compiled
    """Smallest and largest value of the rows ``x[i * step]``, i < n_img (n > 0), as int64."""
    n = x.shape[1]
    n_parts = min(n, 64)
    lows = np.empty(n_parts, np.int64)
    highs = np.empty(n_parts, np.int64)
    for part in numba.prange(n_parts):
        start = part * n // n_parts
        stop = (part + 1) * n // n_parts
        lo = np.int64(x[0, start])
        hi = lo
        for i in range(n_img):
            row = x[i * step, start:stop]
            for t in range(stop - start):
                v = np.int64(row[t])
                lo = min(lo, v)
                hi = max(hi, v)
        lows[part] = lo
        highs[part] = hi
    return lows.min(), highs.max()


@numba.njit(cache=True, parallel=True)
def _seen_values(x, step, n_img, lo, n_bins, mask, n_parts):  # pragma: no cover - compiled
    """``seen[v - lo]``: value v occurs inside the mask in some image's row ``x[i * step]``
    (every value in range)."""
    n = x.shape[1]
    has_mask = mask.size > 0
    parts = np.zeros((n_parts, n_bins), np.bool_)
    for part in numba.prange(n_parts):
        start = part * n // n_parts
        stop = (part + 1) * n // n_parts
        seen = parts[part]
        for i in range(n_img):
            row = x[i * step, start:stop]
            for t in range(stop - start):
                if not has_mask or mask[start + t]:
                    seen[np.int64(row[t]) - lo] = True
    out = np.zeros(n_bins, np.bool_)
    for part in range(n_parts):
        for b in range(n_bins):
            out[b] |= parts[part, b]
    return out


@numba.njit(cache=True, parallel=True)
def _label_gradient_kernel(x, step, n_img, lut, lo, values, mask, shape, inv_h):  # pragma: no cover
    """Per image and label: sum over the mask of |grad| of the label's indicator.

    One image (``x[i * step]``) per thread, line by line along the last axis: the dense
    label indices of the line and of its neighbouring lines along the other axes are looked
    up once, then at each voxel the labels of the two neighbours along every axis
    (numpy.gradient's edge rule) are compared, and each of the (at most 2 ndim) labels
    touched adds the square root of its summed squared components (summed over the axes in
    axis order). Each image's sums run in voxel order, flushed every 4096 voxels.
    """
    n_vox = x.shape[1]
    n_labels = values.size
    trash = n_labels
    ndim = shape.size
    nx = shape[ndim - 1]
    strides = np.ones(ndim, np.int64)
    for d in range(ndim - 2, -1, -1):
        strides[d] = strides[d + 1] * shape[d + 1]
    has_mask = mask.size > 0
    no_mask = np.zeros(0, np.bool_)
    edge_x = inv_h[ndim - 1] * inv_h[ndim - 1]
    mid_x = 0.25 * inv_h[ndim - 1] * inv_h[ndim - 1]
    gsum = np.zeros((n_img, n_labels), np.float64)
    for i in numba.prange(n_img):
        row = x[i * step]
        out = gsum[i]
        gpart = np.zeros(n_labels, np.float64)
        gsq = np.zeros(n_labels + 1, np.float64)
        touched = np.empty(2 * ndim, np.int64)
        coords = np.zeros(ndim, np.int64)
        kc = np.empty(nx, np.int32)  # the line's label indices
        kp = np.empty((ndim, nx), np.int32)  # its neighbour lines' (outer axes of size > 1)
        km = np.empty((ndim, nx), np.int32)
        fac2 = np.empty(ndim, np.float64)
        for base in range(0, n_vox, nx):
            _lookup_block(row[base : base + nx], lut, lo, values, no_mask, trash, kc)
            n_out = 0
            for d in range(ndim - 1):
                size = shape[d]
                if size == 1:
                    continue
                c = coords[d]
                if c == 0 or c == size - 1:
                    fac2[n_out] = inv_h[d] * inv_h[d]
                else:
                    fac2[n_out] = 0.25 * inv_h[d] * inv_h[d]
                up = base + strides[d] if c < size - 1 else base
                down = base - strides[d] if c > 0 else base
                _lookup_block(row[up : up + nx], lut, lo, values, no_mask, trash, kp[n_out])
                _lookup_block(row[down : down + nx], lut, lo, values, no_mask, trash, km[n_out])
                n_out += 1
            for t in range(nx):
                v = base + t
                if has_mask and not mask[v]:
                    continue
                if v % 4096 == 0:  # blocked summation keeps float rounding small
                    for k in range(n_labels):
                        out[k] += gpart[k]
                        gpart[k] = 0.0
                n_t = 0
                for d in range(n_out + (1 if nx > 1 else 0)):
                    if d < n_out:
                        a = kp[d, t]
                        b = km[d, t]
                        f = fac2[d]
                    elif t == 0:  # last axis: one-sided at the ends, central inside
                        a = kc[1]
                        b = kc[0]
                        f = edge_x
                    elif t == nx - 1:
                        a = kc[t]
                        b = kc[t - 1]
                        f = edge_x
                    else:
                        a = kc[t + 1]
                        b = kc[t - 1]
                        f = mid_x
                    if a != b:
                        if a < trash:
                            if gsq[a] == 0.0:
                                touched[n_t] = a
                                n_t += 1
                            gsq[a] += f
                        if b < trash:
                            if gsq[b] == 0.0:
                                touched[n_t] = b
                                n_t += 1
                            gsq[b] += f
                for r in range(n_t):
                    c = touched[r]
                    gpart[c] += math.sqrt(gsq[c])
                    gsq[c] = 0.0
            for d in range(ndim - 2, -1, -1):  # advance the coordinates of the line
                coords[d] += 1
                if coords[d] < shape[d]:
                    break
                coords[d] = 0
        for k in range(n_labels):
            out[k] += gpart[k]
    return gsum


# -- fuzzy memberships: private --------------------------------------------------------------


@numba.njit(cache=True, parallel=True)
def _membership_stats(flat, mask):  # pragma: no cover - compiled
    """Per image the smallest and largest membership (whole grid), and per image and
    component whether a membership is nonzero inside the mask: one pass, one image per
    thread."""
    n_img, n_comp, n = flat.shape
    lows = np.empty(n_img)
    highs = np.empty(n_img)
    present = np.zeros((n_img, n_comp), np.bool_)
    has_mask = mask.size > 0
    for i in numba.prange(n_img):
        lo = np.inf
        hi = -np.inf
        for k in range(n_comp):
            row = flat[i, k]
            nonzero = False
            for v in range(n):
                a = row[v]
                lo = min(lo, a)
                hi = max(hi, a)
                nonzero |= a != 0 and (not has_mask or mask[v])
            present[i, k] = nonzero
        lows[i] = lo
        highs[i] = hi
    return lows, highs, present


@numba.njit(cache=True, parallel=True)
def _active_voxels(rows, step, n_img, mask, active):  # pragma: no cover - compiled
    """``active[v]``: some image has a nonzero membership at v inside the mask (image i's
    memberships are ``rows[i * step]``)."""
    n = rows.shape[1]
    n_chunks = (n + 4095) // 4096
    for c in numba.prange(n_chunks):
        start = c * 4096
        stop = min(start + 4096, n)
        act = active[start:stop]
        act[:] = False
        for i in range(n_img):
            row = rows[i * step, start:stop]
            for t in range(stop - start):
                act[t] |= row[t] != 0
        if mask.size > 0:
            mk = mask[start:stop]
            for t in range(stop - start):
                act[t] &= mk[t]


@numba.njit(cache=True, parallel=True)
def _pair_sums(
    rows, step, voxels, net_lo, net_hi, dense_share, packed, vol, spair
):  # pragma: no cover - compiled
    """Pair sums of the memberships of N = ``vol.size`` images (image i's: ``rows[i * step]``)
    over `voxels`, in blocks of ``_BLOCK`` voxels shared among the threads.

    A block where more than `dense_share` of the values lie strictly in (0, 1) is sorted by
    the network (:func:`_packed_network_kernel` for float32 input when `packed`, else
    :func:`_network_pair_kernel`), any other by :func:`_sparse_pair_kernel`. Each block
    writes its own partial sums, added up in block order afterwards: the result does not
    depend on the number of threads. Adds to ``vol`` and ``spair`` (N,); returns (sum of
    pairwise minima, sum of maxima).
    """
    n_img = vol.size
    n_blocks = (voxels.size + _BLOCK - 1) // _BLOCK
    pmin = np.zeros(n_blocks)
    pmax = np.zeros(n_blocks)
    vparts = np.zeros((n_blocks, n_img))
    sparts = np.zeros((n_blocks, n_img))
    for b in numba.prange(n_blocks):
        start = b * _BLOCK
        stop = min(start + _BLOCK, voxels.size)
        block = np.empty((n_img, stop - start))
        fractional = _gather(rows, step, voxels[start:stop], block)
        if fractional > dense_share * block.size:
            if packed:
                pk, qk = _packed_network_kernel(block, net_lo, net_hi, vparts[b], sparts[b])
            else:
                pk, qk = _network_pair_kernel(block, net_lo, net_hi, vparts[b], sparts[b])
        else:
            pk, qk = _sparse_pair_kernel(block, vparts[b], sparts[b])
        pmin[b] = pk
        pmax[b] = qk
    for b in range(n_blocks):
        for i in range(n_img):
            vol[i] += vparts[b, i]
            spair[i] += sparts[b, i]
    return pmin.sum(), pmax.sum()


@numba.njit(cache=True, parallel=True)
def _gradient_sums(rows, step, mask, shape, inv_h, out):  # pragma: no cover - compiled
    """``out[i] = sum_v |grad rows[i * step]|`` over the mask, one image per thread."""
    for i in numba.prange(out.size):
        out[i] = _gradient_sum_row(rows[i * step], mask, shape, inv_h)


@numba.njit(cache=True, nogil=True)
def _gradient_sum_row(row, mask, shape, inv_h):  # pragma: no cover - compiled
    """``sum_v |grad row|`` over the mask (`row` flat in C order of `shape`).

    Computed only on the slabs (along the first axis) within two of a nonzero one: farther
    out the gradient is zero, and two zero slabs on each side make the cut-out's face rule
    give the full grid's values.
    """
    n = row.size
    plane = n // shape[0]
    first = -1
    for v in range(n):
        if row[v] != 0:
            first = v
            break
    if first < 0:
        return 0.0
    last = first
    for v in range(n - 1, first, -1):
        if row[v] != 0:
            last = v
            break
    lo = max(first // plane - 2, 0)
    hi = min(last // plane + 3, shape[0])
    sub_shape = shape.copy()
    sub_shape[0] = hi - lo
    sub_mask = mask[lo * plane : hi * plane] if mask.size > 0 else mask
    return _grad_sum_kernel(row[lo * plane : hi * plane], sub_mask, sub_shape, inv_h)


@numba.njit(cache=True, nogil=True)
def _gather(rows, step, voxels, out):  # pragma: no cover - compiled
    """Copy ``rows[i * step, voxels]`` into ``out[i, :len(voxels)]`` for every image i < N =
    ``out.shape[0]`` (as float64); return how many of the values lie strictly in (0, 1)."""
    fractional = 0
    for i in range(out.shape[0]):
        row = rows[i * step]
        for t in range(voxels.size):
            a = np.float64(row[voxels[t]])
            out[i, t] = a
            if 0.0 < a < 1.0:
                fractional += 1
    return fractional


@functools.lru_cache(maxsize=16)
def _sorting_network(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Batcher's odd-even merge sort for `n` keys as comparator pairs (lo, hi), lo < hi.

    Built for the next power of two and pruned of comparators that reach past `n` (those
    keys would be +inf, so the pruned comparators never swap). 268 comparators for n = 36.
    """
    pairs = []
    p = 1
    while p < n:
        k = p
        while k >= 1:
            for j in range(k % p, n - k, 2 * k):
                for i in range(min(k, n - j - k)):
                    if (i + j) // (2 * p) == (i + j + k) // (2 * p):
                        pairs.append((i + j, i + j + k))
            k //= 2
        p *= 2
    lo = np.array([a for a, _ in pairs], dtype=np.int64)
    hi = np.array([b for _, b in pairs], dtype=np.int64)
    return lo, hi


def _float_minmax(name: str):
    """A numba intrinsic for ``llvm.minnum`` / ``llvm.maxnum`` on float64 (inputs not NaN).

    Unlike ``min(x, y)`` (compare and select, which LLVM turns into masked stores when the
    result goes back where x came from) these vectorize to plain ``vminpd`` / ``vmaxpd``.
    """

    @numba.extending.intrinsic
    def fn(typingctx, x, y):
        def codegen(context, builder, signature, args):
            dbl = llvm_ir.DoubleType()
            f = builder.module.declare_intrinsic(name, [dbl], llvm_ir.FunctionType(dbl, [dbl, dbl]))
            return builder.call(f, args, fastmath=("nnan",))

        return numba.types.float64(numba.types.float64, numba.types.float64), codegen

    return fn


_fmin = _float_minmax("llvm.minnum")
_fmax = _float_minmax("llvm.maxnum")


@numba.njit(cache=True, nogil=True)
def _packed_network_kernel(block, net_lo, net_hi, vol, spair):  # pragma: no cover - compiled
    """As :func:`_network_pair_kernel`, for float32 memberships (held in `block` as float64,
    which it overwrites).

    Layout: the sort keys are an (N, m) float64 array, row i holding image i's memberships
    of the m voxels of the block, so every comparator (lo, hi) of the network is one
    branch-free pass ``x = min(row lo, row hi), row hi = max(...)`` over m contiguous values
    (SIMD across voxels). The image index rides along inside the key: a float32 value as
    float64 has its low 29 mantissa bits zero, and writing i there keeps the order of the
    values (nonnegative floats order like their bit patterns; ties break by image), so the
    sort moves keys only, instead of keys and a separate index array. After the sort, rank
    row k is split back into the exact value and the image index.
    """
    n_img, m = block.shape
    keys = block  # sorted in place
    bits = keys.view(np.int64)
    for i in range(n_img):
        bi = bits[i]
        for t in range(m):
            bi[t] |= i
    for c in range(net_lo.size):
        va = keys[net_lo[c]]
        vb = keys[net_hi[c]]
        for t in range(m):
            x = va[t]
            y = vb[t]
            va[t] = _fmin(x, y)
            vb[t] = _fmax(x, y)
    low = np.int64((1 << _INDEX_BITS) - 1)
    img = np.empty(m, np.int64)
    below = np.zeros(m)
    pmin = 0.0
    pmax = 0.0
    for k in range(n_img):
        bk = bits[k]
        for t in range(m):
            i = bk[t] & low
            img[t] = i
            bk[t] -= i  # keys[k, t] is now the membership itself
        vk = keys[k]
        up = n_img - 1 - k
        total = 0.0
        for t in range(m):
            a = vk[t]
            total += a
            spair[img[t]] += a * up + below[t]
            vol[img[t]] += a
            below[t] += a
        pmin += total * up
        pmax += total * k
    return pmin, pmax


@numba.njit(cache=True, nogil=True)
def _network_pair_kernel(block, net_lo, net_hi, vol, spair):  # pragma: no cover - compiled
    """Pair sums of the memberships `block` (N, n_voxels) by sorting every voxel's column.

    The columns are sorted ascending with the comparator network (net_lo, net_hi), run on
    whole rows at once (branch-free, vectorized across voxels), carrying each value's image
    index. With a_(k) the k-th smallest (k = 0..N-1), a voxel adds ``a_(k) (N - 1 - k)`` to
    the sum of pairwise minima, ``a_(k) k`` to the maxima, and ``sum_{m<k} a_(m) +
    a_(k) (N - 1 - k)`` (= ``sum_{j != i} min(a_i, a_j)``) to ``spair`` of its image i; ties
    do not matter. Adds memberships to ``vol``; returns (sum of minima, sum of maxima).
    """
    n_img, m = block.shape
    val = np.empty((n_img, m), np.float64)
    img = np.empty((n_img, m), np.int64)
    for i in range(n_img):
        for t in range(m):
            val[i, t] = block[i, t]
            img[i, t] = i
    for c in range(net_lo.size):
        va = val[net_lo[c]]
        vb = val[net_hi[c]]
        ia = img[net_lo[c]]
        ib = img[net_hi[c]]
        for t in range(m):
            x = va[t]
            y = vb[t]
            i1 = ia[t]
            i2 = ib[t]
            swap = y < x
            va[t] = y if swap else x
            vb[t] = x if swap else y
            ia[t] = i2 if swap else i1
            ib[t] = i1 if swap else i2
    below = np.zeros(m)
    vpart = np.zeros(n_img)
    spart = np.zeros(n_img)
    pmin = 0.0
    pmax = 0.0
    for k in range(n_img):
        vk = val[k]
        ik = img[k]
        up = n_img - 1 - k
        total = 0.0
        for t in range(m):
            a = vk[t]
            total += a
            spart[ik[t]] += a * up + below[t]
            vpart[ik[t]] += a
            below[t] += a
        pmin += total * up
        pmax += total * k
    for i in range(n_img):
        vol[i] += vpart[i]
        spair[i] += spart[i]
    return pmin, pmax


@numba.njit(cache=True, nogil=True)
def _sparse_pair_kernel(block, vol, spair):  # pragma: no cover - compiled
    """As :func:`_network_pair_kernel`, for memberships that are mostly exactly 0 or 1.

    Per voxel, zeros take the lowest ranks and add nothing, the o ones take the top ranks,
    and only the fractional values in between are sorted (insertion sort, carrying the
    image index): O(N) for a voxel without fractional values.
    """
    n_img, m = block.shape
    vals = np.empty(n_img, np.float64)
    ids = np.empty(n_img, np.int64)
    ones = np.empty(n_img, np.int64)
    vpart = np.zeros(n_img, np.float64)
    spart = np.zeros(n_img, np.float64)
    pmin = 0.0
    pmax = 0.0
    for t in range(m):
        n_frac = 0
        n_one = 0
        for i in range(n_img):
            a = np.float64(block[i, t])
            if a == 0.0:
                continue
            if a == 1.0:
                ones[n_one] = i
                n_one += 1
                continue
            j = n_frac
            while j > 0 and vals[j - 1] > a:
                vals[j] = vals[j - 1]
                ids[j] = ids[j - 1]
                j -= 1
            vals[j] = a
            ids[j] = i
            n_frac += 1
        if n_frac + n_one == 0:
            continue
        first = n_img - n_one - n_frac  # 0-based rank of the smallest nonzero value
        below = 0.0
        for r in range(n_frac):
            rank = first + r
            a = vals[r]
            up = a * (n_img - 1 - rank)
            pmin += up
            pmax += a * rank
            spart[ids[r]] += up + below
            vpart[ids[r]] += a
            below += a
        if n_one > 0:
            top = n_img - n_one  # ones hold ranks top .. N - 1
            pmin += n_one * (n_one - 1) / 2.0
            pmax += (top + n_img - 1) * n_one / 2.0
            for r in range(n_one):  # min with the other ones (1 each) and every smaller value
                spart[ones[r]] += (n_one - 1) + below
                vpart[ones[r]] += 1.0
    for i in range(n_img):
        vol[i] += vpart[i]
        spair[i] += spart[i]
    return pmin, pmax


@numba.njit(cache=True, nogil=True, fastmath={"reassoc", "nsz"})
def _grad_sum_kernel(row, mask, shape, inv_h):  # pragma: no cover - compiled
    """``sum_v |grad row|`` over the masked voxels; `row` flat in C order of `shape`.

    One pass, line by line along the last (contiguous) axis: the squared differences of
    every axis go into a line of scratch (the neighbouring lines along the other axes are
    whole lines too, so every inner loop is contiguous and vectorizes), then the line's
    square roots are summed. ``mask`` is flat boolean or empty (no mask).
    """
    n = row.size
    ndim = shape.size
    nx = shape[ndim - 1]
    strides = np.ones(ndim, np.int64)
    for d in range(ndim - 2, -1, -1):
        strides[d] = strides[d + 1] * shape[d + 1]
    coords = np.zeros(ndim, np.int64)
    g = np.zeros(nx)
    fx1 = inv_h[ndim - 1]
    fx2 = 0.5 * fx1
    total = 0.0
    for base in range(0, n, nx):
        r = row[base : base + nx]
        if nx > 1:  # last axis: one-sided at the ends, central inside
            e = (np.float64(r[1]) - np.float64(r[0])) * fx1
            g[0] = e * e
            e = (np.float64(r[nx - 1]) - np.float64(r[nx - 2])) * fx1
            g[nx - 1] = e * e
            hi = r[2:]
            lo = r[: nx - 2]
            mid = g[1 : nx - 1]
            for t in range(nx - 2):
                e = (np.float64(hi[t]) - np.float64(lo[t])) * fx2
                mid[t] = e * e
        else:
            g[0] = 0.0
        for d in range(ndim - 1):  # the other axes: whole neighbouring lines
            size = shape[d]
            if size == 1:
                continue
            c = coords[d]
            f = inv_h[d] if c == 0 or c == size - 1 else 0.5 * inv_h[d]
            up = base + strides[d] if c < size - 1 else base
            down = base - strides[d] if c > 0 else base
            rp = row[up : up + nx]
            rm = row[down : down + nx]
            for t in range(nx):
                e = (np.float64(rp[t]) - np.float64(rm[t])) * f
                g[t] += e * e
        for start in range(0, nx, 4096):  # blocked summation keeps float rounding small
            part = 0.0
            stop = min(start + 4096, nx)
            if mask.size > 0:
                mk = mask[base : base + nx]
                for t in range(start, stop):
                    part += math.sqrt(g[t]) if mk[t] else 0.0
            else:
                for t in range(start, stop):
                    part += math.sqrt(g[t])
            total += part
        for d in range(ndim - 2, -1, -1):  # advance the coordinates of the line
            coords[d] += 1
            if coords[d] < shape[d]:
                break
            coords[d] = 0
    return total
