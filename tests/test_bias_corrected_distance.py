"""The subjects' bias-corrected distance (issue 42): bias-corrected images and their distance to
the mean of the others, against brute-force references, and through ``evaluate`` on an
oblique, anisotropic 3D case not co-located with its reference."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import SimpleITK as sitk
from hypothesis import given, settings
from hypothesis import strategies as st
from test_orientation import make_moved_masked_case_3d

import itk_nrreval as nr
from itk_nrreval.measures._subject_measures import (
    CONCERN_TERMS,
    bias_corrected,
    concern_scores,
    others_mean_distances,
)


def _brute_force_local_mean(x, region, spacing, scale_mm):
    """The Gaussian-weighted mean over the region around each voxel, voxel by voxel:
    weights exp(-d^2 / 2 sigma^2) per axis within scipy's radius (4 sigma, rounded), in
    numpy axis order."""
    sigma = scale_mm / np.asarray(spacing, float)[::-1]
    radius = [int(4.0 * s + 0.5) for s in sigma]
    out = np.zeros(x.shape)
    for p in zip(*np.nonzero(region), strict=True):
        num = den = 0.0
        for q in zip(*np.nonzero(region), strict=True):
            d = [abs(a - b) for a, b in zip(p, q, strict=True)]
            if any(di > r for di, r in zip(d, radius, strict=True)):
                continue
            w = math.prod(math.exp(-0.5 * (di / s) ** 2) for di, s in zip(d, sigma, strict=True))
            num += w * x[q]
            den += w
        out[p] = num / den
    return out


def test_bias_corrected_is_the_image_over_its_region_weighted_local_mean():
    rng = np.random.default_rng(3)
    shape = (5, 6, 7)  # z, y, x
    spacing = (1.0, 1.5, 2.5)  # x, y, z: anisotropic
    x = rng.uniform(50.0, 150.0, shape)
    region = rng.random(shape) < 0.6
    local = _brute_force_local_mean(x, region, spacing, 3.0)
    want = np.where(region, x / np.where(region, local, 1.0), 0.0)
    got = bias_corrected(x, region, spacing=spacing, scale_mm=3.0)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=0)  # computed in float32


def test_bias_corrected_takes_away_a_gain_and_a_smooth_bias():
    """Two images of one anatomy under different gains and a smooth multiplicative bias are
    nearly the same after correction, while the raw images are far apart."""
    rng = np.random.default_rng(1)
    shape = (40, 48)
    yy, xx = np.mgrid[: shape[0], : shape[1]] * 1.0
    anatomy = 100.0 + 40.0 * (((xx - 24) ** 2 + (yy - 20) ** 2) < 100) + rng.normal(0, 1, shape)
    bias = np.exp(0.3 * np.sin(xx / 40.0) + 0.2 * np.cos(yy / 35.0))  # varies over ~100 mm
    region = np.ones(shape, bool)
    a = bias_corrected(anatomy, region, spacing=(1.0, 1.0))
    b = bias_corrected(1.7 * bias * anatomy, region, spacing=(1.0, 1.0))
    raw = np.linalg.norm(1.7 * bias * anatomy / np.mean(anatomy) - anatomy / np.mean(anatomy))
    assert np.linalg.norm(a - b) < 0.1 * raw
    # a gain alone is taken away exactly
    np.testing.assert_allclose(
        bias_corrected(3.0 * anatomy, region, spacing=(1.0, 1.0)), a, rtol=1e-5
    )


def test_bias_corrected_rejects_a_region_of_another_shape():
    with pytest.raises(ValueError, match="shape"):
        bias_corrected(np.ones((4, 5)), np.ones((5, 4), bool), spacing=(1.0, 1.0))


@settings(max_examples=30, deadline=None)
@given(n=st.integers(2, 9), v=st.integers(1, 40), seed=st.integers(0, 10_000))
def test_others_mean_distances_are_the_distances_to_the_others_mean(n, v, seed):
    h = np.random.default_rng(seed).normal(size=(n, v))
    centred = h - h.mean(axis=0)
    got = others_mean_distances(np.einsum("iv,iv->i", centred, centred))
    want = [np.linalg.norm(h[k] - np.delete(h, k, axis=0).mean(axis=0)) for k in range(n)]
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-12)


def test_the_concern_takes_the_corrected_z_not_the_model_distance():
    keys = {t.key for t in CONCERN_TERMS}
    assert "corrected_z" in keys and "z" not in keys
    concern, _ = concern_scores({"corrected_z": [2.0], "z": [100.0]})
    assert concern[0] == pytest.approx(2.0)  # the model distance is no term of it


def test_evaluate_reports_each_subjects_bias_corrected_distance(tmp_path):
    """Oblique, anisotropic 3D images not co-located with their reference: every subject's
    bias-corrected distance in results equals the one recomputed from the exported resampled
    images and the region, and its z enters the concern."""
    # a mask (the phantom, dilated), so that the local means are taken inside a region
    folder = make_moved_masked_case_3d(tmp_path)
    cache = tmp_path / "cache"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        result = nr.evaluate(
            folder / "manifest.yaml",
            n_samples=1000,
            seed=0,
            confidence=False,
            progress=False,
            execution=nr.Execution(cache=cache, keep_resampled=True),
        )
    out = nr.export_resampled(result, tmp_path / "resampled", cache=cache)
    region_image = sitk.ReadImage(str(out / "region.nii.gz"))
    region = sitk.GetArrayFromImage(region_image) > 0
    assert 0.1 < region.mean() < 1.0
    for name, scores in result.scores.items():
        images = [
            sitk.GetArrayFromImage(sitk.ReadImage(str(out / name / f"image_{q.index:03d}.nii.gz")))
            for q in scores.subjects
        ]
        corrected = np.stack(
            [bias_corrected(x, region, spacing=region_image.GetSpacing())[region] for x in images]
        )
        want = [
            np.linalg.norm(corrected[k] - np.delete(corrected, k, axis=0).mean(axis=0))
            for k in range(len(images))
        ]
        got = [q.corrected_distance for q in scores.subjects]
        # the cache holds the resampled and the corrected images in float32
        np.testing.assert_allclose(got, want, rtol=1e-4)
        assert all(q.corrected_z is not None for q in scores.subjects)
