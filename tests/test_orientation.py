"""Physical space is what counts: the same case under a rigid change of coordinates.

Every image, label map, reference and displacement field of a case is moved by a rigid
motion M of physical space (an oblique direction matrix, a moved origin); each transform T
(reference points -> image points) becomes ``M o T o M^-1``: a displacement field is carried
to the moved grid with its vectors rotated. Nothing about the registrations changes, so every
score must too -- up to round-off.
"""

from __future__ import annotations

import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
import yaml
from scipy.spatial.transform import Rotation
from test_evaluate import make_case

import itk_nrreval as nr

ANGLE = np.deg2rad(27.0)
ROTATION = np.array([[np.cos(ANGLE), -np.sin(ANGLE)], [np.sin(ANGLE), np.cos(ANGLE)]])
SHIFT = np.array([31.5, -12.25])


# 3D: 27 degrees about an oblique axis
ROTATION_3D = Rotation.from_rotvec(ANGLE * np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0)).as_matrix()
SHIFT_3D = np.array([31.5, -12.25, 7.0])


def move(point, rotation=ROTATION, shift=SHIFT) -> list[float]:
    return (rotation @ np.asarray(point, float) + shift).tolist()


def moved_copy(src, dst, rotation=ROTATION, shift=SHIFT) -> None:
    """Copy a case's files from `src` to `dst`, every one moved by the rigid motion."""
    dim = len(shift)
    shutil.copytree(src, dst)
    for path in dst.iterdir():
        if path.suffix == ".mat":
            continue  # identity affines: M o I o M^-1 = I
        if not (path.name.endswith(".nii.gz") or path.suffix == ".mha"):
            continue
        img = sitk.ReadImage(str(path))
        direction = rotation @ np.asarray(img.GetDirection()).reshape(dim, dim)
        origin = move(img.GetOrigin(), rotation, shift)
        if img.GetNumberOfComponentsPerPixel() == dim:  # a displacement field: rotate vectors
            arr = sitk.GetArrayFromImage(img) @ rotation.T
            img2 = sitk.GetImageFromArray(arr, isVector=True)
            img2.SetSpacing(img.GetSpacing())
            img = img2
        img.SetOrigin(origin)
        img.SetDirection(direction.reshape(-1).tolist())
        sitk.WriteImage(img, str(path))


@pytest.fixture(scope="module")
def both(tmp_path_factory):
    base = tmp_path_factory.mktemp("orientation")
    (base / "plain").mkdir()
    make_case(base / "plain")
    moved_copy(base / "plain", base / "moved")
    kw = dict(n_samples=3000, seed=3, progress=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        a = nr.evaluate(base / "plain" / "manifest.yaml", **kw)
        b = nr.evaluate(base / "moved" / "manifest.yaml", **kw)
    return a, b


def test_moved_case_is_really_oblique(tmp_path):
    (tmp_path / "plain").mkdir()
    make_case(tmp_path / "plain")
    moved_copy(tmp_path / "plain", tmp_path / "moved")
    img = sitk.ReadImage(str(tmp_path / "moved" / "img0.nii.gz"))
    np.testing.assert_allclose(np.reshape(img.GetDirection(), (2, 2)), ROTATION, atol=1e-6)
    field = sitk.ReadImage(str(tmp_path / "moved" / "truth0_1Warp.nii.gz"))
    t = sitk.DisplacementFieldTransform(sitk.Cast(field, sitk.sitkVectorFloat64))
    plain = sitk.DisplacementFieldTransform(
        sitk.Cast(
            sitk.ReadImage(str(tmp_path / "plain" / "truth0_1Warp.nii.gz")), sitk.sitkVectorFloat64
        )
    )
    p = np.array([20.3, 17.9])
    np.testing.assert_allclose(
        t.TransformPoint(move(p)), move(plain.TransformPoint(p.tolist())), atol=1e-4
    )


def test_evaluate_scores_do_not_depend_on_the_physical_frame(both):
    a, b = both
    for name in a.scores:
        sa, sb = a.scores[name], b.scores[name]
        for measure, va in sa.measures().items():
            assert sb.measures()[measure] == pytest.approx(va, rel=1e-6), (name, measure)
        assert sb.frame.spread_mean_mm == pytest.approx(sa.frame.spread_mean_mm, abs=1e-4)
        pa, pb = sa.plausibility, sb.plausibility
        assert pb.folded_fraction == pa.folded_fraction
        assert pb.sdlogj == pytest.approx(pa.sdlogj, rel=1e-6)
        assert pb.jacobian_min == pytest.approx(pa.jacobian_min, rel=1e-6)
        assert pb.jacobian_max == pytest.approx(pa.jacobian_max, rel=1e-6)
        np.testing.assert_allclose(b.mean_images[name], a.mean_images[name], atol=1e-6 * 100)
    assert a.verdict.ranking == b.verdict.ranking


# ----------------------------------------------------------------------------- 3D, anisotropic

SIZE_3D = (20, 18, 12)  # ITK (x, y, z)
SPACING_3D = (1.0, 1.25, 2.0)


def _field_3d(seed: int, amplitude: float) -> np.ndarray:
    """A smooth displacement (mm), numpy (z, y, x, 3), zero at the border."""
    rng = np.random.default_rng(seed)
    rel = np.meshgrid(*[np.linspace(0, 1, n) for n in SIZE_3D[::-1]], indexing="ij")  # z, y, x
    bump = np.prod([np.sin(np.pi * r) for r in rel], axis=0)
    out = np.zeros((*SIZE_3D[::-1], 3))
    for c in range(3):
        a, p = rng.uniform(-1, 1, 2)
        out[..., c] = amplitude * bump * a * np.sin(np.pi * (rel[2 - c] + p))
    return out


def _image_3d(arr: np.ndarray) -> sitk.Image:
    img = sitk.GetImageFromArray(arr, isVector=arr.ndim == 4)
    img.SetSpacing(SPACING_3D)
    img.SetOrigin((-3.0, 4.0, 10.0))
    return img


def make_moved_masked_case_3d(tmp_path) -> Path:
    """:func:`make_case_3d` moved by ``ROTATION_3D``, ``SHIFT_3D`` (oblique, not co-located
    with its reference), with a mask (the phantom, dilated by a voxel) in its manifest; the
    case's folder."""
    (tmp_path / "plain").mkdir()
    make_case_3d(tmp_path / "plain")
    folder = tmp_path / "moved"
    moved_copy(tmp_path / "plain", folder, ROTATION_3D, SHIFT_3D)
    template = sitk.ReadImage(str(folder / "template.nii.gz"))
    mask = sitk.BinaryDilate(sitk.BinaryThreshold(template, 1.0, 1e9), [1, 1, 1])
    sitk.WriteImage(sitk.Cast(mask, sitk.sitkUInt8), str(folder / "mask.nii.gz"))
    data = yaml.safe_load((folder / "manifest.yaml").read_text())
    data["mask"] = "mask.nii.gz"
    (folder / "manifest.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    return folder


def make_case_3d(folder) -> None:
    """Five 3D images: an ellipsoid phantom with two inner structures, warped by known fields.

    Anisotropic voxels (1 x 1.25 x 2 mm). Registrations: the truth, the truth perturbed
    by a second field, and the identity (in image 0's frame).
    """
    z, y, x = np.meshgrid(
        *[np.arange(n) * s for n, s in zip(SIZE_3D, SPACING_3D, strict=True)][::-1], indexing="ij"
    )
    centre = np.array([9.5, 10.6, 11.0])  # mm, (x, y, z) from the first voxel
    labels = np.zeros(SIZE_3D[::-1], np.int16)
    for k, (shift, radii) in enumerate(
        [((0, 0, 0), (8, 9, 9)), ((-3, 2, 0), (3, 3, 5)), ((3, -2, 2), (3, 4, 4))], start=1
    ):
        c = centre + shift
        inside = ((x - c[0]) / radii[0]) ** 2 + ((y - c[1]) / radii[1]) ** 2
        labels[inside + ((z - c[2]) / radii[2]) ** 2 <= 1] = k
    intensity = np.array([0.0, 60.0, 100.0, 140.0])[labels]
    tmpl = _image_3d(intensity)
    sitk.WriteImage(tmpl, str(folder / "template.nii.gz"))
    rng = np.random.default_rng(0)
    data = {"images": [], "labels": [], "registrations": {}}
    truth, perturbed, identity = [], [], []
    for i in range(5):
        s_i = sitk.DisplacementFieldTransform(_image_3d(_field_3d(i, 2.0)))
        contrast = intensity * (1.0 + 0.1 * rng.standard_normal()) + 5.0 * (labels == 2) * i
        img = sitk.Resample(_image_3d(contrast), tmpl, s_i, sitk.sitkLinear, 0.0)
        lab = sitk.Resample(_image_3d(labels), tmpl, s_i, sitk.sitkNearestNeighbor, 0)
        sitk.WriteImage(img, str(folder / f"img{i}.nii.gz"))
        sitk.WriteImage(lab, str(folder / f"lab{i}.nii.gz"))
        inverse = sitk.InvertDisplacementField(
            _image_3d(_field_3d(i, 2.0)),
            maximumNumberOfIterations=50,
            maxErrorToleranceThreshold=0.01,
            meanErrorToleranceThreshold=1e-4,
        )
        sitk.WriteImage(inverse, str(folder / f"truth{i}.nii.gz"))
        sitk.WriteImage(_image_3d(_field_3d(100 + i, 1.5)), str(folder / f"pert{i}.mha"))
        sitk.WriteTransform(sitk.AffineTransform(3), str(folder / f"id{i}.mat"))
        data["images"].append(f"img{i}.nii.gz")
        data["labels"].append(f"lab{i}.nii.gz")
        truth.append(f"truth{i}.nii.gz")
        perturbed.append([f"pert{i}.mha", f"truth{i}.nii.gz"])
        identity.append(f"id{i}.mat")
    data["registrations"] = {
        "truth": {"reference": "template.nii.gz", "transforms": truth},
        "perturbed": {"reference": "template.nii.gz", "transforms": perturbed},
        "identity": {"reference": "img0.nii.gz", "reference_index": 0, "transforms": identity},
    }
    (folder / "manifest.yaml").write_text(yaml.safe_dump(data, sort_keys=False))


def test_evaluate_3d_scores_do_not_depend_on_the_physical_frame(tmp_path):
    """3D, anisotropic voxels, rotated about an oblique axis and moved."""
    (tmp_path / "plain").mkdir()
    make_case_3d(tmp_path / "plain")
    moved_copy(tmp_path / "plain", tmp_path / "moved", ROTATION_3D, SHIFT_3D)
    moved = sitk.ReadImage(str(tmp_path / "moved" / "img0.nii.gz"))
    assert np.abs(np.reshape(moved.GetDirection(), (3, 3)) - np.eye(3)).min(axis=1).max() > 0.1
    kw = dict(n_samples=2000, seed=3, progress=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        a = nr.evaluate(tmp_path / "plain" / "manifest.yaml", **kw)
        b = nr.evaluate(tmp_path / "moved" / "manifest.yaml", **kw)
    assert a.scores["truth"].specificity.value < a.scores["perturbed"].specificity.value
    for name in a.scores:
        sa, sb = a.scores[name], b.scores[name]
        # "perturbed" reaches the common frame through the mean of numerically inverted
        # fields, whose fixed-point iteration stops at 0.01 voxel: not round-off, so 1e-4.
        rel = 1e-4 if sa.frame.method == "mean" else 1e-6
        for measure, va in sa.measures().items():
            assert sb.measures()[measure] == pytest.approx(va, rel=rel), (name, measure)
        assert sb.frame.spread_mean_mm == pytest.approx(sa.frame.spread_mean_mm, abs=1e-3)
        assert sb.plausibility.sdlogj == pytest.approx(sa.plausibility.sdlogj, rel=1e-6)
        assert sb.coverage.evaluated == sa.coverage.evaluated
    assert a.verdict.ranking == b.verdict.ranking


def test_images_stored_with_finer_anisotropic_voxels_score_the_same(tmp_path):
    """make_case's images stored at 0.5 x 1 mm instead of 1 x 1 mm.

    The fine grid's voxel centres include the coarse ones, so linear interpolation on it of
    a linearly upsampled image reproduces linear interpolation on the coarse grid exactly:
    the images in the common frame, and hence specificity, must not change. (Its field of
    view is a quarter voxel narrower at each end, where the transforms do not reach.) Label
    maps upsampled by nearest neighbour move label boundaries by up to a quarter voxel, so
    the overlap may move a little.
    """
    (tmp_path / "plain").mkdir()
    data = make_case(tmp_path / "plain")
    shutil.copytree(tmp_path / "plain", tmp_path / "fine")
    for key, interp in (("images", sitk.sitkLinear), ("labels", sitk.sitkNearestNeighbor)):
        for name in data[key]:
            path = str(tmp_path / "fine" / name)
            img = sitk.ReadImage(path)
            fine = sitk.Image([2 * img.GetSize()[0] - 1, img.GetSize()[1]], img.GetPixelID())
            fine.SetSpacing((0.5, 1.0))
            fine.SetOrigin(img.GetOrigin())
            sitk.WriteImage(sitk.Resample(img, fine, sitk.Transform(), interp, 0), path)
    kw = dict(n_samples=2000, seed=3, progress=False, confidence=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        a = nr.evaluate(tmp_path / "plain" / "manifest.yaml", **kw)
        b = nr.evaluate(tmp_path / "fine" / "manifest.yaml", **kw)
    for name in a.scores:
        sa, sb = a.scores[name], b.scores[name]
        assert sb.specificity.value == pytest.approx(sa.specificity.value, rel=1e-6), name
        for w, va in sa.overlap.items():
            # measured: up to 0.008 (the label maps really differ)
            assert sb.overlap[w] == pytest.approx(va, abs=0.02), (name, w)
    assert a.verdict.ranking == b.verdict.ranking


def test_validate_does_not_depend_on_the_physical_frame(tmp_path):
    """The validation experiment on a manifest, before and after the rigid motion."""
    from itk_nrreval.experiments.perturbation import validate_manifest

    (tmp_path / "plain").mkdir()
    make_case(tmp_path / "plain")
    moved_copy(tmp_path / "plain", tmp_path / "moved")
    kw = dict(displacements=(0.0, 0.5, 1.0), repeats=1, n_samples=1000, seed=2, progress=False)
    a = validate_manifest(tmp_path / "plain" / "manifest.yaml", **kw)
    b = validate_manifest(tmp_path / "moved" / "manifest.yaml", **kw)
    assert len(a.rows) == len(b.rows) == 3
    for ra, rb in zip(a.rows, b.rows, strict=True):
        assert rb.displacement == ra.displacement
        assert rb.specificity == pytest.approx(ra.specificity, rel=1e-6)
        for w, v in ra.overlap.items():
            assert rb.overlap[w] == pytest.approx(v, abs=1e-6)
    assert a.rows[0].specificity < a.rows[-1].specificity  # the perturbation does something


@pytest.mark.parametrize("labels", [True, False])
def test_images_of_a_mean_frame_registration_equal_itk_resampling_through_the_composite(
    tmp_path, labels
):
    """The composed displacement the pipeline samples for a registration reached through its
    mean frame F (no composite built) gives what ITK's own resampling through
    ``CompositeTransform([T_i^R, F])`` gives: oblique, anisotropic 3D, float32 as cached;
    with label maps (one sampling for both) and without (the image alone, by the same
    kernels)."""
    from itk_nrreval.io.transforms import chain_transform

    (tmp_path / "plain").mkdir()
    make_case_3d(tmp_path / "plain")
    folder = tmp_path / "moved"
    moved_copy(tmp_path / "plain", folder, ROTATION_3D, SHIFT_3D)
    data = yaml.safe_load((folder / "manifest.yaml").read_text())
    if not labels:
        assert data.pop("labels")
        (folder / "manifest.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        result = nr.evaluate(
            folder / "manifest.yaml",
            n_samples=2000,
            seed=5,
            progress=False,
            execution=nr.Execution(cache=tmp_path / "cache", keep_resampled=True),
        )
    # what is checked is the resampled images saved
    nr.export_resampled(result, tmp_path / "out" / "resampled", cache=tmp_path / "cache")
    frame = result.scores["perturbed"].frame
    assert frame.method == "mean"
    common = sitk.ReadImage(str(folder / "template.nii.gz"))
    for i, item in enumerate(data["registrations"]["perturbed"]["transforms"]):
        t = chain_transform([folder / p for p in item])
        img = sitk.Cast(sitk.ReadImage(str(folder / data["images"][i])), sitk.sitkFloat64)
        composite = sitk.CompositeTransform([t, frame.transform])
        ref = sitk.GetArrayFromImage(
            sitk.Resample(img, common, composite, sitk.sitkLinear, np.nan, sitk.sitkFloat64)
        )
        saved = tmp_path / "out" / "resampled" / "perturbed" / f"image_{i:03d}.nii.gz"
        got = sitk.GetArrayFromImage(sitk.ReadImage(str(saved)))
        inside = ~np.isnan(ref)
        assert inside.mean() > 0.5
        np.testing.assert_array_equal(got[~inside], 0.0)
        scale = np.abs(ref[inside]).max()
        np.testing.assert_allclose(got[inside], ref[inside], rtol=0, atol=1e-6 * scale)
