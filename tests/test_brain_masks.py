"""Brain masks, where the inputs have them (issue 42, item 6).

Each subject's brain mask is brought into the common frame through its image's transform and
compared with the common mask by its Dice. The Dice is checked against a count written out
here voxel by voxel (each reference voxel's centre mapped through the affine map by hand, the
mask read at the nearest voxel or interpolated linearly), on oblique, anisotropic grids far
from the reference; the manifest's ``masks`` key is read and checked (one-line errors naming
the file); BIDS derivatives give each subject's ``desc-brain_mask``; and the pipeline's Dice
under a registration is that of the pure functions.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import SimpleITK as sitk
import yaml
from test_bad_inputs import assert_one_line, run_cli
from test_derivatives import SPACE, anat, write, write_tree

import itk_nrreval as nr
from data_synth import make_population
from itk_nrreval import InputError
from itk_nrreval._executors import InProcessExecutor
from itk_nrreval._pipeline import run_pipeline
from itk_nrreval.io._brain_masks import (
    BRAIN_MASK_DICE_MIN,
    majority_mask,
    resample_mask,
    subject_mask_dice,
)
from itk_nrreval.io._images import Geometry
from itk_nrreval.io.manifest import load_manifest, write_manifest
from itk_nrreval.io.transforms import chain_transform

# ----------------------------------------------------------------------------- geometry


def rotation(dim: int, degrees: float) -> np.ndarray:
    """A rotation matrix: about z in 3D (then a little about x), in the plane in 2D."""
    a = math.radians(degrees)
    r2 = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    if dim == 2:
        return r2
    r = np.eye(3)
    r[:2, :2] = r2
    b = math.radians(degrees / 3)
    rx = np.array([[1, 0, 0], [0, math.cos(b), -math.sin(b)], [0, math.sin(b), math.cos(b)]])
    return r @ rx


def grid(size, spacing, origin, direction: np.ndarray) -> Geometry:
    return Geometry(
        tuple(int(s) for s in size),
        tuple(float(s) for s in spacing),
        tuple(float(o) for o in origin),
        tuple(float(d) for d in direction.ravel()),
    )


def centres(g: Geometry) -> np.ndarray:
    """Every voxel centre (mm, LPS) of `g`, shape (*numpy shape, dim)."""
    index = np.stack(np.meshgrid(*(np.arange(s) for s in g.size), indexing="ij"), -1)
    d = np.asarray(g.direction).reshape(g.dimension, g.dimension)
    points = np.asarray(g.origin) + (index * np.asarray(g.spacing)) @ d.T
    return points.transpose(*reversed(range(g.dimension)), g.dimension)  # ITK -> numpy order


def centre_mm(g: Geometry) -> np.ndarray:
    d = np.asarray(g.direction).reshape(g.dimension, g.dimension)
    middle = (np.asarray(g.size) - 1) / 2 * np.asarray(g.spacing)
    return np.asarray(g.origin) + d @ middle


def ellipsoid(g: Geometry, centre, radii) -> np.ndarray:
    """uint8 mask (numpy order) of the voxels of `g` whose centres lie in an axis-aligned
    ellipsoid (mm, LPS); its border voxels are 0 (checked)."""
    inside = (((centres(g) - centre) / radii) ** 2).sum(-1) <= 1
    for axis in range(g.dimension):
        assert not inside.take([0, -1], axis=axis).any()
    return inside.astype(np.uint8)


def image(array: np.ndarray, g: Geometry) -> sitk.Image:
    out = sitk.GetImageFromArray(array)
    return g.apply_to(out)


def affine(A: np.ndarray, centre, translation) -> sitk.AffineTransform:
    """``q = A (p - centre) + centre + translation``: reference points -> image points."""
    t = sitk.AffineTransform(len(centre))
    t.SetMatrix(A.ravel().tolist())
    t.SetCenter([float(c) for c in centre])
    t.SetTranslation([float(v) for v in translation])
    return t


# ----------------------------------------------------------------------------- brute force


def brute_resampled(mask: np.ndarray, g_mask: Geometry, A, c, t, ref: Geometry, method: str):
    """The mask at each reference voxel, one voxel at a time: its centre p mapped by hand to
    q = A (p - c) + c + t, q's continuous index in the mask's grid, then the nearest voxel
    (outside the mask's grid: 0) or the multilinear interpolation of the 0/1 voxels (a
    corner outside the grid counts 0: the mask's border voxels are 0), inside at >= 0.5."""
    d_ref = np.asarray(ref.direction).reshape(ref.dimension, ref.dimension)
    d_mask = np.asarray(g_mask.direction).reshape(ref.dimension, ref.dimension)
    size = np.asarray(g_mask.size)
    out = np.zeros(ref.shape, bool)
    for np_index in itertools.product(*(range(s) for s in ref.shape)):
        ijk = np.array(np_index[::-1], float)
        p = np.asarray(ref.origin) + d_ref @ (ijk * np.asarray(ref.spacing))
        q = A @ (p - c) + c + t
        cont = np.linalg.solve(d_mask, q - np.asarray(g_mask.origin)) / np.asarray(g_mask.spacing)
        if method == "nearest":
            k = np.floor(cont + 0.5).astype(int)
            if np.all(k >= 0) and np.all(k < size):
                out[np_index] = mask[tuple(k[::-1])] != 0
            continue
        if np.any(cont < -0.5) or np.any(cont > size - 0.5):
            continue  # outside the mask's field of view (ITK's rule)
        base = np.floor(cont).astype(int)
        frac = cont - base
        value = 0.0
        for corner in itertools.product((0, 1), repeat=ref.dimension):
            k = base + np.array(corner)
            if np.all(k >= 0) and np.all(k < size):
                w = np.prod([f if b else 1 - f for f, b in zip(frac, corner, strict=True)])
                value += w * mask[tuple(k[::-1])]
        out[np_index] = value >= 0.5
    return out


def brute_dice(a: np.ndarray, b: np.ndarray) -> float:
    both = in_a = in_b = 0
    for x, y in zip(a.ravel().tolist(), b.ravel().tolist(), strict=True):
        in_a += x
        in_b += y
        both += x and y
    return 2 * both / (in_a + in_b)


def brute_majority(masks: list[np.ndarray]) -> np.ndarray:
    out = np.zeros(masks[0].shape, bool)
    for index in itertools.product(*(range(s) for s in out.shape)):
        votes = sum(int(m[index]) for m in masks)
        out[index] = votes > len(masks) / 2
    return out


# ----------------------------------------------------------------------------- the Dice

CASES = {
    # reference grid (size, spacing, origin, degrees), subjects' grids and shifts
    2: dict(
        ref=((23, 17), (1.3, 2.1), (-40.0, 25.0), 20.0),
        images=[
            ((37, 21), (0.9, 1.7), (110.0, -80.0), -15.0),
            ((31, 29), (1.1, 1.2), (-190.0, 60.0), 35.0),
            ((46, 33), (1.05, 1.45), (75.0, 140.0), 5.0),
        ],
        shifts=[(0.8, -0.6), (-1.5, 1.1), (6.5, -4.2)],  # mm: the last one misplaced
    ),
    3: dict(
        ref=((13, 11, 9), (1.7, 1.1, 2.4), (-30.0, 12.0, 55.0), 25.0),
        images=[
            ((19, 18, 13), (1.3, 1.4, 1.9), (120.0, -60.0, 20.0), -10.0),
            ((23, 16, 15), (1.1, 1.6, 1.7), (-150.0, 90.0, -40.0), 40.0),
            ((25, 31, 18), (1.5, 1.2, 2.1), (60.0, 160.0, 95.0), 15.0),
        ],
        shifts=[(0.7, -0.4, 0.9), (-1.2, 0.8, -0.5), (5.5, -3.0, 4.0)],
    ),
}


def dice_case(dim: int):
    """A reference grid, three subjects' masks on oblique anisotropic grids far from it (a
    100-200 mm translation away), each with the affine map from the reference to its grid,
    and a common mask on the reference grid."""
    case = CASES[dim]
    size, spacing, origin, degrees = case["ref"]
    ref = grid(size, spacing, origin, rotation(dim, degrees))
    ref_centre = centre_mm(ref)
    radii = np.array([0.3 * s * n for s, n in zip(spacing, size, strict=True)])
    common = ellipsoid(ref, ref_centre, radii).astype(bool)
    subjects = []
    for k, ((isize, ispacing, iorigin, ideg), shift) in enumerate(
        zip(case["images"], case["shifts"], strict=True)
    ):
        g = grid(isize, ispacing, iorigin, rotation(dim, ideg))
        # a small rotation and scaling about the reference's centre, then the image's place
        A = rotation(dim, 3.0 + 2 * k) * (1.0 + 0.02 * (k - 1))
        t = centre_mm(g) - ref_centre
        mask = ellipsoid(g, centre_mm(g) + np.asarray(shift), radii * (1 + 0.03 * k))
        subjects.append((mask, g, A, ref_centre, t))
    return ref, common, subjects


@pytest.mark.parametrize("method", ["nearest", "linear"])
@pytest.mark.parametrize("dim", [2, 3])
def test_mask_dice_against_a_brute_force_count(dim, method):
    ref, common, subjects = dice_case(dim)
    brute = [brute_resampled(mask, g, A, c, t, ref, method) for mask, g, A, c, t in subjects]
    resampled = [
        resample_mask(image(mask, g), affine(A, c, t), ref, method=method)
        for mask, g, A, c, t in subjects
    ]
    for ours, theirs in zip(resampled, brute, strict=True):
        assert ours.shape == ref.shape
        assert theirs.sum() > 20  # the masks land on the reference grid
        np.testing.assert_array_equal(ours, theirs)

    # against the manifest's common mask
    given = subject_mask_dice(resampled, common=common)
    assert given.common == "mask" and given.common_voxels == int(common.sum())
    assert given.dice == pytest.approx([brute_dice(b, common) for b in brute], abs=1e-12)
    # against the majority vote of the subjects' masks (each voting for itself too)
    voted = subject_mask_dice(resampled)
    majority = brute_majority(brute)
    np.testing.assert_array_equal(majority_mask(resampled), majority)
    assert voted.common == "majority" and voted.common_voxels == int(majority.sum())
    assert voted.dice == pytest.approx([brute_dice(b, majority) for b in brute], abs=1e-12)
    # the misplaced subject stands out; those below 0.8 are flagged (a coarse 3D grid of
    # ~140 mask voxels loses some Dice to its voxels alone)
    assert given.threshold == BRAIN_MASK_DICE_MIN == 0.8
    assert int(np.argmin(given.dice)) == int(np.argmin(voted.dice)) == 2
    assert given.below == tuple(i for i, b in enumerate(brute) if brute_dice(b, common) < 0.8)
    assert 2 in given.below and 2 in voted.below and 0 not in given.below
    assert given.to_dict()["dice"] == list(given.dice)


def test_mask_dice_of_empty_masks_is_nan_and_never_below_the_threshold():
    empty = np.zeros((4, 5), bool)
    full = np.ones((4, 5), bool)
    result = subject_mask_dice([empty, full, full], common=empty)
    assert math.isnan(result.dice[0]) and result.dice[1:] == (0.0, 0.0)
    assert result.below == (1, 2)
    assert result.to_dict()["dice"] == [None, 0.0, 0.0]


# ----------------------------------------------------------------------------- manifest


def write_cohort(folder, n: int = 3) -> dict:
    """`n` 2D images (16 x 16, 1.5 x 2 mm, origin (-7, 4)), their binary masks, identity
    transforms: a manifest dict of relative paths."""
    data = {"images": [], "masks": [], "registrations": {"reg": {"transforms": []}}}
    y, x = np.mgrid[0:16, 0:16]
    for i in range(n):
        rng = np.random.default_rng(i)
        arr = np.sin(0.4 * x + i) + np.cos(0.3 * y) + 0.1 * rng.random((16, 16))
        img = sitk.GetImageFromArray(arr.astype(np.float32))
        img.SetSpacing((1.5, 2.0))
        img.SetOrigin((-7.0, 4.0))
        mask = sitk.GetImageFromArray(((x - 8) ** 2 + (y - 7 - i) ** 2 < 25).astype(np.uint8))
        mask.CopyInformation(img)
        sitk.WriteImage(img, str(folder / f"i{i}.nii.gz"))
        sitk.WriteImage(mask, str(folder / f"m{i}.nii.gz"))
        sitk.WriteTransform(sitk.AffineTransform(2), str(folder / f"t{i}.tfm"))
        data["images"].append(f"i{i}.nii.gz")
        data["masks"].append(f"m{i}.nii.gz")
        data["registrations"]["reg"]["transforms"].append(f"t{i}.tfm")
    data["registrations"]["reg"]["reference"] = "i0.nii.gz"
    return data


def test_manifest_masks_read_and_written_back(tmp_path):
    data = write_cohort(tmp_path)
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(data))
    m = load_manifest(tmp_path / "m.yaml")
    assert m.masks == tuple(tmp_path / f"m{i}.nii.gz" for i in range(3))
    assert m.describe()["masks"] == [str(tmp_path / f"m{i}.nii.gz") for i in range(3)]
    assert set(m.masks) <= set(m.files)
    # the manifest nrreval writes keeps them, relative to its folder
    write_manifest(m, tmp_path / "out.yaml")
    assert yaml.safe_load((tmp_path / "out.yaml").read_text())["masks"] == data["masks"]
    assert load_manifest(tmp_path / "out.yaml").masks == m.masks
    # without the key: no masks
    del data["masks"]
    assert load_manifest(data, base_dir=tmp_path).masks is None


def _wrong_count(data, folder):
    data["masks"] = data["masks"][:2]
    return "masks: 2 brain masks for 3 images"


def _too_many(data, folder):
    data["masks"].append("m0.nii.gz")
    return "masks: 4 brain masks for 3 images"


def _missing(data, folder):
    data["masks"][1] = "gone.nii.gz"
    return f"masks[1]: file not found: {folder / 'gone.nii.gz'}"


def _not_binary(data, folder):
    mask = sitk.ReadImage(str(folder / "m2.nii.gz"))
    sitk.WriteImage(mask * 2, str(folder / "m2.nii.gz"))  # values 0 and 2
    return "masks[2]: m2.nii.gz holds values other than 0 and 1 (2): a brain mask is binary"


def _probabilities(data, folder):
    mask = sitk.Cast(sitk.ReadImage(str(folder / "m1.nii.gz")), sitk.sitkFloat32) * 0.75
    sitk.WriteImage(mask, str(folder / "m1.nii.gz"))
    return "masks[1]: m1.nii.gz holds values other than 0 and 1 (0.75): a brain mask is binary"


def _empty(data, folder):
    mask = sitk.ReadImage(str(folder / "m0.nii.gz")) * 0
    sitk.WriteImage(mask, str(folder / "m0.nii.gz"))
    return "masks[0]: m0.nii.gz is empty (every voxel is 0)"


def _off_grid(data, folder):
    mask = sitk.ReadImage(str(folder / "m1.nii.gz"))
    mask.SetOrigin((-7.0, 14.0))
    sitk.WriteImage(mask, str(folder / "m1.nii.gz"))
    return "masks[1]: m1.nii.gz is not on the grid of images[1] i1.nii.gz: origin (-7.0, 14.0)"


@pytest.mark.parametrize(
    "spoil", [_wrong_count, _too_many, _missing, _not_binary, _probabilities, _empty, _off_grid]
)
def test_manifest_masks_checked_in_one_line(tmp_path, spoil):
    data = write_cohort(tmp_path)
    expected = spoil(data, tmp_path)
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(InputError) as caught:
        load_manifest(tmp_path / "m.yaml")
    message = str(caught.value)
    assert "\n" not in message
    assert message.startswith(f"{tmp_path / 'm.yaml'}: {expected}"), message


def test_evaluate_refuses_a_bad_mask_in_one_line(tmp_path, capsys):
    data = write_cohort(tmp_path)
    expected = _not_binary(data, tmp_path)
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(data))
    code, err = run_cli(
        ["evaluate", str(tmp_path / "m.yaml"), "--out", str(tmp_path / "r")], capsys
    )
    assert code == 2
    assert_one_line(err, expected)
    assert not (tmp_path / "r").exists()


# ----------------------------------------------------------------------------- derivatives


@pytest.fixture(scope="module")
def population():
    """Four 2D subjects with their true transforms (template -> subject)."""
    return make_population("phantom", dim=2, n=4, seed=4, spacing=4.0, size=(52, 60))


KEYS = [("01", ""), ("02", ""), ("03", "A"), ("03", "B")]


def test_derivatives_give_each_subjects_brain_mask(tmp_path, population):
    root = write_tree(tmp_path / "prep", population, version="1.0", keys=KEYS)
    # a template-space mask beside it is not the subject's
    folder, stem = anat(root, "01")
    write(population.template > 0, folder / f"{stem}_space-{SPACE}_desc-brain_mask.nii.gz")
    m = nr.manifest_from_derivatives([root])
    expected = [anat(root, s, ses) for s, ses in KEYS]
    assert m.masks == tuple(f / f"{stem}_desc-brain_mask.nii.gz" for f, stem in expected)
    assert m.images == tuple(f / f"{stem}_desc-preproc_T1w.nii.gz" for f, stem in expected)

    # a subject without one: masks left out, in one line
    folder, stem = anat(root, "02")
    (folder / f"{stem}_desc-brain_mask.nii.gz").unlink()
    with pytest.warns(UserWarning, match=r"brain masks left out \(sub-02 has no ") as caught:
        m = nr.manifest_from_derivatives([root])
    assert m.masks is None and len(caught) == 1


def run(m, cache):
    return run_pipeline(
        m,
        InProcessExecutor(),
        execution=nr.Execution(cache=cache),
        n_samples=200,
        seed=0,
        distance="l1",
        progress=False,
    )


@pytest.mark.filterwarnings("ignore:the scores are taken on:UserWarning")
def test_pipeline_dice_is_the_pure_functions_and_flags_a_misplaced_mask(tmp_path, population):
    root = write_tree(tmp_path / "prep", population, version="1.0", keys=KEYS)
    # subject 02's skull-strip failed: its mask 40 mm off its brain
    folder, stem = anat(root, "02")
    path = folder / f"{stem}_desc-brain_mask.nii.gz"
    mask = sitk.ReadImage(str(path))
    moved = sitk.Image(mask)
    moved.SetOrigin([o + 40.0 for o in mask.GetOrigin()])
    sitk.WriteImage(
        sitk.Resample(moved, mask, sitk.Transform(), sitk.sitkNearestNeighbor), str(path)
    )
    m = nr.manifest_from_derivatives([root])
    reg = m.registrations["SynthPrep-1.0"]
    reference = sitk.ReadImage(str(reg.reference))
    by_hand = [
        resample_mask(sitk.ReadImage(str(p)), chain_transform(chain), reference, method="linear")
        for p, chain in zip(m.masks, reg.transforms, strict=True)
    ]

    # the common mask: the majority vote of the subjects' masks
    result = run(m, tmp_path / "cache").registrations["SynthPrep-1.0"].brain_masks
    assert result == subject_mask_dice(by_hand) and result.common == "majority"
    assert result.below == (1,), result.dice
    assert min(d for i, d in enumerate(result.dice) if i != 1) > 0.9, result.dice

    # the common mask: the manifest's (the template's brain)
    template_mask = tmp_path / "template_mask.nii.gz"
    write(sitk.Cast(population.template_labels > 0, sitk.sitkUInt8), template_mask)
    m = nr.manifest_from_derivatives([root], mask=template_mask)
    result = run(m, tmp_path / "cache").registrations["SynthPrep-1.0"].brain_masks
    common = sitk.GetArrayFromImage(sitk.ReadImage(str(template_mask))) != 0
    assert result == subject_mask_dice(by_hand, common=common) and result.common == "mask"
    assert result.below == (1,), result.dice


@pytest.mark.filterwarnings("ignore:the scores are taken on:UserWarning")
def test_a_misplaced_mask_flags_its_subject_in_results_and_subjects_csv(tmp_path, population):
    """Issue 42, item 6, end to end: the Dice reaches each subject's quality control, flags
    the one subject below 0.8 (and only it), and is a column of subjects.csv."""
    import csv

    root = write_tree(tmp_path / "prep", population, version="1.0", keys=KEYS)
    folder, stem = anat(root, "02")
    path = folder / f"{stem}_desc-brain_mask.nii.gz"
    mask = sitk.ReadImage(str(path))
    moved = sitk.Image(mask)
    moved.SetOrigin([o + 40.0 for o in mask.GetOrigin()])
    sitk.WriteImage(
        sitk.Resample(moved, mask, sitk.Transform(), sitk.sitkNearestNeighbor), str(path)
    )
    m = nr.manifest_from_derivatives([root])
    result = nr.evaluate(m, n_samples=200, confidence=False, progress=False)
    result.write(tmp_path / "o", figures=False)  # (what is read back is subjects.csv)
    (subjects,) = [s.subjects for s in result.scores.values()]
    flagged = [q.index for q in subjects if any("brain mask" in f for f in q.flags)]
    assert flagged == [1], [q.flags for q in subjects]
    assert (
        subjects[1].brain_mask_dice
        < BRAIN_MASK_DICE_MIN
        < min(q.brain_mask_dice for q in subjects if q.index != 1)
    )
    rows = list(csv.DictReader(open(tmp_path / "o" / "subjects.csv")))
    by_index = {int(row["index"]): float(row["brain_mask_dice"]) for row in rows}
    assert by_index == {q.index: pytest.approx(q.brain_mask_dice) for q in subjects}
