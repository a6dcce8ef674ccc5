"""Generalized overlap: the one-pass per-label table against the naive all-pairs loop.

First the common crisp case, ``generalized_overlap(labels, weighting="inverse_volume")``
(which computes only pair counts and volumes: no gradients, no target overlap), on
N = 36 random label maps of 64^3 voxels with 18 labels (0 = background, not evaluated) and
on the structured 96^3 maps below, side by side with two references: plain numpy counting
(per label ``c = (labels == l).sum(0)``, then the sum of C(c, 2); given the label list) and
the naive loop over the 630 pairs. Medians of several repeats, after a warm-up call that
compiles the numba kernels; the three results must agree to 1e-12.

Then the full table, N = 36 label images of 96^3 voxels with 18 labels, crisp (int16 label
maps) and fuzzy (float32 memberships: 36 x 18 x 96^3 x 4 bytes = 2.3 GB; float64 would be
4.6 GB), the latter both as partial-volume memberships (resampled one-hot maps) and dense
softmax. Both sides produce everything the five weightings need: pair sums of minima and
maxima per label, volumes, and the complexity weights (gradient magnitudes). The naive side
loops over the 630 pairs and the labels with numpy, and takes gradients with
``numpy.gradient``.
"""

from __future__ import annotations

import os
import time

import numba
import numpy as np
from scipy import ndimage

from itk_nrreval.measures.overlap import WEIGHTINGS, generalized_overlap, overlap_table

N_IMAGES = 36
N_LABELS = 18
SIZE = 96
SEED = 20261122
RANDOM_SIZE = 64  # the random crisp inverse-volume case


def _scores(rng: np.random.Generator) -> list[np.ndarray]:
    """N label-score fields (18, 96, 96, 96); the argmax is the label map.

    A noisy Voronoi partition: label l scores minus the distance to its seed (voxels) plus a
    smooth random field (amplitude ~ 6 voxels), so structures are blobs ~ 35 voxels across
    with irregular boundaries. Each image jitters the seeds (+-3 voxels) and shifts the
    noise, as a misregistered group would.
    """
    seeds = rng.uniform(0.1 * SIZE, 0.9 * SIZE, size=(N_LABELS, 3))
    low = rng.normal(scale=6.0, size=(N_LABELS, 8, 8, 8))
    noise = ndimage.zoom(low, (1, SIZE / 8, SIZE / 8, SIZE / 8), order=1).astype(np.float32)
    grid = np.arange(SIZE, dtype=np.float32)
    out = []
    for _ in range(N_IMAGES):
        jittered = seeds + rng.uniform(-3, 3, size=seeds.shape)
        shift = tuple(int(s) for s in rng.integers(-2, 3, size=3))
        f = np.roll(noise, shift, axis=(1, 2, 3))
        for lab, (z, y, x) in enumerate(jittered.astype(np.float32)):
            d2 = (
                (grid[:, None, None] - z) ** 2
                + (grid[None, :, None] - y) ** 2
                + (grid[None, None, :] - x) ** 2
            )
            f[lab] -= np.sqrt(d2)
        out.append(f)
    return out


def _crisp(scores) -> np.ndarray:
    return np.stack([f.argmax(axis=0).astype(np.int16) for f in scores])


def _partial_volume(crisp: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Fuzzy memberships as resampling makes them: each one-hot label map shifted by a random
    sub-voxel offset with trilinear interpolation (float32; exact 0 and 1 away from edges)."""
    out = np.zeros((N_IMAGES, N_LABELS, SIZE, SIZE, SIZE), np.float32)
    for i in range(N_IMAGES):
        t = rng.uniform(0, 1, size=3).astype(np.float32)
        for corner in np.ndindex(2, 2, 2):
            w = np.prod([t[d] if c else 1 - t[d] for d, c in enumerate(corner)])
            shifted = np.roll(crisp[i], corner, axis=(0, 1, 2))
            for lab in range(N_LABELS):
                out[i, lab] += w * (shifted == lab)
    return np.clip(out, 0.0, 1.0)


def _softmax(scores, beta: float = 1.0) -> np.ndarray:
    """Dense fuzzy memberships (no exact zeros): a softmax of the scores (float32)."""
    out = np.empty((N_IMAGES, N_LABELS, SIZE, SIZE, SIZE), np.float32)
    for i, f in enumerate(scores):
        e = np.exp(beta * (f - f.max(axis=0)))
        out[i] = e / e.sum(axis=0)
    return np.clip(out, 0.0, 1.0)


def _naive(memberships_of, n_images: int, n_labels: int, crisp: bool) -> dict:
    """All pairs, label by label, with plain numpy; gradients with numpy.gradient.

    `memberships_of(i)` gives image i's (n_labels, *spatial) memberships (bool for crisp).
    """
    p = np.zeros(n_labels)
    q = np.zeros(n_labels)
    t0 = time.perf_counter()
    cache = [memberships_of(i) for i in range(n_images)]
    for i in range(n_images):
        for j in range(i + 1, n_images):
            a, b = cache[i], cache[j]
            for lab in range(n_labels):
                if crisp:
                    p[lab] += np.count_nonzero(a[lab] & b[lab])
                    q[lab] += np.count_nonzero(a[lab] | b[lab])
                else:
                    p[lab] += np.minimum(a[lab], b[lab]).sum(dtype=np.float64)
                    q[lab] += np.maximum(a[lab], b[lab]).sum(dtype=np.float64)
    t_pairs = time.perf_counter() - t0
    vol = np.zeros((n_images, n_labels))
    grad = np.zeros((n_images, n_labels))
    for i in range(n_images):
        for lab in range(n_labels):
            m = cache[i][lab].astype(np.float64)
            vol[i, lab] = m.sum()
            grad[i, lab] = np.sqrt(sum(g**2 for g in np.gradient(m))).sum()
    complexity = np.array(
        [np.mean(grad[vol[:, k] > 0, k] / vol[vol[:, k] > 0, k]) for k in range(n_labels)]
    )
    volume = vol.mean(axis=0)
    alphas = {
        "volume": np.ones(n_labels),
        "inverse_volume": 1 / volume,
        "inverse_volume_squared": 1 / volume**2,
        "complexity": complexity,
        "inverse_volume_complexity": complexity / volume,
    }
    return {
        "time": time.perf_counter() - t0,
        "time_pairs": t_pairs,
        "pair_min": p,
        "pair_max": q,
        "generalized": {w: float((a @ p) / (a @ q)) for w, a in alphas.items()},
    }


def _median_time(fn, repeats: int) -> tuple[float, object]:
    """Median wall time of `repeats` calls of `fn` (seconds), and its last result."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), result


def _plain_inverse_volume(labels: np.ndarray, values) -> float:
    """Plain numpy counting: per label the number c of images carrying it at each voxel."""
    n = labels.shape[0]
    p, q, vol = [], [], []
    for lab in values:
        c = (labels == lab).sum(axis=0)
        pair_min = int((c * (c - 1) // 2).sum())
        total = int(c.sum())
        p.append(pair_min)
        q.append((n - 1) * total - pair_min)  # the pair sums of a_i + a_j are min + max
        vol.append(total / n)
    alpha = 1.0 / np.asarray(vol)
    return float(alpha @ np.asarray(p, float) / (alpha @ np.asarray(q, float)))


def _naive_inverse_volume(labels: np.ndarray, values) -> float:
    """The naive loop over every pair of images and every label (numpy within a pair)."""
    n = labels.shape[0]
    onehot = [np.stack([labels[i] == lab for lab in values]) for i in range(n)]
    p = np.zeros(len(values))
    q = np.zeros(len(values))
    for i in range(n):
        for j in range(i + 1, n):
            a, b = onehot[i], onehot[j]
            for k in range(len(values)):
                p[k] += np.count_nonzero(a[k] & b[k])
                q[k] += np.count_nonzero(a[k] | b[k])
    vol = np.array([sum(np.count_nonzero(m[k]) for m in onehot) for k in range(len(values))])
    alpha = n / vol
    return float(alpha @ p / (alpha @ q))


def _compare_inverse_volume(name: str, labels: np.ndarray, repeats: tuple[int, int, int]) -> dict:
    """Time ours, plain numpy counting and the naive all-pairs loop (median of repeats)."""
    values = [v for v in range(N_LABELS) if v != 0]
    generalized_overlap(labels[:, :4], weighting="inverse_volume")  # compile outside timing
    t_ours, ours = _median_time(
        lambda: generalized_overlap(labels, weighting="inverse_volume"), repeats[0]
    )
    t_plain, plain = _median_time(lambda: _plain_inverse_volume(labels, values), repeats[1])
    t_naive, naive = _median_time(lambda: _naive_inverse_volume(labels, values), repeats[2])
    rel = max(abs(ours / plain - 1), abs(ours / naive - 1))
    if not rel <= 1e-12:
        raise AssertionError(f"{name}: results differ: {ours!r}, {plain!r}, {naive!r}")
    return {
        "case": name,
        "ours_s": t_ours,
        "plain_numpy_s": t_plain,
        "naive_pairs_s": t_naive,
        "ratio_plain": t_plain / t_ours,
        "ratio_naive": t_naive / t_ours,
        "repeats": list(repeats),
        "max_rel_diff": rel,
        "overlap": ours,
    }


def _compare(name: str, data, naive_input, crisp: bool) -> dict:
    overlap_table(data[..., :8, :, :], include_background=True)  # compile outside the timing
    for _ in range(2):  # the naive side reads the data once before its clock starts, too
        naive_input(0)
    t0 = time.perf_counter()
    table = overlap_table(data, include_background=True)
    ours = {w: table.generalized(w) for w in WEIGHTINGS}
    t_ours = time.perf_counter() - t0
    ref = _naive(naive_input, N_IMAGES, N_LABELS, crisp)
    rel = max(
        float(np.max(np.abs(table.pair_min / ref["pair_min"] - 1))),
        float(np.max(np.abs(table.pair_max / ref["pair_max"] - 1))),
        max(abs(ours[w] / ref["generalized"][w] - 1) for w in WEIGHTINGS),
    )
    identical = bool(
        np.array_equal(table.pair_min, ref["pair_min"])
        and np.array_equal(table.pair_max, ref["pair_max"])
    )
    return {
        "case": name,
        "ours_s": t_ours,
        "naive_s": ref["time"],
        "naive_pairs_only_s": ref["time_pairs"],
        "ratio": ref["time"] / t_ours,
        "ratio_vs_pairs_only": ref["time_pairs"] / t_ours,
        "pair_sums_identical": identical,
        "max_rel_diff": rel,
        "overlap": ours,
    }


def main() -> dict:
    load_before = os.getloadavg()[0]
    rng = np.random.default_rng(SEED)
    random_labels = np.random.default_rng(SEED + 1).integers(
        0, N_LABELS, size=(N_IMAGES,) + (RANDOM_SIZE,) * 3
    )
    inverse_volume = [
        _compare_inverse_volume(
            f"random int16, {RANDOM_SIZE}^3", random_labels.astype(np.int16), (15, 7, 3)
        )
    ]
    del random_labels
    scores = _scores(rng)
    crisp = _crisp(scores)
    inverse_volume.append(
        _compare_inverse_volume(f"noisy Voronoi int16, {SIZE}^3", crisp, (9, 5, 1))
    )
    print(
        f"generalized_overlap(labels, weighting='inverse_volume'), crisp, N = {N_IMAGES}, "
        f"{N_LABELS} labels (background not evaluated); {numba.get_num_threads()} numba "
        f"threads, load average {load_before:.2f} at the start (another job may share the "
        "cores). Median of (ours, plain, naive) repeats as listed.\n"
    )
    print(
        "| case | ours (s) | plain numpy counting (s) | ratio | naive all pairs (s) | ratio "
        "| repeats | max rel. diff |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for r in inverse_volume:
        print(
            f"| {r['case']} | {r['ours_s']:.4f} | {r['plain_numpy_s']:.3f} "
            f"| {r['ratio_plain']:.1f}x | {r['naive_pairs_s']:.2f} | {r['ratio_naive']:.0f}x "
            f"| {'/'.join(str(k) for k in r['repeats'])} | {r['max_rel_diff']:.1e} |"
        )
    print(flush=True)

    results = [
        _compare(
            "crisp int16",
            crisp,
            lambda i, c=crisp: np.stack([c[i] == lab for lab in range(N_LABELS)]),
            crisp=True,
        )
    ]
    fuzzy = _partial_volume(crisp, rng)
    del crisp
    results.append(
        _compare("fuzzy float32, partial volume", fuzzy, lambda i, f=fuzzy: f[i], crisp=False)
    )
    fuzzy = _softmax(scores)
    del scores
    results.append(
        _compare("fuzzy float32, dense softmax", fuzzy, lambda i, f=fuzzy: f[i], crisp=False)
    )
    del fuzzy

    print(
        f"N = {N_IMAGES} images, {N_LABELS} labels, {SIZE}^3 voxels (noisy Voronoi label maps); "
        "fuzzy memberships in float32 (float64 would need 4.6 GB): partial-volume memberships "
        "as resampling makes them (exact 0 and 1 away from boundaries), and dense softmax "
        "memberships (no zeros: the worst case). Both sides compute pair sums, volumes and "
        "complexity for all five weightings.\n"
    )
    print("| case | ours (s) | naive (s) | ratio | naive pairs only (s) | ratio | max rel. diff |")
    print("|---|---|---|---|---|---|---|")
    for r in results:
        same = " (pair sums identical)" if r["pair_sums_identical"] else ""
        print(
            f"| {r['case']} | {r['ours_s']:.2f} | {r['naive_s']:.1f} | {r['ratio']:.1f}x "
            f"| {r['naive_pairs_only_s']:.1f} | {r['ratio_vs_pairs_only']:.1f}x "
            f"| {r['max_rel_diff']:.1e}{same} |"
        )
    print()
    print("| weighting | " + " | ".join(r["case"] for r in results) + " |")
    print("|---|" + "---|" * len(results))
    for w in WEIGHTINGS:
        print(f"| {w} | " + " | ".join(f"{r['overlap'][w]:.6f}" for r in results) + " |")
    return {
        "n_images": N_IMAGES,
        "n_labels": N_LABELS,
        "size": SIZE,
        "random_size": RANDOM_SIZE,
        "numba_threads": numba.get_num_threads(),
        "load_average_at_start": load_before,
        "inverse_volume_crisp": inverse_volume,
        "fuzzy_dtype": "float32",
        "results": results,
    }


if __name__ == "__main__":
    main()
