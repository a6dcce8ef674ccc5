"""Specificity of a Gaussian-mixture model (issue 19) against brute-force references.

The references never look inside the model: each group's mean and modes come from an SVD of
that group's images in image space, samples are rebuilt as images from the package's
standard normals (``_search.sampling.standard_normals``, the documented counter-based stream), and
distances are taken by numpy / scipy to every training image. Conventions the references
follow because they are documented (not because the code does them): groups in order of
first appearance; group g's samples are numbers ``offset_g .. offset_g + M_g - 1``; each group
mode is signed so that the group image with the largest-magnitude coordinate along it has a
positive coordinate.
"""

from __future__ import annotations

import importlib
import json
import math

import numba
import numpy as np
import pytest
import SimpleITK as sitk
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.distance import cdist

import itk_nrreval as nr
from itk_nrreval.cli import main
from itk_nrreval.measures import _search
from itk_nrreval.measures.model import MixtureModel

spec_mod = importlib.import_module("itk_nrreval.measures.specificity")

# Interleaved groups, of unequal sizes, so that image order and group order differ.
GROUPS = ["t1", "t2", "t1", "t1", "t2", "t1", "t2", "t1", "t2", "t1", "t1", "t2"]


@pytest.fixture(scope="module")
def two_contrasts() -> np.ndarray:
    """12 images (12, 14): a T1-like and a T2-like cluster (different structure and spread)."""
    rng = np.random.default_rng(19)
    t1, t2 = rng.normal(size=(2, 12, 14))
    out = np.empty((12, 12, 14))
    for i, g in enumerate(GROUPS):
        out[i] = (
            3.0 * t1 + 0.6 * rng.normal(size=(12, 14))
            if g == "t1"
            else (-2.0 * t2 + 1.1 * rng.normal(size=(12, 14)))
        )
    return out


def _group_modes(flat: np.ndarray):
    """Mean, signed unit modes (rows) and unbiased standard deviations of one group's images."""
    mean = flat.mean(axis=0)
    u, s, vt = np.linalg.svd(flat - mean, full_matrices=False)
    keep = s > s[0] * 1e-9
    u, s, vt = u[:, keep], s[keep], vt[keep]
    for k in range(s.size):  # the documented sign: largest-|coordinate| image positive
        if u[np.argmax(np.abs(u[:, k])), k] < 0:
            vt[k] = -vt[k]
    return mean, vt, s / math.sqrt(flat.shape[0] - 1)


def _check_allocation(result, sizes):
    m = result.n_samples
    alloc = result.mixture.n_samples
    assert alloc.sum() == m
    assert np.all(np.abs(alloc - m * np.asarray(sizes) / sum(sizes)) < 1)
    return alloc


def _brute_force(images, groups, result, seed):
    """Per-sample reference: images rebuilt from group means and modes, all N distances.

    Returns the sample images (M, n_voxels), their group, and the training images (N, n).
    """
    flat = images.reshape(images.shape[0], -1)
    names = list(dict.fromkeys(groups))
    members = [np.flatnonzero(np.asarray(groups) == g) for g in names]
    alloc = _check_allocation(result, [len(m) for m in members])
    samples, sample_group = [], []
    offset = 0
    for g, idx in enumerate(members):
        mean, modes, sd = _group_modes(flat[idx])
        z = _search.sampling.standard_normals(seed, offset, offset + alloc[g], sd.size)
        samples.append(mean + (z * sd) @ modes)
        sample_group.append(np.full(alloc[g], g))
        offset += alloc[g]
    return np.concatenate(samples), np.concatenate(sample_group), flat, names, members


def _joint_params(flat_train: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Coordinates along the joint principal axes of the training images (any signs/order)."""
    mean = flat_train.mean(axis=0)
    _, s, vt = np.linalg.svd(flat_train - mean, full_matrices=False)
    vt = vt[s > s[0] * 1e-9]
    return (points - mean) @ vt.T


def _reference_numbers(d, sample_group, names, members, n_images, exponent):
    """Stratified value / stderr, per-group values, counts and generalization from distances."""
    per_sample = d.min(axis=1) ** exponent
    weights = np.array([len(m) for m in members]) / n_images
    values = np.array([per_sample[sample_group == g].mean() for g in range(len(names))])
    stderrs = np.array(
        [
            per_sample[sample_group == g].std() / math.sqrt((sample_group == g).sum() - 1)
            for g in range(len(names))
        ]
    )
    image_group = np.empty(n_images, dtype=int)
    for g, idx in enumerate(members):
        image_group[idx] = g
    nearest = d.argmin(axis=1)
    matrix = np.zeros((len(names), len(names)), dtype=int)
    np.add.at(matrix, (sample_group, image_group[nearest]), 1)
    return dict(
        value=float(weights @ values),
        stderr=float(np.sqrt(np.sum((weights * stderrs) ** 2))),
        values=values,
        stderrs=stderrs,
        counts=np.bincount(nearest, minlength=n_images),
        matrix=matrix,
        gen=d.min(axis=0) ** exponent,
    )


def _assert_matches(spec, gen, ref, rtol):
    assert spec.value == pytest.approx(ref["value"], rel=rtol)
    assert spec.stderr == pytest.approx(ref["stderr"], rel=1e3 * rtol)
    np.testing.assert_allclose(spec.mixture.values, ref["values"], rtol=rtol)
    np.testing.assert_allclose(spec.mixture.stderrs, ref["stderrs"], rtol=1e3 * rtol)
    np.testing.assert_array_equal(spec.nearest_counts, ref["counts"])
    np.testing.assert_array_equal(spec.mixture.nearest_counts, ref["matrix"])
    np.testing.assert_allclose(gen.nearest_distances, ref["gen"], rtol=rtol)


@pytest.mark.parametrize("exponent", [1.0, 2.0])
def test_l2_mixture_equals_image_space_brute_force(two_contrasts, exponent):
    m, seed = 3001, 7  # M * N_g / N is not an integer: the allocation's remainders matter
    spec, gen = nr.texture_measures(
        two_contrasts, groups=GROUPS, n_samples=m, distance="l2", exponent=exponent, seed=seed
    )
    samples, sample_group, flat, names, members = _brute_force(two_contrasts, GROUPS, spec, seed)
    d = cdist(samples, flat)  # image-space Euclidean distances to all N training images
    ref = _reference_numbers(d, sample_group, names, members, 12, exponent)
    _assert_matches(spec, gen, ref, 1e-9)
    assert spec.mixture.groups == ("t1", "t2")
    np.testing.assert_array_equal(spec.mixture.sizes, [7, 5])
    np.testing.assert_array_equal(spec.mixture.n_modes, [6, 4])
    np.testing.assert_allclose(spec.mixture.weights, [7 / 12, 5 / 12])
    # Both clusters are well apart: samples land nearest their own group.
    assert np.all(np.diag(spec.mixture.nearest_counts) > 0.95 * spec.mixture.n_samples)


def test_l1_mixture_equals_brute_force_in_the_joint_parameter_space(two_contrasts):
    m, seed = 2500, 3
    spec, gen = nr.texture_measures(two_contrasts, groups=GROUPS, n_samples=m, seed=seed)
    assert spec.distance == "l1"
    samples, sample_group, flat, names, members = _brute_force(two_contrasts, GROUPS, spec, seed)
    d = cdist(_joint_params(flat, samples), _joint_params(flat, flat), "cityblock")
    ref = _reference_numbers(d, sample_group, names, members, 12, 1.0)
    _assert_matches(spec, gen, ref, 1e-9)
    assert spec.n_modes == 11  # the joint space of all N images


def test_three_groups_and_the_gram_matrix_path(two_contrasts):
    groups = ["a", "b", "a", "c", "b", "a", "c", "a", "b", "c", "a", "b"]
    m, seed = 2000, 11
    spec, gen = nr.texture_measures(
        two_contrasts, groups=groups, n_samples=m, distance="l2", seed=seed
    )
    samples, sample_group, flat, names, members = _brute_force(two_contrasts, groups, spec, seed)
    ref = _reference_numbers(cdist(samples, flat), sample_group, names, members, 12, 1.0)
    _assert_matches(spec, gen, ref, 1e-9)
    # The same mixture from the Gram matrix of the centred images alone.
    centred = flat - flat.mean(axis=0)
    model = nr.TextureModel.from_gram(centred @ centred.T)
    for distance in ("l1", "l2"):
        a, _ = nr.texture_measures(model, groups=groups, n_samples=m, distance=distance, seed=seed)
        b, _ = nr.texture_measures(
            two_contrasts, groups=groups, n_samples=m, distance=distance, seed=seed
        )
        assert a.value == pytest.approx(b.value, rel=1e-9)
        np.testing.assert_array_equal(a.mixture.nearest_counts, b.mixture.nearest_counts)


def test_groups_none_is_todays_estimator(two_contrasts):
    # groups=None runs the single-Gaussian kernel unchanged: the same bits as driving the
    # kernel directly with the paper's formulas, and no trace of a mixture in the output.
    m, seed = 5000, 4
    model = nr.TextureModel.from_images(two_contrasts)
    for distance in ("l1", "l2"):
        spec, gen = nr.texture_measures(
            two_contrasts, n_samples=m, distance=distance, seed=seed, groups=None
        )
        n_chunks = -(-m // _search.sampling.CHUNK)
        means, m2s, counts, gmin = _search.sampling.run_single(
            np.ascontiguousarray(model.training_params.T),
            np.sqrt(model.mode_variances),
            _search.sampling.stream_key(seed),
            m,
            distance == "l2",
            1.0,
            _search.sampling.CHUNK,
            0,
            n_chunks,
        )
        mean, m2 = _search.sampling.combine_moments(means, m2s, m, _search.sampling.CHUNK)
        assert spec.value == mean
        assert spec.stderr == math.sqrt(m2 / m) / math.sqrt(m - 1)
        np.testing.assert_array_equal(spec.nearest_counts, counts.sum(axis=0))
        raw = gmin.min(axis=0)
        np.testing.assert_array_equal(
            gen.nearest_distances, np.sqrt(raw) if distance == "l2" else raw
        )
        assert spec.mixture is None and gen.groups is None
        assert "mixture" not in spec.to_dict() and "groups" not in gen.to_dict()
        assert (
            spec.to_dict()
            == nr.specificity(two_contrasts, n_samples=m, distance=distance, seed=seed).to_dict()
        )


@pytest.mark.parametrize("distance", ["l1", "l2"])
def test_one_group_is_identical_to_todays_estimator(two_contrasts, distance):
    kw = dict(n_samples=4500, distance=distance, seed=9, exponent=0.5)
    s0, g0 = nr.texture_measures(two_contrasts, **kw)
    s1, g1 = nr.texture_measures(two_contrasts, groups=["all"] * 12, **kw)
    assert (s1.value, s1.stderr, s1.n_modes) == (s0.value, s0.stderr, s0.n_modes)
    np.testing.assert_array_equal(s1.nearest_counts, s0.nearest_counts)
    np.testing.assert_array_equal(g1.nearest_distances, g0.nearest_distances)
    assert (g1.value, g1.stderr) == (g0.value, g0.stderr)
    assert s1.mixture.nearest_counts.tolist() == [[4500]]
    assert (s1.mixture.values[0], s1.mixture.stderrs[0]) == (s0.value, s0.stderr)
    other = two_contrasts * 1.2 + np.random.default_rng(1).normal(size=two_contrasts.shape)
    c0 = nr.compare_specificity(two_contrasts, other, **kw)
    c1 = nr.compare_specificity(two_contrasts, other, groups=["all"] * 12, **kw)
    assert (c1.difference, c1.difference_stderr) == (c0.difference, c0.difference_stderr)
    assert (c1.a.value, c1.b.value) == (c0.a.value, c0.b.value)


def test_counts_sum_to_m_and_agree(two_contrasts):
    m = 4099
    r = nr.specificity(two_contrasts, groups=GROUPS, n_samples=m, seed=2)
    mix = r.mixture
    assert mix.nearest_counts.sum() == m == r.nearest_counts.sum()
    np.testing.assert_array_equal(mix.nearest_counts.sum(axis=1), mix.n_samples)
    # Column h of the group matrix is the per-image counts summed over group h's images.
    for h, name in enumerate(mix.groups):
        assert mix.nearest_counts[:, h].sum() == r.nearest_counts[np.asarray(GROUPS) == name].sum()
    d = r.to_dict()
    assert sum(map(sum, d["mixture"]["nearest_counts"])) == m
    json.dumps(d)  # JSON-ready


def test_seeds_threads_and_paths_reproduce(two_contrasts, monkeypatch):
    kw = dict(groups=GROUPS, n_samples=9000, distance="l2")
    a = nr.specificity(two_contrasts, seed=5, **kw)
    b = nr.specificity(two_contrasts, seed=5, **kw)
    c = nr.specificity(two_contrasts, seed=6, **kw)
    assert a.to_dict() == b.to_dict()
    assert a.value != c.value
    before = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = nr.specificity(two_contrasts, seed=5, **kw)
    finally:
        numba.set_num_threads(before)
    assert one.to_dict() == a.to_dict()
    # The blocked search draws through the same routine: the same bits.
    for distance in ("l1", "l2"):
        kw["distance"] = distance
        monkeypatch.setitem(spec_mod._BLOCKED_MIN_IMAGES, distance, 1 << 60)
        per_sample = nr.texture_measures(two_contrasts, seed=5, backend="cpu", **kw)
        monkeypatch.setitem(spec_mod._BLOCKED_MIN_IMAGES, distance, 0)
        blocked = nr.texture_measures(two_contrasts, seed=5, backend="cpu", **kw)
        assert blocked[0].to_dict() == per_sample[0].to_dict()
        assert blocked[1].to_dict() == per_sample[1].to_dict()


@pytest.mark.parametrize("distance", ["l1", "l2"])
def test_torch_backend_equals_cpu(two_contrasts, distance):
    pytest.importorskip("torch")
    kw = dict(groups=GROUPS, n_samples=1500, distance=distance, seed=5)
    cpu = nr.texture_measures(two_contrasts, backend="cpu", **kw)
    gpu = nr.texture_measures(two_contrasts, backend="torch", **kw)
    assert gpu[0].value == pytest.approx(cpu[0].value, rel=1e-10)
    np.testing.assert_array_equal(gpu[0].mixture.nearest_counts, cpu[0].mixture.nearest_counts)
    np.testing.assert_allclose(gpu[1].nearest_distances, cpu[1].nearest_distances, rtol=1e-10)


@pytest.mark.parametrize("blocked", [False, True])
def test_compare_specificity_shares_groups_and_normals(two_contrasts, monkeypatch, blocked):
    monkeypatch.setitem(spec_mod._BLOCKED_MIN_IMAGES, "l1", 0 if blocked else 1 << 60)
    rng = np.random.default_rng(3)
    other = two_contrasts + 0.4 * rng.normal(size=two_contrasts.shape)
    kw = dict(groups=GROUPS, n_samples=3000, seed=8)
    cmp = nr.compare_specificity(two_contrasts, other, **kw)
    a = nr.specificity(two_contrasts, **kw)
    b = nr.specificity(other, **kw)
    assert cmp.a.value == pytest.approx(a.value, rel=1e-12)
    assert cmp.b.value == pytest.approx(b.value, rel=1e-12)
    np.testing.assert_array_equal(cmp.b.mixture.nearest_counts, b.mixture.nearest_counts)
    assert cmp.difference == pytest.approx(a.value - b.value, rel=1e-9)
    # A scaled copy sees exactly proportional samples (same group and normals per number),
    # so every paired difference is -0.1 times a's value: so are the mean and its stderr.
    scaled = nr.compare_specificity(two_contrasts, 1.1 * two_contrasts, **kw)
    assert scaled.difference == pytest.approx(-0.1 * scaled.a.value, rel=1e-9)
    assert scaled.difference_stderr == pytest.approx(0.1 * scaled.a.stderr, rel=1e-7)


@settings(max_examples=10, deadline=None)
@given(
    sizes=st.lists(st.integers(2, 5), min_size=2, max_size=3),
    shift=st.floats(-100, 100),
    scale=st.floats(0.1, 10),
    seed=st.integers(0, 2**32),
)
def test_mixture_is_shift_invariant_and_scales_linearly(sizes, shift, scale, seed):
    rng = np.random.default_rng(seed)
    groups = rng.permutation(np.repeat(np.arange(len(sizes)), sizes)).tolist()
    images = rng.normal(size=(len(groups), 6, 5)) + 3 * np.asarray(groups)[:, None, None]
    kw = dict(groups=groups, n_samples=300, seed=seed)
    base = nr.specificity(images, **kw)
    moved = nr.specificity(scale * images + shift, **kw)
    assert moved.value == pytest.approx(scale * base.value, rel=1e-7)
    np.testing.assert_array_equal(base.mixture.nearest_counts, moved.mixture.nearest_counts)


def test_mixture_model_components_are_the_groups(two_contrasts):
    flat = two_contrasts.reshape(12, -1)
    mix = MixtureModel.from_model(nr.TextureModel.from_images(two_contrasts), GROUPS)
    params = mix.joint.training_params
    for g, name in enumerate(mix.groups):
        idx = np.flatnonzero(np.asarray(GROUPS) == name)
        mean = flat[idx].mean(axis=0)
        # The centre is the group mean: its distance to every image is the image-space one.
        np.testing.assert_allclose(
            np.linalg.norm(params - mix.centres[g], axis=1),
            np.linalg.norm(flat - mean, axis=1),
            rtol=1e-10,
        )
        # The component's covariance is the group's unbiased sample covariance.
        p = params[idx] - mix.centres[g]
        basis = mix.bases[g]
        assert basis.shape == (idx.size - 1, mix.n_modes)
        np.testing.assert_allclose(
            basis.T @ basis, p.T @ p / (idx.size - 1), atol=1e-10 * np.abs(p).max() ** 2
        )
        sd = np.linalg.norm(basis, axis=1)
        np.testing.assert_allclose(sd**2, mix.mode_variances[g], rtol=1e-10)
        _, s, _ = np.linalg.svd(flat[idx] - mean, full_matrices=False)
        np.testing.assert_allclose(sd, s[: idx.size - 1] / math.sqrt(idx.size - 1), rtol=1e-9)
        # Documented sign: the largest-|coordinate| group image is on the positive side.
        coords = p @ (basis / sd[:, None]).T
        assert np.all(coords[np.argmax(np.abs(coords), axis=0), np.arange(sd.size)] > 0)


# ------------------------------------------------------------------------------ bad input


@pytest.mark.parametrize(
    "groups, message",
    [
        (GROUPS[:-1], "groups: 11 labels for 12 images"),
        (["t1"] * 11 + ["t2"], "group 't2' has only 1 image (image 11)"),
        ("t1,t2", "got a string"),
        ([["t1"]] * 12, "groups[0]: a group label must be hashable, got list"),
    ],
)
def test_bad_groups_are_refused(two_contrasts, groups, message):
    with pytest.raises(nr.InputError) as info:
        nr.specificity(two_contrasts, groups=groups, n_samples=100)
    assert message in str(info.value)


def test_identical_group_and_too_few_samples_are_refused(two_contrasts):
    images = two_contrasts.copy()
    images[4] = images[1]
    groups = ["y", "x", "y", "y", "x"] + ["y"] * 7
    # given as images, the image given twice is refused first, by name
    with pytest.raises(nr.InputError, match=r"images\[4\] is the same as images\[1\]"):
        nr.specificity(images, groups=groups, n_samples=100)
    # a model from its Gram matrix alone (as the pipeline builds it): the group's check
    centred = images.reshape(len(images), -1) - images.reshape(len(images), -1).mean(axis=0)
    model = nr.TextureModel.from_gram(centred @ centred.T)
    with pytest.raises(nr.InputError, match="the 2 images of group 'x' are identical"):
        nr.specificity(model, groups=groups, n_samples=100)
    # 5 samples for groups of 10 and 2 images: 5 * 2 / 12 < 2, so group t2 gets 1 sample.
    groups = ["t1"] * 10 + ["t2"] * 2
    with pytest.raises(ValueError, match=r"n_samples=5 gives group 't2' 1 samples"):
        nr.specificity(two_contrasts, groups=groups, n_samples=5)
    assert nr.specificity(two_contrasts, groups=groups, n_samples=12).mixture.n_samples[1] == 2


def _write(tmp_path, images):
    paths = []
    for i, arr in enumerate(images):
        path = tmp_path / f"s{i:02d}.nii.gz"
        sitk.WriteImage(sitk.GetImageFromArray(arr), str(path))
        paths.append(str(path))
    return paths


def test_cli_groups(tmp_path, two_contrasts, capsys):
    paths = _write(tmp_path, two_contrasts.astype(np.float32))
    out = tmp_path / "spec.json"
    args = ["specificity", *paths, "--samples", "2000", "--seed", "4", "--json", str(out)]
    assert main([*args, "--groups", ",".join(GROUPS)]) == 0
    printed = capsys.readouterr().out
    expected = nr.specificity(paths, groups=GROUPS, n_samples=2000, seed=4)
    assert f"specificity = {expected.value:.6g} ± " in printed
    assert "group t1:" in printed and "group t2:" in printed
    data = json.loads(out.read_text())
    assert data["groups"] == GROUPS
    assert data["specificity"]["mixture"]["groups"] == ["t1", "t2"]
    assert sum(map(sum, data["specificity"]["mixture"]["nearest_counts"])) == 2000


@pytest.mark.parametrize(
    "labels, message",
    [
        (",".join(GROUPS[:-1]), "groups: 11 labels for 12 images"),
        (",".join(["t1"] * 11 + ["t2"]), "group 't2' has only 1 image"),
        ("t1,,t2", "expected comma-separated group labels"),
    ],
)
def test_cli_bad_groups_one_line_exit_2(tmp_path, two_contrasts, capsys, labels, message):
    paths = _write(tmp_path, two_contrasts.astype(np.float32))
    out = tmp_path / "spec.json"
    assert main(["specificity", *paths, "--groups", labels, "--json", str(out)]) == 2
    err = capsys.readouterr().err
    assert message in err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert not out.exists()


def test_two_contrast_population_true_registration_beats_none():
    # A generated T1/T2 population: the true registration of each contrast into the template
    # frame against the unregistered images, on common random numbers group by group.
    from data_synth.population import make_population, perfect_registration

    pop = make_population("phantom", dim=2, n=4, seed=2, contrasts=("t1", "t2"))
    groups = [c for c in pop.contrasts for _ in pop.subjects]
    true = [
        sitk.GetArrayFromImage(image)
        for c in pop.contrasts
        for image in perfect_registration(pop, contrast=c).images
    ]
    raw = [sitk.GetArrayFromImage(s.images[c]) for c in pop.contrasts for s in pop.subjects]
    cmp = nr.compare_specificity(np.stack(true), np.stack(raw), groups=groups, n_samples=4000)
    assert cmp.difference < -5 * cmp.difference_stderr
    # T1 and T2 clusters are far apart: every sample lands nearest its own contrast's images.
    np.testing.assert_array_equal(cmp.a.mixture.nearest_counts, np.diag(cmp.a.mixture.n_samples))
