"""Reading, chaining, inverting and checking registration transforms (SimpleITK at the edge).

Conventions
-----------
* Every transform maps **reference (fixed) points to image (moving) points**, in physical
  coordinates (mm, LPS), as ITK, SimpleITK, ANTs and elastix write them: an image is
  resampled onto the reference grid by looking up, for each reference voxel centre p, the
  image value at T(p).
* A **chain** is listed in the order ANTs reports ``fwdtransforms``: the first listed acts
  first. ``[s00_1Warp.nii.gz, s00_0GenericAffine.mat]`` maps a reference point p to the
  image point ``affine(warp(p))``. ``sitk.CompositeTransform`` applies the *last* transform
  of its list first, so it is given the reversed list (:func:`chain_transform` does this).
* Displacement fields are vector images whose vectors are physical displacements (mm) with
  components in ITK (x, y[, z]) order; ``sitk.GetArrayFromImage`` gives them as numpy
  arrays of shape ``(*spatial_zyx, dim)``. ANTs ``*1Warp.nii.gz`` files are 5D NIfTI
  ``(X, Y, Z, 1, 3)``; SimpleITK reads them as 3D images of 3-vectors (float32), which are
  cast to float64 here. A displacement field is always interpolated linearly.

In-memory transforms
--------------------
Wherever a transform file is accepted, a transform object is too (:func:`to_sitk_transform`):
a ``sitk.Transform`` of any kind (composites included), an ITK Python transform (converted
through a temporary HDF5 file, ITK's own transform IO, so every type ITK can write comes
over with its exact parameters), or a displacement field given as an image (SimpleITK, ITK,
or an array with its grid, see :mod:`itk_nrreval._images`). A manifest keeps such an object
as an :class:`InMemoryTransform`: a private copy, the manifest item's name for messages
(``registrations.fluid.transforms[3]``), and a digest of its content
(:func:`transform_digest`: each piece's type, parameters and fixed parameters, a field's
values and grid) that the result cache uses as its key -- the same key as a file holding
the same transform.
"""

from __future__ import annotations

import hashlib
import math
import os
import pickle
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numba
import numpy as np
import SimpleITK as sitk

from ._elastix_files import is_elastix_parameter_file, read_elastix_transform
from ._errors import InputError
from ._executors import ITK_READ_LOCK
from ._foreign_transforms import ForeignTransform
from ._images import Geometry, read_image
from ._in_memory_images import image_digest, is_finite, itk_kind, source_kind, to_sitk_image
from ._itk_hdf5 import check_file as check_hdf5_file
from ._itk_hdf5 import read_pieces as read_hdf5_pieces
from ._output import atomic_path

__all__ = [
    "TRANSFORM_SUFFIXES",
    "FIELD_SUFFIXES",
    "InMemoryTransform",
    "to_sitk_transform",
    "transform_digest",
    "read_transform",
    "file_stem",
    "file_suffix",
    "leaves",
    "chain_transform",
    "TransformPieces",
    "transform_pieces",
    "flatten",
    "write_transform",
    "field_transform",
    "displacement_field",
    "invert",
    "INVERSION_STOPPING",
    "PointwiseInverse",
    "composed_displacement",
    "displacement_after",
    "displacement_array",
    "PointMap",
    "has_only_fields",
    "is_linear",
    "jacobian_determinant",
    "folded_fraction",
    "field_components_problem",
]

#: File suffixes read with ``sitk.ReadTransform`` (ITK text / HDF5 / MATLAB, incl. ANTs affines).
TRANSFORM_SUFFIXES = (".tfm", ".txt", ".h5", ".hdf5", ".mat")
#: File suffixes read as displacement-field images.
FIELD_SUFFIXES = (".nii.gz", ".nii", ".nrrd", ".nhdr", ".mha", ".mhd")

_TransformLike = "sitk.Transform | itk.Transform | InMemoryTransform | str | os.PathLike"


def file_stem(path: str | os.PathLike) -> str:
    """The file name without its image suffix (``s01.nii.gz`` -> ``s01``), else without its
    last suffix: a name for what is written about that image."""
    name = Path(path).name
    for suffix in FIELD_SUFFIXES:
        if name.endswith(suffix):
            return name[: -len(suffix)]
    return Path(name).stem


def file_suffix(path: Path) -> str:
    """The lower-case suffix that decides a file's format (``.nii.gz`` counts as one)."""
    name = path.name.lower()
    return ".nii.gz" if name.endswith(".nii.gz") else path.suffix.lower()


def _reason(exc: Exception) -> str:
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    useful = [ln for ln in lines if not ln.startswith("sitk::ERROR") and "ERROR" not in ln[:12]]
    return ((useful or lines or ["unreadable"])[-1])[:160]


def field_transform(field: sitk.Image) -> sitk.DisplacementFieldTransform:
    """A displacement-field transform from a vector image, without consuming the image.

    Parameters
    ----------
    field : sitk.Image
        Vector image of ``dim`` components per voxel (mm, ITK (x, y[, z]) order): the
        transform maps p to ``p + field(p)`` (linear interpolation; zero outside the grid).

    Returns
    -------
    sitk.DisplacementFieldTransform
        Owns a float64 copy (``sitk.DisplacementFieldTransform(img)`` empties ``img``).
    """
    dim = field.GetDimension()
    if field.GetNumberOfComponentsPerPixel() != dim:
        raise InputError(
            f"displacement field: {field.GetNumberOfComponentsPerPixel()} components per voxel "
            f"for a {dim}D grid (expected {dim})"
        )
    copy = sitk.Cast(field, sitk.sitkVectorFloat64)  # always a new image
    return sitk.DisplacementFieldTransform(copy)


# ----------------------------------------------------------------------------- in memory


def to_sitk_transform(value, *, name: str = "transform") -> sitk.Transform:
    """A SimpleITK transform from a SimpleITK or ITK Python transform, or a displacement field.

    Parameters
    ----------
    value : sitk.Transform, itk.Transform, or an image
        Any SimpleITK transform (composites included); any ITK Python transform that ITK's
        HDF5 transform IO writes (composites included; float transforms become double); a
        displacement field as a vector image (``sitk.Image``, ``itk.Image``, or the array
        form of :func:`itk_nrreval._images.to_sitk_image`, components last), mm, ITK
        (x, y[, z]) order. Every transform maps reference points to image points.
    name : str
        What to call `value` in messages.

    Returns
    -------
    sitk.Transform
        A private copy in a canonical form: nested composites flattened, every displacement
        field a float64 ``DisplacementFieldTransform`` interpolated linearly (what a field
        read from a file becomes); the same mapping.

    Raises
    ------
    InputError
        An unsupported object, an ITK transform that cannot be converted, or a field image
        without one vector component per dimension.
    """
    if isinstance(value, sitk.Transform):
        return _canonical(value, name)
    kind = itk_kind(value)
    if kind == "transform":
        return _canonical(_from_itk(value, name), name)
    if kind == "image" or isinstance(value, (sitk.Image, Mapping)):
        return field_transform(_field_image(value, name))
    raise InputError(
        f"{name}: expected a file path, a transform (sitk.Transform, itk.Transform) or a "
        f"displacement field image, got {type(value).__name__}"
    )


def _field_image(value, name: str) -> sitk.Image:
    """A displacement field given as an image, as a SimpleITK vector image (not copied)."""
    image = to_sitk_image(value, name=name)
    dim, comps = image.GetDimension(), image.GetNumberOfComponentsPerPixel()
    if comps != dim:
        raise InputError(
            f"{name}: cannot read transform the in-memory {source_kind(value)} "
            f"({field_components_problem(dim, comps)})"
        )
    return image


def field_components_problem(dim: int, comps: int) -> str:
    """The words for a displacement field without one vector component per dimension."""
    return f"a displacement field needs {dim} vector components per voxel, has {comps}"


def _canonical(transform: sitk.Transform, name: str) -> sitk.Transform:
    parts = [
        field_transform(t.GetDisplacementField())
        if isinstance(t, sitk.DisplacementFieldTransform)
        else t
        for t in leaves(transform)
    ]
    if not parts:
        raise InputError(f"{name}: an empty composite transform")
    return parts[0] if len(parts) == 1 else sitk.CompositeTransform(parts)


def _from_itk(value, name: str) -> sitk.Transform:
    """An ITK Python transform through ITK's HDF5 writer and SimpleITK's reader (exact)."""
    import itk

    with tempfile.TemporaryDirectory(prefix="nrreval-itk-") as tmp:
        path = os.path.join(tmp, "transform.h5")
        try:
            with ITK_READ_LOCK:
                itk.transformwrite([value], path)
                return sitk.ReadTransform(path)
        except (RuntimeError, TypeError, ValueError) as exc:
            raise InputError(
                f"{name}: cannot convert the ITK transform {type(value).__name__} ({_reason(exc)})"
            ) from None


def transform_digest(transform: sitk.Transform) -> str:
    """BLAKE2b (128-bit) hex digest of what a transform is: its pieces' types and parameters.

    A composite is digested as the list of its pieces (:func:`leaves`; nesting does not
    matter), each by its class name, dimension, fixed parameters and parameters (and a
    B-spline's order); a displacement field by its float64 values and grid, exactly as
    :func:`itk_nrreval._images.image_digest` digests the vector image it came from. So a
    transform file and the transform read from it, or the same transform from ITK, give the
    same digest; a single piece gives the digest of that piece.
    """
    digests = [_piece_digest(t) for t in leaves(transform)]
    if len(digests) == 1:
        return digests[0]
    h = hashlib.blake2b(digest_size=16)
    h.update(("composite:" + ",".join(digests)).encode())
    return h.hexdigest()


def _piece_digest(t: sitk.Transform) -> str:
    if isinstance(t, sitk.DisplacementFieldTransform):
        field = t.GetDisplacementField()
        if field.GetNumberOfPixels() > 0:
            return image_digest(field)
    h = hashlib.blake2b(digest_size=16)
    h.update(f"{t.GetName()}:{t.GetDimension()}:".encode())
    if isinstance(t, sitk.BSplineTransform):
        h.update(f"order {t.GetOrder()}:".encode())
    h.update(np.asarray(t.GetFixedParameters(), np.float64).tobytes())
    h.update(b":")
    h.update(np.asarray(t.GetParameters(), np.float64).tobytes())
    return h.hexdigest()


#: Transform files already found finite, by :func:`_file_signature`: the check takes a
#: composite apart, which copies every displacement field (~0.1 s at 1 mm), and a run reads
#: one file several times (its key, its image's task, frame estimates, checks of mix-ups).
_FINITE_FILES: set[tuple] = set()


def _check_finite_file(signature: tuple, transform) -> None:
    """InputError unless the file of `signature`, read as `transform` (or its pieces), was
    found finite before or is now (then remembered)."""
    if signature not in _FINITE_FILES and not _finite(transform):
        raise InputError("transform contains NaN or infinite values")
    if len(_FINITE_FILES) >= 4096:
        _FINITE_FILES.clear()
    _FINITE_FILES.add(signature)


def _file_signature(path: Path) -> tuple:
    """What changes when a file's content may have: its path, size, times and inode."""
    st = path.stat()
    return (str(path.resolve()), st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino)


def _finite(transform: sitk.Transform) -> bool:
    """Whether every parameter (every field value) of every piece is finite."""
    for t in leaves(transform):
        if isinstance(t, sitk.DisplacementFieldTransform):
            values = sitk.GetArrayViewFromImage(t.GetDisplacementField())
        else:
            values = np.asarray(t.GetFixedParameters() + t.GetParameters(), np.float64)
        if not np.isfinite(values).all():
            return False
    return True


@dataclass(frozen=True, eq=False)
class InMemoryTransform:
    """A transform of a manifest handed in as an object rather than a file.

    Attributes
    ----------
    value : sitk.Transform or sitk.Image
        A private copy: a transform in canonical form (:func:`to_sitk_transform`), or a
        displacement field given as an image, kept as that image (SimpleITK copies on
        write, so a field the caller holds is not duplicated in memory); :attr:`transform`
        makes the transform of it when it is read, as for a field file.
    name : str
        The manifest item it was given as (``registrations.fluid.transforms[3]``), for
        messages; also ``str()`` of the object.
    source : str
        What it was given as (``"sitk.Transform"``, ``"itk.Transform"``, ``"sitk.Image"``...).
    content_digest : str
        :func:`transform_digest` of :attr:`transform` (for a field image, the equal
        :func:`itk_nrreval._images.image_digest`): the result cache's key for it.
    finite : bool
        Whether every parameter (field value) is finite; reading it (:func:`read_transform`)
        refuses it if not, as it refuses such a file.

    Pickles with its transform, so it travels to Dask workers: as in-band bytes, because
    SimpleITK's own pickling of a displacement field (or B-spline) transform hands pickle
    protocol 5 (Dask's) an out-of-band buffer of a temporary image, which is freed before the
    buffer is sent -- the worker would read freed memory.
    """

    value: sitk.Transform | sitk.Image = field(repr=False)
    name: str
    source: str
    content_digest: str
    finite: bool

    def __reduce__(self):
        state = (self.name, self.source, self.content_digest, self.finite)
        return _restore_transform, (pickle.dumps(self.value, protocol=4), *state)

    @classmethod
    def from_object(cls, value, *, name: str) -> InMemoryTransform:
        """Wrap a transform or a displacement field image; InputError naming `name`."""
        if itk_kind(value) == "image" or isinstance(value, (sitk.Image, Mapping)):
            image = _field_image(value, name)
            return cls(image, name, source_kind(value), image_digest(image), is_finite(image))
        t = to_sitk_transform(value, name=name)
        return cls(t, name, source_kind(value), transform_digest(t), _finite(t))

    def __str__(self) -> str:
        return self.name

    @property
    def transform(self) -> sitk.Transform:
        """The transform: reference points -> image points (mm, LPS)."""
        if isinstance(self.value, sitk.Image):
            return field_transform(self.value)
        return self.value

    @property
    def dimension(self) -> int:
        return int(self.value.GetDimension())

    def describe(self) -> str:
        """A one-line description for reports (its name, type and content digest)."""
        if isinstance(self.value, sitk.Image):
            kinds = "DisplacementFieldTransform"
        else:
            kinds = "+".join(t.GetName() for t in leaves(self.value))
        return f"<in-memory {self.source} {self.name}: {kinds}, content {self.content_digest[:12]}>"


def _restore_transform(data: bytes, *state) -> InMemoryTransform:
    return InMemoryTransform(pickle.loads(data), *state)


# ----------------------------------------------------------------------------- reading


def read_transform(item: sitk.Transform | InMemoryTransform | str | os.PathLike) -> sitk.Transform:
    """Read one transform: a transform file, a displacement-field image, or pass one through.

    Parameters
    ----------
    item : sitk.Transform, InMemoryTransform or path
        ``.tfm`` / ``.txt`` / ``.h5`` / ``.hdf5`` / ``.mat`` (incl. ANTs
        ``*0GenericAffine.mat``) are read with ``sitk.ReadTransform``, an elastix
        ``TransformParameters.<k>.txt`` with its initial transforms
        (:func:`itk_nrreval._elastix_files.read_elastix_transform`); ``.nii.gz`` / ``.nii``
        / ``.nrrd`` / ``.mha`` / ``.mhd`` (incl. ANTs ``*1Warp.nii.gz``) are displacement
        fields. A manifest entry in another tool's format
        (:class:`~itk_nrreval._foreign_transforms.ForeignTransform`: FSL, AFNI, FreeSurfer
        LTA, NiftyReg) is converted into this convention. An in-memory transform is returned
        as is; a manifest's transform object
        (:class:`InMemoryTransform`) gives its transform. An HDF5 file is first checked
        with h5py (:func:`itk_nrreval._itk_hdf5.check_file`): one HDF5 cannot read is
        refused without HDF5's error stack on stderr.

    Returns
    -------
    sitk.Transform
        Down-cast to its concrete class (``AffineTransform``, ``CompositeTransform``, ...).

    Raises
    ------
    InputError
        Missing or unreadable file, unknown suffix, a NaN or infinite parameter or field
        value in a file or manifest object (the message names the file or the item).
    """
    if isinstance(item, sitk.Transform):
        return item.Downcast()
    if isinstance(item, InMemoryTransform):
        if not item.finite:
            if isinstance(item.value, sitk.Image):  # worded as for a field file
                raise InputError(
                    f"{item.name}: displacement field contains NaN or infinite voxel values"
                )
            raise InputError(f"{item.name}: transform contains NaN or infinite values")
        return item.transform.Downcast()
    if isinstance(item, ForeignTransform):  # another tool's file: converted into ITK's terms
        t = item.read()
        if not _finite(t):
            raise InputError(f"{item.path}: transform contains NaN or infinite values")
        return t
    if not isinstance(item, (str, os.PathLike)):
        raise InputError(f"transform: expected a path or sitk.Transform, got {type(item).__name__}")
    path = Path(item)
    if not path.is_file():
        raise InputError(f"{path}: transform file not found")
    suffix = file_suffix(path)
    if suffix in FIELD_SUFFIXES:
        # read as images are: unreadable, truncated (NIfTI) or non-finite fields are refused
        image = read_image(path, what="displacement field")
        try:
            return field_transform(image)
        except InputError as exc:
            raise InputError(f"{path}: {exc}") from None
    if suffix == ".txt" and is_elastix_parameter_file(path):
        t = read_elastix_transform(path)
        if not _finite(t):
            raise InputError(f"{path}: transform contains NaN or infinite values")
        return t
    if suffix in (".h5", ".hdf5"):
        try:  # before ITK, whose HDF5 library would print its error stack on stderr
            check_hdf5_file(path)
        except ValueError as exc:
            raise InputError(f"{path}: cannot read transform ({exc})") from None
    try:
        if suffix in TRANSFORM_SUFFIXES:
            signature = _file_signature(path)  # before reading: a later change gets a new one
            with ITK_READ_LOCK:
                t = sitk.ReadTransform(str(path)).Downcast()
            _check_finite_file(signature, t)
            return t
    except RuntimeError as exc:
        raise InputError(f"{path}: cannot read transform ({_reason(exc)})") from None
    except InputError as exc:
        raise InputError(f"{path}: {exc}") from None
    raise InputError(
        f"{path}: unknown transform format {suffix!r} (expected one of "
        f"{', '.join(TRANSFORM_SUFFIXES + FIELD_SUFFIXES)})"
    )


def chain_transform(items: sitk.Transform | str | os.PathLike | Sequence) -> sitk.Transform:
    """One transform from a chain listed in ANTs ``fwdtransforms`` order (first acts first).

    Parameters
    ----------
    items : transform, path, or sequence of them
        ``[t1, t2, ..., tn]`` maps a reference point p to ``tn(...t2(t1(p)))``; e.g.
        ``[warp, affine]`` gives ``affine(warp(p))``.

    Returns
    -------
    sitk.Transform
        The single transform for a chain of one; otherwise a flat
        ``sitk.CompositeTransform([tn, ..., t2, t1])`` (SimpleITK applies its list from the
        back), with nested composites flattened.

    Examples
    --------
    >>> import SimpleITK as sitk
    >>> shift = sitk.TranslationTransform(2, (1.0, 0.0))
    >>> scale = sitk.ScaleTransform(2, (2.0, 2.0))
    >>> chain_transform([shift, scale]).TransformPoint((1.0, 1.0))  # scale(shift(p))
    (4.0, 2.0)
    """
    if isinstance(items, TransformPieces):
        return flatten(items)
    if isinstance(items, (sitk.Transform, InMemoryTransform, str, os.PathLike)):
        return read_transform(items)
    items = list(items)
    transforms = [read_transform(t) for t in items]
    if not transforms:
        raise InputError("transform chain: empty")
    if len(transforms) == 1:
        return transforms[0]
    # Every composite built or taken apart copies its displacement fields (~0.1 s per 1 mm
    # field), so the chain grows in place: on the last item's composite when this call read
    # it from a file (nobody else holds it), and the earlier items, which act first, appended
    # at the back of SimpleITK's list.
    last = transforms[-1]
    if isinstance(items[-1], (str, os.PathLike)) and isinstance(last, sitk.CompositeTransform):
        chain = last
    else:
        chain = sitk.CompositeTransform(last.GetDimension())
        chain.AddTransform(last)
    for t in reversed(transforms[:-1]):
        chain.AddTransform(t)
    chain.FlattenTransform()
    return chain


class TransformPieces(tuple):
    """A transform held as its pieces, in SimpleITK list order (the last acts first), none a
    composite: what :func:`transform_pieces` returns.

    Every function here that takes a transform or a chain takes it as that transform
    (:func:`chain_transform` builds its composite, :func:`transform_pieces` returns it as it
    is), never as a chain in ANTs order, which a plain list is.
    """

    __slots__ = ()


def transform_pieces(items: sitk.Transform | str | os.PathLike | Sequence) -> TransformPieces:
    """A transform or a chain as its pieces, in SimpleITK list order (the last acts first).

    What ``leaves(chain_transform(items))`` gives, without building a composite and taking it
    apart again (each copies every displacement field: 0.1 to 0.25 s per 1 mm field), and
    with ITK HDF5 files of affine maps and displacement fields (ANTs' ``Composite.h5``,
    ``sitk.WriteTransform``'s ``.h5``) read by h5py
    (:func:`itk_nrreval._itk_hdf5.read_pieces`: the same values in about a quarter of
    ``sitk.ReadTransform``'s time); any other item is read by :func:`read_transform`.

    Parameters
    ----------
    items : transform, path, or sequence of them
        As :func:`chain_transform`: ``[t1, ..., tn]`` in ANTs order maps p to
        ``tn(...t1(p))``.

    Returns
    -------
    TransformPieces
        Linear maps, displacement fields and other transforms, none a composite; `items`
        itself when it is one.

    Raises
    ------
    InputError
        As :func:`read_transform`, for the file or item at fault.
    """
    if isinstance(items, TransformPieces):
        return items
    if isinstance(items, (sitk.Transform, InMemoryTransform, str, os.PathLike)):
        return TransformPieces(_file_pieces(items))
    items = list(items)
    if not items:
        raise InputError("transform chain: empty")
    # tn acts last, so its pieces come first in SimpleITK's list
    return TransformPieces(piece for item in reversed(items) for piece in _file_pieces(item))


def _file_pieces(item) -> list[sitk.Transform]:
    """One item's pieces (:func:`transform_pieces`)."""
    if isinstance(item, (str, os.PathLike)):
        path = Path(item)
        if file_suffix(path) in (".h5", ".hdf5") and path.is_file():
            signature = _file_signature(path)  # before reading: a later change gets a new one
            pieces = read_hdf5_pieces(path)
            if pieces is not None:
                try:
                    _check_finite_file(signature, pieces)
                except InputError as exc:
                    raise InputError(f"{path}: {exc}") from None
                return pieces
    return leaves(read_transform(item))


def leaves(transform: sitk.Transform | Sequence[sitk.Transform]) -> list[sitk.Transform]:
    """Sub-transforms of a (possibly nested) composite, in SimpleITK list order.

    Taking a composite apart copies its displacement fields (about 0.1 s per 1 mm field): a
    list of pieces already taken apart (this function's result) is returned as it is, so
    that functions that take transforms apart can be given the pieces instead.
    """
    if isinstance(transform, (list, tuple)):
        return [
            leaf
            for t in transform
            for leaf in (leaves(t) if isinstance(t, sitk.CompositeTransform) else [t])
        ]
    t = transform.Downcast()
    if isinstance(t, sitk.CompositeTransform):
        out = []
        for i in range(t.GetNumberOfTransforms()):
            out.extend(leaves(t.GetNthTransform(i)))
        return out
    return [t]


def flatten(transform: sitk.Transform) -> sitk.Transform:
    """The same mapping without nested composites (writable to one file).

    A composite of one transform becomes that transform.
    """
    parts = leaves(transform)
    if len(parts) == 1:
        return parts[0]
    return sitk.CompositeTransform(parts)


def write_transform(transform: sitk.Transform, path: str | os.PathLike) -> Path:
    """Write `transform` to `path` atomically (``.h5`` recommended for fields), flattened first.

    ITK cannot write a composite nested in a composite, so nested composites are flattened.
    """
    path = Path(path)
    with atomic_path(path) as tmp:
        sitk.WriteTransform(flatten(transform), str(tmp))
    return path


def _grid(reference: sitk.Image | Geometry) -> Geometry:
    return reference if isinstance(reference, Geometry) else Geometry.from_image(reference)


def displacement_field(transform: sitk.Transform, reference: sitk.Image | Geometry) -> sitk.Image:
    """Sample ``T(p) - p`` on the grid of `reference`.

    Parameters
    ----------
    transform : sitk.Transform
        Any transform of the grid's dimension.
    reference : sitk.Image or Geometry
        The grid of points p (voxel centres, mm, LPS).

    Returns
    -------
    sitk.Image
        ``sitkVectorFloat64`` image on that grid; vectors in mm, ITK (x, y[, z]) order.
    """
    g = _grid(reference)
    return sitk.TransformToDisplacementField(
        transform,
        sitk.sitkVectorFloat64,
        list(g.size),
        list(g.origin),
        list(g.spacing),
        list(g.direction),
    )


#: The stopping rule of ITK's field inversion by default (:func:`invert`'s `max_iterations`,
#: `max_error`, `mean_error`), and always in :class:`PointwiseInverse`.
INVERSION_STOPPING = (50, 0.01, 1e-4)


def invert(
    transform: sitk.Transform | str | os.PathLike | Sequence,
    *,
    grid: sitk.Image | Geometry | None = None,
    max_iterations: int = INVERSION_STOPPING[0],
    max_error: float = INVERSION_STOPPING[1],
    mean_error: float = INVERSION_STOPPING[2],
    field_step: int = 1,
    refine_steps: int = 3,
) -> sitk.Transform:
    """The inverse mapping (image points to reference points).

    Linear transforms are inverted exactly. A displacement field is inverted with
    ``sitk.InvertDisplacementField`` (fixed-point iteration; never the slow
    ``InverseDisplacementField``) on its own grid grown by its largest displacement, so
    that the inverse is right wherever the field moves points off its grid. A chain is
    inverted piece by piece in reverse order: ``(t2 o t1)^-1 = t1^-1 o t2^-1``, so each
    field is inverted where it lives. Other smooth pieces (B-splines) are first sampled as
    a displacement field on `grid`.

    Parameters
    ----------
    transform : sitk.Transform, path or chain (ANTs order)
    grid : sitk.Image or Geometry, optional
        Where to sample pieces that are neither linear nor displacement fields (e.g.
        B-splines): the registration's reference grid, on which those pieces act.
    max_iterations : int
        Iterations of the field inversion.
    max_error, mean_error : float
        Stopping tolerances of the field inversion (voxels; the filter's units).
    field_step : int
        Invert each displacement field first on every `field_step`-th node of its grid along
        each axis (its own values there; ``field_step**dim`` times fewer voxels to iterate
        on), then refine that inverse on the field's own grid by `refine_steps` fixed-point
        steps ``v(q) <- -u(q + v(q))`` (:func:`_fixed_point_steps`). 1 (the default) inverts
        on the field's own grid alone.
    refine_steps : int
        Fixed-point steps on the field's own grid after a coarse inversion (`field_step` > 1;
        each halves the coarse inverse's error or better where the field's Jacobian is
        near the identity).

    Returns
    -------
    sitk.Transform
        A transform of the same dimension; a composite when the input was one.

    Raises
    ------
    InputError
        A piece that is neither linear nor a displacement field, and no `grid`.
    """
    parts = transform_pieces(transform)
    inverted = [
        _invert_one(t, grid, (max_iterations, max_error, mean_error), field_step, refine_steps)
        for t in parts
    ]
    # sitk list [a, b] means a(b(p)); its inverse is b^-1(a^-1(q)): list [b^-1, a^-1].
    inverted = list(reversed(inverted))
    return inverted[0] if len(inverted) == 1 else sitk.CompositeTransform(inverted)


class PointwiseInverse:
    """A transform's numerical inverse, evaluated at any points without an inverse field.

    The inverse :func:`invert` gives with ``field_step`` and ``refine_steps``, except that
    each displacement field's fixed-point steps ``y <- r - u(y)`` run at the points asked
    about rather than at the nodes of the field's grid (whose results :func:`invert` then
    interpolates). For a round trip ``T^-1(T(p))`` on every second voxel this is an eighth of
    the refinement's work and no full-size inverse field (issue 30: 1.9 s -> 0.3 s at 1 mm).
    The coarse inverse it starts from and the convention beyond the field's grid are
    :func:`invert`'s: the inverse is the identity beyond the field's grid grown by its
    largest displacement, and the field is extended by its edge values.

    Parameters
    ----------
    transform : sitk.Transform, path, chain (ANTs order) or TransformPieces
        Grid points -> image points (mm, LPS).
    grid : sitk.Image or Geometry, optional
        Where pieces that are neither linear nor displacement fields (B-splines) are sampled
        as displacement fields first (as :func:`invert`).
    field_step : int
        Each displacement field is first inverted by ITK on every `field_step`-th node of
        its grid (:func:`invert`).
    refine_steps : int
        Fixed-point steps at each point after the coarse inverse.

    Raises
    ------
    InputError
        A piece that is neither linear nor a displacement field and no `grid`, or a linear
        piece that is not invertible.
    """

    def __init__(
        self,
        transform,
        *,
        grid: sitk.Image | Geometry | None = None,
        field_step: int = 1,
        refine_steps: int = 3,
    ):
        pieces = transform_pieces(transform)  # files read once; no composite is built
        self.dimension = pieces[0].GetDimension()
        self.refine_steps = int(refine_steps)
        # sitk list [a, b] means a(b(p)): its inverse applies a^-1 first
        self._pieces = [_pointwise_piece(t, grid, int(field_step)) for t in pieces]

    def map_points(self, points: np.ndarray) -> np.ndarray:
        """``T^-1`` at `points`.

        Parameters
        ----------
        points : ndarray of shape (m, dim)
            Physical points (mm, LPS, ITK (x, y[, z]) order).

        Returns
        -------
        ndarray of shape (m, dim), float64
            Their images under the numerical inverse.
        """
        y = np.zeros((len(points), 3))
        y[:, : self.dimension] = points
        self._map_in_place(y)
        return y[:, : self.dimension]

    def _map_in_place(self, y: np.ndarray) -> None:
        """:meth:`map_points` on points as 3-vectors (m, 3), in place."""
        for piece in self._pieces:
            if isinstance(piece, _FieldPiece):
                _fixed_point_at_points(y, *piece.arrays(), self.refine_steps)
            else:
                _affine_in_place(y, *piece)


def composed_displacement(
    inverse: PointwiseInverse, first: sitk.Transform | Sequence[sitk.Transform], grid: Geometry
) -> np.ndarray:
    """``inverse(first(p)) - p`` on `grid`'s voxels p: `first` sampled at the voxels, then
    the numerical inverse at the points it gives (no inverse field is built).

    Parameters
    ----------
    inverse : PointwiseInverse
        A numerical inverse ``T^-1``.
    first : sitk.Transform or list of sitk.Transform
        Grid points -> points where `inverse` is evaluated (mm, LPS). A transform is
        sampled by ITK (``TransformToDisplacementField``); its pieces (:func:`leaves`), all
        linear or displacement fields (:func:`has_only_fields`), by the compiled kernels of
        :func:`displacement_after`, to about 1e-13 mm of ITK's sampling, faster and without
        ITK's output image and its copy (0.4 GB at 1 mm).
    grid : Geometry
        The points p.

    Returns
    -------
    ndarray of shape (*grid.shape, dim)
        Displacements in mm, numpy axis order for the grid and ITK (x, y[, z]) order last
        (as ``sitk.GetArrayFromImage`` of a displacement field).
    """
    dim = grid.dimension
    origin, matrix, size = _voxel_point_map(grid)
    if isinstance(first, (list, tuple)):
        y = _points_after(first, grid)  # first(p)
    else:
        # An array view does not keep its image alive: `field` stays named while it is read
        field = displacement_field(first, grid)
        if dim == 3:  # one copy of the field, not a zeroed array filled from it
            y = sitk.GetArrayFromImage(field).reshape(-1, 3).astype(np.float64, copy=False)
        else:
            y = np.zeros((math.prod(grid.size), 3))
            y[:, :dim] = sitk.GetArrayViewFromImage(field).reshape(-1, dim)
        del field
        _add_voxel_points(y, origin, matrix, size, 1.0)  # first(p)
    inverse._map_in_place(y)
    _add_voxel_points(y, origin, matrix, size, -1.0)
    return (y if dim == 3 else y[:, :dim]).reshape(*grid.shape, dim)


def _voxel_point_map(grid: Geometry) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`grid`'s voxel -> point map in the kernels' 3D form: (origin (3,), index -> point
    matrix (3, 3), ITK size (3,), int64), a 2D grid in the upper-left block."""
    dim = grid.dimension
    origin, matrix = np.zeros(3), np.zeros((3, 3))
    origin[:dim] = grid.origin
    matrix[:dim, :dim] = np.asarray(grid.direction, float).reshape(dim, dim) * grid.spacing
    size = np.ones(3, np.int64)
    size[:dim] = grid.size
    return origin, matrix, size


def displacement_after(
    transform: sitk.Transform | Sequence[sitk.Transform], displacement: np.ndarray, grid: Geometry
) -> np.ndarray:
    """``T(p + d(p)) - p`` on `grid`'s voxels p: the displacement of ``T o D``, where D is
    ``p -> p + d(p)`` given at the voxels (a frame F on the common grid).

    What ``displacement_field(sitk.CompositeTransform([T, D]), grid)`` gives, D as a
    displacement-field transform on `grid`, to about 1e-13 mm (the same interpolation in
    another order of operations), without building that composite, which copies every
    field of T and D (at 1 mm, 0.1 s and 215 MB each).

    Parameters
    ----------
    transform : sitk.Transform or list of sitk.Transform
        T, of linear pieces and displacement fields only (:func:`has_only_fields`); each
        field by ITK's rules: linear interpolation, the edge values in the half-voxel
        border of its buffer, the identity beyond. Or T's pieces, :func:`leaves`.
    displacement : ndarray of shape (*grid.shape, dim)
        d(p) in mm, ITK (x, y[, z]) order last; any float dtype.
    grid : Geometry
        The points p.

    Returns
    -------
    ndarray of shape (*grid.shape, dim), float64
        Displacements in mm, as ``sitk.GetArrayFromImage`` of a displacement field.

    Raises
    ------
    ValueError
        A piece of T is neither linear nor a displacement field, or `displacement` is not
        shaped as the grid.
    """
    dim = grid.dimension
    if displacement.shape != (*grid.shape, dim):
        raise ValueError(f"displacement: shape {displacement.shape}, not the grid's")
    return _minus_voxel_points(_points_after(transform, grid, displacement), grid)


def displacement_array(
    transform: sitk.Transform | Sequence[sitk.Transform], grid: Geometry
) -> np.ndarray:
    """``T(p) - p`` on `grid`'s voxels p, as an array: by the compiled kernels of
    :func:`displacement_after` when T is linear maps and displacement fields only (to about
    1e-13 mm of ITK's sampling, without its output image and the copy of it), otherwise by
    ITK (:func:`displacement_field`).

    Parameters
    ----------
    transform : sitk.Transform or list of sitk.Transform
        T, or its pieces (:func:`leaves`, :func:`transform_pieces`): grid points -> image
        points (mm, LPS).
    grid : Geometry
        The points p.

    Returns
    -------
    ndarray of shape (*grid.shape, dim), float64
        Displacements in mm, ITK (x, y[, z]) order last (as ``sitk.GetArrayFromImage`` of
        :func:`displacement_field`).
    """
    pieces = leaves(transform)  # once: taking a composite apart copies its fields
    if not has_only_fields(pieces):
        t = transform if isinstance(transform, sitk.Transform) else flatten(pieces)
        return sitk.GetArrayFromImage(displacement_field(t, grid))
    return _minus_voxel_points(_points_after(pieces, grid), grid)


def _minus_voxel_points(y: np.ndarray, grid: Geometry) -> np.ndarray:
    """Points ``q(p)`` at `grid`'s voxels (n_voxels, 3), as :func:`_points_after` gives
    them, less the voxels' points p, in place: ``(*grid.shape, dim)``, ITK order last."""
    dim = grid.dimension
    _add_voxel_points(y, *_voxel_point_map(grid), -1.0)
    return (y if dim == 3 else y[:, :dim]).reshape(*grid.shape, dim)


@dataclass(frozen=True, eq=False)
class PointMap:
    """The map ``p -> T(p + d(p))`` at a grid's voxels p, for the compiled kernels to
    evaluate a slab of the grid at a time (:meth:`points`): no array of the whole grid's
    points is built, where a caller needs each slab's points once.

    Attributes
    ----------
    pieces : TransformPieces
        T's pieces (:func:`transform_pieces`), linear maps and displacement fields only
        (:func:`has_only_fields`): grid points -> image points (mm, LPS). Sampled as
        :func:`displacement_after` samples them (to about 1e-13 mm of ITK's).
    displacement : ndarray of shape ``(*grid.shape, dim)`` or None
        d in mm on the whole grid, ITK (x, y[, z]) order last (a frame F's ``F(p) - p``), or
        None for d = 0.
    """

    pieces: TransformPieces
    displacement: np.ndarray | None = None

    def __post_init__(self):
        if not has_only_fields(self.pieces):
            raise ValueError("transform: a piece is neither linear nor a displacement field")

    def points(self, slab: Geometry, first: int, *, out: np.ndarray | None = None) -> np.ndarray:
        """``T(p + d(p))`` at the voxels of `slab`, the whole grid's planes (numpy axis 0)
        from `first` on: (m, 3) float64, mm, C order, a 2D point's third coordinate 0.
        `out`, if given, is a float64 C-ordered array of at least m rows of 3 that the
        points are written into (its first m rows are returned)."""
        d = self.displacement
        if d is not None:
            d = d[first : first + slab.shape[0]]
        return _points_after(self.pieces, slab, d, out=out)


def _points_after(
    transform: sitk.Transform | Sequence[sitk.Transform],
    grid: Geometry,
    displacement: np.ndarray | None = None,
    *,
    out: np.ndarray | None = None,
) -> np.ndarray:
    """``T(p + d(p))`` (d = 0 when None) at `grid`'s voxels p: (n_voxels, 3) float64, mm,
    C order, a 2D point's third coordinate 0 (:func:`displacement_after`); into the first
    rows of `out` when given."""
    dim = grid.dimension
    pieces = leaves(transform)  # once: taking a composite apart copies its fields
    if not all(_is_linear_or_field(t) for t in pieces):
        raise ValueError("transform: a piece is neither linear nor a displacement field")
    origin, matrix, size = _voxel_point_map(grid)
    m = math.prod(grid.size)
    y = np.empty((m, 3)) if out is None else out[:m]
    if displacement is None:
        _voxel_points(origin, matrix, size, y)  # p
    else:
        _voxel_points_plus(displacement.reshape(-1, dim), origin, matrix, size, y)  # D(p)
    # SimpleITK's list [a, b] is a(b(p)): the last piece acts first
    for piece in reversed(pieces):
        if piece.IsLinear():
            _affine_in_place(y, *_linear_parts(piece))
            continue
        field = piece.GetDisplacementField()
        u = sitk.GetArrayViewFromImage(field)  # `field` stays named while `u` is read
        # ITK's IsInsideBuffer, -0.5 <= index < size - 0.5, in the kernel's 3D axes
        lower, upper = np.full(3, -0.5), np.full(3, 0.5)
        upper[:dim] = np.asarray(field.GetSize()) - 0.5
        _field_in_place(y, _as_plane(u) if dim == 2 else u, *_index_map(field), lower, upper)
        del u, field
    return y


def has_only_fields(transform: sitk.Transform | Sequence[sitk.Transform]) -> bool:
    """Whether every piece of `transform` (or every one of its pieces, :func:`leaves`) is
    linear or a displacement field."""
    return all(_is_linear_or_field(t) for t in leaves(transform))


def is_linear(transform: sitk.Transform | TransformPieces) -> bool:
    """Whether `transform` is linear; given as its pieces, whether every piece is (what
    their composite's ``IsLinear`` says), without building the composite."""
    if isinstance(transform, TransformPieces):
        return all(piece.IsLinear() for piece in transform)
    return transform.IsLinear()


def _is_linear_or_field(t: sitk.Transform) -> bool:
    return t.IsLinear() or isinstance(t, sitk.DisplacementFieldTransform)


@numba.njit(cache=True, parallel=True)
def _field_in_place(y, u, origin, to_index, lower, upper):  # pragma: no cover - compiled
    """In place, each point p (row of `y` (m, 3)) -> ``p + u(p)`` where p's continuous index
    in u's grid lies in ``[lower, upper)`` on every axis (ITK's DisplacementFieldTransform:
    the buffer's -0.5 to size - 0.5), `u` (nz, ny, nx, 3) sampled linearly, clamped to its
    nodes; unchanged elsewhere. `origin`, `to_index`: u's grid (:func:`_index_map`)."""
    for f in numba.prange(y.shape[0]):
        p0, p1, p2 = y[f, 0], y[f, 1], y[f, 2]
        c0, c1, c2 = _continuous_index(p0, p1, p2, origin, to_index)
        if not _in_box(c0, c1, c2, lower, upper):
            continue
        w0, w1, w2 = _linear_at_index(u, c0, c1, c2)
        y[f, 0], y[f, 1], y[f, 2] = p0 + w0, p1 + w1, p2 + w2


@numba.njit(cache=True, parallel=True)
def _add_voxel_points(y, origin, matrix, size, sign):  # pragma: no cover - compiled
    """In place, row f of `y` (m, 3) += `sign` * the physical point of voxel f of a grid of
    ITK `size` (3,) (C order: x fastest): ``origin + matrix @ index``."""
    nx, ny = size[0], size[1]
    for f in numba.prange(y.shape[0]):
        i = f % nx
        j = (f // nx) % ny
        k = f // (nx * ny)
        for a in range(3):
            y[f, a] += sign * (origin[a] + matrix[a, 0] * i + matrix[a, 1] * j + matrix[a, 2] * k)


@numba.njit(cache=True, parallel=True)
def _voxel_points(origin, matrix, size, y):  # pragma: no cover - compiled
    """Row f of `y` (m, 3) = the physical point of voxel f (:func:`_add_voxel_points`'s
    arithmetic on a zeroed `y`: the same bits), in one pass over `y`'s pages."""
    nx, ny = size[0], size[1]
    for f in numba.prange(y.shape[0]):
        i = f % nx
        j = (f // nx) % ny
        k = f // (nx * ny)
        for a in range(3):
            point = origin[a] + matrix[a, 0] * i + matrix[a, 1] * j + matrix[a, 2] * k
            y[f, a] = 0.0 + 1.0 * point


@numba.njit(cache=True, parallel=True)
def _voxel_points_plus(d, origin, matrix, size, y):  # pragma: no cover - compiled
    """Row f of `y` (m, 3) = row f of `d` (m, dim; 0 beyond dim) + the physical point of
    voxel f (:func:`_add_voxel_points`'s arithmetic: the same bits as adding it to a zeroed
    copy of `d`), in one pass."""
    nx, ny = size[0], size[1]
    dim = d.shape[1]
    for f in numba.prange(y.shape[0]):
        i = f % nx
        j = (f // nx) % ny
        k = f // (nx * ny)
        for a in range(3):
            v = np.float64(d[f, a]) if a < dim else 0.0
            y[f, a] = v + 1.0 * (origin[a] + matrix[a, 0] * i + matrix[a, 1] * j + matrix[a, 2] * k)


@numba.njit(cache=True, parallel=True)
def _affine_in_place(y, matrix, offset):  # pragma: no cover - compiled
    """In place, each row of `y` (m, 3) -> ``matrix @ row + offset``."""
    for f in numba.prange(y.shape[0]):
        a0, a1, a2 = y[f, 0], y[f, 1], y[f, 2]
        for r in range(3):
            y[f, r] = matrix[r, 0] * a0 + matrix[r, 1] * a1 + matrix[r, 2] * a2 + offset[r]


@dataclass(frozen=True)
class _FieldPiece:
    """A displacement field and its coarse inverse, as :func:`_fixed_point_at_points` reads
    them (3D arrays; a 2D field as one plane)."""

    u: np.ndarray  # (nz, ny, nx, 3), mm
    u_origin: np.ndarray  # (3,)
    u_to_index: np.ndarray  # (3, 3): mm -> u's index steps (ITK axis order)
    lower: np.ndarray  # (3,): the grown grid's buffer, in u's continuous index
    upper: np.ndarray
    v: np.ndarray  # the coarse inverse, (vz, vy, vx, 3)
    v_origin: np.ndarray
    v_to_index: np.ndarray
    images: tuple  # the images whose buffers `u` and `v` view (kept alive with them)

    def arrays(self) -> tuple:
        return (
            self.u,
            self.u_origin,
            self.u_to_index,
            self.lower,
            self.upper,
            self.v,
            self.v_origin,
            self.v_to_index,
        )


def _pointwise_piece(t: sitk.Transform, grid, step: int):
    """One piece of :class:`PointwiseInverse`: a :class:`_FieldPiece`, or the inverse of a
    linear piece as ``(matrix (3, 3), offset (3,))`` acting on 3-vectors."""
    t = t.Downcast()
    dim = t.GetDimension()
    if t.IsLinear():
        try:
            inverse = t.GetInverse()
        except RuntimeError as exc:
            raise InputError(f"{t.GetName()}: not invertible ({_reason(exc)})") from None
        return _linear_parts(inverse)
    if not isinstance(t, sitk.DisplacementFieldTransform):
        if grid is None:
            raise InputError(
                f"{t.GetName()}: cannot invert this transform type without a grid to sample "
                "it on (pass grid=, e.g. the registration's reference)"
            )
        t = field_transform(displacement_field(t, grid))
    field = t.GetDisplacementField()
    coarse = _coarse_inverse(field, step, INVERSION_STOPPING)
    # views: the piece keeps `field` and `coarse` alive (a copy of a 1 mm field: 0.1 s)
    u = sitk.GetArrayViewFromImage(field)
    v = sitk.GetArrayViewFromImage(coarse)
    pad = _padding(u, np.asarray(field.GetSpacing()))
    if dim == 2:
        u, v = _as_plane(u), _as_plane(v)
    lower, upper = np.full(3, -np.inf), np.full(3, np.inf)
    # ITK's inside-buffer test of the grown grid: -0.5 <= index < size - 0.5 there
    lower[:dim] = -pad - 0.5
    upper[:dim] = np.asarray(field.GetSize()) + pad - 0.5
    return _FieldPiece(u, *_index_map(field), lower, upper, v, *_index_map(coarse), (field, coarse))


def _linear_parts(t: sitk.Transform) -> tuple[np.ndarray, np.ndarray]:
    """A linear transform as ``(matrix (3, 3), offset (3,))`` acting on 3-vectors (a 2D
    one in the upper-left block), from the images of the origin and the unit vectors."""
    dim = t.GetDimension()
    origin = np.asarray(t.TransformPoint((0.0,) * dim))
    matrix, offset = np.eye(3), np.zeros(3)
    for j in range(dim):
        unit = np.zeros(dim)
        unit[j] = 1.0
        matrix[:dim, j] = np.asarray(t.TransformPoint(unit.tolist())) - origin
    offset[:dim] = origin
    return matrix, offset


def _coarse_inverse(field: sitk.Image, step: int, stopping: tuple) -> sitk.Image:
    """ITK's inverse of `field` from every `step`-th node of its grid, grown by its largest
    displacement (:func:`_edge_padded`); `stopping` is ``(iterations, max_error,
    mean_error)``."""
    iterations, max_error, mean_error = stopping
    return sitk.InvertDisplacementField(
        _edge_padded(_every_nth_node(field, step)),
        maximumNumberOfIterations=int(iterations),
        maxErrorToleranceThreshold=float(max_error),
        meanErrorToleranceThreshold=float(mean_error),
        enforceBoundaryCondition=False,
    )


def _index_map(image: sitk.Image) -> tuple[np.ndarray, np.ndarray]:
    """`image`'s origin (3,) and its mm -> continuous index map (3, 3), ITK axis order, as
    3D (a 2D image's third row and column zero)."""
    dim = image.GetDimension()
    origin, to_index = np.zeros(3), np.zeros((3, 3))
    origin[:dim] = image.GetOrigin()
    direction = np.asarray(image.GetDirection()).reshape(dim, dim)
    to_index[:dim, :dim] = direction.T / np.asarray(image.GetSpacing())[:, None]
    return origin, to_index


@numba.njit(cache=True, parallel=True)
def _fixed_point_at_points(
    y, u, u_origin, u_to_index, lower, upper, v, v_origin, v_to_index, steps
):  # pragma: no cover - compiled
    """In place, each point r of `y` (m, 3) -> the inverse of ``p -> p + u(p)`` at r: the
    coarse inverse `v` interpolated there, then `steps` steps ``y <- r - u(y)``; r itself
    where it lies beyond the grown grid (`lower`, `upper`: its buffer in u's continuous
    index). Fields are sampled linearly, clamped to their grids (:func:`_fixed_point_step`'s
    rules). Each point alone, by the same operations: the numbers do not depend on the
    threads."""
    for f in numba.prange(y.shape[0]):
        r0, r1, r2 = y[f, 0], y[f, 1], y[f, 2]
        c0, c1, c2 = _continuous_index(r0, r1, r2, u_origin, u_to_index)
        if not _in_box(c0, c1, c2, lower, upper):
            continue
        w0, w1, w2 = _linear_at(v, r0, r1, r2, v_origin, v_to_index)
        a0, a1, a2 = r0 + w0, r1 + w1, r2 + w2
        for _ in range(steps):
            w0, w1, w2 = _linear_at(u, a0, a1, a2, u_origin, u_to_index)
            a0, a1, a2 = r0 - w0, r1 - w1, r2 - w2
        y[f, 0], y[f, 1], y[f, 2] = a0, a1, a2


def _invert_one(t: sitk.Transform, grid, stopping: tuple, step: int, refine_steps: int):
    t = t.Downcast()
    if not t.IsLinear() and not isinstance(t, sitk.DisplacementFieldTransform):
        if grid is None:
            raise InputError(
                f"{t.GetName()}: cannot invert this transform type without a grid to sample "
                "it on (pass grid=, e.g. the registration's reference)"
            )
        t = field_transform(displacement_field(t, grid))
    if isinstance(t, sitk.DisplacementFieldTransform):
        own = t.GetDisplacementField()
        inverse = _coarse_inverse(own, int(step), stopping)
        if step > 1:
            inverse = _fixed_point_steps(own, inverse, int(refine_steps))
        if inverse.GetPixelID() != sitk.sitkVectorFloat64:
            inverse = sitk.Cast(inverse, sitk.sitkVectorFloat64)
        # `inverse` is this function's own image: the transform may take its buffer, where
        # field_transform would copy it first (~0.1 s per 9 M voxels)
        return sitk.DisplacementFieldTransform(inverse)
    if t.IsLinear():
        try:
            return t.GetInverse().Downcast()
        except RuntimeError as exc:
            raise InputError(f"{t.GetName()}: not invertible ({_reason(exc)})") from None
    raise AssertionError("unreachable: every piece is linear or a field here")


def _fixed_point_steps(field: sitk.Image, inverse: sitk.Image, steps: int) -> sitk.Image:
    """The inverse of `field` on its grid grown as :func:`_edge_padded` grows it: `inverse`
    (on a coarser grid of the same direction) refined by `steps` fixed-point steps
    ``v(q) <- -u(q + v(q))``.

    This is the iteration ``sitk.InvertDisplacementField`` runs, started from the coarse
    inverse instead of zero, with both fields interpolated linearly and extended by their
    edge values beyond their grids (as :func:`_edge_padded` extends them; `field` itself is
    never padded: sampling it clamped to its grid is the same).
    """
    dim = field.GetDimension()
    u = sitk.GetArrayViewFromImage(field)  # `field` stays named: the view reads its buffer
    spacing = np.asarray(field.GetSpacing())
    direction = np.asarray(field.GetDirection()).reshape(dim, dim)
    pad = _padding(u, spacing)  # voxels per ITK axis
    origin = np.asarray(field.GetOrigin()) - direction @ (pad * spacing)
    v = sitk.GetArrayFromImage(inverse)
    _, to_index = _index_map(field)  # mm -> the field's index steps (ITK axis order)
    # the grown grid's node i in the coarse inverse's continuous index: offset + ratio * i
    ratio, offset = np.zeros(3), np.zeros(3)
    ratio[:dim] = spacing / np.asarray(inverse.GetSpacing())
    coarse_to_index = direction.T / np.asarray(inverse.GetSpacing())[:, None]
    offset[:dim] = coarse_to_index @ (origin - np.asarray(inverse.GetOrigin()))
    u_offset = np.zeros(3)
    u_offset[:dim] = -pad
    if dim == 2:  # one plane of 3D with a zero third component: the same numbers, one kernel
        u, v = _as_plane(u), _as_plane(v)
    grown = np.zeros(3, int)
    grown[:dim] = 2 * pad  # ITK axis order
    shape = (u.shape[0] + grown[2], u.shape[1] + grown[1], u.shape[2] + grown[0], 3)
    buffers = [np.empty(shape), np.empty(shape) if steps > 1 else None]
    on_grid = False
    for n in range(max(int(steps), 1)):
        out = buffers[n % 2]
        _fixed_point_step(u, v, out, u_offset, to_index, ratio, offset, on_grid)
        v, on_grid = out, True
    del buffers, out  # the other buffer goes before the image copies `v` (283 MB at 1 mm)
    result = sitk.GetImageFromArray(v[0, ..., :2] if dim == 2 else v, isVector=True)
    result.SetSpacing(field.GetSpacing())
    result.SetDirection(field.GetDirection())
    result.SetOrigin(origin.tolist())
    return result


def _as_plane(a: np.ndarray) -> np.ndarray:
    """A 2D field (ny, nx, 2) as one plane of a 3D one, (1, ny, nx, 3), third component 0."""
    plane = np.zeros((1, *a.shape[:2], 3))
    plane[0, ..., :2] = a
    return plane


def _padding(u: np.ndarray, spacing: np.ndarray) -> np.ndarray:
    """Voxels per ITK axis by which :func:`_edge_padded` grows a field `u` (mm, numpy order,
    components last): its largest displacement and one voxel; 0 for a zero field."""
    reach = math.sqrt(_largest_squared_norm(u.reshape(-1, u.shape[-1]))) if u.size else 0.0
    if reach == 0.0:
        return np.zeros(len(spacing), int)
    return np.ceil(reach / spacing).astype(int) + 1


@numba.njit(cache=True, nogil=True)
def _largest_squared_norm(u):  # pragma: no cover - compiled
    """max_i |u_i|^2 of the rows of `u` (m, d): one pass, no temporaries (0.2 s -> 0.02 s at
    1 mm)."""
    best = 0.0
    for i in range(u.shape[0]):
        s = 0.0
        for c in range(u.shape[1]):
            s += u[i, c] * u[i, c]
        best = max(best, s)
    return best


@numba.njit(cache=True, inline="always")
def _corner(x, n):  # pragma: no cover - compiled
    """Lower and upper node and weight of continuous index `x` on an axis of `n` nodes,
    clamped to the axis (the edge value beyond it)."""
    x = min(max(x, 0.0), n - 1.0)
    x0 = min(int(x), max(n - 2, 0))
    return x0, min(x0 + 1, n - 1), x - x0


@numba.njit(cache=True, inline="always")
def _continuous_index(p0, p1, p2, origin, to_index):  # pragma: no cover - compiled
    """Physical point p's continuous index (ITK axis order) in a grid of `origin` (3,) and
    `to_index` (3, 3): mm -> index (:func:`_index_map`)."""
    d0, d1, d2 = p0 - origin[0], p1 - origin[1], p2 - origin[2]
    return (
        to_index[0, 0] * d0 + to_index[0, 1] * d1 + to_index[0, 2] * d2,
        to_index[1, 0] * d0 + to_index[1, 1] * d1 + to_index[1, 2] * d2,
        to_index[2, 0] * d0 + to_index[2, 1] * d1 + to_index[2, 2] * d2,
    )


@numba.njit(cache=True, inline="always")
def _in_box(c0, c1, c2, lower, upper):  # pragma: no cover - compiled
    """Whether a continuous index lies in ``[lower, upper)`` on every axis (NaN: no)."""
    return lower[0] <= c0 < upper[0] and lower[1] <= c1 < upper[1] and lower[2] <= c2 < upper[2]


@numba.njit(cache=True, inline="always")
def _linear_at(a, p0, p1, p2, origin, to_index):  # pragma: no cover - compiled
    """The three components of `a` (nz, ny, nx, 3) at physical point p, sampled linearly and
    clamped to its grid (`origin` (3,), `to_index` (3, 3): mm -> index, ITK axis order)."""
    c0, c1, c2 = _continuous_index(p0, p1, p2, origin, to_index)
    return _linear_at_index(a, c0, c1, c2)


@numba.njit(cache=True, inline="always")
def _linear_at_index(a, c0, c1, c2):  # pragma: no cover - compiled
    """The three components of `a` (nz, ny, nx, 3) at continuous index (c0, c1, c2) (ITK
    axis order), sampled linearly and clamped to its grid."""
    nz, ny, nx, _ = a.shape
    x0, x1, fx = _corner(c0, nx)
    y0, y1, fy = _corner(c1, ny)
    z0, z1, fz = _corner(c2, nz)
    return (
        _trilinear(a, z0, z1, fz, y0, y1, fy, x0, x1, fx, 0),
        _trilinear(a, z0, z1, fz, y0, y1, fy, x0, x1, fx, 1),
        _trilinear(a, z0, z1, fz, y0, y1, fy, x0, x1, fx, 2),
    )


@numba.njit(cache=True, inline="always")
def _trilinear(a, z0, z1, fz, y0, y1, fy, x0, x1, fx, c):  # pragma: no cover - compiled
    """Component `c` of `a` (nz, ny, nx, 3) interpolated between the given nodes."""
    return (1 - fz) * (
        (1 - fy) * ((1 - fx) * a[z0, y0, x0, c] + fx * a[z0, y0, x1, c])
        + fy * ((1 - fx) * a[z0, y1, x0, c] + fx * a[z0, y1, x1, c])
    ) + fz * (
        (1 - fy) * ((1 - fx) * a[z1, y0, x0, c] + fx * a[z1, y0, x1, c])
        + fy * ((1 - fx) * a[z1, y1, x0, c] + fx * a[z1, y1, x1, c])
    )


@numba.njit(cache=True, parallel=True)
def _fixed_point_step(u, v, out, u_offset, to_index, ratio, offset, v_on_grid):  # pragma: no cover
    """``out(q) = -u(q + v(q))`` on out's grid (nz, ny, nx, 3), whose node i is u's
    continuous index ``i + u_offset`` and v's ``offset + ratio * i`` (ITK axis order; with
    `v_on_grid`, v is on out's own grid and read at its nodes); `to_index` (3, 3) maps mm to
    u's index steps. u and v are sampled linearly, clamped to their grids.

    Slices run in parallel; each node is computed alone by the same operations, so the
    numbers do not depend on the number of threads."""
    nz, ny, nx, _ = out.shape
    uz, uy, ux, _ = u.shape
    vz, vy, vx, _ = v.shape
    t00, t01, t02 = to_index[0, 0], to_index[0, 1], to_index[0, 2]
    t10, t11, t12 = to_index[1, 0], to_index[1, 1], to_index[1, 2]
    t20, t21, t22 = to_index[2, 0], to_index[2, 1], to_index[2, 2]
    for k in numba.prange(nz):
        for j in range(ny):
            for i in range(nx):
                if v_on_grid:
                    a0, a1, a2 = v[k, j, i, 0], v[k, j, i, 1], v[k, j, i, 2]
                else:
                    x0, x1, fx = _corner(offset[0] + i * ratio[0], vx)
                    y0, y1, fy = _corner(offset[1] + j * ratio[1], vy)
                    z0, z1, fz = _corner(offset[2] + k * ratio[2], vz)
                    a0 = _trilinear(v, z0, z1, fz, y0, y1, fy, x0, x1, fx, 0)
                    a1 = _trilinear(v, z0, z1, fz, y0, y1, fy, x0, x1, fx, 1)
                    a2 = _trilinear(v, z0, z1, fz, y0, y1, fy, x0, x1, fx, 2)
                x0, x1, fx = _corner(i + u_offset[0] + (t00 * a0 + t01 * a1 + t02 * a2), ux)
                y0, y1, fy = _corner(j + u_offset[1] + (t10 * a0 + t11 * a1 + t12 * a2), uy)
                z0, z1, fz = _corner(k + u_offset[2] + (t20 * a0 + t21 * a1 + t22 * a2), uz)
                out[k, j, i, 0] = -_trilinear(u, z0, z1, fz, y0, y1, fy, x0, x1, fx, 0)
                out[k, j, i, 1] = -_trilinear(u, z0, z1, fz, y0, y1, fy, x0, x1, fx, 1)
                out[k, j, i, 2] = -_trilinear(u, z0, z1, fz, y0, y1, fy, x0, x1, fx, 2)


def _every_nth_node(field: sitk.Image, step: int) -> sitk.Image:
    """`field` on every `step`-th node along each axis (from its origin): its own values there."""
    if step == 1:
        return field
    dim = field.GetDimension()
    arr = sitk.GetArrayViewFromImage(field)[(slice(None, None, step),) * dim]
    out = sitk.GetImageFromArray(np.ascontiguousarray(arr), isVector=True)
    out.SetSpacing([s * step for s in field.GetSpacing()])
    out.SetOrigin(field.GetOrigin())
    out.SetDirection(field.GetDirection())
    return out


def _edge_padded(field: sitk.Image) -> sitk.Image:
    """`field` on its grid grown by its largest displacement, extended by its edge values.

    The inverse of ``p -> p + u(p)`` is needed wherever the forward map lands, which reaches
    up to ``max |u|`` beyond the field's own grid: inverted on that grid alone, it would be the
    identity there (a 12 mm shift came back 12 mm out). Beyond the grown grid no point of the
    field's grid can land, so the inverse is the identity there, as ITK gives outside a field.
    The extension by edge values is what lets the fixed-point inversion find preimages inside
    the grid for points that landed outside it.
    """
    arr = sitk.GetArrayFromImage(field)  # (*zyx, dim), mm
    spacing = np.array(field.GetSpacing())
    pad = _padding(arr, spacing)  # voxels per ITK axis
    if not pad.any():
        return field
    dim = field.GetDimension()
    padded = np.pad(arr, [*((k, k) for k in pad[::-1]), (0, 0)], mode="edge")
    out = sitk.GetImageFromArray(padded, isVector=True)
    direction = np.array(field.GetDirection()).reshape(dim, dim)
    out.SetSpacing(field.GetSpacing())
    out.SetDirection(field.GetDirection())
    out.SetOrigin((np.array(field.GetOrigin()) - direction @ (pad * spacing)).tolist())
    return out


def jacobian_determinant(
    displacement: np.ndarray, *, spacing: Sequence[float], direction: Sequence[float] | None = None
) -> np.ndarray:
    """Jacobian determinant of ``p -> p + u(p)`` from a sampled displacement field.

    Parameters
    ----------
    displacement : ndarray of shape (*spatial, dim)
        Displacements in mm, numpy axis order for ``spatial`` ((z, y, x) in 3D) and ITK
        (x, y[, z]) order for the last axis -- what ``sitk.GetArrayFromImage`` gives.
    spacing : sequence of float, length dim
        Voxel size in mm along ITK (x, y[, z]).
    direction : sequence of float, length dim * dim, optional
        Row-major direction cosines (default identity).

    Returns
    -------
    ndarray of shape (*spatial,)
        ``det(I + du/dx)`` with derivatives in physical coordinates (central differences
        inside, one-sided at the border). Values <= 0 mark folded voxels; 1 is volume
        preserving.
    """
    u = np.asarray(displacement, dtype=np.float64)
    dim = u.shape[-1]
    if u.ndim != dim + 1 or dim not in (2, 3):
        raise ValueError(
            f"displacement: expected shape (*spatial, dim) with {dim} spatial axes, got {u.shape}"
        )
    spacing = np.asarray(spacing, dtype=np.float64)
    d = np.eye(dim) if direction is None else np.asarray(direction, np.float64).reshape(dim, dim)
    # physical x = origin + D @ diag(spacing) @ index  =>  d index / d x = (D diag(s))^-1
    index_per_mm = np.linalg.inv(d @ np.diag(spacing))
    det = np.empty(u.shape[:-1])
    # one compiled pass (no (n, dim, dim) temporaries); a 2D field as one plane of 3D
    _jacobian_determinant(u if dim == 3 else u[None], index_per_mm, det if dim == 3 else det[None])
    return det


@numba.njit(cache=True, inline="always")
def _difference_ends(at, n):  # pragma: no cover - compiled
    """The nodes a derivative along an axis of `n` nodes differences at node `at`, and the
    factor on their difference: np.gradient's (central, 1/2, inside; one-sided, 1, at the
    border; 0 on an axis of one node)."""
    if n == 1:
        return 0, 0, 0.0
    if at == 0:
        return 0, 1, 1.0
    if at == n - 1:
        return n - 2, n - 1, 1.0
    return at - 1, at + 1, 0.5


@numba.njit(cache=True, inline="always")
def _scaled(diff, factor):  # pragma: no cover - compiled
    """`diff` times a factor of :func:`_difference_ends` (a halving as a division, so
    that it rounds as np.gradient's does)."""
    if factor == 0.5:
        return diff / 2.0
    return diff if factor == 1.0 else 0.0


@numba.njit(cache=True, parallel=True)
def _jacobian_determinant(u, m, out):  # pragma: no cover - compiled
    """``out = det(I + G @ m)`` with ``G[c, a] = d u_c / d index_a`` of a field `u`
    (nz, ny, nx, d), d 2 or 3 (a 2D field as nz = 1), `m` (d, d) index steps per mm.
    Slices run in parallel; every voxel is computed alone, so the numbers do not depend on
    the number of threads. Written out for d = 3 and d = 2 (a loop over the 3 x 3 entries
    costs three times as much at 1 mm)."""
    nz, ny, nx, d = u.shape
    for slice_ in numba.prange(nz):
        k = np.int64(slice_)  # prange's index is unsigned
        zl, zh, zf = _difference_ends(k, nz)
        for j in range(ny):
            yl, yh, yf = _difference_ends(j, ny)
            for i in range(nx):
                xl, xh, xf = _difference_ends(i, nx)
                # g_ca: d u_c / d index a (x, y, z)
                g00 = _scaled(u[k, j, xh, 0] - u[k, j, xl, 0], xf)
                g10 = _scaled(u[k, j, xh, 1] - u[k, j, xl, 1], xf)
                g01 = _scaled(u[k, yh, i, 0] - u[k, yl, i, 0], yf)
                g11 = _scaled(u[k, yh, i, 1] - u[k, yl, i, 1], yf)
                if d == 2:
                    j00 = (0.0 + g00 * m[0, 0] + g01 * m[1, 0]) + 1.0
                    j01 = 0.0 + g00 * m[0, 1] + g01 * m[1, 1]
                    j10 = 0.0 + g10 * m[0, 0] + g11 * m[1, 0]
                    j11 = (0.0 + g10 * m[0, 1] + g11 * m[1, 1]) + 1.0
                    out[k, j, i] = j00 * j11 - j01 * j10
                    continue
                g20 = _scaled(u[k, j, xh, 2] - u[k, j, xl, 2], xf)
                g21 = _scaled(u[k, yh, i, 2] - u[k, yl, i, 2], yf)
                g02 = _scaled(u[zh, j, i, 0] - u[zl, j, i, 0], zf)
                g12 = _scaled(u[zh, j, i, 1] - u[zl, j, i, 1], zf)
                g22 = _scaled(u[zh, j, i, 2] - u[zl, j, i, 2], zf)
                # J = I + G m, each entry summed from 0 in the order a = x, y, z
                j00 = (0.0 + g00 * m[0, 0] + g01 * m[1, 0] + g02 * m[2, 0]) + 1.0
                j01 = 0.0 + g00 * m[0, 1] + g01 * m[1, 1] + g02 * m[2, 1]
                j02 = 0.0 + g00 * m[0, 2] + g01 * m[1, 2] + g02 * m[2, 2]
                j10 = 0.0 + g10 * m[0, 0] + g11 * m[1, 0] + g12 * m[2, 0]
                j11 = (0.0 + g10 * m[0, 1] + g11 * m[1, 1] + g12 * m[2, 1]) + 1.0
                j12 = 0.0 + g10 * m[0, 2] + g11 * m[1, 2] + g12 * m[2, 2]
                j20 = 0.0 + g20 * m[0, 0] + g21 * m[1, 0] + g22 * m[2, 0]
                j21 = 0.0 + g20 * m[0, 1] + g21 * m[1, 1] + g22 * m[2, 1]
                j22 = (0.0 + g20 * m[0, 2] + g21 * m[1, 2] + g22 * m[2, 2]) + 1.0
                out[k, j, i] = (
                    j00 * (j11 * j22 - j12 * j21)
                    - j01 * (j10 * j22 - j12 * j20)
                    + j02 * (j10 * j21 - j11 * j20)
                )


def folded_fraction(
    transform: sitk.Transform | str | os.PathLike | Sequence,
    reference: sitk.Image | Geometry,
    *,
    mask: np.ndarray | None = None,
) -> float:
    """Fraction of the reference grid's voxels where `transform` folds (Jacobian det <= 0).

    Parameters
    ----------
    transform : sitk.Transform, path or chain (ANTs order)
    reference : sitk.Image or Geometry
        The grid the Jacobian is sampled on.
    mask : ndarray of bool, numpy shape of the grid, optional
        Count only these voxels.

    Returns
    -------
    float
        In [0, 1]; 0 for a transform that is invertible everywhere on the grid.
    """
    g = _grid(reference)
    field = displacement_field(chain_transform(transform), g)
    det = jacobian_determinant(
        sitk.GetArrayViewFromImage(field), spacing=g.spacing, direction=g.direction
    )
    folded = det <= 0
    if mask is not None:
        folded = folded[np.asarray(mask, bool)]
    return float(folded.mean()) if folded.size else 0.0
