"""Evaluation images: another scan of each subject, resampled through the registration's
transforms and scored in its image's place (the manifest's ``evaluation_images``)."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
import yaml
from test_in_memory import oblique_3d_direction

import itk_nrreval as nr
from data_synth import make_population, write_population
from itk_nrreval._errors import InputError
from itk_nrreval.cli import main
from itk_nrreval.io.manifest import load_manifest, write_manifest

KW = dict(n_samples=2000, seed=3, progress=False)
N = 6


@pytest.fixture(scope="module")
def two_contrasts(tmp_path_factory):
    """A small 3D population imaged in T1 and T2 (independent noise and bias), with its true
    registration of the T1 images: (folder, T1 images, T2 images, labels, truth entry)."""
    folder = tmp_path_factory.mktemp("contrasts")
    pop = make_population(
        "phantom", dim=3, n=N, seed=5, spacing=4.0, size=(24, 28, 22), contrasts=("t1", "t2")
    )
    m = load_manifest(write_population(pop, folder, montage=False, progress=False))
    t1 = [p for p, g in zip(m.images, m.groups, strict=True) if g == "t1"]
    t2 = [p for p, g in zip(m.images, m.groups, strict=True) if g == "t2"]
    labels = list(m.labels[:N])
    truth = m.registrations["truth"]
    entry = {
        "reference": str(truth.reference),
        "transforms": [[str(t) for t in c] for c in truth.transforms[:N]],
    }
    return folder, t1, t2, labels, entry


def _manifest(images, labels, entry, **extra) -> dict:
    return {
        "images": [str(p) for p in images],
        "labels": [str(p) for p in labels],
        **extra,
        "registrations": {"truth": entry},
    }


def test_the_evaluation_images_are_scored_with_the_registrations_own_geometry(two_contrasts):
    """Scoring T1 images with T2 evaluation images gives the specificity of the T2 images
    registered by the same transforms (a manifest listing the T2 images as its images: the
    independent reference), and the T1 manifest's labels, overlap and plausibility."""
    folder, t1, t2, labels, entry = two_contrasts
    with_t2 = nr.evaluate(
        _manifest(t1, labels, entry, evaluation_images=[str(p) for p in t2]), **KW
    )
    t2_alone = nr.evaluate(_manifest(t2, labels, entry), **KW)
    t1_alone = nr.evaluate(_manifest(t1, labels, entry), **KW)
    a, b, c = (r.scores["truth"] for r in (with_t2, t2_alone, t1_alone))
    assert a.specificity.value == b.specificity.value
    assert a.generalization.value == b.generalization.value
    assert a.specificity.value != c.specificity.value  # the T2 voxels are what is scored
    assert a.overlap == c.overlap and a.plausibility == c.plausibility
    assert with_t2.options["scored_images"] == "evaluation_images"
    assert t1_alone.options["scored_images"] == "images"
    assert with_t2.inputs["evaluation_images"] == [str(p) for p in t2]


def test_a_written_manifest_keeps_its_evaluation_images(two_contrasts, tmp_path):
    folder, t1, t2, labels, entry = two_contrasts
    m = load_manifest(_manifest(t1, labels, entry, evaluation_images=[str(p) for p in t2]))
    path = write_manifest(m, tmp_path / "manifest.yaml")
    assert "evaluation_images:" in path.read_text()
    again = load_manifest(path)
    assert [p.resolve() for p in again.evaluation_images] == [p.resolve() for p in t2]
    assert set(t2) <= {p.resolve() for p in again.files}  # an output folder may not hold them


def _oblique_copy(path, out, *, shift_mm: float = 0.0) -> str:
    """The image resampled onto an oblique (rotated about all three axes), anisotropic grid
    covering its physical space, then moved by `shift_mm` along x."""
    image = sitk.ReadImage(str(path))
    direction = oblique_3d_direction()
    spacing = np.asarray(image.GetSpacing()) * np.array([1.0, 1.5, 0.75])
    # 1.5x the extent: the rotated grid covers the whole of the original
    size = [
        int(1.5 * n * s / t)
        for n, s, t in zip(image.GetSize(), image.GetSpacing(), spacing, strict=True)
    ]
    centre = np.asarray(
        image.TransformContinuousIndexToPhysicalPoint((np.asarray(image.GetSize()) - 1) / 2)
    )
    origin = centre - direction @ (spacing * (np.asarray(size) - 1) / 2) + [shift_mm, 0, 0]
    grid = sitk.Image(size, image.GetPixelID())
    grid.SetSpacing(spacing.tolist())
    grid.SetDirection(direction.ravel().tolist())
    grid.SetOrigin(origin.tolist())
    sitk.WriteImage(sitk.Resample(image, grid, sitk.Transform(), sitk.sitkLinear, 0.0), str(out))
    return str(out)


def test_an_oblique_anisotropic_scan_of_the_same_space_is_accepted(two_contrasts, tmp_path):
    """Evaluation images on another grid (oblique, anisotropic, larger) in the same physical
    space pass the same-space check and are scored like the same files listed as images."""
    folder, t1, t2, labels, entry = two_contrasts
    oblique = [_oblique_copy(p, tmp_path / f"o{i}.nii.gz") for i, p in enumerate(t2)]
    result = nr.evaluate(_manifest(t1, labels, entry, evaluation_images=oblique), **KW)
    reference = nr.evaluate(_manifest(oblique, labels, entry), **KW)
    assert result.scores["truth"].specificity.value == reference.scores["truth"].specificity.value


@pytest.mark.parametrize(
    "edit, message",
    [
        (
            lambda d, t2, tmp: d.update(evaluation_images=d["evaluation_images"][:-1]),
            "evaluation_images: 5 images for 6 images",
        ),
        (
            lambda d, t2, tmp: d["evaluation_images"].__setitem__(2, str(tmp / "missing.nii.gz")),
            "evaluation_images[2]: file not found",
        ),
        (
            lambda d, t2, tmp: d["evaluation_images"].__setitem__(
                1, _oblique_copy(t2[1], tmp / "far.nii.gz", shift_mm=400.0)
            ),
            "evaluation_images[1]: far.nii.gz shares 0% of its physical extent with images[1]",
        ),
    ],
)
def test_bad_evaluation_images_one_line_exit_2(two_contrasts, tmp_path, capsys, edit, message):
    folder, t1, t2, labels, entry = two_contrasts
    data = _manifest(t1, labels, entry, evaluation_images=[str(p) for p in t2])
    edit(data, t2, tmp_path)
    with pytest.raises(InputError, match=message.replace("[", r"\[").replace("]", r"\]")):
        load_manifest(data)
    path = tmp_path / "m.yaml"
    path.write_text(yaml.safe_dump(data))
    out = tmp_path / "out"
    assert main(["evaluate", str(path), "--out", str(out), "--samples", "500"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err and not out.exists()
