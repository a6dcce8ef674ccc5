"""A label map's values as the channels of its memberships: the label map and the options of
a resampling checked (:func:`checked_labels`), each requested value given a channel
(:func:`label_table`: a lookup table over the values' range, or a sort where they spread too
widely), and the channel of every voxel (:func:`channel_codes`).

Used by :mod:`itk_nrreval.io._memberships`, which resamples the channels.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import SimpleITK as sitk

from .._errors import InputError, readable
from ._images import Geometry
from ._membership_kernels import mark_present

__all__ = ["LABEL_INTERPOLATIONS", "channel_codes", "checked_labels", "label_table"]


#: The ways label maps can be resampled into memberships (:func:`resample_label_memberships`).
LABEL_INTERPOLATIONS = ("linear", "nearest", "gaussian")


#: Label-value ranges up to this many values are mapped to channels with a lookup table.
_LUT_MAX = 1 << 22


def checked_labels(
    label_map: sitk.Image, transform: sitk.Transform | None, g: Geometry, method: str, sigma_mm
) -> np.ndarray:
    """The label map's values as an integer array (numpy order) once the arguments of
    :func:`resample_label_memberships` are checked (InputError otherwise; `transform` None:
    not yet built, its dimension unchecked)."""
    dim = g.dimension
    if dim not in (2, 3):
        raise InputError(f"grid: {dim}D, expected 2D or 3D")
    t_dim = dim if transform is None else transform.GetDimension()
    if label_map.GetDimension() != dim or t_dim != dim:
        raise InputError(
            f"label map ({label_map.GetDimension()}D), transform ({t_dim}D) "
            f"and grid ({dim}D) must have the same dimension"
        )
    if label_map.GetNumberOfComponentsPerPixel() != 1:
        raise InputError("label map: expected a scalar image, got a vector image")
    labels = sitk.GetArrayViewFromImage(label_map)
    if labels.dtype.kind == "f":  # label maps saved as float by some tools: integers only
        bad = ~np.isfinite(labels) | (labels != np.round(labels))
        if bad.any():
            raise InputError(
                f"label map: non-integer value {float(labels[bad].flat[0]):g} in a "
                f"{label_map.GetPixelIDTypeAsString()} label map; label values must be integers"
            )
        labels = labels.astype(np.int64)
    elif labels.dtype.kind not in "iu":
        raise InputError(
            f"label map: expected an integer pixel type, got {label_map.GetPixelIDTypeAsString()}"
        )
    if method not in LABEL_INTERPOLATIONS:
        raise InputError(f"label interpolation: {method!r} is not one of {LABEL_INTERPOLATIONS}")
    if method == "gaussian":
        if isinstance(sigma_mm, bool) or not isinstance(sigma_mm, (int, float)):
            raise InputError(f"label smoothing: expected a number of mm, got {readable(sigma_mm)}")
        if not 0 < sigma_mm < np.inf:
            raise InputError(
                f"label smoothing: expected a finite sigma > 0 mm, got {readable(sigma_mm)}"
            )
    elif sigma_mm is not None:
        raise InputError(f"label smoothing: sigma_mm is only for method 'gaussian', not {method!r}")
    return labels


def label_table(
    labels3: np.ndarray, values: Sequence[int] | None
) -> tuple[np.ndarray, int, np.ndarray, np.ndarray]:
    """How label values become channels: ``channel = lut[label - vmin]`` (-1: no channel).

    Parameters
    ----------
    labels3 : ndarray of shape (nz, ny, nx), integer
        The label map (a 2D map as one plane).
    values : sequence of int or None
        Requested label values, or None for the sorted values present.

    Returns
    -------
    labels : ndarray of shape (nz, ny, nx), integer
        What the kernel reads: `labels3` itself, or its channel numbers when the values
        spread too widely for a table.
    vmin : int
        Offset of the table.
    lut : ndarray of int32
        Channel per value ``vmin, vmin + 1, ...``; covers every value in `labels`.
    values : ndarray of shape (n_labels,), int64
        The channels' label values.
    """
    if values is not None:
        requested = np.asarray(values)
        if requested.ndim != 1 or (requested.size and requested.dtype.kind not in "iu"):
            raise InputError(f"values: expected a sequence of integers, got {readable(values)}")
        requested = requested.astype(np.int64)
        if np.unique(requested).size != requested.size:
            raise InputError(f"values: repeated label values in {requested.tolist()}")
    if labels3.dtype == np.uint64 and labels3.size and labels3.max() > np.iinfo(np.int64).max:
        raise InputError("label map: label values above 2**63 - 1")
    lo, hi = (int(labels3.min()), int(labels3.max())) if labels3.size else (0, 0)
    if hi - lo < _LUT_MAX:
        # A table over the values' range: linear passes, never a sort of the label map.
        if values is None:
            seen = np.zeros(hi - lo + 1, np.bool_)
            mark_present(labels3, lo, seen)
            requested = lo + np.flatnonzero(seen).astype(np.int64)
        lut = np.full(hi - lo + 1, -1, np.int32)
        hit = (requested >= lo) & (requested <= hi)
        lut[requested[hit] - lo] = np.flatnonzero(hit)
        return labels3, lo, lut, requested
    # Values spread too widely for a table (e.g. hashes): channel numbers by a sort, read by
    # the kernel through the table lut[c + 1] = c.
    flat = labels3.astype(np.int64).ravel()
    if values is None:
        requested = np.unique(flat)
    order = np.argsort(requested, kind="stable")
    ranked = requested[order]
    codes = np.full(flat.shape, -1, np.int32)
    if ranked.size:
        pos = np.minimum(np.searchsorted(ranked, flat), ranked.size - 1)
        found = ranked[pos] == flat
        codes[found] = order[pos[found]]
    lut = np.arange(-1, requested.size, dtype=np.int32)
    return codes.reshape(labels3.shape), -1, lut, requested


def channel_codes(labels3: np.ndarray, vmin: int, lut: np.ndarray) -> np.ndarray:
    """Channel number + 1 of every voxel (0 where its value has no channel), int32."""
    flat = labels3.astype(np.int64, copy=False).ravel()
    codes = lut[flat - vmin].astype(np.int32) + 1
    return codes.reshape(labels3.shape)
