"""The subjects' bias-corrected distance (issue 42): bias-corrected images and their distance to
the mean of the others, against brute-force references, and through ``evaluate`` on an
oblique, anisotropic 3D case not co-located with its reference."""

from __future__ import annotations

import argparse
import math
import warnings

import numpy as np
import pytest
import SimpleITK as sitk
from hypothesis import given, settings
from hypothesis import strategies as st
from test_orientation import make_moved_masked_case_3d
from test_subject_qc import bump_field

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


def _distances_from_export(out, name: str, indices) -> np.ndarray:
    """Each subject's bias-corrected distance to the mean of the others, recomputed from
    `export_resampled`'s folder `out`: registration `name`'s images of `indices`, corrected
    over the exported region and compared over it (brute force, one subject at a time)."""
    region_image = sitk.ReadImage(str(out / "region.nii.gz"))
    region = sitk.GetArrayFromImage(region_image) > 0
    corrected = np.stack(
        [
            bias_corrected(
                sitk.GetArrayFromImage(sitk.ReadImage(str(out / name / f"image_{i:03d}.nii.gz"))),
                region,
                spacing=region_image.GetSpacing(),
            )[region]
            for i in indices
        ]
    )
    return np.array(
        [
            np.linalg.norm(corrected[k] - np.delete(corrected, k, axis=0).mean(axis=0))
            for k in range(len(corrected))
        ]
    )


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
    region = sitk.GetArrayFromImage(sitk.ReadImage(str(out / "region.nii.gz"))) > 0
    assert 0.1 < region.mean() < 1.0
    for name, scores in result.scores.items():
        want = _distances_from_export(out, name, [q.index for q in scores.subjects])
        got = [q.corrected_distance for q in scores.subjects]
        # the cache holds the resampled and the corrected images in float32
        np.testing.assert_allclose(got, want, rtol=1e-4)
        assert all(q.corrected_z is not None for q in scores.subjects)


# ------------------------------------------------------- the flag on the corrected distance


def test_a_misregistered_subject_is_flagged_and_a_gain_and_bias_is_not(tmp_path):
    """Issue 42: a subject whose bias-corrected distance to the others' mean is more than
    `corrected_ratio` (1.4) times the cohort's median is flagged. A generated cohort of 16
    registered by its true transforms, but subject 5's composed with a smooth local shift
    of 4 mm (no fold) and subject 9's image given a gain of 1.6 and a smooth bias of 30%
    (its registration is right). The flags are recomputed from the exported resampled images
    (each subject's distance to the others' mean, bias-corrected, over the median of the
    others but the reference, subject 0); subject 5 is flagged and subject 9 is not, and a
    threshold of 10 flags no one."""
    from data_synth import make_population

    pop = make_population("phantom", dim=2, n=16, seed=5, size=40)
    images = []
    for i, s in enumerate(pop.subjects):
        image = s.image
        if i == 9:
            arr = sitk.GetArrayFromImage(image).astype(np.float64)
            x = np.indices(arr.shape)[1] / (arr.shape[1] - 1)
            image = sitk.GetImageFromArray(arr * 1.6 * (1.0 + 0.3 * x))
            image.CopyInformation(s.image)
        images.append(str(tmp_path / f"s{i:02d}.nii.gz"))
        sitk.WriteImage(image, images[-1])
    template = str(tmp_path / "template.nii.gz")
    sitk.WriteImage(pop.template, template)
    chains = [[s.template_to_subject] for s in pop.subjects]
    # a steepest slope of 4 / 8 * exp(-1/2) = 0.3: it misregisters, it does not fold
    chains[5] = [bump_field(pop.template, amplitude_mm=4.0, width_mm=8.0), *chains[5]]
    manifest = {
        "images": images,
        "registrations": {"shifted": {"reference": template, "transforms": chains}},
    }

    def flagged(threshold: float, cache=None):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = nr.evaluate(
                manifest,
                n_samples=200,
                confidence=False,
                progress=False,
                subject_thresholds=nr.SubjectThresholds(corrected_ratio=threshold),
                execution=nr.Execution(cache=cache, keep_resampled=cache is not None),
            )
        subjects = result.scores["shifted"].subjects
        kinds = {
            q.index
            for q in subjects
            if any(f.startswith("far from the others once gain and bias") for f in q.flags)
        }
        return result, kinds

    cache = tmp_path / "cache"
    result, kinds = flagged(1.4, cache)
    out = nr.export_resampled(result, tmp_path / "resampled", cache=cache)
    distance = _distances_from_export(out, "shifted", range(16))
    # no reference among the subjects (the template is): the median over all of them
    ratio = distance / np.median(distance)
    assert ratio[5] > 1.4 and ratio[9] < 1.4  # the premise, measured independently
    assert kinds == set(np.flatnonzero(ratio > 1.4)), ratio
    assert 5 in kinds and 9 not in kinds
    flags = result.scores["shifted"].subjects[5].flags
    words = next(f for f in flags if f.startswith("far from the others"))
    assert f"{ratio[5]:.2f}x the cohort's median" in words
    assert flagged(10.0)[1] == set()
    assert flagged(None)[1] == set()  # the default: off
    assert nr.SubjectThresholds().corrected_ratio is None


def test_the_reference_is_neither_flagged_for_its_distance_nor_in_the_median():
    """assess_subjects on numbers: the corrected distances come from centred sums of squares
    of vectors made here, one subject far off and the reference (subject 0) farther still.
    The median the others are judged by leaves the reference out (brute force below), and
    the reference is never flagged."""
    from itk_nrreval.measures.subject_qc import assess_subjects

    rng = np.random.default_rng(7)
    n, v = 10, 500
    h = 1.0 + 0.05 * rng.standard_normal((n, v))
    h[0] += 0.4 * rng.standard_normal(v)  # the reference: far from everyone
    h[6] += 0.11 * rng.standard_normal(v)  # one subject far off
    squares = ((h - h.mean(axis=0)) ** 2).sum(axis=1)
    distance = np.array(
        [np.linalg.norm(h[k] - np.delete(h, k, axis=0).mean(axis=0)) for k in range(n)]
    )
    ratio = distance / np.median(distance[1:])  # the reference left out
    expected = set(np.flatnonzero(ratio > 1.4)) - {0}
    assert 6 in expected and ratio[0] > 1.4  # the premise
    pixels = rng.standard_normal((n, 64))
    centred = pixels - pixels.mean(axis=0)
    deformation = {
        "folded_fraction": [0.0] * n,
        "sdlogj": [0.1] * n,
        "jacobian_min": [0.6] * n,
        "jacobian_max": [1.6] * n,
        "inverse_consistency_mm": [0.2] * n,
        "linear_det": [1.0] * n,
        "nonlinear_rms_mm": [2.0] * n,
        "displacement_rms_mm": [3.0] * n,
    }
    subjects = assess_subjects(
        images=[f"s{i}.nii.gz" for i in range(n)],
        scored=list(range(n)),
        gram=centred @ centred.T,
        deformation=deformation,
        coverage=[1.0] * n,
        reference=0,
        corrected_squares=squares,
        thresholds=nr.SubjectThresholds(corrected_ratio=1.4),
    )
    np.testing.assert_allclose([q.corrected_distance for q in subjects], distance, rtol=1e-10)
    got = {q.index for q in subjects if any(f.startswith("far from the others") for f in q.flags)}
    assert got == expected
    assert subjects[0].reference and subjects[0].flags == ()


def test_the_corrected_ratio_option_takes_a_ratio_above_one_or_off(capsys):
    from itk_nrreval.cli import build_parser

    parser = build_parser()

    def parsed(*extra):
        return parser.parse_args(["evaluate", "m.yaml", "--out", "o", *extra])

    assert parsed().subject_corrected_ratio is None
    assert parsed("--subject-corrected-ratio", "1.4").subject_corrected_ratio == 1.4
    assert parsed("--subject-corrected-ratio", "off").subject_corrected_ratio is None
    with pytest.raises(SystemExit):
        parsed("--subject-corrected-ratio", "0.9")
    assert "expected a number > 1, or off, got '0.9'" in capsys.readouterr().err
    commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    evaluate = commands.choices["evaluate"]._actions
    words = next(a.help for a in evaluate if a.dest == "subject_corrected_ratio")
    assert words.endswith("(default off)")
