"""Image input at the edge of the toolkit: arrays, SimpleITK images or files, checked.

Everything inside the toolkit works on numpy arrays in SimpleITK's array order
(``(z, y, x)`` for volumes); this module turns whatever the user handed in into such an
array plus the grid it lives on, and refuses grids that do not match with a message naming
the first offending file.
"""

from __future__ import annotations

import functools
import os
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from ._errors import InputError

__all__ = ["Geometry", "ImageStack", "read_image", "image_stack", "mask_array"]

ImageLike = "np.ndarray | sitk.Image | str | os.PathLike"


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
                return f"{name} {tuple(np.round(b, 6))} differs from {tuple(np.round(a, 6))}"
        return None

    def apply_to(self, image: sitk.Image) -> sitk.Image:
        """Stamp this grid's spacing, origin and direction onto `image` (same size)."""
        image.SetSpacing(self.spacing)
        image.SetOrigin(self.origin)
        image.SetDirection(self.direction)
        return image


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


def read_image(path: str | os.PathLike, *, what: str = "image") -> sitk.Image:
    """Read one image with SimpleITK, turning any failure into a one-line :class:`InputError`.

    NIfTI files are also read once (per process and file version) with nibabel, in slabs,
    because SimpleITK's NIfTI reader hides two kinds of damage: it returns NaN voxels as 0,
    and it zero-fills a truncated ``.nii.gz`` without a word. Either is an InputError here.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: {what} file not found")
    if path.is_dir():
        raise InputError(f"{path}: is a directory, expected an {what} file")
    try:
        image = sitk.ReadImage(str(path))
    except RuntimeError as exc:
        first = str(exc).strip().splitlines()
        reason = next((ln for ln in first if "ERROR" not in ln and ln.strip()), "unreadable")
        raise InputError(f"{path}: cannot read {what} ({reason.strip()[:160]})") from None
    if path.name.lower().endswith((".nii", ".nii.gz")):
        stat = path.stat()
        _check_nifti(str(path.resolve()), stat.st_size, stat.st_mtime_ns, what, str(path))
    return image


_NIFTI_SLAB_BYTES = 1 << 26  # 64 MiB of voxel data per slab


@functools.lru_cache(maxsize=4096)
def _check_nifti(path: str, size: int, mtime_ns: int, what: str, shown: str) -> None:
    """Read a NIfTI file's voxels with nibabel, slab by slab: every byte there, all finite.

    `size` and `mtime_ns` are part of the cache key, so a file that changes is checked again;
    `shown` is the path as the user gave it, for messages.
    """
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
        for start in range(0, shape[-1], step):
            block = np.asarray(proxy[..., start : start + step])
            if floating and not np.isfinite(block).all():
                raise InputError(f"{shown}: {what} contains NaN or infinite voxel values")
    except InputError:
        raise
    except (EOFError, OSError, ValueError, zlib.error, ImageFileError) as exc:
        reason = str(exc).strip().splitlines()[0][:120] if str(exc).strip() else type(exc).__name__
        raise InputError(f"{shown}: {what} file is truncated or corrupt ({reason})") from None


def _as_sitk(item, name: str, what: str) -> sitk.Image:
    if isinstance(item, sitk.Image):
        return item
    if isinstance(item, (str, os.PathLike)):
        return read_image(item, what=what)
    raise InputError(
        f"{name}: expected a SimpleITK image or a file path, got {type(item).__name__}"
    )


def image_stack(
    images, *, what: str = "image", dtype=np.float64, allow_vector: bool = False
) -> ImageStack:
    """Turn an array, a list of SimpleITK images or a list of paths into an :class:`ImageStack`.

    Parameters
    ----------
    images : ndarray of shape (n_images, *spatial), or sequence of sitk.Image or paths
        The images. A bare array carries no grid, so nothing is checked but its values.
    what : str
        What the images are ("image", "label map"), for messages.
    dtype : numpy dtype or None
        Cast the voxel values to this type; None keeps the file's type.
    allow_vector : bool
        Accept multi-component images; components become the second axis of ``data``.

    Raises
    ------
    InputError
        Unreadable files, or images whose size, spacing, origin or direction differ from the
        first one's (the message names the first offending image), or non-finite values.
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
    """A boolean mask of numpy shape `shape` from an array, SimpleITK image or path (None passes).

    A mask image must lie on `geometry` (when known); nonzero voxels are inside.
    """
    if mask is None:
        return None
    name = str(mask) if isinstance(mask, (str, os.PathLike)) else "mask"
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
