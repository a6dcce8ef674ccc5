"""Sparse label memberships against ITK's dense one-hot resampling (real SimpleITK throughout)."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk
from scipy import ndimage

from itk_nrreval._errors import InputError
from itk_nrreval.io import _memberships
from itk_nrreval.io._images import Geometry
from itk_nrreval.io._memberships import SparseMemberships, resample_label_memberships

LARGE_VALUES = (0, 3, 1000, 14175)  # non-contiguous, FreeSurfer-sized


# ------------------------------------------------------------------------------- reference


def dense_reference(label_map: sitk.Image, transform, grid: Geometry, values) -> np.ndarray:
    """Today's method: the float32 one-hot vector image through ``sitk.Resample`` (linear,
    default 0). Returns (n_labels, *grid.shape) float32."""
    arr = sitk.GetArrayViewFromImage(label_map)
    onehot = np.stack([arr == v for v in values], axis=-1).astype(np.float32)
    vec = sitk.GetImageFromArray(onehot, isVector=True)
    vec.CopyInformation(label_map)
    out = sitk.Resample(
        vec,
        list(grid.size),
        transform,
        sitk.sitkLinear,
        list(grid.origin),
        list(grid.spacing),
        list(grid.direction),
        0.0,
        sitk.sitkVectorFloat32,
    )
    return np.moveaxis(sitk.GetArrayFromImage(out).reshape(*grid.shape, len(values)), -1, 0)


def itk_inside(label_map: sitk.Image, transform, grid: Geometry) -> np.ndarray:
    """Grid points whose image ITK counts as inside the label map's buffer (bool, grid shape)."""
    ones = sitk.Image(label_map.GetSize(), sitk.sitkFloat32) + 1.0
    ones.CopyInformation(label_map)
    out = sitk.Resample(
        ones,
        list(grid.size),
        transform,
        sitk.sitkNearestNeighbor,
        list(grid.origin),
        list(grid.spacing),
        list(grid.direction),
        0.0,
        sitk.sitkFloat32,
    )
    return sitk.GetArrayFromImage(out) > 0


def check_structure(sm: SparseMemberships, shape: tuple[int, ...]) -> None:
    assert sm.shape == shape
    assert sm.values.dtype == np.int64 and sm.ptr.dtype == np.int64
    assert sm.index.dtype == np.int64 and sm.weight.dtype == np.float32
    assert sm.ptr.shape == (sm.values.size + 1,) and sm.ptr[0] == 0
    assert sm.ptr[-1] == sm.index.size == sm.weight.size
    assert np.all(np.diff(sm.ptr) >= 0)
    assert np.all(sm.weight > 0) and np.all(sm.weight <= 1)
    for k in range(sm.values.size):
        idx, _ = sm.label(k)
        assert np.all(np.diff(idx) > 0), "indices ascending within a label"
        assert idx.size == 0 or (idx[0] >= 0 and idx[-1] < np.prod(shape))


def compare(label_map, transform, grid, values=None) -> SparseMemberships:
    sm = resample_label_memberships(label_map, transform, grid, values=values)
    check_structure(sm, grid.shape)
    expected = values if values is not None else np.unique(sitk.GetArrayViewFromImage(label_map))
    np.testing.assert_array_equal(sm.values, np.asarray(expected, np.int64))
    ref = dense_reference(label_map, transform, grid, sm.values)
    np.testing.assert_allclose(sm.dense(), ref, rtol=0, atol=1e-6)
    return sm


# ------------------------------------------------------------------------------ the inputs


def rotation(dim: int, angles) -> np.ndarray:
    if dim == 2:
        c, s = np.cos(angles[0]), np.sin(angles[0])
        return np.array([[c, -s], [s, c]])
    out = np.eye(3)
    for axis, a in enumerate(angles):
        i, j = [k for k in range(3) if k != axis]
        r = np.eye(3)
        r[i, i] = r[j, j] = np.cos(a)
        r[i, j], r[j, i] = -np.sin(a), np.sin(a)
        out = out @ r
    return out


def voronoi_labels(shape, values, rng, dtype=np.int32) -> np.ndarray:
    """Blobs: each voxel gets the value of its nearest random seed (numpy order shape)."""
    seeds = rng.uniform(0, 1, size=(3 * len(values), len(shape))) * np.array(shape)
    grid = np.stack(np.indices(shape), -1).astype(float)
    nearest = np.argmin(((grid[..., None, :] - seeds) ** 2).sum(-1), axis=-1)
    return np.asarray(values, dtype=dtype)[nearest % len(values)]


def oblique_label_map(dim: int, rng, values=LARGE_VALUES, dtype=np.int32) -> sitk.Image:
    """Anisotropic spacing, rotated direction cosines, origin off the grid's."""
    shape = (14, 17, 19)[-dim:] if dim == 3 else (17, 19)
    img = sitk.GetImageFromArray(voronoi_labels(shape, values, rng, dtype))
    img.SetSpacing([1.5, 1.0, 2.5][:dim])
    img.SetOrigin([-3.0, 2.0, -1.0][:dim])
    img.SetDirection(rotation(dim, [0.3, -0.2, 0.25][: 1 if dim == 2 else 3]).ravel().tolist())
    return img


def common_grid(dim: int) -> Geometry:
    """A grid larger than the label map, so part of it maps outside (zeros there)."""
    size = (26, 24, 18)[:dim]
    spacing = (1.3, 1.1, 1.7)[:dim]
    origin = (-9.0, -6.0, -8.0)[:dim]
    direction = rotation(dim, [-0.1, 0.15, 0.05][: 1 if dim == 2 else 3]).ravel()
    return Geometry(size, spacing, origin, tuple(direction))


def smooth_field(grid: Geometry, rng, amplitude: float = 2.5) -> sitk.DisplacementFieldTransform:
    """A smooth random displacement field (mm) on `grid`."""
    dim = grid.dimension
    coarse = rng.normal(size=(*(4,) * dim, dim))
    u = ndimage.zoom(coarse, [s / 4 for s in grid.shape] + [1], order=3)
    u *= amplitude / np.abs(u).max()
    img = sitk.GetImageFromArray(u, isVector=True)
    grid.apply_to(img)
    return sitk.DisplacementFieldTransform(sitk.Cast(img, sitk.sitkVectorFloat64))


def rotating_affine(dim: int, rng) -> sitk.AffineTransform:
    a = sitk.AffineTransform(dim)
    m = rotation(dim, [0.2, 0.1, -0.15][: 1 if dim == 2 else 3]) @ (
        np.eye(dim) + 0.05 * rng.standard_normal((dim, dim))
    )
    a.SetMatrix(m.ravel().tolist())
    a.SetTranslation(rng.normal(scale=2.0, size=dim).tolist())
    a.SetCenter(rng.normal(scale=3.0, size=dim).tolist())
    return a


def bspline(grid: Geometry, rng) -> sitk.BSplineTransform:
    img = sitk.Image(list(grid.size), sitk.sitkFloat32)
    grid.apply_to(img)
    t = sitk.BSplineTransformInitializer(img, [3] * grid.dimension)
    t.SetParameters(rng.normal(scale=1.5, size=len(t.GetParameters())).tolist())
    return t


def make_transform(kind: str, grid: Geometry, rng) -> sitk.Transform:
    dim = grid.dimension
    if kind == "identity":
        return sitk.Transform(dim, sitk.sitkIdentity)
    if kind == "affine":
        return rotating_affine(dim, rng)
    if kind == "field":
        return smooth_field(grid, rng)
    if kind == "composite":  # the field acts first, then the affine (sitk applies from the back)
        return sitk.CompositeTransform([rotating_affine(dim, rng), smooth_field(grid, rng)])
    if kind == "bspline":
        return bspline(grid, rng)
    raise AssertionError(kind)


def resampling_case(dim: int, seed: int, kind: str = "composite") -> tuple:
    """A seeded oblique label map, a float32 image on its grid, the common grid and a
    transform of `kind`: ``(label_map, image, grid, transform)``."""
    rng = np.random.default_rng(seed)
    label_map = oblique_label_map(dim, rng)
    image = intensity_on(label_map, rng, np.float32)
    grid = common_grid(dim)
    return label_map, image, grid, make_transform(kind, grid, rng)


def itk_sampling(transform, grid: Geometry) -> np.ndarray:
    """``transform(p) - p`` on `grid` as ITK samples it (``TransformToDisplacementField``):
    ``(*grid.shape, dim)``, mm, ITK order last."""
    field = sitk.TransformToDisplacementField(
        transform, sitk.sitkVectorFloat64, grid.size, grid.origin, grid.spacing, grid.direction
    )
    return sitk.GetArrayFromImage(field)


# --------------------------------------------------------------------------------- the tests


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("kind", ["identity", "affine", "field", "composite", "bspline"])
def test_equals_dense_itk_resampling(dim, kind):
    rng = np.random.default_rng(7 + dim)
    label_map = oblique_label_map(dim, rng)
    grid = common_grid(dim)
    sm = compare(label_map, make_transform(kind, grid, rng), grid)
    # part of the grid maps outside the label map, and many points are fuzzy
    total = sm.dense(dtype=np.float64).sum(axis=0)
    assert (total == 0).any() and (total == 1).any()
    assert ((total > 0) & (sm.dense().max(axis=0) < 1)).any()


@pytest.mark.parametrize("dim", [2, 3])
def test_memberships_sum_to_one_inside_and_zero_outside(dim):
    rng = np.random.default_rng(11)
    label_map = oblique_label_map(dim, rng)
    grid = common_grid(dim)
    transform = make_transform("composite", grid, rng)
    sm = resample_label_memberships(label_map, transform, grid)
    total = sm.dense(dtype=np.float64).sum(axis=0)
    inside = itk_inside(label_map, transform, grid)
    assert inside.any() and (~inside).any()
    np.testing.assert_allclose(total[inside], 1.0, atol=1e-6)
    assert np.all(total[~inside] == 0)


def grid_point(grid: Geometry, index) -> np.ndarray:
    """Physical point (mm) of an ITK-order voxel index of `grid`."""
    m = np.array(grid.direction).reshape(grid.dimension, -1) * np.array(grid.spacing)
    return np.array(grid.origin) + m @ np.array(index, float)


def exact_border_case(dim: int, flip: bool):
    """Axis-aligned grids in exactly representable numbers: grid points land on label-map
    voxel centres, halfway between them, and on both half-voxel buffer borders."""
    rng = np.random.default_rng(3)
    shape = (6, 5, 7)[-dim:] if dim == 3 else (5, 7)
    label_map = sitk.GetImageFromArray(voronoi_labels(shape, LARGE_VALUES, rng, np.uint16))
    spacing = np.array([2.0, 1.0, 0.5][:dim])
    label_map.SetSpacing(spacing.tolist())
    label_map.SetOrigin([4.0, -2.0, 1.0][:dim])
    direction = np.eye(dim)
    if flip:
        direction[0, 0] = -1.0
    label_map.SetDirection(direction.ravel().tolist())
    # grid spacing = half a voxel; the grid starts one voxel before the map and ends after it
    n = np.array(label_map.GetSize())
    first = np.array(label_map.TransformContinuousIndexToPhysicalPoint([-1.0] * dim))
    grid = Geometry(
        tuple(int(k) for k in 2 * n + 4),
        tuple(spacing / 2),
        tuple(first),
        tuple(direction.ravel()),
    )
    return label_map, grid


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("flip", [False, True])
@pytest.mark.parametrize("kind", ["identity", "zero_field", "translation"])
@pytest.mark.parametrize("decided_by", ["itk", "here"])
def test_exact_voxel_centres_and_buffer_border(dim, flip, kind, decided_by, monkeypatch):
    """Points on the border are normally handed to ITK; in exact arithmetic the kernel's own
    test (forced with a negative tolerance) must give the same answer."""
    if decided_by == "here":
        monkeypatch.setattr(_memberships, "_BORDER_EPS", -1.0)
    label_map, grid = exact_border_case(dim, flip)
    n = np.array(label_map.GetSize())
    if kind == "identity":  # ITK's linear-transform path
        transform = sitk.Transform(dim, sitk.sitkIdentity)
        shift = np.zeros(dim)
    elif kind == "zero_field":  # ITK's per-point (non-linear) path
        img = sitk.Image(list(grid.size), sitk.sitkVectorFloat64, dim)
        grid.apply_to(img)
        transform = sitk.DisplacementFieldTransform(img)
        shift = np.zeros(dim)
    else:  # a whole number of half voxels
        shift = np.array([1.0, -0.5, 0.25][:dim])
        transform = sitk.TranslationTransform(dim, shift.tolist())
    # continuous indices (first ITK axis) of the images of the grid's first row of points
    row = [grid_point(grid, (i,) + (0,) * (dim - 1)) + shift for i in range(grid.size[0])]
    cx = np.array([label_map.TransformPhysicalPointToContinuousIndex(p)[0] for p in row])
    assert -0.5 in cx and n[0] - 0.5 in cx and 0.0 in cx and 0.5 in cx  # the cases at stake

    sm = compare(label_map, transform, grid)
    total = sm.dense(dtype=np.float64).sum(axis=0).reshape(-1, grid.size[0])
    # ITK's half-open buffer: the lower border is inside, the upper one is not
    inner_rows = total[total.max(axis=1) > 0]
    assert np.all(inner_rows[:, cx == -0.5] == 1.0)
    assert np.all(inner_rows[:, cx == n[0] - 0.5] == 0.0)
    assert np.all(inner_rows[:, cx == n[0] - 1.0] == 1.0)


def test_resampling_onto_its_own_grid_is_one_hot():
    rng = np.random.default_rng(5)
    label_map = oblique_label_map(3, rng)
    grid = Geometry.from_image(label_map)
    sm = compare(label_map, sitk.Transform(3, sitk.sitkIdentity), grid)
    assert np.all(sm.weight == 1.0)
    assert sm.index.size == np.prod(grid.shape)
    arr = sitk.GetArrayViewFromImage(label_map).ravel()
    for k, v in enumerate(sm.values):
        np.testing.assert_array_equal(sm.label(k)[0], np.flatnonzero(arr == v))


@pytest.mark.parametrize("dim", [2, 3])
def test_requested_values_absent_unrequested_and_order(dim):
    rng = np.random.default_rng(13)
    label_map = oblique_label_map(dim, rng)
    grid = common_grid(dim)
    transform = make_transform("composite", grid, rng)
    values = [14175, 3, 42, 0]  # unsorted; 42 absent; 1000 present but not requested
    sm = compare(label_map, transform, grid, values=values)
    assert sm.label(2)[0].size == 0 and sm.ptr[3] == sm.ptr[2]
    total = sm.dense(dtype=np.float64).sum(axis=0)
    assert (total[(total > 0)] < 1 - 1e-3).any(), "label 1000's share is missing"
    assert np.all(total <= 1 + 1e-6)
    empty = resample_label_memberships(label_map, transform, grid, values=[])
    assert empty.values.shape == (0,) and empty.ptr.tolist() == [0]
    assert empty.dense().shape == (0, *grid.shape)


@pytest.mark.parametrize(
    "dtype, values",
    [
        (np.uint8, (0, 1, 7, 255)),
        (np.int16, (-5, 0, 12, 3000)),
        (np.int64, (0, 3, 2**40, 2**62)),  # too spread for a table: the sorting path
    ],
)
def test_integer_pixel_types(dtype, values):
    rng = np.random.default_rng(17)
    label_map = oblique_label_map(2, rng, values=values, dtype=dtype)
    assert sitk.GetArrayViewFromImage(label_map).dtype == dtype
    grid = common_grid(2)
    transform = make_transform("affine", grid, rng)
    sm = compare(label_map, transform, grid)
    assert sm.values.tolist() == sorted(values)
    compare(label_map, transform, grid, values=[values[2], 99, values[0]])


def test_dense_round_trip_and_label_views():
    rng = np.random.default_rng(19)
    label_map = oblique_label_map(3, rng)
    grid = common_grid(3)
    sm = resample_label_memberships(label_map, make_transform("field", grid, rng), grid)
    dense = sm.dense()
    assert dense.shape == (sm.values.size, *grid.shape) and dense.dtype == np.float32
    assert sm.dense(dtype=np.float64).dtype == np.float64
    for k in range(sm.values.size):
        idx, w = sm.label(k)
        flat = dense[k].ravel()
        np.testing.assert_array_equal(idx, np.flatnonzero(flat))
        np.testing.assert_array_equal(w, flat[idx])
    with pytest.raises(IndexError):
        sm.label(sm.values.size)
    with pytest.raises(ValueError):
        sm.weight[0] = 0.5  # read-only


def test_many_labels_per_point_and_small_slabs(monkeypatch):
    """Salt-and-pepper labels upsampled: most points see several labels (the entry buffer
    grows), and slabs far smaller than the grid (one plane each, then part of a plane)."""
    rng = np.random.default_rng(23)
    arr = rng.choice(np.array([0, 5, 9, 300, 14175], np.int32), size=(9, 10, 11))
    label_map = sitk.GetImageFromArray(arr)
    label_map.SetSpacing([2.0, 2.5, 3.0])
    grid = Geometry((30, 28, 26), (0.7, 0.9, 1.1), (-1.0, -0.5, -1.5), tuple(np.eye(3).ravel()))
    transform = make_transform("composite", grid, rng)
    sm = compare(label_map, transform, grid)
    assert sm.index.size > 2 * np.prod(grid.shape) * 0.5
    for slab in (grid.size[0] * grid.size[1], 100):
        monkeypatch.setattr(_memberships, "_SLAB_VOXELS", slab)
        again = resample_label_memberships(label_map, transform, grid)
        np.testing.assert_array_equal(again.ptr, sm.ptr)
        np.testing.assert_array_equal(again.index, sm.index)
        np.testing.assert_array_equal(again.weight, sm.weight)


def test_border_decided_by_itk_or_here_agree(monkeypatch):
    """Generic points are far from the border: deciding inside-ness from our continuous
    indices or asking ITK for every point gives the same memberships."""
    rng = np.random.default_rng(29)
    label_map = oblique_label_map(3, rng)
    grid = common_grid(3)
    transform = make_transform("composite", grid, rng)
    ours = resample_label_memberships(label_map, transform, grid)
    monkeypatch.setattr(_memberships, "_BORDER_EPS", np.inf)  # every slab asks ITK
    itk = resample_label_memberships(label_map, transform, grid)
    np.testing.assert_array_equal(ours.index, itk.index)
    np.testing.assert_array_equal(ours.weight, itk.weight)


@pytest.mark.parametrize("dim", [2, 3])
def test_itk_asked_point_by_point_or_for_the_whole_grid_agree(dim, monkeypatch):
    """Every point handed to ITK (an infinite tolerance): asked point by point, as its
    resampling maps a transform that is not linear, or by resampling the whole grid, the
    same memberships, image and coverage, and the same as ITK's resampling."""
    label_map, image, grid, transform = resampling_case(dim, 37 + dim)
    monkeypatch.setattr(_memberships, "_BORDER_EPS", np.inf)
    results = {}
    for way, limit in (("whole", 0), ("points", 10**9)):
        monkeypatch.setattr(_memberships, "_POINTWISE_LIMIT", limit)
        if way == "points":  # the whole grid's resampling is not asked for
            monkeypatch.setattr(_memberships, "_itk_inside", None)
        results[way] = (
            _memberships.resample_image_and_memberships(
                image, label_map, transform, grid, values=LARGE_VALUES
            ),
            _memberships.covered_voxels(Geometry.from_image(image), transform, grid),
        )
    (values, sm), covered = results["points"]
    (values_w, sm_w), covered_w = results["whole"]
    np.testing.assert_array_equal(sm.index, sm_w.index)
    np.testing.assert_array_equal(sm.weight, sm_w.weight)
    np.testing.assert_array_equal(values, values_w)
    np.testing.assert_array_equal(covered, covered_w)
    np.testing.assert_array_equal(covered, itk_covered(image, transform, grid, sitk.sitkLinear))


def assert_same_resampling(values, memberships, ref_values, ref_memberships) -> None:
    """The same image (NaN where the reference's is, values to 1e-12) and memberships."""
    np.testing.assert_array_equal(np.isnan(values), np.isnan(ref_values))
    np.testing.assert_allclose(values, ref_values, rtol=1e-12, atol=1e-9, equal_nan=True)
    np.testing.assert_allclose(memberships.dense(), ref_memberships.dense(), rtol=0, atol=1e-6)


@pytest.mark.parametrize("dim", [2, 3])
def test_itk_asked_point_by_point_through_the_pieces(dim, monkeypatch):
    """A transform given as its pieces (TransformPieces, with its sampling): every point
    handed to ITK is decided piece by piece, as the composite's TransformPoint calls them,
    with no composite built and the whole grid never resampled: the same coverage as ITK's
    resampling through the composite, and the same image and memberships as from the
    composite's own sampling."""
    from itk_nrreval.io.transforms import TransformPieces, transform_pieces

    label_map, image, grid, transform = resampling_case(dim, 43 + dim)
    sampled = itk_sampling(transform, grid)
    values_t, sm_t = _memberships.resample_image_and_memberships(
        image, label_map, transform, grid, values=LARGE_VALUES
    )
    pieces = transform_pieces(transform)
    assert isinstance(pieces, TransformPieces) and len(pieces) == 2
    monkeypatch.setattr(_memberships, "_BORDER_EPS", np.inf)
    monkeypatch.setattr(_memberships, "_POINTWISE_LIMIT", 10**9)
    monkeypatch.setattr(_memberships, "_itk_inside", None)  # the whole grid: not asked
    monkeypatch.setattr(_memberships, "flatten", None)  # no composite built
    covered = _memberships.covered_voxels(
        Geometry.from_image(image), pieces, grid, displacement=sampled
    )
    np.testing.assert_array_equal(covered, itk_covered(image, transform, grid, sitk.sitkLinear))
    assert covered.any() and not covered.all()
    values, sm = _memberships.resample_image_and_memberships(
        image, label_map, pieces, grid, values=LARGE_VALUES, displacement=sampled
    )
    assert_same_resampling(values, sm, values_t, sm_t)
    with pytest.raises(ValueError, match="displacement"):
        _memberships.covered_voxels(Geometry.from_image(image), pieces, grid)


def test_grid_as_image_and_fully_outside():
    rng = np.random.default_rng(31)
    label_map = oblique_label_map(2, rng)
    reference = sitk.Image([12, 10], sitk.sitkUInt8)
    reference.SetOrigin([500.0, 500.0])
    sm = resample_label_memberships(label_map, sitk.Transform(2, sitk.sitkIdentity), reference)
    assert sm.shape == (10, 12) and sm.index.size == 0
    assert sm.ptr.tolist() == [0] * (len(LARGE_VALUES) + 1)


def test_bad_input():
    rng = np.random.default_rng(37)
    label_map = oblique_label_map(2, rng)
    grid = common_grid(2)
    ident = sitk.Transform(2, sitk.sitkIdentity)
    # a float label map holding integers is read as integers; a fractional value is refused
    as_float = sitk.Cast(label_map, sitk.sitkFloat32)
    same = resample_label_memberships(as_float, ident, grid)
    np.testing.assert_array_equal(
        same.dense(), resample_label_memberships(label_map, ident, grid).dense()
    )
    as_float[0, 0] = 1.5
    with pytest.raises(InputError, match="non-integer value 1.5"):
        resample_label_memberships(as_float, ident, grid)
    with pytest.raises(InputError, match="integer pixel type"):
        resample_label_memberships(sitk.Cast(label_map, sitk.sitkComplexFloat32), ident, grid)
    with pytest.raises(InputError, match="scalar"):
        vec = sitk.Compose(label_map, label_map)
        resample_label_memberships(vec, ident, grid)
    with pytest.raises(InputError, match="repeated"):
        resample_label_memberships(label_map, ident, grid, values=[3, 0, 3])
    with pytest.raises(InputError, match="integers"):
        resample_label_memberships(label_map, ident, grid, values=[0.5, 3])
    with pytest.raises(InputError, match="dimension"):
        resample_label_memberships(label_map, sitk.Transform(3, sitk.sitkIdentity), grid)


# ------------------------------------------------------------------ nearest and gaussian


def grid_image(grid: Geometry) -> sitk.Image:
    """An image on `grid`, for ``sitk.Resample``'s reference-image form."""
    return grid.apply_to(sitk.Image(list(grid.size), sitk.sitkUInt8))


def dense_nearest_reference(label_map, transform, grid: Geometry, values) -> np.ndarray:
    """The label map itself through ``sitk.Resample`` with nearest neighbour, then one-hot.

    The default value is one no channel has, so points outside read as no label."""
    outside = int(max(values)) + 1
    labels = sitk.Cast(label_map, sitk.sitkInt64)
    out = sitk.Resample(labels, grid_image(grid), transform, sitk.sitkNearestNeighbor, outside)
    arr = sitk.GetArrayFromImage(out)
    return np.stack([arr == v for v in values]).astype(np.float32)


def dense_gaussian_reference(label_map, transform, grid: Geometry, values, sigma) -> np.ndarray:
    """Each whole one-hot channel smoothed (ITK, mm), then resampled linearly (default 0)."""
    arr = sitk.GetArrayViewFromImage(label_map)
    out = []
    for v in values:
        channel = sitk.GetImageFromArray((arr == v).astype(np.float32))
        channel.CopyInformation(label_map)
        smooth = sitk.SmoothingRecursiveGaussian(channel, [sigma] * label_map.GetDimension())
        res = sitk.Resample(smooth, grid_image(grid), transform, sitk.sitkLinear, 0.0)
        out.append(sitk.GetArrayFromImage(res))
    return np.stack(out)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("kind", ["identity", "affine", "composite", "bspline"])
def test_nearest_equals_itk_nearest_neighbour_resampling(dim, kind):
    rng = np.random.default_rng(31 + dim)
    label_map = oblique_label_map(dim, rng)
    grid = common_grid(dim)
    transform = make_transform(kind, grid, rng)
    sm = resample_label_memberships(label_map, transform, grid, method="nearest")
    check_structure(sm, grid.shape)
    np.testing.assert_array_equal(sm.values, np.asarray(LARGE_VALUES, np.int64))
    ref = dense_nearest_reference(label_map, transform, grid, LARGE_VALUES)
    np.testing.assert_array_equal(sm.dense(), ref)
    # crisp: every stored membership is 1, every inside point has exactly one label
    assert np.all(sm.weight == 1)
    inside = itk_inside(label_map, transform, grid)
    total = sm.dense().sum(axis=0)
    assert np.all(total[inside] == 1) and np.all(total[~inside] == 0)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("sigma", [0.8, 2.5])
def test_gaussian_equals_smoothing_whole_channels_then_linear_resampling(dim, sigma):
    rng = np.random.default_rng(41 + dim)
    label_map = oblique_label_map(dim, rng)
    grid = common_grid(dim)
    transform = make_transform("composite", grid, rng)
    sm = resample_label_memberships(label_map, transform, grid, method="gaussian", sigma_mm=sigma)
    check_structure(sm, grid.shape)
    ref = dense_gaussian_reference(label_map, transform, grid, LARGE_VALUES, sigma)
    # Differences: channels cropped 4 sigma beyond each label, values below 1e-6 not stored.
    np.testing.assert_allclose(sm.dense(), np.clip(ref, 0, 1), rtol=0, atol=1e-3)
    total = sm.dense(dtype=np.float64).sum(axis=0)
    inside = itk_inside(label_map, transform, grid)
    np.testing.assert_allclose(total[inside], 1.0, atol=2e-3)
    # smoothing makes memberships fuzzier than linear interpolation alone
    linear = resample_label_memberships(label_map, transform, grid)
    fuzzy = lambda m: int(((m.dense() > 0.01) & (m.dense() < 0.99)).sum())  # noqa: E731
    assert fuzzy(sm) > fuzzy(linear)


def test_label_interpolation_options_are_checked():
    rng = np.random.default_rng(3)
    label_map = oblique_label_map(2, rng)
    grid = common_grid(2)
    t = sitk.Transform(2, sitk.sitkIdentity)
    with pytest.raises(InputError, match="label interpolation: 'cubic' is not one of"):
        resample_label_memberships(label_map, t, grid, method="cubic")
    with pytest.raises(InputError, match="expected a finite sigma > 0 mm, got 0"):
        resample_label_memberships(label_map, t, grid, method="gaussian", sigma_mm=0)
    with pytest.raises(InputError, match="expected a number of mm, got None"):
        resample_label_memberships(label_map, t, grid, method="gaussian")
    with pytest.raises(InputError, match="only for method 'gaussian'"):
        resample_label_memberships(label_map, t, grid, method="nearest", sigma_mm=1.0)


# ------------------------------------------------- the image resampled beside the memberships


def intensity_on(label_map: sitk.Image, rng, dtype=np.int16) -> sitk.Image:
    """A smooth image with sharp steps on the label map's own grid (header copied)."""
    labels = sitk.GetArrayFromImage(label_map).astype(float)
    smooth = ndimage.gaussian_filter(rng.normal(size=labels.shape), 1.5)
    arr = (300.0 * smooth / np.abs(smooth).max() + 0.01 * labels).astype(dtype)
    img = sitk.GetImageFromArray(arr)
    img.CopyInformation(label_map)
    return img


def itk_linear(image: sitk.Image, transform, grid: Geometry) -> np.ndarray:
    """ITK's own linear resampling in float64, NaN outside the buffer (flat, C order)."""
    image = sitk.Cast(image, sitk.sitkFloat64)
    out = sitk.Resample(image, grid_image(grid), transform, sitk.sitkLinear, float("nan"))
    return sitk.GetArrayFromImage(out).ravel()


def check_image_and_memberships(image, label_map, transform, grid) -> np.ndarray:
    """The shared sampling's image equals ITK's linear resampling (NaN where ITK's is, values
    to 1e-12 of the image's range) and its memberships are the memberships' own, bit for bit."""
    values, sm = _memberships.resample_image_and_memberships(
        image, label_map, transform, grid, values=LARGE_VALUES
    )
    ref = itk_linear(image, transform, grid)
    assert values.shape == ref.shape and values.dtype == np.float64
    np.testing.assert_array_equal(np.isnan(values), np.isnan(ref))
    ok = ~np.isnan(ref)
    scale = float(np.abs(sitk.GetArrayViewFromImage(image)).max())
    np.testing.assert_allclose(values[ok], ref[ok], rtol=0, atol=1e-12 * scale)
    own = resample_label_memberships(label_map, transform, grid, values=LARGE_VALUES)
    for a, b in ((sm.ptr, own.ptr), (sm.index, own.index), (sm.weight, own.weight)):
        np.testing.assert_array_equal(a, b)
    # the image alone (no label map): the same values, by the same kernels
    alone, none = _memberships.resample_image_and_memberships(image, None, transform, grid)
    assert none is None
    np.testing.assert_array_equal(alone, values)
    return values


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("kind", ["identity", "affine", "field", "composite", "bspline"])
@pytest.mark.parametrize("dtype", [np.int16, np.float32])
def test_image_resampled_beside_the_memberships_equals_itk(dim, kind, dtype):
    """Oblique, anisotropic, not co-located with the grid; part of the grid maps outside."""
    rng = np.random.default_rng(21 + dim)
    label_map = oblique_label_map(dim, rng)
    grid = common_grid(dim)
    values = check_image_and_memberships(
        intensity_on(label_map, rng, dtype), label_map, make_transform(kind, grid, rng), grid
    )
    assert np.isnan(values).any() and (~np.isnan(values)).any()


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("flip", [False, True])
@pytest.mark.parametrize("decided_by", ["itk", "here"])
def test_image_beside_the_memberships_on_voxel_centres_and_the_buffer_border(
    dim, flip, decided_by, monkeypatch
):
    """Grid points exactly on voxel centres and on both half-voxel borders (ITK's half-open
    buffer): inside and outside decided as ITK decides them."""
    if decided_by == "here":
        monkeypatch.setattr(_memberships, "_BORDER_EPS", -1.0)
    label_map, grid = exact_border_case(dim, flip)
    image = intensity_on(label_map, np.random.default_rng(5), np.float32)
    for transform in (
        sitk.Transform(dim, sitk.sitkIdentity),
        sitk.TranslationTransform(dim, [1.0, -0.5, 0.25][:dim]),
    ):
        check_image_and_memberships(image, label_map, transform, grid)


def test_image_beside_the_memberships_needs_the_label_maps_grid():
    rng = np.random.default_rng(2)
    label_map = oblique_label_map(3, rng)
    image = intensity_on(label_map, rng)
    image.SetOrigin([o + 0.5 for o in image.GetOrigin()])
    grid = common_grid(3)
    with pytest.raises(ValueError, match="grid"):
        _memberships.resample_image_and_memberships(
            image, label_map, sitk.Transform(3, sitk.sitkIdentity), grid, values=LARGE_VALUES
        )
    assert not _memberships.shares_grid(image, label_map)
    assert _memberships.shares_grid(label_map, label_map)


@pytest.mark.parametrize("dim", [2, 3])
def test_image_and_memberships_from_the_callers_sampling(dim, monkeypatch):
    """With the transform already sampled on the grid (displacement=), the same image and
    memberships as from their own slab-by-slab sampling (several slabs here)."""
    monkeypatch.setattr(_memberships, "_SLAB_VOXELS", 200)
    label_map, image, grid, t = resampling_case(dim, 31 + dim)
    sampled = itk_sampling(t, grid)
    own_values, own = _memberships.resample_image_and_memberships(
        image, label_map, t, grid, values=LARGE_VALUES
    )
    values, sm = _memberships.resample_image_and_memberships(
        image, label_map, t, grid, values=LARGE_VALUES, displacement=sampled
    )
    assert_same_resampling(values, sm, own_values, own)
    with pytest.raises(ValueError, match="displacement"):
        _memberships.resample_image_and_memberships(
            image, label_map, t, grid, values=LARGE_VALUES, displacement=sampled[1:]
        )


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("frame", ["identity", "field"])
def test_image_memberships_and_coverage_from_a_point_map(dim, frame, monkeypatch):
    """The transform as a PointMap (T's pieces after F's displacement d, sampled by the
    compiled kernels a slab at a time; several slabs here): the image, memberships and
    coverage of ITK's resampling through the composite ``T o (p + d(p))``, F given to ITK as
    a displacement-field transform. Oblique grids, an image not co-located with the grid."""
    from itk_nrreval.io.transforms import PointMap, transform_pieces

    monkeypatch.setattr(_memberships, "_SLAB_VOXELS", 200)
    label_map, image, grid, t = resampling_case(dim, 47 + dim)
    pieces = transform_pieces(t)
    if frame == "identity":
        point_map, composite = PointMap(pieces), t
    else:
        f = smooth_field(grid, np.random.default_rng(53 + dim), amplitude=1.5)
        d = sitk.GetArrayFromImage(f.GetDisplacementField())
        point_map = PointMap(pieces, d)
        composite = sitk.CompositeTransform([*pieces, f])
    ref_values, ref_memberships = _memberships.resample_image_and_memberships(
        image, label_map, composite, grid, values=LARGE_VALUES
    )
    np.testing.assert_allclose(
        ref_values, itk_linear(image, composite, grid), rtol=1e-12, atol=1e-9, equal_nan=True
    )
    values, sm = _memberships.resample_image_and_memberships(
        image, label_map, lambda: composite, grid, values=LARGE_VALUES, displacement=point_map
    )
    assert_same_resampling(values, sm, ref_values, ref_memberships)
    alone, none = _memberships.resample_image_and_memberships(
        image, None, lambda: composite, grid, displacement=point_map
    )
    assert none is None
    np.testing.assert_array_equal(alone, values)
    covered = _memberships.covered_voxels(
        Geometry.from_image(image), lambda: composite, grid, displacement=point_map
    )
    np.testing.assert_array_equal(covered, itk_covered(image, composite, grid, sitk.sitkLinear))
    assert covered.any() and not covered.all()


# ------------------------------------------------------------------ coverage, not resampling


def itk_covered(image: sitk.Image, transform, grid: Geometry, interpolator) -> np.ndarray:
    """Where ``sitk.Resample`` gives the image a value (NaN default elsewhere): flat bool."""
    image = sitk.Cast(image, sitk.sitkFloat64)
    out = sitk.Resample(image, grid_image(grid), transform, interpolator, float("nan"))
    return ~np.isnan(sitk.GetArrayFromImage(out).ravel())


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("kind", ["identity", "affine", "field", "composite", "bspline"])
@pytest.mark.parametrize("interpolator", [sitk.sitkLinear, sitk.sitkBSpline])
def test_covered_voxels_are_where_itk_resampling_gives_a_value(
    dim, kind, interpolator, monkeypatch
):
    """Oblique, anisotropic image not co-located with the grid, several slabs: the voxels
    covered are exactly those ITK's resampling (any interpolator) gives a value, and
    exactly those the shared sampling does not leave NaN."""
    monkeypatch.setattr(_memberships, "_SLAB_VOXELS", 300)
    label_map, image, grid, t = resampling_case(dim, 41 + dim, kind)
    covered = _memberships.covered_voxels(Geometry.from_image(image), t, grid)
    assert covered.dtype == np.bool_ and covered.shape == (int(np.prod(grid.shape)),)
    np.testing.assert_array_equal(covered, itk_covered(image, t, grid, interpolator))
    assert covered.any() and not covered.all()
    sampled = itk_sampling(t, grid)
    from_sampled = _memberships.covered_voxels(
        Geometry.from_image(image), t, grid, displacement=sampled
    )
    np.testing.assert_array_equal(from_sampled, covered)
    values, _ = _memberships.resample_image_and_memberships(
        image, label_map, t, grid, values=LARGE_VALUES
    )
    np.testing.assert_array_equal(covered, ~np.isnan(values))


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("flip", [False, True])
@pytest.mark.parametrize(
    "decided_by, linear",
    [("itk", True), ("itk", False), ("itk_points", False), ("here", True), ("here", False)],
)
@pytest.mark.parametrize("given", ["array", "point_map"])
def test_covered_voxels_on_the_buffer_border(dim, flip, decided_by, linear, given, monkeypatch):
    """Points exactly on both half-voxel borders (ITK's half-open buffer): decided by ITK
    (from a sampled displacement or a PointMap, with the transform built only then; point
    by point for a transform that is not linear, here a translation composed with a zero
    field, else by resampling the whole grid) or by the kernel's own test in exact
    arithmetic, as ITK decides them."""
    from itk_nrreval.io.transforms import PointMap, transform_pieces

    if decided_by == "here":
        monkeypatch.setattr(_memberships, "_BORDER_EPS", -1.0)
    if decided_by == "itk_points":  # (a linear transform: ITK maps rows by increments)
        monkeypatch.setattr(_memberships, "_itk_inside", None)  # point by point only
    label_map, grid = exact_border_case(dim, flip)
    built = []

    def transform():
        built.append(1)
        shift = sitk.TranslationTransform(dim, [1.0, -0.5, 0.25][:dim])
        if linear:
            return shift
        zero = sitk.Image(list(grid.size), sitk.sitkVectorFloat64, dim)
        grid.apply_to(zero)
        return sitk.CompositeTransform([shift, sitk.DisplacementFieldTransform(zero)])

    t = transform()
    sampled = itk_sampling(t, grid)
    if given == "point_map":
        sampled = PointMap(transform_pieces(t))
    built.clear()
    covered = _memberships.covered_voxels(
        Geometry.from_image(label_map), transform, grid, displacement=sampled
    )
    expected = itk_covered(label_map, t, grid, sitk.sitkLinear)
    np.testing.assert_array_equal(covered, expected)
    assert expected.any() and not expected.all()
    assert len(built) == (0 if decided_by == "here" else 1)
    with pytest.raises(ValueError, match="displacement"):
        _memberships.covered_voxels(Geometry.from_image(label_map), transform, grid)
