"""Membership images on disk: the file format of ``memberships_###.nii.gz`` (one float32
component per label, a JSON sidecar and a NIfTI description that name the labels), written by
``nrreval evaluate --save-resampled`` and read back by ``nrreval overlap``.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from .._errors import InputError
from .._output import atomic_path, write_json
from ._images import Geometry, read_header
from .transforms import file_stem

__all__ = ["MEMBERSHIPS_KIND", "membership_file_labels", "sidecar_path", "write_membership_image"]


#: The ``kind`` in the JSON sidecar of a membership image (:func:`write_membership_image`).
MEMBERSHIPS_KIND = "memberships"


#: How the NIfTI description of a membership image starts (:func:`write_membership_image`).
_HEADER = "nrreval memberships"


_HEADER_WITH_LABELS = re.compile(r"nrreval memberships; labels (-?\d+(?:,-?\d+)*); ")


#: ITK refuses a longer NIfTI description (``descrip`` holds 80 bytes with its terminator).
_NIFTI_DESCRIPTION_MAX = 79


def sidecar_path(path: str | os.PathLike) -> Path:
    """The JSON sidecar of the image at `path`: same folder and stem, ``.json``
    (``memberships_000.nii.gz`` -> ``memberships_000.json``)."""
    return Path(path).with_name(file_stem(path) + ".json")


def write_membership_image(
    path: str | os.PathLike,
    memberships: np.ndarray,
    *,
    labels: Sequence[int],
    geometry: Geometry,
    about: Mapping[str, object] | None = None,
) -> None:
    """Write fuzzy memberships as one multi-component image that says which labels they are.

    The file format of ``memberships_###.nii.gz`` (``nrreval evaluate --save-resampled``):

    * the image: one float32 component per label, component k the membership in [0, 1] of
      label ``labels[k]``; no background component (background is one minus the sum of
      the components inside the field of view); every component 0 outside it. One label
      gives a scalar image (NIfTI stores no one-component vector);
    * its JSON sidecar (:func:`sidecar_path`): ``{"kind": "memberships", "labels": [...],
      "background": false, "image": <file name>, ...}`` plus the entries of `about`;
    * its NIfTI description: ``nrreval memberships; labels 2,5,9; no background``, or, when
      the labels do not fit in the header's 79 characters, ``nrreval memberships; labels in
      <sidecar>; no background``.

    :func:`membership_file_labels` reads the labels back; ``nrreval overlap`` uses them
    instead of taking component 0 for background.

    Parameters
    ----------
    path : path
        The image file (NIfTI, ``.nii.gz``); the sidecar is written beside it. Both are
        written atomically (a temporary file renamed on success).
    memberships : ndarray of shape (n_labels, *geometry.shape), float32
        The memberships, numpy axis order (label, [z,] y, x).
    labels : sequence of int, length n_labels
        The label value of each component, nonzero, in component order.
    geometry : Geometry
        The grid (spacing mm, origin mm LPS, direction).
    about : mapping of str to JSON values, optional
        Added to the sidecar (e.g. the subject's index and the registration's name).
    """
    labels = [int(v) for v in labels]
    if memberships.shape[0] != len(labels) or 0 in labels:
        raise ValueError(
            f"{len(labels)} nonzero labels for {memberships.shape[0]} components: {labels}"
        )
    path = Path(path)
    sidecar = sidecar_path(path)
    description = f"{_HEADER}; labels {','.join(map(str, labels))}; no background"
    if len(description) > _NIFTI_DESCRIPTION_MAX:
        description = f"{_HEADER}; labels in {sidecar.name}; no background"
    img = sitk.GetImageFromArray(np.moveaxis(memberships, 0, -1), isVector=True)
    geometry.apply_to(img)
    # ITK's NIfTI writer puts this key in the header's description (`descrip`)
    img.SetMetaData("ITK_FileNotes", description[:_NIFTI_DESCRIPTION_MAX])
    with atomic_path(path) as tmp:
        sitk.WriteImage(img, str(tmp), True)
    write_json(
        sidecar,
        {
            "kind": MEMBERSHIPS_KIND,
            "image": path.name,
            "labels": labels,
            "background": False,
            "components": "component k is the membership in [0, 1] of label labels[k]; "
            "background is 1 minus their sum inside the field of view; all are 0 outside it",
            **(about or {}),
        },
    )


def membership_file_labels(item, *, name: str) -> tuple[int, ...] | None:
    """The label value of each component of a membership image, when the image says so.

    Parameters
    ----------
    item : path or sitk.Image
        A membership image. For a path, its JSON sidecar (:func:`sidecar_path`) is read
        when it has ``"kind": "memberships"`` (other JSON beside an image, e.g. a BIDS
        sidecar, is not ours and is ignored); otherwise the header's description.
    name : str
        The image's name in messages.

    Returns
    -------
    tuple of int, or None
        ``labels[k]`` is the label of component k (a scalar image has one component). None
        when neither sidecar nor header says (a third-party file: the caller's own rules).

    Raises
    ------
    InputError
        A memberships sidecar with malformed labels or as many labels as the image has
        components, or a header that says the labels are in a sidecar that is missing.
    """
    if isinstance(item, sitk.Image):
        n_components = item.GetNumberOfComponentsPerPixel()
        keys = set(item.GetMetaDataKeys())
        key = "descrip" if "descrip" in keys else "ITK_FileNotes"
        description = item.GetMetaData(key) if key in keys else ""
        sidecar = None
    elif isinstance(item, (str, os.PathLike)):
        reader = read_header(item)
        n_components = reader.GetNumberOfComponents()
        has = reader.HasMetaDataKey("descrip")
        description = reader.GetMetaData("descrip") if has else ""
        sidecar = sidecar_path(item)
        labels = _sidecar_labels(sidecar)
        if labels is not None:
            if len(labels) != n_components:
                raise InputError(
                    f"{sidecar}: names {len(labels)} labels, but {name} has "
                    f"{n_components} components"
                )
            return labels
    else:
        return None
    if not description.startswith(_HEADER):
        return None
    found = _HEADER_WITH_LABELS.match(description)
    if found is None:
        where = sidecar.name if sidecar is not None else "its JSON sidecar"
        raise InputError(
            f"{name}: a membership image whose labels are listed in {where}, which is missing"
            + (" (an in-memory image: pass the file)" if sidecar is None else "")
        )
    labels = tuple(int(v) for v in found.group(1).split(","))
    if len(labels) != n_components:
        raise InputError(
            f"{name}: its description names {len(labels)} labels for {n_components} components"
        )
    return labels


def _sidecar_labels(sidecar: Path) -> tuple[int, ...] | None:
    """The labels of a memberships sidecar; None when there is none, or not ours."""
    try:
        data = json.loads(sidecar.read_text())
    except (OSError, UnicodeDecodeError, ValueError):  # absent, or not a JSON sidecar of ours
        return None
    if not isinstance(data, dict) or data.get("kind") != MEMBERSHIPS_KIND:
        return None
    labels = data.get("labels")
    if (
        not isinstance(labels, list)
        or not labels
        or not all(isinstance(v, int) and not isinstance(v, bool) for v in labels)
        or len(set(labels)) != len(labels)
    ):
        raise InputError(
            f"{sidecar}: 'labels' must be a non-empty list of distinct integers, got {labels!r}"
        )
    return tuple(labels)
