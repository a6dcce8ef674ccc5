"""Multi-modal groups through the manifest and `evaluate` (issue 19)."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
import yaml
from test_bad_inputs import assert_one_line

import itk_nrreval as nr
from itk_nrreval.cli import main
from itk_nrreval.io.manifest import load_manifest, write_manifest
from itk_nrreval.io.transforms import chain_transform


@pytest.fixture(scope="module")
def two_contrasts(tmp_path_factory):
    folder = tmp_path_factory.mktemp("t1t2") / "data"
    args = ["synth", "--n", "4", "--contrasts", "t1,t2", "--out", str(folder), "--seed", "3"]
    assert main(args) == 0
    return folder / "manifest.yaml"


def test_manifest_keeps_groups_and_parameters(two_contrasts, tmp_path):
    m = load_manifest(two_contrasts)
    assert m.groups == ("t1",) * 4 + ("t2",) * 4
    data = yaml.safe_load(two_contrasts.read_text())
    data["registrations"]["truth"]["parameters"] = {"smoothing_mm": 5.0, "levels": [4, 2, 1]}
    for key in ("images", "labels"):
        data[key] = [str(two_contrasts.parent / p) for p in data[key]]
    reg = data["registrations"]["truth"]
    reg["reference"] = str(two_contrasts.parent / reg["reference"])
    reg["transforms"] = [str(two_contrasts.parent / p) for p in reg["transforms"]]
    copy = write_manifest(data, tmp_path / "copy.yaml")
    again = load_manifest(copy)
    assert again.groups == m.groups
    assert m.subjects == tuple(f"s{i:02d}" for i in range(4)) * 2
    assert again.subjects == m.subjects
    assert again.registrations["truth"].parameters == {"smoothing_mm": 5.0, "levels": [4, 2, 1]}
    assert again.describe()["registrations"]["truth"]["parameters"]["levels"] == [4, 2, 1]


def test_evaluate_scores_a_mixture_equal_to_the_direct_estimator(two_contrasts):
    """Reference: every image resampled by SimpleITK through its true transform (NaN
    outside), nr.specificity with the same groups on the voxels every image covers."""
    m = load_manifest(two_contrasts)
    reg = m.registrations["truth"]
    grid = sitk.ReadImage(str(reg.reference))
    stack = []
    for path, chain in zip(m.images, reg.transforms, strict=True):
        img = sitk.Cast(sitk.ReadImage(str(path)), sitk.sitkFloat64)
        res = sitk.Resample(img, grid, chain_transform(chain), sitk.sitkLinear, float("nan"))
        stack.append(sitk.GetArrayFromImage(res))
    stack = np.stack(stack)
    region = ~np.isnan(stack).any(axis=0)
    res = nr.evaluate(two_contrasts, n_samples=2000, seed=4, confidence=False, progress=False)
    got = res.scores["truth"].specificity
    expected = nr.specificity(
        np.nan_to_num(stack), mask=region, groups=list(m.groups), n_samples=2000, seed=4
    )
    assert got.value == pytest.approx(expected.value, rel=1e-9)
    assert got.mixture is not None
    np.testing.assert_array_equal(got.mixture.nearest_counts, expected.mixture.nearest_counts)
    assert int(got.mixture.nearest_counts.sum()) == 2000
    assert "mixture" in res.to_dict()["registrations"]["truth"]["specificity"]
    assert res.options["confidence"] is False


def _without(data: dict, folder, drop: set[int]) -> dict:
    """The manifest `data` (paths relative to `folder`) without the images `drop`, paths made
    absolute."""
    out = {key: value for key, value in data.items() if key not in ("registrations", "mask")}
    for key in ("images", "labels"):
        out[key] = [str(folder / p) for i, p in enumerate(data[key]) if i not in drop]
    for key in ("groups", "subjects"):
        if key in data:
            out[key] = [v for i, v in enumerate(data[key]) if i not in drop]
    if data.get("mask"):
        out["mask"] = str(folder / data["mask"])
    out["registrations"] = {}
    for name, reg in data["registrations"].items():
        out["registrations"][name] = {
            "reference": str(folder / reg["reference"]),
            "transforms": [
                str(folder / t) for i, t in enumerate(reg["transforms"]) if i not in drop
            ],
        }
    return out


def test_subject_level_confidence_leaves_out_a_subject_with_all_its_contrasts(
    two_contrasts, tmp_path
):
    """Reference: each replicate is the evaluation of the manifest without that subject's
    T1 and T2 images (a mask inside every image's cover keeps the region the same)."""
    data = yaml.safe_load(two_contrasts.read_text())
    folder = two_contrasts.parent
    assert data["subjects"] == [f"s{i:02d}" for i in range(4)] * 2
    reference = sitk.ReadImage(str(folder / data["registrations"]["truth"]["reference"]))
    size = np.array(reference.GetSize())
    mask = np.zeros(reference.GetSize()[::-1], np.uint8)
    lo, hi = size // 4, size - size // 4
    mask[lo[1] : hi[1], lo[0] : hi[0]] = 1
    mask_image = sitk.GetImageFromArray(mask)
    mask_image.CopyInformation(reference)
    sitk.WriteImage(mask_image, str(tmp_path / "mask.nii.gz"))
    data["mask"] = str(tmp_path / "mask.nii.gz")
    full = write_manifest(_without(data, folder, set()), tmp_path / "full.yaml")
    res = nr.evaluate(full, n_samples=2000, seed=4, progress=False)
    assert res.options["confidence"] is True
    assert res.options["resamples"] == 4  # subjects, not the 8 images
    reps = {"specificity": [], "overlap.volume": []}
    for k in range(4):
        reduced = write_manifest(_without(data, folder, {k, k + 4}), tmp_path / f"no{k}.yaml")
        r = nr.evaluate(reduced, n_samples=2000, seed=4, confidence=False, progress=False)
        reps["specificity"].append(r.scores["truth"].specificity.value)
        reps["overlap.volume"].append(r.scores["truth"].overlap["volume"])
    for measure, values in reps.items():
        r = np.array(values)
        se = np.sqrt(3 / 4 * np.sum((r - r.mean()) ** 2))
        got = res.scores["truth"].intervals[measure]
        assert got.n_replicates == 4
        assert got.stderr == pytest.approx(se, rel=1e-6), measure


def test_groups_without_subjects_get_no_subject_level_confidence(two_contrasts, tmp_path):
    data = yaml.safe_load(two_contrasts.read_text())
    del data["subjects"]
    manifest = write_manifest(_without(data, two_contrasts.parent, set()), tmp_path / "m.yaml")
    with pytest.warns(UserWarning, match="not computed for a manifest with groups and no subj"):
        res = nr.evaluate(manifest, n_samples=500, seed=4, progress=False)
    assert res.options["confidence"] is False
    assert res.scores["truth"].intervals == {}


@pytest.mark.parametrize(
    "key, value, message",
    [
        ("groups", ["t1"] * 4 + ["t2"] * 3 + ["pd"], "groups: group 'pd' has 1 image (needs 2)"),
        ("groups", ["t1"] * 7, "groups: 7 labels for 8 images"),
        ("subjects", ["a", "b"] * 3, "subjects: 6 labels for 8 images"),
        ("subjects", "s00", "subjects: expected a list with one label per image"),
        ("subjects", [1.5] * 8, "subjects: labels must be strings or integers, got 1.5"),
    ],
)
def test_bad_groups_or_subjects_in_a_manifest_is_one_line_exit_2(
    two_contrasts, tmp_path, capsys, key, value, message
):
    data = yaml.safe_load(two_contrasts.read_text())
    data[key] = value
    bad = two_contrasts.parent / f"bad_{key}.yaml"
    bad.write_text(yaml.safe_dump(data, sort_keys=False))
    out = tmp_path / "out"
    assert main(["evaluate", str(bad), "--out", str(out), "--quiet"]) == 2
    assert_one_line(capsys.readouterr().err, f"bad_{key}.yaml", message)
    assert not out.exists()
