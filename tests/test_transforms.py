"""Transforms: reading (incl. ANTs files), chain order, inversion, Jacobian, writing.

References are computed here independently with numpy from the known matrices and fields.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap

import nibabel as nib
import numpy as np
import pytest
import SimpleITK as sitk

from itk_nrreval import InputError
from itk_nrreval.io import frame
from itk_nrreval.io.frame import resample_images
from itk_nrreval.io.transforms import (
    chain_transform,
    field_transform,
    folded_fraction,
    invert,
    jacobian_determinant,
    read_transform,
    write_transform,
)


def grid(dim: int, n: int = 20, spacing=None, origin=None) -> sitk.Image:
    size = [n + 3 * k for k in range(dim)]  # non-cubic, to catch axis-order mistakes
    img = sitk.Image(size, sitk.sitkFloat32)
    img.SetSpacing(spacing or [1.0 + 0.25 * k for k in range(dim)])
    img.SetOrigin(origin or [-5.0 + 3.0 * k for k in range(dim)])
    return img


def physical_points(img: sitk.Image) -> np.ndarray:
    """Voxel-centre positions, numpy shape (*spatial_zyx, dim), (x, y, z) last (identity dir)."""
    idx = np.indices(img.GetSize()[::-1])[::-1]  # x index first
    sp, org = np.array(img.GetSpacing()), np.array(img.GetOrigin())
    return np.moveaxis(idx, 0, -1) * sp + org


def smooth_field(img: sitk.Image, amplitude: float = 1.5) -> np.ndarray:
    """A smooth displacement (mm), numpy (*spatial_zyx, dim), vanishing at the border."""
    dim = img.GetDimension()
    shape = img.GetSize()[::-1]
    rel = [np.linspace(0, 1, s) for s in shape[::-1]]  # per ITK axis
    mesh = np.meshgrid(*rel[::-1], indexing="ij")[::-1]  # ITK-ordered list of arrays
    bump = np.prod([np.sin(np.pi * m) for m in mesh], axis=0)
    u = np.stack(
        [amplitude * bump * np.cos(2 * np.pi * (c + 1) * mesh[c] / 3) for c in range(dim)], axis=-1
    )
    return u


def field_image(u: np.ndarray, like: sitk.Image) -> sitk.Image:
    f = sitk.GetImageFromArray(u, isVector=True)
    f.CopyInformation(like)
    return f


def affine(dim: int) -> tuple[sitk.AffineTransform, np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(dim)
    m = np.eye(dim) + 0.1 * rng.standard_normal((dim, dim))
    t = rng.standard_normal(dim)
    c = rng.standard_normal(dim)
    a = sitk.AffineTransform(dim)
    a.SetMatrix(m.ravel().tolist())
    a.SetTranslation(t.tolist())
    a.SetCenter(c.tolist())
    return a, m, t, c


def apply_affine(p: np.ndarray, m, t, c) -> np.ndarray:
    """ITK affine: A(p) = M (p - c) + c + t."""
    return (p - c) @ m.T + c + t


@pytest.mark.parametrize("dim", [2, 3])
def test_ants_chain_is_affine_of_warp(tmp_path, dim):
    ref = grid(dim, 12)
    u = smooth_field(ref)
    a, m, t, c = affine(dim)
    sitk.WriteTransform(a, str(tmp_path / "x_0GenericAffine.mat"))
    sitk.WriteImage(
        sitk.Cast(field_image(u, ref), sitk.sitkVectorFloat32), str(tmp_path / "x_1Warp.nii.gz")
    )
    chain = chain_transform([tmp_path / "x_1Warp.nii.gz", tmp_path / "x_0GenericAffine.mat"])
    p = physical_points(ref)
    expected = apply_affine(p + u, m, t, c)  # affine(warp(p)) at voxel centres: no interpolation
    pts = p.reshape(-1, dim)[::7]
    got = np.array([chain.TransformPoint(q.tolist()) for q in pts])
    np.testing.assert_allclose(got, expected.reshape(-1, dim)[::7], atol=1e-4)  # float32 file
    # the other order gives a different map: the test can tell the two apart
    wrong = apply_affine(p, m, t, c)
    assert np.abs(got - wrong.reshape(-1, dim)[::7] - u.reshape(-1, dim)[::7]).max() > 0.05


def test_ants_5d_warp_nifti(tmp_path):
    """ANTs writes warps as 5D NIfTI (X, Y, Z, 1, 3), LPS vector components."""
    ref = grid(3, 8)
    u = smooth_field(ref)  # (z, y, x, 3), LPS
    data = np.transpose(u, (2, 1, 0, 3))[:, :, :, None, :].astype(np.float32)  # (X, Y, Z, 1, 3)
    itk_affine = np.eye(4)
    itk_affine[:3, :3] = np.diag(ref.GetSpacing())
    itk_affine[:3, 3] = ref.GetOrigin()
    nifti = nib.Nifti1Image(data, np.diag([-1.0, -1.0, 1.0, 1.0]) @ itk_affine)
    nifti.header.set_intent("vector")
    nib.save(nifti, str(tmp_path / "s00_1Warp.nii.gz"))
    t = read_transform(tmp_path / "s00_1Warp.nii.gz")
    assert isinstance(t, sitk.DisplacementFieldTransform)
    assert t.GetDisplacementField().GetPixelID() == sitk.sitkVectorFloat64
    p = physical_points(ref)
    for idx in [(1, 2, 3), (4, 5, 6), (7, 3, 2)]:  # (z, y, x)
        got = np.array(t.TransformPoint(p[idx].tolist()))
        np.testing.assert_allclose(got, p[idx] + u[idx], atol=1e-5)


@pytest.mark.parametrize("dim", [2, 3])
def test_affine_and_field_chain_recovers_image(dim):
    """Resampling through [warp, affine] gives g(affine(warp(p))) to interpolation accuracy."""
    ref = grid(dim, 24 if dim == 2 else 16)
    u = smooth_field(ref, amplitude=1.0)
    a, m, t, c = affine(dim)
    # moving image: an analytic smooth function g sampled on its own, larger grid
    mov = grid(dim, 60, spacing=[0.8] * dim, origin=[-12.0] * dim)
    centre = np.array(ref.GetOrigin()) + 0.5 * np.array(ref.GetSize()) * np.array(ref.GetSpacing())

    def g(q):
        return np.exp(-np.sum((q - centre) ** 2, axis=-1) / (2 * 5.0**2))

    mov_img = sitk.GetImageFromArray(g(physical_points(mov)))
    mov_img.CopyInformation(mov)
    chain = chain_transform([field_transform(field_image(u, ref)), a])
    got = resample_images([mov_img], [chain], ref, progress=False)[0]
    q = apply_affine(physical_points(ref) + u, m, t, c)
    expected = g(q)
    vox = (q - np.array(mov.GetOrigin())) / 0.8
    inside = np.all((vox >= 0) & (vox <= np.array(mov.GetSize()) - 1), axis=-1)
    assert inside.mean() > 0.95
    # (multi)linear interpolation error <= sum over axes of h^2/8 max|d2g/dx2| (= 1/sigma^2)
    bound = dim * 0.8**2 / 8 / 5.0**2
    np.testing.assert_allclose(got[inside], expected[inside], atol=bound)
    assert np.all(got[~inside] < expected[~inside] + bound)  # zero outside the moving image
    assert np.ptp(expected) > 0.3  # the image has content


@pytest.mark.parametrize("dim", [2, 3])
def test_field_inverse_round_trip(dim):
    ref = grid(dim, 24 if dim == 2 else 14)
    u = smooth_field(ref, amplitude=1.0)  # up to ~1 voxel, min Jacobian ~0.6
    t = field_transform(field_image(u, ref))
    ti = invert(t)
    assert isinstance(ti, sitk.DisplacementFieldTransform)
    p = physical_points(ref).reshape(-1, dim)
    sp = np.array(ref.GetSpacing())
    for q in p[:: 3 if dim == 2 else 7]:
        back = np.array(ti.TransformPoint(t.TransformPoint(q.tolist())))
        assert np.all(np.abs(back - q) / sp < 0.05)


@pytest.mark.parametrize("dim", [2, 3])
def test_bspline_in_a_chain_is_inverted_on_the_given_grid(dim):
    ref = grid(dim, 24 if dim == 2 else 14)
    bspline = sitk.BSplineTransformInitializer(ref, [3] * dim)
    rng = np.random.default_rng(dim)
    # Small smooth coefficients (mm): the map stays well inside invertibility.
    bspline.SetParameters((0.6 * rng.standard_normal(bspline.GetNumberOfParameters())).tolist())
    a, *_ = affine(dim)
    chain = sitk.CompositeTransform([a, bspline])  # a(bspline(p))
    with pytest.raises(InputError, match="BSplineTransform.*without a grid"):
        invert(chain)
    inv = invert(chain, grid=ref)
    sp = np.array(ref.GetSpacing())
    inner = physical_points(ref)[(slice(3, -3),) * dim].reshape(-1, dim)
    for p in inner[:: 5 if dim == 2 else 23]:
        back = np.array(inv.TransformPoint(chain.TransformPoint(p.tolist())))
        assert np.all(np.abs(back - p) / sp < 0.05), (p, back)


@pytest.mark.parametrize("dim", [2, 3])
def test_affine_inverse_exact_and_chain_inverse(dim):
    ref = grid(dim, 16)
    a, m, t, c = affine(dim)
    ai = invert(a)
    q = np.array([1.5, -2.0, 0.5][:dim])
    expected = np.linalg.solve(m, q - c - t) + c  # A^-1(q) from A(p) = M (p - c) + c + t
    np.testing.assert_allclose(ai.TransformPoint(q.tolist()), expected, atol=1e-10)
    u = smooth_field(ref, amplitude=1.0)
    chain = [field_transform(field_image(u, ref)), a]
    inv = invert(chain)
    fwd = chain_transform(chain)
    for p in physical_points(ref).reshape(-1, dim)[::17]:
        back = np.array(inv.TransformPoint(fwd.TransformPoint(p.tolist())))
        np.testing.assert_allclose(back, p, atol=0.05)


def test_jacobian_of_linear_field_with_direction_and_spacing():
    """u(x) = B x has Jacobian det(I + B) everywhere, whatever the grid's orientation."""
    rng = np.random.default_rng(1)
    b = 0.2 * rng.standard_normal((3, 3))
    theta = 0.4
    d = np.array([[np.cos(theta), -np.sin(theta), 0], [np.sin(theta), np.cos(theta), 0], [0, 0, 1]])
    spacing = np.array([0.8, 1.3, 2.0])
    idx = np.moveaxis(np.indices((5, 6, 7))[::-1], 0, -1)  # (z, y, x, 3) with x index first
    x = (idx * spacing) @ d.T
    u = x @ b.T
    det = jacobian_determinant(u, spacing=spacing, direction=d.ravel())
    np.testing.assert_allclose(det, np.linalg.det(np.eye(3) + b), rtol=1e-10)


def _reference_jacobian_determinant(u, spacing, direction):
    """det(I + du/dx) by np.gradient (central inside, one-sided at the border; 0 along an
    axis of one node) and LU."""
    dim = u.shape[-1]
    index_per_mm = np.linalg.inv(np.asarray(direction).reshape(dim, dim) @ np.diag(spacing))
    jac = np.zeros((*u.shape[:-1], dim, dim))
    for k in range(dim):  # ITK index axis k is numpy axis dim - 1 - k
        if u.shape[dim - 1 - k] > 1:
            jac[..., k] = np.gradient(u, axis=dim - 1 - k)
    return np.linalg.det(np.eye(dim) + jac @ index_per_mm)


@pytest.mark.parametrize("shape", [(7, 9, 11), (2, 5, 4), (13, 6), (1, 5, 4), (6, 1), (3, 1, 4)])
def test_jacobian_determinant_of_a_rough_field_on_an_oblique_grid(shape):
    # Issue 30: det J comes from one compiled pass over the field (1 mm: 2.4 s -> 0.3 s);
    # on a rough random field on an oblique, anisotropic grid, borders and an axis of two
    # nodes included, it is np.gradient's and LU's to rounding. Axes of one node (a slab of
    # one plane) have no derivative.
    dim = len(shape)
    rng = np.random.default_rng(3)
    u = 0.7 * rng.standard_normal((*shape, dim))
    theta = 0.5
    rotation = np.eye(dim)
    rotation[:2, :2] = [[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]]
    spacing = np.array([0.8, 1.3, 2.0][:dim])
    det = jacobian_determinant(u, spacing=spacing, direction=rotation.ravel())
    expected = _reference_jacobian_determinant(u, spacing, rotation.ravel())
    assert (expected <= 0).any() and (expected > 0).any()  # folds and does not
    np.testing.assert_allclose(det, expected, rtol=1e-12, atol=1e-12)


def test_folded_fraction():
    ref = grid(2, 20)
    # reflection in x inside the grid: u_x = -2 x => det = -1 everywhere
    p = physical_points(ref)
    u = np.zeros_like(p)
    u[..., 0] = -2 * p[..., 0]
    assert folded_fraction(field_transform(field_image(u, ref)), ref) == 1.0
    assert folded_fraction(field_transform(field_image(smooth_field(ref), ref)), ref) == 0.0
    # fold only where x > 0: u_x = -2 x for x > 0 (det -1 there, 1 elsewhere)
    u[..., 0] = np.where(p[..., 0] > 0, -2 * p[..., 0], 0.0)
    frac = folded_fraction(field_transform(field_image(u, ref)), ref)
    inside = np.mean(p[..., 0] > 0)
    assert abs(frac - inside) <= 2 / ref.GetSize()[0]  # one column of finite-difference blur


def test_write_nested_composite_round_trip(tmp_path):
    ref = grid(3, 8)
    a, *_ = affine(3)
    nested = sitk.CompositeTransform(
        [
            sitk.CompositeTransform([a, sitk.TranslationTransform(3, (1.0, 2.0, 3.0))]),
            field_transform(field_image(smooth_field(ref), ref)),
        ]
    )
    path = write_transform(nested, tmp_path / "chain.h5")
    back = read_transform(path)
    for p in physical_points(ref).reshape(-1, 3)[::31]:
        np.testing.assert_allclose(
            back.TransformPoint(p.tolist()), nested.TransformPoint(p.tolist()), atol=1e-9
        )
    assert not list(tmp_path.glob(".*tmp*"))


def test_read_errors(tmp_path):
    with pytest.raises(InputError, match=r"missing\.tfm: transform file not found"):
        read_transform(tmp_path / "missing.tfm")
    (tmp_path / "t.xyz").write_text("x")
    with pytest.raises(InputError, match=r"t\.xyz: unknown transform format '\.xyz'"):
        read_transform(tmp_path / "t.xyz")
    (tmp_path / "bad.tfm").write_text("not a transform\n")
    with pytest.raises(InputError, match=r"bad\.tfm: cannot read transform"):
        read_transform(tmp_path / "bad.tfm")
    sitk.WriteImage(sitk.Image([4, 4], sitk.sitkFloat32), str(tmp_path / "scalar.nii.gz"))
    with pytest.raises(InputError, match=r"scalar\.nii\.gz: displacement field: 1 components"):
        read_transform(tmp_path / "scalar.nii.gz")


@pytest.mark.parametrize("dim", [2, 3])
def test_field_inverse_is_right_where_the_field_maps_points_off_its_own_grid(dim):
    """A field that moves points off its own grid is still inverted there (issue 15, item 5).

    A 12 mm shift plus a smooth wobble on an oblique, anisotropic 40-voxel grid: T(p) leaves
    the grid for every p within 12 mm of its far edge. The inverse must bring every T(p) back
    to p, including those -- the inverse computed on the forward field's own grid returned
    T(p) unchanged there (identity outside the grid).
    """
    n = 40 if dim == 2 else 30
    ref = grid(dim, n, spacing=[1.0, 1.6, 1.3][:dim], origin=[4.0, -7.0, 2.0][:dim])
    theta = 0.5
    rot = np.eye(dim)
    rot[:2, :2] = [[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]]
    ref.SetDirection(rot.ravel().tolist())
    shift = 12.0 * rot[:, 0]  # along the grid's first axis, in mm
    wobble = smooth_field(ref, amplitude=1.0)  # numpy (*zyx, dim); array layout only
    u = wobble + shift
    t = field_transform(field_image(u, ref))
    ti = invert(t)
    idx = np.stack(np.meshgrid(*[np.arange(s) for s in ref.GetSize()], indexing="ij"), -1)
    idx = idx.reshape(-1, dim)[::7]
    far = 0
    for i in idx:
        p = np.array(ref.TransformIndexToPhysicalPoint([int(v) for v in i]))
        q = t.TransformPoint(p.tolist())
        inside = np.array(ref.TransformPhysicalPointToContinuousIndex(q))
        far += bool(np.any(inside > np.array(ref.GetSize()) - 0.5))
        back = np.array(ti.TransformPoint(q))
        assert np.linalg.norm(back - p) < 0.05, (p, q, back)
    assert far > len(idx) // 5  # many of the checked points did leave the grid


def test_inverting_a_field_leaves_it_as_it_was():
    # Issue 30: invert() hands the inverse it computes to its transform without a copy; the
    # field it inverts, which the caller still holds, must keep its values.
    ref = grid(3, 8)
    t = field_transform(field_image(smooth_field(ref, amplitude=1.0), ref))
    before = sitk.GetArrayFromImage(t.GetDisplacementField())
    for step in (1, 2):
        inverse = invert(t, field_step=step)
        np.testing.assert_array_equal(sitk.GetArrayFromImage(t.GetDisplacementField()), before)
        p = physical_points(ref).reshape(-1, 3)[40]
        back = inverse.TransformPoint(t.TransformPoint(p.tolist()))
        np.testing.assert_allclose(back, p, atol=0.05)


_READ_FROM_THREADS = textwrap.dedent(
    """
    import sys, threading
    import SimpleITK as sitk
    from itk_nrreval.io._cache import content_digest
    from itk_nrreval.io.transforms import chain_transform

    path = sys.argv[1]
    field = sitk.DisplacementFieldTransform(sitk.Image([20, 20, 20], sitk.sitkVectorFloat64, 3))
    sitk.WriteTransform(sitk.CompositeTransform([sitk.AffineTransform(3), field]), path)
    errors = []

    def read():
        try:
            for _ in range(50):
                chain_transform(path)
                content_digest(path)
        except Exception as exc:
            errors.append(repr(exc))

    threads = [threading.Thread(target=read) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    print("done", errors)
    """
)


def test_hdf5_transforms_read_from_threads(tmp_path):
    # ITK's HDF5 library is not thread-safe: four threads reading one .h5 transform ended the
    # process ("double free or corruption"; "HDF5: infinite loop closing library" when
    # evaluate's tasks ran on two threads). Every SimpleITK read takes one lock.
    done = subprocess.run(
        [sys.executable, "-c", _READ_FROM_THREADS, str(tmp_path / "t.h5")],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-500:]
    assert done.stdout.strip() == "done []"


def test_a_transform_file_changed_to_nan_after_a_first_read_is_refused(tmp_path):
    # A file once found finite is not taken apart again to check it (issue 30: that copies
    # every field), but only while it is unchanged: rewritten with a NaN, it is refused.
    from itk_nrreval.io.transforms import read_transform

    field = sitk.Image([6, 5, 4], sitk.sitkVectorFloat64, 3)
    values = sitk.GetArrayFromImage(field)  # the transform takes the image's buffer
    path = tmp_path / "t.h5"
    sitk.WriteTransform(
        sitk.CompositeTransform([sitk.AffineTransform(3), sitk.DisplacementFieldTransform(field)]),
        str(path),
    )
    assert read_transform(path).GetNumberOfTransforms() == 2
    assert read_transform(path).GetNumberOfTransforms() == 2  # the second read: remembered
    values[2, 3, 1, 0] = np.nan
    bad = sitk.GetImageFromArray(values, isVector=True)
    sitk.WriteTransform(
        sitk.CompositeTransform([sitk.AffineTransform(3), sitk.DisplacementFieldTransform(bad)]),
        str(path),
    )
    with pytest.raises(InputError, match="t.h5: transform contains NaN or infinite values"):
        read_transform(path)


def test_a_chain_is_built_in_place_without_touching_the_callers_transforms(tmp_path):
    # chain_transform grows the composite it read from the last file in place (issue 30);
    # a composite the caller passed is copied, never changed, and the map is the chain's.
    from itk_nrreval.io.transforms import chain_transform, leaves

    first = sitk.Euler3DTransform((1.0, 2.0, 0.0), 0.1, -0.2, 0.3, (2.0, -1.0, 0.5))
    field = sitk.Image([8, 7, 6], sitk.sitkVectorFloat64, 3)
    field.SetSpacing((1.5, 0.8, 1.2))
    field.SetOrigin((-3.0, -2.0, -4.0))
    values = np.random.default_rng(4).normal(0.0, 0.7, (6, 7, 8, 3))
    shifted = sitk.GetImageFromArray(values, isVector=True)
    shifted.CopyInformation(field)
    last = sitk.CompositeTransform(
        [sitk.ScaleTransform(3, (1.1, 0.9, 1.05)), sitk.DisplacementFieldTransform(shifted)]
    )
    path = tmp_path / "last.h5"
    sitk.WriteTransform(last, str(path))
    points = [(0.3, -1.2, 0.4), (2.0, 1.0, -1.5), (-2.5, 0.5, 1.0)]
    expected = [last.TransformPoint(first.TransformPoint(p)) for p in points]
    for given in (path, last):
        chain = chain_transform([first, given])
        assert [t.GetName() for t in leaves(chain)] == [
            "ScaleTransform",
            "DisplacementFieldTransform",
            "Euler3DTransform",
        ]
        np.testing.assert_allclose([chain.TransformPoint(p) for p in points], expected, atol=1e-12)
    assert last.GetNumberOfTransforms() == 2  # the caller's composite is unchanged


def _oblique(size, spacing, origin, angle: float) -> sitk.Image:
    """An empty image on an oblique grid (rotated by `angle` about a skew axis in 3D)."""
    img = sitk.Image(list(size), sitk.sitkFloat32)
    img.SetSpacing(spacing)
    img.SetOrigin(origin)
    if len(size) == 2:
        c, s = np.cos(angle), np.sin(angle)
        img.SetDirection([c, -s, s, c])
    else:
        axis = np.array([1.0, 2.0, 0.5]) / np.linalg.norm([1.0, 2.0, 0.5])
        k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        rot = np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k
        img.SetDirection(rot.ravel().tolist())
    return img


@pytest.mark.parametrize("dim", [2, 3])
def test_displacement_after_equals_itk_sampling_the_composite(dim):
    """T o D without the composite: ITK's own sampling of CompositeTransform([T, D]), where T
    is an affine after a field after an affine (fields on oblique, anisotropic grids that do
    not cover the whole common grid, so points fall in their half-voxel borders and beyond)
    and D a rough field on the common grid."""
    from itk_nrreval.io._images import Geometry
    from itk_nrreval.io.transforms import displacement_after, leaves

    rng = np.random.default_rng(dim)
    n = (23, 19, 11)[:dim]
    common = _oblique(n, [1.2, 0.9, 1.7][:dim], [3.0, -4.0, 2.0][:dim], 0.3)
    g = Geometry.from_image(common)
    # rough (neighbouring voxels move apart), and exact in float32, as the cache holds frames
    d = rng.normal(0.0, 1.5, (*n[::-1], dim)).astype(np.float32).astype(np.float64)
    on_common = field_transform(field_image(d, common))
    grid_t = _oblique([k - 6 for k in n], [1.1, 1.3, 0.8][:dim], [5.0, -2.0, 3.5][:dim], -0.5)
    u = rng.normal(0.0, 2.0, (*grid_t.GetSize()[::-1], dim))
    first, _, _, _ = affine(dim)
    last = sitk.AffineTransform(dim)
    last.SetTranslation(rng.normal(0.0, 3.0, dim).tolist())
    t = chain_transform([first, field_transform(field_image(u, grid_t)), last])
    expected = sitk.GetArrayFromImage(
        sitk.TransformToDisplacementField(
            sitk.CompositeTransform([t, on_common]),
            sitk.sitkVectorFloat64,
            common.GetSize(),
            common.GetOrigin(),
            common.GetSpacing(),
            common.GetDirection(),
        )
    )
    got = displacement_after(t, d, g)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-11)
    # points beyond the field's buffer (the identity there) and in its border both occur
    ends = sitk.CompositeTransform([first, on_common])
    moved = np.array([ends.TransformPoint(p) for p in _voxel_points(common)])
    cidx = np.array([grid_t.TransformPhysicalPointToContinuousIndex(p) for p in moved])
    size = np.array(grid_t.GetSize())
    outside = ((cidx < -0.5) | (cidx >= size - 0.5)).any(axis=1)
    border = ~outside & ((cidx < 0) | (cidx > size - 1)).any(axis=1)
    assert outside.mean() > 0.1 and border.sum() > 5
    np.testing.assert_array_equal(displacement_after(t, d.astype(np.float32), g), got)
    # given T's pieces (taken apart once by the caller), the same bits
    pieces = leaves(t)
    assert len(pieces) == 3 and leaves(pieces) == pieces
    assert all(a is b for a, b in zip(leaves(pieces), pieces, strict=True))
    np.testing.assert_array_equal(displacement_after(pieces, d, g), got)


@pytest.mark.parametrize("dim", [2, 3])
def test_composed_displacement_from_pieces_equals_itks_sampling(dim):
    """``R^-1(C(p)) - p`` with C given as its pieces (sampled by the compiled kernels, as
    frame estimates are) or as a transform (sampled by ITK): the same to 1e-11 mm, for C an
    affine after a field on an oblique, anisotropic grid that does not cover the common
    one, and R a field after an affine (inverted numerically)."""
    from itk_nrreval.io._images import Geometry
    from itk_nrreval.io.frame import frame_estimate
    from itk_nrreval.io.transforms import PointwiseInverse, composed_displacement, leaves

    rng = np.random.default_rng(10 + dim)
    n = (21, 17, 9)[:dim]
    common = _oblique(n, [1.2, 0.9, 1.7][:dim], [3.0, -4.0, 2.0][:dim], 0.3)
    g = Geometry.from_image(common)
    grid_c = _oblique([k - 5 for k in n], [1.1, 1.3, 0.8][:dim], [5.0, -2.0, 3.5][:dim], -0.5)
    first, _, _, _ = affine(dim)
    c = chain_transform(
        [field_transform(field_image(rng.normal(0, 1.5, (*grid_c.GetSize()[::-1], dim)), grid_c)),
         first]
    )  # fmt: skip
    r = chain_transform(
        [first, field_transform(field_image(rng.normal(0, 0.3, (*n[::-1], dim)), common))]
    )
    inverse = PointwiseInverse(r, field_step=2, refine_steps=3)
    by_itk = composed_displacement(inverse, c, g)
    by_kernels = composed_displacement(inverse, leaves(c), g)
    assert by_kernels.shape == by_itk.shape == (*n[::-1], dim)
    np.testing.assert_allclose(by_kernels, by_itk, rtol=0, atol=1e-11)
    assert np.abs(by_itk).max() > 1.0  # not a trivial map
    # a frame estimate samples C by the kernels: the same as through ITK's sampling
    got = frame_estimate(c, r, g)
    ref = composed_displacement(
        PointwiseInverse(r, field_step=frame.ESTIMATE_FIELD_STEP,
                         refine_steps=frame.ESTIMATE_REFINE_STEPS), c, g
    )  # fmt: skip
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-11)


def _voxel_points(img: sitk.Image) -> list:
    return [
        img.TransformIndexToPhysicalPoint([int(i) for i in idx])
        for idx in np.ndindex(*img.GetSize())
    ]


def test_displacement_after_refuses_what_it_cannot_apply():
    from itk_nrreval.io._images import Geometry
    from itk_nrreval.io.transforms import displacement_after

    img = grid(2)
    g = Geometry.from_image(img)
    bspline = sitk.BSplineTransformInitializer(img, [3, 3])
    with pytest.raises(ValueError, match="neither linear nor a displacement field"):
        displacement_after(bspline, np.zeros((*g.shape, 2)), g)
    with pytest.raises(ValueError, match="not the grid's"):
        displacement_after(sitk.AffineTransform(2), np.zeros((3, 3, 2)), g)
