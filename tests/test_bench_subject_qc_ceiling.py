"""The recall a Spearman implies (benchmarks/bench_subject_qc_ceiling.py) against a
simulation that reads it off drawn subjects, and its logistic fit against known weights."""

import numpy as np
import pytest
from _benchmarks import benchmark_module
from scipy.stats import spearmanr

ceiling = benchmark_module("bench_subject_qc_ceiling")


@pytest.mark.parametrize(("rho", "failed", "alarms"), [(0.8, 0.1, 0.05), (0.5, 0.2, 0.03)])
def test_implied_recall_matches_drawn_subjects(rho, failed, alarms):
    rng = np.random.default_rng(0)
    r = 2.0 * np.sin(np.pi * rho / 6.0)
    n = 400_000
    error = rng.standard_normal(n)
    score = r * error + np.sqrt(1.0 - r * r) * rng.standard_normal(n)
    assert spearmanr(score[:20_000], error[:20_000]).statistic == pytest.approx(rho, abs=0.02)
    bad = error > np.quantile(error, 1.0 - failed)
    flagged = score > np.quantile(score[~bad], 1.0 - alarms)
    assert flagged[~bad].mean() == pytest.approx(alarms, abs=1e-3)
    got = ceiling.implied_recall(rho, failed_fraction=failed, false_alarms=alarms)
    assert got == pytest.approx(flagged[bad].mean(), abs=0.01)


def test_a_score_unrelated_to_the_error_finds_the_failed_as_often_as_the_others():
    assert ceiling.implied_recall(0.0, failed_fraction=0.1, false_alarms=0.05) == pytest.approx(
        0.05, abs=1e-6
    )
    rising = [
        ceiling.implied_recall(r, failed_fraction=0.1, false_alarms=0.05) for r in (0.3, 0.6, 0.9)
    ]
    assert rising == sorted(rising) and rising[-1] < 1.0


def test_logistic_fit_recovers_the_weights_it_was_drawn_with():
    rng = np.random.default_rng(1)
    x = rng.standard_normal((20_000, 3))
    w = np.array([1.5, -0.5, 0.0])
    failed = rng.random(20_000) < 1.0 / (1.0 + np.exp(-(x @ w - 2.0)))
    fitted = ceiling.fit_logistic(x, failed, ridge=0.0)
    np.testing.assert_allclose(fitted, [*w, -2.0], atol=0.1)


def test_found_among_worst_counts_per_registration():
    score = np.array([5.0, 1.0, 3.0, 9.0, 0.0, 2.0])
    failed = np.array([False, True, True, False, True, False])
    names = np.array(["a", "a", "a", "b", "b", "b"])
    # a: the worst two are rows 0 and 2 (one failed); b: rows 3 and 5 (none)
    assert ceiling.found_among_worst(score, failed, names, 2) == (1, 3)
    assert ceiling.found_among_worst(score, failed, names, 3) == (3, 3)


@pytest.mark.parametrize("rho", [1.0, -1.0, float("nan")])
def test_implied_recall_refuses_a_perfect_or_undefined_spearman(rho):
    with pytest.raises(ValueError, match="spearman must be in"):
        ceiling.implied_recall(rho, failed_fraction=0.1, false_alarms=0.05)
