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

import numpy as np
import pytest
import SimpleITK as sitk
from test_evaluate import make_case

import itk_nrreval as nr

ANGLE = np.deg2rad(27.0)
ROTATION = np.array([[np.cos(ANGLE), -np.sin(ANGLE)], [np.sin(ANGLE), np.cos(ANGLE)]])
SHIFT = np.array([31.5, -12.25])


def move(point) -> list[float]:
    return (ROTATION @ np.asarray(point, float) + SHIFT).tolist()


def moved_copy(src, dst) -> None:
    """Copy make_case's files from `src` to `dst`, every one moved by the rigid motion."""
    shutil.copytree(src, dst)
    for path in dst.iterdir():
        if path.suffix == ".mat":
            continue  # identity affines: M o I o M^-1 = I
        if not (path.name.endswith(".nii.gz") or path.suffix == ".mha"):
            continue
        img = sitk.ReadImage(str(path))
        direction = ROTATION @ np.asarray(img.GetDirection()).reshape(2, 2)
        origin = move(img.GetOrigin())
        if img.GetNumberOfComponentsPerPixel() == 2:  # a displacement field: rotate vectors
            arr = sitk.GetArrayFromImage(img) @ ROTATION.T
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
