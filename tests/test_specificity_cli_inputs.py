"""``nrreval specificity`` refuses what evaluate's manifest check refuses in its images: an
image listed twice (the same file or the same voxels on the same grid), a constant image,
NaN voxels. Each would change the numbers without a word; each is one line, exit 2,
before any work, and nothing is written."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import SimpleITK as sitk

from itk_nrreval.cli import main


def _write(path, array):
    """A 3D image on an oblique, anisotropic grid away from the origin (all images share it)."""
    img = sitk.GetImageFromArray(array.astype(np.float32))
    img.SetSpacing((1.2, 0.9, 2.5))
    img.SetOrigin((-30.0, 12.5, 7.0))
    c, s = np.cos(0.3), np.sin(0.3)
    img.SetDirection((c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0))
    sitk.WriteImage(img, str(path))
    return str(path)


@pytest.fixture
def images(tmp_path):
    rng = np.random.default_rng(7)
    return [_write(tmp_path / f"s{i}.nii.gz", rng.normal(size=(6, 8, 7))) for i in range(3)]


@pytest.mark.parametrize("problem", ["same file", "same voxels", "constant", "nan"])
def test_images_that_would_change_the_numbers_silently_are_refused(
    images, tmp_path, capsys, problem
):
    listed = list(images)
    if problem == "same file":
        listed.append(images[1])
        expected = "images[3] s1.nii.gz is the same file as images[1] s1.nii.gz"
    elif problem == "same voxels":
        listed.append(str(shutil.copy(images[2], tmp_path / "copy_of_s2.nii.gz")))
        expected = "holds the same voxels on the same grid as images[2]"
    elif problem == "constant":
        listed.append(_write(tmp_path / "zeros.nii.gz", np.zeros((6, 8, 7))))
        expected = "zeros.nii.gz is constant (every voxel is 0)"
    else:
        values = np.random.default_rng(8).normal(size=(6, 8, 7))
        values[2, 3, 4] = np.nan
        listed.append(_write(tmp_path / "nan.nii.gz", values))
        expected = "nan.nii.gz: image contains NaN or infinite voxel values"
    out = tmp_path / "numbers.json"
    capsys.readouterr()
    code = main(["specificity", *listed, "--samples", "50", "--json", str(out)])
    err = capsys.readouterr().err
    assert code == 2
    assert err.count("\n") == 1 and "Traceback" not in err
    assert expected in err, err
    assert not out.exists()


def test_distinct_images_are_scored(images, tmp_path, capsys):
    out = tmp_path / "numbers.json"
    assert main(["specificity", *images, "--samples", "50", "--json", str(out), "--quiet"]) == 0
    assert out.exists()
