"""Model samples and their nearest training points, fused, in parallel (numba).

Samples are never stored: sample ``mu`` of a model with mode standard deviations ``sd`` is
``y[k] = z(seed, mu, k) * sd[k]``, where ``z`` is a counter-based standard normal (the
splitmix64 stream at a position fixed by ``(mu, k)``, turned normal by the ziggurat). Hence

* the same seed gives the same numbers whatever the thread count or chunk size;
* two models sharing a seed see the same standard normals in their common modes
  (common random numbers, for paired comparisons);
* memory is O(chunk x N) per thread, whatever M is.

Distances to the N training points are accumulated mode by mode across all N at once, which
vectorizes; the per-sample nearest distance (L1 sum, or squared L2) and its index come out.

A Gaussian mixture (:class:`itk_nrreval.measures.model.MixtureModel`) is sampled group by group: its
samples are numbered ``0 .. M - 1`` with group g owning one contiguous range (a *span* table,
:func:`mixture_spans`), and sample ``mu`` of group g is ``centre_g + z(seed, mu, :K_g) @ basis_g``
(:func:`draw_mixture`), in the joint parameter space where the training points live. The same
three properties hold: a sample depends only on the seed, its number and its group.
"""

from __future__ import annotations

import numba
import numpy as np

from ..._errors import readable

__all__ = [
    "stream_key",
    "fill_normals",
    "finish_distances",
    "chunk_moments",
    "standard_normals",
    "run_single",
    "run_paired",
    "draw_mixture",
    "mixture_spans",
    "run_mixture",
    "run_mixture_paired",
    "nearest_of_samples",
    "combine_moments",
    "CHUNK",
]

CHUNK = 4096
_GAMMA = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_INV_2_53 = 1.0 / 9007199254740992.0
# Counter layout: ((mu << 18 | k) << 10) | (attempt << 2) | draw. Limits: k < 2**18 modes,
# mu < 2**36 samples, and 256 ziggurat attempts (the chance of needing more is below 1e-300).
MAX_MODES = 1 << 18
MAX_SAMPLES = 1 << 36
_MAX_ATTEMPTS = 256


def _ziggurat_tables():
    """Marsaglia & Tsang's 256-layer ziggurat for the standard normal, 52-bit magnitudes."""
    r = 3.6541528853610088
    v = 0.00492867323399
    m = 2.0**52
    ki = np.zeros(256, dtype=np.uint64)
    wi = np.zeros(256)
    fi = np.zeros(256)
    dn = tn = r
    q = v / np.exp(-0.5 * dn * dn)
    ki[0] = np.uint64((dn / q) * m)
    ki[1] = 0
    wi[0] = q / m
    wi[255] = dn / m
    fi[0] = 1.0
    fi[255] = np.exp(-0.5 * dn * dn)
    for i in range(254, 0, -1):
        dn = np.sqrt(-2.0 * np.log(v / dn + np.exp(-0.5 * dn * dn)))
        ki[i + 1] = np.uint64((dn / tn) * m)
        tn = dn
        fi[i] = np.exp(-0.5 * dn * dn)
        wi[i] = dn / m
    return ki, wi, fi, r


_KI, _WI, _FI, _ZIG_R = _ziggurat_tables()
_ZIG_INV_R = 1.0 / _ZIG_R


@numba.njit(inline="always", cache=True)
def _bits(key, counter):
    """The splitmix64 stream `key` at position `counter`: 64 random bits."""
    x = key + (counter + np.uint64(1)) * _GAMMA
    x = (x ^ (x >> np.uint64(30))) * _M1
    x = (x ^ (x >> np.uint64(27))) * _M2
    return x ^ (x >> np.uint64(31))


@numba.njit(inline="always", cache=True)
def _uniform(key, counter):
    """A uniform in [0, 1) from the stream `key` at position `counter`."""
    return (_bits(key, counter) >> np.uint64(11)) * _INV_2_53


@numba.njit(cache=True)
def _normal_slow(key, base, attempt, idx, negative, x):
    """The ziggurat's rare paths (wedge test, tail), then fresh attempts, for one normal."""
    while True:
        c = base | (np.uint64(attempt) << np.uint64(2))
        if idx == 0:  # the tail beyond r
            for tail in range(_MAX_ATTEMPTS):
                tail_key = key ^ (_M1 * np.uint64(tail + 1))  # a stream per tail attempt
                xx = -_ZIG_INV_R * np.log1p(-_uniform(tail_key, c | np.uint64(2)))
                yy = -np.log1p(-_uniform(tail_key, c | np.uint64(3)))
                if yy + yy > xx * xx:
                    return -(_ZIG_R + xx) if negative else _ZIG_R + xx
        else:
            u = _uniform(key, c | np.uint64(1))
            if (_FI[idx - 1] - _FI[idx]) * u + _FI[idx] < np.exp(-0.5 * x * x):
                return x
        attempt += 1
        if attempt == _MAX_ATTEMPTS:
            return x
        r = _bits(key, base | (np.uint64(attempt) << np.uint64(2)))
        idx = np.int64(r & np.uint64(0xFF))
        r = r >> np.uint64(8)
        negative = (r & np.uint64(1)) != 0
        rabs = (r >> np.uint64(1)) & np.uint64(0x000FFFFFFFFFFFFF)
        x = -(rabs * _WI[idx]) if negative else rabs * _WI[idx]
        if rabs < _KI[idx]:
            return x


@numba.njit(cache=True)
def fill_normals(key, mu, out):
    """Standard normals z(key, mu, k) for k < len(out): each fixed by (key, mu, k) alone.

    Ziggurat (Marsaglia & Tsang, 256 layers, as numpy's): normal k of sample mu reads the
    stream at counters ``((mu << 18 | k) << 10) | (attempt << 2) | draw``; the first attempt's
    fast path (about 99% of draws) is inlined here.
    """
    sample_base = np.uint64(mu) << np.uint64(18)
    n_slow = 0
    for k in range(out.shape[0]):
        r = _bits(key, (sample_base | np.uint64(k)) << np.uint64(10))
        idx = np.int64(r & np.uint64(0xFF))
        r = r >> np.uint64(8)
        rabs = (r >> np.uint64(1)) & np.uint64(0x000FFFFFFFFFFFFF)
        x = rabs * _WI[idx]
        out[k] = -x if (r & np.uint64(1)) != 0 else x
        if rabs >= _KI[idx]:
            out[k] = np.nan  # finished below: a call in this loop would slow every draw
            n_slow += 1
    if n_slow:
        for k in range(out.shape[0]):
            if np.isnan(out[k]):
                base = (sample_base | np.uint64(k)) << np.uint64(10)
                r = _bits(key, base)
                idx = np.int64(r & np.uint64(0xFF))
                r = r >> np.uint64(8)
                x = ((r >> np.uint64(1)) & np.uint64(0x000FFFFFFFFFFFFF)) * _WI[idx]
                negative = (r & np.uint64(1)) != 0
                out[k] = _normal_slow(key, base, 0, idx, negative, -x if negative else x)


def stream_key(seed: int) -> np.uint64:
    """The splitmix64-mixed stream key of a user seed."""
    if not 0 <= int(seed) < 2**63:
        raise ValueError(f"seed must be an integer in [0, 2**63), got {readable(seed)}")
    mask = 2**64 - 1
    x = (int(seed) + int(_GAMMA)) & mask
    x = ((x ^ (x >> 30)) * int(_M1)) & mask
    x = ((x ^ (x >> 27)) * int(_M2)) & mask
    return np.uint64(x ^ (x >> 31))


def standard_normals(seed: int, start: int, stop: int, n_modes: int) -> np.ndarray:
    """The standard normals of samples ``start:stop`` as an array (for tests and references)."""
    key = stream_key(seed)
    out = np.empty((stop - start, n_modes))
    for row, mu in enumerate(range(start, stop)):
        fill_normals(key, mu, out[row])
    return out


@numba.njit(cache=True)
def _nearest_one(train_t, y, l2, dist, gen_min):
    """Nearest training point to one sample y (raw L1 sum or squared L2) and its index.

    train_t is (n_modes, n_images): distances to all N points are accumulated mode by mode,
    which vectorizes over N. gen_min (n_images,) is lowered in place to each training point's
    nearest sample distance.
    """
    n_modes, n_images = train_t.shape
    for i in range(n_images):
        dist[i] = 0.0
    for k in range(n_modes):
        yk = y[k]
        row = train_t[k]
        if l2:
            for i in range(n_images):
                diff = yk - row[i]
                dist[i] += diff * diff
        else:
            for i in range(n_images):
                dist[i] += abs(yk - row[i])
    best = dist[0]
    besti = 0
    for i in range(n_images):
        d = dist[i]
        if d < best:
            best = d
            besti = i
        if d < gen_min[i]:
            gen_min[i] = d
    return best, besti


@numba.njit(cache=True)
def _chunk(train_t, sd, key, start, stop, l2, y, dist, values, nearest, gen_min):
    """Samples start:stop of the model with mode standard deviations sd: nearest per sample."""
    for mu in range(start, stop):
        fill_normals(key, mu, y)
        for k in range(y.shape[0]):
            y[k] *= sd[k]
        values[mu - start], nearest[mu - start] = _nearest_one(train_t, y, l2, dist, gen_min)


@numba.njit(parallel=True, cache=True)
def nearest_of_samples(train_t, samples, l2, chunk):
    """Raw nearest distance and index for explicit samples (n_samples, n_modes).

    The search alone, without the fused sampling; used where the samples come from elsewhere
    and to benchmark the search against plain references on identical samples.
    """
    n = samples.shape[0]
    values = np.empty(n)
    nearest = np.empty(n, dtype=np.int64)
    n_chunks = (n + chunk - 1) // chunk
    for c in numba.prange(n_chunks):
        dist = np.empty(train_t.shape[1])
        gen = np.full(train_t.shape[1], np.inf)
        for j in range(c * chunk, min(n, (c + 1) * chunk)):
            values[j], nearest[j] = _nearest_one(train_t, samples[j], l2, dist, gen)
    return values, nearest


@numba.njit(cache=True)
def finish_distances(values, count, l2, exponent):
    """Turn raw nearest distances into |x - y|^exponent in place."""
    for j in range(count):
        v = values[j]
        if l2:
            v = np.sqrt(v)
        if exponent != 1.0:
            v = v**exponent
        values[j] = v


@numba.njit(cache=True)
def chunk_moments(values, count):
    s = 0.0
    for j in range(count):
        s += values[j]
    m = s / count
    m2 = 0.0
    for j in range(count):
        d = values[j] - m
        m2 += d * d
    return m, m2


@numba.njit(cache=True)
def _summarise_chunk(values, nearest, count, l2, exponent, counts_row):
    """Finish a chunk's distances, count its nearest images; return its (mean, M2)."""
    finish_distances(values, count, l2, exponent)
    for j in range(count):
        counts_row[nearest[j]] += 1
    return chunk_moments(values, count)


@numba.njit(cache=True)
def _summarise_pair(va, na, vb, nb, count, l2, exponent, moments, c, counts_a, counts_b):
    """As :func:`_summarise_chunk` for two models on the same samples, and for a - b:
    ``moments[0|1|2, c]`` (mean, M2) of a, b and a - b; `va` ends as a - b."""
    moments[0, c, 0], moments[0, c, 1] = _summarise_chunk(va, na, count, l2, exponent, counts_a)
    moments[1, c, 0], moments[1, c, 1] = _summarise_chunk(vb, nb, count, l2, exponent, counts_b)
    for j in range(count):
        va[j] -= vb[j]
    moments[2, c, 0], moments[2, c, 1] = chunk_moments(va, count)


@numba.njit(parallel=True, cache=True)
def run_single(train_t, sd, key, n_samples, l2, exponent, chunk, first, last):
    """Per-chunk (count, mean, M2) of the sample nearest distances, Voronoi counts, gen minima.

    Chunk c holds samples ``[c * chunk, min((c + 1) * chunk, n_samples))``; this call runs
    chunks ``first .. last - 1`` (so a caller can show progress between calls; the numbers
    of a chunk do not depend on how the chunks are grouped).
    """
    n_modes, n_images = train_t.shape
    n_chunks = last - first
    means = np.empty(n_chunks)
    m2s = np.empty(n_chunks)
    counts = np.zeros((n_chunks, n_images), dtype=np.int64)
    gen = np.full((n_chunks, n_images), np.inf)
    for c in numba.prange(n_chunks):
        start = (first + c) * chunk
        stop = min(n_samples, start + chunk)
        y = np.empty(n_modes)
        dist = np.empty(n_images)
        values = np.empty(stop - start)
        nearest = np.empty(stop - start, dtype=np.int64)
        _chunk(train_t, sd, key, start, stop, l2, y, dist, values, nearest, gen[c])
        means[c], m2s[c] = _summarise_chunk(values, nearest, stop - start, l2, exponent, counts[c])
    return means, m2s, counts, gen


@numba.njit(parallel=True, cache=True)
def run_paired(train_a, sd_a, train_b, sd_b, key, n_samples, l2, exponent, chunk):
    """As run_single for two models on the same standard normals, plus their difference a - b."""
    n_chunks = (n_samples + chunk - 1) // chunk
    moments = np.empty((3, n_chunks, 2))
    counts_a = np.zeros((n_chunks, train_a.shape[1]), dtype=np.int64)
    counts_b = np.zeros((n_chunks, train_b.shape[1]), dtype=np.int64)
    gen_a = np.full((n_chunks, train_a.shape[1]), np.inf)
    gen_b = np.full((n_chunks, train_b.shape[1]), np.inf)
    for c in numba.prange(n_chunks):
        start = c * chunk
        stop = min(n_samples, start + chunk)
        m = stop - start
        va = np.empty(m)
        vb = np.empty(m)
        na = np.empty(m, dtype=np.int64)
        nb = np.empty(m, dtype=np.int64)
        _chunk(
            train_a,
            sd_a,
            key,
            start,
            stop,
            l2,
            np.empty(train_a.shape[0]),
            np.empty(train_a.shape[1]),
            va,
            na,
            gen_a[c],
        )
        _chunk(
            train_b,
            sd_b,
            key,
            start,
            stop,
            l2,
            np.empty(train_b.shape[0]),
            np.empty(train_b.shape[1]),
            vb,
            nb,
            gen_b[c],
        )
        _summarise_pair(va, na, vb, nb, m, l2, exponent, moments, c, counts_a[c], counts_b[c])
    return moments, counts_a, counts_b, gen_a, gen_b


@numba.njit(cache=True)
def draw_mixture(centre, basis, key, mu, z, y):
    """Sample `mu` of one mixture component into y: ``centre + z @ basis``.

    ``centre`` (n_modes,) and ``basis`` (n_group_modes, n_modes, rows: unit modes times their
    standard deviations) are in joint parameters; ``z`` (n_group_modes,) receives the
    standard normals ``z(key, mu, k)``. The sum is taken in a fixed order (the centre, then
    the modes in turn), so every path that draws through here gets the same bits.
    """
    fill_normals(key, mu, z)
    n_modes = y.shape[0]
    n_basis = z.shape[0]
    for k in range(n_modes):
        y[k] = centre[k]
    j = 0
    while j + 3 < n_basis:  # four modes per pass over y: the additions stay in order
        z0, z1, z2, z3 = z[j], z[j + 1], z[j + 2], z[j + 3]
        r0, r1, r2, r3 = basis[j], basis[j + 1], basis[j + 2], basis[j + 3]
        for k in range(n_modes):
            y[k] = (((y[k] + z0 * r0[k]) + z1 * r1[k]) + z2 * r2[k]) + z3 * r3[k]
        j += 4
    for jj in range(j, n_basis):
        zj = z[jj]
        row = basis[jj]
        for k in range(n_modes):
            y[k] += zj * row[k]


def mixture_spans(group_samples, chunk: int) -> np.ndarray:
    """The chunks of a mixture's samples: rows ``(start, stop, group)``, int64.

    Group g owns samples ``offset_g .. offset_g + M_g - 1`` (``offset_g = sum_{h<g} M_h``),
    cut into chunks of at most `chunk` samples; no chunk mixes groups.
    """
    rows = []
    offset = 0
    for g, m in enumerate(int(v) for v in group_samples):
        for start in range(offset, offset + m, chunk):
            rows.append((start, min(offset + m, start + chunk), g))
        offset += m
    return np.asarray(rows, dtype=np.int64).reshape(-1, 3)


@numba.njit(cache=True)
def _chunk_mixture(train_t, centre, basis, key, start, stop, l2, values, nearest, gen_min):
    """Samples start:stop of one mixture component: nearest training point per sample."""
    z = np.empty(basis.shape[0])
    y = np.empty(train_t.shape[0])
    dist = np.empty(train_t.shape[1])
    for mu in range(start, stop):
        draw_mixture(centre, basis, key, mu, z, y)
        values[mu - start], nearest[mu - start] = _nearest_one(train_t, y, l2, dist, gen_min)


@numba.njit(parallel=True, cache=True)
def run_mixture(train_t, centres, basis_rows, basis_start, spans, key, l2, exponent, first, last):
    """As :func:`run_single` for a mixture, chunk c being ``spans[c] = (start, stop, group)``.

    Group g's basis is ``basis_rows[basis_start[g]:basis_start[g + 1]]`` and its centre
    ``centres[g]``. Runs chunks ``first .. last - 1``; returns per chunk (mean, M2) of the
    finished nearest distances, the nearest counts per training image and the gen minima.
    """
    n_images = train_t.shape[1]
    n_chunks = last - first
    means = np.empty(n_chunks)
    m2s = np.empty(n_chunks)
    counts = np.zeros((n_chunks, n_images), dtype=np.int64)
    gen = np.full((n_chunks, n_images), np.inf)
    for c in numba.prange(n_chunks):
        start, stop, g = spans[first + c, 0], spans[first + c, 1], spans[first + c, 2]
        m = stop - start
        values = np.empty(m)
        nearest = np.empty(m, dtype=np.int64)
        basis = basis_rows[basis_start[g] : basis_start[g + 1]]
        _chunk_mixture(train_t, centres[g], basis, key, start, stop, l2, values, nearest, gen[c])
        means[c], m2s[c] = _summarise_chunk(values, nearest, m, l2, exponent, counts[c])
    return means, m2s, counts, gen


@numba.njit(parallel=True, cache=True)
def run_mixture_paired(
    train_a,
    centres_a,
    rows_a,
    start_a,
    train_b,
    centres_b,
    rows_b,
    start_b,
    spans,
    key,
    l2,
    exponent,
):
    """As :func:`run_paired` for two mixtures on the same spans and standard normals."""
    n_chunks = spans.shape[0]
    moments = np.empty((3, n_chunks, 2))
    counts_a = np.zeros((n_chunks, train_a.shape[1]), dtype=np.int64)
    counts_b = np.zeros((n_chunks, train_b.shape[1]), dtype=np.int64)
    gen_a = np.full((n_chunks, train_a.shape[1]), np.inf)
    gen_b = np.full((n_chunks, train_b.shape[1]), np.inf)
    for c in numba.prange(n_chunks):
        start, stop, g = spans[c, 0], spans[c, 1], spans[c, 2]
        m = stop - start
        va = np.empty(m)
        vb = np.empty(m)
        na = np.empty(m, dtype=np.int64)
        nb = np.empty(m, dtype=np.int64)
        basis_a = rows_a[start_a[g] : start_a[g + 1]]
        basis_b = rows_b[start_b[g] : start_b[g + 1]]
        _chunk_mixture(train_a, centres_a[g], basis_a, key, start, stop, l2, va, na, gen_a[c])
        _chunk_mixture(train_b, centres_b[g], basis_b, key, start, stop, l2, vb, nb, gen_b[c])
        _summarise_pair(va, na, vb, nb, m, l2, exponent, moments, c, counts_a[c], counts_b[c])
    return moments, counts_a, counts_b, gen_a, gen_b


def combine_moments(means: np.ndarray, m2s: np.ndarray, n_samples: int, chunk: int):
    """Combine per-chunk means and M2 (Chan et al.) into the overall mean and M2."""
    sizes = np.full(means.shape[0], chunk, dtype=np.float64)
    sizes[-1] = n_samples - chunk * (means.shape[0] - 1)
    mean = float(np.sum(sizes * means) / n_samples)
    m2 = float(np.sum(m2s) + np.sum(sizes * (means - mean) ** 2))
    return mean, m2
