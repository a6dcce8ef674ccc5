"""Specificity speed: N = 36 images, M = 500,000 samples, L1, 35 modes (issue 2).

References in the same run, on the same samples:
* naive: numpy standard normals, then a chunked numpy broadcast |y - x| sum and a min;
* cdist: chunked ``scipy.spatial.distance.cdist(..., "cityblock")`` and a min.
Ours: the numba search alone on the same explicit samples, and the whole ``nr.specificity``
call (sampling fused with the search).
"""

from __future__ import annotations

import time

import numpy as np
from scipy.spatial.distance import cdist

import itk_nrreval as nr
from itk_nrreval.measures import _search

N, M, SHAPE = 36, 500_000, (64, 64)
CHUNK = 8192


def _best_of(fn, repeats=3):
    best, out = np.inf, None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def naive_search(train, samples):
    out = np.empty(samples.shape[0])
    for s in range(0, samples.shape[0], CHUNK):
        y = samples[s : s + CHUNK]
        out[s : s + CHUNK] = np.abs(y[:, None, :] - train[None]).sum(axis=2).min(axis=1)
    return out


def cdist_search(train, samples):
    out = np.empty(samples.shape[0])
    for s in range(0, samples.shape[0], CHUNK):
        out[s : s + CHUNK] = cdist(samples[s : s + CHUNK], train, "cityblock").min(axis=1)
    return out


def main() -> dict:
    images = np.random.default_rng(0).normal(size=(N, *SHAPE))
    model = nr.TextureModel.from_images(images)
    train = model.training_params
    sd = np.sqrt(model.mode_variances)
    train_t = np.ascontiguousarray(train.T)
    nr.specificity(model, n_samples=1000)  # compile outside the timings
    _search.sampling.nearest_of_samples(train_t, train[:10].copy(), False, 1024)

    t_draw, samples = _best_of(lambda: np.random.default_rng(1).standard_normal((M, 35)) * sd)
    t_naive, ref = _best_of(lambda: naive_search(train, samples), repeats=1)
    t_cdist, ref_cdist = _best_of(lambda: cdist_search(train, samples))
    t_ours, (ours, _) = _best_of(
        lambda: _search.sampling.nearest_of_samples(train_t, samples, False, 4096)
    )
    t_whole, result = _best_of(lambda: nr.specificity(model, n_samples=M, seed=1))
    max_rel = float(np.max(np.abs(ours - ref) / ref))
    numbers = {
        "n_images": N,
        "n_samples": M,
        "n_modes": model.n_modes,
        "seconds": {
            "numpy_draw": t_draw,
            "naive_search": t_naive,
            "cdist_search": t_cdist,
            "our_search": t_ours,
            "naive_whole": t_draw + t_naive,
            "our_whole": t_whole,
        },
        "search_vs_naive": t_naive / t_ours,
        "search_vs_cdist": t_cdist / t_ours,
        "whole_vs_naive_whole": (t_draw + t_naive) / t_whole,
        "max_relative_difference_search": max_rel,
        "max_relative_difference_cdist": float(np.max(np.abs(ref_cdist - ref) / ref)),
        "specificity": result.value,
    }
    print(f"N = {N}, M = {M:,}, L1, {model.n_modes} modes")
    print("| step | reference s | ours s | ratio |")
    print("|---|---|---|---|")
    print(f"| search vs naive broadcast | {t_naive:.3f} | {t_ours:.3f} | {t_naive / t_ours:.1f}x |")
    print(f"| search vs chunked cdist | {t_cdist:.3f} | {t_ours:.3f} | {t_cdist / t_ours:.1f}x |")
    print(
        f"| whole call vs numpy draw + naive | {t_draw + t_naive:.3f} | {t_whole:.3f} | "
        f"{(t_draw + t_naive) / t_whole:.1f}x |"
    )
    print(f"\nsame samples, max relative difference ours vs naive: {max_rel:.1e}")
    return numbers


if __name__ == "__main__":
    main()
