"""One set of input checks for every command (issue 25, items 4, 5 and 9).

Each command that reads images refuses the same things with the same one-line message
(exit code 2, the file named) and warns about the same things: a 4D image, a label map
given as an image. A manifest whose images disagree names the odd one out. Through the CLI
in process, on small files written here.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import h5py
import numpy as np
import pytest
import SimpleITK as sitk
import yaml
from test_bad_inputs import assert_one_line, run_cli

from data_synth import make_population, write_population
from itk_nrreval import InputError
from itk_nrreval.cli import main
from itk_nrreval.io.manifest import load_manifest

# evaluate's warning, as tests/test_bad_inputs.py pins it (one line, after the CLI's prefix)
LABEL_LIKE = (
    r"the image holds only \d+ distinct integer values: is it a label map given as an image\?"
)


def write_2d(path: Path, seed: int, *, size: int = 16) -> Path:
    """A smooth random float 2D image (every value distinct)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:size, 0:size] / size
    arr = np.sin(3 * x + rng.uniform(0, 3)) + np.cos(2 * y) + 0.1 * rng.random((size, size))
    sitk.WriteImage(sitk.GetImageFromArray(arr.astype(np.float32)), str(path))
    return path


def write_label_map(path: Path, seed: int, *, size: int = 16) -> Path:
    """A uint8 2D label map with labels 0..3 (a disc and two squares, shifted per seed)."""
    y, x = np.mgrid[0:size, 0:size]
    lab = np.zeros((size, size), np.uint8)
    lab[(y - 8) ** 2 + (x - 8) ** 2 < 30] = 1
    lab[2 : 5 + seed % 2, 2:5] = 2
    lab[10:13, 11 : 14 - seed % 2] = 3
    sitk.WriteImage(sitk.GetImageFromArray(lab), str(path))
    return path


def write_4d(path: Path, seed: int, *, integer: bool = False) -> Path:
    """A true 4D image (three 3D volumes joined along t), as a 4D NIfTI holds an fMRI series."""
    rng = np.random.default_rng(seed)
    shape = (4, 5, 6)
    vols = [
        rng.integers(0, 3, shape).astype(np.uint8)
        if integer
        else rng.random(shape).astype(np.float32)
        for _ in range(3)
    ]
    image = sitk.JoinSeries([sitk.GetImageFromArray(v) for v in vols])
    assert image.GetDimension() == 4 and image.GetNumberOfComponentsPerPixel() == 1
    sitk.WriteImage(image, str(path))
    return path


def warnings_of(err: str) -> list[str]:
    return [ln for ln in err.splitlines() if ": warning: " in ln]


# ----------------------------------------------------------------------------- item 4


def test_specificity_refuses_4d_images(tmp_path, capsys):
    paths = [str(write_4d(tmp_path / f"v{i}.nii.gz", i)) for i in range(4)]
    code, err = run_cli(["specificity", *paths, "--samples", "200", "--quiet"], capsys)
    assert code == 2
    assert_one_line(err, paths[0], "is 4D", "2D or 3D")


def test_specificity_names_a_4d_image_among_2d_ones(tmp_path, capsys):
    paths = [str(write_2d(tmp_path / f"i{i}.nii.gz", i)) for i in range(4)]
    paths[2] = str(write_4d(tmp_path / "odd.nii.gz", 9))
    code, err = run_cli(["specificity", *paths, "--samples", "200", "--quiet"], capsys)
    assert code == 2
    assert_one_line(err, paths[2], "is 4D", "2D or 3D")


def test_overlap_refuses_4d_label_maps(tmp_path, capsys):
    paths = [str(write_4d(tmp_path / f"l{i}.nii.gz", i, integer=True)) for i in range(3)]
    code, err = run_cli(["overlap", *paths, "--quiet"], capsys)
    assert code == 2
    assert_one_line(err, paths[0], "is 4D", "2D or 3D")


def test_specificity_warns_about_label_maps_given_as_images_as_evaluate_does(tmp_path, capsys):
    paths = [str(write_2d(tmp_path / f"i{i}.nii.gz", i)) for i in range(4)]
    paths[1] = str(write_label_map(tmp_path / "lab1.nii.gz", 1))
    code, err = run_cli(["specificity", *paths, "--samples", "200", "--quiet"], capsys)
    assert code == 0, err
    found = warnings_of(err)
    assert len(found) == 1, err
    expected = rf"^nrreval specificity: warning: {re.escape(paths[1])}: {LABEL_LIKE}$"
    assert re.match(expected, found[0]), found[0]
    assert "Traceback" not in err


def _identity_manifest(folder: Path, images: list[Path], *, reference_index: int = 0) -> Path:
    """A manifest of `images` with one identity registration to image `reference_index`."""
    tfm = []
    for i in range(len(images)):
        sitk.WriteTransform(sitk.AffineTransform(2), str(folder / f"id{i}.tfm"))
        tfm.append(f"id{i}.tfm")
    data = {
        "images": [p.name for p in images],
        "registrations": {
            "reg": {
                "reference": images[reference_index].name,
                "reference_index": reference_index,
                "transforms": tfm,
            }
        },
    }
    path = folder / "manifest.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def test_diagnose_warns_about_a_label_map_given_as_an_image(tmp_path, capsys):
    images = [write_2d(tmp_path / f"i{i}.nii.gz", i) for i in range(5)]
    images[3] = write_label_map(tmp_path / "lab3.nii.gz", 3)
    manifest = _identity_manifest(tmp_path, images)
    args = ["diagnose", str(manifest), "--registration", "reg", "--samples", "20", "--quiet"]
    code, err = run_cli([*args, "--out", str(tmp_path / "out")], capsys)
    assert code == 0, err
    found = warnings_of(err)
    assert len(found) == 1, err
    assert re.match(rf"^nrreval diagnose: warning: \S*lab3\.nii\.gz: {LABEL_LIKE}$", found[0])


# ----------------------------------------------------------------------------- item 5


def test_a_4d_image_in_a_manifest_is_named_as_the_odd_one_out(tmp_path, capsys):
    images = [write_2d(tmp_path / f"s{i:02d}.nii.gz", i) for i in range(12)]
    images[0] = write_4d(tmp_path / "s00.nii.gz", 0)
    manifest = _identity_manifest(tmp_path, images, reference_index=1)
    code, err = run_cli(
        ["evaluate", str(manifest), "--out", str(tmp_path / "out"), "--quiet"], capsys
    )
    assert code == 2
    assert_one_line(err, "images[0]: s00.nii.gz is 4D; the other 11 images are 2D")
    for i in range(1, 12):  # no other image is blamed
        assert f"images[{i}]" not in err, err
    assert "problems" not in err


def test_a_manifest_of_4d_images_is_refused_in_one_problem(tmp_path, capsys):
    images = [write_4d(tmp_path / f"s{i:02d}.nii.gz", i) for i in range(4)]
    manifest = _identity_manifest(tmp_path, images)
    code, err = run_cli(
        ["evaluate", str(manifest), "--out", str(tmp_path / "out"), "--quiet"], capsys
    )
    assert code == 2
    assert_one_line(err, str(manifest), "all 4 images are 4D", "s00.nii.gz", "2D or 3D")


# ----------------------------------------------------------------------------- item 9


@pytest.fixture(scope="module")
def t1_t2(tmp_path_factory):
    """Three subjects imaged in T1 and T2 (small), as `nrreval synth --contrasts t1,t2` writes
    them: the manifest lists every T1 before every T2, a shell glob lists them by subject."""
    population = make_population(
        "phantom", dim=2, n=3, seed=0, spacing=4.0, size=48, contrasts=("t1", "t2")
    )
    folder = tmp_path_factory.mktemp("t1_t2")
    manifest = write_population(population, folder, montage=False, progress=False)
    globbed = sorted(str(p) for p in (folder / "img").glob("*.nii.gz"))
    assert [Path(p).name for p in globbed[:2]] == ["s00_t1.nii.gz", "s00_t2.nii.gz"]
    return manifest, globbed


def test_register_matches_images_given_in_shell_order_to_the_manifest(t1_t2, capsys):
    manifest, globbed = t1_t2
    before = load_manifest(manifest)
    groups = [Path(p).name[4:6] for p in globbed]  # --groups in --images order: t1 t2 t1 ...
    out = manifest.parent / "per-group"
    code = main(
        [
            "register",
            *("--method", "multimodal", "--strategy", "per-group", "--engine", "simpleitk"),
            *("--images", *globbed, "--groups", *groups, "--out", str(out), "--no-progress"),
        ]
    )
    assert code == 0, capsys.readouterr().err
    m = load_manifest(manifest)
    assert m.images == before.images and m.groups == before.groups == ("t1",) * 3 + ("t2",) * 3
    reg = m.registrations["multimodal-per-group"]
    for image, chain in zip(m.images, reg.transforms, strict=True):  # each image its transform
        assert chain[0].name.endswith(f"_{image.name.removesuffix('.nii.gz')}.h5"), chain
    assert m.groups[reg.reference_index] == "t1"  # the first group's image is the frame


def test_register_names_the_images_that_do_not_match_the_manifest(t1_t2, tmp_path, capsys):
    manifest, globbed = t1_t2
    stranger = tmp_path / "s09_t1.nii.gz"
    stranger.write_bytes(Path(globbed[0]).read_bytes())
    given = [p for p in globbed if not p.endswith("s01_t2.nii.gz")] + [str(stranger)]
    out = tmp_path / "out"
    args = ["register", "--method", "multimodal", "--strategy", "per-group", "--images", *given]
    code, err = run_cli([*args, "--manifest", str(manifest), "--out", str(out)], capsys)
    assert code == 2
    assert_one_line(
        err,
        f"{stranger} is not one of its images",
        "images[4] img/s01_t2.nii.gz (group t2) is not given",
    )
    assert not out.exists()  # refused before any registration


def _oblique_field(dim: int, size: tuple[int, ...]) -> sitk.Image:
    rng = np.random.default_rng(dim)
    field = sitk.GetImageFromArray(rng.normal(size=(*size[::-1], dim)), isVector=True)
    field.SetSpacing([0.8 + 0.3 * k for k in range(dim)])
    field.SetOrigin([-5.0 + k for k in range(dim)])
    q, _ = np.linalg.qr(rng.normal(size=(dim, dim)))
    field.SetDirection(q.reshape(-1).tolist())
    return field


@pytest.mark.parametrize("dim", [2, 3])
def test_hdf5_transform_dimension_from_the_layout_is_itks(tmp_path, dim):
    """The manifest check reads an HDF5 transform's dimension from its layout (the fields'
    values are not read); it must be what ITK reads whole, and a file whose layout is not
    one it knows, or whose counts are off, must be left to ITK (None)."""
    from itk_nrreval.io._itk_hdf5 import transform_dimension as _hdf5_transform_dimension

    size = (7, 5, 4)[:dim]
    affine = sitk.AffineTransform(dim)
    affine.SetMatrix(np.eye(dim).reshape(-1) * 1.1)
    field = sitk.DisplacementFieldTransform(_oblique_field(dim, size))
    composite = sitk.CompositeTransform([affine])
    composite.AddTransform(sitk.DisplacementFieldTransform(_oblique_field(dim, size)))
    known = {"affine": affine, "field": field, "composite": composite}
    for name, t in known.items():
        path = tmp_path / f"{name}.h5"
        sitk.WriteTransform(t, str(path))
        assert _hdf5_transform_dimension(path) == sitk.ReadTransform(str(path)).GetDimension()
    bspline = sitk.BSplineTransformInitializer(sitk.Image([9] * dim, sitk.sitkFloat32), [3] * dim)
    sitk.WriteTransform(bspline, str(tmp_path / "bspline.hdf5"))
    assert _hdf5_transform_dimension(tmp_path / "bspline.hdf5") is None  # read whole instead
    short = tmp_path / "short.h5"
    sitk.WriteTransform(composite, str(short))
    with h5py.File(short, "r+") as f:
        n = len(f["TransformGroup/2/TransformParameters"])
        del f["TransformGroup/2/TransformParameters"]
        f["TransformGroup/2/TransformParameters"] = np.zeros(n - 1)
    assert _hdf5_transform_dimension(short) is None
    with pytest.raises(RuntimeError):  # what the check then reports
        sitk.ReadTransform(str(short))
    (tmp_path / "text.h5").write_text("not HDF5\n")
    assert _hdf5_transform_dimension(tmp_path / "text.h5") is None


# ----------------------------------------------------------------------------- issue 44
# Inputs accepted until now that change the numbers silently: refused by the manifest's
# upfront check (one line, exit 2, nothing written), or warned about where a legitimate use
# exists. A small 3D cohort on a realistic grid: anisotropic voxels, an origin far from 0,
# an oblique direction.

SIZE_3D = (14, 12, 8)  # ITK (x, y, z)
SPACING_3D = (1.2, 0.9, 2.5)  # mm
ORIGIN_3D = (-61.5, 14.25, 103.0)  # mm, LPS


def _rotation(axis, degrees: float) -> np.ndarray:
    """The rotation by `degrees` about `axis` (Rodrigues)."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    cross = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    t = np.radians(degrees)
    return np.eye(3) + np.sin(t) * cross + (1 - np.cos(t)) * cross @ cross


DIRECTION_3D = _rotation((1.0, 2.0, 3.0), 25.0)


def _on_grid(arr: np.ndarray, *, spacing=SPACING_3D, origin=ORIGIN_3D) -> sitk.Image:
    """`arr` (numpy (z, y, x)) as an image on the cohort's oblique grid (or `spacing`/`origin`)."""
    img = sitk.GetImageFromArray(arr)
    img.SetSpacing(spacing)
    img.SetOrigin(origin)
    img.SetDirection(DIRECTION_3D.reshape(-1).tolist())
    return img


def _subject_arrays(i: int) -> tuple[np.ndarray, np.ndarray]:
    """Subject i's float32 image and int16 label map (labels 1..3 in every subject)."""
    rng = np.random.default_rng(100 + i)
    z, y, x = np.mgrid[0 : SIZE_3D[2], 0 : SIZE_3D[1], 0 : SIZE_3D[0]].astype(float)
    labels = np.zeros(SIZE_3D[::-1], np.int16)
    labels[((x - 7) / 5) ** 2 + ((y - 6) / 4.5) ** 2 + ((z - 3.5) / 3) ** 2 <= 1] = 1
    labels[2:5, 3 : 6 + i % 2, 2:5] = 2
    labels[3:6, 6:9, 9 : 12 - i % 2] = 3
    image = 100.0 * (labels == 1) + 160.0 * (labels == 2) + 60.0 * (labels == 3)
    image = image * rng.uniform(0.9, 1.1) + rng.normal(0.0, 4.0, image.shape)
    return image.astype(np.float32), labels


def _cohort(folder: Path, n: int = 5, *, labels: bool = True) -> dict:
    """Write n subjects (img{i}.nii.gz, lab{i}.nii.gz) and an identity registration; return
    the manifest's data (written to folder/manifest.yaml by :func:`_write`)."""
    data: dict = {"images": [], "labels": [] if labels else None}
    for i in range(n):
        image, lab = _subject_arrays(i)
        sitk.WriteImage(_on_grid(image), str(folder / f"img{i}.nii.gz"))
        data["images"].append(f"img{i}.nii.gz")
        if labels:
            sitk.WriteImage(_on_grid(lab), str(folder / f"lab{i}.nii.gz"))
            data["labels"].append(f"lab{i}.nii.gz")
        sitk.WriteTransform(sitk.AffineTransform(3), str(folder / f"id{i}.tfm"))
    if not labels:
        del data["labels"]
    tfm = [f"id{i}.tfm" for i in range(n)]
    data["registrations"] = {
        "identity": {"reference": "img0.nii.gz", "reference_index": 0, "transforms": tfm}
    }
    return data


def _write(folder: Path, data: dict) -> Path:
    path = folder / "manifest.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def _refused(folder: Path, capsys, *fragments: str) -> str:
    """evaluate the folder's manifest through the CLI: exit 2, one line holding `fragments`,
    nothing written (refused before any heavy work); the line."""
    out = folder / "out"
    before = set(folder.rglob("*"))
    code, err = run_cli(
        ["evaluate", str(folder / "manifest.yaml"), "--out", str(out), "--samples", "200"]
        + ["--quiet", "--no-figures"],
        capsys,
    )
    assert code == 2, err
    assert_one_line(err, *fragments)
    assert set(folder.rglob("*")) == before  # no output folder, no cache
    return err


def _manifest_error(path: Path) -> str:
    with pytest.raises(InputError) as info:
        load_manifest(path)
    message = str(info.value)
    assert "\n" not in message
    return message


def test_cohort_of_the_issue_44_checks_is_accepted(tmp_path):
    """The baseline: the checks below refuse what they refuse, not this cohort."""
    m = load_manifest(_write(tmp_path, _cohort(tmp_path)))
    assert m.n_images == 5


# ----------------------------------------------------------------------------- item 6


def test_the_same_image_file_listed_twice_is_refused(tmp_path, capsys):
    data = _cohort(tmp_path)
    data["images"][3] = "./img1.nii.gz"  # the same file, written another way
    path = _write(tmp_path, data)
    message = _manifest_error(path)
    assert "images[1]" in message and "images[3]" in message and "img1.nii.gz" in message
    assert "same file" in message
    _refused(tmp_path, capsys, "images[1]", "images[3]", "same file")


def test_the_same_image_linked_under_another_name_is_refused(tmp_path):
    data = _cohort(tmp_path)
    (tmp_path / "alias.nii.gz").symlink_to(tmp_path / "img1.nii.gz")
    data["images"][4] = "alias.nii.gz"
    message = _manifest_error(_write(tmp_path, data))
    assert "images[1]" in message and "images[4]" in message and "alias.nii.gz" in message


def test_two_files_with_the_same_voxels_on_the_same_grid_are_refused(tmp_path, capsys):
    data = _cohort(tmp_path)
    # another file, other bytes (uncompressed), the same image: the same subject twice
    sitk.WriteImage(sitk.ReadImage(str(tmp_path / "img1.nii.gz")), str(tmp_path / "copy.nii"))
    assert (tmp_path / "copy.nii").read_bytes() != (tmp_path / "img1.nii.gz").read_bytes()
    data["images"][3] = "copy.nii"
    message = _manifest_error(_write(tmp_path, data))
    assert "images[3]" in message and "copy.nii" in message
    assert "images[1]" in message and "img1.nii.gz" in message
    _refused(tmp_path, capsys, "images[3]", "copy.nii", "images[1]", "same voxels")


def test_an_image_that_differs_in_one_voxel_is_not_a_duplicate(tmp_path):
    data = _cohort(tmp_path)
    arr = sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / "img1.nii.gz")))
    arr[4, 5, 6] += 1.0
    sitk.WriteImage(_on_grid(arr), str(tmp_path / "near.nii.gz"))
    data["images"][3] = "near.nii.gz"
    assert load_manifest(_write(tmp_path, data)).n_images == 5


# ----------------------------------------------------------------------------- item 7


@pytest.mark.parametrize("value", [0.0, 37.5])
def test_a_constant_image_is_refused(tmp_path, capsys, value):
    data = _cohort(tmp_path)
    flat = np.full(SIZE_3D[::-1], value, np.float32)
    sitk.WriteImage(_on_grid(flat), str(tmp_path / "img2.nii.gz"))
    message = _manifest_error(_write(tmp_path, data))
    assert "images[2]" in message and "img2.nii.gz" in message
    assert f"every voxel is {value:g}" in message
    _refused(tmp_path, capsys, "images[2]", "img2.nii.gz", f"every voxel is {value:g}")


def test_non_finite_and_constant_images_and_others_are_reported_at_once(tmp_path, capsys):
    data = _cohort(tmp_path, n=6)
    arr, _ = _subject_arrays(1)
    arr[2, 3:5, 4] = np.nan
    sitk.WriteImage(_on_grid(arr), str(tmp_path / "img1.nii.gz"))
    arr, _ = _subject_arrays(3)
    arr[0, 0, 0] = np.inf
    sitk.WriteImage(_on_grid(arr), str(tmp_path / "img3.nrrd"))  # not NIfTI: read by ITK
    data["images"][3] = "img3.nrrd"
    sitk.WriteImage(_on_grid(np.zeros(SIZE_3D[::-1], np.int16)), str(tmp_path / "img5.nii.gz"))
    data["registrations"]["identity"]["transforms"][2] = "gone.tfm"  # a header-level problem
    message = _manifest_error(_write(tmp_path, data))
    assert "4 problems" in message, message
    for fragment in ("img1.nii.gz", "img3.nrrd", "NaN or infinite", "img5.nii.gz", "gone.tfm"):
        assert fragment in message, (fragment, message)
    _refused(tmp_path, capsys, "4 problems", "img1.nii.gz", "img3.nrrd", "img5.nii.gz")


def test_evaluation_images_are_checked_as_images(tmp_path):
    data = _cohort(tmp_path)
    data["evaluation_images"] = list(data["images"])
    sitk.WriteImage(_on_grid(np.zeros(SIZE_3D[::-1], np.float32)), str(tmp_path / "t2.nii.gz"))
    data["evaluation_images"][4] = "t2.nii.gz"
    message = _manifest_error(_write(tmp_path, data))
    assert "evaluation_images[4]" in message and "t2.nii.gz" in message


def test_two_images_are_too_few_for_a_model_and_said_upfront(tmp_path, capsys):
    data = _cohort(tmp_path, n=2)
    message = _manifest_error(_write(tmp_path, data))
    assert "2 images" in message and "at least 3" in message
    _refused(tmp_path, capsys, "2 images", "at least 3")


# ----------------------------------------------------------------------------- item 8


def test_negative_label_values_are_refused(tmp_path, capsys):
    data = _cohort(tmp_path)
    _, lab = _subject_arrays(2)
    lab[lab == 3] = -3
    sitk.WriteImage(_on_grid(lab), str(tmp_path / "lab2.nii.gz"))
    message = _manifest_error(_write(tmp_path, data))
    assert "labels[2]" in message and "lab2.nii.gz" in message and "negative" in message
    assert "-3" in message
    _refused(tmp_path, capsys, "labels[2]", "lab2.nii.gz", "negative")


def test_a_label_of_one_subject_only_is_warned_about_not_refused(tmp_path, capsys):
    data = _cohort(tmp_path)
    _, lab = _subject_arrays(3)
    lab[5:7, 2:4, 10:12] = 9  # a lesion, say: legitimate, but it lowers the overlap
    sitk.WriteImage(_on_grid(lab), str(tmp_path / "lab3.nii.gz"))
    path = _write(tmp_path, data)
    with pytest.warns(UserWarning, match=r"label 9 is only in labels\[3\] lab3\.nii\.gz"):
        load_manifest(path)
    out = tmp_path / "out"
    args = ["evaluate", str(path), "--out", str(out), "--samples", "200", "--quiet"]
    code, err = run_cli([*args, "--no-figures", "--no-confidence"], capsys)
    assert code == 0, err
    found = [w for w in warnings_of(err) if "label 9" in w]
    assert len(found) == 1, err
    assert found[0].startswith("nrreval evaluate: warning: ")
    assert "lab3.nii.gz" in found[0]
    # and results.json keeps it, for a pipeline that reads the JSON and not stderr
    kept = json.loads((out / "results.json").read_text())["options"]["manifest_warnings"]
    assert len(kept) == 1 and "label 9 is only in labels[3]" in kept[0], kept
    assert found[0].endswith(kept[0])


def test_a_label_of_one_subject_with_several_images_is_that_subjects(tmp_path):
    """With ``subjects``, a label in both images of one subject is still one subject's."""
    data = _cohort(tmp_path, n=6)
    data["subjects"] = ["a", "a", "b", "b", "c", "c"]
    for i in (0, 1):
        _, lab = _subject_arrays(i)
        lab[5:7, 2:4, 10:12] = 9
        sitk.WriteImage(_on_grid(lab), str(tmp_path / f"lab{i}.nii.gz"))
    with pytest.warns(UserWarning, match=r"label 9 is only in subject 'a'"):
        load_manifest(_write(tmp_path, data))


@pytest.mark.parametrize("how", ["moved", "labels-moved-on-a-larger-grid"])
def test_a_label_map_30_mm_off_its_image_is_refused(tmp_path, capsys, how):
    data = _cohort(tmp_path)
    _, lab = _subject_arrays(2)
    if how == "moved":
        moved = np.asarray(ORIGIN_3D) + 30.0 * DIRECTION_3D[:, 0]  # 30 mm along the image's x
        off = _on_grid(lab, origin=tuple(moved))
    else:  # a grid 25 voxels (30 mm) wider on each side in x, the labels in its left part
        wide = np.zeros((SIZE_3D[2], SIZE_3D[1], SIZE_3D[0] + 50), np.int16)
        wide[..., : SIZE_3D[0]] = lab
        moved = np.asarray(ORIGIN_3D) - 25 * SPACING_3D[0] * DIRECTION_3D[:, 0]
        off = _on_grid(wide, origin=tuple(moved))
    sitk.WriteImage(off, str(tmp_path / "lab2.nii.gz"))
    message = _manifest_error(_write(tmp_path, data))
    assert "labels[2]" in message and "lab2.nii.gz" in message and "images[2]" in message
    assert "np." not in message
    _refused(tmp_path, capsys, "labels[2]", "lab2.nii.gz", "outside")


def test_a_label_map_at_another_resolution_on_the_same_field_of_view_is_accepted(tmp_path):
    data = _cohort(tmp_path)
    _, lab = _subject_arrays(2)
    fine = _on_grid(lab)
    # 2 x 1.5 x 1.6 times coarser, its first voxel's centre where ITK's shrink puts it
    spacing = np.array(SPACING_3D) * (2.0, 1.5, 1.6)
    size = np.ceil(np.array(SIZE_3D) * SPACING_3D / spacing).astype(int)
    origin = np.asarray(ORIGIN_3D) + DIRECTION_3D @ ((spacing - SPACING_3D) / 2)
    coarse = sitk.Resample(
        fine, size.tolist(), sitk.Transform(), sitk.sitkNearestNeighbor, origin.tolist(),
        spacing.tolist(), DIRECTION_3D.reshape(-1).tolist(), 0, sitk.sitkInt16,
    )  # fmt: skip
    sitk.WriteImage(coarse, str(tmp_path / "lab2.nii.gz"))
    # and one on a larger (padded) grid: its extent is not on the image, its labels are
    padded = sitk.ConstantPad(_on_grid(_subject_arrays(4)[1]), [6, 6, 3], [6, 6, 3], 0)
    sitk.WriteImage(padded, str(tmp_path / "lab4.nii.gz"))
    # and an image cropped after labelling (8 columns of x gone): its labels reach past it
    image = sitk.ReadImage(str(tmp_path / "img3.nii.gz"))
    cropped = sitk.RegionOfInterest(image, [SIZE_3D[0] - 8, *SIZE_3D[1:]], [0, 0, 0])
    sitk.WriteImage(cropped, str(tmp_path / "img3.nii.gz"))
    assert load_manifest(_write(tmp_path, data)).n_images == 5


# ----------------------------------------------------------------------------- item 14


def test_a_mask_off_the_grid_is_named_with_plain_numbers(tmp_path, capsys):
    data = _cohort(tmp_path)
    mask = _on_grid(
        np.ones(SIZE_3D[::-1], np.uint8), origin=(ORIGIN_3D[0] + 5000.0, *ORIGIN_3D[1:])
    )
    sitk.WriteImage(mask, str(tmp_path / "mask.nii.gz"))
    data["mask"] = "mask.nii.gz"
    _write(tmp_path, data)
    err = _refused(tmp_path, capsys, "mask.nii.gz", "grid", "origin (4938.5, 14.25, 103.0)")
    assert "np." not in err


def test_a_seed_that_is_not_an_integer_is_an_input_error_naming_it():
    import itk_nrreval as nr

    images = np.random.default_rng(0).normal(size=(5, 6, 7))
    for seed in ("abc", 1.5, -1, True, 2**63, None):
        with pytest.raises(InputError, match=r"^seed must be an integer in \[0, 2\*\*63\), got"):
            nr.specificity(images, n_samples=50, seed=seed)
        with pytest.raises(InputError, match=r"^seed"):
            nr.compare_specificity(images, images[::-1], n_samples=50, seed=seed)
    assert nr.specificity(images, n_samples=50, seed=np.int64(3)).n_samples == 50


def test_objects_in_memory_get_the_same_voxel_checks_as_files(tmp_path):
    """A dict manifest mixing files and objects: the same image as a file and as an object
    is one image listed twice (the cache's content digest is the same); a constant array
    and an object with NaN are refused, named as the manifest names objects."""
    data = _cohort(tmp_path)
    data["images"][3] = sitk.ReadImage(str(tmp_path / "img1.nii.gz"))
    flat = np.zeros(SIZE_3D[::-1], np.float32)
    grid = {"spacing": SPACING_3D, "origin": ORIGIN_3D, "direction": DIRECTION_3D}
    data["images"][2] = {"array": flat, **grid}
    nan, _ = _subject_arrays(4)
    nan[1, 2, 3] = np.nan
    data["images"][4] = _on_grid(nan)
    with pytest.raises(InputError) as info:
        load_manifest(data, base_dir=tmp_path)
    message = str(info.value)
    assert message.startswith("manifest: 3 problems: "), message
    assert "images[2]: the in-memory array is constant (every voxel is 0)" in message
    assert (
        "images[3]: the in-memory sitk.Image holds the same voxels on the same grid as "
        "images[1] img1.nii.gz" in message
    )
    assert "images[4]: the in-memory sitk.Image: image contains NaN or infinite" in message
