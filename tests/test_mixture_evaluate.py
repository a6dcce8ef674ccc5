"""Multi-modal groups through the manifest and `evaluate` (issue 19)."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
import yaml
from test_bad_inputs import assert_one_line

import itk_nrreval as nr
from itk_nrreval.cli import main
from itk_nrreval.manifest import load_manifest, write_manifest
from itk_nrreval.transforms import chain_transform


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
    with pytest.warns(UserWarning, match="not computed for a manifest with groups"):
        res = nr.evaluate(two_contrasts, n_samples=2000, seed=4, progress=False)
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


@pytest.mark.parametrize(
    "groups, message",
    [
        (["t1"] * 4 + ["t2"] * 3 + ["pd"], "groups: group 'pd' has 1 image (needs 2)"),
        (["t1"] * 7, "groups: 7 labels for 8 images"),
    ],
)
def test_bad_groups_in_a_manifest_is_one_line_exit_2(
    two_contrasts, tmp_path, capsys, groups, message
):
    data = yaml.safe_load(two_contrasts.read_text())
    data["groups"] = groups
    bad = two_contrasts.parent / "bad_groups.yaml"
    bad.write_text(yaml.safe_dump(data, sort_keys=False))
    out = tmp_path / "out"
    assert main(["evaluate", str(bad), "--out", str(out), "--quiet"]) == 2
    assert_one_line(capsys.readouterr().err, "bad_groups.yaml", message)
    assert not out.exists()
