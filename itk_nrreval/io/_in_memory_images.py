"""In-memory images: images handed in as objects rather than files, and their digests.

Wherever an image file is accepted, an image object is too (:func:`to_sitk_image`):

* a ``SimpleITK.Image``;
* an ITK Python image (``itk.Image``, ``itk.VectorImage``; the ``itk`` package that
  itk-elastix installs), converted with its array view and its origin, spacing and direction
  carried over exactly;
* a numpy array *with its grid*, as a dict ``{"array": a, "spacing": s, "origin": o,
  "direction": d}``: ``a`` in numpy order (``(z, y, x)`` for a volume, the reverse of ITK's
  index order, as ``sitk.GetArrayFromImage`` gives it; a trailing axis of components for a
  vector image such as a displacement field), ``s`` the voxel size in mm and ``o`` the
  physical position (mm, LPS) of the first voxel's centre, both in ITK (x, y[, z]) order,
  ``d`` the direction cosines (``dim * dim`` values, row-major, or a ``dim x dim`` matrix).
  All four keys are required: a bare array has no grid, and a guessed grid would give
  numbers that are silently wrong.

A manifest keeps such an object as an :class:`InMemoryImage`: a private SimpleITK copy,
the manifest item's name for messages (``images[3]``), and a digest of its content (pixel
type, grid, voxel values; :func:`image_digest`) that the result cache uses as its key -- the
same key as a file holding the same image (:func:`itk_nrreval.io._cache.content_digest`).
:func:`itk_nrreval.io._images.read_image` reads it as it reads a file.
"""

from __future__ import annotations

import hashlib
import pickle
import sys
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
import SimpleITK as sitk

from .._errors import InputError

__all__ = [
    "ARRAY_KEYS",
    "InMemoryImage",
    "to_sitk_image",
    "image_digest",
    "is_finite",
    "itk_kind",
    "source_kind",
]

#: The keys of an array given with its grid (module docstring).
ARRAY_KEYS = ("array", "spacing", "origin", "direction")


def itk_kind(value) -> str | None:
    """``"image"`` or ``"transform"`` for an ITK Python object, else None (never imports itk)."""
    if "itk" not in sys.modules:  # no ITK object can exist before the package is imported
        return None
    names = [c.__name__ for c in type(value).__mro__]
    if any(n.startswith("itkImageBase") for n in names):
        return "image"
    if any(n.startswith("itkTransformBaseTemplate") for n in names):
        return "transform"
    return None


def source_kind(value) -> str:
    """A short name of what an in-memory object is, for messages and descriptions."""
    if isinstance(value, sitk.Image):
        return "sitk.Image"
    if isinstance(value, sitk.Transform):
        return "sitk.Transform"
    if isinstance(value, Mapping):
        return "array"
    kind = itk_kind(value)
    return f"itk.{kind.capitalize()}" if kind else type(value).__name__


def to_sitk_image(value, *, name: str = "image") -> sitk.Image:
    """A SimpleITK image from a SimpleITK image, an ITK Python image or an array with its grid.

    Parameters
    ----------
    value : sitk.Image, itk.Image or dict
        See the module docstring for the dict form ``{"array", "spacing", "origin",
        "direction"}``. The voxel values keep their type (a ``bool`` array becomes
        ``uint8``).
    name : str
        What to call `value` in messages.

    Returns
    -------
    sitk.Image
        A copy (SimpleITK copies on write): later changes to `value` do not reach it.
        Origin, spacing and direction are ITK's (mm, LPS), carried over exactly.

    Raises
    ------
    InputError
        An unsupported object, a bare numpy array, or a dict whose grid does not fit its array.
    """
    if isinstance(value, sitk.Image):
        return sitk.Image(value)
    if isinstance(value, Mapping):
        return _from_array(value, name)
    if itk_kind(value) == "image":
        return _from_itk(value, name)
    if isinstance(value, np.ndarray):
        raise InputError(
            f"{name}: a numpy array has no grid; give it as "
            "{'array': a, 'spacing': ..., 'origin': ..., 'direction': ...}"
        )
    raise InputError(
        f"{name}: expected a file path or an image (sitk.Image, itk.Image, or "
        f"{{'array', 'spacing', 'origin', 'direction'}}), got {type(value).__name__}"
    )


def _from_array(value: Mapping, name: str) -> sitk.Image:
    missing = [k for k in ARRAY_KEYS if k not in value]
    unknown = [str(k) for k in value if k not in ARRAY_KEYS]
    if missing or unknown:
        what = f"missing {', '.join(missing)}" if missing else f"unknown {', '.join(unknown)}"
        raise InputError(
            f"{name}: an array needs exactly the keys {', '.join(ARRAY_KEYS)} ({what})"
        )
    arr = np.asarray(value["array"])
    if arr.dtype == np.bool_:
        arr = arr.astype(np.uint8)
    try:
        spacing = tuple(float(v) for v in value["spacing"])
        origin = tuple(float(v) for v in value["origin"])
        direction = tuple(float(v) for v in np.asarray(value["direction"], np.float64).ravel())
    except (TypeError, ValueError):
        raise InputError(f"{name}: spacing, origin and direction must be numbers") from None
    dim = len(spacing)
    if len(origin) != dim or len(direction) != dim * dim:
        raise InputError(
            f"{name}: {dim} spacings need {dim} origin values and {dim * dim} direction "
            f"values, got {len(origin)} and {len(direction)}"
        )
    if arr.dtype.kind not in "iuf" or arr.ndim not in (dim, dim + 1):
        raise InputError(
            f"{name}: expected a numeric array with {dim} axes (or {dim + 1}, components "
            f"last) for {dim} spacings, got {arr.dtype} of shape {arr.shape}"
        )
    try:
        image = sitk.GetImageFromArray(arr, isVector=arr.ndim == dim + 1)
        image.SetSpacing(spacing)
        image.SetOrigin(origin)
        image.SetDirection(direction)
    except (RuntimeError, TypeError, ValueError) as exc:
        reason = next((ln for ln in str(exc).splitlines() if ln.strip()), "refused")
        raise InputError(f"{name}: not a valid image ({reason.strip()[:120]})") from None
    return image


def _from_itk(value, name: str) -> sitk.Image:
    """Copy an ITK Python image into SimpleITK: the same voxels, in the same index order."""
    import itk

    buffered, largest = value.GetBufferedRegion(), value.GetLargestPossibleRegion()
    if tuple(buffered.GetSize()) != tuple(largest.GetSize()) or tuple(buffered.GetIndex()) != tuple(
        largest.GetIndex()
    ):
        raise InputError(
            f"{name}: the ITK image's buffer does not hold its whole grid "
            "(call Update() on the filter that made it)"
        )
    dim = int(value.GetImageDimension())
    # ITK's array view is in numpy order, (z, y, x[, components]): the layout of
    # sitk.GetImageFromArray, so no axis is swapped (checked voxel by voxel in the tests).
    arr = np.ascontiguousarray(itk.array_view_from_image(value))
    image = sitk.GetImageFromArray(arr, isVector=arr.ndim == dim + 1)
    start = tuple(int(i) for i in buffered.GetIndex())
    # sitk images start at index 0: an ITK grid starting elsewhere moves its origin there
    origin = value.GetOrigin() if not any(start) else value.TransformIndexToPhysicalPoint(start)
    image.SetOrigin(tuple(float(v) for v in origin))
    image.SetSpacing(tuple(float(v) for v in value.GetSpacing()))
    direction = np.asarray(itk.array_from_matrix(value.GetDirection()), np.float64)
    image.SetDirection(tuple(float(v) for v in direction.ravel()))  # row-major, as sitk
    return image


def image_digest(image: sitk.Image) -> str:
    """BLAKE2b (128-bit) hex digest of what an image holds: pixel type, grid, voxel values.

    Metadata (header fields, file name) is left out, so a file and the image read from it,
    or the same image from ITK or an array, give the same digest. A vector image of ``dim``
    components on a ``dim``-D grid is digested as the displacement field it would be (float64
    values), so it equals the digest of the ``sitk.DisplacementFieldTransform`` made from it
    (:func:`itk_nrreval.io.transforms.transform_digest`).
    """
    h = hashlib.blake2b(digest_size=16)
    dim, comps = image.GetDimension(), image.GetNumberOfComponentsPerPixel()
    arr = sitk.GetArrayViewFromImage(image)
    if comps == dim > 1:
        h.update(b"field:")
        arr = arr.astype(np.float64)
    else:
        h.update(f"image:{image.GetPixelIDTypeAsString()}:{comps}:".encode())
    grid = (image.GetSize(), image.GetSpacing(), image.GetOrigin(), image.GetDirection())
    h.update(repr(tuple(tuple(float(v) for v in part) for part in grid)).encode())
    h.update(np.ascontiguousarray(arr).data)
    return h.hexdigest()


def is_finite(image: sitk.Image) -> bool:
    """Whether every voxel value of `image` is finite (integer images always are)."""
    arr = sitk.GetArrayViewFromImage(image)
    if not np.issubdtype(arr.dtype, np.floating):
        return True
    with np.errstate(over="ignore", invalid="ignore"):
        if np.isfinite(np.add.reduce(arr, axis=None)):  # one cheap reduction clears most
            return True
    return bool(np.isfinite(arr).all())


@dataclass(frozen=True, eq=False)
class InMemoryImage:
    """An image of a manifest handed in as an object rather than a file.

    Attributes
    ----------
    image : sitk.Image
        A private SimpleITK copy (:func:`to_sitk_image`).
    name : str
        The manifest item it was given as (``images[3]``, ``registrations.fluid.reference``),
        for messages; also ``str()`` of the object.
    source : str
        What it was given as: ``"sitk.Image"``, ``"itk.Image"`` or ``"array"``.
    content_digest : str
        :func:`image_digest` of `image`: the result cache's key for it.
    finite : bool
        Whether every voxel value is finite; reading it (:func:`read_image`) refuses it if not,
        as it refuses such a file.

    Pickles with its image, so it travels to Dask workers: as in-band bytes, never as an
    out-of-band view of SimpleITK's buffer that does not keep the image alive (pickle
    protocol 5, which Dask uses).
    """

    image: sitk.Image = field(repr=False)
    name: str
    source: str
    content_digest: str
    finite: bool

    def __reduce__(self):
        state = (self.name, self.source, self.content_digest, self.finite)
        return _restore_image, (pickle.dumps(self.image, protocol=4), *state)

    @classmethod
    def from_object(cls, value, *, name: str) -> InMemoryImage:
        """Wrap a SimpleITK / ITK image or an array with its grid; InputError naming `name`."""
        image = to_sitk_image(value, name=name)
        return cls(image, name, source_kind(value), image_digest(image), is_finite(image))

    def __str__(self) -> str:
        return self.name

    @property
    def label(self) -> str:
        """How messages refer to it where they give a file's name."""
        return f"the in-memory {self.source}"

    def describe(self) -> str:
        """A one-line description for reports (its name, type and content digest)."""
        size = "x".join(str(s) for s in self.image.GetSize())
        return (
            f"<in-memory {self.source} {self.name}: {self.image.GetPixelIDTypeAsString()} "
            f"{size}, content {self.content_digest[:12]}>"
        )


def _restore_image(data: bytes, *state) -> InMemoryImage:
    return InMemoryImage(pickle.loads(data), *state)
