"""What `nrreval evaluate --save-resampled` writes, `nrreval overlap` reads as evaluate meant it.

The saved membership images have one component per nonzero label value and no background
component; a sidecar ``memberships_###.json`` (and the NIfTI description) names the labels.
The reference for every figure is evaluate's own results.json, not this toolkit's reader.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import SimpleITK as sitk
import yaml
from test_bad_inputs import assert_one_line
from test_evaluate import SIZE, make_case

from itk_nrreval.cli import main
from itk_nrreval.io._images import Geometry
from itk_nrreval.io._membership_files import membership_file_labels, write_membership_image
from itk_nrreval.measures.overlap import WEIGHTINGS

# non-consecutive values, so that a component index read as a label value shows
RELABEL = {1: 2, 2: 5, 3: 9}


def _evaluated_case(folder, relabel: dict[int, int], *, mask: np.ndarray | None = None):
    """make_case with its labels renamed by `relabel` (0 stays 0, absent keys become 0),
    only the "truth" registration (and `mask` on the common grid, numpy (y, x)), evaluated
    with --save-resampled; returns (out, results)."""
    data = make_case(folder)
    data["registrations"] = {"truth": data["registrations"]["truth"]}
    if mask is not None:
        img = sitk.GetImageFromArray(mask.astype(np.uint8))
        img.CopyInformation(sitk.ReadImage(str(folder / "template.nii.gz")))
        sitk.WriteImage(img, str(folder / "mask.nii.gz"))
        data["mask"] = "mask.nii.gz"
    (folder / "manifest.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    for name in data["labels"]:
        img = sitk.ReadImage(str(folder / name))
        arr = sitk.GetArrayFromImage(img)
        renamed = np.zeros_like(arr)
        for old, new in relabel.items():
            renamed[arr == old] = new
        out = sitk.GetImageFromArray(renamed)
        out.CopyInformation(img)
        sitk.WriteImage(out, str(folder / name))
    out = folder / "out"
    args = ["evaluate", str(folder / "manifest.yaml"), "--out", str(out), "--samples", "50"]
    code = main([*args, "--save-resampled", "--quiet", "--no-figures", "--no-confidence"])
    assert code == 0
    return out, json.loads((out / "results.json").read_text())


@pytest.fixture(scope="module")
def evaluated(tmp_path_factory):
    return _evaluated_case(tmp_path_factory.mktemp("case"), RELABEL)


def _overlap(files, tmp_path, *extra) -> dict:
    report = tmp_path / "overlap.json"
    code = main(["overlap", *map(str, files), "--json", str(report), "--quiet", *extra])
    assert code == 0
    return json.loads(report.read_text())


def _saved(out, kind="memberships"):
    return sorted((out / "resampled" / "truth").glob(f"{kind}_*.nii.gz"))


def _assert_same_as_evaluate(ov: dict, results: dict, labels: list[int]) -> None:
    assert [row["label"] for row in ov["labels"]] == labels
    expected = results["registrations"]["truth"]["overlap"]
    for w in WEIGHTINGS:
        assert ov["generalized"][w] == pytest.approx(expected[w], abs=1e-9), w


def test_overlap_of_saved_memberships_equals_evaluate(evaluated, tmp_path):
    out, results = evaluated
    assert results["registrations"]["truth"]["coverage"]["evaluated"] == 1.0  # same voxels
    labels = [v for v in results["options"]["label_values"] if v != 0]
    assert labels == sorted(RELABEL.values())
    ov = _overlap(_saved(out), tmp_path)
    _assert_same_as_evaluate(ov, results, labels)


def test_sidecar_names_the_labels_and_no_background(evaluated):
    out, _ = evaluated
    files = _saved(out)
    assert len(files) == 6
    for path in files:
        sidecar = json.loads(path.with_name(path.name.replace(".nii.gz", ".json")).read_text())
        assert sidecar["kind"] == "memberships"
        assert sidecar["labels"] == [2, 5, 9]
        assert sidecar["background"] is False
        img = sitk.ReadImage(str(path))
        assert img.GetNumberOfComponentsPerPixel() == 3
        assert img.GetMetaData("descrip").startswith("nrreval memberships")


def test_header_alone_is_enough_when_the_sidecar_is_lost(evaluated, tmp_path):
    out, results = evaluated
    copies = []
    for path in _saved(out):
        copies.append(tmp_path / path.name)
        shutil.copy(path, copies[-1])  # the image alone, without its sidecar
    ov = _overlap(copies, tmp_path)
    _assert_same_as_evaluate(ov, results, [2, 5, 9])


def test_single_label_memberships_are_not_read_as_a_crisp_map(tmp_path):
    # one component: NIfTI gives it back as a scalar float image
    out, results = _evaluated_case(tmp_path, {2: 7})
    files = _saved(out)
    assert sitk.ReadImage(str(files[0])).GetNumberOfComponentsPerPixel() == 1
    ov = _overlap(files, tmp_path)
    _assert_same_as_evaluate(ov, results, [7])


def test_evaluated_region_is_saved_and_reproduces_evaluate_under_a_mask(tmp_path):
    mask = np.zeros((SIZE, SIZE), bool)
    mask[8:30, 5:33] = True  # cuts through the labels: the figure differs from the grid's
    out, results = _evaluated_case(tmp_path, RELABEL, mask=mask)
    region = out / "resampled" / "region.nii.gz"
    np.testing.assert_array_equal(sitk.GetArrayFromImage(sitk.ReadImage(str(region))), mask)
    everywhere = _overlap(_saved(out), tmp_path)
    expected = results["registrations"]["truth"]["overlap"]["inverse_volume"]
    assert abs(everywhere["generalized"]["inverse_volume"] - expected) > 1e-3
    ov = _overlap(_saved(out), tmp_path, "--mask", str(region))
    _assert_same_as_evaluate(ov, results, [2, 5, 9])


def test_saved_images_say_what_they_are(evaluated):
    out, _ = evaluated
    for path in _saved(out, "image"):
        sidecar = json.loads(path.with_name(path.name.replace(".nii.gz", ".json")).read_text())
        assert sidecar["kind"] == "resampled image"
        assert sidecar["outside_field_of_view"] == 0.0
        assert sitk.ReadImage(str(path)).GetMetaData("descrip").startswith("nrreval resampled")


def _copy_saved(out, folder):
    folder.mkdir()
    for path in sorted((out / "resampled" / "truth").glob("memberships_*")):
        shutil.copy(path, folder / path.name)
    return sorted(folder.glob("memberships_*.nii.gz"))


def _bad_sidecar_labels(files):
    sidecar = files[1].with_name("memberships_001.json")
    data = json.loads(sidecar.read_text())
    data["labels"] = [2, 5]
    sidecar.write_text(json.dumps(data))
    return files, ["memberships_001.json", "names 2 labels", "3 components"]


def _other_labels(files):
    sidecar = files[1].with_name("memberships_001.json")
    data = json.loads(sidecar.read_text())
    data["labels"] = [2, 5, 8]
    sidecar.write_text(json.dumps(data))
    return files, ["memberships_001.nii.gz", "[2, 5, 8]", "[2, 5, 9]"]


def _header_without_labels(files):
    # more labels than the NIfTI description holds: the sidecar is then the only record
    img = sitk.ReadImage(str(files[2]))
    img.SetMetaData("ITK_FileNotes", "nrreval memberships; labels in memberships_002.json")
    sitk.WriteImage(img, str(files[2]), True)
    files[2].with_name("memberships_002.json").unlink()
    return files, ["memberships_002.nii.gz", "memberships_002.json", "missing"]


def _mixed_with_a_third_party_file(files):
    arr = np.moveaxis(sitk.GetArrayFromImage(sitk.ReadImage(str(files[0]))), -1, 0)
    third = sitk.GetImageFromArray(np.moveaxis(arr, 0, -1), isVector=True)
    third.CopyInformation(sitk.ReadImage(str(files[0])))
    path = files[0].with_name("third_party.nii.gz")
    sitk.WriteImage(third, str(path), True)
    return [*files, path], ["third_party.nii.gz", "does not say which labels"]


def _include_background(files):
    return [*files, "--include-background"], ["memberships_000.nii.gz", "no background"]


@pytest.mark.parametrize(
    "damage",
    [
        _bad_sidecar_labels,
        _other_labels,
        _header_without_labels,
        _mixed_with_a_third_party_file,
        _include_background,
    ],
    ids=lambda f: f.__name__.strip("_"),
)
def test_inconsistent_membership_files_are_refused(evaluated, tmp_path, capsys, damage):
    out, _ = evaluated
    args, fragments = damage(_copy_saved(out, tmp_path / "m"))
    report = tmp_path / "overlap.json"
    capsys.readouterr()
    code = main(["overlap", *map(str, args), "--json", str(report), "--quiet"])
    assert code == 2
    assert_one_line(capsys.readouterr().err, *fragments)
    assert not report.exists()


def test_many_labels_are_named_by_the_sidecar_when_the_header_is_too_short(tmp_path):
    labels = list(range(100, 130))  # "100,101,..." is longer than NIfTI's 79 characters
    rng = np.random.default_rng(1)
    grid = Geometry((3, 4), (1.0, 1.0), (0.0, 0.0), (1.0, 0.0, 0.0, 1.0))
    path = tmp_path / "m.nii.gz"
    write_membership_image(
        path, rng.random((30, 4, 3)).astype(np.float32) / 30, labels=labels, geometry=grid
    )
    assert sitk.ReadImage(str(path)).GetMetaData("descrip") == (
        "nrreval memberships; labels in m.json; no background"
    )
    assert membership_file_labels(path, name="m") == tuple(labels)
