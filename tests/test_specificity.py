"""Specificity and generalization against brute-force image-space references."""

from __future__ import annotations

import math

import numpy as np
import pytest
import SimpleITK as sitk
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats
from scipy.spatial.distance import cdist, pdist

import itk_nrreval as nr
from itk_nrreval.cli import main
from itk_nrreval.measures import _search


def _image_space_samples(images: np.ndarray, model: nr.TextureModel, z: np.ndarray) -> np.ndarray:
    """Samples mean + P b in image space, with the modes P recovered from the data alone."""
    flat = images.reshape(images.shape[0], -1)
    centred = flat - flat.mean(axis=0)
    # centred = B P^T, so P^T = pinv(B) centred: no use of the model's internals but b.
    modes_t = np.linalg.pinv(model.training_params) @ centred
    np.testing.assert_allclose(modes_t @ modes_t.T, np.eye(model.n_modes), atol=1e-9)
    b = z * np.sqrt(model.mode_variances)
    return flat.mean(axis=0) + b @ modes_t


def test_training_distances_are_preserved(small_images):
    model = nr.TextureModel.from_images(small_images)
    flat = small_images.reshape(10, -1)
    np.testing.assert_allclose(pdist(model.training_params), pdist(flat), rtol=1e-10)
    np.testing.assert_allclose(
        pdist(model.training_params, "sqeuclidean"), pdist(flat, "sqeuclidean"), rtol=1e-10
    )


def test_mode_variances_are_the_unbiased_covariance_eigenvalues(small_images):
    model = nr.TextureModel.from_images(small_images)
    flat = small_images.reshape(10, -1)
    sv = np.linalg.svd(flat - flat.mean(axis=0), compute_uv=False)
    assert model.n_modes == 9
    np.testing.assert_allclose(model.mode_variances, sv[:9] ** 2 / 9, rtol=1e-10)
    np.testing.assert_allclose(model.mean, flat.mean(axis=0), rtol=1e-12)


@pytest.mark.parametrize("exponent", [1.0, 2.0, 0.5])
def test_l2_specificity_equals_image_space_distances(small_images, exponent):
    m = 3000
    model = nr.TextureModel.from_images(small_images)
    r = nr.specificity(model, n_samples=m, distance="l2", exponent=exponent, seed=7)
    z = _search.sampling.standard_normals(7, 0, m, model.n_modes)
    samples = _image_space_samples(small_images, model, z)
    d = cdist(samples, small_images.reshape(10, -1))
    per_sample = d.min(axis=1) ** exponent
    assert r.value == pytest.approx(per_sample.mean(), rel=1e-9)
    assert r.stderr == pytest.approx(per_sample.std() / math.sqrt(m - 1), rel=1e-7)
    np.testing.assert_array_equal(r.nearest_counts, np.bincount(d.argmin(axis=1), minlength=10))
    assert r.nearest_counts.sum() == m


def test_l1_specificity_and_generalization_match_brute_force(small_images):
    m = 5000  # not a multiple of the chunk size
    model = nr.TextureModel.from_images(small_images)
    spec, gen = nr.texture_measures(model, n_samples=m, distance="l1", seed=3)
    samples = _search.sampling.standard_normals(3, 0, m, model.n_modes) * np.sqrt(
        model.mode_variances
    )
    d = np.abs(samples[:, None, :] - model.training_params[None]).sum(axis=2)
    assert spec.value == pytest.approx(d.min(axis=1).mean(), rel=1e-12)
    assert spec.stderr == pytest.approx(d.min(axis=1).std() / math.sqrt(m - 1), rel=1e-9)
    np.testing.assert_allclose(gen.nearest_distances, d.min(axis=0), rtol=1e-12)
    assert gen.value == pytest.approx(d.min(axis=0).mean(), rel=1e-12)
    assert gen.stderr == pytest.approx(d.min(axis=0).std() / math.sqrt(9), rel=1e-9)
    assert nr.generalization(model, n_samples=m, seed=3).value == gen.value


def test_same_seed_same_numbers_other_seed_other_numbers(small_images):
    a = nr.specificity(small_images, n_samples=2000, seed=11)
    b = nr.specificity(small_images, n_samples=2000, seed=11)
    c = nr.specificity(small_images, n_samples=2000, seed=12)
    assert (a.value, a.stderr) == (b.value, b.stderr)
    np.testing.assert_array_equal(a.nearest_counts, b.nearest_counts)
    assert a.value != c.value


def test_results_do_not_depend_on_thread_count(small_images):
    import numba

    before = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = nr.specificity(small_images, n_samples=20_000, seed=5)
    finally:
        numba.set_num_threads(before)
    many = nr.specificity(small_images, n_samples=20_000, seed=5)
    assert one.value == pytest.approx(many.value, rel=1e-13)
    np.testing.assert_array_equal(one.nearest_counts, many.nearest_counts)


def test_standard_normals_are_standard_normal_and_independent():
    z = _search.sampling.standard_normals(0, 0, 40_000, 5)
    assert stats.kstest(z.ravel(), "norm").pvalue > 1e-3
    corr = np.corrcoef(z.T)
    assert np.abs(corr - np.eye(5)).max() < 0.03
    # Consecutive samples are not correlated either.
    assert abs(np.corrcoef(z[:-1, 0], z[1:, 0])[0, 1]) < 0.03


def test_standard_normal_tails_follow_the_normal_law():
    # Draws beyond the ziggurat's base strip (|z| > 3.654) take the tail path.
    z = _search.sampling.standard_normals(9, 0, 50_000, 20).ravel()
    for t in (2.0, 3.0, 3.654):
        expected = 2 * stats.norm.sf(t) * z.size
        observed = np.count_nonzero(np.abs(z) > t)
        assert abs(observed - expected) < 5 * np.sqrt(expected), t
    assert np.abs(z).max() > 3.654


def test_common_random_numbers_share_normals_across_models():
    # A sample's first modes do not depend on how many modes the model has.
    a = _search.sampling.standard_normals(4, 100, 110, 3)
    b = _search.sampling.standard_normals(4, 100, 110, 8)
    np.testing.assert_array_equal(a, b[:, :3])


def test_compare_specificity_pairs_on_common_random_numbers(small_images, rng):
    other = small_images + 0.3 * rng.normal(size=small_images.shape)
    cmp = nr.compare_specificity(small_images, other, n_samples=4000, seed=2)
    a = nr.specificity(small_images, n_samples=4000, seed=2)
    b = nr.specificity(other, n_samples=4000, seed=2)
    assert cmp.a.value == pytest.approx(a.value, rel=1e-12)
    assert cmp.b.value == pytest.approx(b.value, rel=1e-12)
    np.testing.assert_array_equal(cmp.b.nearest_counts, b.nearest_counts)
    assert cmp.difference == pytest.approx(a.value - b.value, rel=1e-9)
    # Scaled copies see exactly proportional samples, so the paired spread is tiny.
    scaled = nr.compare_specificity(small_images, 1.1 * small_images, n_samples=4000, seed=2)
    assert scaled.difference == pytest.approx(-0.1 * scaled.a.value, rel=1e-9)
    assert scaled.difference_stderr == pytest.approx(0.1 * scaled.a.stderr, rel=1e-7)


def test_loo_generalization_matches_image_space_reconstruction(small_images):
    flat = small_images.reshape(10, -1)
    expected = []
    for i in range(10):
        rest = np.delete(flat, i, axis=0)
        centre = rest.mean(axis=0)
        _, _, vt = np.linalg.svd(rest - centre, full_matrices=False)
        modes = vt[:8]
        r = flat[i] - centre
        expected.append(np.linalg.norm(r - modes.T @ (modes @ r)))
    g = nr.loo_generalization(small_images)
    np.testing.assert_allclose(g.nearest_distances, expected, rtol=1e-8)
    assert g.stderr == pytest.approx(np.std(expected) / 3.0, rel=1e-8)
    # Fewer modes can only reconstruct worse.
    assert nr.loo_generalization(small_images, n_modes=2).value > g.value


def test_mask_selects_voxels(small_images, rng):
    mask = rng.random(small_images.shape[1:]) > 0.4
    masked = nr.specificity(small_images, n_samples=3000, seed=1, mask=mask)
    direct = nr.specificity(small_images[:, mask][:, :, None], n_samples=3000, seed=1)
    assert masked.value == pytest.approx(direct.value, rel=1e-9)


@settings(max_examples=15, deadline=None)
@given(
    n=st.integers(3, 12),
    shift=st.floats(-100, 100),
    scale=st.floats(0.1, 10),
    seed=st.integers(0, 2**32),
)
def test_specificity_is_shift_invariant_and_scales_linearly(n, shift, scale, seed):
    images = np.random.default_rng(seed).normal(size=(n, 6, 5))
    base = nr.specificity(images, n_samples=500, seed=seed)
    moved = nr.specificity(scale * images + shift, n_samples=500, seed=seed)
    assert moved.value == pytest.approx(scale * base.value, rel=1e-7)
    np.testing.assert_array_equal(base.nearest_counts, moved.nearest_counts)


def _write_images(tmp_path, images, spacing=(1.0, 1.0)):
    paths = []
    for i, arr in enumerate(images):
        img = sitk.GetImageFromArray(arr)
        img.SetSpacing(spacing)
        path = tmp_path / f"s{i:02d}.nii.gz"
        sitk.WriteImage(img, str(path))
        paths.append(str(path))
    return paths


def test_files_and_sitk_images_give_the_array_result(tmp_path, small_images):
    paths = _write_images(tmp_path, small_images.astype(np.float32))
    ref = nr.specificity(small_images.astype(np.float32), n_samples=1000, seed=0)
    assert nr.specificity(paths, n_samples=1000, seed=0).value == pytest.approx(ref.value)
    sitk_images = [sitk.ReadImage(p) for p in paths]
    assert nr.specificity(sitk_images, n_samples=1000, seed=0).value == pytest.approx(ref.value)


def test_degenerate_inputs_are_refused(small_images):
    with pytest.raises(nr.InputError, match="at least 3 images"):
        nr.specificity(small_images[:2])
    with pytest.raises(nr.InputError, match="identical"):
        nr.specificity(np.repeat(small_images[:1], 4, axis=0))
    bad = small_images.copy()
    bad[3, 0, 0] = np.nan
    with pytest.raises(nr.InputError, match=r"image\[3\]: contains NaN"):
        nr.specificity(bad)
    with pytest.raises(ValueError, match="distance must be one of"):
        nr.specificity(small_images, distance="cosine")
    with pytest.raises(ValueError, match=r"n_samples must be an integer in \[2, 2\*\*36\)"):
        nr.specificity(small_images, n_samples=1)


def test_an_image_given_twice_or_a_constant_image_is_refused_by_the_library(small_images):
    """What ``nrreval specificity`` refuses, the library refuses too: an image given twice
    (a subject weighs twice in the model, and the model's samples fall near it twice as
    often: a lower specificity, silently) and a constant image (no texture). Both were
    scored without a word through specificity(), texture_measures() and
    TextureModel.from_images()."""
    twice = small_images.copy()
    twice[4] = twice[1]
    for call in (nr.specificity, nr.texture_measures, nr.TextureModel.from_images):
        with pytest.raises(nr.InputError, match=r"images\[4\] is the same as images\[1\]"):
            call(twice)
    flat = small_images.copy()
    flat[2] = 7.0
    with pytest.raises(nr.InputError, match=r"images\[2\] is constant"):
        nr.specificity(flat)
    # a mask that leaves only voxels where two images agree: the same, where it is scored
    mask = np.zeros(small_images.shape[1:], bool)
    mask[0, :3] = True
    twice_inside = small_images.copy()
    twice_inside[4][mask] = twice_inside[1][mask]
    with pytest.raises(nr.InputError, match=r"images\[4\] is the same as images\[1\]"):
        nr.TextureModel.from_images(twice_inside, mask=mask)
    nr.TextureModel.from_images(twice_inside)  # they differ outside it


def test_images_on_different_grids_name_the_first_offender(tmp_path, small_images):
    paths = _write_images(tmp_path, small_images)
    sitk.WriteImage(sitk.GetImageFromArray(small_images[4][:, :-1]), paths[4])  # a different size
    with pytest.raises(
        nr.InputError, match=r"s04\.nii\.gz: not on the grid of .*s00\.nii\.gz: size"
    ):
        nr.specificity(paths)


def test_cli_prints_and_writes_json(tmp_path, small_images, capsys):
    paths = _write_images(tmp_path, small_images)
    out = tmp_path / "spec.json"
    assert (
        main(["specificity", *paths, "--samples", "2000", "--seed", "4", "--json", str(out)]) == 0
    )
    printed = capsys.readouterr().out
    expected = nr.specificity(paths, n_samples=2000, seed=4)
    assert f"specificity = {expected.value:.6g} ± " in printed
    assert "(2000 samples, 10 images)" in printed
    import json

    data = json.loads(out.read_text())
    assert data["specificity"]["value"] == expected.value
    assert sum(data["specificity"]["nearest_counts"]) == 2000


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda paths: paths[:2], "at least 3 images"),
        (lambda paths: [*paths[:3], "missing.nii.gz"], "missing.nii.gz: image file not found"),
    ],
)
def test_cli_bad_input_is_one_line_exit_2(tmp_path, small_images, capsys, mutate, message):
    paths = _write_images(tmp_path, small_images)
    out = tmp_path / "spec.json"
    assert main(["specificity", *mutate(paths), "--json", str(out)]) == 2
    err = capsys.readouterr().err
    assert message in err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert not out.exists()


def test_cli_unreadable_file(tmp_path, small_images, capsys):
    paths = _write_images(tmp_path, small_images)
    (tmp_path / "junk.nii.gz").write_bytes(b"not an image")
    assert main(["specificity", *paths, str(tmp_path / "junk.nii.gz")]) == 2
    err = capsys.readouterr().err
    # the message evaluate's manifest check gives for the same file
    assert "junk.nii.gz" in err and "truncated or corrupt" in err
    assert len(err.strip().splitlines()) == 1


def test_non_finite_check_is_not_fooled_by_overflowing_sums():
    from itk_nrreval.io._images import image_stack

    big = np.full((4, 8, 8), 1e307)  # finite, but each image's sum overflows to inf
    big[1:] *= np.linspace(0.1, 0.9, 64).reshape(8, 8)
    with np.errstate(over="ignore"):
        assert np.isinf(big.reshape(4, -1).sum(axis=1)).all()
    assert image_stack(big).data.shape == (4, 8, 8)
    big[2, 3, 3] = -np.inf
    with pytest.raises(nr.InputError, match=r"image\[2\]: contains NaN or infinite"):
        image_stack(big)
