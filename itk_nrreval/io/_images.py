"""Image input at the edge of the toolkit: arrays, SimpleITK / ITK images or files, checked.

Everything inside the toolkit works on numpy arrays in SimpleITK's array order
(``(z, y, x)`` for volumes); this module turns whatever the user handed in into such an
array plus the grid it lives on, and refuses grids that do not match with a message naming
the first offending file.

In-memory images
----------------
Wherever an image file is accepted, an image object is too: a SimpleITK or ITK image, or a
numpy array with its grid (:func:`~itk_nrreval.io._in_memory_images.to_sitk_image`). Their
conversion, the manifest's :class:`~itk_nrreval.io._in_memory_images.InMemoryImage` and the
content digests the result cache keys them by live in :mod:`itk_nrreval.io._in_memory_images`;
this module reads them as it reads files and lists those names for its importers.
"""

from __future__ import annotations

import functools
import os
import warnings
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from .._errors import InputError, readable
from .._executors import ITK_READ_LOCK
from ._in_memory_images import InMemoryImage, image_digest, is_finite, itk_kind, to_sitk_image

__all__ = [
    "Geometry",
    "ImageStack",
    "InMemoryImage",
    "read_image",
    "read_header",
    "check_components",
    "image_stack",
    "mask_array",
    "to_sitk_image",
    "image_digest",
    "is_finite",
    "itk_kind",
    "SPATIAL_DIMENSIONS",
    "dimension_problem",
    "label_like_values",
    "warn_label_like",
    "voxel_range",
    "LabelSummary",
    "label_summary",
]

ImageLike = "np.ndarray | sitk.Image | itk.Image | dict | str | os.PathLike"


@dataclass(frozen=True)
class Geometry:
    """The physical grid of an image, in ITK conventions.

    Attributes
    ----------
    size : tuple of int
        Voxels along (x, y[, z]) -- ITK order, the reverse of the numpy array shape.
    spacing : tuple of float
        Voxel size in mm along (x, y[, z]).
    origin : tuple of float
        Physical position (mm, LPS) of the first voxel's centre.
    direction : tuple of float
        Row-major direction cosine matrix, ``dim * dim`` values.
    """

    size: tuple[int, ...]
    spacing: tuple[float, ...]
    origin: tuple[float, ...]
    direction: tuple[float, ...]

    @classmethod
    def from_image(cls, image: sitk.Image) -> Geometry:
        return cls(
            tuple(int(s) for s in image.GetSize()),
            tuple(float(s) for s in image.GetSpacing()),
            tuple(float(o) for o in image.GetOrigin()),
            tuple(float(d) for d in image.GetDirection()),
        )

    @property
    def dimension(self) -> int:
        return len(self.size)

    @property
    def shape(self) -> tuple[int, ...]:
        """The numpy array shape, ``size`` reversed."""
        return tuple(reversed(self.size))

    def mismatch(self, other: Geometry, *, tol: float = 1e-5) -> str | None:
        """Describe how `other` differs from this grid, or return None when they match."""
        if self.size != other.size:
            return f"size {other.size} differs from {self.size}"
        for name in ("spacing", "origin", "direction"):
            a, b = np.asarray(getattr(self, name)), np.asarray(getattr(other, name))
            if not np.allclose(a, b, rtol=tol, atol=tol):
                return f"{name} {_plain(b)} differs from {_plain(a)}"
        return None

    def apply_to(self, image: sitk.Image) -> sitk.Image:
        """Stamp this grid's spacing, origin and direction onto `image` (same size)."""
        image.SetSpacing(self.spacing)
        image.SetOrigin(self.origin)
        image.SetDirection(self.direction)
        return image


def _plain(values: np.ndarray) -> str:
    """Grid values as a person writes them, ``(4938.5, 14.25, 103.0)``: Python floats rounded
    to 6 decimals (a numpy scalar's repr, ``np.float64(4938.5)``, is not for users)."""
    return readable(tuple(float(v) for v in np.round(values, 6)))


@dataclass(frozen=True)
class ImageStack:
    """N images on one grid.

    Attributes
    ----------
    data : ndarray of shape (n_images, *spatial)
        Voxel values, numpy order (``(z, y, x)`` per image).
    geometry : Geometry or None
        The shared grid; None when the input was a bare array.
    names : tuple of str
        A name per image (the file path, or ``"image[i]"``) for messages.
    """

    data: np.ndarray
    geometry: Geometry | None
    names: tuple[str, ...]


# ----------------------------------------------------------------------------- checks
# One set of checks on what an image holds, for every command and the manifest loader.

SPATIAL_DIMENSIONS = (2, 3)  # what the registrations, the frame and the warps are made for


def dimension_problem(dimension: int, *, what: str = "image") -> str | None:
    """Why an image of `dimension` spatial dimensions cannot be used, or None (2D or 3D).

    The text follows the image's name in a message: ``"s00.nii.gz is 4D; expected a 2D or
    3D image"``. A 4D file (a time series) would otherwise be scored as if its time axis
    were space.
    """
    if dimension in SPATIAL_DIMENSIONS:
        return None
    return f"is {dimension}D; expected a 2D or 3D {what}"


LABEL_LIKE_VALUES = 32  # an image with at most this many distinct integer values
_LABEL_LIKE_PROBE = 4096  # voxels looked at first: an intensity image is told apart there


def label_like_values(image: sitk.Image) -> int | None:
    """The number of distinct values when `image` looks like a label map, else None.

    It looks like one when every voxel value is an integer and there are at most
    :data:`LABEL_LIKE_VALUES` distinct values. A label map given as an image scores as a
    wildly variable texture (every label boundary a step of several intensity units):
    worth a warning (:func:`warn_label_like`), not an error.
    """
    arr = sitk.GetArrayViewFromImage(image)
    flat = arr.reshape(-1)
    # A regular subsample holds a subset of the values: when it already has a non-integer or
    # too many distinct values, so has the image, and the full sort below is skipped.
    probe = flat[:: max(1, flat.size // _LABEL_LIKE_PROBE)]
    for values in (probe, flat):
        if values.dtype.kind == "f" and not np.array_equal(values, np.round(values)):
            return None
        found = np.unique(values)
        if found.size > LABEL_LIKE_VALUES:
            return None
    return int(found.size)


def warn_label_like(name: str, n_values: int, *, stacklevel: int = 2) -> None:
    """Warn that image `name`, holding `n_values` distinct integer values, looks like a label map.

    `stacklevel` counts as :func:`warnings.warn`'s does from the caller of this function.
    """
    warnings.warn(
        f"{name}: the image holds only {n_values} distinct integer values: is it a label map "
        "given as an image?",
        UserWarning,
        stacklevel=stacklevel + 1,
    )


# ----------------------------------------------------------------------------- files


def read_header(path: str | os.PathLike) -> sitk.ImageFileReader:
    """An image file's header without its voxels (size, spacing, origin, direction,
    components, metadata), read under :data:`~itk_nrreval._executors.ITK_READ_LOCK`: ITK
    asks every image reader it knows, the HDF5 one included, whether it can read the file.

    Raises
    ------
    RuntimeError
        ITK cannot read the file (as ``ReadImageInformation``).
    """
    reader = sitk.ImageFileReader()
    reader.SetFileName(str(path))
    with ITK_READ_LOCK:
        reader.ReadImageInformation()
    return reader


def check_components(labels) -> None:
    """Refuse label maps that mix scalar and multi-component images (naming the first odd
    one); a single array, path or image passes. Unreadable items are left to
    :func:`image_stack` to report."""
    if isinstance(labels, (np.ndarray, str, os.PathLike, sitk.Image)):
        return
    first = None
    for i, item in enumerate(labels):
        try:
            if isinstance(item, sitk.Image):
                n = item.GetNumberOfComponentsPerPixel()
            else:
                n = read_header(item).GetNumberOfComponents()
        except (RuntimeError, TypeError):  # unreadable: image_stack reports it properly
            return
        if first is None:
            first = (n, str(item) if not isinstance(item, sitk.Image) else f"label map[{i}]")
        elif n != first[0]:
            name = str(item) if not isinstance(item, sitk.Image) else f"label map[{i}]"
            raise InputError(f"{name}: has {n} components per voxel, but {first[1]} has {first[0]}")


def read_image(path: str | os.PathLike | InMemoryImage, *, what: str = "image") -> sitk.Image:
    """Read one image with SimpleITK, turning any failure into a one-line :class:`InputError`.

    A floating-point image holding a NaN or an infinite voxel value is refused. NIfTI files
    are also read once (per process and file version) with nibabel, in slabs, because
    SimpleITK's NIfTI reader hides two kinds of damage: it returns NaN voxels as 0, and it
    zero-fills a truncated ``.nii.gz`` without a word. Either is an InputError here.

    An :class:`InMemoryImage` (a manifest's image object) gives its image, under the same
    checks; messages name its manifest item instead of a file.
    """
    if isinstance(path, InMemoryImage):
        if not path.finite:
            raise InputError(f"{path.name}: {what} contains NaN or infinite voxel values")
        return path.image
    if not isinstance(path, (str, os.PathLike)):
        raise InputError(f"{what}: expected a SimpleITK image or a path, got {type(path).__name__}")
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: {what} file not found")
    if path.is_dir():
        article = "an" if what[:1] in "aeiou" else "a"
        raise InputError(f"{path}: is a directory, expected {article} {what} file")
    try:
        with ITK_READ_LOCK:
            image = sitk.ReadImage(str(path))
    except RuntimeError as exc:
        first = str(exc).strip().splitlines()
        reason = next((ln for ln in first if "ERROR" not in ln and ln.strip()), "unreadable")
        raise InputError(f"{path}: cannot read {what} ({reason.strip()[:160]})") from None
    if _is_nifti(path):
        stat = path.stat()
        _check_nifti(str(path.resolve()), stat.st_size, stat.st_mtime_ns, what, str(path))
    elif not is_finite(image):
        raise InputError(f"{path}: {what} contains NaN or infinite voxel values")
    return image


_NIFTI_SLAB_BYTES = 1 << 26  # 64 MiB of voxel data per slab


class _NonFinite(Exception):
    """A NIfTI file holds a NaN or an infinite voxel value."""


class _Unreadable(Exception):
    """A NIfTI file's voxels cannot all be read (its text: why)."""


def _check_nifti(path: str, size: int, mtime_ns: int, what: str, shown: str) -> tuple[float, float]:
    """Read a NIfTI file's voxels with nibabel, slab by slab: every byte there, all finite.

    Returns the smallest and largest voxel value (:func:`voxel_range`). The pass is made once
    per process and file version (:func:`_nifti_range`, keyed by `size` and `mtime_ns`, so a
    file that changes is read again); `what` and `shown` (the path as the user gave it) only
    word the message.

    Raises
    ------
    InputError
        A NaN or infinite voxel value, or a truncated or corrupt file.
    """
    try:
        return _nifti_range(path, size, mtime_ns)
    except _NonFinite:
        raise InputError(f"{shown}: {what} contains NaN or infinite voxel values") from None
    except _Unreadable as exc:
        raise InputError(f"{shown}: {what} file is truncated or corrupt ({exc})") from None


@functools.lru_cache(maxsize=4096)
def _nifti_range(path: str, size: int, mtime_ns: int) -> tuple[float, float]:
    """(min, max) of a NIfTI file's voxels, read slab by slab; :class:`_NonFinite` or
    :class:`_Unreadable` when they cannot be used (not cached: raised again on a rerun)."""
    import nibabel as nib
    from nibabel.filebasedimages import ImageFileError

    try:
        img = nib.load(path, keep_file_open=True)
        proxy = img.dataobj
        shape = tuple(int(n) for n in img.shape)
        floating = np.issubdtype(img.get_data_dtype(), np.floating) or (
            img.header.get_slope_inter()[0] not in (None, 1.0)
        )
        # NIfTI stores the first axis fastest: slabs along the last axis are contiguous.
        per_index = int(np.prod(shape[:-1])) * img.get_data_dtype().itemsize
        step = max(1, _NIFTI_SLAB_BYTES // max(per_index, 1))
        low, high = np.inf, -np.inf
        for start in range(0, shape[-1], step):
            block = np.asarray(proxy[..., start : start + step])
            # min and max carry a NaN or an infinity through: two passes check the values
            # and give the range a constant image is told by
            lo, hi = float(block.min()), float(block.max())
            if floating and not (np.isfinite(lo) and np.isfinite(hi)):
                raise _NonFinite
            low, high = min(low, lo), max(high, hi)
    except _NonFinite:
        raise
    except (EOFError, OSError, ValueError, zlib.error, ImageFileError) as exc:
        reason = str(exc).strip().splitlines()[0][:120] if str(exc).strip() else type(exc).__name__
        raise _Unreadable(reason) from None
    return low, high


def _is_nifti(path: Path) -> bool:
    return path.name.lower().endswith((".nii", ".nii.gz"))


def _version(path: Path) -> tuple[str, int, int] | None:
    """A file's cache key for what is read from its voxels (resolved path, size, modification
    time); None for header + data pairs (``.mhd``, ``.nhdr``), whose data file's changes do
    not show in the header's times: those are read every time."""
    if path.name.lower().endswith((".mhd", ".nhdr")):
        return None
    stat = path.stat()
    return str(path.resolve()), stat.st_size, stat.st_mtime_ns


def voxel_range(
    item: str | os.PathLike | InMemoryImage, *, what: str = "image"
) -> tuple[float, float]:
    """The smallest and largest voxel value of an image file or in-memory image.

    Every voxel is looked at once and checked as :func:`read_image` checks it: a NaN or an
    infinite value, or a truncated NIfTI file, is an :class:`InputError` with its message. A
    NIfTI file's range comes from the nibabel pass :func:`read_image` makes anyway (kept per
    process and file version, so a later :func:`read_image` of it does not read it again);
    another file is read by ITK once per process and file version.

    Parameters
    ----------
    item : path or InMemoryImage
        The image (its header already known to be readable).
    what : str
        What it is, for messages (``"image"``).

    Returns
    -------
    (float, float)
        Its minimum and maximum; equal for a constant image, which carries no texture.
    """
    if isinstance(item, InMemoryImage):
        arr = sitk.GetArrayViewFromImage(read_image(item, what=what))
        return float(arr.min()), float(arr.max())
    path = Path(item)
    if not path.is_file():
        read_image(path, what=what)  # its message: not found, a folder
    if _is_nifti(path):
        return _check_nifti(str(path.resolve()), *_version(path)[1:], what, str(path))
    key = _version(path)
    if key is None:
        return _file_range(str(path), what)
    return _cached_file_range(*key, what, str(path))


def _file_range(path: str, what: str) -> tuple[float, float]:
    arr = sitk.GetArrayViewFromImage(read_image(path, what=what))
    return float(arr.min()), float(arr.max())


@functools.lru_cache(maxsize=4096)
def _cached_file_range(
    resolved: str, size: int, mtime_ns: int, what: str, shown: str
) -> tuple[float, float]:
    return _file_range(shown, what)


@dataclass(frozen=True)
class LabelSummary:
    """What a label map holds, from one read of its voxels (:func:`label_summary`).

    Attributes
    ----------
    values : tuple of int
        Its distinct values, ascending (background 0 included when present).
    foreground : tuple of (tuple of int, tuple of int), or None
        The first and last index, in ITK (x, y[, z]) order, of its nonzero voxels along each
        axis (the box they lie in); None when every voxel is 0.
    """

    values: tuple[int, ...]
    foreground: tuple[tuple[int, ...], tuple[int, ...]] | None


def label_summary(
    item: str | os.PathLike | InMemoryImage, *, what: str = "label map"
) -> LabelSummary:
    """The values of a label map and the box its labelled voxels lie in, from one read.

    A file's summary is kept per process and file version (as :func:`voxel_range`'s range).

    Raises
    ------
    InputError
        The file cannot be read (:func:`read_image`), or it holds a value that is not an
        integer (an intensity image given as a label map, most likely).
    """
    if isinstance(item, InMemoryImage):
        return _summarise_labels(read_image(item, what=what), item.name)
    path = Path(item)
    if not path.is_file() or (key := _version(path)) is None:
        return _summarise_labels(read_image(path, what=what), str(path))
    return _cached_label_summary(*key, what, str(path))


@functools.lru_cache(maxsize=4096)
def _cached_label_summary(
    resolved: str, size: int, mtime_ns: int, what: str, shown: str
) -> LabelSummary:
    return _summarise_labels(read_image(shown, what=what), shown)


def _summarise_labels(image: sitk.Image, name: str) -> LabelSummary:
    arr = sitk.GetArrayViewFromImage(image)
    found = np.unique(arr)
    if found.dtype.kind == "f":
        bad = found[found != np.round(found)]  # read_image refused non-finite values
        if bad.size:
            raise InputError(
                f"{name}: label map holds non-integer values (e.g. {float(bad[0]):g}; "
                f"{bad.size} of {found.size} distinct values): is it an intensity image?"
            )
    nonzero = arr != 0
    if not nonzero.any():
        return LabelSummary(tuple(int(v) for v in found), None)
    # numpy axes are ITK's reversed: the box along ITK axis k is along numpy axis d - 1 - k
    d = arr.ndim
    first, last = [], []
    for k in range(d):
        along = np.flatnonzero(nonzero.any(axis=tuple(a for a in range(d) if a != d - 1 - k)))
        first.append(int(along[0]))
        last.append(int(along[-1]))
    return LabelSummary(tuple(int(v) for v in found), (tuple(first), tuple(last)))


def _as_sitk(item, name: str, what: str) -> sitk.Image:
    if isinstance(item, sitk.Image):
        return item
    if isinstance(item, (str, os.PathLike, InMemoryImage)):
        return read_image(item, what=what)
    image = to_sitk_image(item, name=name)  # an ITK image, an array with its grid
    if not is_finite(image):
        raise InputError(f"{name}: {what} contains NaN or infinite voxel values")
    return image


def image_stack(
    images,
    *,
    what: str = "image",
    dtype=np.float64,
    allow_vector: bool = False,
    warn_if_label_like: bool = False,
) -> ImageStack:
    """Turn an array, a list of SimpleITK images or a list of paths into an :class:`ImageStack`.

    Parameters
    ----------
    images : ndarray of shape (n_images, *spatial), or sequence of images or paths
        The images. A bare array carries no grid, so nothing is checked but its values. A
        sequence may mix paths, SimpleITK and ITK images, and arrays with their grid (see
        the module docstring).
    what : str
        What the images are ("image", "label map"), for messages.
    dtype : numpy dtype or None
        Cast the voxel values to this type; None keeps the file's type.
    allow_vector : bool
        Accept multi-component images; components become the second axis of ``data``.
    warn_if_label_like : bool
        Warn about each image of a sequence that looks like a label map
        (:func:`label_like_values`), as ``evaluate`` does.

    Raises
    ------
    InputError
        Unreadable files, images that are not 2D or 3D (:func:`dimension_problem`), images
        whose size, spacing, origin or direction differ from the first one's (the message
        names the first offending image), or non-finite values.
    """
    if isinstance(images, np.ndarray):
        data = images if dtype is None else np.asarray(images, dtype=dtype)
        names = tuple(f"{what}[{i}]" for i in range(data.shape[0])) if data.ndim else ()
        if data.ndim < 2:
            raise InputError(
                f"{what}s: expected an array of shape (n_images, *spatial), got {data.shape}"
            )
        _check_finite(data, names)
        return ImageStack(data, None, names)
    if isinstance(images, (str, os.PathLike, sitk.Image)) or not isinstance(images, Sequence):
        raise InputError(
            f"{what}s: expected a sequence of images or paths, got {type(images).__name__}"
        )
    if len(images) == 0:
        raise InputError(f"{what}s: the list is empty")
    names = tuple(
        str(item) if isinstance(item, (str, os.PathLike)) else f"{what}[{i}]"
        for i, item in enumerate(images)
    )
    geometry = None
    arrays = []
    for item, name in zip(images, names, strict=True):
        img = _as_sitk(item, name, what)
        if (problem := dimension_problem(img.GetDimension(), what=what)) is not None:
            raise InputError(f"{name}: {problem}")
        if img.GetNumberOfComponentsPerPixel() > 1 and not allow_vector:
            raise InputError(
                f"{name}: has {img.GetNumberOfComponentsPerPixel()} components per voxel, "
                f"expected a scalar {what}"
            )
        g = Geometry.from_image(img)
        if geometry is None:
            geometry = g
        elif (problem := geometry.mismatch(g)) is not None:
            raise InputError(f"{name}: not on the grid of {names[0]}: {problem}")
        if warn_if_label_like and (n_values := label_like_values(img)) is not None:
            warn_label_like(name, n_values)
        arr = sitk.GetArrayFromImage(img)
        if arr.ndim == g.dimension + 1:  # vector image: components last in sitk, first for us
            arr = np.moveaxis(arr, -1, 0)
        arrays.append(arr if dtype is None else arr.astype(dtype, copy=False))
    data = np.stack(arrays)
    _check_finite(data, names)
    return ImageStack(data, geometry, names)


def _check_finite(data: np.ndarray, names: Sequence[str]) -> None:
    if not np.issubdtype(data.dtype, np.floating):
        return
    flat = data.reshape(data.shape[0], -1)
    # A NaN or infinity makes an image's sum non-finite, so one cheap reduction clears the
    # usual case; only images whose sum is not finite (or overflowed) are checked voxel-wise.
    with np.errstate(over="ignore", invalid="ignore"):
        sums = np.add.reduce(flat, axis=1)
    for i in np.flatnonzero(~np.isfinite(sums)):
        if not np.isfinite(flat[i]).all():
            raise InputError(f"{names[i]}: contains NaN or infinite voxel values")


def mask_array(mask, *, shape: tuple[int, ...], geometry: Geometry | None) -> np.ndarray | None:
    """A boolean mask of numpy shape `shape` from an array, an image or a path (None passes).

    A mask image (file, SimpleITK / ITK image, array with its grid, :class:`InMemoryImage`)
    must lie on `geometry` (when known); nonzero voxels are inside.
    """
    if mask is None:
        return None
    name = str(mask) if isinstance(mask, (str, os.PathLike, InMemoryImage)) else "mask"
    if isinstance(mask, np.ndarray):
        arr = mask
    else:
        img = _as_sitk(mask, name, "mask")
        if geometry is not None and (problem := geometry.mismatch(Geometry.from_image(img))):
            raise InputError(f"{name}: mask is not on the images' grid: {problem}")
        arr = sitk.GetArrayFromImage(img)
    if arr.shape != tuple(shape):
        raise InputError(f"{name}: mask shape {arr.shape} differs from the images' {tuple(shape)}")
    arr = arr != 0
    if not arr.any():
        raise InputError(f"{name}: mask is empty (no nonzero voxel)")
    return arr
