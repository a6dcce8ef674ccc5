"""Transforms from FSL, AFNI, FreeSurfer and NiftyReg, read into ITK's convention (issue 46).

Each format is checked against a reference that does not go through the reader under test:

- points mapped by hand from the format's documented convention (FSL's scaled-voxel
  coordinates with the x flip for positive-determinant grids, LTA's voxel-to-voxel and
  RAS-to-RAS matrices between its src and dst volumes, AFNI's DICOM matrices, FNIRT's
  relative displacements and premat);
- files the libraries write (nitransforms' FSL and AFNI writers, fslpy's FNIRT writer) and
  the tools themselves wrote (NiftyReg's reg_transform / reg_f3d output in tests/data/niftyreg,
  FreeSurfer's bbregister and lta_convert LTAs that nitransforms ships with its tests);
- the ITK reading (``sitk.ReadTransform``) of the same transform written as an ITK file.

Mapped points agree within 1e-4 mm, on oblique, anisotropic grids whose reference and moving
images lie 60-200 mm apart, in 2D where the format has it and in 3D.
"""

from __future__ import annotations

import math
import re
import warnings
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
import SimpleITK as sitk
import yaml

import itk_nrreval as nr
from itk_nrreval import InputError
from itk_nrreval.cli import main
from itk_nrreval.io._foreign_transforms import ForeignTransform
from itk_nrreval.io.manifest import load_manifest, write_manifest
from itk_nrreval.io.transforms import read_transform

nitransforms = pytest.importorskip("nitransforms")
pytest.importorskip("fsl.transform.fnirt")

DATA = Path(__file__).resolve().parent / "data" / "niftyreg"
D = np.diag([-1.0, -1.0, 1.0, 1.0])  # RAS <-> LPS
TOL = 1e-4  # mm


# ----------------------------------------------------------------------------- grids


def rotation(dim: int, angles) -> np.ndarray:
    if dim == 2:
        c, s = math.cos(angles[0]), math.sin(angles[0])
        return np.array([[c, -s], [s, c]])
    t = sitk.Euler3DTransform()
    t.SetRotation(*angles)
    return np.array(t.GetMatrix()).reshape(3, 3)


def write_grid(path: Path, size, spacing, origin, direction, *, values=None) -> Path:
    """An image file (SimpleITK's NIfTI, sform = qform) on the given ITK grid (LPS)."""
    dim = len(size)
    if values is None:
        rng = np.random.default_rng(len(str(path)))
        values = rng.random(tuple(reversed(size))).astype(np.float32)
    img = sitk.GetImageFromArray(values)
    img.SetSpacing([float(s) for s in spacing])
    img.SetOrigin([float(o) for o in origin])
    img.SetDirection(np.asarray(direction, float).reshape(dim * dim).tolist())
    sitk.WriteImage(img, str(path))
    return path


def grids(folder: Path, dim: int, *, ref_flip: bool, mov_flip: bool) -> tuple[Path, Path]:
    """A reference and a moving image on oblique, anisotropic grids some 150 mm apart; a
    flip makes the grid's determinant negative (radiological)."""
    if dim == 3:
        rd = rotation(3, (0.2, -0.1, 0.3)) @ np.diag([1, 1, -1 if ref_flip else 1])
        md = rotation(3, (-0.3, 0.25, 0.1)) @ np.diag([1, -1 if mov_flip else 1, 1])
        ref = write_grid(folder / "ref.nii.gz", (17, 14, 11), (1.2, 0.9, 1.5), (-30, 40, 12), rd)
        mov = write_grid(folder / "mov.nii.gz", (15, 16, 12), (0.8, 1.1, 1.3), (110, -60, 90), md)
    else:
        rd = rotation(2, (0.3,)) @ np.diag([1, -1 if ref_flip else 1])
        md = rotation(2, (-0.25,)) @ np.diag([-1 if mov_flip else 1, 1])
        ref = write_grid(folder / "ref.nii.gz", (21, 17), (1.2, 0.9), (-30, 40), rd)
        mov = write_grid(folder / "mov.nii.gz", (19, 23), (0.8, 1.1), (110, -60), md)
    return ref, mov


def known_affine(dim: int) -> np.ndarray:
    """Reference world -> moving world (RAS): rotation, anisotropic scaling, shear and a
    translation of about 150 mm."""
    t = np.eye(4)
    if dim == 3:
        t[:3, :3] = rotation(3, (0.15, -0.2, 0.25)) @ np.array(
            [[1.05, 0.03, 0.0], [0.0, 0.96, -0.02], [0.01, 0.0, 1.02]]
        )
        t[:3, 3] = (-150.0, 95.0, 80.0)
    else:
        t[:2, :2] = rotation(2, (0.2,)) @ np.array([[1.05, 0.03], [0.0, 0.96]])
        t[:2, 3] = (-150.0, 95.0)
    return t


def points(path: Path, n: int = 40, *, seed: int = 0) -> np.ndarray:
    """Physical points (LPS) at random continuous indices inside an image, shape (n, dim)."""
    img = sitk.ReadImage(str(path))
    size = np.array(img.GetSize(), float)
    idx = np.random.default_rng(seed).uniform(0, size - 1, (n, len(size)))
    return np.array([img.TransformContinuousIndexToPhysicalPoint(p.tolist()) for p in idx])


def mapped(transform: sitk.Transform, pts: np.ndarray) -> np.ndarray:
    return np.array([transform.TransformPoint(p.tolist()) for p in pts])


def lps_matrix_map(m_lps: np.ndarray, pts: np.ndarray) -> np.ndarray:
    dim = pts.shape[1]
    return pts @ m_lps[:dim, :dim].T + m_lps[:dim, 3]


def itk_file(folder: Path, ras: np.ndarray, dim: int) -> sitk.Transform:
    """The same RAS affine written as an ITK file (LPS) and read back by SimpleITK."""
    lps = D @ ras @ D
    t = sitk.AffineTransform(dim)
    t.SetMatrix(lps[:dim, :dim].ravel().tolist())
    t.SetTranslation(lps[:dim, 3].tolist())
    path = folder / "same.tfm"
    sitk.WriteTransform(t, str(path))
    return sitk.ReadTransform(str(path))


def fsl_scaled(img) -> np.ndarray:
    """FSL's voxel -> scaled-voxel matrix (FLIRT's coordinates), from the NIfTI header by
    FSL's documented rule: voxel index times pixdim, the first axis reversed where the
    voxel-to-world matrix has a positive determinant."""
    zooms = list(img.header.get_zooms()[:3]) + [1.0] * (3 - len(img.header.get_zooms()[:3]))
    s = np.diag([*zooms, 1.0])
    if np.linalg.det(img.affine) > 0:
        flip = np.eye(4)
        flip[0, 0], flip[0, 3] = -1, img.shape[0] - 1
        s = s @ flip
    return s


def to_ras_points(pts: np.ndarray) -> np.ndarray:
    """LPS points as homogeneous RAS points, shape (4, n) (2D points in the plane z = 0)."""
    out = np.zeros((4, len(pts)))
    out[: pts.shape[1]] = pts.T
    out[3] = 1
    return D @ out


# ----------------------------------------------------------------------------- FSL FLIRT


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("ref_flip,mov_flip", [(False, False), (True, False), (False, True)])
def test_flirt_matrix_maps_points_as_fsl_documents_it(tmp_path, dim, ref_flip, mov_flip):
    """A FLIRT matrix written by nitransforms from a known affine: the toolkit's reading maps
    reference points as FSL's scaled-voxel convention does by hand, and as the ITK file of
    the same affine does (1e-4 mm), in 2D (FLIRT's -2D) and 3D, for both determinant signs."""
    from nitransforms.io.fsl import FSLLinearTransform

    ref, mov = grids(tmp_path, dim, ref_flip=ref_flip, mov_flip=mov_flip)
    ras = known_affine(dim)
    ref_img, mov_img = nib.load(ref), nib.load(mov)
    (tmp_path / "s.mat").write_text(
        FSLLinearTransform.from_ras(ras, reference=ref_img, moving=mov_img).to_string()
    )
    ours = read_transform(ForeignTransform(tmp_path / "s.mat", "fsl", ref, mov))
    assert ours.GetDimension() == dim

    pts = points(ref)
    # by hand: reference world -> its voxel -> its scaled voxel; FLIRT's matrix goes from
    # the moving image's scaled voxels to the reference's, so its inverse; then -> world
    flirt = np.loadtxt(tmp_path / "s.mat")
    chain = (
        mov_img.affine
        @ np.linalg.inv(fsl_scaled(mov_img))
        @ np.linalg.inv(flirt)
        @ fsl_scaled(ref_img)
        @ np.linalg.inv(ref_img.affine)
    )
    by_hand = (D @ chain @ to_ras_points(pts))[:dim].T
    got = mapped(ours, pts)
    assert np.abs(got - by_hand).max() < TOL
    assert np.abs(got - mapped(itk_file(tmp_path, ras, dim), pts)).max() < TOL
    assert np.abs(lps_matrix_map(D @ ras @ D, pts) - got).max() < TOL


def test_flirt_matrix_agrees_with_fslpy(tmp_path):
    """FSL's own Python library reads the same FLIRT matrix to the same world mapping."""
    from fsl.data.image import Image
    from fsl.transform import flirt

    ref, mov = grids(tmp_path, 3, ref_flip=False, mov_flip=True)
    matrix = np.array(
        [
            [1.02, 0.05, -0.03, 4.0],
            [-0.04, 0.97, 0.02, -3.0],
            [0.01, -0.02, 1.05, 2.0],
            [0, 0, 0, 1],
        ]
    )
    np.savetxt(tmp_path / "s.mat", matrix)
    ours = read_transform(ForeignTransform(tmp_path / "s.mat", "fsl", ref, mov))
    world = flirt.fromFlirt(matrix, Image(str(mov)), Image(str(ref)), "world", "world")
    pts = points(ref)
    expected = (D @ np.linalg.inv(world) @ to_ras_points(pts))[:3].T
    assert np.abs(mapped(ours, pts) - expected).max() < TOL


# ----------------------------------------------------------------------------- AFNI


@pytest.mark.parametrize("oblique", [False, True])
def test_afni_matrix(tmp_path, oblique):
    """An AFNI matrix written by nitransforms. On plumb grids it is DICOM (LPS) base ->
    source as written, so the ITK matrix is its 12 numbers (by hand); on oblique grids the
    reading undoes AFNI's deobliquing as nitransforms writes it (the library's round trip:
    no independent reference for AFNI's obliquity is at hand)."""
    from nitransforms.io.afni import AFNILinearTransform

    if oblique:
        ref, mov = grids(tmp_path, 3, ref_flip=False, mov_flip=False)
    else:
        ref = write_grid(
            tmp_path / "ref.nii.gz", (17, 14, 11), (1.2, 0.9, 1.5), (-30, 40, 12), np.eye(3)
        )
        mov = write_grid(
            tmp_path / "mov.nii.gz",
            (15, 16, 12),
            (0.8, 1.1, 1.3),
            (110, -60, 90),
            np.diag([1, -1, 1]),
        )
    ras = known_affine(3)
    afni = AFNILinearTransform.from_ras(ras, reference=nib.load(ref), moving=nib.load(mov))
    # nitransforms prints six significant digits (0.2 um at 150 mm): the same numbers in full
    row = afni.structarr["parameters"][:3].ravel()
    (tmp_path / "s.aff12.1D").write_text(
        "# 3dAllineate matrix\n" + "\t".join(f"{v:.17g}" for v in row)
    )
    ours = read_transform(ForeignTransform(tmp_path / "s.aff12.1D", "afni", ref, mov))
    pts = points(ref)
    got = mapped(ours, pts)
    assert np.abs(got - mapped(itk_file(tmp_path, ras, 3), pts)).max() < TOL
    if not oblique:
        row = np.loadtxt(tmp_path / "s.aff12.1D", comments="#").reshape(3, 4)
        assert np.abs(got - (pts @ row[:, :3].T + row[:, 3])).max() < TOL


def test_afni_warp(tmp_path):
    """A 3dQwarp-style warp (5D NIfTI on the base grid, DICOM (LPS) displacements from base
    to source): read through nitransforms it maps p to p + d(p) (by hand; d linear in the
    voxel index, so interpolating it is exact), as ITK reads the same file (1e-4 mm)."""
    ref, _ = grids(tmp_path, 3, ref_flip=False, mov_flip=False)
    ref_img = nib.load(ref)
    shape = ref_img.shape
    idx = np.stack(np.meshgrid(*[np.arange(n, dtype=float) for n in shape], indexing="ij"), -1)
    slope = np.array([[0.3, -0.1, 0.05], [0.02, 0.2, -0.1], [-0.05, 0.1, 0.15]])
    disp = idx @ slope.T + np.array([3.0, -2.0, 1.5])  # mm, DICOM x, y, z
    warp = nib.Nifti1Image(disp[:, :, :, None, :].astype(np.float32), ref_img.affine)
    warp.header.set_intent("vector")
    warp.to_filename(tmp_path / "s_WARP.nii.gz")
    ours = read_transform(ForeignTransform(tmp_path / "s_WARP.nii.gz", "afni", ref, ref))
    pts = points(ref, seed=5)
    v = np.linalg.inv(ref_img.affine) @ to_ras_points(pts)
    expected = pts + v[:3].T @ slope.T + np.array([3.0, -2.0, 1.5])
    assert np.abs(mapped(ours, pts) - expected).max() < TOL
    plain = read_transform(tmp_path / "s_WARP.nii.gz")
    assert np.abs(mapped(ours, pts) - mapped(plain, pts)).max() < TOL


# ----------------------------------------------------------------------------- FreeSurfer LTA


def lta_text(kind: int, matrix: np.ndarray, src: Path, dst: Path) -> str:
    """An LTA as FreeSurfer writes it (type, the 4 x 4 matrix, then the src and dst volume
    geometry: size, voxel size, direction cosines and the RAS of the centre voxel)."""

    def volume(path: Path) -> list[str]:
        img = nib.load(path)
        shape = np.array(img.shape[:3])
        zooms = np.linalg.norm(img.affine[:3, :3], axis=0)
        cosines = img.affine[:3, :3] / zooms
        c_ras = img.affine @ np.r_[shape / 2, 1]
        return [
            "valid = 1  # volume info valid",
            f"filename = {path.name}",
            "volume = {} {} {}".format(*shape),
            "voxelsize = {:.15e} {:.15e} {:.15e}".format(*zooms),
            *(
                f"{a}ras   = {c[0]:.15e} {c[1]:.15e} {c[2]:.15e}"
                for a, c in zip("xyz", cosines.T, strict=True)
            ),
            "cras   = {:.15e} {:.15e} {:.15e}".format(*c_ras[:3]),
        ]

    lines = [
        "# transform file written by hand, as FreeSurfer writes it",
        f"type      = {kind} # {'LINEAR_VOX_TO_VOX' if kind == 0 else 'LINEAR_RAS_TO_RAS'}",
        "nxforms   = 1",
        "mean      = 0.0000 0.0000 0.0000",
        "sigma     = 10000.0000",
        "1 4 4",
        *(" ".join(f"{v:.15e}" for v in row) for row in matrix),
        "src volume info",
        *volume(src),
        "dst volume info",
        *volume(dst),
        "subject unknown",
        "fscale 0.100000",
        "",
    ]
    return "\n".join(lines)


@pytest.mark.parametrize("kind", [0, 1])
@pytest.mark.parametrize("src_is_moving", [True, False])
def test_lta_maps_src_to_dst_and_is_turned_by_its_volumes(tmp_path, kind, src_is_moving):
    """An LTA maps its src volume's points to its dst volume's (voxel-to-voxel, type 0, or
    RAS-to-RAS, type 1). Written by hand both ways round (src the moving image, as
    mri_robust_register --mov and bbregister write it, or the reference), it reads to the
    same reference -> moving mapping, which is the known affine (1e-4 mm)."""
    ref, mov = grids(tmp_path, 3, ref_flip=True, mov_flip=False)
    ras = known_affine(3)  # reference world -> moving world
    a_ref, a_mov = nib.load(ref).affine, nib.load(mov).affine
    src, dst, src_to_dst = (mov, ref, np.linalg.inv(ras)) if src_is_moving else (ref, mov, ras)
    a_src, a_dst = (a_mov, a_ref) if src_is_moving else (a_ref, a_mov)
    matrix = src_to_dst if kind == 1 else np.linalg.inv(a_dst) @ src_to_dst @ a_src
    (tmp_path / "s.lta").write_text(lta_text(kind, matrix, src, dst))
    ours = read_transform(ForeignTransform(tmp_path / "s.lta", "lta", ref, mov))
    pts = points(ref)
    got = mapped(ours, pts)
    # by hand, from the file's own numbers: the voxel-to-voxel matrix goes src -> dst
    if kind == 0:
        v = np.linalg.inv(matrix) if src_is_moving else matrix  # reference voxel -> moving voxel
        by_hand = a_mov @ v @ np.linalg.inv(a_ref)
    else:
        by_hand = np.linalg.inv(matrix) if src_is_moving else matrix
    assert np.abs(got - (D @ by_hand @ to_ras_points(pts))[:3].T).max() < TOL
    assert np.abs(got - mapped(itk_file(tmp_path, ras, 3), pts)).max() < TOL


REGRESSIONS = Path(nitransforms.__file__).parent / "tests" / "data" / "regressions"


def test_lta_written_by_freesurfer(tmp_path):
    """bbregister's voxel-to-voxel LTA and lta_convert's RAS-to-RAS copy of it (FreeSurfer's
    own output, shipped with nitransforms' tests) read to the same mapping, and to the ITK
    file shipped beside them, at points all over the dst (T1) volume (1e-4 mm)."""
    v2v = REGRESSIONS / "from-fsnative_to-bold_mode-image.lta"
    r2r = REGRESSIONS / "from-fsnative_to-bold_mode-image_type-ras2ras.lta"
    tfm = REGRESSIONS / "from-fsnative_to-bold_mode-image.tfm"
    if not (v2v.exists() and r2r.exists() and tfm.exists()):
        pytest.skip("nitransforms' test data (FreeSurfer's LTAs) is not installed")
    from nitransforms.io.lta import FSLinearTransformArray

    geometry = FSLinearTransformArray.from_filename(v2v).xforms[0]
    # the moving image: a NIfTI on the LTA's src grid (bbregister's --mov, the BOLD run)
    src = geometry["src"]
    shape = tuple(int(v) for v in src["volume"])
    nib.Nifti1Image(np.zeros(shape, np.uint8), src.as_affine()).to_filename(tmp_path / "bold.nii")
    dst = geometry["dst"]
    t1 = nib.Nifti1Image(np.zeros((8, 8, 8), np.uint8), dst.as_affine())  # a corner of T1w
    t1.to_filename(tmp_path / "t1.nii")
    a = read_transform(ForeignTransform(v2v, "lta", tmp_path / "t1.nii", tmp_path / "bold.nii"))
    b = read_transform(ForeignTransform(r2r, "lta", tmp_path / "t1.nii", tmp_path / "bold.nii"))
    idx = np.array([[0, 0, 0], [255, 255, 255], [128, 128, 128], [60, 200, 100], [255, 0, 30]])
    pts = (D @ dst.as_affine() @ np.c_[idx, np.ones(len(idx))].T)[:3].T
    assert np.abs(mapped(a, pts) - mapped(b, pts)).max() < TOL
    assert np.abs(mapped(a, pts) - mapped(sitk.ReadTransform(str(tfm)), pts)).max() < TOL


def test_lta_whose_volumes_are_not_the_moving_image_is_refused(tmp_path):
    ref, mov = grids(tmp_path, 3, ref_flip=False, mov_flip=False)
    other = write_grid(tmp_path / "other.nii.gz", (9, 9, 9), (1, 1, 1), (0, 0, 0), np.eye(3))
    (tmp_path / "s.lta").write_text(lta_text(1, np.eye(4), ref, other))
    with pytest.raises(InputError, match=r"s\.lta: its moving image .*mov\.nii\.gz is neither"):
        read_transform(ForeignTransform(tmp_path / "s.lta", "lta", ref, mov))


# ----------------------------------------------------------------------------- NiftyReg


def niftyreg(name: str, dim: int) -> ForeignTransform:
    return ForeignTransform(
        DATA / name, "niftyreg", DATA / f"ref{dim}.nii.gz", DATA / f"flo{dim}.nii.gz"
    )


@pytest.mark.parametrize("dim", [2, 3])
def test_niftyreg_affine_as_niftyreg_maps_points(dim):
    """reg_transform -makeAff's affine (reg_aladin's -aff format) maps reference world points
    (RAS) to floating world points: the toolkit's reading agrees with NiftyReg's own
    reg_transform -land (6 significant digits) off the voxel centres and with its -def field
    of the affine (float32) at every voxel centre, within 1e-4 mm, in 2D and 3D."""
    ours = read_transform(niftyreg(f"aff{dim}.txt", dim))
    assert isinstance(ours, sitk.AffineTransform) and ours.GetDimension() == dim
    lps = np.r_[-1.0, -1.0, 1.0][:dim]
    land = np.loadtxt(DATA / f"land{dim}.txt", ndmin=2)
    expected = np.loadtxt(DATA / f"land{dim}_aff.txt", ndmin=2)
    assert np.abs(mapped(ours, land * lps) * lps - expected).max() < TOL
    # every voxel centre, against reg_transform -def of the same affine
    field = nib.load(DATA / f"affdef{dim}.nii.gz")
    positions = np.asarray(field.dataobj, float)[..., 0, :].reshape(-1, dim)
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in field.shape[:dim]], indexing="ij"), -1)
    world = np.c_[
        idx.reshape(-1, dim), np.zeros((idx[..., 0].size, 3 - dim)), np.ones(positions.shape[0])
    ]
    centres = (D @ field.affine @ world.T)[:dim].T
    assert np.abs(mapped(ours, centres) * lps - positions).max() < TOL
    # and by hand: the text's matrix, RAS to RAS
    matrix = np.loadtxt(DATA / f"aff{dim}.txt")
    assert (
        np.abs(mapped(ours, land * lps) - lps_matrix_map(D @ matrix @ D, land * lps)).max() < 1e-9
    )


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("name", ["def", "disp"])
def test_niftyreg_fields_map_points_as_niftyreg(dim, name):
    """reg_transform -def (world positions) and -disp (displacements) of reg_f3d's
    control-point grid: read into ITK fields, they map points off the voxel centres as
    reg_transform -land maps them through the control-point grid itself (1e-4 mm)."""
    ours = read_transform(niftyreg(f"{name}{dim}.nii.gz", dim))
    assert isinstance(ours, sitk.DisplacementFieldTransform) and ours.GetDimension() == dim
    lps = np.r_[-1.0, -1.0, 1.0][:dim]
    land = np.loadtxt(DATA / f"land{dim}.txt", ndmin=2)
    expected = np.loadtxt(DATA / f"land{dim}_cpp.txt", ndmin=2)
    affine_only = np.loadtxt(DATA / f"land{dim}_aff.txt", ndmin=2)
    assert np.abs(expected - affine_only).max() > 0.05  # reg_f3d did deform
    assert np.abs(mapped(ours, land * lps) * lps - expected).max() < TOL


def test_niftyreg_control_point_grid_is_refused_naming_the_conversion():
    with pytest.raises(
        InputError,
        match=r"cpp3\.nii\.gz: a NiftyReg cubic B-spline control-point"
        r" grid, .*reg_transform -ref <reference> -def cpp3\.nii\.gz",
    ):
        read_transform(niftyreg("cpp3.nii.gz", 3))


# ----------------------------------------------------------------------------- FSL FNIRT


@pytest.mark.parametrize("ref_flip", [False, True])
def test_fnirt_displacement_field_by_hand(tmp_path, ref_flip):
    """A FNIRT relative displacement field written by hand (intent 2006, on the reference's
    grid): the source's scaled-voxel point is the reference's plus the displacement. fslpy's
    reading, converted to an ITK field, maps points off the voxel centres as that convention
    does by hand (the displacement is linear in the voxel index, so interpolating it is
    exact) (1e-4 mm)."""
    ref, mov = grids(tmp_path, 3, ref_flip=ref_flip, mov_flip=not ref_flip)
    ref_img, mov_img = nib.load(ref), nib.load(mov)
    # where the moving image's scaled voxels are, seen from the reference's: a known affine
    to_mov = np.linalg.inv(fsl_scaled(mov_img)) @ np.linalg.inv(mov_img.affine)
    start = to_mov @ known_affine(3) @ ref_img.affine  # reference voxel -> moving voxel
    shape = ref_img.shape
    idx = np.stack(np.meshgrid(*[np.arange(n, dtype=float) for n in shape], indexing="ij"), -1)
    hom = np.concatenate([idx, np.ones((*shape, 1))], -1)
    wobble = np.array([[0.02, -0.01, 0.03], [0.01, 0.02, 0.0], [-0.02, 0.01, 0.01]])
    target = (hom @ (fsl_scaled(mov_img) @ start).T)[..., :3] + idx @ wobble.T
    disp = target - (hom @ fsl_scaled(ref_img).T)[..., :3]  # FSL: source = reference + d
    field = nib.Nifti1Image(disp.astype(np.float32), ref_img.affine)
    field.header.set_intent(2006)  # FSL_FNIRT_DISPLACEMENT_FIELD
    field.to_filename(tmp_path / "warp.nii.gz")
    ours = read_transform(ForeignTransform(tmp_path / "warp.nii.gz", "fsl", ref, mov))
    assert isinstance(ours, sitk.DisplacementFieldTransform)
    # by hand, at points off the voxel centres (inside the grid)
    pts = points(ref, seed=3)
    v = np.linalg.inv(ref_img.affine) @ to_ras_points(pts)
    src_fsl = fsl_scaled(mov_img) @ start @ v
    src_fsl[:3] += wobble @ v[:3]
    expected = (D @ mov_img.affine @ np.linalg.inv(fsl_scaled(mov_img)) @ src_fsl)[:3].T
    assert np.abs(mapped(ours, pts) - expected).max() < TOL


def test_fnirt_coefficients_written_by_fslpy(tmp_path):
    """A FNIRT coefficient file written by fslpy (cubic B-spline knots, constant coefficients
    c, a FLIRT premat in its header): FNIRT's convention gives source = premat^-1 (reference)
    + c in scaled voxels wherever the spline sums to one; the reading agrees at those voxel
    centres (1e-4 mm)."""
    from fsl.data.image import Image
    from fsl.transform import affine, fnirt, nonlinear

    ref, mov = grids(tmp_path, 3, ref_flip=False, mov_flip=True)
    ref_img, mov_img = nib.load(ref), nib.load(mov)
    knots = np.array([3, 3, 3])
    shape = tuple(int(math.ceil(s / k)) + 3 for s, k in zip(ref_img.shape, knots, strict=True))
    c = np.array([1.5, -2.0, 0.75])
    coefficients = np.broadcast_to(c, (*shape, 3)).astype(np.float32).copy()
    # FLIRT's premat (kept in the coefficient file's header): moving scaled voxels ->
    # reference scaled voxels, here the known affine's
    ref_to_src = (
        fsl_scaled(mov_img)
        @ np.linalg.inv(mov_img.affine)
        @ known_affine(3)
        @ ref_img.affine
        @ np.linalg.inv(fsl_scaled(ref_img))
    )
    src_to_ref = np.linalg.inv(ref_to_src)
    field = nonlinear.CoefficientField(
        coefficients,
        Image(str(mov)),
        Image(str(ref)),
        srcSpace="fsl",
        refSpace="fsl",
        fieldType="cubic",
        knotSpacing=knots,
        srcToRefMat=src_to_ref,
        fieldToRefMat=affine.scaleOffsetXform(knots, 0),
    )
    fnirt.toFnirt(field).save(str(tmp_path / "coef.nii.gz"))
    ours = read_transform(ForeignTransform(tmp_path / "coef.nii.gz", "fsl", ref, mov))
    # interior voxel centres: 4 knots on every side
    inner = np.stack(
        np.meshgrid(*[np.arange(4, n - 4) for n in ref_img.shape], indexing="ij"), -1
    ).reshape(-1, 3)
    v = np.c_[inner, np.ones(len(inner))].T
    src_fsl = np.linalg.inv(src_to_ref) @ fsl_scaled(ref_img) @ v
    src_fsl[:3] += c[:, None]
    expected = (D @ mov_img.affine @ np.linalg.inv(fsl_scaled(mov_img)) @ src_fsl)[:3].T
    pts = (D @ ref_img.affine @ v)[:3].T
    assert len(pts) > 20
    assert np.abs(mapped(ours, pts) - expected).max() < TOL


# ----------------------------------------------------------------------------- the manifest


def population(folder: Path, n: int = 4) -> dict:
    """A 2D reference and `n` images on their own oblique grids, each the reference moved by a
    known affine; each registration's transforms written as ITK, FSL (nitransforms' writer)
    and NiftyReg (reg_aladin's text) files. Returns the manifest (paths relative to
    `folder`)."""
    from nitransforms.io.fsl import FSLLinearTransform

    size, spacing = (40, 36), (1.1, 0.9)
    y, x = np.mgrid[0 : size[1], 0 : size[0]].astype(float)
    phantom = (
        100 * np.exp(-((x - 20) ** 2 / 90 + (y - 18) ** 2 / 60))
        + 40 * np.exp(-((x - 14) ** 2 / 10 + (y - 12) ** 2 / 14))
        + 30 * ((x - 26) ** 2 / 16 + (y - 24) ** 2 / 9 < 1)
    ).astype(np.float32)
    ref = write_grid(
        folder / "ref.nii.gz", size, spacing, (-20, 30), rotation(2, (0.2,)), values=phantom
    )
    template = sitk.ReadImage(str(ref))
    rng = np.random.default_rng(7)
    data = {"images": [], "registrations": {k: [] for k in ("itk", "fsl", "niftyreg")}}
    for i in range(n):
        ras = np.eye(4)
        ras[:2, :2] = rotation(2, (rng.uniform(-0.15, 0.15),)) @ np.diag(rng.uniform(0.93, 1.07, 2))
        ras[:2, 3] = (60 + 10 * i, -80 + rng.uniform(-5, 5))  # the image lies elsewhere
        lps = D @ ras @ D
        pull = sitk.AffineTransform(2)  # reference points -> image points
        pull.SetMatrix(lps[:2, :2].ravel().tolist())
        pull.SetTranslation(lps[:2, 3].tolist())
        centre = np.array(
            pull.TransformPoint(template.TransformContinuousIndexToPhysicalPoint((19.5, 17.5)))
        )
        direction = rotation(2, (rng.uniform(-0.5, 0.5),)) @ np.diag([1, -1 if i % 2 else 1])
        grid_spacing = np.array([0.9 + 0.05 * i, 1.05])
        origin = centre - direction @ (grid_spacing * (np.array([60, 56]) - 1) / 2)
        grid = sitk.Image([60, 56], sitk.sitkFloat32)  # covers the whole reference
        grid.SetSpacing(grid_spacing.tolist())
        grid.SetOrigin(origin.tolist())
        grid.SetDirection(direction.ravel().tolist())
        moved = sitk.Resample(template, grid, pull.GetInverse(), sitk.sitkLinear, 0.0)
        noise = rng.normal(0, 2.0, sitk.GetArrayFromImage(moved).shape).astype(np.float32)
        img = sitk.GetImageFromArray(sitk.GetArrayFromImage(moved) + noise)
        img.CopyInformation(moved)
        sitk.WriteImage(img, str(folder / f"sub-{i}.nii.gz"))
        data["images"].append(f"sub-{i}.nii.gz")
        (folder / "itk").mkdir(exist_ok=True)
        sitk.WriteTransform(pull, str(folder / "itk" / f"sub-{i}.tfm"))
        (folder / "flirt").mkdir(exist_ok=True)
        flirt = FSLLinearTransform.from_ras(
            ras, reference=nib.load(ref), moving=nib.load(folder / f"sub-{i}.nii.gz")
        )
        # nitransforms (like FLIRT) prints 8 decimals, about 1e-6 mm here: below any
        # interpolation's noise, but it shows at 1e-6 in the scores; the numbers in full
        np.savetxt(folder / "flirt" / f"sub-{i}.mat", flirt.structarr["parameters"], fmt="%.17g")
        (folder / "nr").mkdir(exist_ok=True)
        np.savetxt(folder / "nr" / f"sub-{i}_aff.txt", ras, fmt="%.10f")
        data["registrations"]["itk"].append(f"itk/sub-{i}.tfm")
        data["registrations"]["fsl"].append({"file": f"flirt/sub-{i}.mat", "format": "fsl"})
        data["registrations"]["niftyreg"].append(
            {"file": f"nr/sub-{i}_aff.txt", "format": "niftyreg"}
        )
    data["registrations"] = {
        name: {"reference": "ref.nii.gz", "transforms": transforms}
        for name, transforms in data["registrations"].items()
    }
    return data


def test_same_motions_as_fsl_niftyreg_and_itk_score_the_same(tmp_path):
    """One evaluation: the same known motions given as ITK, FSL (FLIRT) and NiftyReg
    (reg_aladin) files give the same specificity and generalization (1e-6)."""
    data = population(tmp_path)
    (tmp_path / "manifest.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    result = nr.evaluate(
        tmp_path / "manifest.yaml",
        n_samples=300,
        seed=1,
        progress=False,
        confidence=False,
        inverse_consistency=False,
    )
    itk = result.scores["itk"]
    for name in ("fsl", "niftyreg"):
        other = result.scores[name]
        for key, value in itk.measures().items():
            if isinstance(value, float) and math.isfinite(value):
                assert other.measures()[key] == pytest.approx(value, rel=1e-6, abs=1e-6), (
                    name,
                    key,
                )
        assert other.specificity.value == pytest.approx(itk.specificity.value, rel=1e-6)


def test_manifest_entries_defaults_and_writing(tmp_path):
    """An entry names its format; its images default to the registration's reference and the
    subject's image (in a chain: the first transform's reference, the last's moving image);
    written back as given; ``format: itk`` is a bare path."""
    data = population(tmp_path, n=3)
    data["registrations"]["fsl"]["transforms"][1] = {
        "file": "flirt/sub-1.mat",
        "format": "FSL",
        "reference": "ref.nii.gz",
        "moving": "sub-1.nii.gz",
    }
    data["registrations"]["niftyreg"]["transforms"][2] = [
        {"file": "nr/sub-2_aff.txt", "format": "niftyreg"},
        {"file": "itk/sub-0.tfm", "format": "itk"},
    ]
    data["registrations"]["framed"] = {  # a frame transform names both its images
        **data["registrations"]["itk"],
        "frame_transform": {
            "file": "flirt/sub-2.mat",
            "format": "fsl",
            "reference": "ref.nii.gz",
            "moving": "sub-2.nii.gz",
        },
    }
    m = load_manifest(data, base_dir=tmp_path)
    frame = m.registrations["framed"].frame_transform
    assert isinstance(frame, ForeignTransform) and frame.given == ("reference", "moving")
    first = m.registrations["fsl"].transforms[0][0]
    assert isinstance(first, ForeignTransform) and first.format == "fsl"
    assert first.reference == tmp_path / "ref.nii.gz" and first.moving == tmp_path / "sub-0.nii.gz"
    assert first.given == ()
    assert m.registrations["fsl"].transforms[1][0].given == ("reference", "moving")
    chain = m.registrations["niftyreg"].transforms[2]
    assert chain[0].reference == tmp_path / "ref.nii.gz" and chain[0].moving is None
    assert chain[1] == tmp_path / "itk" / "sub-0.tfm"
    assert (tmp_path / "flirt" / "sub-0.mat") in m.files
    assert "format fsl" in m.describe()["registrations"]["fsl"]["transforms"][0][0]
    write_manifest(m, tmp_path / "out" / "m.yaml")
    written = yaml.safe_load((tmp_path / "out" / "m.yaml").read_text())
    fsl = written["registrations"]["fsl"]["transforms"]
    assert fsl[0] == {"file": "../flirt/sub-0.mat", "format": "fsl"}
    assert fsl[1] == {
        "file": "../flirt/sub-1.mat",
        "format": "fsl",
        "reference": "../ref.nii.gz",
        "moving": "../sub-1.nii.gz",
    }
    assert written["registrations"]["niftyreg"]["transforms"][2][1] == "../itk/sub-0.tfm"
    assert written["registrations"]["framed"]["frame_transform"]["moving"] == "../sub-2.nii.gz"
    again = load_manifest(tmp_path / "out" / "m.yaml")
    assert again.registrations["fsl"].transforms == m.registrations["fsl"].transforms
    assert again.registrations["framed"].frame_transform == frame
    # without its images, a frame transform's FLIRT matrix is one line
    data["registrations"]["framed"]["frame_transform"] = {
        "file": "flirt/sub-2.mat",
        "format": "fsl",
    }
    with pytest.raises(
        InputError, match=r"framed\.frame_transform: a fsl transform needs 'reference'"
    ):
        load_manifest(data, base_dir=tmp_path)


@pytest.mark.parametrize(
    "entry,message",
    [
        ({"file": "flirt/sub-0.mat", "format": "spm"}, r"format 'spm' is not one of fsl, afni"),
        ({"file": "flirt/sub-0.mat"}, r"format None is not one of"),
        ({"format": "fsl"}, r"missing 'file'"),
        ({"file": "flirt/sub-0.mat", "format": "fsl", "ref": "x"}, r"unknown key 'ref'"),
        ({"file": "flirt/none.mat", "format": "fsl"}, r"none\.mat: transform file not found"),
        ({"file": "flirt/bad.mat", "format": "fsl"}, r"bad\.mat: cannot read it as a fsl"),
        (
            [
                {"file": "itk/sub-0.tfm", "format": "itk"},
                {"file": "flirt/sub-0.mat", "format": "fsl"},
            ],
            r"transforms\[0\]\[1\]: a fsl transform needs 'reference' here",
        ),
    ],
)
def test_bad_entries_one_line(tmp_path, entry, message):
    data = population(tmp_path, n=3)
    (tmp_path / "flirt" / "bad.mat").write_text("1 0 0\n0 1 0\n")
    data["registrations"]["fsl"]["transforms"][0] = entry
    (tmp_path / "manifest.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(InputError, match=r"registrations\.fsl\.transforms\[0\]") as err:
        load_manifest(tmp_path / "manifest.yaml")
    assert "\n" not in str(err.value)
    assert err.match(message)


def test_cli_manifest_fsl_and_niftyreg_layouts(tmp_path, capsys, monkeypatch):
    """``nrreval manifest --fsl NAME='pattern' --niftyreg 'pattern'`` finds one file per
    subject, matched to the images by what the * stands for, and writes entries naming their
    format; the manifest reads back to the same transforms."""
    data = population(tmp_path, n=3)
    monkeypatch.chdir(tmp_path)
    code = main(
        [
            "manifest",
            "--images", "sub-*.nii.gz",
            "--reference", "ref.nii.gz",
            "--fsl", "flirt=flirt/sub-*.mat",
            "--niftyreg", "nr/sub-*_aff.txt",
            "--out", "m.yaml",
        ]
    )  # fmt: skip
    assert code == 0, capsys.readouterr().err
    written = yaml.safe_load((tmp_path / "m.yaml").read_text())
    assert list(written["registrations"]) == ["flirt", "niftyreg"]
    assert written["registrations"]["flirt"]["transforms"][2] == {
        "file": "flirt/sub-2.mat",
        "format": "fsl",
    }
    # FLIRT and reg_aladin matrices say which method wrote them (the verdict's families)
    assert written["registrations"]["flirt"]["parameters"] == {"engine": "fsl", "method": "flirt"}
    assert written["registrations"]["niftyreg"]["parameters"] == {
        "engine": "niftyreg",
        "method": "aladin",
    }
    m = load_manifest(tmp_path / "m.yaml")
    itk = [read_transform(tmp_path / t) for t in data["registrations"]["itk"]["transforms"]]
    pts = points(tmp_path / "ref.nii.gz", 10)
    for name in ("flirt", "niftyreg"):
        for i, chain in enumerate(m.registrations[name].transforms):
            assert np.abs(mapped(read_transform(chain[0]), pts) - mapped(itk[i], pts)).max() < TOL
    # a transform without its image: one line naming it
    (tmp_path / "flirt" / "sub-9.mat").write_text((tmp_path / "flirt" / "sub-0.mat").read_text())
    code = main(["manifest", "--images", "sub-*.nii.gz", "--reference", "ref.nii.gz",
                 "--fsl", "flirt/sub-*.mat", "--out", "m2.yaml"])  # fmt: skip
    assert code == 2
    err = capsys.readouterr().err
    assert "sub-9.mat: a transform without its image" in err and len(err.splitlines()) == 1


@pytest.mark.parametrize(("intent", "method"), [(2007, "fnirt"), (2009, "fnirt"), (2006, None)])
def test_fsl_field_names_fnirt_only_by_its_coefficients(tmp_path, intent, method):
    """FNIRT's coefficient files (intent codes 2007-2009) are fnirt's alone; a displacement
    field (2006) may come from convertwarp's chain of anything, so it names no method. Read
    from the NIfTI header as nibabel writes it."""
    from itk_nrreval.io._transform_patterns import method_written

    img = nib.Nifti1Image(np.zeros((4, 5, 6, 3), np.float32), np.eye(4))
    img.header.set_intent(intent)
    chains = {}
    for i in range(2):
        nib.save(img, tmp_path / f"warp-{i}.nii.gz")
        chains[(str(i),)] = [{"file": str(tmp_path / f"warp-{i}.nii.gz"), "format": "fsl"}]
    assert nib.load(tmp_path / "warp-0.nii.gz").header["intent_code"] == intent
    assert method_written("fsl", chains) == method


# ----------------------------------------------------------------------------- RAS as LPS


def warped_population(folder: Path, *, negate: bool | tuple[int, ...]) -> Path:
    """A 2D template and images warped by smooth fields of a few mm; the registration's
        fields (ITK files, template -> image points), their x and y negated with `negate` (all,
    or the subjects listed); and a
        registration whose chains put a smooth random field of about 2 mm before them (a wrong
        field that its negation may improve, but that the chain aligns better without)."""
    y, x = np.mgrid[0:48, 0:52].astype(float)
    template = (
        100 * np.exp(-((x - 26) ** 2 / 120 + (y - 24) ** 2 / 80))
        + 60 * ((x - 18) ** 2 / 20 + (y - 16) ** 2 / 30 < 1)
        + 40 * ((x - 34) ** 2 / 25 + (y - 32) ** 2 / 12 < 1)
    ).astype(np.float32)
    ref = write_grid(
        folder / "template.nii.gz",
        (52, 48),
        (1.0, 1.0),
        (-20, 10),
        rotation(2, (0.3,)),
        values=template,
    )
    tmpl = sitk.ReadImage(str(ref))
    names = []
    for i in range(3):
        rng = np.random.default_rng(i)
        bump = np.sin(np.pi * x / 51) * np.sin(np.pi * y / 47)
        u = np.stack([bump * rng.uniform(3, 5) * s for s in rng.choice([-1, 1], 2)], -1)
        u[..., 0] += 2.5 * bump  # and a shift along x
        field = sitk.GetImageFromArray(u, isVector=True)
        field.CopyInformation(tmpl)
        # the image is the template moved by the field: image(p + u(p)) = template(p)
        img = sitk.Resample(tmpl, tmpl, _inverse(field), sitk.sitkLinear, 0.0)
        sitk.WriteImage(img, str(folder / f"img{i}.nii.gz"))
        flip = negate if isinstance(negate, bool) else i in negate
        stored = sitk.GetImageFromArray(u * (-1 if flip else 1), isVector=True)
        stored.CopyInformation(tmpl)
        sitk.WriteImage(sitk.Cast(stored, sitk.sitkVectorFloat32), str(folder / f"warp{i}.nii.gz"))
        noise = np.stack([bump * np.cos(np.pi * (x / 13 + k * i)) * 2.0 for k in (1, 2)], -1)
        pert = sitk.GetImageFromArray(noise, isVector=True)
        pert.CopyInformation(tmpl)
        sitk.WriteImage(sitk.Cast(pert, sitk.sitkVectorFloat32), str(folder / f"pert{i}.mha"))
        names.append(i)
    data = {
        "images": [f"img{i}.nii.gz" for i in names],
        "registrations": {
            "syn": {
                "reference": "template.nii.gz",
                "transforms": [f"warp{i}.nii.gz" for i in names],
            },
            "perturbed": {
                "reference": "template.nii.gz",
                "transforms": [[f"pert{i}.mha", f"warp{i}.nii.gz"] for i in names],
            },
        },
    }
    (folder / "manifest.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    return folder / "manifest.yaml"


def _inverse(field: sitk.Image) -> sitk.Transform:
    inv = sitk.InvertDisplacementField(
        sitk.Cast(field, sitk.sitkVectorFloat64),
        maximumNumberOfIterations=50,
        maxErrorToleranceThreshold=0.01,
        meanErrorToleranceThreshold=1e-4,
    )
    return sitk.DisplacementFieldTransform(inv)


def test_field_written_in_ras_is_warned_by_name(tmp_path):
    """Fields whose x and y were negated (RAS written as LPS) align the images worse than
    their negation: load_manifest warns, naming the registration and file. The fields as
    written by ITK draw no warning, nor does a wrong field put before them (perturbed), nor
    one subject's field negated among correct ones."""
    for name, negate in (("good", False), ("one", (1,))):
        (tmp_path / name).mkdir()
        with warnings.catch_warnings():  # one subject's field negated: an accident, not told
            warnings.simplefilter("error")
            load_manifest(warped_population(tmp_path / name, negate=negate))
    (tmp_path / "bad").mkdir()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        load_manifest(warped_population(tmp_path / "bad", negate=True))
    lines = [str(w.message) for w in caught if "negated" in str(w.message)]
    assert len(lines) == 2, lines  # one line per registration
    assert re.search(
        r"registrations\.syn\.transforms\[0\]: warp0\.nii\.gz aligns img0\.nii\.gz with the "
        r"reference better with its x and y displacements negated .*\(and 2 more of the 3 "
        r"checked\): a field written in RAS",
        lines[0],
    )
    # in the chain [perturbation, field], the field is named, not the perturbation
    assert "registrations.perturbed.transforms[0]: warp0.nii.gz aligns" in lines[1]


def test_field_whose_header_says_another_convention_is_refused(tmp_path):
    """A NiftyReg deformation field or a FNIRT field given as a plain (ITK) field is refused
    in one line: its header says what it is and which format to give."""
    data = population(tmp_path, n=3)
    import shutil

    shutil.copy(DATA / "def2.nii.gz", tmp_path / "def2.nii.gz")
    data["registrations"]["itk"]["transforms"][0] = "def2.nii.gz"
    with pytest.raises(
        InputError,
        match=r"transforms\[0\]: def2\.nii\.gz is a NiftyReg deformation"
        r" field .*format: niftyreg",
    ):
        load_manifest(data, base_dir=tmp_path)
