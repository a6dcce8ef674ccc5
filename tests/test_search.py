"""The nearest-training search behind one selector: every backend, the same numbers.

References: brute-force distances (scipy's cdist) from the package's documented standard
normals, and each backend against the others to the tolerance the package promises (the
blocked search: bit-identical to the per-sample one; torch: equal to rounding).
"""

from __future__ import annotations

import importlib.util
import math

import numpy as np
import pytest
from scipy.spatial.distance import cdist

import itk_nrreval as nr
from itk_nrreval.measures import _search
from itk_nrreval.measures.model import MixtureModel

HAS_TORCH = importlib.util.find_spec("torch") is not None
NEVER, ALWAYS = 1 << 60, 0
GROUPS = ["a", "b", "a", "b", "a", "b", "b", "a", "b", "a"]


def _public(images, monkeypatch, distance, search, **kw):
    """texture_measures through the public API, on the named search."""
    if search == "torch":
        return nr.texture_measures(images, distance=distance, backend="torch", **kw)
    threshold = ALWAYS if search == "blocked" else NEVER
    monkeypatch.setitem(_search.BLOCKED_MIN_IMAGES, distance, threshold)
    return nr.texture_measures(images, distance=distance, backend="cpu", **kw)


def _searches():
    return ["per-sample", "blocked", *(["torch"] if HAS_TORCH else [])]


@pytest.mark.parametrize("groups", [None, GROUPS], ids=["gaussian", "mixture"])
@pytest.mark.parametrize("distance", ["l1", "l2"])
def test_every_backend_gives_the_same_specificity(small_images, monkeypatch, distance, groups):
    # 4099 samples: a full chunk and a short one (for the mixture, a chunk per group too).
    kw = dict(n_samples=4099, exponent=0.5, seed=6, groups=groups)
    results = {s: _public(small_images, monkeypatch, distance, s, **kw) for s in _searches()}
    (spec, gen) = results["per-sample"]
    if groups is None:  # an independent reference for the single Gaussian
        model = nr.TextureModel.from_images(small_images)
        z = _search.sampling.standard_normals(6, 0, 4099, model.n_modes)
        d = cdist(
            z * np.sqrt(model.mode_variances),
            model.training_params,
            "cityblock" if distance == "l1" else "euclidean",
        )
        per_sample = d.min(axis=1) ** 0.5
        assert spec.value == pytest.approx(per_sample.mean(), rel=1e-10)
        assert spec.stderr == pytest.approx(per_sample.std() / math.sqrt(4098), rel=1e-8)
        np.testing.assert_array_equal(spec.nearest_counts, np.bincount(d.argmin(1), minlength=10))
        np.testing.assert_allclose(gen.nearest_distances, d.min(axis=0) ** 0.5, rtol=1e-10)
    blocked = results["blocked"]
    assert blocked[0].to_dict() == spec.to_dict()  # bit-identical, as documented
    assert blocked[1].to_dict() == gen.to_dict()
    if HAS_TORCH:
        t_spec, t_gen = results["torch"]
        assert t_spec.value == pytest.approx(spec.value, rel=1e-10)
        assert t_spec.stderr == pytest.approx(spec.stderr, rel=1e-10)
        np.testing.assert_array_equal(t_spec.nearest_counts, spec.nearest_counts)
        np.testing.assert_allclose(t_gen.nearest_distances, gen.nearest_distances, rtol=1e-10)


@pytest.mark.parametrize("groups", [None, GROUPS], ids=["gaussian", "mixture"])
def test_a_pair_on_every_backend_is_the_public_comparison(small_images, groups):
    # A paired run is a batch of two models on one sample stream: on every backend, the
    # same per-chunk numbers as compare_specificity (which runs on the CPU).
    other = small_images * 1.3 + 0.2 * np.random.default_rng(2).normal(size=small_images.shape)
    kw = dict(n_samples=5000, distance="l1", seed=4, groups=groups)
    public = nr.compare_specificity(small_images, other, **kw)
    models = [nr.TextureModel.from_images(x) for x in (small_images, other)]
    if groups is not None:
        models = [MixtureModel.from_model(m, groups) for m in models]
    split = public.a.mixture.n_samples if groups is not None else [5000]
    for backend in _searches():
        found = _search.search(
            models, samples_per_group=split, seed=4, distance="l1", exponent=1.0, backend=backend
        )
        assert len(found.models) == 2 and found.difference.shape == (found.spans.shape[0], 2)
        for stats, result in zip(found.models, (public.a, public.b), strict=True):
            np.testing.assert_array_equal(stats.counts.sum(axis=0), result.nearest_counts)
        # The difference: the per-group means of the chunks' means, weighted N_g / N.
        sums = (found.spans[:, 1] - found.spans[:, 0]) * found.difference[:, 0]
        per_group = [sums[found.spans[:, 2] == g].sum() / m for g, m in enumerate(split)]
        weights = [1.0] if groups is None else public.a.mixture.weights
        assert np.dot(weights, per_group) == pytest.approx(public.difference, rel=1e-10)


def test_the_selector_refuses_an_unknown_backend(small_images):
    model = nr.TextureModel.from_images(small_images)
    kw = dict(samples_per_group=[100], seed=0, distance="l1", exponent=1.0)
    with pytest.raises(ValueError, match=r"backend must be one of .*'per-sample'.*got 'gpu'"):
        _search.search([model], backend="gpu", **kw)
    with pytest.raises(ValueError, match=r"one model or a pair"):
        _search.search([model] * 3, backend="cpu", **kw)
    # The public functions offer the policies only; the selector's own names stay internal.
    with pytest.raises(ValueError, match=r"backend must be one of \('auto', 'cpu', 'torch'\)"):
        nr.specificity(model, n_samples=100, backend="blocked")
