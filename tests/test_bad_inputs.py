"""Bad inputs through the CLI: one line naming the file and the problem, exit 2, no
traceback, nothing written."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
from test_evaluate import make_case

from itk_nrreval.cli import main


def nan_nifti(path, shape=(40, 40)):
    """A float NIfTI whose top half is NaN (SimpleITK's NIfTI reader turns NaN into 0)."""
    arr = np.random.default_rng(0).random(shape).astype(np.float32)
    arr[: shape[0] // 2] = np.nan
    img = sitk.GetImageFromArray(arr)
    img.SetSpacing((1.0, 1.0))
    sitk.WriteImage(img, str(path))


def truncated(path, keep: float = 0.1):
    raw = path.read_bytes()
    path.write_bytes(raw[: max(1, int(len(raw) * keep))])


def run_cli(args, capsys) -> tuple[int, str]:
    code = main(args)
    err = capsys.readouterr().err
    return code, err


def assert_one_line(err: str, *fragments: str) -> None:
    lines = [ln for ln in err.strip().splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    for f in fragments:
        assert f in lines[0], (f, lines[0])


@pytest.mark.parametrize(
    "damage, message",
    [
        (lambda p: nan_nifti(p), "contains NaN or infinite voxel values"),
        (lambda p: truncated(p), "truncated or corrupt"),
    ],
    ids=["nan-in-nifti", "truncated-nii-gz"],
)
def test_evaluate_refuses_a_damaged_nifti_image(tmp_path, capsys, damage, message):
    make_case(tmp_path)
    bad = tmp_path / "img3.nii.gz"
    damage(bad)
    out = tmp_path / "out"
    args = ["evaluate", str(tmp_path / "manifest.yaml"), "--out", str(out), "--samples", "500"]
    code, err = run_cli(args + ["--quiet", "--no-figures"], capsys)
    assert code == 2
    assert_one_line(err, str(bad), message)
    assert not (out / "results.json").exists()


@pytest.mark.parametrize("damage", ["nan", "truncated"])
def test_specificity_refuses_a_damaged_nifti_image(tmp_path, capsys, damage):
    paths = []
    for i in range(4):
        p = tmp_path / f"i{i}.nii.gz"
        img = sitk.GetImageFromArray(np.random.default_rng(i).random((30, 30)).astype(np.float32))
        sitk.WriteImage(img, str(p))
        paths.append(str(p))
    bad = tmp_path / "i2.nii.gz"
    nan_nifti(bad, (30, 30)) if damage == "nan" else truncated(bad)
    code, err = run_cli(["specificity", *paths, "--samples", "200"], capsys)
    assert code == 2
    assert_one_line(err, str(bad))


def test_evaluate_refuses_an_intensity_image_given_as_a_label_map(tmp_path, capsys):
    make_case(tmp_path)
    bad = tmp_path / "lab2.nii.gz"
    img = sitk.ReadImage(str(tmp_path / "img2.nii.gz"))  # float intensities
    sitk.WriteImage(img, str(bad))
    out = tmp_path / "out"
    args = ["evaluate", str(tmp_path / "manifest.yaml"), "--out", str(out), "--quiet"]
    code, err = run_cli(args, capsys)
    assert code == 2
    assert_one_line(err, str(bad), "label map holds non-integer values", "intensity image")
    assert not (out / "results.json").exists()


def test_float_label_map_with_fractional_values_is_refused_not_truncated(tmp_path, capsys):
    make_case(tmp_path)
    bad = tmp_path / "lab4.nii.gz"
    arr = sitk.GetArrayFromImage(sitk.ReadImage(str(bad))).astype(np.float32)
    arr[arr == 2] = 2.5  # int(2.5) would silently become label 2
    img = sitk.GetImageFromArray(arr)
    img.CopyInformation(sitk.ReadImage(str(bad)))
    sitk.WriteImage(img, str(bad))
    code, err = run_cli(
        ["evaluate", str(tmp_path / "manifest.yaml"), "--out", str(tmp_path / "o"), "--quiet"],
        capsys,
    )
    assert code == 2
    assert_one_line(err, str(bad), "non-integer values (e.g. 2.5")


def test_a_label_map_given_as_an_image_is_warned_about(tmp_path):
    import yaml

    import itk_nrreval as nr

    data = make_case(tmp_path)
    data["images"][1] = "lab1.nii.gz"
    (tmp_path / "manifest.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.warns(UserWarning, match=r"lab1.nii.gz: the image holds only \d distinct integer"):
        nr.evaluate(tmp_path / "manifest.yaml", n_samples=500, progress=False)


@pytest.mark.parametrize(
    "option, value, message",
    [
        ("--samples", "0", "--samples: expected an integer >= 2, got '0'"),
        ("--samples", "-5", "--samples: expected an integer >= 2, got '-5'"),
        ("--samples", "1", "--samples: expected an integer >= 2, got '1'"),
        ("--samples", "1e12", "more samples than the sampler can number"),
        ("--samples", "many", "--samples: expected an integer >= 2, got 'many'"),
        ("--seed", "-1", "--seed: expected an integer in [0, "),
        ("--workers", "0", "--workers: expected an integer >= 1, got '0'"),
        ("--flag-folded-max", "1.5", "--flag-folded-max: expected a fraction in [0, 1]"),
        ("--confidence-samples", "1", "--confidence-samples: expected an integer >= 2"),
    ],
)
def test_numeric_options_are_checked_when_parsed(tmp_path, capsys, option, value, message):
    make_case(tmp_path)
    out = tmp_path / "out"
    assert (
        main(["evaluate", str(tmp_path / "manifest.yaml"), "--out", str(out), option, value]) == 2
    )
    assert_one_line(capsys.readouterr().err, message)
    assert not out.exists()


def test_samples_in_exponent_notation_are_accepted(tmp_path, capsys):
    make_case(tmp_path, with_labels=False)
    out = tmp_path / "out"
    args = ["evaluate", str(tmp_path / "manifest.yaml"), "--out", str(out), "--samples", "2e3"]
    assert main(args + ["--quiet", "--no-figures", "--no-confidence"]) == 0
    import json

    assert json.loads((out / "results.json").read_text())["options"]["n_samples"] == 2000


@pytest.mark.parametrize("kind", ["file", "under-a-file"])
def test_out_that_cannot_be_a_folder_fails_before_any_work(tmp_path, capsys, kind):
    make_case(tmp_path)
    blocker = tmp_path / "blocker"
    blocker.write_text("not a folder")
    out = blocker if kind == "file" else blocker / "sub"
    code, err = run_cli(["evaluate", str(tmp_path / "manifest.yaml"), "--out", str(out)], capsys)
    assert code == 2
    assert_one_line(err, f"--out {out}")
    assert blocker.read_text() == "not a folder"


def test_cli_warnings_are_one_readable_line(tmp_path, capsys):
    import yaml

    data = make_case(tmp_path)
    data["images"][1] = "lab1.nii.gz"  # a label map given as an image: a warning
    (tmp_path / "manifest.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    args = ["evaluate", str(tmp_path / "manifest.yaml"), "--out", str(tmp_path / "o")]
    code, err = run_cli(args + ["--quiet", "--samples", "500", "--no-figures"], capsys)
    assert code == 0
    warning_lines = [ln for ln in err.splitlines() if "warning" in ln]
    assert warning_lines and all(
        ln.startswith("nrreval evaluate: warning: ") for ln in warning_lines
    )
    assert "warnings.warn" not in err and ".py:" not in err
