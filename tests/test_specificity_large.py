"""Specificity at large N: the blocked L1 / GEMM L2 / torch paths against the per-sample one."""

from __future__ import annotations

import importlib
import importlib.util
import math

import numba
import numpy as np
import pytest
from scipy.spatial.distance import cdist

import itk_nrreval as nr
from itk_nrreval.measures import _search

spec_mod = importlib.import_module(
    "itk_nrreval.measures.specificity"
)  # the module, not the function

ALWAYS, NEVER = 0, 1 << 60


@pytest.fixture(scope="module")
def model_300():
    images = np.random.default_rng(11).normal(size=(300, 24, 24))
    return nr.TextureModel.from_images(images)


def _params_model(params: np.ndarray, variances: np.ndarray) -> nr.TextureModel:
    return nr.TextureModel(
        training_params=params, mode_variances=variances, mean=np.zeros(1), mask=None, geometry=None
    )


def _measures(model, monkeypatch, distance, blocked: bool, **kw):
    monkeypatch.setitem(spec_mod._BLOCKED_MIN_IMAGES, distance, ALWAYS if blocked else NEVER)
    kw.setdefault("backend", "cpu")
    return nr.texture_measures(model, distance=distance, **kw)


def _assert_same(a, b, rtol=1e-10, counts=True):
    (sa, ga), (sb, gb) = a, b
    assert sa.value == pytest.approx(sb.value, rel=rtol)
    assert sa.stderr == pytest.approx(sb.stderr, rel=rtol)
    if counts:
        np.testing.assert_array_equal(sa.nearest_counts, sb.nearest_counts)
    np.testing.assert_allclose(ga.nearest_distances, gb.nearest_distances, rtol=rtol)
    assert ga.value == pytest.approx(gb.value, rel=rtol)
    assert ga.stderr == pytest.approx(gb.stderr, rel=rtol)


@pytest.mark.parametrize("distance", ["l1", "l2"])
@pytest.mark.parametrize("exponent", [1.0, 2.0])
def test_blocked_equals_per_sample(model_300, monkeypatch, distance, exponent):
    # 4099 samples: a full chunk and a chunk of 3 (an odd L1 task and a short GEMM block).
    kw = dict(n_samples=4099, exponent=exponent, seed=5)
    old = _measures(model_300, monkeypatch, distance, False, **kw)
    new = _measures(model_300, monkeypatch, distance, True, **kw)
    _assert_same(new, old)
    assert int(new[0].nearest_counts.sum()) == 4099


@pytest.mark.parametrize("distance", ["l1", "l2"])
def test_blocked_is_bit_identical_to_run_single(model_300, distance):
    train = model_300.training_params
    sd = np.sqrt(model_300.mode_variances)
    key = _search.sampling.stream_key(2)
    l2 = distance == "l2"
    old = _search.sampling.run_single(
        np.ascontiguousarray(train.T), sd, key, 1000, l2, 1.0, 256, 0, 4
    )
    new = _search.blocked.run_single_blocked(train, sd, key, 1000, l2, 1.0, 256)
    for a, b in zip(old, new, strict=True):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("distance", ["l1", "l2"])
def test_blocked_independent_of_chunks_blocks_and_threads(model_300, monkeypatch, distance):
    train = model_300.training_params
    sd = np.sqrt(model_300.mode_variances)
    key = _search.sampling.stream_key(9)
    l2 = distance == "l2"
    n = 1200

    def combined(chunk):
        means, m2s, counts, gen = _search.blocked.run_single_blocked(
            train, sd, key, n, l2, 1.0, chunk
        )
        return _search.sampling.combine_moments(means, m2s, n, chunk), counts.sum(0), gen.min(0)

    (mean, m2), counts, gen = combined(4096)
    for chunk in (500, 333):
        (mean_c, m2_c), counts_c, gen_c = combined(chunk)
        assert mean_c == pytest.approx(mean, rel=1e-12)
        assert m2_c == pytest.approx(m2, rel=1e-10)
        np.testing.assert_array_equal(counts_c, counts)
        np.testing.assert_array_equal(gen_c, gen)
    monkeypatch.setattr(_search.blocked, "L2_BLOCK_RANGE", (37, 37))  # GEMM blocks of 37 samples
    (mean_b, m2_b), counts_b, gen_b = combined(4096)
    assert (mean_b, m2_b) == (mean, m2)
    np.testing.assert_array_equal(counts_b, counts)
    np.testing.assert_array_equal(gen_b, gen)
    threads = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        (mean_1, m2_1), counts_1, gen_1 = combined(4096)
    finally:
        numba.set_num_threads(threads)
    assert (mean_1, m2_1) == (mean, m2)
    np.testing.assert_array_equal(counts_1, counts)
    np.testing.assert_array_equal(gen_1, gen)


@pytest.mark.parametrize("distance", ["l1", "l2"])
@pytest.mark.parametrize("exponent", [1.0, 0.5])
def test_blocked_against_brute_force(monkeypatch, distance, exponent):
    rng = np.random.default_rng(4)
    model = nr.TextureModel.from_images(rng.normal(size=(40, 12, 12)))
    m, seed = 3000, 8
    spec, gen = _measures(
        model, monkeypatch, distance, True, n_samples=m, exponent=exponent, seed=seed
    )
    samples = _search.sampling.standard_normals(seed, 0, m, model.n_modes) * np.sqrt(
        model.mode_variances
    )
    d = cdist(samples, model.training_params, "cityblock" if distance == "l1" else "euclidean")
    per_sample = d.min(axis=1) ** exponent
    assert spec.value == pytest.approx(per_sample.mean(), rel=1e-10)
    assert spec.stderr == pytest.approx(per_sample.std() / math.sqrt(m - 1), rel=1e-8)
    np.testing.assert_array_equal(spec.nearest_counts, np.bincount(d.argmin(axis=1), minlength=40))
    np.testing.assert_allclose(gen.nearest_distances, d.min(axis=0) ** exponent, rtol=1e-10)


@pytest.mark.parametrize("distance", ["l1", "l2"])
def test_ties_and_cancellation_match_per_sample(monkeypatch, distance):
    # Far from the origin (|y|^2 - 2 y.x + |x|^2 loses ~8 digits) with duplicated training
    # points: the GEMM candidates are re-summed exactly, and ties go to the lower index.
    rng = np.random.default_rng(6)
    base = rng.normal(size=(60, 20))
    params = np.concatenate([base, base[:10]]) + 1e4
    model = _params_model(params, np.linspace(2.0, 0.5, 20))
    kw = dict(n_samples=2000, seed=1)
    old = _measures(model, monkeypatch, distance, False, **kw)
    new = _measures(model, monkeypatch, distance, True, **kw)
    _assert_same(new, old, rtol=0)
    assert not new[0].nearest_counts[60:].any()  # duplicates never win a tie


@pytest.mark.parametrize("distance", ["l1", "l2"])
def test_compare_specificity_blocked_equals_per_sample(model_300, monkeypatch, distance):
    other = _params_model(model_300.training_params * 1.05 + 0.01, model_300.mode_variances * 1.1)
    kw = dict(n_samples=1500, distance=distance, seed=3)
    monkeypatch.setitem(spec_mod._BLOCKED_MIN_IMAGES, distance, NEVER)
    old = nr.compare_specificity(model_300, other, **kw)
    monkeypatch.setitem(spec_mod._BLOCKED_MIN_IMAGES, distance, ALWAYS)
    new = nr.compare_specificity(model_300, other, **kw)
    assert new.difference == pytest.approx(old.difference, rel=1e-10)
    assert new.difference_stderr == pytest.approx(old.difference_stderr, rel=1e-10)
    for a, b in ((new.a, old.a), (new.b, old.b)):
        assert a.value == pytest.approx(b.value, rel=1e-10)
        np.testing.assert_array_equal(a.nearest_counts, b.nearest_counts)


@pytest.mark.parametrize("distance", ["l1", "l2"])
def test_torch_backend_equals_cpu(model_300, monkeypatch, distance):
    pytest.importorskip("torch")
    kw = dict(n_samples=1200, exponent=1.0, seed=5)
    cpu = _measures(model_300, monkeypatch, distance, False, **kw)
    gpu = _measures(model_300, monkeypatch, distance, False, backend="torch", **kw)
    _assert_same(gpu, cpu)


def test_torch_backend_without_torch_is_a_clear_error(model_300, monkeypatch):
    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == "torch" else real(name, *a)
    )
    with pytest.raises(ValueError, match=r"backend='torch' needs PyTorch.*\[gpu\]"):
        nr.specificity(model_300, n_samples=100, backend="torch")
    # "auto" falls back to the CPU without torch.
    assert nr.specificity(model_300, n_samples=100, backend="auto").n_samples == 100


def test_unknown_backend_is_rejected(model_300):
    with pytest.raises(ValueError, match=r"backend must be one of .*'gpu'"):
        nr.generalization(model_300, n_samples=100, backend="gpu")
