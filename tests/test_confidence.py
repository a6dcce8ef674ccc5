"""Subject-level confidence: jackknife replicates against brute force, interval coverage."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import SimpleITK as sitk
from hypothesis import given, settings
from hypothesis import strategies as st

import itk_nrreval as nr
from itk_nrreval.measures._overlap_kernels import membership_gradient_sum, membership_pair_sums
from itk_nrreval.measures.confidence import (
    compare,
    jackknife_groups,
    jackknife_interval,
    overlap_replicates,
    probability_best,
    specificity_replicates,
)
from itk_nrreval.measures.model import TextureModel


def gram_of(images: np.ndarray) -> np.ndarray:
    flat = images.reshape(images.shape[0], -1)
    centred = flat - flat.mean(axis=0)
    return centred @ centred.T


def test_groups_partition_the_subjects():
    groups = jackknife_groups(10, 4)
    assert sorted(np.concatenate(groups).tolist()) == list(range(10))
    assert [g.tolist() for g in groups][:2] == [[0, 4, 8], [1, 5, 9]]
    assert len(jackknife_groups(7)) == 7  # default: leave one out
    with pytest.raises(ValueError, match="at least 4 images"):
        jackknife_groups(3)
    with pytest.raises(ValueError, match="fewer than 3 images"):
        jackknife_groups(5, 2)


@pytest.mark.parametrize("distance", ["l1", "l2"])
def test_replicates_equal_specificity_of_the_subjects_left(distance):
    rng = np.random.default_rng(1)
    images = rng.normal(size=(9, 12, 11)) + np.linspace(0, 3, 9)[:, None, None]
    groups = jackknife_groups(9, 3)
    spec, gen = specificity_replicates(
        gram_of(images), groups=groups, n_samples=3000, distance=distance, seed=4
    )
    for k, out in enumerate(groups):
        keep = np.setdiff1d(np.arange(9), out)
        s, g = nr.texture_measures(images[keep], n_samples=3000, distance=distance, seed=4)
        assert spec[k] == pytest.approx(s.value, rel=1e-9)
        assert gen[k] == pytest.approx(g.value, rel=1e-9)


def test_gram_model_without_mean_scores_like_the_image_model():
    rng = np.random.default_rng(2)
    images = rng.normal(size=(6, 40))
    a = nr.specificity(images, n_samples=2000, seed=1)
    b = nr.specificity(TextureModel.from_gram(gram_of(images)), n_samples=2000, seed=1)
    assert b.value == pytest.approx(a.value, rel=1e-10)


def fuzzy_memberships(rng, n: int, n_labels: int, shape) -> np.ndarray:
    """Random partial-volume memberships (N, L + 1, *shape), component 0 background."""
    logits = rng.normal(size=(n, n_labels + 1, *shape)) * 3
    m = np.exp(logits - logits.max(axis=1, keepdims=True))
    m /= m.sum(axis=1, keepdims=True)
    m[m < 0.05] = 0.0  # exact zeros, as resampled one-hot memberships have
    m /= m.sum(axis=1, keepdims=True)
    m[:, 3] *= rng.random(n)[:, None, None] < 0.7  # label 3 missing in some subjects
    return m.astype(np.float32)


def per_image_sums(memb: np.ndarray, mask: np.ndarray | None, spacing):
    """The labels present, and the per-image sums (voxel units) from the kernels the
    pipeline uses: volume, target sums, gradient sums (n, L) and pair sums p, q (L,)."""
    n, shape = memb.shape[0], memb.shape[2:]
    labels = nr.overlap_table(memb, mask=mask, spacing=spacing).labels
    flat = memb.reshape(n, memb.shape[1], -1)
    mflat = None if mask is None else mask.reshape(-1)
    vol = np.zeros((n, labels.size))
    spair = np.zeros((n, labels.size))
    gsum = np.zeros((n, labels.size))
    p = np.zeros(labels.size)
    q = np.zeros(labels.size)
    for k, comp in enumerate(labels):
        p[k], q[k], vol[:, k], spair[:, k] = membership_pair_sums(flat[:, comp], mask=mflat)
        for i in range(n):
            gsum[i, k] = membership_gradient_sum(
                flat[i, comp], shape=shape, spacing=spacing, mask=mflat
            )
    return labels, (vol, spair, gsum, p, q)


@pytest.mark.parametrize("mask", [False, True])
def test_overlap_replicates_equal_the_overlap_of_the_subjects_left(mask):
    rng = np.random.default_rng(3)
    memb = fuzzy_memberships(rng, 7, 4, (9, 10))
    m = rng.random((9, 10)) < 0.8 if mask else None
    spacing = (0.7, 1.3)
    n = memb.shape[0]
    labels, (vol, spair, gsum, p, q) = per_image_sums(memb, m, spacing)
    weightings = nr.WEIGHTINGS
    reps = overlap_replicates(
        vol, spair, gsum, p, q, labels=labels, spacing=spacing, weightings=weightings
    )
    for k in range(n):
        keep = np.arange(n) != k
        table = nr.overlap_table(memb[keep], mask=m, spacing=spacing)
        for w in weightings:
            assert reps[w][k] == pytest.approx(table.generalized(w), rel=1e-12, abs=1e-14), (k, w)


def test_groups_leave_out_whole_subjects():
    # images 0-5 are T1 scans, 6-11 the T2 scans of the same six subjects
    subjects = [f"s{i}" for i in range(6)] * 2
    groups = jackknife_groups(12, subjects=subjects)
    assert [g.tolist() for g in groups] == [[i, i + 6] for i in range(6)]
    groups = jackknife_groups(12, 3, subjects=subjects)
    assert [g.tolist() for g in groups] == [[0, 3, 6, 9], [1, 4, 7, 10], [2, 5, 8, 11]]
    with pytest.raises(ValueError, match="at least 4 subjects"):
        jackknife_groups(6, subjects=["a", "b", "c"] * 2)
    with pytest.raises(ValueError, match="length"):
        jackknife_groups(12, subjects=subjects[:-1])


@pytest.mark.parametrize("distance", ["l1", "l2"])
def test_mixture_replicates_equal_the_mixture_of_the_subjects_left(distance):
    rng = np.random.default_rng(5)
    n = 5  # subjects, each imaged in two contrasts with different means
    t1 = rng.normal(size=(n, 9, 8)) + np.linspace(0, 2, n)[:, None, None]
    t2 = 4 - 0.5 * t1 + rng.normal(scale=0.3, size=t1.shape)
    images = np.concatenate([t1, t2])
    labels = ["t1"] * n + ["t2"] * n
    groups = jackknife_groups(2 * n, subjects=list(range(n)) * 2)
    spec, gen = specificity_replicates(
        gram_of(images),
        groups=groups,
        image_groups=labels,
        n_samples=2000,
        distance=distance,
        seed=3,
    )
    for k, out in enumerate(groups):
        keep = np.setdiff1d(np.arange(2 * n), out)
        s, g = nr.texture_measures(
            images[keep],
            groups=[labels[i] for i in keep],
            n_samples=2000,
            distance=distance,
            seed=3,
        )
        assert spec[k] == pytest.approx(s.value, rel=1e-9)
        assert gen[k] == pytest.approx(g.value, rel=1e-9)


@pytest.mark.parametrize("mask", [False, True])
def test_overlap_replicates_leaving_out_whole_subjects(mask):
    rng = np.random.default_rng(6)
    memb = fuzzy_memberships(rng, 8, 3, (7, 9))
    m = rng.random((7, 9)) < 0.8 if mask else None
    spacing = (1.1, 0.6)
    n = memb.shape[0]
    labels, (vol, spair, gsum, p, q) = per_image_sums(memb, m, spacing)
    flat = memb.reshape(n, memb.shape[1], -1).astype(np.float64)
    mflat = np.ones(flat.shape[-1], bool) if m is None else m.reshape(-1)
    # four subjects with two images each (images i and i + 4), plus a pair no subject shares
    subjects = [0, 1, 2, 3] * 2
    left_out = jackknife_groups(n, subjects=subjects)
    pairs = np.array([[i, i + 4] for i in range(4)])
    pair_min = np.array(
        [[np.minimum(flat[a, c], flat[b, c])[mflat].sum() for c in labels] for a, b in pairs]
    )
    reps = overlap_replicates(
        vol,
        spair,
        gsum,
        p,
        q,
        labels=labels,
        spacing=spacing,
        weightings=nr.WEIGHTINGS,
        left_out=left_out,
        subject_pairs=pairs,
        subject_pair_min=pair_min,
    )
    for k, out in enumerate(left_out):
        keep = np.setdiff1d(np.arange(n), out)
        table = nr.overlap_table(memb[keep], mask=m, spacing=spacing)
        for w in nr.WEIGHTINGS:
            assert reps[w][k] == pytest.approx(table.generalized(w), rel=1e-9), (k, w)
    with pytest.raises(ValueError, match="images 0 and 4"):
        overlap_replicates(
            vol,
            spair,
            gsum,
            p,
            q,
            labels=labels,
            spacing=spacing,
            weightings=["volume"],
            left_out=left_out,
        )


def test_jackknife_of_a_mean_is_the_classic_standard_error():
    rng = np.random.default_rng(5)
    x = rng.normal(size=25)
    reps = np.array([np.delete(x, k).mean() for k in range(x.size)])
    iv = jackknife_interval(x.mean(), reps)
    assert iv.stderr == pytest.approx(x.std(ddof=1) / math.sqrt(x.size), rel=1e-12)
    assert iv.lo < x.mean() < iv.hi and iv.n_replicates == 25


def null_and_clear(seed: int, n: int = 16):
    """Two registrations with identically distributed images, and a clearly worse one."""
    rng = np.random.default_rng(seed)
    modes = rng.normal(size=(4, 150))

    def population(noise: float) -> np.ndarray:
        return rng.normal(size=(n, 4)) @ modes + noise * rng.normal(size=(n, 150))

    return population(1.0), population(1.0), population(2.0)


def test_null_difference_covers_zero_and_clear_difference_excludes_it():
    covered = 0
    clear = 0
    seeds = range(40)
    groups = jackknife_groups(16)
    for seed in seeds:
        a, b, worse = null_and_clear(seed)
        vals, reps = {}, {}
        for name, images in (("a", a), ("b", b), ("worse", worse)):
            reps[name] = specificity_replicates(
                gram_of(images), groups=groups, n_samples=4000, distance="l1", seed=seed
            )[0]
            vals[name] = nr.specificity(images, n_samples=4000, seed=seed).value
        by_pair = {(c.a, c.b): c for c in compare("specificity", vals, reps)}
        lo, hi = by_pair[("a", "b")].ci95
        covered += lo <= 0 <= hi
        clear += by_pair[("a", "worse")].separable and by_pair[("a", "worse")].difference < 0
    assert covered >= 0.9 * len(seeds)
    assert clear >= 0.9 * len(seeds)


def test_probability_best():
    reps = {"a": np.array([1.0, 1.1, 0.9, 1.0]), "b": np.array([3.0, 3.2, 2.9, 3.1])}
    pb = probability_best({"a": 1.0, "b": 3.0}, reps, higher_is_better=False)
    assert pb == {"a": 1.0, "b": 0.0}
    same = {"a": reps["a"], "b": reps["a"] + 0.0}
    pb = probability_best({"a": 1.0, "b": 1.0}, same, higher_is_better=True, n_draws=4000)
    assert sum(pb.values()) == pytest.approx(1.0)


def test_results_state_the_number_of_replicates_the_jackknife_ran():
    """More than 50 subjects: the default groups are 50, and options say so (they said N)."""
    rng = np.random.default_rng(8)
    n = 53
    yy, xx = np.mgrid[:10, :10]
    grid = {"spacing": (1.0, 1.5), "origin": (3.0, -2.0), "direction": (0.0, 1.0, 1.0, 0.0)}
    images = [
        {
            "array": np.exp(-((xx - 4.5 - rng.normal()) ** 2 + (yy - 4.5) ** 2) / 8) + i / n,
            **grid,
        }
        for i in range(n)
    ]
    manifest = {
        "images": images,
        "registrations": {
            "identity": {
                "reference": {"array": np.zeros((10, 10)), **grid},
                "transforms": [sitk.Transform(2, sitk.sitkIdentity) for _ in range(n)],
            }
        },
    }
    res = nr.evaluate(manifest, n_samples=200, seed=1, progress=False)
    used = res.scores["identity"].intervals["specificity"].n_replicates
    assert used == 50
    assert res.options["resamples"] == used


# ----------------------------------------------------------------------------- ties (issue 44)


def _comparisons(values: dict, separable: set, measure: str = "specificity") -> list:
    """compare() on replicates built so that exactly the unordered pairs in `separable`
    are separable: a pair's difference replicates spread by 1e-6 (separable unless the
    scores are equal) or by +-10 (never separable here)."""
    out = []
    names = list(values)
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            tight = frozenset((a, b)) in separable
            spread = 1e-6 * np.arange(6) if tight else 10.0 * np.array([1, -1] * 3)
            out += compare(measure, {a: values[a], b: values[b]}, {a: spread, b: 0 * spread})
    return out


def test_ties_do_not_chain_across_a_separable_pair():
    """The issue's table: groupwise and pairwise_near both "rank 1 (tied)" through a
    neighbour each is not separable from, while their own comparison is separable (and
    the verdict decides groupwise better by it). A pair the comparison separates is never
    tied, even when the Monte-Carlo errors overlap."""
    spec = {"groupwise": 1.00, "fluid": 1.10, "pairwise_near": 1.28, "affine": 3.0}
    comparisons = _comparisons(
        spec,
        {frozenset(("groupwise", "pairwise_near"))}
        | {frozenset((n, "affine")) for n in spec if n != "affine"},
    )
    ranks = nr.ranks(spec, higher_is_better=False, comparisons=comparisons)
    assert ranks["groupwise"] < ranks["pairwise_near"]
    from itk_nrreval.measures.confidence import tie_groups

    groups = tie_groups(spec, higher_is_better=False, comparisons=comparisons)
    assert groups == [("groupwise", "fluid"), ("pairwise_near",), ("affine",)]
    # separable, though within 1.96 combined Monte-Carlo errors: told apart, as the verdict
    two = {"a": 1.0, "b": 1.01}
    sep = _comparisons(two, {frozenset(two)})
    assert sep[0].separable
    stderr = {"a": 0.05, "b": 0.05}
    assert tie_groups(two, higher_is_better=False, stderr=stderr, comparisons=sep) == [
        ("a",),
        ("b",),
    ]


@settings(max_examples=200, deadline=None)
@given(
    values=st.lists(st.floats(0.0, 5.0).map(lambda v: round(v, 1)), min_size=1, max_size=7),
    stderr=st.lists(st.sampled_from([None, 0.0, 0.05, 0.5]), min_size=7, max_size=7),
    bits=st.integers(0, 2**21 - 1),
    compared=st.floats(0.0, 1.0),
    higher=st.booleans(),
)
def test_tie_groups_never_hold_a_separable_pair_and_end_only_where_the_rule_says(
    values, stderr, bits, compared, higher
):
    """Restated from the rule: groups are runs in score order, best first; no group holds
    two registrations whose comparison is separable; two registrations a comparison does
    not separate share a group unless a separable pair lies between them in a run; and a
    run ends only before a registration separable from one in it, or where nothing in it
    is tied (not separable; or, without a comparison, equal or within 1.96 combined
    standard errors) with anything after it."""
    from itk_nrreval.evaluation import TIE_Z, tie_groups  # confidence's, where ranks use it

    names = [f"r{i}" for i in range(len(values))]
    scores = dict(zip(names, values, strict=True))
    se = {n: s for n, s in zip(names, stderr, strict=False) if s is not None}
    pairs = [frozenset(p) for p in itertools.combinations(names, 2)]
    separable = {p for k, p in enumerate(pairs) if bits >> k & 1}
    with_comparison = set(pairs[: round(compared * len(pairs))])
    comparisons = [
        c for c in _comparisons(scores, separable) if frozenset((c.a, c.b)) in with_comparison
    ]
    told = {frozenset((c.a, c.b)): c.separable for c in comparisons}

    def tied(a, b):
        p = frozenset((a, b))
        if p in told:
            return not told[p]
        if scores[a] == scores[b]:
            return True
        return (
            a in se and b in se and abs(scores[a] - scores[b]) <= TIE_Z * math.hypot(se[a], se[b])
        )

    groups = tie_groups(scores, higher_is_better=higher, stderr=se, comparisons=comparisons)
    flat = [n for g in groups for n in g]
    assert sorted(flat) == sorted(names)
    sign = -1 if higher else 1
    assert [sign * scores[n] for n in flat] == sorted(sign * scores[n] for n in flat)
    for g in groups:
        assert not any(told.get(frozenset(p)) for p in itertools.combinations(g, 2))
    for g, h in itertools.pairwise(groups):
        later = flat[flat.index(h[0]) :]
        assert any(told.get(frozenset((m, h[0]))) for m in g) or not any(
            tied(m, x) for m in g for x in later
        ), (groups, told)
    rank = nr.ranks(scores, higher_is_better=higher, stderr=se, comparisons=comparisons)
    for p in separable & set(told):
        a, b = sorted(p)
        if scores[a] != scores[b]:
            assert rank[a] != rank[b]
