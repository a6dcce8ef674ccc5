"""The subject-QC benchmark's sampling floor (benchmarks/bench_subject_qc_genuine.py,
``least_spearman_by_chance``) against a brute-force reference: the same draws, each
registration's Spearman by scipy."""

import math

import numpy as np
from _benchmarks import benchmark_module
from scipy.stats import spearmanr

least_spearman_by_chance = benchmark_module("bench_subject_qc_genuine").least_spearman_by_chance


def _brute_force(subjects, rho, seed, draws):
    rng = np.random.default_rng(seed)
    r = 2.0 * math.sin(math.pi * rho / 6.0)
    per_registration = []
    for n in subjects:  # the same draws, in the same order
        x = rng.standard_normal((draws, n))
        y = r * x + math.sqrt(1.0 - r * r) * rng.standard_normal((draws, n))
        per_registration.append([spearmanr(x[d], y[d]).statistic for d in range(draws)])
    return float(np.median(np.min(per_registration, axis=0)))


def test_least_spearman_by_chance_matches_scipy_on_the_same_draws():
    for subjects, rho, seed in (([11, 11, 15], 0.82, 0), ([9, 35], 0.5, 3), ([6] * 4, -0.2, 1)):
        got = least_spearman_by_chance(subjects, rho, seed=seed, draws=60)
        assert math.isclose(got, _brute_force(subjects, rho, seed, 60), abs_tol=1e-12)


def test_least_spearman_by_chance_properties():
    # a perfect score is ranked perfectly under every registration
    assert least_spearman_by_chance([11] * 5, 1.0, draws=50) == 1.0
    # more registrations, or fewer subjects each, only lower the least (same seed)
    few = least_spearman_by_chance([11] * 5, 0.85, draws=400)
    many = least_spearman_by_chance([11] * 34, 0.85, draws=400)
    bigger = least_spearman_by_chance([36] * 34, 0.85, draws=400)
    assert many < few < 0.85
    assert many < bigger
    # the population Spearman is recovered where there is one registration of many subjects
    assert abs(least_spearman_by_chance([2000], 0.6, draws=20) - 0.6) < 0.03
