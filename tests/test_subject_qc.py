"""Per-subject quality control (issue 27): which subjects' registrations failed, and why.

Real evaluate runs on a tiny generated cohort (data_synth) whose true registration is known,
with one subject per damage (data_synth.damage); references are computed independently, in
image space, from the resampled images evaluate saves.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
import re
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
from hypothesis import given, settings
from hypothesis import strategies as st

import itk_nrreval as nr
from data_synth import make_population
from data_synth.damage import DIAGNOSES, write_damaged
from itk_nrreval.io._images import InMemoryImage
from itk_nrreval.io.plausibility import affine_fit
from itk_nrreval.measures.subject_qc import robust_z, subject_overlaps

#: The cohort size the flag thresholds were set for (benchmarks/bench_subject_qc.py); at
#: N = 14 one clean subject of the seed below is twice as far from the others' model as the
#: median one (z = 6.4): with few subjects an unusual anatomy is an outlier too.
N = 36
DAMAGES = {2: "mirrored", 9: "affine_only", 16: "scaled", 23: "duplicated", 35: "off_grid"}


@pytest.fixture(scope="module")
def population():
    """One small 2D phantom cohort, with its true transforms both ways."""
    return make_population("phantom", dim=2, n=N, seed=4, size=40)


@pytest.fixture(scope="module")
def cohort(population, tmp_path_factory):
    """The clean and the damaged manifests of `population`."""
    folder = tmp_path_factory.mktemp("cohort")
    return write_damaged(population, folder, DAMAGES)


def _evaluate(manifest, out):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # coverage and flagged-registration warnings
        result = nr.evaluate(
            manifest,
            n_samples=200,
            confidence=False,
            progress=False,
            execution=nr.Execution(cache=out / "cache", keep_resampled=True),
        )
    result.write(out, figures=False)
    nr.export_resampled(result, out / "resampled", cache=out / "cache")
    return result


@pytest.fixture(scope="module")
def damaged(cohort, tmp_path_factory):
    out = tmp_path_factory.mktemp("damaged") / "out"
    return _evaluate(cohort[1], out), out


@pytest.fixture(scope="module")
def clean(cohort, tmp_path_factory):
    out = tmp_path_factory.mktemp("clean") / "out"
    return _evaluate(cohort[0], out), out


# ----------------------------------------------------------------------------- end to end


def test_a_subject_off_the_grid_is_left_out_and_the_rest_scored(damaged):
    result, _ = damaged
    subjects = result.scores["damaged"].subjects
    assert result.options["left_out_of_scores"] == [35]
    assert [q.in_scores for q in subjects] == [i != 35 for i in range(N)]
    assert subjects[35].score is None and subjects[35].coverage < 0.05
    assert math.isfinite(result.scores["damaged"].specificity.value)
    assert result.scores["damaged"].specificity.n_images == N - 1


def test_leave_one_out_score_is_the_distance_to_a_refitted_model(damaged):
    """Brute force in image space: for each scored subject, PCA of the others' resampled
    images (inside the evaluated region) with every mode, then the residual of its image."""
    result, out = damaged
    region = sitk.GetArrayFromImage(sitk.ReadImage(str(out / "resampled/region.nii.gz")))
    region = region.astype(bool)
    subjects = result.scores["damaged"].subjects
    scored = [q.index for q in subjects if q.in_scores]
    folder = out / "resampled/damaged"
    x = np.stack(
        [
            sitk.GetArrayFromImage(sitk.ReadImage(str(folder / f"image_{i:03d}.nii.gz")))[region]
            for i in scored
        ]
    )
    for row, i in enumerate(scored):
        others = np.delete(x, row, axis=0)
        mean = others.mean(axis=0)
        _, sv, vt = np.linalg.svd(others - mean, full_matrices=False)
        basis = vt[sv > sv[0] * 1e-10]
        r = x[row] - mean
        expected = np.linalg.norm(r - basis.T @ (basis @ r))
        assert subjects[i].score == pytest.approx(expected, rel=1e-6, abs=1e-9 * sv[0])


@pytest.mark.parametrize("index", sorted(DAMAGES))
def test_each_damaged_subject_is_flagged_and_diagnosed(damaged, index):
    q = damaged[0].scores["damaged"].subjects[index]
    assert q.flags
    assert DIAGNOSES[DAMAGES[index]] in q.diagnosis


def test_only_the_damaged_subjects_and_the_duplicated_ones_partner_are_flagged(damaged):
    flagged = {q.index for q in damaged[0].scores["damaged"].subjects if q.flags}
    partner = 22  # subject 23 is a copy of subject 22: the pair is flagged, either may be it
    assert flagged == set(DAMAGES) | {partner}
    assert "subject 23" in damaged[0].scores["damaged"].subjects[partner].diagnosis


def test_a_clean_cohort_flags_no_one(clean):
    result, _ = clean
    subjects = result.scores["truth"].subjects
    assert len(subjects) == N
    assert [q.flags for q in subjects] == [()] * N
    assert all(q.diagnosis is None and q.in_scores for q in subjects)
    assert result.options["left_out_of_scores"] == []


def test_an_inverse_consistency_error_too_small_to_matter_flags_no_one(tmp_path):
    """Issue 30: inverse consistency now inverts pointwise, without the interpolation of an
    inverse field, so smooth true fields measure 1e-4 mm or less; a subject at a few
    thousandths of a mm was then 20 times its cohort's median and z in the hundreds, and
    clean 2D cohorts of 36 at 64 pixels flagged 14 % of their subjects. Below a hundredth
    of a mm an inverse-consistency error is the numerical inverse's own."""
    pop = make_population("phantom", dim=2, n=N, seed=2, size=64)
    clean, _ = write_damaged(pop, tmp_path, {3: "mirrored"})
    result = _evaluate(clean, tmp_path / "out")
    subjects = result.scores["truth"].subjects
    ic = [q.deformation["inverse_consistency_mm"] for q in subjects]
    assert max(ic) < 0.01 and max(ic) > 2 * float(np.median(ic))  # spread, all tiny
    assert [q.flags for q in subjects] == [()] * N


def test_a_clean_3d_cohort_of_12_flags_no_one(tmp_path):
    """2 mm voxels, N = 12: its overlaps with the others lie within 0.009 of each other, so
    a subject 0.009 below the median had z = -7 without being any worse registered (the
    true transforms). Two guards: the overlap z-score's scale is at least 0.01 (issue 44),
    and a flag needs the overlap to be materially lower too (the ratio)."""
    pop = make_population("phantom", dim=3, n=12, seed=17, size=32)
    clean, _ = write_damaged(pop, tmp_path, {3: "mirrored"})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # coverage
        result = nr.evaluate(clean, n_samples=200, confidence=False, progress=False)
    subjects = result.scores["truth"].subjects
    overlaps = np.array([q.overlap for q in subjects])
    assert overlaps.max() - overlaps.min() < 0.02  # the premise: all alike
    assert min(robust_z(overlaps)) < -3.5  # ... yet far apart in z over their own MAD
    z = np.array([q.overlap_z for q in subjects])
    np.testing.assert_allclose(z, robust_z(overlaps, least_spread=0.01))
    assert min(z) > -3.5  # over a spread of at least 0.01, they are not
    assert [q.flags for q in subjects] == [()] * 12
    # the z alone (no ratio asked for) flags only the subjects far below the others in z
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        z_alone = nr.evaluate(
            clean,
            n_samples=200,
            confidence=False,
            progress=False,
            subject_thresholds=nr.SubjectThresholds(overlap_ratio=0.0),
        )
    flagged = {q.index for q in z_alone.scores["truth"].subjects if q.flags}
    assert flagged == {q.index for q in subjects if q.overlap_z < -3.5}


#: Transforms mixed up: subject 5's inverted, subjects 11 and 12 each with the other's.
MIXUPS = {5: "inverted", 12: "swapped"}


@pytest.fixture(scope="module")
def mixed_up(population, tmp_path_factory):
    folder = tmp_path_factory.mktemp("mixups")
    _, manifest = write_damaged(population, folder, MIXUPS)
    out = folder / "out"
    return _evaluate(manifest, out), out, folder


@pytest.mark.parametrize("index, damage", [(5, "inverted"), (11, "swapped"), (12, "swapped")])
def test_an_inverted_or_swapped_transform_is_flagged_and_diagnosed(mixed_up, index, damage):
    q = mixed_up[0].scores["damaged"].subjects[index]
    assert q.flags
    assert DIAGNOSES[damage] in q.diagnosis


def test_a_swap_names_the_other_subject_and_only_the_mixed_up_ones_are_flagged(mixed_up):
    subjects = mixed_up[0].scores["damaged"].subjects
    assert {q.index for q in subjects if q.flags} == {5, 11, 12}
    assert {q.index for q in subjects if q.better_fit is not None} == {5, 11, 12}
    assert "subject 12's image" in subjects[11].diagnosis
    assert "subject 11's image" in subjects[12].diagnosis


def _distance_to_span(x: np.ndarray, others: np.ndarray) -> float:
    """The Euclidean distance of `x` to the affine span of the rows of `others` (SVD)."""
    mean = others.mean(axis=0)
    _, sv, vt = np.linalg.svd(others - mean, full_matrices=False)
    basis = vt[sv > sv[0] * 1e-10]
    r = x - mean
    return float(np.linalg.norm(r - basis.T @ (basis @ r)))


def test_the_swap_and_inversion_ratios_are_brute_force_fits_in_image_space(mixed_up):
    """Independent of the Gram matrix and of the toolkit's inversion: the images resampled
    by SimpleITK through the population's own true transforms (subject 11's for subject 12's
    transform, which it is; subject 5's true one for the inverse of its inverted one),
    against a PCA of the others' saved resampled images inside the evaluated region."""
    result, out, folder = mixed_up
    subjects = result.scores["damaged"].subjects
    region = sitk.GetArrayFromImage(sitk.ReadImage(str(out / "resampled/region.nii.gz")))
    region = region.astype(bool)
    saved = out / "resampled/damaged"
    x = {
        i: sitk.GetArrayFromImage(sitk.ReadImage(str(saved / f"image_{i:03d}.nii.gz")))[region]
        for i in range(N)
    }
    template = sitk.ReadImage(str(folder / "truth/template.nii.gz"))

    def through(image: int, truth_of: int) -> np.ndarray:
        moving = sitk.ReadImage(str(folder / f"img/s{image:02d}.nii.gz"), sitk.sitkFloat64)
        t = sitk.ReadTransform(str(folder / f"truth/s{truth_of:02d}.h5"))
        return sitk.GetArrayFromImage(sitk.Resample(moving, template, t, sitk.sitkLinear))[region]

    # subject 12's transform is subject 11's true one: subject 11's image fits it
    others = np.stack([x[k] for k in range(N) if k not in (11, 12)])
    expected = _distance_to_span(x[12], others) / _distance_to_span(through(11, 11), others)
    assert subjects[12].better_fit == pytest.approx(expected, rel=1e-3)
    assert f"fits it {expected:.1f}x better" in subjects[12].diagnosis
    # the inverse of subject 5's inverted transform is (numerically) its true transform
    others = np.stack([x[k] for k in range(N) if k != 5])
    expected = _distance_to_span(x[5], others) / _distance_to_span(through(5, 5), others)
    assert expected > 2
    assert subjects[5].better_fit == pytest.approx(expected, rel=0.1)


def test_mixup_checks_in_chunks_of_one_alternative_give_the_same_fits(mixed_up, monkeypatch):
    """The changed images are resampled and reduced a bounded chunk at a time (64
    alternatives of a 1 mm region would be 2.5 GB at once): one at a time, the same fits."""
    from itk_nrreval._pipeline import _reduction

    monkeypatch.setattr(_reduction, "ALTERNATIVE_CHUNK_BYTES", 1)  # one alternative per chunk
    result, _, folder = mixed_up
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        again = nr.evaluate(
            folder / "damaged.yaml",
            n_samples=200,
            confidence=False,
            progress=False,
        )
    for q, r in zip(
        result.scores["damaged"].subjects, again.scores["damaged"].subjects, strict=True
    ):
        if q.better_fit is None:
            assert r.better_fit is None
        else:
            assert r.better_fit == pytest.approx(q.better_fit, rel=1e-9)
            assert r.diagnosis == q.diagnosis


def test_results_json_csv_and_summary_name_the_subjects(damaged):
    result, out = damaged
    entries = json.loads((out / "results.json").read_text())["registrations"]["damaged"]["subjects"]
    assert [e["index"] for e in entries] == list(range(N))
    assert set(entries[0]) >= {"index", "image", "score", "z", "plausibility", "overlap"}
    assert entries[2]["flags"] and "mirrored" in entries[2]["diagnosis"]
    assert entries[0]["diagnosis"] is None and entries[0]["flags"] == []
    assert entries[35]["score"] is None and entries[35]["in_scores"] is False
    with open(out / "subjects.csv", newline="") as f:
        rows = {int(r["index"]): r for r in csv.DictReader(f)}  # ranked: by index here
    assert sorted(rows) == list(range(N))
    assert rows[9]["diagnosis"].startswith("stopped early or affine only")
    assert float(rows[0]["score"]) == pytest.approx(entries[0]["score"])
    summary = (out / "summary.md").read_text()
    assert "6 of the 36 subjects flagged" in summary
    assert "Left out of every registration's scores (off the common grid): subject 35" in summary


def test_every_subject_threshold_has_an_evaluate_option_with_its_default():
    from itk_nrreval.cli import build_parser

    args = build_parser().parse_args(["evaluate", "m.yaml", "--out", "o"])
    fields = [f.name for f in dataclasses.fields(nr.SubjectThresholds)]
    assert {f: getattr(args, f"subject_{f}") for f in fields} == dataclasses.asdict(
        nr.SubjectThresholds()
    )


def test_subject_thresholds_from_the_command_line_decide_the_flags(cohort, tmp_path, capsys):
    """--subject-z 1 flags the subjects of the clean cohort whose model distance has z > 1,
    which the default 3.5 leaves alone; a ratio below 1 is refused in one line."""
    from itk_nrreval.cli import main

    out = tmp_path / "out"
    args = ["evaluate", str(cohort[0]), "--out", str(out), "--samples", "200", "--quiet"]
    args += ["--no-figures", "--no-confidence"]
    assert main([*args, "--subject-z", "1", "--subject-better-fit", "3"]) == 0
    res = json.loads((out / "results.json").read_text())
    assert res["options"]["subject_thresholds"]["outlier_z"] == 1.0
    assert res["options"]["subject_thresholds"]["better_fit_ratio"] == 3.0
    subjects = res["registrations"]["truth"]["subjects"]
    far = {e["index"] for e in subjects if e["z"] > 1}
    assert far and {e["index"] for e in subjects if e["flags"]} >= far
    capsys.readouterr()
    assert main([*args, "--subject-better-fit", "0.5"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert "--subject-better-fit: expected a number >= 1, got '0.5'" in err


# ----------------------------------------------------------------------------- the numerics


def test_robust_z_of_a_normal_sample_is_about_standard():
    x = np.random.default_rng(0).normal(5.0, 2.0, 20_000)
    z = robust_z(x)
    assert np.median(z) == pytest.approx(0.0, abs=0.03)
    assert np.std(z) == pytest.approx(1.0, abs=0.03)
    assert robust_z([1.0, 1.0, 1.0, 2.0]).tolist() == [0.0, 0.0, 0.0, math.inf]
    assert np.isnan(robust_z([1.0, math.nan, 2.0, 3.0])[1])


def test_subject_overlaps_match_pairwise_minima_and_maxima():
    rng = np.random.default_rng(1)
    a = rng.uniform(size=(5, 3, 40)) ** 3  # 5 images, 3 labels, 40 voxels of memberships
    weights = np.array([1.0, 0.5, 2.0])
    vol = a.sum(axis=2)
    target = np.zeros((5, 3))
    mins, maxs = np.zeros(5), np.zeros(5)
    for i in range(5):
        for j in range(5):
            if j == i:
                continue
            for k in range(3):
                low = np.minimum(a[i, k], a[j, k]).sum()
                target[i, k] += low
                mins[i] += weights[k] * low
                maxs[i] += weights[k] * np.maximum(a[i, k], a[j, k]).sum()
    expected = mins / maxs
    assert subject_overlaps(vol, target, weights) == pytest.approx(expected, rel=1e-12)


def test_affine_fit_recovers_a_mirroring_affine_map_and_a_field():
    grid = nr.io._images.Geometry((20, 16), (1.5, 1.0), (3.0, -2.0), (0.0, 1.0, -1.0, 0.0))
    t = sitk.AffineTransform(2)
    t.SetMatrix((-1.1, 0.2, 0.1, 0.9))
    t.SetTranslation((4.0, -3.0))
    fit = affine_fit(t, grid)
    assert fit.linear_det == pytest.approx(-1.1 * 0.9 - 0.2 * 0.1, rel=1e-9)
    assert fit.nonlinear_rms_mm < 1e-6
    u = np.random.default_rng(2).normal(size=(16, 20, 2))
    field = sitk.GetImageFromArray(u, isVector=True)
    grid.apply_to(field)
    fit = affine_fit(sitk.DisplacementFieldTransform(field), grid, max_slab_voxels=50)
    # the residual of white noise on its best affine fit, by numpy least squares
    idx = np.indices((16, 20)).reshape(2, -1)[::-1].T
    d = np.asarray(grid.direction).reshape(2, 2)
    p = np.asarray(grid.origin) + (idx * grid.spacing) @ d.T
    design = np.hstack([p, np.ones((p.shape[0], 1))])
    coef, *_ = np.linalg.lstsq(design, u.reshape(-1, 2), rcond=None)
    residual = u.reshape(-1, 2) - design @ coef
    assert fit.nonlinear_rms_mm == pytest.approx(np.sqrt((residual**2).sum(1).mean()), rel=1e-9)
    assert fit.displacement_rms_mm == pytest.approx(np.sqrt((u**2).sum(-1).mean()), rel=1e-12)


def test_the_jackknife_runs_over_the_subjects_in_the_scores(cohort, tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = nr.evaluate(
            cohort[1],
            n_samples=100,
            confidence=nr.Confidence(samples=100),
            progress=False,
            execution=nr.Execution(cache=tmp_path),
        )
    assert result.options["resamples"] == N - 1  # leave-one-out over the 35 scored subjects
    assert math.isfinite(result.scores["damaged"].intervals["specificity"].lo)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(4, 30), extra=st.integers(0, 40))
def test_leave_one_out_distances_equal_refitting_each_model(seed, n, extra):
    """The closed form (one eigendecomposition) against refitting the model of the others
    for every subject (loo_generalization, an SVD each), on random images."""
    from itk_nrreval.measures.specificity import loo_generalization
    from itk_nrreval.measures.subject_qc import leave_one_out_distances

    rng = np.random.default_rng(seed)
    images = rng.normal(size=(n, n + extra)) * rng.uniform(0.1, 10)
    centred = images - images.mean(axis=0)
    fast = leave_one_out_distances(centred @ centred.T)
    slow = loo_generalization(images).nearest_distances
    np.testing.assert_allclose(fast, slow, rtol=1e-6, atol=1e-9 * np.abs(slow).max())


def test_leave_one_out_distance_of_a_duplicated_image_is_zero():
    from itk_nrreval.measures.subject_qc import leave_one_out_distances

    rng = np.random.default_rng(1)
    images = rng.normal(size=(8, 30))
    images[5] = images[2]
    centred = images - images.mean(axis=0)
    d = leave_one_out_distances(centred @ centred.T)
    assert d[5] < 1e-6 and d[2] < 1e-6 and d[0] > 1


def test_left_out_under_another_registration_is_said_as_such(cohort, tmp_path):
    """Subject 35 is off the grid under 'damaged' only: under 'truth' it covers the grid, is
    left out all the same (one region for every registration), and the flag says why;
    its own transform is not blamed. A near-copy is named with its distance to the original."""
    import yaml

    clean, damaged = (yaml.safe_load(open(p)) for p in cohort)
    both = {**damaged, "registrations": {**clean["registrations"], **damaged["registrations"]}}
    manifest = tmp_path / "both.yaml"
    base = cohort[0].parent
    manifest.write_text(yaml.safe_dump(both))
    for name in ("img", "lab", "truth", "damaged"):  # the manifests' relative paths
        if (base / name).exists():
            (tmp_path / name).symlink_to(base / name)
    result = _evaluate(manifest, tmp_path / "out")
    truth = result.scores["truth"].subjects[35]
    assert not truth.in_scores
    assert truth.flags == (
        f"left out of the scores: another registration maps it off the common grid "
        f"(it covers {truth.coverage:.0%} here)",
    )
    assert truth.diagnosis is None
    assert "off the common grid" in result.scores["damaged"].subjects[35].diagnosis
    flags = result.scores["damaged"].subjects[23].flags
    # a near-copy (an exact one is refused by the manifest's check): named with its distance
    (flag,) = [f for f in flags if "subject 22's" in f]
    assert re.fullmatch(
        r"its resampled image is 0\.00\d+x the median pairwise distance from subject 22's", flag
    ), flag


def test_an_image_that_stands_out_under_every_registration_is_named_as_such(cohort, tmp_path):
    """Subject 5's image with its contrast inverted: far from the model under both
    registrations (the true one and a copy of it), so its diagnosis blames the image, not a
    registration; the clean subjects stay unflagged."""
    import shutil

    import yaml

    base = cohort[0].parent
    for name in ("img", "lab", "truth"):
        shutil.copytree(base / name, tmp_path / name)
    odd = tmp_path / "img" / "s05.nii.gz"
    image = sitk.ReadImage(str(odd))
    array = sitk.GetArrayFromImage(image)
    inverted = sitk.GetImageFromArray(array.max() - array)
    inverted.CopyInformation(image)
    sitk.WriteImage(inverted, str(odd))
    data = yaml.safe_load(open(cohort[0]))
    data["registrations"]["truth_again"] = data["registrations"]["truth"]
    (tmp_path / "two.yaml").write_text(yaml.safe_dump(data))
    result = _evaluate(tmp_path / "two.yaml", tmp_path / "out")
    for name in ("truth", "truth_again"):
        subjects = result.scores[name].subjects
        assert subjects[5].z > 3.5
        assert subjects[5].diagnosis.startswith("far from the model under every registration")
        assert not [q.index for q in subjects if q.flags and q.index != 5]


def test_each_subjects_frame_estimate_deviation_is_reported(tmp_path):
    """Registration b = registration a after a translation t_i of subject i: F_i(p) = p + t_i
    exactly, F = p + mean(t), so subject i's deviation is |t_i - mean(t)| at every voxel."""
    import yaml

    from data_synth import write_population

    pop = make_population("phantom", dim=2, n=8, seed=2, size=32)
    manifest = write_population(pop, tmp_path / "data", montage=False, progress=False)
    data = yaml.safe_load(manifest.read_text())
    folder = manifest.parent
    shifts = np.random.default_rng(3).uniform(-2, 2, size=(8, 2))
    truth = [
        sitk.ReadTransform(str(folder / t)) for t in data["registrations"]["truth"]["transforms"]
    ]
    shifted = [
        [sitk.TranslationTransform(2, tuple(-shift)), t]
        for shift, t in zip(shifts, truth, strict=True)
    ]
    m = {
        "images": [str(folder / p) for p in data["images"]],
        "registrations": {
            "truth": {
                "reference": str(folder / data["registrations"]["truth"]["reference"]),
                "transforms": truth,
            },
            "shifted": {
                "reference": str(folder / data["registrations"]["truth"]["reference"]),
                "transforms": shifted,
            },
        },
    }
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = nr.evaluate(m, n_samples=200, confidence=False, progress=False)
    expected = np.linalg.norm(shifts - shifts.mean(axis=0), axis=1)
    got = [q.deformation["frame_deviation_mm"] for q in result.scores["shifted"].subjects]
    # b's inverse is numerical (the true transforms are fields): within 0.015 mm
    np.testing.assert_allclose(got, expected, rtol=0, atol=0.015)
    z = [q.deformation["frame_deviation_z"] for q in result.scores["shifted"].subjects]
    np.testing.assert_allclose(z, robust_z(got, log=True, floor=1e-3))
    # the common registration has no estimate of its own frame
    assert all(q.deformation["frame_deviation_mm"] is None for q in result.scores["truth"].subjects)
    assert result.scores["shifted"].frame.spread_mean_mm == pytest.approx(
        np.mean(expected), abs=0.015
    )


# ----------------------------------------------------------------------------- issue 44


def _cohort_numbers(ic_mm, seed=0):
    """One registration's per-subject numbers as assess_subjects takes them: a Gram matrix
    of generated phantom images (the cohort's own texture), deformation measures of the
    size a good registration has, and the inverse-consistency errors given."""
    n = len(ic_mm)
    pop = make_population("phantom", dim=2, n=n, seed=seed, size=32)
    flat = np.stack([sitk.GetArrayFromImage(s.image).ravel() for s in pop.subjects])
    centred = flat - flat.mean(axis=0)
    rng = np.random.default_rng(seed)
    deformation = {
        "folded_fraction": [0.0] * n,
        "sdlogj": list(0.1 * np.exp(0.2 * rng.standard_normal(n))),
        "jacobian_min": [0.6] * n,
        "jacobian_max": [1.6] * n,
        "inverse_consistency_mm": list(ic_mm),
        "linear_det": list(1 + 0.05 * rng.standard_normal(n)),
        "nonlinear_rms_mm": list(2.0 * np.exp(0.2 * rng.standard_normal(n))),
        "displacement_rms_mm": list(3.0 * np.exp(0.2 * rng.standard_normal(n))),
    }
    return dict(
        images=[f"s{i:02d}.nii.gz" for i in range(n)],
        scored=list(range(n)),
        gram=centred @ centred.T,
        deformation=deformation,
        coverage=[1.0] * n,
        thresholds=nr.SubjectThresholds(),
    )


def test_inverse_consistency_errors_far_below_a_voxel_are_no_flag_and_no_infinite_z():
    """The issue's cohort: over half the subjects' inverse-consistency errors below a
    hundredth of a mm, the others a few hundredths (16 of 36); the MAD was 0 and those 16
    scored z = +inf and were flagged. Every z is finite now and none of them is flagged;
    a subject off by 3 mm among them still is."""
    from itk_nrreval.measures.subject_qc import assess_subjects

    rng = np.random.default_rng(1)
    ic = np.concatenate([rng.uniform(0.001, 0.009, 20), rng.uniform(0.02, 0.09, 16)])
    subjects = assess_subjects(**_cohort_numbers(ic))
    z = np.array([q.deformation["inverse_consistency_z"] for q in subjects])
    assert np.all(np.isfinite(z)), z
    assert [q.flags for q in subjects] == [()] * len(ic)
    ic[7] = 3.0  # a meaningful failure: 3 mm, where the others are below a tenth of a mm
    subjects = assess_subjects(**_cohort_numbers(ic))
    flagged = {q.index: q.flags for q in subjects if q.flags}
    assert list(flagged) == [7] and "inverse-consistency error" in flagged[7][0]
    assert "inf" not in flagged[7][0]
    assert all(math.isfinite(q.deformation["inverse_consistency_z"]) for q in subjects)


@settings(max_examples=200, deadline=None)
@given(
    values=st.lists(st.one_of(st.just(0.005), st.floats(1e-4, 10.0)), min_size=1, max_size=40),
    least=st.sampled_from([0.01, 0.1, 1.0]),
    log=st.booleans(),
)
def test_a_robust_z_with_a_least_spread_is_finite_and_never_wider_than_it_allows(
    values, least, log
):
    """With a least spread the z-scores are finite whatever the cohort (over half of it at
    one value included); a departure d from the median in the measure's units is at most
    d / least spread standard deviations (linear), or at most as many as the log distance
    from the median to a value `least` above it allows (log); where the cohort's own
    spread is wider, the z-scores are those without the floor."""
    x = np.array(values)
    z = robust_z(x, log=log, floor=1e-3, least_spread=least)
    assert np.all(np.isfinite(z))
    y = np.log(np.maximum(x, 1e-3)) if log else x
    med = float(np.median(y))
    mad_scale = 1.4826 * float(np.median(np.abs(y - med)))
    floor_scale = math.log1p(least / max(math.exp(med), least)) if log else least
    assert np.all(np.abs(z) <= np.abs(y - med) / floor_scale * (1 + 1e-9) + 1e-12)
    if mad_scale > floor_scale:
        np.testing.assert_allclose(z, robust_z(x, log=log, floor=1e-3), rtol=1e-12)


# ----------------------------------------------------------------------------- issue 42


def bump_field(template: sitk.Image, *, amplitude_mm: float = 20.0, width_mm: float = 6.0):
    """A displacement field on `template`'s grid (identity direction): a Gaussian bump of
    `amplitude_mm` along x, of standard deviation `width_mm`, at the grid's centre. Its
    steepest slope is amplitude / width * exp(-1/2): with the defaults du_x/dx falls below -1
    (det J = 1 + du_x/dx <= 0) on 2.6% of the phantom's 40 x 40 grid of 1.6 mm (counted
    analytically), so it folds; below a slope of 1 it only moves."""
    size = np.array(template.GetSize())
    spacing, origin = np.array(template.GetSpacing()), np.array(template.GetOrigin())
    y, x = np.indices(size[::-1])
    px, py = origin[0] + x * spacing[0], origin[1] + y * spacing[1]
    centre = origin + spacing * (size - 1) / 2
    bump = amplitude_mm * np.exp(
        -((px - centre[0]) ** 2 + (py - centre[1]) ** 2) / (2 * width_mm**2)
    )
    field = sitk.GetImageFromArray(np.stack([bump, np.zeros_like(bump)], axis=-1), isVector=True)
    field.CopyInformation(template)
    return sitk.DisplacementFieldTransform(field)


#: The subjects of the cohort registered to its own subject 0: the first 16 (three
#: registrations of 36 took 7 s).
OWN_N = 16


@pytest.fixture(scope="module")
def own_subject_0(population, cohort, tmp_path_factory):
    """The cohort's first :data:`OWN_N` subjects registered to subject 0, three ways,
    evaluated.

    Subject i's transform maps subject 0's points to subject i's: subject 0's true transform
    into the template, then subject i's true transform out of it; subject 0's is the
    identity. ``to_s00`` names its reference with ``reference_index: 0``; ``to_copy_of_s00``
    only by its file, a copy of subject 0's image; ``folding`` (reference: subject 0's image
    file) composes every subject's transform, subject 0's too, with a field that folds."""
    base = cohort[0].parent
    names = [f"s{i:02d}" for i in range(OWN_N)]
    images = [str(base / f"img/{n}.nii.gz") for n in names]
    to_0 = population.subjects[0].subject_to_template
    chains = [[sitk.Transform(2, sitk.sitkIdentity)]]
    chains += [[to_0, str(base / f"truth/{n}.h5")] for n in names[1:]]
    copy = tmp_path_factory.mktemp("own_subject_0") / "reference_s00.nii.gz"
    shutil.copyfile(images[0], copy)
    fold = bump_field(population.template)
    same_frame = {"frame_transform": "identity"}  # subject 0's space, as to_s00's
    manifest = {
        "images": images,
        "labels": [str(base / f"lab/{n}.nii.gz") for n in names],
        "registrations": {
            "to_s00": {"reference": images[0], "reference_index": 0, "transforms": chains},
            "to_copy_of_s00": {"reference": str(copy), **same_frame, "transforms": chains},
            "folding": {
                "reference": images[0],
                **same_frame,
                "transforms": [[fold, *chain] for chain in chains],
            },
        },
    }
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the flagged registration's warning
        return nr.evaluate(manifest, n_samples=200, confidence=False, progress=False)


@pytest.mark.parametrize("name", ["to_s00", "to_copy_of_s00"])
def test_a_cohort_registered_to_its_own_subject_0_does_not_flag_it(own_subject_0, name):
    """Issue 42: subject 0, registered to itself (the identity), was flagged 'stopped early
    or affine only' (no non-linear displacement, against the cohort's median). It is the
    reference, named by reference_index or by its file and its identity transform: reported
    as such, never flagged, and out of the statistics the others are judged by."""
    subjects = own_subject_0.scores[name].subjects
    first = subjects[0]
    assert first.deformation["displacement_rms_mm"] < 1e-9  # the premise: the identity
    assert first.flags == () and first.diagnosis is None
    assert first.reference and first.concern is None and first.registration_flags == ()
    assert not any(q.reference for q in subjects[1:])
    assert not [q.index for q in subjects if q.flags]  # the others: true transforms
    # the others are judged against the others alone: their z-scores over subjects 1..N-1
    for key, z_key in (("nonlinear_rms_mm", "nonlinear_rms_z"), ("sdlogj", "sdlogj_z")):
        values = [q.deformation[key] for q in subjects]
        z = [q.deformation[z_key] for q in subjects]
        least = {"nonlinear_rms_mm": 0.1, "sdlogj": 0.01}[key]
        np.testing.assert_allclose(
            z[1:], robust_z(values[1:], log=True, floor=1e-3, least_spread=least)[:]
        )
    overlaps = [q.overlap for q in subjects]
    np.testing.assert_allclose(
        [q.overlap_z for q in subjects[1:]], robust_z(overlaps[1:], least_spread=0.01)
    )


def test_the_same_reference_file_with_a_transform_that_moves_is_no_reference(own_subject_0):
    """Under ``folding`` the reference is subject 0's file too, but subject 0's transform
    folds: it is a subject like the others. And the reference found by its file is the one
    reference_index names."""
    from itk_nrreval.measures.subject_qc import reference_subject

    assert not any(q.reference for q in own_subject_0.scores["folding"].subjects)
    folder = Path(own_subject_0.inputs["images"][0]).parent
    images = sorted(str(p) for p in folder.glob("s*.nii.gz"))
    moves = [0.0] + [1.0] * (OWN_N - 1)
    link = folder.parent / "link_to_s03.nii.gz"  # through another spelling
    link.unlink(missing_ok=True)
    link.symlink_to(images[3])
    assert reference_subject(link, images, displacement_rms_mm=moves) is None
    moves[3] = 0.0
    assert reference_subject(link, images, displacement_rms_mm=moves) == 3
    # the same voxels on the same grid, as an object in memory
    in_memory = InMemoryImage.from_object(sitk.ReadImage(images[5]), name="reference")
    assert reference_subject(in_memory, images, displacement_rms_mm=moves) is None
    moves[5] = 0.004  # within a hundredth of a mm of the identity
    assert reference_subject(in_memory, images, displacement_rms_mm=moves) == 5
    moves[5] = math.nan  # not measured: not the identity
    assert reference_subject(in_memory, images, displacement_rms_mm=moves) is None
    # reference_index names it, whatever the transforms
    assert reference_subject(images[0], images, reference_index=7) == 7


def test_a_registration_folding_in_every_subject_is_one_registration_flag(own_subject_0):
    """Issue 42: a property most subjects share is the registration's, said once: every
    subject folds more than the subject threshold (1%), so no subject is flagged for it,
    and the registration has one flag that names how many fold and how much."""
    subjects = own_subject_0.scores["folding"].subjects
    folded = np.array([q.deformation["folded_fraction"] for q in subjects])
    assert folded.min() > 0.01  # the premise: every subject beyond the subject threshold
    assert not [f for q in subjects for f in q.flags if "fold" in f]
    from itk_nrreval.measures.subject_qc import registration_flags

    (flag,) = registration_flags(subjects)
    n = OWN_N
    assert flag.startswith(f"{n} of the {n} subjects fold more than 1% of their voxels (")
    assert f"{folded.min():.1%}" in flag and f"{folded.max():.1%}" in flag
    assert all(q.registration_flags == (flag,) for q in subjects)
    # the registrations where none folds have no registration flag
    assert registration_flags(own_subject_0.scores["to_s00"].subjects) == ()


#: The concern by hand (issue 42): each z-score's sign (worse positive), its weight, and
#: whether only above zero counts; the concern is the weighted mean of those measured.
CONCERN_BY_HAND = {
    "overlap_z": (-1, 3, False),
    "corrected_z": (1, 1, False),
    "sdlogj_z": (1, 1, True),
    "inverse_consistency_z": (1, 1, True),
}
CONCERN_WORDS = {
    "overlap_z": "overlap",
    "corrected_z": "bias-corrected distance",
    "sdlogj_z": "SDlogJ",
    "inverse_consistency_z": "inverse consistency",
}


def _concern_by_hand(z: dict) -> tuple[float | None, str | None]:
    """A subject's concern and the term contributing most, from its z-scores (key -> float,
    None or NaN when not measured), written out term by term."""
    parts = {}
    for key, (sign, weight, worse_only) in CONCERN_BY_HAND.items():
        if z.get(key) is None or math.isnan(z[key]):
            continue
        t = sign * z[key]
        parts[key] = (weight, weight * (max(t, 0.0) if worse_only else t))
    if not parts:
        return None, None
    total = sum(p[1] for p in parts.values()) / sum(p[0] for p in parts.values())
    first_largest = max(parts, key=lambda k: parts[k][1])  # dicts keep the terms' order
    return total, CONCERN_WORDS[first_largest]


def test_subjects_csv_lists_every_subject_worst_first_by_its_concern(damaged):
    """Issue 42: one documented score per subject, the concern (the weighted mean of its
    z-scores signed so that positive is worse: overlap 3, bias-corrected distance, SDlogJ
    and inverse consistency 1, the last two above zero only), and every subject listed by
    it, worst first. Checked on each row's own z-score columns; the damages the
    bias-corrected distance and the overlap see rank at the top."""
    result, out = damaged
    with open(out / "subjects.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [int(r["rank"]) for r in rows] == list(range(1, N + 1))
    assert sorted(int(r["index"]) for r in rows) == list(range(N))
    concern = [float(r["concern"]) for r in rows]
    assert concern == sorted(concern, reverse=True)
    for r in rows:
        expected, words = _concern_by_hand(
            {k: float(r[k]) if r[k] != "" else None for k in CONCERN_BY_HAND}
        )
        assert float(r["concern"]) == pytest.approx(expected)
        assert r["concern_from"] == words
    # the subjects off by a scale and by a flip
    top = [int(r["index"]) for r in rows[:3]]
    assert {16, 2} <= set(top), top
    # results.json keeps manifest order, with the same concern
    subjects = result.scores["damaged"].subjects
    by_index = {int(r["index"]): float(r["concern"]) for r in rows}
    assert [q.concern for q in subjects] == pytest.approx([by_index[i] for i in range(N)])


def test_with_no_subject_flagged_the_summary_names_the_worst_by_concern(clean):
    """A cohort that flags no one still has a worst few: summary.md names the three of
    highest concern, in subjects.csv's order."""
    result, out = clean
    with open(out / "subjects.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert not any(r["flags"] for r in rows)
    summary = (out / "summary.md").read_text()
    (line,) = [ln for ln in summary.splitlines() if ln.startswith("- truth:")]
    assert line.startswith(f"- truth: none of the {N} subjects is flagged; the highest concern: ")
    named = [int(k) for k in re.findall(r"subject (\d+) \(", line)]
    assert named == [int(r["index"]) for r in rows[:3]]
    assert f"concern {float(rows[0]['concern']):.1f} ({rows[0]['concern_from']})" in line


def test_the_reports_say_which_flags_are_the_registrations_and_name_the_reference(own_subject_0):
    """summary.md, subjects.csv and report.html say the folding once, as the registration's,
    and name subject 0 as the reference where it is."""
    from itk_nrreval.measures.subject_qc import registration_flags
    from itk_nrreval.report._html import escape
    from itk_nrreval.report.evaluation_page import report_html
    from itk_nrreval.report.evaluation_text import subjects_csv, summary_table

    result = own_subject_0
    (flag,) = registration_flags(result.scores["folding"].subjects)
    summary = summary_table(result)
    assert summary.count(flag) == 1
    assert f"  - registration flag: {flag}." in summary.splitlines()
    reference = "  - subject 0 ({}): the reference of this registration"
    assert summary.count(reference.format(result.scores["to_s00"].subjects[0].image)) == 2
    assert f"of the {OWN_N - 1} subjects other than its reference" in summary
    rows = list(csv.DictReader(io.StringIO(subjects_csv(result))))
    folding = [r for r in rows if r["registration"] == "folding"]
    assert all(r["registration_flags"] == flag and "fold" not in r["flags"] for r in folding)
    for name in ("to_s00", "to_copy_of_s00"):
        mine = [r for r in rows if r["registration"] == name]
        assert [(r["index"], r["reference"]) for r in mine if r["reference"] == "True"] == [
            ("0", "True")
        ]
        assert mine[-1]["index"] == "0" and mine[-1]["concern"] == ""  # listed last
    page = report_html(result, figures={})
    assert page.count(escape(flag)) == 1
    assert "Registration flag</b>" in page
    assert page.count("is the reference of this registration") == 2


def test_a_subject_folding_only_between_grid_points_is_flagged_for_folding():
    """Issue 42, item 5: a transform whose folds central differences miss (0 folded voxels)
    but a one-sided or tetrahedral stencil sees (3% non-diffeomorphic) is flagged for
    folding, saying so; the same fraction by central differences is flagged as before, and
    a subject measured before the stencils existed (NaN) is not."""
    from itk_nrreval.measures.subject_qc import assess_subjects

    numbers = _cohort_numbers([0.05] * 12)
    n = 12
    numbers["deformation"]["nondiffeomorphic_fraction"] = [0.0] * n
    numbers["deformation"]["nondiffeomorphic_fraction"][4] = 0.03
    numbers["deformation"]["nondiffeomorphic_fraction"][6] = math.nan
    subjects = assess_subjects(**numbers)
    flagged = {q.index: q.flags for q in subjects if q.flags}
    assert list(flagged) == [4], flagged
    assert "fold by some finite-difference stencil" in flagged[4][0]
    assert "central differences: 0.00%" in flagged[4][0]


def _concern_cohort(thresholds):
    """A generated cohort of 12 registered to its own subject 0 (the identity), with one
    subject of poor label overlap (9), one rough (7: SDlogJ 4x) and one stopped early (4),
    assessed with and without labels under `thresholds`: (labelled, unlabelled)."""
    from itk_nrreval.measures.subject_qc import assess_subjects

    n, n_labels = 12, 4
    numbers = {**_cohort_numbers([0.3] * n, seed=3), "thresholds": thresholds}
    defo = numbers["deformation"]
    for key, value in (("sdlogj", 0.0), ("nonlinear_rms_mm", 0.0), ("displacement_rms_mm", 0.0)):
        defo[key][0] = value  # the reference: the identity
    defo["inverse_consistency_mm"][0] = 0.0
    defo["sdlogj"][7] *= 4  # rough
    defo["sdlogj"][4], defo["nonlinear_rms_mm"][4] = 0.002, 0.01  # stopped early
    rng = np.random.default_rng(3)
    numbers["corrected_squares"] = rng.uniform(90, 110, n)  # the image term, measured
    volume = rng.uniform(80, 120, size=(n, n_labels))
    share = rng.uniform(0.75, 0.85, n)
    share[9] = 0.3  # poor overlap
    mins = np.minimum(volume[:, None, :], volume[None, :, :]) * share[:, None, None]
    target = mins.sum(axis=1) - np.einsum("iil->il", mins)
    labelled = assess_subjects(
        **numbers,
        reference=0,
        overlap_volume=volume,
        overlap_target_sums=target,
        overlap_weights=np.ones(n_labels),
    )
    return labelled, assess_subjects(**numbers, reference=0)


@pytest.mark.parametrize(
    ("with_labels", "without_labels"),
    [(0.5, 2.0), (2.0, 0.5), (1.0, 1.0), (None, 1.0), (1.0, None)],
)
def test_the_concern_flag_flags_exactly_the_subjects_above_its_threshold(
    with_labels, without_labels
):
    """Issue 42: `SubjectThresholds.concern` flags a subject whose concern, written out by
    hand from its own z-scores, is above the threshold, and no other subject for that
    reason; `concern_without_labels` does the same where the overlap was not measured; the
    reference never; None (off) flags none for it. Its words give the concern and the term
    it comes from most."""
    thresholds = nr.SubjectThresholds(concern=with_labels, concern_without_labels=without_labels)
    labelled, unlabelled = _concern_cohort(thresholds)
    for subjects, threshold in ((labelled, with_labels), (unlabelled, without_labels)):
        reference, *others = subjects
        assert reference.flags == () and reference.concern is None
        flagged = set()
        for q in others:
            assert (q.overlap_z is not None) == (subjects is labelled)
            by_hand, words = _concern_by_hand(
                {
                    "overlap_z": q.overlap_z,
                    "corrected_z": q.corrected_z,
                    "sdlogj_z": q.deformation["sdlogj_z"],
                    "inverse_consistency_z": q.deformation["inverse_consistency_z"],
                }
            )
            mine = [f for f in q.flags if f.startswith("among the worst of its cohort")]
            expected = threshold is not None and by_hand > threshold
            assert bool(mine) == expected, (q.index, by_hand)
            if expected:
                (flag,) = mine
                assert (
                    f"concern {by_hand:+.2f} (above {threshold:g}; most from its {words})" in flag
                )
                flagged.add(q.index)
        # each cohort has subjects on both sides of the thresholds tried (the test can fail):
        # with labels the poor overlap (9) is above 2; without labels the rough one (7) is
        # between 1 and 2, the rest below 1
        if subjects is labelled:
            assert (9 in flagged) == (threshold is not None)
        else:
            assert (7 in flagged) == (threshold is not None and threshold < 1.5)
        assert len(flagged) < 11


def test_the_concern_is_the_weighted_mean_of_its_z_scores_and_ranks_worst_first():
    """Issue 42: on a generated cohort registered to its own subject 0 (the identity), with
    one subject of poor label overlap, one rough (SDlogJ 4x) and one stopped early (almost no
    non-linear displacement, the least SDlogJ): every subject's concern and the term it comes
    from are the ones written out by hand from its own z-scores, with and without labels;
    the subjects are ranked by it, worst first; the reference has none, is never flagged and
    is listed last."""
    from itk_nrreval.measures.subject_qc import ranked

    labelled, unlabelled = _concern_cohort(nr.SubjectThresholds())
    for subjects, labels in ((labelled, True), (unlabelled, False)):
        reference, *others = subjects
        assert reference.reference and reference.concern is None
        assert reference.concern_from is None and reference.flags == ()
        by_hand = {}
        for q in others:
            z = {
                "overlap_z": q.overlap_z,
                "corrected_z": q.corrected_z,
                "sdlogj_z": q.deformation["sdlogj_z"],
                "inverse_consistency_z": q.deformation["inverse_consistency_z"],
            }
            assert (q.overlap_z is not None) == labels
            assert q.corrected_z is not None
            by_hand[q.index], words = _concern_by_hand(z)
            assert q.concern == pytest.approx(by_hand[q.index], rel=1e-12), q.index
            assert q.concern_from == words, q.index
        order = sorted(by_hand, key=lambda i: (-by_hand[i], i))
        assert [q.index for q in ranked(subjects)] == [*order, 0]
        if labels:
            assert order[0] == 9 and labelled[9].concern_from == "overlap"
        assert unlabelled[7].concern_from == "SDlogJ" and order.index(7) < 3
        # stopped early: its SDlogJ z far below the cohort's counts as 0, not against it
        stopped = subjects[4]
        sdlogj_z = stopped.deformation["sdlogj_z"]
        assert sdlogj_z < -3 and stopped.flags
        counted = by_hand[4] + sdlogj_z / (6 if labels else 3)  # were it counted as it is
        assert stopped.concern == pytest.approx(by_hand[4]) and stopped.concern > counted + 0.5


@settings(max_examples=100, deadline=None)
@given(
    values=st.lists(
        st.tuples(*[st.one_of(st.just(math.nan), st.floats(-50, 50)) for _ in range(4)]),
        min_size=1,
        max_size=8,
    ),
    missing=st.sampled_from([(), ("overlap_z",), ("corrected_z", "sdlogj_z")]),
)
def test_concern_scores_are_the_weighted_means_written_out_by_hand(values, missing):
    """concern_scores on arrays (NaN: not measured; a key left out: no such term, e.g. no
    labels) against the concern written out term by term, subject by subject; a subject
    with nothing measured has NaN and no term."""
    from itk_nrreval.measures.subject_qc import CONCERN_TERMS, concern_scores

    keys = list(CONCERN_BY_HAND)
    columns = {k: np.array([v[j] for v in values]) for j, k in enumerate(keys)}
    given_keys = {k: c for k, c in columns.items() if k not in missing}
    concern, largest = concern_scores(given_keys)
    assert concern.shape == largest.shape == (len(values),)
    for i in range(len(values)):
        expected, words = _concern_by_hand({k: float(c[i]) for k, c in given_keys.items()})
        if expected is None:
            assert math.isnan(concern[i]) and largest[i] == -1
        else:
            assert concern[i] == pytest.approx(expected, rel=1e-12, abs=1e-12)
            assert CONCERN_TERMS[largest[i]].words == words


def test_a_reference_whose_content_cannot_be_read_names_no_subject(tmp_path):
    """Two digests that could not be taken are not two equal images: an identity-transform
    subject is not named the reference because neither file could be read."""
    from itk_nrreval.measures.subject_qc import reference_subject

    missing = [tmp_path / "gone_reference.nii.gz", tmp_path / "gone_subject.nii.gz"]
    assert reference_subject(missing[0], [missing[1]], displacement_rms_mm=[0.0]) is None
    # the same file, even unreadable, is still the same file
    assert reference_subject(missing[0], [missing[0]], displacement_rms_mm=[0.0]) is None
