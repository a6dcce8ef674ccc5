"""ITK's HDF5 transform files (``.h5``, ``.hdf5``) read with h5py, for the layouts we know.

ITK writes a transform as ``/TransformGroup/<k>/`` groups, each with a ``TransformType``
(``"AffineTransform_double_3_3"``), and for all but a composite its
``TransformFixedParameters`` and ``TransformParameters``; a composite is group 0 and its
pieces follow in SimpleITK's list order (the last acts first). ANTs' ``Composite.h5`` and
``sitk.WriteTransform`` of an affine map, a displacement field or a composite of them write
this layout.

``sitk.ReadTransform`` of a 1 mm displacement field (0.2 GB) takes about 0.45 s of CPU, and
taking its composite apart copies the field once more (0.1 to 0.25 s): the per-image tasks of
``evaluate`` read every field two or three times. Reading the arrays with h5py and building
the pieces from them takes one read and one copy (:func:`read_pieces`: tested equal to
ITK's reading, bit for bit). Anything else -- other transform types, float precision,
parameter counts that do not fit the type -- is left to ITK (None), whose messages name
what is wrong.

A file HDF5 itself cannot read (truncated, damaged) is refused here first
(:func:`check_file`): ITK's own copy of the HDF5 library prints its whole error stack
(``HDF5-DIAG``, about 25 lines) on the process's stderr before ITK raises, while h5py's copy
keeps its stack to itself and raises.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import h5py
import numpy as np
import SimpleITK as sitk

#: The pieces read here: name -> (fixed, parameters) counts for dimension d and, for a
#: displacement field, its grid size (the first d fixed parameters).
PIECE_COUNTS = {
    "CompositeTransform": lambda d, size: (0, 0),
    "AffineTransform": lambda d, size: (d, d * d + d),
    "DisplacementFieldTransform": lambda d, size: (d * (3 + d), math.prod(size) * d),
}

_TYPE = re.compile(r"(\w+?)_(double|float)_(\d)_(\d)")

#: What a file that is not one we know raises while it is read here.
_UNKNOWN = (OSError, KeyError, ValueError, TypeError, IndexError)

#: Datasets up to this many values are read whole by :func:`check_file`: every piece's type
#: name and fixed parameters, an affine map's parameters; not a displacement field's values
#: (0.2 GB at 1 mm), whose dataset's header is loaded only.
_READ_WHOLE = 4096


def check_file(path: Path) -> None:
    """Refuse a file HDF5 cannot read, before ITK reads it.

    The file is opened with h5py, the header of every object in it loaded and every small
    dataset read: what HDF5 finds wrong (a file shorter than its superblock says, a bad
    checksum, an address past the end) raises here without a word on stderr, where ITK's
    reading would first print HDF5's error stack.

    Parameters
    ----------
    path : Path
        An ``.h5`` / ``.hdf5`` file.

    Raises
    ------
    ValueError
        What is wrong, in words for a message naming the file: ``truncated HDF5 file: 4168
        of its 8336 bytes``, ``not an HDF5 file``, or HDF5's own reason.
    """

    def load(_name: str, item) -> None:  # None: visititems goes on to the next object
        if isinstance(item, h5py.Dataset) and item.size <= _READ_WHOLE:
            item[()]

    try:
        with h5py.File(path, "r") as f:
            f.visititems(load)
    except (OSError, RuntimeError, KeyError, ValueError, TypeError) as exc:
        raise ValueError(_problem(exc)) from None


def _problem(exc: Exception) -> str:
    """h5py's message (``Unable to synchronously open file (truncated file: eof = 4168,
    sblock->base_addr = 0, stored_eof = 8336)``) in a user's words."""
    text = " ".join(str(exc).split())
    if m := re.search(r"truncated file: eof = (\d+).*stored_eof = (\d+)", text):
        return f"truncated HDF5 file: {m.group(1)} of its {m.group(2)} bytes"
    if "file signature not found" in text:
        return "not an HDF5 file"
    if m := re.search(r"error message = '([^']*)'", text):  # the system's: permission denied
        return m.group(1)
    reason = re.search(r"\(([^()]*)\)\s*$", text)
    return f"damaged HDF5 file: {reason.group(1) if reason else text}"[:160]


def _layout(f: h5py.File) -> list[tuple[str, str, int, h5py.Group]] | None:
    """Each group's (name, precision, dimension, group), in file order; None unless every
    piece is a known type of one dimension with the counts ITK reads for it, and a
    composite, if any, is group 0 of several."""
    group = f["TransformGroup"]
    out = []
    for k in range(len(group)):
        piece = group[str(k)]
        kind = piece["TransformType"][0]
        kind = kind.decode() if isinstance(kind, bytes) else str(kind)
        m = _TYPE.fullmatch(kind)
        if m is None or m.group(1) not in PIECE_COUNTS or m.group(3) != m.group(4):
            return None
        name, d = m.group(1), int(m.group(3))
        if name == "CompositeTransform":
            if k != 0:  # ITK writes no nested composite
                return None
        else:
            fixed = piece["TransformFixedParameters"]
            size = fixed[:d] if len(fixed) >= d else ()
            expected = PIECE_COUNTS[name](d, [int(v) for v in size])
            if (len(fixed), len(piece["TransformParameters"])) != expected:
                return None
        out.append((name, m.group(2), d, piece))
    if not out or len({d for _n, _p, d, _g in out}) != 1:
        return None
    return out


def transform_dimension(path: Path) -> int | None:
    """A transform file's dimension from its layout alone: every piece's type and its
    parameters' counts, not their values (a 1 mm displacement field is 0.2 GB; reading them
    all took 44 s of a 36-image manifest's check of five registrations).

    Returns
    -------
    int or None
        None when the file is not an HDF5 file (ITK refuses it too, in one line of its own)
        or its layout is not one :func:`_layout` knows: the caller reads it with ITK.

    Raises
    ------
    ValueError
        An HDF5 file that HDF5 cannot read (:func:`check_file`): ITK's reading of it would
        print HDF5's error stack.
    """
    if not h5py.is_hdf5(path):
        return None
    check_file(path)
    try:
        with h5py.File(path, "r") as f:
            layout = _layout(f)
    except _UNKNOWN:
        return None
    return None if layout is None else layout[0][2]


def read_pieces(path: Path) -> list[sitk.Transform] | None:
    """The transform in an ITK HDF5 file as its pieces, in SimpleITK list order.

    Parameters
    ----------
    path : Path
        An ``.h5`` / ``.hdf5`` transform file.

    Returns
    -------
    list of sitk.Transform, or None
        What ``leaves(sitk.ReadTransform(path))`` gives, to the bit: ``sitk.AffineTransform``
        and ``sitk.DisplacementFieldTransform`` (its field ``sitkVectorFloat64``, on the
        file's grid: size, origin, spacing, direction). None when the file is not one of
        double-precision affine maps, displacement fields and a composite of them: the caller
        reads it with ITK. Values are not checked finite here.
    """
    try:
        with h5py.File(path, "r") as f:
            layout = _layout(f)
            if layout is None or any(p != "double" for _n, p, _d, _g in layout):
                return None
            return [_piece(name, d, g) for name, _p, d, g in layout if name != "CompositeTransform"]
    except _UNKNOWN:
        return None


def _piece(name: str, d: int, group: h5py.Group) -> sitk.Transform:
    fixed = np.asarray(group["TransformFixedParameters"][()], np.float64)
    data = group["TransformParameters"]
    if name == "AffineTransform":
        t = sitk.AffineTransform(d)
        t.SetFixedParameters(fixed.tolist())
        t.SetParameters(np.asarray(data[()], np.float64).tolist())
        return t
    size = [int(v) for v in fixed[:d]]
    values = np.empty(data.shape, np.float64)
    data.read_direct(values)
    field = sitk.GetImageFromArray(values.reshape(*size[::-1], d), isVector=True)
    del values
    field.SetOrigin(fixed[d : 2 * d].tolist())
    field.SetSpacing(fixed[2 * d : 3 * d].tolist())
    field.SetDirection(fixed[3 * d :].tolist())
    return sitk.DisplacementFieldTransform(field)  # takes the image's buffer over
