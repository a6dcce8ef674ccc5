"""Bad inputs through the CLI: one line naming the file and the problem, exit 2, no
traceback, nothing written."""

from __future__ import annotations

import h5py
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


# ----------------------------------------------------------------------------- a table of cases


def _edit_manifest(tmp_path, edit) -> str:
    import yaml

    data = make_case(tmp_path)
    edit(data)
    (tmp_path / "manifest.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    return str(tmp_path / "manifest.yaml")


def _evaluate(manifest) -> list[str]:
    return ["evaluate", str(manifest), "--samples", "500", "--quiet", "--no-figures"]


def _case_missing_manifest(tmp_path):
    return _evaluate(tmp_path / "nowhere.yaml"), ["nowhere.yaml", "not found"]


def _case_manifest_is_a_folder(tmp_path):
    (tmp_path / "m.yaml").mkdir()
    return _evaluate(tmp_path / "m.yaml"), ["m.yaml", "folder"]


def _case_manifest_is_binary(tmp_path):
    (tmp_path / "m.yaml").write_bytes(bytes(range(256)) * 4)
    return _evaluate(tmp_path / "m.yaml"), ["m.yaml"]


def _case_manifest_is_empty(tmp_path):
    (tmp_path / "m.yaml").write_text("")
    return _evaluate(tmp_path / "m.yaml"), ["m.yaml", "empty"]


def _case_manifest_is_a_list(tmp_path):
    (tmp_path / "m.yaml").write_text("- a.nii.gz\n- b.nii.gz\n")
    return _evaluate(tmp_path / "m.yaml"), ["m.yaml", "mapping"]


def _case_no_images(tmp_path):
    return _evaluate(_edit_manifest(tmp_path, lambda d: d.update(images=[]))), ["images"]


def _case_image_is_a_folder(tmp_path):
    m = _edit_manifest(tmp_path, lambda d: None)
    (tmp_path / "img2.nii.gz").unlink()
    (tmp_path / "img2.nii.gz").mkdir()
    return _evaluate(m), ["img2.nii.gz", "folder"]


def _case_image_is_text(tmp_path):
    m = _edit_manifest(tmp_path, lambda d: None)
    (tmp_path / "img1.nii.gz").write_text("this is not an image\n")
    return _evaluate(m), ["img1.nii.gz"]


def _case_image_is_a_vector_image(tmp_path):
    m = _edit_manifest(tmp_path, lambda d: None)
    field = sitk.ReadImage(str(tmp_path / "pert0.mha"))  # 2 components per voxel
    sitk.WriteImage(field, str(tmp_path / "img4.nii.gz"))
    return _evaluate(m), ["img4.nii.gz", "component"]


def _case_transform_is_garbage(tmp_path):
    m = _edit_manifest(tmp_path, lambda d: None)
    (tmp_path / "id3_0GenericAffine.mat").write_bytes(b"\x00garbage\xff" * 10)
    return _evaluate(m), ["id3_0GenericAffine.mat"]


def _case_transform_text_is_nonsense(tmp_path):
    def edit(d):
        d["registrations"]["identity"]["transforms"][2] = "odd.tfm"

    m = _edit_manifest(tmp_path, edit)
    (tmp_path / "odd.tfm").write_text("#Insight Transform File V1.0\nTransform: Nonsense\n")
    return _evaluate(m), ["odd.tfm"]


def _h5_case(tmp_path, write):
    """The manifest with transforms[2] of 'identity' replaced by ``odd.h5``, `write` (path)."""

    def edit(d):
        d["registrations"]["identity"]["transforms"][2] = "odd.h5"

    m = _edit_manifest(tmp_path, edit)
    write(tmp_path / "odd.h5")
    return _evaluate(m), ["odd.h5", "cannot read transform"]


def _case_h5_transform_is_garbage(tmp_path):
    return _h5_case(tmp_path, lambda p: p.write_bytes(b"\x89HDF\r\n\x1a\n" + b"\xff" * 300))


def _case_h5_transform_is_truncated(tmp_path):
    def write(p):
        field = sitk.Image([40, 40], sitk.sitkVectorFloat64, 2)
        sitk.WriteTransform(sitk.DisplacementFieldTransform(field), str(p))
        truncated(p, keep=0.5)

    return _h5_case(tmp_path, write)


def _case_h5_field_with_too_few_values(tmp_path):
    # a well-formed file whose field has fewer values than its grid needs: read from its
    # layout, the check must still refuse it, as reading it whole does
    def write(p):
        field = sitk.Image([40, 40], sitk.sitkVectorFloat64, 2)
        composite = sitk.CompositeTransform([sitk.AffineTransform(2)])
        composite.AddTransform(sitk.DisplacementFieldTransform(field))
        sitk.WriteTransform(composite, str(p))
        with h5py.File(p, "r+") as f:
            del f["TransformGroup/2/TransformParameters"]
            f["TransformGroup/2/TransformParameters"] = np.zeros(40 * 40 * 2 - 2)

    return _h5_case(tmp_path, write)


def _case_h5_file_is_not_a_transform(tmp_path):
    def write(p):
        with h5py.File(p, "w") as f:
            f["TransformGroup/0/Something"] = np.zeros(3)

    return _h5_case(tmp_path, write)


def _case_field_of_wrong_dimension(tmp_path):
    m = _edit_manifest(tmp_path, lambda d: None)
    field = sitk.Image([8, 8, 8], sitk.sitkVectorFloat64, 3)
    sitk.WriteImage(field, str(tmp_path / "pert1.mha"))
    return _evaluate(m), ["pert1.mha", "3D"]


def _case_reference_missing(tmp_path):
    m = _edit_manifest(tmp_path, lambda d: None)
    (tmp_path / "template.nii.gz").unlink()
    return _evaluate(m), ["template.nii.gz", "not found"]


def _case_label_map_3d(tmp_path):
    m = _edit_manifest(tmp_path, lambda d: None)
    sitk.WriteImage(sitk.Image([40, 40, 3], sitk.sitkUInt8), str(tmp_path / "lab0.nii.gz"))
    return _evaluate(m), ["lab0.nii.gz", "3D"]


def _case_mask_on_another_grid(tmp_path):
    m = _edit_manifest(tmp_path, lambda d: d.update(mask="mask.nii.gz"))
    sitk.WriteImage(sitk.Image([17, 23], sitk.sitkUInt8) + 1, str(tmp_path / "mask.nii.gz"))
    return _evaluate(m), ["mask.nii.gz", "grid"]


def _case_registration_not_a_mapping(tmp_path):
    m = _edit_manifest(tmp_path, lambda d: d["registrations"].update(truth="fields/*.nii.gz"))
    return _evaluate(m), ["registrations.truth"]


def _case_distance_unknown(tmp_path):
    m = _edit_manifest(tmp_path, lambda d: None)
    return _evaluate(m) + ["--distance", "l3"], ["--distance", "l3"]


def _case_specificity_too_few_images(tmp_path):
    make_case(tmp_path)
    args = ["specificity", str(tmp_path / "img0.nii.gz"), str(tmp_path / "img1.nii.gz")]
    return args + ["--samples", "200"], ["at least 3"]


def _case_specificity_exponent_zero(tmp_path):
    make_case(tmp_path)
    paths = [str(tmp_path / f"img{i}.nii.gz") for i in range(4)]
    return ["specificity", *paths, "--exponent", "0"], ["--exponent"]


def _case_specificity_images_on_different_grids(tmp_path):
    make_case(tmp_path)
    paths = [str(tmp_path / f"img{i}.nii.gz") for i in range(4)]
    sitk.WriteImage(sitk.Image([31, 40], sitk.sitkFloat32), paths[2])
    return ["specificity", *paths, "--samples", "200"], ["img2.nii.gz"]


def _case_overlap_missing_label_map(tmp_path):
    make_case(tmp_path)
    paths = [str(tmp_path / f"lab{i}.nii.gz") for i in range(3)] + [str(tmp_path / "gone.nii.gz")]
    return ["overlap", *paths], ["gone.nii.gz", "not found"]


def _case_diagnose_missing_manifest(tmp_path):
    args = ["diagnose", str(tmp_path / "nowhere.yaml"), "--registration", "truth"]
    return args, ["nowhere.yaml", "not found"]


CASES = {
    name[len("_case_") :]: fn for name, fn in list(globals().items()) if name.startswith("_case_")
}


@pytest.mark.parametrize("case", list(CASES))
def test_bad_input_is_one_line_exit_2_nothing_written(tmp_path, capsys, case):
    args, fragments = CASES[case](tmp_path)
    out = tmp_path / "out"
    args = [*args, "--out", str(out)] if args[0] in ("evaluate", "diagnose") else args
    if args[0] in ("specificity", "overlap"):
        args = [*args, "--json", str(out / "numbers.json")]
    before = {p for p in tmp_path.rglob("*")}
    code, err = run_cli(args, capsys)
    assert code == 2, err
    assert_one_line(err, *fragments)
    assert {p for p in tmp_path.rglob("*")} == before  # nothing written, nothing left behind
