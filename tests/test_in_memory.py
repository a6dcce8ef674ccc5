"""Images and transforms in memory wherever paths are accepted (issue 20).

One generated population with real geometry (oblique direction cosines, anisotropic spacing,
origin away from zero) is written to files and read back as SimpleITK objects, as ITK Python
objects, and as arrays with their grid. Evaluated from each, it must give the same scores
(1e-12) and the same cache keys as from the files; bad objects must give the one-line error
a bad file gives, apart from the item's name. The ITK conversions are checked against ITK
itself, point by point and voxel by voxel.
"""

from __future__ import annotations

import json
import math
import pickle
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
import yaml

import itk_nrreval as nr
from itk_nrreval import InputError
from itk_nrreval._output import MARKER
from itk_nrreval.cli import main
from itk_nrreval.experiments.perturbation import manifest_set
from itk_nrreval.io._cache import content_digest, digest_of
from itk_nrreval.io._images import InMemoryImage, to_sitk_image
from itk_nrreval.io.transforms import InMemoryTransform, to_sitk_transform

N_IMAGES = 5
SHAPE = (36, 40)  # numpy (y, x)
SPACING = (1.1, 0.9)  # mm, (x, y)
ORIGIN = (-20.3, 15.7)
ANGLE = math.radians(25.0)
DIRECTION = (math.cos(ANGLE), -math.sin(ANGLE), math.sin(ANGLE), math.cos(ANGLE))
KW = dict(n_samples=1000, seed=4, progress=False)
FAST = dict(n_samples=300, seed=1, progress=False, confidence=False, inverse_consistency=False)


# ----------------------------------------------------------------------------- the population


def on_grid(arr: np.ndarray, *, vector: bool = False) -> sitk.Image:
    """`arr` (numpy order; components last when `vector`) on the oblique test grid."""
    img = sitk.GetImageFromArray(arr, isVector=vector)
    img.SetSpacing(SPACING)
    img.SetOrigin(ORIGIN)
    img.SetDirection(DIRECTION)
    return img


def phantom() -> tuple[np.ndarray, np.ndarray]:
    """Three elliptic blobs (index space): intensities and labels 0..3."""
    y, x = np.mgrid[0 : SHAPE[0], 0 : SHAPE[1]].astype(float)
    labels = np.zeros(SHAPE, np.int16)
    for k, (cy, cx, ry, rx) in enumerate([(18, 20, 12, 14), (13, 16, 4, 3), (23, 24, 4, 5)], 1):
        labels[((y - cy) / ry) ** 2 + ((x - cx) / rx) ** 2 <= 1] = k
    return labels.astype(float), labels


def smooth_field(seed: int, amplitude: float) -> np.ndarray:
    """A smooth displacement (mm), numpy (y, x, 2), zero at the border."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0 : SHAPE[0], 0 : SHAPE[1]] / (np.array(SHAPE)[:, None, None] - 1)
    bump = np.sin(np.pi * x) * np.sin(np.pi * y)
    out = np.zeros((*SHAPE, 2))
    for c in range(2):
        a, b, p = rng.uniform(-1, 1, 3)
        out[..., c] = amplitude * bump * (a * np.sin(np.pi * (x + p)) + b * np.cos(np.pi * y))
    return out


def write_population(folder: Path) -> dict:
    """Files of N images warped from a phantom, their labels, a mask and four registrations.

    ``truth``: the inverse fields (``.nii.gz``); ``perturbed``: a chain ``[pert.mha,
    truth.nii.gz]``; ``composite``: one ``.h5`` CompositeTransform (a small affine after the
    truth); ``identity``: an affine ``.tfm`` to image 0 (``reference_index``). Returns the
    manifest as a dict with paths relative to `folder` (also written as manifest.yaml).
    """
    intensity, labels = phantom()
    template = on_grid((intensity * 100.0).astype(np.float32))
    sitk.WriteImage(template, str(folder / "template.nii.gz"))
    lab_img = on_grid(labels)
    mask = np.zeros(SHAPE, np.uint8)
    mask[3:33, 4:36] = 1
    sitk.WriteImage(on_grid(mask), str(folder / "mask.nii.gz"))
    centre = template.TransformContinuousIndexToPhysicalPoint([(s - 1) / 2 for s in SHAPE[::-1]])
    small = sitk.AffineTransform(2)
    small.SetCenter(centre)
    small.SetMatrix((0.99, -0.03, 0.035, 1.01))
    small.SetTranslation((0.4, -0.3))
    rng = np.random.default_rng(0)
    reg: dict[str, list] = {"truth": [], "perturbed": [], "composite": [], "identity": []}
    images, label_files = [], []
    for i in range(N_IMAGES):
        contrast = intensity * (100.0 + 10 * rng.standard_normal()) + 5 * (labels == 2) * i
        s_i = sitk.DisplacementFieldTransform(on_grid(smooth_field(i, 3.0), vector=True))
        img = sitk.Resample(on_grid(contrast), template, s_i, sitk.sitkLinear, 0.0)
        sitk.WriteImage(sitk.Cast(img, sitk.sitkFloat32), str(folder / f"img{i}.nii.gz"))
        lab = sitk.Resample(lab_img, template, s_i, sitk.sitkNearestNeighbor, 0)
        sitk.WriteImage(sitk.Cast(lab, sitk.sitkInt16), str(folder / f"lab{i}.nii.gz"))
        truth = sitk.InvertDisplacementField(
            on_grid(smooth_field(i, 3.0), vector=True),
            maximumNumberOfIterations=50,
            maxErrorToleranceThreshold=0.01,
            meanErrorToleranceThreshold=1e-4,
        )
        sitk.WriteImage(sitk.Cast(truth, sitk.sitkVectorFloat32), str(folder / f"truth{i}.nii.gz"))
        pert = on_grid(smooth_field(100 + i, 2.0).astype(np.float32), vector=True)
        sitk.WriteImage(pert, str(folder / f"pert{i}.mha"))
        composite = sitk.CompositeTransform(
            [small, sitk.DisplacementFieldTransform(sitk.Cast(truth, sitk.sitkVectorFloat64))]
        )
        sitk.WriteTransform(composite, str(folder / f"comp{i}.h5"))
        sitk.WriteTransform(small, str(folder / f"id{i}.tfm"))
        images.append(f"img{i}.nii.gz")
        label_files.append(f"lab{i}.nii.gz")
        reg["truth"].append(f"truth{i}.nii.gz")
        reg["perturbed"].append([f"pert{i}.mha", f"truth{i}.nii.gz"])
        reg["composite"].append(f"comp{i}.h5")
        reg["identity"].append(f"id{i}.tfm")
    data = {
        "images": images,
        "labels": label_files,
        "mask": "mask.nii.gz",
        "registrations": {
            "truth": {"reference": "template.nii.gz", "transforms": reg["truth"]},
            "perturbed": {"reference": "template.nii.gz", "transforms": reg["perturbed"]},
            "composite": {"reference": "template.nii.gz", "transforms": reg["composite"]},
            "identity": {
                "reference": "img0.nii.gz",
                "reference_index": 0,
                "transforms": reg["identity"],
            },
        },
    }
    (folder / "manifest.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    return data


IMAGE_SUFFIXES = (".nii.gz", ".mha")


def convert(data: dict, folder: Path, image, transform) -> dict:
    """The manifest `data` with every file replaced by ``image(path)`` / ``transform(path)``."""

    def item(p):
        if isinstance(p, list):
            return [item(q) for q in p]
        path = folder / p
        return image(path) if path.name.endswith(IMAGE_SUFFIXES) else transform(path)

    out = {
        "images": [item(p) for p in data["images"]],
        "labels": [item(p) for p in data["labels"]],
        "mask": item(data["mask"]),
        "registrations": {},
    }
    for name, entry in data["registrations"].items():
        out["registrations"][name] = {
            **entry,
            "reference": item(entry["reference"]),
            "transforms": [item(t) for t in entry["transforms"]],
        }
    return out


def sitk_objects(data: dict, folder: Path) -> dict:
    return convert(
        data, folder, lambda p: sitk.ReadImage(str(p)), lambda p: sitk.ReadTransform(str(p))
    )


def itk_objects(data: dict, folder: Path) -> dict:
    itk = pytest.importorskip("itk")
    return convert(
        data, folder, lambda p: itk.imread(str(p)), lambda p: itk.transformread(str(p))[0]
    )


def as_array(img: sitk.Image) -> dict:
    """The array form of an image: numpy order, its grid explicit."""
    return {
        "array": sitk.GetArrayFromImage(img),
        "spacing": img.GetSpacing(),
        "origin": img.GetOrigin(),
        "direction": np.reshape(img.GetDirection(), (img.GetDimension(),) * 2),
    }


def cache_keys(cache: Path) -> dict[str, list[str]]:
    """Every entry of a cache folder by kind: the keys the run used."""
    out: dict[str, list[str]] = {}
    for entry in sorted(cache.glob("*/*/*/entry.json")):
        out.setdefault(entry.parent.parent.parent.name, []).append(entry.parent.name)
    return out


def assert_identical(a, b, *, tol: float = 1e-12) -> None:
    """The same scores, frames, plausibility and mean images (to `tol`), and the same ranks."""
    assert list(a.scores) == list(b.scores)
    for name, sa in a.scores.items():
        sb = b.scores[name]
        for key, va in sa.measures().items():
            assert abs(sb.measures()[key] - va) <= tol * max(1.0, abs(va)), (name, key)
        assert abs(sb.specificity.stderr - sa.specificity.stderr) <= tol * sa.specificity.stderr
        for k in ("spread_mean_mm", "spread_max_mm"):
            assert getattr(sb.frame, k) == pytest.approx(getattr(sa.frame, k), abs=tol)
        pa, pb = sa.plausibility.to_dict(), sb.plausibility.to_dict()
        # The inverse-consistency error comes from sitk.InvertDisplacementField, whose result
        # varies run to run at ~1e-6 mm with several threads (files against the same files
        # too; bit-identical with one thread): compared to 1%, everything else to `tol`.
        ic_a, ic_b = pa.pop("inverse_consistency_mm"), pb.pop("inverse_consistency_mm")
        assert ic_b == pytest.approx(ic_a, rel=1e-2, abs=1e-9), name
        assert pb == pytest.approx(pa, abs=tol), name
        np.testing.assert_allclose(b.mean_images[name], a.mean_images[name], rtol=0, atol=tol)
        for m, iv in sa.intervals.items():
            assert sb.intervals[m].to_list() == pytest.approx(iv.to_list(), abs=tol), (name, m)
    assert a.ranks == b.ranks and a.verdict == b.verdict


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    folder = tmp_path_factory.mktemp("population")
    return folder, write_population(folder)


@pytest.fixture(scope="module")
def from_files(case, tmp_path_factory):
    """The population evaluated from its files, with its cache folder."""
    folder, _ = case
    cache = tmp_path_factory.mktemp("files_cache")
    execution = nr.Execution(cache=cache, keep_resampled=True)  # every entry, to compare keys
    return nr.evaluate(folder / "manifest.yaml", execution=execution, **KW), cache


# ----------------------------------------------------------------------------- same numbers


def test_sitk_objects_give_the_files_scores_and_cache_keys(case, from_files, tmp_path):
    folder, data = case
    files, files_cache = from_files
    manifest = sitk_objects(data, folder)
    kept = nr.Execution(cache=tmp_path / "c", keep_resampled=True)
    objects = nr.evaluate(manifest, execution=kept, **KW)
    assert_identical(files, objects)
    assert cache_keys(tmp_path / "c") == cache_keys(files_cache)
    assert set(cache_keys(files_cache)) >= {
        "resampled",
        "measures",
        "frame",
        "frame_spread",
        "mask",
        "reg_mask",
    }
    # the objects find the files' entries: nothing is computed again
    again = nr.evaluate(
        manifest, execution=nr.Execution(cache=files_cache, keep_resampled=True), **KW
    )
    assert again.run["cache_computed"] == 0
    assert again.run["cache_reused"] == files.run["cache_computed"] > 0
    assert_identical(files, again)
    assert objects.inputs["images"][0].startswith("<in-memory sitk.Image images[0]: 32-bit float")
    described = objects.inputs["registrations"]["composite"]["transforms"][1]
    assert len(described) == 1 and described[0].startswith(
        "<in-memory sitk.Transform registrations.composite.transforms[1]: "
        "AffineTransform+DisplacementFieldTransform, content "
    )


def test_itk_objects_give_the_files_scores_and_cache_keys(case, from_files, tmp_path):
    folder, data = case
    files, files_cache = from_files
    manifest = itk_objects(data, folder)
    objects = nr.evaluate(
        manifest, execution=nr.Execution(cache=tmp_path / "c", keep_resampled=True), **KW
    )
    assert_identical(files, objects)
    assert cache_keys(tmp_path / "c") == cache_keys(files_cache)
    assert objects.inputs["images"][2].startswith("<in-memory itk.Image images[2]")


def test_a_mixed_manifest_gives_the_files_scores_and_keys(case, from_files, tmp_path):
    """Paths, SimpleITK images and transforms, arrays with their grid, and displacement
    fields as transforms, images and arrays, side by side in one manifest."""
    folder, data = case
    files, files_cache = from_files
    read = lambda p: sitk.ReadImage(str(folder / p))  # noqa: E731
    m = json.loads(json.dumps(data))  # a deep copy, paths relative to `folder`
    m["images"][1] = read(data["images"][1])
    m["images"][3] = as_array(read(data["images"][3]))
    m["labels"][0] = as_array(read(data["labels"][0]))
    m["labels"][4] = read(data["labels"][4])
    m["mask"] = as_array(read(data["mask"]))
    truth = m["registrations"]["truth"]
    truth["reference"] = read("template.nii.gz")
    field = read(data["registrations"]["truth"]["transforms"][2])
    truth["transforms"][0] = sitk.DisplacementFieldTransform(
        sitk.Cast(read(truth["transforms"][0]), sitk.sitkVectorFloat64)
    )
    truth["transforms"][2] = as_array(field)  # a field as an array with its grid
    nested = sitk.CompositeTransform(  # a composite in a composite, flattened: one field
        [sitk.CompositeTransform([sitk.DisplacementFieldTransform(
            sitk.Cast(read(truth["transforms"][4]), sitk.sitkVectorFloat64)
        )])]
    )  # fmt: skip
    truth["transforms"][4] = nested
    pert = m["registrations"]["perturbed"]["transforms"]
    pert[1] = [read(pert[1][0]), pert[1][1]]  # a chain mixing an image and a path
    pert[3] = [pert[3][0], read(pert[3][1])]
    comp = m["registrations"]["composite"]["transforms"]
    comp[4] = sitk.ReadTransform(str(folder / comp[4]))
    m["registrations"]["identity"]["transforms"][2] = sitk.ReadTransform(str(folder / "id2.tfm"))
    loaded = nr.load_manifest(m, base_dir=folder)
    assert loaded.in_memory and not nr.load_manifest(folder / "manifest.yaml").in_memory
    assert isinstance(loaded.images[3], InMemoryImage) and loaded.images[3].source == "array"
    assert isinstance(loaded.images[0], Path)
    result = nr.evaluate(
        loaded, execution=nr.Execution(cache=tmp_path / "c", keep_resampled=True), **KW
    )
    assert_identical(files, result)
    assert cache_keys(tmp_path / "c") == cache_keys(files_cache)


def test_objects_on_dask_give_the_files_scores_and_keys(case, from_files, tmp_path):
    """The objects travel to worker processes (SimpleITK images and transforms pickle)."""
    pytest.importorskip("dask.distributed")
    folder, data = case
    files, files_cache = from_files
    manifest = sitk_objects(data, folder)
    scaled = nr.evaluate(
        manifest,
        execution=nr.Execution(
            scheduler="local", workers=1, cache=tmp_path / "c", keep_resampled=True
        ),
        **KW,
    )
    assert scaled.run["scheduler"] == "local"
    assert_identical(files, scaled)
    assert cache_keys(tmp_path / "c") == cache_keys(files_cache)


def test_cache_keys_are_the_same_in_a_new_process(case):
    """Keys come from content, not object identity: another process, reading the same files
    into new objects, finds the same keys -- and they equal the files' own keys."""
    folder, data = case
    items = {
        "image": ("img3.nii.gz", "image"),
        "field": ("truth1.nii.gz", "transform"),
        "composite": ("comp2.h5", "transform"),
        "affine": ("id4.tfm", "transform"),
    }
    code = (
        "import sys, json, SimpleITK as sitk\n"
        "from itk_nrreval.io._images import InMemoryImage\n"
        "from itk_nrreval.io.transforms import InMemoryTransform\n"
        "out = {}\n"
        f"for key, (p, kind) in {items!r}.items():\n"
        f"    path = {str(folder)!r} + '/' + p\n"
        "    if kind == 'image':\n"
        "        obj = InMemoryImage.from_object(sitk.ReadImage(path), name=key)\n"
        "    elif path.endswith('.nii.gz'):\n"
        "        obj = InMemoryTransform.from_object(sitk.ReadImage(path), name=key)\n"
        "    else:\n"
        "        obj = InMemoryTransform.from_object(sitk.ReadTransform(path), name=key)\n"
        "    out[key] = obj.content_digest\n"
        "print(json.dumps(out))\n"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    there = json.loads(run.stdout)
    here = {
        "image": InMemoryImage.from_object(sitk.ReadImage(str(folder / "img3.nii.gz")), name="a"),
        "field": InMemoryTransform.from_object(
            sitk.ReadImage(str(folder / "truth1.nii.gz")), name="b"
        ),
        "composite": InMemoryTransform.from_object(
            sitk.ReadTransform(str(folder / "comp2.h5")), name="c"
        ),
        "affine": InMemoryTransform.from_object(
            sitk.ReadTransform(str(folder / "id4.tfm")), name="d"
        ),
    }
    for key, (p, _) in items.items():
        assert there[key] == here[key].content_digest == content_digest(folder / p), key
        assert digest_of(["x", here[key]]) == digest_of(["x", folder / p]), key


# ----------------------------------------------------------------------------- same errors


def nan_copy(path: Path, folder: Path, suffix: str) -> tuple[Path, sitk.Image]:
    """A copy of image (or field) `path` with NaN in a block: as a file and as an object."""
    img = sitk.ReadImage(str(path))
    arr = sitk.GetArrayFromImage(img)
    arr[5:9, 6:12] = np.nan
    bad = sitk.GetImageFromArray(arr, isVector=img.GetNumberOfComponentsPerPixel() > 1)
    bad.CopyInformation(img)
    out = folder / f"bad{suffix}"
    sitk.WriteImage(bad, str(out))
    return out, bad


def error_of(manifest) -> str:
    with pytest.raises(InputError) as info:
        nr.evaluate(manifest, **FAST)
    message = str(info.value)
    assert "\n" not in message
    return message


def load_error(manifest: dict, folder: Path) -> str:
    """The one-line error of the manifest's check (before any work)."""
    with pytest.raises(InputError) as info:
        nr.load_manifest(manifest, base_dir=folder)
    message = str(info.value)
    assert "\n" not in message
    return message


def same_apart_from_names(file_msg: str, obj_msg: str, path: Path, item: str, label: str = ""):
    """Replace the file's name (full path or name) and the object's (its item, where the file
    message has the path; its label, where it has the name) by one placeholder."""
    f = file_msg.replace(str(path), "<X>").replace(path.name, "<X>")
    o = obj_msg.replace(label, "<X>") if label else obj_msg
    if item and o.startswith(item + ": "):
        o = "<X>" + o[len(item) :]
    assert f == o, (file_msg, obj_msg)


def small_manifest(data: dict) -> dict:
    """The population with one registration (fast errors)."""
    m = json.loads(json.dumps(data))
    m["registrations"] = {"truth": m["registrations"]["truth"]}
    return m


@pytest.mark.parametrize("form", ["sitk", "itk", "array"])
def test_an_image_with_nan_fails_like_the_file(case, tmp_path, form):
    folder, data = case
    bad_file, bad = nan_copy(folder / "img2.nii.gz", tmp_path, ".nii.gz")
    if form == "itk":
        itk = pytest.importorskip("itk")
        obj, label = itk.GetImageFromArray(sitk.GetArrayFromImage(bad)), "the in-memory itk.Image"
        obj.SetOrigin(bad.GetOrigin())
        obj.SetSpacing(bad.GetSpacing())
        obj.SetDirection(itk.matrix_from_array(np.reshape(bad.GetDirection(), (2, 2))))
    else:
        obj = bad if form == "sitk" else as_array(bad)
        label = "the in-memory " + ("sitk.Image" if form == "sitk" else "array")
    with_file, with_obj = small_manifest(data), small_manifest(data)
    with_file["images"][2] = str(bad_file)
    with_obj["images"][2] = obj
    # refused by the manifest's check, before any work (issue 44)
    f = load_error(with_file, folder)
    o = load_error(with_obj, folder)
    assert f == f"manifest: images[2]: {bad_file}: image contains NaN or infinite voxel values"
    assert o == f"manifest: images[2]: {label}: image contains NaN or infinite voxel values"
    same_apart_from_names(f, o, bad_file, "images[2]", label)


def test_a_field_with_nan_fails_like_the_file(case, tmp_path):
    folder, data = case
    bad_file, bad = nan_copy(folder / "truth1.nii.gz", tmp_path, ".mha")
    with_file, with_obj = small_manifest(data), small_manifest(data)
    with_file["registrations"]["truth"]["transforms"][1] = str(bad_file)
    with_obj["registrations"]["truth"]["transforms"][1] = bad
    f = error_of(nr.load_manifest(with_file, base_dir=folder))
    o = error_of(nr.load_manifest(with_obj, base_dir=folder))
    assert f == f"{bad_file}: displacement field contains NaN or infinite voxel values"
    assert o == (
        "registrations.truth.transforms[1]: displacement field contains NaN or infinite voxel "
        "values"
    )
    same_apart_from_names(f, o, bad_file, "registrations.truth.transforms[1]")


def test_a_transform_with_nan_fails_like_the_file(case, tmp_path):
    folder, data = case
    bad = sitk.AffineTransform(2)
    bad.SetTranslation((math.nan, 0.5))
    bad_file = tmp_path / "nan.h5"
    sitk.WriteTransform(bad, str(bad_file))
    with_file, with_obj = small_manifest(data), small_manifest(data)
    with_file["registrations"]["truth"]["transforms"][1] = str(bad_file)
    with_obj["registrations"]["truth"]["transforms"][1] = bad
    f = error_of(nr.load_manifest(with_file, base_dir=folder))
    o = error_of(nr.load_manifest(with_obj, base_dir=folder))
    assert o == "registrations.truth.transforms[1]: transform contains NaN or infinite values"
    same_apart_from_names(f, o, bad_file, "registrations.truth.transforms[1]")


def test_an_image_of_the_wrong_dimension_fails_like_the_file(case, tmp_path):
    folder, data = case
    vol = sitk.Image([8, 9, 10], sitk.sitkFloat32)
    vol.SetSpacing((1.0, 1.5, 2.0))
    bad_file = tmp_path / "vol.nii.gz"
    sitk.WriteImage(vol, str(bad_file))
    with_file, with_obj = small_manifest(data), small_manifest(data)
    with_file["images"][2] = str(bad_file)
    with_obj["images"][2] = vol
    with pytest.raises(InputError) as f:
        nr.load_manifest(with_file, base_dir=folder)
    with pytest.raises(InputError) as o:
        nr.load_manifest(with_obj, base_dir=folder)
    expected = "manifest: images[2]: the in-memory sitk.Image is 3D; the other 4 images are 2D"
    assert str(o.value) == expected
    same_apart_from_names(
        str(f.value), str(o.value), bad_file, "images[2]", "the in-memory sitk.Image"
    )


@pytest.mark.parametrize("form", ["sitk", "itk", "field"])
def test_a_transform_of_the_wrong_dimension_fails_like_the_file(case, tmp_path, form):
    folder, data = case
    if form == "field":  # a 3D displacement field, as a file and as an image
        obj = sitk.Image([8, 8, 8], sitk.sitkVectorFloat64, 3)
        bad_file = tmp_path / "field3.mha"
        sitk.WriteImage(obj, str(bad_file))
    else:
        bad_file = tmp_path / "a3.tfm"
        sitk.WriteTransform(sitk.AffineTransform(3), str(bad_file))
        obj = sitk.AffineTransform(3)
    if form == "itk":
        itk = pytest.importorskip("itk")
        obj = itk.AffineTransform[itk.D, 3].New()
    with_file, with_obj = json.loads(json.dumps(data)), json.loads(json.dumps(data))
    with_file["registrations"]["identity"]["transforms"][2] = str(bad_file)
    with_obj["registrations"]["identity"]["transforms"][2] = obj
    with pytest.raises(InputError) as f:
        nr.load_manifest(with_file, base_dir=folder)
    with pytest.raises(InputError) as o:
        nr.load_manifest(with_obj, base_dir=folder)
    where = "manifest: registrations.identity.transforms[2]: "
    if form == "field":
        expected = where + "the in-memory sitk.Image is a 3D displacement field, the images are 2D"
        assert str(o.value) == expected
        same_apart_from_names(str(f.value), str(o.value), bad_file, "", "the in-memory sitk.Image")
    else:
        assert str(f.value) == str(o.value) == where + "3D transform for 2D images"


def test_a_non_integer_label_map_fails_like_the_file(case, tmp_path):
    folder, data = case
    lab = sitk.Cast(sitk.ReadImage(str(folder / "lab1.nii.gz")), sitk.sitkFloat32) * 1.25
    bad_file = tmp_path / "lab.nii.gz"
    sitk.WriteImage(lab, str(bad_file))
    with_file, with_obj = small_manifest(data), small_manifest(data)
    with_file["labels"][1] = str(bad_file)
    with_obj["labels"][1] = lab
    f = load_error(with_file, folder)  # refused by the manifest's check (issue 44)
    o = load_error(with_obj, folder)
    assert "labels[1]: " in o and "non-integer values (e.g. 1.25" in o, o
    same_apart_from_names(f, o, bad_file, "labels[1]", "the in-memory sitk.Image")


def test_a_scalar_image_as_a_transform_fails_like_the_file(case):
    folder, data = case
    scalar = sitk.ReadImage(str(folder / "img0.nii.gz"))
    with_file, with_obj = small_manifest(data), small_manifest(data)
    with_file["registrations"]["truth"]["transforms"][3] = "img0.nii.gz"
    with_obj["registrations"]["truth"]["transforms"][3] = scalar
    with pytest.raises(InputError) as f:
        nr.load_manifest(with_file, base_dir=folder)
    with pytest.raises(InputError) as o:
        nr.load_manifest(with_obj, base_dir=folder)
    assert "a displacement field needs 2 vector components per voxel, has 1" in str(o.value)
    same_apart_from_names(
        str(f.value), str(o.value), folder / "img0.nii.gz", "", "the in-memory sitk.Image"
    )


def test_objects_that_are_not_images_are_refused_all_at_once(case):
    folder, data = case
    m = json.loads(json.dumps(data))
    m["images"][0] = np.zeros(SHAPE)  # no grid
    m["labels"][1] = {"array": np.zeros(SHAPE), "spacing": SPACING, "origin": ORIGIN}
    m["mask"] = {**as_array(sitk.ReadImage(str(folder / "mask.nii.gz"))), "spacing": (1.0,)}
    m["registrations"]["truth"]["transforms"][2] = 42
    m["registrations"]["identity"]["transforms"][0] = object()
    with pytest.raises(InputError) as info:
        nr.load_manifest(m, base_dir=folder)
    message = str(info.value)
    assert message.startswith("manifest: 5 problems: ")
    assert "images[0]: a numpy array has no grid; give it as {'array': a, 'spacing'" in message
    assert (
        "labels[1]: an array needs exactly the keys array, spacing, origin, direction " in message
    )
    assert "(missing direction)" in message
    assert "mask: 1 spacings need 1 origin values and 1 direction values, got 2 and 4" in message
    assert "registrations.truth.transforms[2]: expected a file path, got 42" in message
    assert "registrations.identity.transforms[0]: expected a file path, a transform" in message


def test_the_manifest_keeps_a_private_copy(case):
    folder, data = case
    img = sitk.ReadImage(str(folder / "img1.nii.gz"))
    m = nr.load_manifest(
        {**data, "images": [*data["images"][:1], img, *data["images"][2:]]}, base_dir=folder
    )
    before = m.images[1].content_digest
    img[3, 4] = 1e6  # the caller changes its image afterwards
    assert m.images[1].image[3, 4] != 1e6
    assert InMemoryImage.from_object(m.images[1].image, name="x").content_digest == before
    with pytest.raises(InputError, match=r"images\[1\] is an in-memory sitk.Image and cannot"):
        nr.write_manifest(m, folder / "never.yaml")
    assert not (folder / "never.yaml").exists()


def test_in_memory_items_pickle_with_their_content():
    rng = np.random.default_rng(3)
    img = on_grid(rng.random(SHAPE).astype(np.float32))
    field = on_grid(rng.normal(size=(*SHAPE, 2)), vector=True)
    affine = sitk.AffineTransform(2)
    affine.SetMatrix((1.02, 0.1, -0.05, 0.97))
    affine.SetTranslation((1.5, -2.0))
    chain = sitk.CompositeTransform([affine, sitk.DisplacementFieldTransform(field)])
    a = InMemoryImage.from_object(img, name="images[0]")
    t = InMemoryTransform.from_object(chain, name="registrations.r.transforms[0]")
    # Protocol 5, as Dask pickles: SimpleITK would hand out-of-band buffers of temporary
    # images (freed before they are sent); the items keep everything in band.
    buffers: list = []
    a_bytes, t_bytes = (pickle.dumps(x, protocol=5, buffer_callback=buffers.append) for x in (a, t))
    assert buffers == []
    a2, t2 = pickle.loads(a_bytes), pickle.loads(t_bytes)
    assert a2.name == a.name and a2.content_digest == a.content_digest
    np.testing.assert_array_equal(sitk.GetArrayFromImage(a2.image), sitk.GetArrayFromImage(img))
    assert (a2.image.GetOrigin(), a2.image.GetDirection()) == (ORIGIN, DIRECTION)
    assert InMemoryImage.from_object(a2.image, name="x").content_digest == a.content_digest
    assert InMemoryTransform.from_object(t2.transform, name="x").content_digest == t.content_digest
    points = rng.uniform(-25, 25, (50, 2)) + np.array([0.0, 30.0])
    for p in points:
        assert t2.transform.TransformPoint(p) == chain.TransformPoint(p)


# ----------------------------------------------------------------------------- conversions


def test_array_form_is_the_image_with_its_grid():
    rng = np.random.default_rng(5)
    arr = rng.random((4, 5, 6)).astype(np.float32)  # numpy (z, y, x)
    d = np.array([[0.0, 1.0, 0.0], [0.6, 0.0, -0.8], [-0.8, 0.0, -0.6]])
    img = to_sitk_image(
        {"array": arr, "spacing": (0.5, 1.0, 2.5), "origin": (1, -2, 3.5), "direction": d},
        name="x",
    )
    assert img.GetSize() == (6, 5, 4) and img.GetPixelID() == sitk.sitkFloat32
    assert img.GetDirection() == tuple(d.ravel()) and img.GetSpacing() == (0.5, 1.0, 2.5)
    assert img[5, 1, 2] == arr[2, 1, 5]  # sitk index (x, y, z) = numpy [z, y, x]
    # the physical point of voxel (i, j, k): origin + D diag(spacing) (i, j, k)
    expected = np.array([1, -2, 3.5]) + d @ (np.array([0.5, 1.0, 2.5]) * [5, 1, 2])
    np.testing.assert_allclose(img.TransformIndexToPhysicalPoint((5, 1, 2)), expected, atol=1e-12)
    vec = to_sitk_image(
        {
            "array": rng.random((5, 6, 2)),
            "spacing": (1, 1),
            "origin": (0, 0),
            "direction": (1, 0, 0, 1),
        },
        name="x",
    )
    assert vec.GetNumberOfComponentsPerPixel() == 2 and vec.GetSize() == (6, 5)
    with pytest.raises(InputError, match=r"x: expected a numeric array with 2 axes \(or 3"):
        to_sitk_image(
            {
                "array": np.zeros((2, 3, 4, 5)),
                "spacing": (1, 1),
                "origin": (0, 0),
                "direction": (1, 0, 0, 1),
            },
            name="x",
        )


def euler_3d(angles, translation, centre):
    t = sitk.Euler3DTransform()
    t.SetRotation(*angles)
    t.SetTranslation(translation)
    t.SetCenter(centre)
    return t


def oblique_3d_direction() -> np.ndarray:
    return np.asarray(euler_3d((0.3, -0.2, 0.5), (0, 0, 0), (0, 0, 0)).GetMatrix()).reshape(3, 3)


def test_itk_images_keep_voxels_and_geometry_exactly():
    itk = pytest.importorskip("itk")
    rng = np.random.default_rng(7)
    arr = rng.random((7, 8, 9)).astype(np.float32)  # numpy (z, y, x)
    src = itk.image_from_array(arr)
    src.SetSpacing((0.7, 1.3, 2.1))
    src.SetOrigin((-12.5, 7.25, 30.0))
    src.SetDirection(itk.matrix_from_array(oblique_3d_direction()))
    img = to_sitk_image(src, name="x")
    assert img.GetSize() == (9, 8, 7)
    assert img.GetOrigin() == (-12.5, 7.25, 30.0) and img.GetSpacing() == (0.7, 1.3, 2.1)
    assert img.GetDirection() == tuple(oblique_3d_direction().ravel())
    for index in [(0, 0, 0), (8, 7, 6), (3, 5, 1), (6, 2, 4)]:  # ITK order (x, y, z)
        assert img.GetPixel(index) == src.GetPixel(index)
        assert img.TransformIndexToPhysicalPoint(index) == tuple(
            src.TransformIndexToPhysicalPoint(index)
        )
    # a vector image (a 3D displacement field)
    field = itk.image_from_array(rng.random((7, 8, 9, 3)).astype(np.float32), is_vector=True)
    vec = to_sitk_image(field, name="x")
    assert vec.GetNumberOfComponentsPerPixel() == 3
    assert vec.GetPixel((4, 2, 6)) == pytest.approx(tuple(field.GetPixel((4, 2, 6))), abs=0)
    # an ITK grid that does not start at index 0: same voxels at the same physical points
    extract = itk.ExtractImageFilter.New(src)
    region = itk.ImageRegion[3]()
    region.SetIndex((2, 3, 1))
    region.SetSize((5, 4, 3))
    extract.SetExtractionRegion(region)
    extract.SetDirectionCollapseToIdentity()
    extract.Update()
    part = extract.GetOutput()
    assert tuple(part.GetLargestPossibleRegion().GetIndex()) == (2, 3, 1)
    sub = to_sitk_image(part, name="x")
    assert sub.GetSize() == (5, 4, 3)
    for q in [(0, 0, 0), (4, 3, 2), (1, 2, 1)]:
        itk_index = tuple(int(a + b) for a, b in zip(q, (2, 3, 1), strict=True))
        assert sub.GetPixel(q) == part.GetPixel(itk_index)
        np.testing.assert_allclose(
            sub.TransformIndexToPhysicalPoint(q),
            part.TransformIndexToPhysicalPoint(itk_index),
            atol=1e-12,
        )


def test_itk_transforms_map_points_as_itk_does():
    """A composite of ITK Python transforms (rigid, affine, B-spline, displacement field),
    converted, maps points exactly as the ITK pieces applied one after the other."""
    itk = pytest.importorskip("itk")
    rng = np.random.default_rng(11)
    euler = itk.Euler3DTransform[itk.D].New()
    euler.SetRotation(0.1, -0.2, 0.15)
    euler.SetTranslation((2.0, -1.0, 0.5))
    euler.SetCenter((1.0, 2.0, 3.0))
    affine = itk.AffineTransform[itk.D, 3].New()
    affine.SetMatrix(itk.matrix_from_array(np.eye(3) + 0.05 * rng.normal(size=(3, 3))))
    affine.SetTranslation((0.3, 0.2, -0.4))
    bspline = itk.BSplineTransform[itk.D, 3, 3].New()
    fixed = [6, 6, 6, -20, -20, -20, 8, 8, 8, *np.eye(3).ravel()]  # size, origin, spacing, dir
    bspline.SetFixedParameters(itk_parameters(itk, fixed))
    n = bspline.GetNumberOfParameters()
    bspline.SetParameters(itk_parameters(itk, rng.normal(scale=1.5, size=n)))
    composite = itk.CompositeTransform[itk.D, 3].New()
    for t in (euler, affine, bspline):
        composite.AddTransform(t)  # ITK applies the last added first: euler(affine(bspline(p)))
    converted = to_sitk_transform(composite, name="t")
    assert [p.GetName() for p in nr_leaves(converted)] == [
        "Euler3DTransform",
        "AffineTransform",
        "BSplineTransform",
    ]
    points = rng.uniform(-15, 15, (200, 3))
    for p in points:
        expected = euler.TransformPoint(affine.TransformPoint(bspline.TransformPoint(p)))
        np.testing.assert_allclose(converted.TransformPoint(p), expected, rtol=0, atol=1e-9)
    # a displacement field transform (ITK Python wraps float fields): float arithmetic there
    field_type = itk.Image[itk.Vector[itk.F, 3], 3]
    grid = itk.image_from_array(rng.normal(size=(6, 7, 8, 3)).astype(np.float32), ttype=field_type)
    grid.SetSpacing((2.0, 1.5, 1.0))
    grid.SetOrigin((-5.0, -4.0, -3.0))
    grid.SetDirection(itk.matrix_from_array(oblique_3d_direction()))
    dft = itk.DisplacementFieldTransform[itk.F, 3].New()
    dft.SetDisplacementField(grid)
    field = to_sitk_transform(dft, name="t")
    assert isinstance(field, sitk.DisplacementFieldTransform)
    for p in rng.uniform(-6, 6, (100, 3)):
        np.testing.assert_allclose(field.TransformPoint(p), dft.TransformPoint(p), atol=1e-5)


def itk_parameters(itk, values):
    out = itk.OptimizerParameters[itk.D](len(values))
    for i, v in enumerate(values):
        out[i] = float(v)
    return out


def nr_leaves(t):
    from itk_nrreval.io.transforms import leaves

    return leaves(t)


# ----------------------------------------------------------------------------- the other entries


def test_diagnose_and_validation_read_objects_like_files(case, tmp_path):
    folder, data = case
    objects = sitk_objects(data, folder)
    kw = dict(registrations=["truth", "identity"], n_samples=40, seed=2, progress=False)
    a = nr.diagnose(folder / "manifest.yaml", **kw)
    b = nr.diagnose(objects, out=tmp_path / "d", **kw)
    assert b.names == ("truth", "identity")
    for ra, rb in zip(a.results, b.results, strict=True):
        np.testing.assert_array_equal(rb.raw.counts, ra.raw.counts)
        np.testing.assert_array_equal(rb.projected.counts, ra.projected.counts)
        np.testing.assert_allclose(rb.representation_error, ra.representation_error, atol=1e-12)
    written = sorted(p.name for p in (tmp_path / "d").iterdir() if p.name != MARKER)
    assert written == [
        "appearance_cells.png",
        "appearance_diagnostics.json",
        "appearance_table1.csv",
        "appearance_table1.md",
    ]
    assert (tmp_path / "d" / "appearance_table1.md").read_text() == a.table_markdown()
    saved = json.loads((tmp_path / "d" / "appearance_diagnostics.json").read_text())
    assert saved["inputs"]["images"][0].startswith("<in-memory sitk.Image images[0]")
    # validation reads a manifest through the same loader
    images_f, members_f, grid_f = manifest_set(folder / "manifest.yaml")
    images_o, members_o, grid_o = manifest_set(objects)
    np.testing.assert_array_equal(images_o, images_f)
    np.testing.assert_array_equal(members_o, members_f)
    assert grid_o == grid_f


def _subjects_unnamed(path: Path) -> str:
    """`path`'s text with each "subject i (its image)" said as "subject i"."""
    return re.sub(r"(subject \d+) \([^()]*\)", r"\1", path.read_text())


def test_evaluate_out_writes_what_the_cli_writes(case, tmp_path, capsys):
    folder, data = case
    cli_out, api_out = tmp_path / "cli", tmp_path / "api"
    # without the inverse-consistency error, which varies run to run (see assert_identical),
    # the two runs write the same numbers, so their reports can be compared as text
    args = ["evaluate", str(folder / "manifest.yaml"), "--out", str(cli_out)]
    args += ["--samples", "1000", "--seed", "4", "--no-inverse-consistency"]
    assert main([*args, "--no-figures", "--quiet"]) == 0
    capsys.readouterr()
    cache = api_out / "cache"
    result = nr.evaluate(
        sitk_objects(data, folder),
        inverse_consistency=False,
        execution=nr.Execution(cache=cache, keep_resampled=True),
        **KW,
    )
    result.write(api_out, figures=False)
    nr.export_resampled(result, api_out / "resampled", cache=cache)
    for name in ("results.csv", "metrics.csv"):
        assert (api_out / name).read_text() == (cli_out / name).read_text(), name
    # summary.md names subjects by their images, as the inputs do: in memory or a file
    assert _subjects_unnamed(api_out / "summary.md") == _subjects_unnamed(cli_out / "summary.md")
    api = json.loads((api_out / "results.json").read_text())
    cli = json.loads((cli_out / "results.json").read_text())
    # each subject's entry names its image as the inputs do: in memory or a file
    for reg in (*api["registrations"].values(), *cli["registrations"].values()):
        for entry in reg["subjects"]:
            entry.pop("image")
    assert api["registrations"] == cli["registrations"] and api["verdict"] == cli["verdict"]
    assert api["options"] == cli["options"]
    assert api["inputs"]["images"][0].startswith("<in-memory sitk.Image images[0]")
    assert api["inputs"] == result.inputs
    assert (api_out / "cache" / "resampled").is_dir()
    assert (api_out / "resampled" / "truth" / "image_000.nii.gz").is_file()
    assert not list(tmp_path.glob("api.*")) and not list(api_out.rglob(".*tmp*"))
    written = result.write(tmp_path / "again", figures=False)
    assert sorted(p.name for p in written) == [
        "metrics.csv",
        "results.csv",
        "results.json",
        "subjects.csv",
        "summary.md",
    ]
    assert _subjects_unnamed(tmp_path / "again" / "summary.md") == _subjects_unnamed(
        cli_out / "summary.md"
    )
    with pytest.raises(nr.InputError, match="no longer holds the evaluation's resampled"):
        nr.export_resampled(result, tmp_path / "none", cache=tmp_path / "empty")


def test_image_lists_take_itk_images_and_arrays_too(case):
    """The measures that take a list of images (specificity, overlap, validate) read ITK
    images and arrays with their grid like SimpleITK images, grid checks included."""
    itk = pytest.importorskip("itk")
    folder, data = case
    paths = [str(folder / p) for p in data["images"]]
    images = [sitk.ReadImage(p) for p in paths]
    mixed = [itk.imread(paths[0]), as_array(images[1]), *images[2:4], paths[4]]
    a = nr.specificity(images, n_samples=300, seed=2)
    b = nr.specificity(mixed, n_samples=300, seed=2)
    assert b.value == a.value and b.stderr == a.stderr
    moved = as_array(images[1])
    moved["origin"] = (moved["origin"][0] + 0.5, moved["origin"][1])
    with pytest.raises(
        InputError, match=r"^image\[1\]: not on the grid of .*img0\.nii\.gz: origin"
    ):
        nr.specificity([paths[0], moved, *images[2:]], n_samples=300)


def test_many_problems_are_counted_and_the_first_ten_named():
    """A list of 40 bad entries is one readable line: all counted, ten named."""
    bad = {"images": [{"array": np.zeros(SHAPE)} for _ in range(40)], "registrations": {}}
    with pytest.raises(InputError) as e:
        nr.load_manifest(bad)
    message = str(e.value)
    assert message.startswith("manifest: 41 problems: images[0]: an array needs")
    assert "images[9]:" in message and "images[10]:" not in message
    assert message.endswith("; and 31 more")
    assert "\n" not in message
