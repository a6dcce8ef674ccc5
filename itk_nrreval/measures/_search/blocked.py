"""Specificity for large N: blocks of model samples against cache-sized tiles of training points.

The per-sample search of :mod:`.sampling` streams the whole (n_modes x n_images) training
matrix once per sample: ideal for N ~ 36, memory-bound at N ~ 10,000 (800 MB per sample).
Here a block of S samples is drawn at once (the same counter-based normals, so the same
numbers) and compared with the training set in one sweep:

* L1: a numba kernel, modes outer and an S x I accumulator over a tile of I training images
  (the inner loop runs over contiguous images and vectorizes). Every distance is summed over
  the modes in the same order as the per-sample path, so the raw distances, the nearest
  indices and every moment are bit-identical to it.
* L2: squared distances ``|y|^2 - 2 Y X^T + |x|^2`` by one BLAS GEMM per block, then every
  candidate within a rigorous rounding bound of the row (column) minimum is recomputed by
  direct summation in the per-sample path's order; the exact minimum is always among the
  candidates, so the results are again bit-identical and free of cancellation.
* torch (optional): the same blocks on a torch device, float64 (argmin, then exact recompute);
  equal to the CPU paths to rounding.

A Gaussian mixture (``groups``) runs through the same searchers: chunk by chunk of its span
table, each chunk's samples drawn from its group's component (:func:`draw_mixture_block`, the
same sums as :func:`.sampling.draw_mixture`, so again the same bits as the per-sample path).

Chunks of samples are :data:`.sampling.CHUNK` long as in the per-sample path, and each chunk
gives its (mean, M2) and gen minima in the same form, so :func:`.sampling.combine_moments`
and everything after it are shared. Memory per block is O(S (n_modes + n_images)).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from .sampling import chunk_moments, fill_normals, finish_distances, mixture_spans

__all__ = [
    "draw_block",
    "draw_mixture_block",
    "BlockedSearcher",
    "TorchSearcher",
    "search_chunks",
    "run_single_blocked",
]

L1_BLOCK = 32  # samples per parallel task of the L1 kernel
L1_TILE_IMAGES = 256  # training images per tile: an accumulator row is 2 kB (L1 cache)
L1_TILE_MODES = 32  # modes per tile: the training tile is 32 x 256 x 8 B = 64 kB (L2 cache)
# Samples per GEMM block: L2_BLOCK_ELEMENTS / max(N, n_modes) (32 MB each for the block and its
# products), clipped to L2_BLOCK_RANGE: 1024 from N = 1,000 down is 1.6x faster than 256 there.
L2_BLOCK_ELEMENTS = 1 << 22
L2_BLOCK_RANGE = (256, 1024)
L2_TILE_IMAGES = 512  # columns per tile of the column (generalization) pass
TORCH_BLOCK = 256  # samples per torch block
# Mixture samples built together, each basis row loaded once for all: 16 rows of y are 128 kB
# at K = 1000 (L2 cache). The draw of the GEMM path stays serial (see below): measured, a
# parallel draw lost more to the hand-over than it gained, at N = 150 to 1000.
MIXTURE_TILE = 16
_U = 2.0**-53


# The GEMM (L2) and torch paths draw and select serially, between multithreaded BLAS / torch
# calls: numba's OpenMP workers spin after each parallel region and starve the BLAS threads on
# a 2-core machine (measured: ~8 ms lost per hand-over, 8x slower at N = 36, 1.2x at N = 1000),
# while the serial parts cost O(S (N + K)) against the GEMM's O(S N K).
@numba.njit(cache=True)
def draw_block(sd, key, start, stop, out):
    """Model samples ``start:stop`` into ``out[: stop - start]`` (rows: samples, scaled by sd)."""
    for j in range(stop - start):
        y = out[j]
        fill_normals(key, start + j, y)
        for k in range(y.shape[0]):
            y[k] *= sd[k]


@numba.njit(cache=True)
def _draw_mixture_tile(centre, basis, key, start, m, z, out):
    """Samples ``start .. start + m - 1`` of one mixture component into ``out[:m]``.

    The same sums as :func:`.sampling.draw_mixture` (centre, then the modes in turn, for
    every coordinate), so the same bits; but each basis row is loaded once for all m
    samples, not once per sample (the basis, K_g x K, outgrows the caches at large N).
    z (>= m, n_group_modes) is scratch.
    """
    n_modes = out.shape[1]
    n_basis = basis.shape[0]
    for s in range(m):
        fill_normals(key, start + s, z[s])
        for k in range(n_modes):
            out[s, k] = centre[k]
    j = 0
    while j + 3 < n_basis:  # four modes per pass over y: the additions stay in order
        r0, r1, r2, r3 = basis[j], basis[j + 1], basis[j + 2], basis[j + 3]
        for s in range(m):
            z0, z1, z2, z3 = z[s, j], z[s, j + 1], z[s, j + 2], z[s, j + 3]
            y = out[s]
            for k in range(n_modes):
                y[k] = (((y[k] + z0 * r0[k]) + z1 * r1[k]) + z2 * r2[k]) + z3 * r3[k]
        j += 4
    for jj in range(j, n_basis):
        row = basis[jj]
        for s in range(m):
            zj = z[s, jj]
            y = out[s]
            for k in range(n_modes):
                y[k] += zj * row[k]


@numba.njit(cache=True)
def draw_mixture_block(centre, basis, key, start, stop, out):
    """Samples ``start:stop`` of one mixture component into ``out[: stop - start]``."""
    z = np.empty((MIXTURE_TILE, basis.shape[0]))
    for s0 in range(start, stop, MIXTURE_TILE):
        s1 = min(stop, s0 + MIXTURE_TILE)
        _draw_mixture_tile(centre, basis, key, s0, s1 - s0, z, out[s0 - start :])


# ---------------------------------------------------------------------------------------- L1


@numba.njit(cache=True)
def _l1_task(train_t, sd, key, start, stop, y, acc, values, nearest, gen_row):
    """Samples start:stop (at most len(y)) against all training images, tile by tile.

    train_t is (n_modes, n_images). values/nearest (stop - start,) receive each sample's raw
    L1 nearest distance and index; gen_row (n_images,) is lowered to each image's nearest
    sample distance. y (block, n_modes) and acc (block, L1_TILE_IMAGES) are scratch.
    """
    n_modes = train_t.shape[0]
    for j in range(stop - start):
        row = y[j]
        fill_normals(key, start + j, row)
        for k in range(n_modes):
            row[k] *= sd[k]
    _l1_search(train_t, y, stop - start, acc, values, nearest, gen_row)


@numba.njit(cache=True)
def _l1_task_mixture(train_t, centre, basis, key, start, stop, y, acc, values, nearest, gen_row):
    """As :func:`_l1_task` for samples start:stop of one mixture component."""
    z = np.empty((stop - start, basis.shape[0]))
    _draw_mixture_tile(centre, basis, key, start, stop - start, z, y)
    _l1_search(train_t, y, stop - start, acc, values, nearest, gen_row)


@numba.njit(cache=True)
def _l1_search(train_t, y, m, acc, values, nearest, gen_row):
    """The samples y[:m] against all training images (train_t, n_modes x n_images), by tiles."""
    n_modes, n_images = train_t.shape
    for j in range(m):
        values[j] = np.inf
        nearest[j] = 0
    for i0 in range(0, n_images, L1_TILE_IMAGES):
        i1 = min(n_images, i0 + L1_TILE_IMAGES)
        w = i1 - i0
        for j in range(m):
            for t in range(w):
                acc[j, t] = 0.0
        for k0 in range(0, n_modes, L1_TILE_MODES):
            k1 = min(n_modes, k0 + L1_TILE_MODES)
            j = 0
            while j + 1 < m:  # two samples per pass: each training value is loaded once
                a0 = acc[j]
                a1 = acc[j + 1]
                for k in range(k0, k1):
                    y0 = y[j, k]
                    y1 = y[j + 1, k]
                    x = train_t[k, i0:i1]
                    for t in range(w):
                        a0[t] += abs(y0 - x[t])
                        a1[t] += abs(y1 - x[t])
                j += 2
            if j < m:
                a0 = acc[j]
                for k in range(k0, k1):
                    y0 = y[j, k]
                    x = train_t[k, i0:i1]
                    for t in range(w):
                        a0[t] += abs(y0 - x[t])
        for j in range(m):
            best = values[j]
            besti = nearest[j]
            for t in range(w):
                d = acc[j, t]
                if d < best:
                    best = d
                    besti = i0 + t
                if d < gen_row[i0 + t]:
                    gen_row[i0 + t] = d
            values[j] = best
            nearest[j] = besti


@numba.njit(parallel=True, cache=True)
def _l1_chunk(train_t, sd, key, start, stop, values, nearest, gen):
    """Samples start:stop in parallel tasks of L1_BLOCK; gen (n_images,) lowered in place."""
    n_modes, n_images = train_t.shape
    n_tasks = (stop - start + L1_BLOCK - 1) // L1_BLOCK
    gen_tasks = np.full((n_tasks, n_images), np.inf)
    for task in numba.prange(n_tasks):
        s0 = start + task * L1_BLOCK
        s1 = min(stop, s0 + L1_BLOCK)
        y = np.empty((L1_BLOCK, n_modes))
        acc = np.empty((L1_BLOCK, L1_TILE_IMAGES))
        _l1_task(
            train_t,
            sd,
            key,
            s0,
            s1,
            y,
            acc,
            values[s0 - start : s1 - start],
            nearest[s0 - start : s1 - start],
            gen_tasks[task],
        )
    for task in range(n_tasks):
        for i in range(n_images):
            if gen_tasks[task, i] < gen[i]:
                gen[i] = gen_tasks[task, i]


@numba.njit(parallel=True, cache=True)
def _l1_chunk_mixture(train_t, centre, basis, key, start, stop, values, nearest, gen):
    """As :func:`_l1_chunk` for samples start:stop of one mixture component."""
    n_modes, n_images = train_t.shape
    n_tasks = (stop - start + L1_BLOCK - 1) // L1_BLOCK
    gen_tasks = np.full((n_tasks, n_images), np.inf)
    for task in numba.prange(n_tasks):
        s0 = start + task * L1_BLOCK
        s1 = min(stop, s0 + L1_BLOCK)
        y = np.empty((L1_BLOCK, n_modes))
        acc = np.empty((L1_BLOCK, L1_TILE_IMAGES))
        _l1_task_mixture(
            train_t,
            centre,
            basis,
            key,
            s0,
            s1,
            y,
            acc,
            values[s0 - start : s1 - start],
            nearest[s0 - start : s1 - start],
            gen_tasks[task],
        )
    for task in range(n_tasks):
        for i in range(n_images):
            if gen_tasks[task, i] < gen[i]:
                gen[i] = gen_tasks[task, i]


# ---------------------------------------------------------------------------------------- L2


@numba.njit(inline="always", cache=True)
def _sq_exact(y, x):
    """Squared L2 distance summed mode by mode, in the per-sample path's order."""
    s = 0.0
    for k in range(y.shape[0]):
        diff = y[k] - x[k]
        s += diff * diff
    return s


@numba.njit(cache=True)
def _l2_select(y, train, sq_train, norm_train_max, gram, values, nearest, gen):
    """Nearest per sample and per training image from one GEMM block, recomputed exactly.

    y (m, n_modes) samples, train (n_images, n_modes), sq_train (n_images,) their squared
    norms, gram (m, n_images) = y @ train.T. Squared distances ``|y|^2 - 2 g + |x|^2`` carry
    a rounding error below ``gamma (|y| + |x|)^2`` (gamma = (n_modes + 2) u / (1 - ...)); each
    candidate within twice that (both sides) of the minimum is recomputed by direct summation,
    so the exactly summed minimum, with the lowest index among ties, is always found.
    """
    m, n_modes = y.shape
    n_images = train.shape[0]
    gamma = 2.0 * (n_modes + 4) * _U / (1.0 - (n_modes + 4) * _U)
    sq_y = np.empty(m)
    for j in range(m):
        s = 0.0
        for k in range(n_modes):
            s += y[j, k] * y[j, k]
        sq_y[j] = s
    norm_y_max = math.sqrt(sq_y.max())
    for j in range(m):
        g = gram[j]
        base = sq_y[j]
        dmin = np.inf
        for i in range(n_images):
            d = base - 2.0 * g[i] + sq_train[i]
            if d < dmin:
                dmin = d
        r = math.sqrt(base) + norm_train_max
        thr = dmin + 2.0 * gamma * r * r
        best = np.inf
        besti = 0
        for i in range(n_images):
            d = base - 2.0 * g[i] + sq_train[i]
            if d <= thr:
                e = _sq_exact(y[j], train[i])
                if e < best:
                    best = e
                    besti = i
        values[j] = best
        nearest[j] = besti
    n_tiles = (n_images + L2_TILE_IMAGES - 1) // L2_TILE_IMAGES
    for tile in range(n_tiles):  # column tiles: row-contiguous passes over the gram block
        i0 = tile * L2_TILE_IMAGES
        i1 = min(n_images, i0 + L2_TILE_IMAGES)
        colmin = np.full(i1 - i0, np.inf)
        for j in range(m):
            base = sq_y[j]
            g = gram[j]
            for i in range(i0, i1):
                d = base - 2.0 * g[i] + sq_train[i]
                if d < colmin[i - i0]:
                    colmin[i - i0] = d
        for i in range(i0, i1):
            r = norm_y_max + math.sqrt(sq_train[i])
            colmin[i - i0] += 2.0 * gamma * r * r
        for j in range(m):
            base = sq_y[j]
            g = gram[j]
            for i in range(i0, i1):
                d = base - 2.0 * g[i] + sq_train[i]
                if d <= colmin[i - i0]:
                    e = _sq_exact(y[j], train[i])
                    if e < gen[i]:
                        gen[i] = e


def _l2_block(n_images: int, n_modes: int) -> int:
    """Samples per GEMM block for a model of this size."""
    lo, hi = L2_BLOCK_RANGE
    return int(min(hi, max(lo, L2_BLOCK_ELEMENTS // max(n_images, n_modes, 1))))


def _l2_chunk(train, sq_train, norm_max, draw, start, stop, values, nearest, gen, work):
    """Samples start:stop in GEMM blocks of len(work[0]); gen (n_images,) lowered in place.

    ``draw(s0, s1, out)`` writes samples s0:s1 into the rows of `out`.
    """
    y, gram = work
    block = y.shape[0]
    for s0 in range(start, stop, block):
        s1 = min(stop, s0 + block)
        m = s1 - s0
        draw(s0, s1, y)
        np.matmul(y[:m], train.T, out=gram[:m])
        _l2_select(
            y[:m],
            train,
            sq_train,
            norm_max,
            gram[:m],
            values[s0 - start : s1 - start],
            nearest[s0 - start : s1 - start],
            gen,
        )


# ------------------------------------------------------------------------------- drivers


class BlockedSearcher:
    """One model's blocked nearest search, chunk by chunk (CPU).

    Samples are ``sd * z`` (a single Gaussian, `sd` its mode standard deviations) or, when
    :meth:`chunk` is given a mixture component ``(centre, basis)``, ``centre + z @ basis``
    (:func:`.sampling.draw_mixture`; `sd` is then unused and may be None).
    """

    def __init__(self, train: np.ndarray, sd: np.ndarray | None, l2: bool):
        self.l2 = l2
        self.sd = None if sd is None else np.ascontiguousarray(sd, dtype=np.float64)
        n_images, n_modes = train.shape
        self.n_images = n_images
        if l2:
            self.train = np.ascontiguousarray(train, dtype=np.float64)
            self.sq_train = np.einsum("ik,ik->i", self.train, self.train)
            self.norm_max = float(np.sqrt(self.sq_train.max()))
            block = _l2_block(n_images, n_modes)
            self.work = (np.empty((block, n_modes)), np.empty((block, n_images)))
        else:
            self.train_t = np.ascontiguousarray(np.asarray(train, dtype=np.float64).T)

    def chunk(self, key, start: int, stop: int, component=None):
        """Raw nearest distances (m,), indices (m,) and gen minima (n_images,) of a chunk.

        `component` is None (samples ``sd * z``) or a mixture component ``(centre, basis)``.
        """
        m = stop - start
        values = np.empty(m)
        nearest = np.empty(m, dtype=np.int64)
        gen = np.full(self.n_images, np.inf)
        if self.l2:
            if component is None:
                sd = self.sd

                def draw(s0, s1, out):
                    draw_block(sd, key, s0, s1, out)
            else:
                centre, basis = component

                def draw(s0, s1, out):
                    draw_mixture_block(centre, basis, key, s0, s1, out)

            _l2_chunk(
                self.train,
                self.sq_train,
                self.norm_max,
                draw,
                start,
                stop,
                values,
                nearest,
                gen,
                self.work,
            )
        elif component is None:
            _l1_chunk(self.train_t, self.sd, key, start, stop, values, nearest, gen)
        else:
            centre, basis = component
            _l1_chunk_mixture(self.train_t, centre, basis, key, start, stop, values, nearest, gen)
        return values, nearest, gen


def search_chunks(searchers, components, spans, key, l2, exponent, first, last):
    """Chunks ``first .. last - 1`` of a batch of searchers on one sample stream.

    Parameters
    ----------
    searchers : sequence of BlockedSearcher or TorchSearcher
        One per model: one model, or a pair (the same samples' numbers and normals).
    components : sequence, one per searcher, of None or a sequence of (centre, basis)
        None: samples ``sd * z`` (a single Gaussian); else per group g its ``(centre,
        basis)`` in joint parameters (a mixture).
    spans : ndarray of int64, shape (n_chunks, 3)
        Chunk c is samples ``spans[c, 0] .. spans[c, 1] - 1`` of group ``spans[c, 2]``
        (:func:`.sampling.mixture_spans`).
    key : np.uint64
        Stream key of the seed (:func:`.sampling.stream_key`).
    l2 : bool
        Squared L2 (True) or L1 sums (False).
    exponent : float
        Each finished nearest distance is raised to this power.
    first, last : int
        The chunks to run.

    Returns
    -------
    per_model : list of (means, m2s, counts, gen), one per searcher
        Per chunk (n = last - first): (mean, M2) of the finished nearest distances, (n,); the
        nearest counts, int64 (n, n_images); each image's raw nearest-sample distance (n, n_images).
    difference : ndarray of shape (n, 2), or None
        For a pair, per chunk (mean, M2) of the per-sample differences a - b; else None.
    """
    n = last - first
    per_model = [
        (
            np.empty(n),
            np.empty(n),
            np.zeros((n, s.n_images), dtype=np.int64),
            np.empty((n, s.n_images)),
        )
        for s in searchers
    ]
    difference = np.empty((n, 2)) if len(searchers) == 2 else None
    for c in range(n):
        start, stop, g = (int(v) for v in spans[first + c])
        m = stop - start
        finished = []
        for searcher, comps, (means, m2s, counts, gen) in zip(
            searchers, components, per_model, strict=True
        ):
            values, nearest, gen[c] = searcher.chunk(
                key, start, stop, None if comps is None else comps[g]
            )
            finish_distances(values, m, l2, float(exponent))
            means[c], m2s[c] = chunk_moments(values, m)
            counts[c] = np.bincount(nearest, minlength=searcher.n_images)
            finished.append(values)
        if difference is not None:
            difference[c] = chunk_moments(finished[0] - finished[1], m)
    return per_model, difference


def run_single_blocked(train, sd, key, n_samples, l2, exponent, chunk):
    """As :func:`.sampling.run_single` over every chunk, by blocks of samples; the same numbers.

    Parameters
    ----------
    train : ndarray of shape (n_images, n_modes)
        The training parameters (rows: images; not transposed, unlike ``run_single``).
    sd : ndarray of shape (n_modes,)
        Mode standard deviations.
    key : np.uint64
        Stream key of the seed (``sampling.stream_key``).
    n_samples, l2, exponent, chunk
        As ``run_single``.

    Returns
    -------
    means, m2s : ndarray of shape (n_chunks,)
    counts : ndarray of int64, shape (n_chunks, n_images)
    gen : ndarray of shape (n_chunks, n_images)
        Raw (L1 sum or squared L2) nearest-sample distance of each image, per chunk.
    """
    spans = mixture_spans([int(n_samples)], int(chunk))
    searcher = BlockedSearcher(train, sd, l2)
    (stats,), _ = search_chunks([searcher], [None], spans, key, l2, exponent, 0, spans.shape[0])
    return stats


# ------------------------------------------------------------------------------------ torch


class TorchSearcher:
    """The blocked search with distances on a torch device (float64); normals from the CPU."""

    def __init__(self, train: np.ndarray, sd: np.ndarray | None, l2: bool, device):
        import torch

        self.torch = torch
        self.l2 = l2
        self.device = device
        self.sd = None if sd is None else np.ascontiguousarray(sd, dtype=np.float64)
        self.n_images, n_modes = train.shape
        self.train = torch.as_tensor(np.asarray(train, dtype=np.float64), device=device)
        self.sq_train = (self.train * self.train).sum(dim=1)
        self.y = np.empty((TORCH_BLOCK, n_modes))

    def _exact(self, a, b):
        return ((a - b) ** 2).sum(dim=1)

    def chunk(self, key, start: int, stop: int, component=None):
        torch = self.torch
        values = np.empty(stop - start)
        nearest = np.empty(stop - start, dtype=np.int64)
        gen = torch.full((self.n_images,), math.inf, dtype=torch.float64, device=self.device)
        for s0 in range(start, stop, TORCH_BLOCK):
            s1 = min(stop, s0 + TORCH_BLOCK)
            m = s1 - s0
            if component is None:
                draw_block(self.sd, key, s0, s1, self.y)
            else:
                draw_mixture_block(component[0], component[1], key, s0, s1, self.y)
            y = torch.as_tensor(self.y[:m], device=self.device)
            if self.l2:
                d = (y * y).sum(dim=1)[:, None] - 2.0 * (y @ self.train.T) + self.sq_train
                idx = d.argmin(dim=1)
                best = self._exact(y, self.train[idx])
                col = d.argmin(dim=0)
                del d
                col_best = torch.empty_like(gen)
                for i0 in range(0, self.n_images, TORCH_BLOCK):  # bounded: block x n_modes
                    i1 = min(self.n_images, i0 + TORCH_BLOCK)
                    col_best[i0:i1] = self._exact(y[col[i0:i1]], self.train[i0:i1])
            else:
                d = torch.cdist(y[None], self.train[None], p=1.0)[0]
                best, idx = d.min(dim=1)
                col_best = d.min(dim=0).values
                del d
            torch.minimum(gen, col_best, out=gen)
            values[s0 - start : s1 - start] = best.cpu().numpy()
            nearest[s0 - start : s1 - start] = idx.cpu().numpy()
        return values, nearest, gen.cpu().numpy()
