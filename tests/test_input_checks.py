"""One set of input checks for every command (issue 25, items 4, 5 and 9).

Each command that reads images refuses the same things with the same one-line message
(exit code 2, the file named) and warns about the same things: a 4D image, a label map
given as an image. A manifest whose images disagree names the odd one out. Through the CLI
in process, on small files written here.
"""

from __future__ import annotations

import re
from pathlib import Path

import h5py
import numpy as np
import pytest
import SimpleITK as sitk
import yaml
from test_bad_inputs import assert_one_line, run_cli

from data_synth import make_population, write_population
from itk_nrreval.cli import main
from itk_nrreval.manifest import load_manifest

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
    from itk_nrreval._itk_hdf5 import transform_dimension as _hdf5_transform_dimension

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
