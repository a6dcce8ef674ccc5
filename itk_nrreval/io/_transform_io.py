"""Reading, writing and holding transforms: files, in-memory objects, chains and their pieces.

A transform comes as a file (ITK text / HDF5 / MATLAB, an elastix parameter file, a
displacement-field image, another tool's format), as an object, or as a chain of them in
ANTs order; :func:`read_transform`, :func:`chain_transform` and :func:`transform_pieces` make
SimpleITK transforms of all of them, refusing unreadable files and non-finite values with
one-line messages. The conventions (which way a transform maps, chain order, field layout)
are those of :mod:`itk_nrreval.io.transforms`, which lists every public name here.

In-memory transforms
--------------------
Wherever a transform file is accepted, a transform object is too (:func:`to_sitk_transform`):
a ``sitk.Transform`` of any kind (composites included), an ITK Python transform (converted
through a temporary HDF5 file, ITK's own transform IO, so every type ITK can write comes
over with its exact parameters), or a displacement field given as an image (SimpleITK, ITK,
or an array with its grid, see :mod:`itk_nrreval.io._in_memory_images`). A manifest keeps such
an object as an :class:`InMemoryTransform`: a private copy, the manifest item's name for
messages (``registrations.fluid.transforms[3]``), and a digest of its content
(:func:`transform_digest`: each piece's type, parameters and fixed parameters, a field's
values and grid) that the result cache uses as its key -- the same key as a file holding
the same transform.
"""

from __future__ import annotations

import hashlib
import os
import pickle
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from .._errors import InputError
from .._executors import ITK_READ_LOCK
from .._output import atomic_path
from ._elastix_files import is_elastix_parameter_file, read_elastix_transform
from ._foreign_transforms import ForeignTransform
from ._images import read_image
from ._in_memory_images import image_digest, is_finite, itk_kind, source_kind, to_sitk_image
from ._itk_hdf5 import check_file as check_hdf5_file
from ._itk_hdf5 import read_pieces as read_hdf5_pieces

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
    "field_components_problem",
    "itk_error_reason",
]


#: File suffixes read with ``sitk.ReadTransform`` (ITK text / HDF5 / MATLAB, incl. ANTs affines).
TRANSFORM_SUFFIXES = (".tfm", ".txt", ".h5", ".hdf5", ".mat")


#: File suffixes read as displacement-field images.
FIELD_SUFFIXES = (".nii.gz", ".nii", ".nrrd", ".nhdr", ".mha", ".mhd")


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


def itk_error_reason(exc: Exception) -> str:
    """The line of an ITK exception's text that says why (not ITK's location lines), for a
    one-line message: at most 160 characters."""
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


def to_sitk_transform(value, *, name: str = "transform") -> sitk.Transform:
    """A SimpleITK transform from a SimpleITK or ITK Python transform, or a displacement field.

    Parameters
    ----------
    value : sitk.Transform, itk.Transform, or an image
        Any SimpleITK transform (composites included); any ITK Python transform that ITK's
        HDF5 transform IO writes (composites included; float transforms become double); a
        displacement field as a vector image (``sitk.Image``, ``itk.Image``, or the array
        form of :func:`itk_nrreval.io._images.to_sitk_image`, components last), mm, ITK
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
                f"{name}: cannot convert the ITK transform {type(value).__name__} "
                f"({itk_error_reason(exc)})"
            ) from None


def transform_digest(transform: sitk.Transform) -> str:
    """BLAKE2b (128-bit) hex digest of what a transform is: its pieces' types and parameters.

    A composite is digested as the list of its pieces (:func:`leaves`; nesting does not
    matter), each by its class name, dimension, fixed parameters and parameters (and a
    B-spline's order); a displacement field by its float64 values and grid, exactly as
    :func:`itk_nrreval.io._images.image_digest` digests the vector image it came from. So a
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
        :func:`itk_nrreval.io._images.image_digest`): the result cache's key for it.
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


def read_transform(item: sitk.Transform | InMemoryTransform | str | os.PathLike) -> sitk.Transform:
    """Read one transform: a transform file, a displacement-field image, or pass one through.

    Parameters
    ----------
    item : sitk.Transform, InMemoryTransform or path
        ``.tfm`` / ``.txt`` / ``.h5`` / ``.hdf5`` / ``.mat`` (incl. ANTs
        ``*0GenericAffine.mat``) are read with ``sitk.ReadTransform``, an elastix
        ``TransformParameters.<k>.txt`` with its initial transforms
        (:func:`itk_nrreval.io._elastix_files.read_elastix_transform`); ``.nii.gz`` / ``.nii``
        / ``.nrrd`` / ``.mha`` / ``.mhd`` (incl. ANTs ``*1Warp.nii.gz``) are displacement
        fields. A manifest entry in another tool's format
        (:class:`~itk_nrreval.io._foreign_transforms.ForeignTransform`: FSL, AFNI, FreeSurfer
        LTA, NiftyReg) is converted into this convention. An in-memory transform is returned
        as is; a manifest's transform object
        (:class:`InMemoryTransform`) gives its transform. An HDF5 file is first checked
        with h5py (:func:`itk_nrreval.io._itk_hdf5.check_file`): one HDF5 cannot read is
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
        raise InputError(f"{path}: cannot read transform ({itk_error_reason(exc)})") from None
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
    (:func:`itk_nrreval.io._itk_hdf5.read_pieces`: the same values in about a quarter of
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
