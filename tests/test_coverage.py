"""Fields of view: scores are taken where every image has a value (issue 15, item 4).

Voxels of the common grid that a transform maps outside an image's field of view have no
value there. Filled with 0, they entered the PCA and the overlap, so a difference in field
of view read as misregistration. The reference here is independent of the pipeline: each
image resampled with SimpleITK (NaN outside), the region where no image is NaN under any
registration, and :func:`itk_nrreval.specificity` on that region.
"""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
import yaml
from test_evaluate import make_case

import itk_nrreval as nr
from itk_nrreval.io.transforms import chain_transform

KW = dict(n_samples=2000, seed=5, progress=False, confidence=False)
CROPPED = (3, 4, 5)


def cropped_case(tmp_path, *, crop: int = 12) -> dict:
    """make_case with two registrations in the template frame and images 3-5 cropped.

    The cropped images lose their last `crop` columns (physical positions kept), which
    hold part of the phantom.
    """
    data = make_case(tmp_path)
    for i in CROPPED:
        path = str(tmp_path / data["images"][i])
        img = sitk.ReadImage(path)
        size = list(img.GetSize())
        sitk.WriteImage(sitk.RegionOfInterest(img, [size[0] - crop, size[1]], [0, 0]), path)
    sitk.WriteTransform(sitk.AffineTransform(2), str(tmp_path / "frame_identity.tfm"))
    data["registrations"] = {
        "truth": data["registrations"]["truth"],
        "perturbed": {
            **data["registrations"]["perturbed"],
            "frame_transform": "frame_identity.tfm",
        },
    }
    (tmp_path / "manifest.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    return data


def reference_resampled(tmp_path, data) -> dict[str, np.ndarray]:
    """Each registration's images on the template grid, NaN outside their field of view."""
    grid = sitk.ReadImage(str(tmp_path / "template.nii.gz"))
    out = {}
    for name, reg in data["registrations"].items():
        stack = []
        for path, item in zip(data["images"], reg["transforms"], strict=True):
            items = item if isinstance(item, list) else [item]
            t = chain_transform([str(tmp_path / p) for p in items])
            img = sitk.Cast(sitk.ReadImage(str(tmp_path / path)), sitk.sitkFloat64)
            res = sitk.Resample(img, grid, t, sitk.sitkLinear, float("nan"))
            stack.append(sitk.GetArrayFromImage(res))
        out[name] = np.stack(stack)
    return out


@pytest.mark.parametrize("distance", ["l1", "l2"])
def test_specificity_is_taken_where_every_image_has_a_value(tmp_path, distance):
    data = cropped_case(tmp_path)
    stacks = reference_resampled(tmp_path, data)
    region = np.all([~np.isnan(s).any(axis=0) for s in stacks.values()], axis=0)
    assert 0.5 < region.mean() < 0.9  # the crop matters, and leaves most of the grid
    with pytest.warns(UserWarning, match=r"scores are taken on the \d+% of the voxels"):
        res = nr.evaluate(tmp_path / "manifest.yaml", distance=distance, **KW)
    for name, stack in stacks.items():
        expected = nr.specificity(
            np.nan_to_num(stack), mask=region, n_samples=2000, seed=5, distance=distance
        )
        got = res.scores[name].specificity
        # evaluate's cache holds the resampled images in float32 (relative rounding 6e-8)
        assert got.value == pytest.approx(expected.value, rel=1e-6), name
        assert got.stderr == pytest.approx(expected.stderr, rel=1e-6), name


def test_coverage_reported_per_registration(tmp_path):
    data = cropped_case(tmp_path)
    stacks = reference_resampled(tmp_path, data)
    region = np.all([~np.isnan(s).any(axis=0) for s in stacks.values()], axis=0)
    with pytest.warns(UserWarning, match="least: registration"):
        run = nr.evaluate(tmp_path / "manifest.yaml", **KW)
    for name, stack in stacks.items():
        cov = run.scores[name].coverage
        covered = ~np.isnan(stack)
        assert cov.fraction == pytest.approx(covered.all(axis=0).mean(), abs=1e-12)
        np.testing.assert_allclose(cov.per_image, covered.reshape(len(stack), -1).mean(axis=1))
        assert cov.evaluated == pytest.approx(region.mean(), abs=1e-12)
        assert all(cov.per_image[i] == 1.0 for i in range(6) if i not in CROPPED)


def test_full_coverage_changes_nothing_and_warns_nothing(tmp_path, recwarn):
    """Images that cover the whole grid: the region is the grid, no warning about it."""
    make_case(tmp_path)
    res = nr.evaluate(tmp_path / "manifest.yaml", **KW)
    assert not [w for w in recwarn if "scores are taken on" in str(w.message)]
    for name in res.scores:
        assert res.scores[name].coverage.evaluated == 1.0


def test_overlap_is_taken_where_every_image_has_a_value(tmp_path):
    """Reference: one-hot memberships resampled linearly by SimpleITK, overlap in the region."""
    data = cropped_case(tmp_path)
    stacks = reference_resampled(tmp_path, data)
    region = np.all([~np.isnan(s).any(axis=0) for s in stacks.values()], axis=0)
    grid = sitk.ReadImage(str(tmp_path / "template.nii.gz"))
    with pytest.warns(UserWarning, match="scores are taken on"):
        res = nr.evaluate(tmp_path / "manifest.yaml", weightings=("inverse_volume",), **KW)
    for name, reg in data["registrations"].items():
        memberships = []
        for path, item in zip(data["labels"], reg["transforms"], strict=True):
            items = item if isinstance(item, list) else [item]
            t = chain_transform([str(tmp_path / p) for p in items])
            lab = sitk.GetArrayFromImage(sitk.ReadImage(str(tmp_path / path)))
            channels = []
            for v in (0, 1, 2, 3):
                one = sitk.GetImageFromArray((lab == v).astype(np.float64))
                one.CopyInformation(sitk.ReadImage(str(tmp_path / path)))
                res_v = sitk.Resample(one, grid, t, sitk.sitkLinear, 0.0)
                channels.append(sitk.GetArrayFromImage(res_v))
            memberships.append(np.stack(channels))
        expected = nr.generalized_overlap(
            np.stack(memberships), weighting="inverse_volume", mask=region
        )
        got = res.scores[name].overlap["inverse_volume"]
        assert got == pytest.approx(expected, rel=1e-9), name


def test_coverage_that_disagrees_with_the_resampling_is_an_error_not_a_score(tmp_path, monkeypatch):
    """Issue 30: the region is found from each transform's measured coverage before any
    image is resampled. Were the two to disagree, an image's 0 outside its field of view
    would enter the scores: a silent wrong number. Simulated by a coverage that claims every
    voxel of the cropped images."""
    from itk_nrreval._pipeline import _image_tasks

    cropped_case(tmp_path)
    monkeypatch.setattr(
        _image_tasks,
        "covered_voxels",
        lambda image_grid, t, g, **kw: np.ones(np.prod(g.shape), bool),
    )
    with pytest.raises(RuntimeError, match=r"has no value at \d+ voxels of the evaluated region"):
        nr.evaluate(tmp_path / "manifest.yaml", **KW)
