"""Transforms written by FSL, AFNI, FreeSurfer and NiftyReg, read into ITK's convention.

A manifest's transform entry that names its format (``{file: s01.mat, format: fsl}``) is kept
as a :class:`ForeignTransform` and converted when it is read (:meth:`ForeignTransform.read`)
into what every other transform of the toolkit is: a SimpleITK transform that maps reference
(fixed) points to image (moving) points, physical coordinates in mm, LPS. Everything else
(the cache, the pipeline, the checks) sees it as a transform file.

The formats, the library that reads each and the convention it follows
-----------------------------------------------------------------------
``fsl``
    FLIRT's ``.mat`` (4 x 4 text) maps the moving image's (``-in``) *scaled-voxel*
    coordinates to the reference's (``-ref``): voxel index times voxel size, with the first
    axis flipped when the image's voxel-to-world matrix has a positive determinant. It needs
    both images' grids; read by nitransforms (``nitransforms.io.fsl``). FNIRT's coefficient
    files (``--cout``, the FLIRT affine kept in the header) and displacement fields (``--fout``,
    ``convertwarp``, ``fnirtfileutils``) are read by fslpy (``fsl.transform.fnirt``, FSL's own
    Python library), evaluated at the reference's voxel centres and converted to world
    coordinates there. fslpy evaluates a coefficient file in about a minute for a 1 mm brain,
    each time it is read: convert those once with ``fnirtfileutils --withaff`` for a cohort.
``afni``
    3dAllineate / 3dvolreg matrices (one row of 12 numbers, DICOM (LPS) base to source) and
    3dQwarp displacement fields (5D NIfTI, DICOM components), read by nitransforms, which
    also undoes AFNI's deobliquing of oblique grids (it needs both images' grids for that).
``lta``
    FreeSurfer's LTA (``mri_robust_register``, ``bbregister``, ``lta_convert``), read by
    nitransforms. Its matrix (voxel-to-voxel or RAS-to-RAS) maps its ``src`` volume's points
    to its ``dst`` volume's, and the file records both grids. Its direction is decided as
    FreeSurfer's ``mri_vol2vol`` decides it (``MRIvol2VolLTA``): when the moving image's grid
    is the LTA's ``src``, it is inverted; when it is the ``dst``, it is used as it is; a
    moving image that is neither is refused.
``niftyreg``
    No maintained library reads NiftyReg's files (nitransforms, fslpy and SimpleITK do not),
    and its documented conventions are short, so they are read here: reg_aladin's affine
    (``-aff``, 4 x 4 text) maps reference world points to floating world points, world being
    the NIfTI header's (sform when its code is set, else qform: RAS); ``reg_transform -def``
    and ``-disp`` fields (5D NIfTI, ``intent_name NREG_TRANS``, ``intent_p1`` 0 or 1) hold
    world positions or displacements in the floating image at the reference's voxels.
    reg_f3d's control-point grids and velocity fields are refused with the ``reg_transform
    -def`` command that converts them: evaluating NiftyReg's splines here would be a second,
    untested implementation of them.

Conversion into ITK's LPS: a RAS-to-RAS affine ``T`` becomes ``D T D`` with ``D = diag(-1,
-1, 1, 1)``; a RAS displacement ``(dx, dy, dz)`` becomes ``(-dx, -dy, dz)`` on the same grid.
Affines of 2D images (FLIRT's ``-2D``, NiftyReg's 2D runs) are 4 x 4 too: they must map the
plane z = 0 onto itself and keep their in-plane part.

A displacement field given as a plain image is ITK's (LPS components). One whose header says
it is NiftyReg's or FNIRT's is refused (:func:`plain_field_problem`), and
:func:`itk_nrreval.io._field_orientation.orientation_notes` warns, by name, about one that aligns
its image with the reference better with its x and y components negated: RAS displacements
written as LPS.
"""

from __future__ import annotations

import functools
import hashlib
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import SimpleITK as sitk

from .._errors import InputError
from ._images import InMemoryImage, read_header

__all__ = [
    "FORMATS",
    "ForeignTransform",
    "parse_entry",
    "entry_of",
    "plain_field_problem",
    "method_of_file",
]

FORMATS = ("fsl", "afni", "lta", "niftyreg", "itk")
"""The values of a transform entry's ``format``: ``itk`` is what a bare path already is."""

ENTRY_KEYS = ("file", "format", "reference", "moving")
"""The keys of a transform entry."""

#: The grids each format needs: FLIRT's scaled-voxel coordinates and AFNI's deobliquing use
#: both images, an LTA the moving image (its direction), NiftyReg's world coordinates none.
_NEEDS = {"fsl": ("reference", "moving"), "afni": ("reference", "moving"), "lta": ("moving",)}

_NIFTI = (".nii", ".nii.gz")
_D = np.diag([-1.0, -1.0, 1.0, 1.0])  # RAS <-> LPS, its own inverse
_EXTRA = "pip install 'itk-nrreval[foreign]'"
_VERSION = "1"  # of the conversions below: part of every converted transform's cache key

# NiftyReg's transformation types (reg-lib/cpu/_reg_maths.h, NREG_TRANS_TYPE), in intent_p1
_NIFTYREG_TYPES = {
    0: "deformation field",
    1: "displacement field",
    2: "cubic B-spline control-point grid",
    3: "deformation velocity field",
    4: "displacement velocity field",
    5: "B-spline velocity grid",
    6: "linear B-spline control-point grid",
}
# FSL's NIfTI intent codes (fsl.data.constants): FNIRT, topup and DCT fields and coefficients
_FSL_INTENTS = {2006, 2007, 2008, 2009, 2010, 2016, 2017, 2018}
# Of those, FNIRT's coefficient files (cubic spline, DCT, quadratic spline): written by fnirt
# alone. A displacement field (2006) is not among them: convertwarp writes those too, from
# any chain of transforms.
_FNIRT_COEFFICIENTS = {2007, 2008, 2009}


# ----------------------------------------------------------------------------- grids


@dataclass(frozen=True)
class _Grid:
    """What the conversions need of an image: its voxel-to-world matrix as the tools read it
    (RAS, nibabel's ``affine``) and its size. Has the ``affine`` and ``shape`` attributes
    nitransforms' readers take in place of an image.

    Attributes
    ----------
    affine : np.ndarray, shape (4, 4)
        Voxel index (i, j, k) -> world point (mm, RAS); a 2D image's third column is
        ``(0, 0, 1)``, its z origin 0.
    shape : tuple of int
        Voxels along i, j[, k] (ITK's size order).
    """

    affine: np.ndarray
    shape: tuple[int, ...]

    @property
    def dimension(self) -> int:
        return len(self.shape)

    def nifti(self):
        """A header-only stand-in image (zero voxels) for fslpy, which takes images."""
        import nibabel as nib

        shape = self.shape if len(self.shape) == 3 else (*self.shape, 1)
        img = nib.Nifti1Image(np.zeros(shape, np.uint8), self.affine)
        img.set_qform(self.affine, 1)
        img.set_sform(self.affine, 1)
        return img

    def same(self, other: _Grid, *, tol: float = 1e-3) -> bool:
        """The same voxels (count and place, within `tol` mm per voxel step): FreeSurfer's
        ``vg_isEqual`` threshold."""
        a = self.shape if len(self.shape) == 3 else (*self.shape, 1)
        b = other.shape if len(other.shape) == 3 else (*other.shape, 1)
        return a == b and bool(np.allclose(self.affine, other.affine, atol=tol, rtol=0))


def _itk_affine(geometry: sitk.Image | sitk.ImageFileReader) -> tuple[np.ndarray, tuple]:
    """The RAS voxel-to-world matrix and size of an ITK grid (a 2D grid in the plane z = 0)."""
    dim = geometry.GetDimension()
    m = np.eye(4)
    direction = np.asarray(geometry.GetDirection(), float).reshape(dim, dim)
    m[:dim, :dim] = direction * np.asarray(geometry.GetSpacing(), float)
    m[:dim, 3] = geometry.GetOrigin()
    return _D @ m, tuple(int(s) for s in geometry.GetSize())


@functools.lru_cache(maxsize=512)
def _file_grid(path: str, size: int, mtime_ns: int) -> tuple[_Grid | None, str | None]:
    """(grid, problem) of an image file, kept per file version."""
    try:
        reader = read_header(path)
    except RuntimeError as exc:
        return None, f"cannot read image {Path(path).name} ({_first_line(exc)})"
    affine, shape = _itk_affine(reader)
    if Path(path).name.lower().endswith(_NIFTI):
        import nibabel as nib

        # the tools place the voxels by the NIfTI header as nibabel does (sform when its
        # code is set, else qform); where ITK reads the header otherwise (a sform ITK finds
        # not orthonormal), the conversion would be between grids the rest does not use
        try:
            img = nib.load(path)
        except Exception as exc:  # nibabel raises many kinds for a damaged header
            return None, f"cannot read image {Path(path).name} ({_first_line(exc)})"
        tool = np.asarray(img.affine, float)
        corners = _corners(shape)
        gap = np.abs((tool - affine) @ corners).max() if tool.shape == (4, 4) else math.inf
        if gap > 1e-3:
            return None, (
                f"{Path(path).name}: its sform and qform place the voxels up to {gap:.3g} mm "
                "apart, and ITK reads the other one than FSL, AFNI and NiftyReg do; "
                "write the image with one of them (e.g. fslorient -copyqform2sform)"
            )
        affine = tool
    return _Grid(affine, shape), None


def _corners(shape: tuple) -> np.ndarray:
    """Homogeneous voxel indices of a grid's corners, shape (4, 2**dim)."""
    dim = len(shape)
    idx = np.array(np.meshgrid(*[[0, n - 1] for n in shape], indexing="ij")).reshape(dim, -1)
    out = np.zeros((4, idx.shape[1]))
    out[:dim] = idx
    out[3] = 1
    return out


def _grid(item, what: str) -> _Grid:
    """The grid of an image file or manifest image object; InputError naming `what`."""
    if isinstance(item, InMemoryImage):
        affine, shape = _itk_affine(item.image)
        return _Grid(affine, shape)
    path = Path(item)
    if not path.is_file():
        raise InputError(f"{what}: file not found: {path}")
    st = path.stat()
    grid, problem = _file_grid(str(path.resolve()), st.st_size, st.st_mtime_ns)
    if problem is not None:
        raise InputError(f"{what}: {problem}")
    return grid


def _first_line(exc: BaseException) -> str:
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    useful = [ln for ln in lines if "ERROR" not in ln[:12]]
    return ((useful or lines or [type(exc).__name__])[-1])[:160]


# ----------------------------------------------------------------------------- the entry


@dataclass(frozen=True)
class ForeignTransform:
    """A manifest transform entry in another tool's format, converted when read.

    A path-like object (``os.fspath`` gives its file), so whatever names or lists a
    manifest's files treats it as its file.

    Attributes
    ----------
    path : Path
        The transform file.
    format : {"fsl", "afni", "lta", "niftyreg"}
        The tool whose convention it follows.
    reference, moving : Path or InMemoryImage or None
        The images it was computed between (FLIRT's ``-ref`` and ``-in``): their grids, not
        their voxels, are used (by ``fsl`` and ``afni`` both, by ``lta`` the moving one; a
        ``niftyreg`` affine takes only its dimension from them). None where neither given
        nor defaulted.
    given : tuple of str
        Which of ``reference`` / ``moving`` the manifest gave (the others are defaults: the
        registration's reference, the image): what :func:`entry_of` writes back.
    """

    path: Path
    format: str
    reference: Any = None
    moving: Any = None
    given: tuple[str, ...] = ()

    def __fspath__(self) -> str:
        return str(self.path)

    def __str__(self) -> str:
        return str(self.path)

    @property
    def name(self) -> str:
        return self.path.name

    def describe(self) -> str:
        """One line for reports: the file, its format and the images it was read with."""
        parts = [f"format {self.format}"]
        parts += [f"{k} {getattr(self, k)}" for k in ("reference", "moving") if getattr(self, k)]
        return f"{self.path} ({', '.join(parts)})"

    @property
    def content_digest(self) -> str:
        """The result cache's key: the converter's version, the format, the file's bytes and
        the grids of the images it is read with (what the conversion depends on)."""
        h = hashlib.blake2b(digest_size=16)
        h.update(f"foreign:{_VERSION}:{self.format}:".encode())
        h.update(_bytes_digest(self.path).encode())
        for key in ("reference", "moving"):
            item = getattr(self, key)
            if item is None or key not in _NEEDS.get(self.format, ()):
                h.update(b":-")
                continue
            grid = _grid(item, f"{self.path}: {key}")
            h.update(f":{grid.shape}:".encode() + np.asarray(grid.affine, float).tobytes())
        return h.hexdigest()

    @property
    def is_field(self) -> bool:
        """Whether the file is an image (a field or coefficients), not a matrix."""
        return self.path.name.lower().endswith(_NIFTI)

    def check(self) -> int:
        """Check what can be checked cheaply and return the transform's dimension.

        Matrices are converted in full (cheap); fields are checked by their header.

        Raises
        ------
        InputError
            One line naming the file: missing, unreadable, of another kind than `format`
            reads, or its images' grids unreadable or of other dimensions.
        """
        if not self.path.is_file():
            raise InputError(f"{self.path}: transform file not found")
        self._grids()
        if not self.is_field:
            return self.read().GetDimension()
        try:
            return _FIELD_HEADERS[self.format](self)
        except ImportError as exc:
            raise InputError(
                f"{self.path}: reading {self.format} transforms needs {exc.name} ({_EXTRA})"
            ) from None

    def read(self) -> sitk.Transform:
        """The transform: reference points -> image points (mm, LPS), a SimpleITK
        ``AffineTransform`` or ``DisplacementFieldTransform``.

        Raises
        ------
        InputError
            One line naming the file (see :meth:`check`), or the library's own reason.
        """
        if not self.path.is_file():
            raise InputError(f"{self.path}: transform file not found")
        ref, mov = self._grids()
        try:
            if self.is_field:
                field, affine = _FIELD_READERS[self.format](self, ref, mov)
                # float64 already: the transform takes this private image over
                return sitk.DisplacementFieldTransform(_lps_field(field, affine, self.path))
            ras = _MATRIX_READERS[self.format](self, ref, mov)
            # the dimension of the images it maps between (every format writes 4 x 4)
            known = ref or mov or self._known_grid()
            dim = known.dimension if known is not None else 3
            return _lps_affine(ras, dim, self.path, ref or known)
        except InputError:
            raise
        except ImportError as exc:
            raise InputError(
                f"{self.path}: reading {self.format} transforms needs {exc.name} ({_EXTRA})"
            ) from None
        except Exception as exc:  # the libraries raise many kinds for a file they cannot read
            raise InputError(
                f"{self.path}: cannot read it as a {self.format} transform ({_first_line(exc)})"
            ) from None

    def _known_grid(self) -> _Grid | None:
        """The grid of the reference (else the moving image) where the entry has one."""
        for key in ("reference", "moving"):
            if getattr(self, key) is not None:
                return _grid(getattr(self, key), f"{self.path}: {key}")
        return None

    def _grids(self) -> tuple[_Grid | None, _Grid | None]:
        needs = _NEEDS.get(self.format, ())
        grids = []
        for key in ("reference", "moving"):
            item = getattr(self, key)
            if key in needs and item is None:
                raise InputError(f"{self.path}: a {self.format} transform needs its {key} image")
            grids.append(_grid(item, f"{self.path}: {key}") if key in needs else None)
        ref, mov = grids
        if ref is not None and mov is not None and ref.dimension != mov.dimension:
            raise InputError(
                f"{self.path}: its reference is {ref.dimension}D and its moving image "
                f"{mov.dimension}D"
            )
        return ref, mov


@functools.lru_cache(maxsize=1024)
def _cached_bytes_digest(path: str, size: int, mtime_ns: int, ino: int) -> str:
    h = hashlib.blake2b(digest_size=16)
    with open(path, "rb") as f:
        while chunk := f.read(1 << 20):
            h.update(chunk)
    return h.hexdigest()


def _bytes_digest(path: Path) -> str:
    st = path.stat()
    return _cached_bytes_digest(str(path.resolve()), st.st_size, st.st_mtime_ns, st.st_ino)


def parse_entry(
    value: Mapping,
    *,
    resolve,
    what: str,
    problems: list[str],
    reference=None,
    moving=None,
):
    """A manifest transform entry ``{file:, format:[, reference:][, moving:]}``.

    Parameters
    ----------
    value : mapping
        The entry as written.
    resolve : callable
        ``resolve(value, what)`` -> a path (relative to the manifest's folder) or an image
        object, or None after adding a problem (the manifest's own item reader).
    what : str
        The entry's place, for messages (``registrations.fsl.transforms[3]``).
    problems : list of str
        Problems are appended here, one line each.
    reference, moving : path or InMemoryImage, optional
        Defaults for the images the transform was computed between (the registration's
        reference for the transform acting first, the image for the one acting last).

    Returns
    -------
    ForeignTransform, Path or None
        A bare path for ``format: itk``; None after a problem.
    """
    unknown = [k for k in value if k not in ENTRY_KEYS]
    if unknown:
        problems.append(
            f"{what}: unknown key {unknown[0]!r} in a transform entry (expected "
            f"{', '.join(ENTRY_KEYS)})"
        )
        return None
    fmt = value.get("format")
    if not isinstance(fmt, str) or fmt.lower() not in FORMATS:
        problems.append(
            f"{what}: format {fmt!r} is not one of {', '.join(FORMATS)} (a transform entry "
            "names its file's format)"
        )
        return None
    fmt = fmt.lower()
    if value.get("file") is None:
        problems.append(f"{what}: missing 'file' (the transform file)")
        return None
    path = resolve(value["file"], f"{what}.file")
    if path is None:
        return None
    if not isinstance(path, (str, os.PathLike)) or isinstance(path, ForeignTransform):
        problems.append(f"{what}.file: expected a file path")
        return None
    if fmt == "itk":
        return path
    images = {"reference": reference, "moving": moving}
    given = []
    for key in ("reference", "moving"):
        if value.get(key) is not None:
            images[key] = resolve(value[key], f"{what}.{key}")
            if images[key] is None:
                return None
            given.append(key)
    for key in _NEEDS.get(fmt, ()):
        if images[key] is None:
            problems.append(
                f"{what}: a {fmt} transform needs '{key}' here (the {key} image it was "
                "computed with; in a chain only the first transform defaults to the "
                "registration's reference and only the last to the image)"
            )
            return None
    return ForeignTransform(Path(path), fmt, images["reference"], images["moving"], tuple(given))


def entry_of(item: ForeignTransform, rel) -> dict:
    """The manifest entry of `item`, its paths written by ``rel(path)`` (relative to the
    manifest's folder); defaults left out, as the manifest gave them."""
    out = {"file": rel(item.path), "format": item.format}
    for key in item.given:
        out[key] = rel(getattr(item, key))
    return out


# ----------------------------------------------------------------------------- into ITK


def _lps_affine(ras: np.ndarray, dim: int, path: Path, ref: _Grid | None) -> sitk.Transform:
    """A RAS-to-RAS affine (reference world -> moving world) as a SimpleITK affine in LPS.

    A 2D transform must map the plane z = 0 onto itself over the reference's extent (within
    1e-3 mm); only its in-plane part is kept.
    """
    ras = np.asarray(ras, float)
    if ras.shape != (4, 4) or not np.allclose(ras[3], (0, 0, 0, 1), atol=1e-6):
        raise InputError(f"{path}: not an affine matrix (its last row is not 0 0 0 1)")
    if not np.isfinite(ras).all():
        raise InputError(f"{path}: transform contains NaN or infinite values")
    lps = _D @ ras @ _D
    if dim == 2:
        extent = 1.0 if ref is None else float(np.abs(ref.affine @ _corners(ref.shape)).max())
        off = abs(lps[2, 0]) * extent + abs(lps[2, 1]) * extent + abs(lps[2, 3])
        if off > 1e-3:
            raise InputError(
                f"{path}: a 3D transform for 2D images (it moves points of the image plane "
                f"up to {off:.3g} mm out of it)"
            )
    t = sitk.AffineTransform(dim)
    t.SetMatrix(lps[:dim, :dim].ravel().tolist())
    t.SetTranslation(lps[:dim, 3].tolist())
    return t


def _lps_field(field_ras: np.ndarray, affine: np.ndarray, path: Path) -> sitk.Image:
    """A RAS displacement field on a voxel grid as an ITK (LPS) vector image.

    Parameters
    ----------
    field_ras : np.ndarray, shape (nx, ny[, nz], dim)
        Displacements (mm, RAS components) at the voxels, index order (i, j[, k]).
    affine : np.ndarray, shape (4, 4)
        The grid's voxel-to-world matrix (RAS).
    """
    dim = field_ras.shape[-1]
    if dim not in (2, 3) or field_ras.ndim != dim + 1:
        raise InputError(
            f"{path}: a field of {field_ras.shape[-1]} components on a grid of "
            f"shape {field_ras.shape[:-1]}"
        )
    lps = _D @ np.asarray(affine, float)
    block = lps[:dim, :dim]
    if dim == 2 and (abs(lps[2, 0]) > 1e-6 or abs(lps[2, 1]) > 1e-6 or abs(lps[2, 3]) > 1e-6):
        raise InputError(f"{path}: a 2D field whose grid leaves the plane z = 0")
    spacing = np.linalg.norm(block, axis=0)
    direction = block / spacing
    if not np.allclose(direction.T @ direction, np.eye(dim), atol=1e-4):
        raise InputError(f"{path}: its grid is sheared (ITK grids have orthonormal axes)")
    values = np.array(field_ras, np.float64)
    values[..., :2] *= -1.0  # RAS -> LPS: x and y change sign
    if not np.isfinite(values).all():
        raise InputError(f"{path}: displacement field contains NaN or infinite voxel values")
    image = sitk.GetImageFromArray(
        np.ascontiguousarray(values.transpose(*range(dim)[::-1], dim)), isVector=True
    )
    image.SetSpacing(spacing.tolist())
    image.SetOrigin(lps[:dim, 3].tolist())
    image.SetDirection(direction.ravel().tolist())
    return image


# ----------------------------------------------------------------------------- matrices


def _fsl_matrix(item: ForeignTransform, ref: _Grid, mov: _Grid) -> np.ndarray:
    from nitransforms.io.fsl import FSLLinearTransformArray

    xfms = FSLLinearTransformArray.from_filename(item.path).xforms
    if len(xfms) != 1:
        raise InputError(f"{item.path}: {len(xfms)} FLIRT matrices in one file; give one")
    return xfms[0].to_ras(reference=ref, moving=mov)


def _afni_matrix(item: ForeignTransform, ref: _Grid, mov: _Grid) -> np.ndarray:
    from nitransforms.io.afni import AFNILinearTransformArray

    xfms = AFNILinearTransformArray.from_filename(item.path).xforms
    if len(xfms) != 1:
        raise InputError(
            f"{item.path}: {len(xfms)} AFNI matrices (a series, one per volume); give one"
        )
    return xfms[0].to_ras(reference=ref, moving=mov)


def _lta_matrix(item: ForeignTransform, ref: _Grid | None, mov: _Grid) -> np.ndarray:
    from nitransforms.io.lta import FSLinearTransformArray

    lta = FSLinearTransformArray.from_filename(item.path)
    if len(lta.xforms) != 1:
        raise InputError(f"{item.path}: {len(lta.xforms)} transforms in one LTA; give one")
    xfm = lta.xforms[0]
    kind = int(xfm.structarr["type"])
    if kind not in (0, 1):
        raise InputError(
            f"{item.path}: LTA of type {kind}; only LINEAR_VOX_TO_VOX (0) and "
            "LINEAR_RAS_TO_RAS (1) are read (convert it with lta_convert --outlta)"
        )
    volumes = {}
    for key in ("src", "dst"):
        geometry = xfm[key]
        if not int(geometry["valid"]):
            raise InputError(
                f"{item.path}: its {key} volume geometry is not valid, so its direction "
                "cannot be told (write it with lta_convert --src --trg)"
            )
        volumes[key] = _Grid(geometry.as_affine(), tuple(int(v) for v in geometry["volume"]))
    # nitransforms' RAS matrix is the LTA's inverse: dst points -> src points
    dst_to_src = xfm.to_ras()
    # FreeSurfer (MRIvol2VolLTA): the LTA maps src points to dst points and resamples the
    # moving image onto the src grid, inverted first when the moving image is its src
    if mov.same(volumes["src"]):
        return dst_to_src
    if mov.same(volumes["dst"]):
        return np.linalg.inv(dst_to_src)
    raise InputError(
        f"{item.path}: its moving image {item.moving} is neither its src volume "
        f"({'x'.join(map(str, volumes['src'].shape))}) nor its dst volume "
        f"({'x'.join(map(str, volumes['dst'].shape))})"
    )


def _niftyreg_matrix(item: ForeignTransform, ref, mov) -> np.ndarray:
    try:
        values = np.loadtxt(item.path, dtype=float, ndmin=2)
    except ValueError as exc:
        raise InputError(f"{item.path}: not a 4 x 4 NiftyReg affine ({_first_line(exc)})") from None
    if values.shape != (4, 4):
        raise InputError(
            f"{item.path}: not a 4 x 4 NiftyReg affine (holds {values.shape[0]} x "
            f"{values.shape[1] if values.ndim > 1 else 1} numbers)"
        )
    return values  # reference world (RAS) -> floating world (RAS), reg_aladin's -aff


_MATRIX_READERS = {
    "fsl": _fsl_matrix,
    "afni": _afni_matrix,
    "lta": _lta_matrix,
    "niftyreg": _niftyreg_matrix,
}


# ----------------------------------------------------------------------------- fields


def _nifti_header(path: Path):
    import nibabel as nib

    try:
        return nib.load(path)
    except Exception as exc:
        raise InputError(f"{path}: cannot read it as NIfTI ({_first_line(exc)})") from None


def method_of_file(path: str | os.PathLike, fmt: str) -> str | None:
    """The registration method an FSL or NiftyReg transform file names, or None where it
    does not say: a FLIRT matrix is ``flirt``, an FNIRT coefficient file ``fnirt``, a
    reg_aladin matrix ``aladin``; an FSL displacement field and a NiftyReg field do not say
    (convertwarp and reg_transform write them from any chain of transforms).

    Raises
    ------
    InputError
        Naming the file, where an FSL field cannot be read as NIfTI.
    """
    path = Path(path)
    if not path.name.lower().endswith(_NIFTI):
        return {"fsl": "flirt", "niftyreg": "aladin"}.get(fmt)
    if fmt != "fsl":
        return None
    code = int(_nifti_header(path).header["intent_code"])
    return "fnirt" if code in _FNIRT_COEFFICIENTS else None


def _niftyreg_kind(img, path: Path) -> int:
    """NiftyReg's transformation type of a field file (0: deformation, 1: displacement)."""
    header = img.header
    name = bytes(np.asarray(header["intent_name"]).tobytes()).split(b"\0")[0]
    if name != b"NREG_TRANS":
        raise InputError(
            f"{path}: not a NiftyReg transformation (no intent_name NREG_TRANS in its header); "
            "write it with reg_transform -ref <reference> -def <transformation> <field>"
        )
    kind = int(round(float(header["intent_p1"])))
    if kind not in (0, 1):
        what = _NIFTYREG_TYPES.get(kind, f"transformation of type {kind}")
        raise InputError(
            f"{path}: a NiftyReg {what}, which is not read here; convert it with "
            f"reg_transform -ref <reference> -def {path.name} <deformation field>"
        )
    return kind


def _niftyreg_header(item: ForeignTransform) -> int:
    img = _nifti_header(item.path)
    _niftyreg_kind(img, item.path)
    return _field_dimension(img, item.path)


def _field_dimension(img, path: Path) -> int:
    shape = img.shape
    if len(shape) != 5 or shape[3] != 1 or shape[4] not in (2, 3):
        raise InputError(f"{path}: a field file is 5D (x, y, z, 1, components), this is {shape}")
    if shape[4] == 2 and shape[2] != 1:
        raise InputError(f"{path}: 2 components on a 3D grid {shape[:3]}")
    return int(shape[4])


def _niftyreg_field(item: ForeignTransform, ref, mov) -> tuple[np.ndarray, np.ndarray]:
    img = _nifti_header(item.path)
    kind = _niftyreg_kind(img, item.path)
    dim = _field_dimension(img, item.path)
    values = np.asarray(img.dataobj, dtype=np.float64)[:, :, :, 0, :]
    affine = np.asarray(img.affine, float)  # NiftyReg: sform when its code is set, else qform
    if dim == 2:
        values = values[:, :, 0, :]
    if kind == 0:  # world positions in the floating image: subtract the voxels' own
        values = values - _world_points(affine, values.shape[:-1])[..., :dim]
    return values, affine


def _world_points(affine: np.ndarray, shape: tuple) -> np.ndarray:
    """World points (RAS) of every voxel of a grid, shape ``(*shape, 3)``."""
    idx = np.stack(np.meshgrid(*[np.arange(n, dtype=float) for n in shape], indexing="ij"), -1)
    idx3 = np.zeros((*shape, 3))
    idx3[..., : len(shape)] = idx
    return idx3 @ affine[:3, :3].T + affine[:3, 3]


def _fsl_header(item: ForeignTransform) -> int:
    from fsl.transform import fnirt  # noqa: F401  (the reader must be installed)

    img = _nifti_header(item.path)
    code = int(img.header["intent_code"])
    if code not in _FSL_INTENTS:
        raise InputError(
            f"{item.path}: not a FNIRT file (intent code {code}; FNIRT writes 2006 for a "
            "displacement field and 2007-2010 for coefficients)"
        )
    return 3


def _fsl_field(item: ForeignTransform, ref: _Grid, mov: _Grid) -> tuple[np.ndarray, np.ndarray]:
    from fsl.data.image import Image
    from fsl.transform import fnirt, nonlinear

    _fsl_header(item)
    field = fnirt.readFnirt(str(item.path), Image(mov.nifti()), Image(ref.nifti()))
    # world -> world (RAS): fslpy evaluates coefficients at the reference's voxel centres
    # and applies the FLIRT premat as fnirtfileutils does
    world = fnirt.fromFnirt(field, from_="world", to="world")
    if world.absolute:
        values = nonlinear.convertDeformationType(world, "relative")
    else:
        values = np.asarray(world.data, float)
    return np.asarray(values, float), np.asarray(world.getAffine("voxel", "world"), float)


def _afni_header(item: ForeignTransform) -> int:
    return _field_dimension(_nifti_header(item.path), item.path)


def _afni_field(item: ForeignTransform, ref, mov) -> tuple[np.ndarray, np.ndarray]:
    from nitransforms.io.afni import AFNIDisplacementsField

    img = AFNIDisplacementsField.from_filename(item.path)  # RAS displacements, (x, y, z, c)
    return np.asarray(img.dataobj, float), np.asarray(img.affine, float)


_FIELD_READERS = {"fsl": _fsl_field, "afni": _afni_field, "niftyreg": _niftyreg_field}
_FIELD_HEADERS = {"fsl": _fsl_header, "afni": _afni_header, "niftyreg": _niftyreg_header}


def _no_field(item: ForeignTransform, *args):
    raise InputError(f"{item.path}: an LTA is a text file, not an image")


_FIELD_READERS["lta"] = _no_field
_FIELD_HEADERS["lta"] = _no_field


# ----------------------------------------------------------------------------- plain fields


def plain_field_problem(path: Path) -> str | None:
    """Why a displacement-field image given without a format is not ITK's, from its header.

    A NIfTI header naming NiftyReg's transformation types (``intent_name NREG_TRANS``: world
    positions or RAS displacements) or FSL's FNIRT intents (scaled-voxel coordinates) says
    the file follows another convention; read as ITK's LPS displacements it would move every
    point elsewhere. Other files (ITK's, ANTs', AFNI's) give None.
    """
    if not path.name.lower().endswith(_NIFTI):
        return None
    try:
        import nibabel as nib

        header = nib.load(path).header
    except Exception:
        return None  # the field's own reader reports an unreadable file
    name = bytes(np.asarray(header["intent_name"]).tobytes()).split(b"\0")[0]
    if name == b"NREG_TRANS":
        kind = int(round(float(header["intent_p1"])))
        what = _NIFTYREG_TYPES.get(kind, "transformation")
        return (
            f"{path.name} is a NiftyReg {what} (intent_name NREG_TRANS: world coordinates, "
            f"RAS), not ITK displacements; give it as {{file: {path.name}, format: niftyreg}}"
        )
    if int(header["intent_code"]) in _FSL_INTENTS:
        return (
            f"{path.name} is an FSL FNIRT file (intent code {int(header['intent_code'])}: "
            f"FSL's scaled-voxel coordinates), not ITK displacements; give it as "
            f"{{file: {path.name}, format: fsl}}"
        )
    return None
