"""The numbers registration papers report (issue 45, item 1), each against a reference
written here: Dice by counting voxels of label maps ITK resamples itself, HD95 from the
distances between boundary point sets in mm (``scipy.spatial``; the code uses a distance
transform), on oblique anisotropic grids in 2D and 3D; the 30% worst-case aggregate on the
right tail; and the published Learn2Reg script's folding count, 0 on a field that folds."""

from __future__ import annotations

import csv
import json
import math
import warnings

import numpy as np
import pytest
import SimpleITK as sitk
from scipy import ndimage
from scipy.spatial.distance import cdist

import itk_nrreval as nr
from itk_nrreval.io._memberships import resample_label_memberships
from itk_nrreval.io.plausibility import deformation_plausibility
from itk_nrreval.measures.label_metrics import (
    LabelMetrics,
    crisp_labels,
    hausdorff95,
    label_surfaces,
    worst_tail_mean,
)

N = 5

# ----------------------------------------------------------------------------- a cohort


def _rotation(dim: int, degrees: float) -> np.ndarray:
    a = np.deg2rad(degrees)
    if dim == 2:
        return np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    about_z = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    b = np.deg2rad(degrees / 2)
    about_x = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    return about_z @ about_x


def _grid(dim: int) -> sitk.Image:
    """An empty float32 image on an oblique, anisotropic grid far from the origin."""
    if dim == 2:
        size, spacing, origin = (44, 36), (0.8, 1.3), (112.0, -130.0)
    else:
        size, spacing, origin = (22, 20, 18), (1.1, 0.9, 1.7), (105.0, -120.0, 130.0)
    img = sitk.Image(size, sitk.sitkFloat32)
    img.SetSpacing(spacing)
    img.SetOrigin(origin)
    img.SetDirection(tuple(_rotation(dim, 25.0).reshape(-1)))
    return img


def _local_mm(ref: sitk.Image) -> np.ndarray:
    """Every voxel centre's coordinates (mm) along the grid's own axes from its centre,
    numpy shape + (dim,), ITK order last."""
    size = np.array(ref.GetSize())
    spacing = np.array(ref.GetSpacing())
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in size], indexing="ij"), axis=-1)
    q = (idx - (size - 1) / 2) * spacing  # ITK index order, (x, y[, z]) first axes
    return np.transpose(q, (*reversed(range(len(size))), len(size)))  # numpy order


def _centre(ref: sitk.Image) -> tuple[float, ...]:
    size = np.array(ref.GetSize())
    return ref.TransformContinuousIndexToPhysicalPoint(tuple((size - 1) / 2.0))


def _rigid(ref: sitk.Image, degrees: float, shift_mm) -> sitk.Transform:
    dim = ref.GetDimension()
    t = sitk.AffineTransform(dim)
    t.SetCenter(_centre(ref))
    t.SetMatrix(tuple(_rotation(dim, degrees).reshape(-1)))
    t.SetTranslation(tuple(float(s) for s in shift_mm))
    return t


def _template_labels(ref: sitk.Image) -> sitk.Image:
    """Three labels well inside the grid: a large ellipse with a second label inside it and
    a small third one apart."""
    q = _local_mm(ref)
    extent = np.array(ref.GetSize()) * np.array(ref.GetSpacing())
    lab = np.zeros(q.shape[:-1], np.uint8)
    r = np.sqrt((((q[..., :2]) / (0.25 * extent[:2])) ** 2).sum(-1))
    if q.shape[-1] == 3:
        r = np.sqrt(r**2 + (q[..., 2] / (0.22 * extent[2])) ** 2)
    lab[r < 1] = 1
    inner = q.copy()
    inner[..., 0] -= 0.08 * extent[0]
    r2 = np.sqrt(((inner / (0.13 * extent)) ** 2).sum(-1))
    lab[r2 < 1] = 2
    apart = q.copy()
    apart[..., 0] += 0.25 * extent[0]
    r3 = np.sqrt(((apart / (0.08 * extent)) ** 2).sum(-1))
    lab[r3 < 1] = 3
    img = sitk.GetImageFromArray(lab)
    img.CopyInformation(ref)
    return img


def _cohort(dim: int):
    """N subjects on one oblique grid (the template's labels moved by a small rigid map
    each; subject 2's label map has no label 3), and two registrations of them: to_ref
    (to subject 0, ``reference_index: 0``: cases against it) and group (to a template in
    the same space, ``frame_transform: identity``: every pair)."""
    ref = _grid(dim)
    rng = np.random.default_rng(45 + dim)
    template = _template_labels(ref)
    images, labels = [], []
    for i in range(N):
        s_i = _rigid(ref, rng.uniform(-4, 4), rng.uniform(-1.5, 1.5, dim))
        lab = sitk.Resample(template, ref, s_i, sitk.sitkNearestNeighbor, 0)
        arr = sitk.GetArrayFromImage(lab)
        if i == 2:
            arr[arr == 3] = 1
        lab = sitk.GetImageFromArray(arr.astype(np.uint8))
        lab.CopyInformation(ref)
        noisy = 100.0 * arr + 20.0 * (arr == 2) + rng.normal(0, 5, arr.shape)
        img = sitk.GetImageFromArray(noisy.astype(np.float32))
        img.CopyInformation(ref)
        images.append(img)
        labels.append(lab)
    to_ref = [sitk.AffineTransform(dim)] + [
        _rigid(ref, rng.uniform(-3, 3), rng.uniform(-1.0, 1.0, dim)) for _ in range(N - 1)
    ]
    group = [_rigid(ref, rng.uniform(-3, 3), rng.uniform(-1.0, 1.0, dim)) for _ in range(N)]
    tmpl = sitk.GetImageFromArray(
        (100.0 * sitk.GetArrayFromImage(template) + 7.0).astype(np.float32)
    )
    tmpl.CopyInformation(ref)
    manifest = {
        "images": images,
        "labels": labels,
        "registrations": {
            "to_ref": {"reference": images[0], "reference_index": 0, "transforms": to_ref},
            "group": {"reference": tmpl, "frame_transform": "identity", "transforms": group},
        },
    }
    return manifest, ref, labels, {"to_ref": to_ref, "group": group}


# ----------------------------------------------------------------------------- the references


def _boundary_points(lab: np.ndarray, value: int, ref: sitk.Image) -> np.ndarray:
    """Physical points (mm) of the voxels of `value` with a face neighbour (inside the
    grid) of another label: voxel by voxel, through ITK's index-to-point map."""
    points = []
    for idx in zip(*np.nonzero(lab == value), strict=True):
        edge = False
        for axis in range(lab.ndim):
            for step in (-1, 1):
                n = list(idx)
                n[axis] += step
                if 0 <= n[axis] < lab.shape[axis] and lab[tuple(n)] != value:
                    edge = True
        if edge:
            itk_index = tuple(int(i) for i in reversed(idx))
            points.append(ref.TransformIndexToPhysicalPoint(itk_index))
    return np.array(points, np.float64).reshape(-1, lab.ndim)


def _hd95_by_points(a: np.ndarray, b: np.ndarray) -> float:
    if not len(a) or not len(b):
        return math.nan
    d = cdist(a, b)
    return float(max(np.percentile(d.min(axis=1), 95), np.percentile(d.min(axis=0), 95)))


def _reference_metrics(crisp, own, cases, ref):
    """Dice by counting and HD95 by point sets, per case and label 1..3 (NaN where one of
    the two label maps lacks the label)."""
    dice = np.full((len(cases), 3), np.nan)
    hd = np.full((len(cases), 3), np.nan)
    for row, (a, b) in enumerate(cases):
        for k, v in enumerate((1, 2, 3)):
            if v not in own[a] or v not in own[b]:
                continue
            in_a, in_b = crisp[a] == v, crisp[b] == v
            dice[row, k] = 2 * np.count_nonzero(in_a & in_b) / (in_a.sum() + in_b.sum())
            hd[row, k] = _hd95_by_points(
                _boundary_points(crisp[a], v, ref), _boundary_points(crisp[b], v, ref)
            )
    return dice, hd


def _worst(values, *, low: bool) -> float:
    v = sorted(x for x in values if math.isfinite(x))
    k = math.ceil(0.3 * len(v) - 1e-9)
    return float(np.mean(v[:k] if low else v[-k:]))


# ----------------------------------------------------------------------------- evaluate


@pytest.mark.parametrize("dim", [2, 3])
def test_dice_and_hd95_per_case_against_counts_and_point_sets(dim, tmp_path):
    manifest, ref, labels, transforms = _cohort(dim)
    out = tmp_path / "out" if dim == 2 else None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = nr.evaluate(
            manifest,
            n_samples=200,
            confidence=False,
            inverse_consistency=False,
            resampling=nr.Resampling(label_interpolation="nearest"),
            progress=False,
        )
    if out is not None:
        result.write(out)
    own = [set(np.unique(sitk.GetArrayViewFromImage(lab)).tolist()) - {0} for lab in labels]
    # where every image has a value under every registration, as ITK decides it
    ones = sitk.GetImageFromArray(np.ones(sitk.GetArrayViewFromImage(ref).shape, np.uint8))
    ones.CopyInformation(ref)
    covered = np.logical_and.reduce(
        [
            sitk.GetArrayFromImage(sitk.Resample(ones, ref, t, sitk.sitkNearestNeighbor, 0)) > 0
            for ts in transforms.values()
            for t in ts
        ]
    )
    assert 3 not in own[2] and all(3 in own[i] for i in (0, 1, 3, 4))
    for name in ("to_ref", "group"):
        # each subject's labels in the common frame, resampled by ITK itself (F: identity)
        crisp = [
            sitk.GetArrayFromImage(
                sitk.Resample(labels[i], ref, transforms[name][i], sitk.sitkNearestNeighbor, 0)
            )
            for i in range(N)
        ]
        for c in crisp:  # the test's premise: every label and its neighbours in the region
            assert np.all(covered[ndimage.binary_dilation(c > 0)])
        lm = result.scores[name].label_metrics
        if name == "to_ref":
            cases = [(i, 0) for i in range(1, N)]
            assert lm.reference == 0 and lm.against == "reference"
        else:
            cases = [(a, b) for a in range(N) for b in range(a + 1, N)]
            assert lm.reference is None and lm.against == "pairs"
        assert lm.cases == tuple(cases) and lm.labels == (1, 2, 3)
        dice, hd = _reference_metrics(crisp, own, cases, ref)
        np.testing.assert_array_equal(np.isnan(lm.dice), np.isnan(dice))
        np.testing.assert_allclose(lm.dice, dice, rtol=1e-12, equal_nan=True)
        np.testing.assert_array_equal(np.isnan(lm.hd95_mm), np.isnan(hd))
        np.testing.assert_allclose(lm.hd95_mm, hd, rtol=1e-9, equal_nan=True)
        assert np.nanmax(hd) > 1.0  # the cases differ by more than a voxel somewhere
        if out is None:
            continue
        # metrics.csv and results.json carry the same numbers, aggregated as stated
        case_dice = np.nanmean(dice, axis=1)
        case_hd = np.nanmean(hd, axis=1)
        rows = {
            r["label"]: r
            for r in csv.DictReader(open(out / "metrics.csv", newline=""))
            if r["registration"] == name
        }
        got = rows["all"]
        assert float(got["dice_mean"]) == pytest.approx(case_dice.mean(), rel=1e-12)
        assert float(got["dice_worst30"]) == pytest.approx(_worst(case_dice, low=True))
        assert float(got["hd95_mm_mean"]) == pytest.approx(case_hd.mean(), rel=1e-9)
        assert float(got["hd95_mm_worst30"]) == pytest.approx(_worst(case_hd, low=False))
        assert int(got["cases"]) == len(cases) and got["against"] == lm.against
        plaus = result.scores[name].plausibility
        assert float(got["sdlogj"]) == pytest.approx(plaus.sdlogj)
        assert float(got["folded_fraction"]) == plaus.folded_fraction
        # the non-diffeomorphic fraction: tested against its brute force in test_plausibility
        assert float(got["nondiffeomorphic_fraction"]) == plaus.nondiffeomorphic_fraction
        assert plaus.nondiffeomorphic_fraction >= plaus.folded_fraction
        for k, v in enumerate((1, 2, 3)):
            row = rows[str(v)]
            assert float(row["dice_mean"]) == pytest.approx(np.nanmean(dice[:, k]), rel=1e-12)
            assert float(row["hd95_mm_worst30"]) == pytest.approx(_worst(hd[:, k], low=False))
            assert int(row["cases"]) == np.isfinite(dice[:, k]).sum()
        saved = json.loads((out / "results.json").read_text())["registrations"][name]
        assert saved["label_metrics"]["dice"]["mean"] == pytest.approx(case_dice.mean())
        assert saved["label_metrics"]["labels"]["3"]["dice"]["n_cases"] == sum(
            2 not in case for case in cases
        )
    if out is not None:
        page = (out / "report.html").read_text()
        assert "The numbers registration papers report" in page and "HD95 (mm)" in page


# ----------------------------------------------------------------------------- the pieces


@pytest.mark.parametrize("dim", [2, 3])
def test_hausdorff95_against_point_sets_anisotropic(dim):
    """Ragged shapes (several components, holes) on an anisotropic grid: HD95 from one
    distance transform per direction equals the point sets' (points at index x spacing)."""
    rng = np.random.default_rng(7 + dim)
    shape = (30, 26) if dim == 2 else (16, 14, 12)
    spacing = (0.7, 1.9) if dim == 2 else (0.6, 1.3, 2.2)  # ITK order (x, y[, z])
    for _ in range(3):
        a = ndimage.gaussian_filter(rng.normal(size=shape), 1.5) > 0.05
        b = ndimage.gaussian_filter(rng.normal(size=shape), 1.5) > 0.05
        got = hausdorff95(a, b, spacing=spacing)
        pts = []
        for m in (a, b):
            lab = m.astype(np.uint8)
            idx = np.array(np.nonzero(m)).T
            keep = []
            for p in idx:  # a voxel with a face neighbour, inside the grid, outside the mask
                edge = False
                for axis in range(dim):
                    for step in (-1, 1):
                        n = p.copy()
                        n[axis] += step
                        if 0 <= n[axis] < shape[axis] and not lab[tuple(n)]:
                            edge = True
                keep.append(edge)
            pts.append(idx[np.array(keep)] * np.array(spacing[::-1]))
        assert got == pytest.approx(_hd95_by_points(*pts), rel=1e-9)
    assert math.isnan(hausdorff95(a, np.zeros(shape, bool), spacing=spacing))


def test_crisp_labels_are_the_largest_resampled_membership():
    """The crisp map from the sparse memberships equals the argmax over ITK's own linear
    resampling of the one-hot maps with the background (one minus their sum) first, except
    where two memberships tie to float32 rounding."""
    ref = _grid(2)
    lab = _template_labels(ref)
    t = _rigid(ref, 7.0, (0.37, -0.61))
    memb = resample_label_memberships(lab, t, ref, values=[1, 2, 3])
    got = crisp_labels(memb)
    arr = sitk.GetArrayFromImage(lab)
    channels = []
    for v in (1, 2, 3):
        one_hot = sitk.GetImageFromArray((arr == v).astype(np.float32))
        one_hot.CopyInformation(ref)
        channels.append(sitk.GetArrayFromImage(sitk.Resample(one_hot, ref, t, sitk.sitkLinear)))
    stack = np.stack([1.0 - np.sum(channels, axis=0), *channels]).astype(np.float64)
    expected = np.argmax(stack, axis=0)  # first of equals: the background, then label 1...
    top2 = np.sort(stack, axis=0)[-2:]
    differ = got != expected
    assert np.all(top2[1][differ] - top2[0][differ] < 1e-5)
    assert differ.sum() <= 2 and (expected > 0).sum() > 300
    surf = label_surfaces(got, 4)
    np.testing.assert_array_equal(surf.counts, np.bincount(got.reshape(-1), minlength=4))


def test_worst_30_percent_is_the_right_tail():
    """Dice's worst cases are its lowest, HD95's its largest: the mean of the ceil(30%) of
    them. The published script's '30' (np.quantile(values, 0.3)) is HD95's best tail."""
    rng = np.random.default_rng(3)
    hd = rng.permutation(np.arange(1.0, 11.0))  # 10 cases: 1 .. 10 mm
    dice = rng.permutation(np.linspace(0.5, 0.95, 10))
    assert worst_tail_mean(hd, higher_is_better=False) == pytest.approx((8 + 9 + 10) / 3)
    assert worst_tail_mean(dice, higher_is_better=True) == pytest.approx(np.mean(np.sort(dice)[:3]))
    assert np.quantile(hd, 0.3) < np.median(hd) < worst_tail_mean(hd, higher_is_better=False)
    # 7 cases: ceil(2.1) = 3 worst; a NaN is not a case
    seven = np.array([4.0, 1.0, np.nan, 7.0, 2.0, 6.0, 3.0, 5.0])
    assert worst_tail_mean(seven, higher_is_better=False) == pytest.approx(6.0)
    # a registration's aggregate: each case's mean over its labels first (NaN: not compared)
    lm = LabelMetrics(
        labels=(1, 2),
        cases=((1, 0), (2, 0), (3, 0), (4, 0)),
        reference=0,
        dice=np.array([[0.9, 0.7], [0.5, np.nan], [0.8, 0.8], [0.6, 0.4]]),
        hd95_mm=np.array([[1.0, 3.0], [9.0, np.nan], [2.0, 2.0], [4.0, 6.0]]),
    )
    d, h = lm.overall()
    assert d.mean == pytest.approx((0.8 + 0.5 + 0.8 + 0.5) / 4)
    assert d.worst30 == pytest.approx(0.5) and h.worst30 == pytest.approx((9 + 5) / 2)
    per = lm.per_label()
    assert per[2][0].n_cases == 3 and per[2][1].worst30 == pytest.approx(6.0)


# ----------------------------------------------------------------------------- folding


def _published_jacobian_determinant(disp: np.ndarray) -> np.ndarray:
    """MDL-UzL/L2R evaluation/utils.py ``jacobian_determinant``, as published: central
    differences by correlation, the identity added, two voxels cropped per side.
    `disp` (1, 3, H, W, D) in voxels, channel k along axis k."""
    kernels = [
        np.array([-0.5, 0, 0.5]).reshape(s) for s in ((1, 3, 1, 1), (1, 1, 3, 1), (1, 1, 1, 3))
    ]
    grads = [
        np.stack([ndimage.correlate(disp[:, c], k, mode="constant", cval=0.0) for c in range(3)], 1)
        for k in kernels
    ]  # fmt: skip
    jac = np.concatenate(grads, 0) + np.eye(3).reshape(3, 3, 1, 1, 1)
    j = jac[:, :, 2:-2, 2:-2, 2:-2]
    return (
        j[0, 0] * (j[1, 1] * j[2, 2] - j[1, 2] * j[2, 1])
        - j[1, 0] * (j[0, 1] * j[2, 2] - j[0, 2] * j[2, 1])
        + j[2, 0] * (j[0, 1] * j[1, 2] - j[0, 2] * j[1, 1])
    )


def test_published_folding_count_is_zero_on_a_field_that_folds():
    """What not to do (MDL-UzL/L2R issues #6, #7, #8): the published script adds 3 to det J
    and clips it at 1e-9 before counting det J <= 0, so its count is 0 on a field that folds
    a fifth of the grid; the folded fraction here counts the determinant itself."""
    shape = (20, 20, 24)  # numpy (z, y, x); 1 mm voxels, as the published script assumes
    x = np.arange(shape[2], dtype=float)
    field = np.zeros((*shape, 3))
    field[..., 0] = 3.0 * np.sin(2 * np.pi * x / 12)  # d u_x / dx down to -1.57
    disp = np.moveaxis(field[..., ::-1], -1, 0)[None]  # channel k along numpy axis k
    detj = _published_jacobian_determinant(disp)
    jac_det = (detj + 3).clip(0.000000001, 1000000000)  # as published
    assert (jac_det <= 0).astype(float).sum() == 0  # its num_foldings
    assert (detj <= 0).mean() > 0.15  # its own determinant folds
    # the brute-force determinant: np.gradient of the x displacement along x
    folded_np = (1 + np.gradient(field[..., 0], axis=2) <= 0).mean()
    grid = sitk.Image(list(shape[::-1]), sitk.sitkFloat32)
    transform = sitk.DisplacementFieldTransform(sitk.GetImageFromArray(field, isVector=True))
    ours = deformation_plausibility(transform, grid, inverse_consistency=False)
    assert ours.folded_fraction > 0.15
    assert ours.folded_fraction == pytest.approx(folded_np, abs=0.02)
