"""ITK HDF5 transform files read with h5py (issue 30): the same transforms as ITK reads.

The reference is SimpleITK's own ``ReadTransform`` of the file SimpleITK wrote, taken apart
(``leaves``), compared bit for bit: types, fixed parameters, parameters, the fields' values
and grids, and mapped points. Fields are oblique, anisotropic and not centred on the origin.
"""

from __future__ import annotations

import h5py
import numpy as np
import pytest
import SimpleITK as sitk

from itk_nrreval import InputError
from itk_nrreval.io._images import Geometry
from itk_nrreval.io._itk_hdf5 import read_pieces, transform_dimension
from itk_nrreval.io.transforms import (
    PointwiseInverse,
    TransformPieces,
    chain_transform,
    displacement_array,
    displacement_field,
    flatten,
    leaves,
    transform_pieces,
)


def _oblique_field(dim: int, size: tuple[int, ...], seed: int) -> sitk.Image:
    rng = np.random.default_rng(seed)
    field = sitk.GetImageFromArray(rng.normal(scale=1.5, size=(*size[::-1], dim)), isVector=True)
    field.SetSpacing([0.8 + 0.3 * k for k in range(dim)])
    field.SetOrigin([-5.0 + 2.0 * k for k in range(dim)])
    q, _ = np.linalg.qr(rng.normal(size=(dim, dim)))
    field.SetDirection(q.reshape(-1).tolist())
    return field


def _affine(dim: int, seed: int) -> sitk.AffineTransform:
    rng = np.random.default_rng(seed)
    t = sitk.AffineTransform(dim)
    t.SetMatrix((np.eye(dim) + rng.normal(scale=0.05, size=(dim, dim))).reshape(-1).tolist())
    t.SetTranslation(rng.normal(scale=2.0, size=dim).tolist())
    t.SetCenter(rng.normal(scale=3.0, size=dim).tolist())
    return t


def _transforms(dim: int) -> dict[str, sitk.Transform]:
    size = (9, 7, 6)[:dim]
    field = sitk.DisplacementFieldTransform(_oblique_field(dim, size, 1))
    return {
        "affine": _affine(dim, 2),
        "field": field,
        "composite": sitk.CompositeTransform([_affine(dim, 3), field]),
        "three": sitk.CompositeTransform(
            [
                sitk.DisplacementFieldTransform(_oblique_field(dim, size[::-1], 4)),
                _affine(dim, 5),
                sitk.DisplacementFieldTransform(_oblique_field(dim, size, 6)),
            ]
        ),
    }


def _random_points(dim: int, n: int = 200) -> np.ndarray:
    return np.random.default_rng(7).uniform(-12.0, 14.0, size=(n, dim))


def _assert_same_piece(a: sitk.Transform, b: sitk.Transform) -> None:
    assert type(a) is type(b) and a.GetName() == b.GetName()
    assert a.GetFixedParameters() == b.GetFixedParameters()
    if isinstance(a, sitk.DisplacementFieldTransform):
        fa, fb = a.GetDisplacementField(), b.GetDisplacementField()
        assert fa.GetPixelID() == fb.GetPixelID() == sitk.sitkVectorFloat64
        assert (fa.GetSize(), fa.GetOrigin(), fa.GetSpacing(), fa.GetDirection()) == (
            fb.GetSize(),
            fb.GetOrigin(),
            fb.GetSpacing(),
            fb.GetDirection(),
        )
        assert np.array_equal(sitk.GetArrayViewFromImage(fa), sitk.GetArrayViewFromImage(fb))
    else:
        assert a.GetParameters() == b.GetParameters()


@pytest.mark.parametrize("dim", [2, 3])
def test_pieces_read_with_h5py_are_itks(tmp_path, dim):
    for name, t in _transforms(dim).items():
        path = tmp_path / f"{name}.h5"
        sitk.WriteTransform(t, str(path))
        ours = read_pieces(path)
        itk = leaves(sitk.ReadTransform(str(path)))
        assert ours is not None and len(ours) == len(itk), name
        for a, b in zip(ours, itk, strict=True):
            _assert_same_piece(a, b)
        points = _random_points(dim)
        mapped = [flatten(ours).TransformPoint(p.tolist()) for p in points]
        assert mapped == [sitk.ReadTransform(str(path)).TransformPoint(p.tolist()) for p in points]
        assert transform_dimension(path) == dim


def test_layouts_it_does_not_know_are_left_to_itk(tmp_path):
    bspline = sitk.BSplineTransformInitializer(sitk.Image([9, 9, 9], sitk.sitkFloat32), [3] * 3)
    euler = sitk.Euler3DTransform((1.0, 2.0, 3.0), 0.1, 0.2, 0.3, (1.0, 0.0, 0.0))
    for name, t in {"bspline": bspline, "euler": euler}.items():
        sitk.WriteTransform(t, str(tmp_path / f"{name}.h5"))
        assert read_pieces(tmp_path / f"{name}.h5") is None
    short = tmp_path / "short.h5"
    sitk.WriteTransform(_transforms(3)["composite"], str(short))
    with h5py.File(short, "r+") as f:  # one value fewer than the field's grid holds
        n = len(f["TransformGroup/2/TransformParameters"])
        del f["TransformGroup/2/TransformParameters"]
        f["TransformGroup/2/TransformParameters"] = np.zeros(n - 1)
    assert read_pieces(short) is None
    with pytest.raises(InputError, match="short.h5: cannot read transform"):
        transform_pieces(short)  # ITK then reads it, and its error names the file
    (tmp_path / "text.h5").write_text("not HDF5\n")
    assert read_pieces(tmp_path / "text.h5") is None


@pytest.mark.parametrize("dim", [2, 3])
def test_a_chain_as_pieces_is_the_chain(tmp_path, dim):
    """transform_pieces of an ANTs-order chain of files maps every point as chain_transform
    does (the order of the pieces, not only their values)."""
    paths = []
    for name, t in _transforms(dim).items():
        paths.append(tmp_path / f"{name}.h5")
        sitk.WriteTransform(t, str(paths[-1]))
    mat = tmp_path / "affine.mat"
    sitk.WriteTransform(_affine(dim, 11), str(mat))
    chain = [str(paths[2]), str(mat), str(paths[3]), str(paths[1])]
    pieces = transform_pieces(chain)
    reference = chain_transform(chain)
    assert [p.GetName() for p in pieces] == [p.GetName() for p in leaves(reference)]
    points = _random_points(dim)
    assert [flatten(pieces).TransformPoint(p.tolist()) for p in points] == [
        reference.TransformPoint(p.tolist()) for p in points
    ]


def test_a_field_with_nan_read_as_pieces_is_refused(tmp_path):
    field = _oblique_field(3, (6, 5, 4), 3)
    values = sitk.GetArrayFromImage(field)
    values[1, 2, 3, 0] = np.nan
    bad = sitk.GetImageFromArray(values, isVector=True)
    bad.CopyInformation(field)
    path = tmp_path / "nan.h5"
    sitk.WriteTransform(sitk.DisplacementFieldTransform(bad), str(path))
    with pytest.raises(InputError, match="nan.h5: transform contains NaN or infinite values"):
        transform_pieces(path)
    with pytest.raises(InputError, match="nan.h5: transform contains NaN or infinite values"):
        transform_pieces([str(path)])


@pytest.mark.parametrize("dim", [2, 3])
def test_displacement_array_is_itks_sampling(tmp_path, dim):
    """The compiled sampling of pieces equals ITK's TransformToDisplacementField on an
    oblique, anisotropic grid that the fields do not cover; a B-spline goes through ITK."""
    rng = np.random.default_rng(dim)
    q, _ = np.linalg.qr(rng.normal(size=(dim, dim)))
    grid = Geometry(
        (17, 12, 9)[:dim], (0.7, 1.3, 1.1)[:dim], tuple(rng.uniform(-8, -4, dim)), tuple(q.ravel())
    )
    for name, t in _transforms(dim).items():
        reference = sitk.GetArrayFromImage(displacement_field(t, grid))
        got = displacement_array(leaves(t), grid)
        assert got.shape == (*grid.shape, dim)
        np.testing.assert_allclose(got, reference, rtol=0, atol=1e-11, err_msg=name)
    bspline = sitk.BSplineTransformInitializer(sitk.Image([8] * dim, sitk.sitkFloat32), [3] * dim)
    bspline.SetParameters(rng.normal(scale=0.5, size=len(bspline.GetParameters())).tolist())
    mixed = sitk.CompositeTransform([_affine(dim, 9), bspline])
    assert np.array_equal(
        displacement_array(leaves(mixed), grid),
        sitk.GetArrayFromImage(displacement_field(mixed, grid)),
    )


@pytest.mark.parametrize("dim", [2, 3])
def test_pieces_are_their_transform_not_a_chain(dim):
    t = _transforms(dim)["three"]
    points = _random_points(dim, 500)
    reference = PointwiseInverse(t, field_step=2, refine_steps=4).map_points(points)
    pieces = transform_pieces(t)
    assert isinstance(pieces, TransformPieces)
    ours = PointwiseInverse(pieces, field_step=2, refine_steps=4).map_points(points)
    assert np.array_equal(ours, reference)
    # a plain list is a chain in ANTs order: the pieces' order reversed, another map
    chained = PointwiseInverse(list(pieces), field_step=2, refine_steps=4).map_points(points)
    assert not np.allclose(chained, reference)
    assert transform_pieces(pieces) is pieces
    assert chain_transform(pieces).TransformPoint(points[0].tolist()) == t.TransformPoint(
        points[0].tolist()
    )


@pytest.mark.parametrize("frame_kind", ["identity", "field"])
def test_a_chain_of_files_is_measured_as_its_transform(tmp_path, frame_kind):
    """evaluate's measures task reads an image's chain ([affine .mat, affine + field .h5])
    as pieces: its coverage, affine fit and Jacobian must be those of the chain's own
    transform, sampled by ITK (the pieces in another order are another map). F is the
    identity, or a zero field from the cache (the path of a registration not in the common
    frame); the grid is oblique, anisotropic, and the image covers only part of it."""
    from itk_nrreval._pipeline import _image_tasks, _tasks
    from itk_nrreval.io._cache import DiskCache
    from itk_nrreval.io.plausibility import affine_fit

    rng = np.random.default_rng(3)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    grid = Geometry((14, 11, 9), (1.1, 0.9, 1.3), (-7.0, -5.0, -6.0), tuple(q.ravel()))
    image = sitk.GetImageFromArray(rng.uniform(size=(12, 12, 12)).astype(np.float32))
    image.SetSpacing((1.2, 1.0, 0.9))
    image.SetOrigin((-16.0, -14.0, -4.0))
    image_path = tmp_path / "image.nii.gz"
    sitk.WriteImage(image, str(image_path))
    h5, mat = tmp_path / "t.h5", tmp_path / "error.mat"
    sitk.WriteTransform(_transforms(3)["composite"], str(h5))
    sitk.WriteTransform(_affine(3, 12), str(mat))
    item = [str(mat), str(h5)]  # ANTs order: the .mat acts first
    frame = ("identity",)
    if frame_kind == "field":
        zero = {"disp": np.zeros((*grid.shape, 3), np.float32)}
        DiskCache(tmp_path / "cache").put("frame", "zero", zero)
        frame = ("field", "zero")
    task = _image_tasks.MeasureTransform(
        grid=grid,
        mask_key=None,
        image=image_path,
        item=item,
        frame=frame,
        frame_digest=frame_kind,
        reg_grid=grid,
        reg_mask_key=None,
        inverse_consistency=True,
    )
    _key, meta, reused = _tasks.run_cached(str(tmp_path / "cache"), task)
    assert not reused
    reference = chain_transform(item)
    ones = sitk.Image(image.GetSize(), sitk.sitkFloat32) + 1.0
    ones.CopyInformation(image)
    inside = sitk.GetArrayFromImage(
        sitk.Resample(
            ones, list(grid.size), reference, sitk.sitkLinear, grid.origin, grid.spacing,
            grid.direction, 0.0, sitk.sitkFloat32,
        )
    )  # fmt: skip
    assert 0.05 < (inside > 0).mean() < 0.95  # partly covered: the test can tell
    assert meta["coverage"] == float((inside > 0).mean())
    fit = affine_fit(reference, grid).to_dict()
    for name, value in fit.items():
        np.testing.assert_allclose(meta["affine_fit"][name], value, rtol=1e-9, atol=1e-9)
    u = sitk.GetArrayFromImage(displacement_field(reference, grid))
    from itk_nrreval.io.transforms import jacobian_determinant

    det = jacobian_determinant(u, spacing=grid.spacing, direction=grid.direction)
    assert meta["plausibility"]["jacobian_min"] == pytest.approx(det.min(), rel=1e-9)
    assert meta["plausibility"]["jacobian_max"] == pytest.approx(det.max(), rel=1e-9)
    # the round trip through the numerical inverse, of the composite ITK built
    from itk_nrreval.io.plausibility import deformation_measures

    own = deformation_measures(reference, grid).plausibility.inverse_consistency_mm
    assert meta["plausibility"]["inverse_consistency_mm"] == pytest.approx(own, rel=1e-9)


@pytest.mark.parametrize("dim", [2, 3])
def test_the_transform_from_the_common_frame_as_pieces(dim):
    """resampling_transform given T's pieces: the same map as given T, as pieces (F last),
    and the same rule: F the identity is left out only when T is not linear."""
    from itk_nrreval.io.frame import resampling_transform

    points = _random_points(dim)
    identity = sitk.TranslationTransform(dim)
    field_frame = sitk.DisplacementFieldTransform(_oblique_field(dim, (8, 6, 5)[:dim], 21))
    for name, t in _transforms(dim).items():
        pieces = transform_pieces(t)
        for frame in (identity, field_frame):
            ours = resampling_transform(pieces, frame)
            reference = resampling_transform(t, frame)
            assert isinstance(ours, TransformPieces)
            left_out = frame is identity and not t.IsLinear()
            assert (ours is pieces) == left_out == (reference is t), (name, frame)
            assert [flatten(ours).TransformPoint(p.tolist()) for p in points] == [
                reference.TransformPoint(p.tolist()) for p in points
            ], (name, frame)
