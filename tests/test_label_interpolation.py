"""The label-interpolation option of the overlap (issue 17): linear, nearest, gaussian.

The reference is independent of the pipeline and of :mod:`itk_nrreval.io._memberships`: each
label map's one-hot channels (background included) resampled by SimpleITK itself into the
common frame -- nearest neighbour on the label map, or each whole channel smoothed by
``sitk.SmoothingRecursiveGaussian`` and then resampled linearly -- and
:func:`itk_nrreval.generalized_overlap` on the stack.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import SimpleITK as sitk
from test_bad_inputs import run_cli
from test_coverage import cropped_case, reference_resampled
from test_evaluate import make_case

import itk_nrreval as nr
from itk_nrreval.io.transforms import chain_transform

KW = dict(n_samples=500, seed=1, progress=False, confidence=False)
VALUES = (0, 1, 2, 3)


def reference_memberships(tmp_path, data, name, method, sigma=None) -> np.ndarray:
    """(N, labels, *grid) memberships of registration `name`, by SimpleITK alone."""
    grid = sitk.ReadImage(str(tmp_path / "template.nii.gz"))
    out = []
    for path, item in zip(data["labels"], data["registrations"][name]["transforms"], strict=True):
        items = item if isinstance(item, list) else [item]
        t = chain_transform([str(tmp_path / p) for p in items])
        lab = sitk.ReadImage(str(tmp_path / path))
        if method == "nearest":
            res = sitk.GetArrayFromImage(sitk.Resample(lab, grid, t, sitk.sitkNearestNeighbor, 0))
            out.append(np.stack([res == v for v in VALUES]).astype(np.float64))
            continue
        arr = sitk.GetArrayFromImage(lab)
        channels = []
        for v in VALUES:
            one = sitk.GetImageFromArray((arr == v).astype(np.float64))
            one.CopyInformation(lab)
            smooth = sitk.SmoothingRecursiveGaussian(one, [sigma, sigma])
            channels.append(sitk.GetArrayFromImage(sitk.Resample(smooth, grid, t, sitk.sitkLinear)))
        out.append(np.clip(np.stack(channels), 0, 1))
    return np.stack(out)


@pytest.mark.parametrize(
    ("method", "sigma", "rel"), [("nearest", None, 1e-9), ("gaussian", 1.5, 2e-3)]
)
def test_overlap_matches_simpleitk_resampling_of_the_label_maps(tmp_path, method, sigma, rel):
    data = cropped_case(tmp_path, crop=0)  # truth and perturbed, in the template's frame
    # the voxels every image covers under every registration
    stacks = reference_resampled(tmp_path, data)
    region = np.all([~np.isnan(st).any(axis=0) for st in stacks.values()], axis=0)
    assert region.mean() > 0.5
    res = nr.evaluate(
        tmp_path / "manifest.yaml",
        weightings=("volume", "inverse_volume"),
        resampling=nr.Resampling(label_interpolation=method, label_sigma_mm=sigma),
        **KW,
    )
    linear = nr.evaluate(tmp_path / "manifest.yaml", weightings=("inverse_volume",), **KW)
    for name in data["registrations"]:
        memberships = reference_memberships(tmp_path, data, name, method, sigma)
        for w in ("volume", "inverse_volume"):
            expected = nr.generalized_overlap(memberships, weighting=w, mask=region)
            assert res.scores[name].overlap[w] == pytest.approx(expected, rel=rel), (name, w)
        # the option changes the number (so the test above could fail on today's linear)
        assert res.scores[name].overlap["inverse_volume"] != pytest.approx(
            linear.scores[name].overlap["inverse_volume"], rel=10 * rel
        )
    # and only the overlap: the specificity of the same images is untouched
    for name in data["registrations"]:
        assert res.scores[name].specificity.value == linear.scores[name].specificity.value


def test_option_recorded_in_results_json(tmp_path, capsys):
    make_case(tmp_path)
    out = tmp_path / "out"
    args = ["evaluate", str(tmp_path / "manifest.yaml"), "--out", str(out), "--samples", "300"]
    args += ["--no-confidence", "--no-figures", "--quiet"]
    code, err = run_cli([*args, "--label-interpolation", "gaussian", "--label-sigma", "2"], capsys)
    assert code == 0, err
    options = json.loads((out / "results.json").read_text())["options"]
    assert options["label_interpolation"] == "gaussian" and options["label_sigma_mm"] == 2.0
    code, err = run_cli([*args, "--label-interpolation", "nearest"], capsys)
    assert code == 0, err
    options = json.loads((out / "results.json").read_text())["options"]
    assert options["label_interpolation"] == "nearest" and options["label_sigma_mm"] is None


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--label-sigma", "2"], "--label-sigma MM goes with --label-interpolation gaussian"),
        (["--label-interpolation", "gaussian"], "--label-sigma MM goes with"),
        (["--label-interpolation", "gaussian", "--label-sigma", "0"], "--label-sigma"),
        (["--label-interpolation", "cubic"], "--label-interpolation"),
    ],
)
def test_bad_label_interpolation_options(tmp_path, capsys, extra, message):
    make_case(tmp_path)
    out = tmp_path / "out"
    code, err = run_cli(
        ["evaluate", str(tmp_path / "manifest.yaml"), "--out", str(out), "--quiet", *extra], capsys
    )
    assert code == 2 and message in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_api_refuses_inconsistent_options(tmp_path):
    make_case(tmp_path)
    with pytest.raises(ValueError, match="needs a finite sigma > 0 mm"):
        nr.evaluate(
            tmp_path / "manifest.yaml",
            resampling=nr.Resampling(label_interpolation="gaussian"),
            **KW,
        )
    with pytest.raises(ValueError, match="only with label_interpolation='gaussian'"):
        nr.evaluate(tmp_path / "manifest.yaml", resampling=nr.Resampling(label_sigma_mm=1.0), **KW)
    with pytest.raises(ValueError, match="is not one of"):
        nr.evaluate(
            tmp_path / "manifest.yaml",
            resampling=nr.Resampling(label_interpolation="cubic"),
            **KW,
        )
