"""`nrreval validate` on a manifest: 3D integer labels (sparse, large, missing in one image),
slices of the common frame, impossible requests, valid JSON, and ValidationResult.write."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import SimpleITK as sitk
import yaml

from itk_nrreval._errors import InputError
from itk_nrreval.cli import main
from itk_nrreval.experiments.perturbation import (
    OUTPUT_FILES,
    ValidationRow,
    manifest_set,
    summarize,
    validate,
    validate_manifest,
)
from itk_nrreval.measures.overlap import overlap_table

SIZE = (20, 18, 16)  # ITK (x, y, z)
SPACING = (2.0, 2.0, 2.0)
VALUES = (2, 1000, 14175)  # FreeSurfer-like: large and sparse
N = 4


def strict_json(text: str):
    def refuse(name):
        raise ValueError(f"not JSON: {name}")

    return json.loads(text, parse_constant=refuse)


def phantom(i: int):
    """Image i and its label map (numpy order): three blobs, shifted a little per image;
    image 3 has no label 1000."""
    rng = np.random.default_rng(i)
    z, y, x = np.indices(SIZE[::-1]).astype(float)
    lab = np.zeros(SIZE[::-1], dtype=np.uint16)
    centres = [(8, 9, 10), (5, 6, 6), (10, 12, 14)]
    for v, c in zip(VALUES, centres, strict=True):
        if i == 3 and v == 1000:
            continue
        c = np.array(c) + rng.uniform(-1, 1, 3)
        lab[(z - c[0]) ** 2 + (y - c[1]) ** 2 + (x - c[2]) ** 2 < 3.2**2] = v
    img = (
        100.0 * (lab > 0) + 30.0 * (lab == 1000) + 20 * np.sin(x / 3) + rng.normal(0, 2, lab.shape)
    )
    return img.astype(np.float32), lab


def grid_image(arr):
    im = sitk.GetImageFromArray(arr)
    im.SetSpacing(SPACING)
    im.SetOrigin((-10.0, 4.0, 7.0))
    return im


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    folder = tmp_path_factory.mktemp("manifest3d")
    images, labels, transforms = [], [], []
    for i in range(N):
        img, lab = phantom(i)
        sitk.WriteImage(grid_image(img), str(folder / f"img{i}.nii.gz"))
        sitk.WriteImage(grid_image(lab), str(folder / f"lab{i}.nii.gz"))
        sitk.WriteTransform(sitk.AffineTransform(3), str(folder / f"id{i}.tfm"))
        images.append(f"img{i}.nii.gz")
        labels.append(f"lab{i}.nii.gz")
        transforms.append(f"id{i}.tfm")
    data = {
        "images": images,
        "labels": labels,
        "registrations": {"truth": {"reference": "img0.nii.gz", "transforms": transforms}},
    }
    (folder / "manifest.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    return folder


KW = dict(repeats=1, n_samples=300, weightings=("volume", "inverse_volume"), progress=False)


def test_memberships_have_one_channel_per_present_value(case):
    images, members, grid = manifest_set(case / "manifest.yaml", progress=False)
    assert images.shape == (N, *SIZE[::-1])
    assert members.shape == (N, 1 + len(VALUES), *SIZE[::-1])  # not 14176 channels
    np.testing.assert_allclose(members.sum(axis=1), 1.0, atol=1e-6)
    assert not members[3, 2].any()  # image 3 lacks label 1000 (channel 2)
    assert grid.spacing == SPACING


def test_validate_a_3d_manifest_where_one_image_lacks_a_label(case):
    res = validate_manifest(case / "manifest.yaml", displacements=(0.0, 0.05, 0.1), **KW)
    assert [r.displacement for r in res.rows] == [0.0, 0.05, 0.1]
    assert res.shape == SIZE[::-1] and res.spacing == SPACING
    # isotropic 2 mm voxels: d in mm is exactly twice d in pixels
    for row in res.rows:
        assert row.displacement_mm == pytest.approx(2.0 * row.displacement, rel=1e-9, abs=0)
    # the unperturbed overlap is the crisp overlap of the label files themselves
    labels = [str(case / f"lab{i}.nii.gz") for i in range(N)]
    table = overlap_table(labels)
    for w in ("volume", "inverse_volume"):
        assert res.rows[0].overlap[w] == pytest.approx(table.generalized(w), rel=1e-6)
    # warping moves labels: overlap falls, but stays well defined
    assert res.rows[2].overlap["volume"] < res.rows[0].overlap["volume"]
    assert all(0 < r.min_jacobian <= 1 for r in res.rows)
    # issue 44: the result says whose registered set it perturbed (the common frame)
    assert res.parameters["registration"] == "truth"
    # a loaded Manifest is used as it is (nrreval validate loads it once, not twice): the
    # same numbers, and its file as the source
    from itk_nrreval.io.manifest import load_manifest

    loaded = load_manifest(case / "manifest.yaml")
    again = validate_manifest(loaded, displacements=(0.0, 0.05, 0.1), **KW)
    assert [r.to_dict() for r in again.rows] == [r.to_dict() for r in res.rows]
    assert again.source == str(loaded.source) and loaded.source is not None


def test_large_label_values_give_the_same_numbers_as_small_ones():
    rng = np.random.default_rng(0)
    imgs, small = [], []
    for i in range(N):
        img, lab = phantom(i)
        imgs.append(img)
        small.append(np.searchsorted([0, *VALUES], lab))
    imgs, small = np.stack(imgs), np.stack(small)
    big = np.array([0, *VALUES])[small]
    kw = dict(displacements=(0.0, 0.1), spacing=SPACING, **KW)
    a = validate(imgs, big, **kw)
    b = validate(imgs, small, **kw)
    assert a.rows == b.rows
    del rng


def test_memberships_with_rounding_are_accepted_real_violations_refused():
    imgs, labs = zip(*(phantom(i) for i in range(N)), strict=True)
    imgs, labs = np.stack(imgs), np.stack(labs)
    values = np.array([0, *VALUES])
    m = (labs[:, None] == values[None, :, None, None, None]).astype(np.float32)
    m[0, 1, 0, 0, 0] = 1.0 + 3e-7  # float32 resampling rounding
    res = validate(imgs, m, displacements=(0.0, 0.05), spacing=SPACING, **KW)
    assert len(res.rows) == 2
    m[0, 1, 0, 0, 0] = 1.2
    with pytest.raises(InputError, match=r"memberships must lie in \[0, 1\]"):
        validate(imgs, m, displacements=(0.0,), **KW)


def run(args, capsys):
    code = main(args)
    cap = capsys.readouterr()
    return code, cap.out, cap.err


def test_cli_on_the_manifest_writes_valid_json_with_null_for_undefined(case, tmp_path, capsys):
    out = tmp_path / "val"
    args = ["validate", str(case / "manifest.yaml"), "--out", str(out),
            "--displacements", "0,0.05", "--repeats", "1", "--samples", "300",
            "--weighting", "volume", "--no-progress"]  # fmt: skip
    code, printed, err = run(args, capsys)
    assert code == 0, err
    from itk_nrreval._output import MARKER

    assert sorted(p.name for p in out.iterdir()) == sorted([MARKER, *OUTPUT_FILES])
    data = strict_json((out / "validation.json").read_text())
    # no d >= 0.375: the correlations are undefined, and JSON says null, not NaN
    assert data["summary"]["pearson_r"] == {"volume": None}
    assert data["summary"]["spearman"] is None and data["summary"]["pearson_ci"]["volume"] == [
        None,
        None,
    ]
    assert data["spacing"] == list(SPACING) and data["parameters"]["section"] is None
    assert "undefined" in printed
    # result.write writes exactly what the CLI writes
    res = validate_manifest(
        case / "manifest.yaml",
        displacements=(0.0, 0.05),
        repeats=1,
        n_samples=300,
        weightings=("volume",),
        progress=False,
        source=str(case / "manifest.yaml"),
    )
    again = tmp_path / "again"
    assert [p.name for p in res.write(again)] == list(OUTPUT_FILES)
    for name in ("validation.csv", "validation.json"):
        assert (again / name).read_text() == (out / name).read_text()
    for name in OUTPUT_FILES[2:]:
        assert (again / name).stat().st_size > 1000
    assert not list(again.glob(".*tmp*"))  # no temporary left behind


def test_cli_slices_the_common_frame(case, tmp_path, capsys):
    for spec, axis, index, shape in (("z", "z", 8, (18, 20)), ("x:3", "x", 3, (16, 18))):
        out = tmp_path / spec.replace(":", "_")
        args = ["validate", str(case / "manifest.yaml"), "--out", str(out), "--slice", spec,
                "--displacements", "0,0.2", "--repeats", "1", "--samples", "200",
                "--weighting", "volume", "--no-progress"]  # fmt: skip
        code, printed, err = run(args, capsys)
        assert code == 0, err
        data = strict_json((out / "validation.json").read_text())
        assert data["parameters"]["section"] == {"axis": axis, "index": index}
        assert data["shape"] == list(shape) and data["spacing"] == [2.0, 2.0]
        assert f"slice {axis}:{index}" in printed
    # the z slice's unperturbed overlap is that of the label maps' slice itself
    labels = np.stack([sitk.GetArrayFromImage(sitk.ReadImage(str(case / f"lab{i}.nii.gz")))
                       for i in range(N)])[:, 8].astype(np.int64)  # fmt: skip
    data = strict_json((tmp_path / "z" / "validation.json").read_text())
    ref = overlap_table(labels, spacing=(2.0, 2.0)).generalized("volume")
    assert data["rows"][0]["overlap_volume"] == pytest.approx(ref, rel=1e-6)


@pytest.mark.parametrize(
    "extra,needle",
    [
        (["--displacements", "0,3"], "largest safe d"),
        (["--slice", "z:99"], "out of range"),
        (["--slice", "w"], "axis must be x, y or z"),
    ],
)
def test_cli_impossible_requests_are_one_line(case, tmp_path, capsys, extra, needle):
    out = tmp_path / "val"
    args = ["validate", str(case / "manifest.yaml"), "--out", str(out), "--repeats", "1",
            "--samples", "200", "--no-progress", *extra]  # fmt: skip
    code, _, err = run(args, capsys)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("nrreval validate: error:"), err
    assert needle in lines[0]
    assert "Traceback" not in err and not (out / "validation.json").exists()
    if needle == "largest safe d":
        assert " px (" in lines[0] and " mm)" in lines[0]


def test_cli_slice_of_2d_synthetic_data_is_refused(tmp_path, capsys):
    code, _, err = run(
        ["validate", "--synthetic", "phantom", "--out", str(tmp_path), "--slice", "z"], capsys
    )
    assert code == 2 and len(err.strip().splitlines()) == 1 and "--dim 3" in err


def test_summary_interval_fit_and_mm_sensitivity_by_hand():
    rng = np.random.default_rng(3)
    rows, d_all, s_all, o_all = [], [], [], []
    for d in (0.0, 0.5, 1.0, 1.5, 2.0):
        for r in range(3):
            s = 10 + 3 * d + rng.normal(0, 0.2)
            o = 0.9 - 0.1 * d + rng.normal(0, 0.01)
            rows.append(ValidationRow(d, r, s, 0.25, {"volume": o}, 1.0, 1.5 * d))
            if d >= 0.375:
                d_all.append(d)
                s_all.append(s)
                o_all.append(o)
    summ = summarize(rows, ["volume"])
    s_all, o_all, d_all = map(np.array, (s_all, o_all, d_all))
    r = np.corrcoef(s_all, o_all)[0, 1]
    z, h = math.atanh(r), 1.959963984540054 / math.sqrt(len(s_all) - 3)
    assert summ.pearson_r["volume"] == pytest.approx(r, rel=1e-12)
    assert summ.pearson_ci["volume"] == pytest.approx((math.tanh(z - h), math.tanh(z + h)))
    assert summ.fit["volume"] == pytest.approx(tuple(np.polyfit(o_all, s_all, 1)), rel=1e-9)
    slope_mm = np.polyfit(1.5 * d_all, s_all, 1)[0]
    assert summ.slope_mm == pytest.approx(slope_mm, rel=1e-9)
    assert summ.sensitivity_mm == pytest.approx(slope_mm / 0.25, rel=1e-9)
    assert summ.slope == pytest.approx(1.5 * slope_mm, rel=1e-9) and summ.n_fit == 12


def test_specificity_is_taken_inside_the_mask_where_every_image_covers(case, tmp_path):
    """As evaluate does: the manifest's mask and the images' fields of view bound the texture
    model. Reference: the images resampled by SimpleITK with NaN outside, the region where
    no image is NaN and the mask is set, and validate() on arrays with that mask."""
    import shutil

    folder = tmp_path / "cropped"
    shutil.copytree(case, folder)
    for i in (1, 2):  # lose the last 5 columns (x), physical positions kept
        path = str(folder / f"img{i}.nii.gz")
        img = sitk.ReadImage(path)
        sitk.WriteImage(sitk.RegionOfInterest(img, [SIZE[0] - 5, *SIZE[1:]], [0, 0, 0]), path)
    box = np.zeros(SIZE[::-1], np.uint8)
    box[2:-2, 3:-3, 1:] = 1
    sitk.WriteImage(grid_image(box), str(folder / "mask.nii.gz"))
    data = yaml.safe_load((folder / "manifest.yaml").read_text())
    data["mask"] = "mask.nii.gz"
    (folder / "manifest.yaml").write_text(yaml.safe_dump(data, sort_keys=False))

    reference = sitk.ReadImage(str(folder / "img0.nii.gz"))
    stack = np.stack(
        [
            sitk.GetArrayFromImage(
                sitk.Resample(
                    sitk.Cast(sitk.ReadImage(str(folder / f"img{i}.nii.gz")), sitk.sitkFloat64),
                    reference,
                    sitk.AffineTransform(3),
                    sitk.sitkLinear,
                    float("nan"),
                )
            )
            for i in range(N)
        ]
    )
    region = ~np.isnan(stack).any(axis=0) & (box > 0)
    assert 0.3 < region.mean() < box.mean() < 1  # both the crop and the mask matter
    _, members, _ = manifest_set(folder / "manifest.yaml", progress=False)
    kw = dict(displacements=(0.0, 0.05), spacing=SPACING, **KW)
    with pytest.warns(
        UserWarning, match=r"specificity is taken on the \d+% of the voxels of the mask"
    ):
        got = validate_manifest(
            folder / "manifest.yaml", **{k: v for k, v in kw.items() if k != "spacing"}
        )
    expected = validate(np.nan_to_num(stack), members, mask=region, **kw)
    unmasked = validate(np.nan_to_num(stack), members, **kw)
    for g, e, u in zip(got.rows, expected.rows, unmasked.rows, strict=True):
        assert g.specificity == pytest.approx(e.specificity, rel=1e-9)
        assert g.overlap == pytest.approx(e.overlap, rel=1e-9)
        assert g.specificity != pytest.approx(u.specificity, rel=1e-3)  # the region matters
