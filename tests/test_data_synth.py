"""Tests of data_synth: synthetic populations with known true correspondence.

Every check is independent of the generator's internals: overlaps are counted here from the
label arrays, Jacobians come from numpy gradients of dense fields that ITK computes from the
transforms, and round trips go through ITK's own composition.
"""

from __future__ import annotations

import re
from functools import cache
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk

from data_synth.mni import make_mni
from data_synth.phantom import PHANTOM_LABELS, make_phantom
from data_synth.population import make_population, perfect_registration

# Small grids keep the whole file fast: 2D at the default 141 x 141, 3D at coarse voxels.
CASES = [("phantom", 2, None), ("mni", 2, None), ("phantom", 3, 6.0), ("mni", 3, 6.0)]
IDS = [f"{k}-{d}d" for k, d, _ in CASES]


@cache
def population(kind: str, dim: int, spacing: float | None, seed: int = 3, n: int = 3):
    return make_population(kind, dim=dim, n=n, seed=seed, spacing=spacing)


def arr(image: sitk.Image) -> np.ndarray:
    return sitk.GetArrayFromImage(image)


def dice_per_label(a: np.ndarray, b: np.ndarray, values) -> dict[int, float]:
    return {
        int(v): 2.0 * np.sum((a == v) & (b == v)) / (np.sum(a == v) + np.sum(b == v))
        for v in values
    }


def dense_displacement(transform: sitk.Transform, grid: sitk.Image) -> np.ndarray:
    """ITK's displacement field of `transform` on `grid`, numpy order, components (x, y[, z])."""
    field = sitk.TransformToDisplacementField(
        transform,
        sitk.sitkVectorFloat64,
        grid.GetSize(),
        grid.GetOrigin(),
        grid.GetSpacing(),
        grid.GetDirection(),
    )
    return arr(field)


def jacobian_determinant(disp: np.ndarray, spacing_xyz) -> np.ndarray:
    """det(I + grad u) by central differences; `disp` numpy order with (x, y[, z]) components."""
    dim = disp.shape[-1]
    spacing_np = tuple(reversed(spacing_xyz))
    jac = np.empty(disp.shape[:-1] + (dim, dim))
    for comp in range(dim):  # component along ITK axis `comp`
        grads = np.gradient(disp[..., comp], *spacing_np)  # derivatives along numpy axes
        for ax_np, g in enumerate(grads):
            ax_itk = dim - 1 - ax_np
            jac[..., comp, ax_itk] = g + (1.0 if comp == ax_itk else 0.0)
    return np.linalg.det(jac)


# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind,dim,spacing", CASES, ids=IDS)
def test_true_transforms_map_subject_labels_back_onto_template(kind, dim, spacing):
    pop = population(kind, dim, spacing)
    template_labels = arr(pop.template_labels)
    values = sorted(pop.label_names)
    assert set(np.unique(template_labels)) - {0} == set(values)
    volumes = np.array([np.sum(template_labels == v) for v in values], dtype=float)
    for i, subject in enumerate(pop.subjects):
        assert subject.labels.GetPixelID() == sitk.sitkUInt8
        back = arr(
            sitk.Resample(
                subject.labels,
                pop.template,
                subject.template_to_subject,
                sitk.sitkNearestNeighbor,
                0,
                sitk.sitkUInt8,
            )
        )
        dice = dice_per_label(back, template_labels, values)
        weighted = float(np.average([dice[v] for v in values], weights=volumes))
        # Two nearest-neighbour-like resamplings (there and back) only touch label borders.
        assert weighted > (0.93 if dim == 2 else 0.85), (i, dice)
        big = [v for v, vol in zip(values, volumes, strict=True) if vol >= 200]
        assert min(dice[v] for v in big) > (0.85 if dim == 2 else 0.75), (i, dice)
        # Control: another subject's transform must do clearly worse.
        other = pop.subjects[(i + 1) % len(pop.subjects)]
        wrong = arr(
            sitk.Resample(
                subject.labels, pop.template, other.template_to_subject, sitk.sitkNearestNeighbor
            )
        )
        dice_wrong = dice_per_label(wrong, template_labels, values)
        weighted_wrong = float(np.average([dice_wrong[v] for v in values], weights=volumes))
        assert weighted_wrong < weighted - 0.05


@pytest.mark.parametrize("kind,dim,spacing", CASES, ids=IDS)
def test_inverse_round_trips_to_a_twentieth_of_a_voxel(kind, dim, spacing):
    pop = population(kind, dim, spacing)
    voxel = min(pop.template.GetSpacing())
    for subject in pop.subjects:
        # p -> subject -> template: the composite applies its last transform first.
        there_and_back = sitk.CompositeTransform(
            [subject.subject_to_template, subject.template_to_subject]
        )
        err = np.linalg.norm(dense_displacement(there_and_back, pop.template), axis=-1)
        assert err.max() < 0.05 * voxel
        back_and_there = sitk.CompositeTransform(
            [subject.template_to_subject, subject.subject_to_template]
        )
        err = np.linalg.norm(dense_displacement(back_and_there, pop.template), axis=-1)
        assert err.max() < 0.05 * voxel
        # ... and the transform is not the identity: the subjects really move.
        moved = np.linalg.norm(
            dense_displacement(subject.template_to_subject, pop.template), axis=-1
        )
        assert moved.mean() > voxel


@pytest.mark.parametrize("kind,dim,spacing", CASES, ids=IDS)
def test_warps_never_fold(kind, dim, spacing):
    pop = population(kind, dim, spacing)
    for subject in pop.subjects:
        for transform in (subject.template_to_subject, subject.subject_to_template):
            det = jacobian_determinant(
                dense_displacement(transform, pop.template), pop.template.GetSpacing()
            )
            assert det.min() > 0.0
            assert det.max() > 1.02 or det.min() < 0.98  # a real deformation, not a rigid move


def test_warp_is_folding_free_even_for_a_large_amplitude():
    pop = make_population("phantom", dim=2, n=2, seed=11, warp_mm=10.0, smoothness_mm=15.0)
    for subject in pop.subjects:
        det = jacobian_determinant(
            dense_displacement(subject.template_to_subject, pop.template),
            pop.template.GetSpacing(),
        )
        assert det.min() > 0.0
        assert det.min() < 0.8  # large enough to matter


@pytest.mark.parametrize("kind,dim,spacing", CASES[:2] + CASES[2:3], ids=IDS[:3])
def test_same_seed_gives_identical_data_and_another_seed_differs(kind, dim, spacing):
    a = make_population(kind, dim=dim, n=2, seed=5, spacing=spacing)
    b = make_population(kind, dim=dim, n=2, seed=5, spacing=spacing)
    c = make_population(kind, dim=dim, n=2, seed=6, spacing=spacing)
    for sa, sb, sc in zip(a.subjects, b.subjects, c.subjects, strict=True):
        np.testing.assert_array_equal(arr(sa.image), arr(sb.image))
        np.testing.assert_array_equal(arr(sa.labels), arr(sb.labels))
        pa = np.asarray(sa.template_to_subject.TransformPoint([3.0] * dim))
        pb = np.asarray(sb.template_to_subject.TransformPoint([3.0] * dim))
        np.testing.assert_array_equal(pa, pb)
        assert not np.array_equal(arr(sa.image), arr(sc.image))
        assert not np.array_equal(arr(sa.labels), arr(sc.labels))
    assert not np.array_equal(arr(a.subjects[0].image), arr(a.subjects[1].image))


def test_subject_does_not_depend_on_population_size():
    small = make_population("phantom", dim=2, n=1, seed=9)
    large = make_population("phantom", dim=2, n=3, seed=9)
    np.testing.assert_array_equal(arr(small.subjects[0].image), arr(large.subjects[0].image))


def test_perfect_registration_aligns_subjects_with_the_template():
    pop = population("phantom", 2, None)
    reg = perfect_registration(pop)
    template = arr(pop.template)
    assert len(reg.images) == len(reg.labels) == len(pop)
    for subject, image, labels in zip(pop.subjects, reg.images, reg.labels, strict=True):
        assert image.GetSize() == pop.template.GetSize()
        assert labels.GetPixelID() == sitk.sitkUInt8
        aligned = np.corrcoef(arr(image).ravel(), template.ravel())[0, 1]
        unaligned = np.corrcoef(arr(subject.image).ravel(), template.ravel())[0, 1]
        assert aligned > 0.9
        assert aligned > unaligned + 0.05


def test_phantom_labels_span_two_orders_of_magnitude():
    for dim, spacing in ((2, None), (3, 3.0)):
        ph = make_phantom(dim=dim, spacing=spacing)
        labels = arr(ph.labels)
        assert labels.dtype == np.uint8
        assert len(ph.label_names) >= 8
        assert set(ph.label_names.items()) <= set(PHANTOM_LABELS.items())
        volumes = np.array([np.sum(labels == v) for v in ph.label_names])
        assert volumes.min() > 0
        assert volumes.max() / volumes.min() >= 100
        # Left and right structures sit on their own side: +x is the patient's left (LPS).
        x = np.asarray(
            [
                ph.labels.TransformIndexToPhysicalPoint([int(i) for i in idx[::-1]])[0]
                for idx in np.argwhere(labels == 7)
            ]
        )
        assert (x > 0).all()
        # Partial-volume edges: intensities between the tissue levels occur.
        image = arr(ph.image)
        assert 0.0 <= image.min() and image.max() <= 1.0
        assert np.sum((image > 0.52) & (image < 0.78)) > 0.01 * image.size


@pytest.mark.parametrize(
    "kwargs,message",
    [
        ({"kind": "ct"}, r"kind must be one of \('phantom', 'mni'\), got 'ct'"),
        ({"dim": 4}, r"dim must be 2 or 3, got 4"),
        ({"n": 0}, r"n must be a positive number of subjects, got 0"),
        ({"warp_mm": -1.0}, r"warp_mm must be a finite number >= 0, got -1.0"),
        ({"seed": -3}, r"seed must be a non-negative integer, got -3"),
    ],
)
def test_bad_arguments_name_the_argument(kwargs, message):
    kind = kwargs.pop("kind", "phantom")
    with pytest.raises(ValueError, match=message):
        make_population(kind, n=kwargs.pop("n", 1), **kwargs)


# --------------------------------------------------------------------------------------------- CLI


def test_synth_command_writes_files_and_a_manifest_that_resolves(tmp_path, capsys):
    import yaml

    from itk_nrreval.cli import main

    out = tmp_path / "pop"
    assert main(["synth", "--kind", "phantom", "--dim", "2", "--n", "3", "--out", str(out)]) == 0
    manifest = yaml.safe_load((out / "manifest.yaml").read_text())
    assert manifest["images"] == [f"img/s{i:02d}.nii.gz" for i in range(3)]
    assert manifest["labels"] == [f"lab/s{i:02d}.nii.gz" for i in range(3)]
    truth = manifest["registrations"]["truth"]
    assert truth["reference"] == "truth/template.nii.gz"
    assert truth["transforms"] == [f"truth/s{i:02d}.h5" for i in range(3)]
    for rel in [*manifest["images"], *manifest["labels"], *truth["transforms"], truth["reference"]]:
        assert not Path(rel).is_absolute()
        assert (out / rel).is_file()
    assert (out / "montage.png").stat().st_size > 1000
    assert not list(out.rglob(".*tmp-*"))  # no temporary files left behind
    # The written transform is the true one: it maps the written labels onto the template's.
    template_labels = sitk.ReadImage(str(out / "truth/template_labels.nii.gz"))
    for lab, tx in zip(manifest["labels"], truth["transforms"], strict=True):
        back = sitk.Resample(
            sitk.ReadImage(str(out / lab)),
            template_labels,
            sitk.ReadTransform(str(out / tx)),
            sitk.sitkNearestNeighbor,
        )
        a, b = arr(back), arr(template_labels)
        assert np.mean(a[b > 0] == b[b > 0]) > 0.93
    assert "3 subjects" in capsys.readouterr().out


@pytest.mark.parametrize(
    "argv,message",
    [
        (["--kind", "ct"], r"--kind must be 'phantom' or 'mni', got 'ct'"),
        (["--dim", "4"], r"--dim must be 2 or 3, got 4"),
        (["--n", "0"], r"argument --n: expected an integer >= 3, got '0'"),
        (["--warp", "-2"], r"warp_mm must be a finite number >= 0, got -2.0"),
    ],
)
def test_synth_command_bad_input_is_one_line_and_exit_2(tmp_path, capsys, argv, message):
    from itk_nrreval.cli import main

    out = tmp_path / "pop"
    assert main(["synth", "--out", str(out), "--n", "3", *argv]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1
    assert re.search(message, err)
    assert not out.exists()


def test_synth_command_refuses_a_file_as_output(tmp_path, capsys):
    from itk_nrreval.cli import main

    target = tmp_path / "file.txt"
    target.write_text("x")
    assert main(["synth", "--out", str(target), "--n", "3"]) == 2
    assert re.search(r"exists and is not a folder", capsys.readouterr().err)


# ------------------------------------------------------------------------------ two contrasts

# Label values of each tissue class, per kind: (CSF, grey matter, white matter).
TISSUES = {"phantom": ((15, 16), (3, 4), (1, 2)), "mni": ((3,), (1,), (2,))}


@pytest.mark.parametrize("kind", ["phantom", "mni"])
def test_t2_contrast_is_the_same_anatomy_with_t2_like_tissue_order(kind):
    pop = make_population(kind, dim=2, n=2, seed=4, contrasts=("t1", "t2"))
    assert pop.contrasts == ("t1", "t2")
    labels = arr(pop.template_labels)
    means = {}
    for c in pop.contrasts:
        image = arr(pop.templates[c])
        means[c] = [np.mean(image[np.isin(labels, values)]) for values in TISSUES[kind]]
    csf, gm, wm = means["t1"]
    assert csf < gm < wm  # T1: CSF dark, white matter bright
    csf, gm, wm = means["t2"]
    assert csf > gm > wm  # T2: CSF bright, white matter dark
    # One anatomy: the labels do not depend on the contrast, and both templates' tissue
    # borders sit in the same place (their edge maps agree far better than chance).
    maker = make_phantom if kind == "phantom" else make_mni
    np.testing.assert_array_equal(arr(maker(dim=2, contrast="t2").labels), labels)
    edges = [np.hypot(*np.gradient(arr(pop.templates[c]).astype(float))) for c in pop.contrasts]
    assert np.corrcoef(edges[0].ravel(), edges[1].ravel())[0, 1] > 0.5
    assert np.corrcoef(edges[0].ravel(), np.roll(edges[1], 5, axis=1).ravel())[0, 1] < 0.3


def test_each_contrast_follows_the_one_true_transform():
    pop = make_population("phantom", dim=2, n=3, seed=6, contrasts=("t1", "t2"))
    for c in pop.contrasts:
        reg = perfect_registration(pop, contrast=c)
        template = arr(pop.templates[c]).ravel()
        for subject, image in zip(pop.subjects, reg.images, strict=True):
            aligned = np.corrcoef(arr(image).ravel(), template)[0, 1]
            unaligned = np.corrcoef(arr(subject.images[c]).ravel(), template)[0, 1]
            assert aligned > 0.9 and aligned > unaligned + 0.05, (c, aligned, unaligned)
        # Inside the brain, a registered image follows its own contrast's template and is
        # anti-correlated with the other's (the tissue order is reversed).
        brain = arr(pop.template_labels) > 0
        own = arr(pop.templates[c])[brain]
        other = arr(pop.templates["t2" if c == "t1" else "t1"])[brain]
        assert np.corrcoef(arr(reg.images[0])[brain], own)[0, 1] > 0.9
        assert np.corrcoef(arr(reg.images[0])[brain], other)[0, 1] < -0.8
    with pytest.raises(ValueError, match=r"contrast must be one of the population's"):
        perfect_registration(make_population("phantom", n=1), contrast="t2")


def test_adding_a_contrast_changes_no_image_of_another():
    t1 = make_population("phantom", dim=2, n=2, seed=8)
    both = make_population("phantom", dim=2, n=2, seed=8, contrasts=("t1", "t2"))
    t2 = make_population("phantom", dim=2, n=2, seed=8, contrasts=("t2",))
    for a, b, c in zip(t1.subjects, both.subjects, t2.subjects, strict=True):
        np.testing.assert_array_equal(arr(a.image), arr(b.images["t1"]))
        np.testing.assert_array_equal(arr(b.images["t2"]), arr(c.image))
        np.testing.assert_array_equal(arr(a.labels), arr(c.labels))
        pa = np.asarray(a.template_to_subject.TransformPoint([3.0, -2.0]))
        pc = np.asarray(c.template_to_subject.TransformPoint([3.0, -2.0]))
        np.testing.assert_array_equal(pa, pc)
        assert a.image is not None and b.image is b.images["t1"] and c.image is c.images["t2"]
    # Separate acquisitions: the T2 image's noise is not the T1 image's.
    s = both.subjects[0]
    resid = [arr(s.images[c])[:20, :20].ravel() for c in ("t1", "t2")]  # background: noise
    assert abs(np.corrcoef(*resid)[0, 1]) < 0.3


@pytest.mark.parametrize("contrasts", [(), ("t1", "t1"), ("t3",)])
def test_bad_contrasts_name_the_argument(contrasts):
    with pytest.raises(ValueError, match=r"contrasts must be distinct names from"):
        make_population("phantom", n=1, contrasts=contrasts)


def test_synth_command_two_contrasts_writes_groups(tmp_path, capsys):
    import yaml

    from itk_nrreval.cli import main

    out = tmp_path / "pop"
    argv = ["synth", "--n", "3", "--contrasts", "t1,t2", "--out", str(out)]
    assert main(argv) == 0
    assert "t1+t2" in capsys.readouterr().out
    manifest = yaml.safe_load((out / "manifest.yaml").read_text())
    subjects = ["s00", "s01", "s02"]
    assert manifest["images"] == [f"img/{s}_{c}.nii.gz" for c in ("t1", "t2") for s in subjects]
    assert manifest["groups"] == ["t1"] * 3 + ["t2"] * 3
    assert manifest["labels"] == [f"lab/{s}.nii.gz" for s in subjects] * 2
    truth = manifest["registrations"]["truth"]
    assert truth["transforms"] == [f"truth/{s}.h5" for s in subjects] * 2
    assert truth["reference"] == "truth/template_t1.nii.gz"
    assert (out / "truth/template_t2.nii.gz").is_file()
    # The files hold what their names say: T2 images are bright in CSF, dark in white matter.
    for rel, group in zip(manifest["images"], manifest["groups"], strict=True):
        image = arr(sitk.ReadImage(str(out / rel)))
        labels = arr(sitk.ReadImage(str(out / manifest["labels"][manifest["images"].index(rel)])))
        csf, wm = (np.mean(image[np.isin(labels, v)]) for v in ((16,), (1, 2)))
        assert (csf > wm) == (group == "t2"), rel


@pytest.mark.parametrize("value", ["t3", "t1,t1", "t1,,t2"])
def test_synth_command_bad_contrasts_one_line_exit_2(tmp_path, capsys, value):
    from itk_nrreval.cli import main

    out = tmp_path / "pop"
    assert main(["synth", "--out", str(out), "--n", "3", "--contrasts", value]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1
    assert "--contrasts must be distinct names from t1, t2" in err
    assert not out.exists()
