"""Label maps resampled as sparse fuzzy memberships: exactly ITK's linear one-hot resampling.

The dense way of resampling a label map onto a grid as fuzzy memberships builds a one-hot
vector image (one float channel per label) and passes it through ``sitk.Resample`` with
``sitk.sitkLinear``: cost and memory grow with the number of labels L, although each grid
point only ever receives weight from the at most ``2**dim`` label-map voxels around it.

:func:`resample_label_memberships` computes the same numbers label-free: the grid's points
are mapped once, the ``2**dim`` interpolation weights of each point are computed once, and
each weight is added to the membership of the label of its corner. Only nonzero memberships
are stored (:class:`SparseMemberships`, per label a sorted list of voxels and weights).

Conventions
-----------
* ``transform`` maps **grid (reference) points to label-map points**, physical mm, LPS, as
  in ``sitk.Resample``; the label map and the grid may have any origin, spacing and
  direction cosines.
* Grid sizes are in ITK order ``(x, y[, z])``; arrays and flat voxel indices are in numpy
  C order of the shape ``(z, y, x)`` (``(y, x)`` in 2D).

Exactness (what ITK does, and how it is reproduced here)
--------------------------------------------------------
For a grid point mapped to the continuous index ``c`` of the label map (size ``n`` per axis),
ITK's ``ResampleImageFilter`` with ``LinearInterpolateImageFunction`` gives

* the default value 0 unless ``-0.5 <= c < n - 0.5`` on every axis (``IsInsideBuffer``:
  half-open, the lower half-voxel border counts as inside, the upper one does not);
* otherwise the multilinear interpolation of the voxel values with ``c`` clamped to
  ``[0, n - 1]`` per axis: between the outer voxel centres and the buffer border the
  interpolator takes the border voxel's value (its lower neighbour index is raised to the
  start, its upper neighbour beyond the end is dropped).

Both are reproduced in the kernel. The one discontinuity is the buffer border, where a
rounding difference of one unit in the last place between ITK's arithmetic and ours would
flip a point from 0 to full membership; so wherever some point's continuous index lies
within ``1e-6`` voxels of a border, ITK is asked directly which points are inside (one
``sitk.Resample`` of an all-ones uint8 image, same transform and grid), and that answer is
used instead of ours (a point ITK counts as inside while ours lies an ulp outside is then
clamped like any other). Everywhere the memberships agree with ITK's before its float32
cast to rounding (~1e-15), so after it to float32 resolution.
Continuous indices within ``1e-9`` voxels of a voxel centre are put on it, so that resampling
onto the label map's own grid gives exact one-hot memberships rather than neighbours with
weights of 1e-16 (a change far below float32 resolution).
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numba
import numpy as np
import SimpleITK as sitk
from scipy import ndimage

from ._errors import InputError, readable
from ._images import Geometry, read_header
from ._output import atomic_path, write_json
from .transforms import PointMap, TransformPieces, file_stem, flatten, is_linear

__all__ = [
    "LABEL_INTERPOLATIONS",
    "MEMBERSHIPS_KIND",
    "SparseMemberships",
    "covered_voxels",
    "membership_file_labels",
    "resample_label_memberships",
    "sidecar_path",
    "write_membership_image",
]

#: The ways label maps can be resampled into memberships (:func:`resample_label_memberships`).
LABEL_INTERPOLATIONS = ("linear", "nearest", "gaussian")
#: Smoothed memberships below this are not stored (Gaussian tails, recursive-filter noise).
_GAUSSIAN_FLOOR = 1e-6

#: Grid voxels mapped per slab: bounds the float64 (slab, dim) point array (~24 MB in 3D).
_SLAB_VOXELS = 1 << 20
#: Continuous indices closer than this (voxels) to the buffer border are decided by ITK.
_BORDER_EPS = 1e-6
#: Up to this many such points, ITK decides each one as its resampling does, point by point
#: (:func:`_itk_inside_at`); beyond it, or for a linear transform, by resampling the grid.
_POINTWISE_LIMIT = 10_000
#: Continuous indices closer than this (voxels) to a voxel centre are put on it.
_SNAP = 1e-9
#: Label-value ranges up to this many values are mapped to channels with a lookup table.
_LUT_MAX = 1 << 22

#: The ``kind`` in the JSON sidecar of a membership image (:func:`write_membership_image`).
MEMBERSHIPS_KIND = "memberships"
#: How the NIfTI description of a membership image starts (:func:`write_membership_image`).
_HEADER = "nrreval memberships"
_HEADER_WITH_LABELS = re.compile(r"nrreval memberships; labels (-?\d+(?:,-?\d+)*); ")
#: ITK refuses a longer NIfTI description (``descrip`` holds 80 bytes with its terminator).
_NIFTI_DESCRIPTION_MAX = 79


@dataclass(frozen=True, eq=False)
class SparseMemberships:
    """Fuzzy memberships of one label map on a grid, stored per label where they are nonzero.

    A compressed-sparse-row layout with one row per label: label ``k`` (value ``values[k]``)
    has membership ``weight[j]`` at the flat voxel ``index[j]`` for ``ptr[k] <= j <
    ptr[k + 1]``, and 0 at every voxel not listed. The arrays are read-only.

    Attributes
    ----------
    values : ndarray of shape (n_labels,), int64
        The label values, in the order requested.
    shape : tuple of int
        Numpy shape of the grid, ``(z, y, x)`` (``(y, x)`` in 2D): the reverse of the grid's
        ITK size.
    ptr : ndarray of shape (n_labels + 1,), int64
        Label k's entries are ``[ptr[k], ptr[k + 1])``; ``ptr[0] == 0``, ``ptr[-1] == nnz``.
    index : ndarray of shape (nnz,), int64
        Flat C-order voxel indices into `shape`, ascending within each label.
    weight : ndarray of shape (nnz,), float32
        Memberships in (0, 1] (exact zeros are not stored).
    """

    values: np.ndarray
    shape: tuple[int, ...]
    ptr: np.ndarray
    index: np.ndarray
    weight: np.ndarray

    @property
    def n_labels(self) -> int:
        """Number of labels (channels)."""
        return int(self.values.shape[0])

    def label(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Label k's nonzero memberships.

        Parameters
        ----------
        k : int
            Channel number, ``0 <= k < n_labels`` (not the label value).

        Returns
        -------
        index : ndarray of shape (n_k,), int64
            Flat C-order voxel indices, ascending (views, read-only).
        weight : ndarray of shape (n_k,), float32
            The memberships there, in (0, 1].
        """
        if not 0 <= k < self.n_labels:
            raise IndexError(f"label channel {k} out of range for {self.n_labels} labels")
        lo, hi = int(self.ptr[k]), int(self.ptr[k + 1])
        return self.index[lo:hi], self.weight[lo:hi]

    def dense(self, *, dtype=np.float32) -> np.ndarray:
        """The memberships as a dense array.

        Parameters
        ----------
        dtype : numpy dtype
            Of the result.

        Returns
        -------
        ndarray of shape (n_labels, *shape)
            Zero wherever a label has no entry; what the dense one-hot resampling gives.
        """
        out = np.zeros((self.n_labels, int(np.prod(self.shape))), dtype=dtype)
        for k in range(self.n_labels):
            idx, w = self.label(k)
            out[k, idx] = w
        return out.reshape(self.n_labels, *self.shape)


def resample_label_memberships(
    label_map: sitk.Image,
    transform: sitk.Transform,
    grid: Geometry | sitk.Image,
    *,
    values: Sequence[int] | None = None,
    method: str = "linear",
    sigma_mm: float | None = None,
) -> SparseMemberships:
    """Resample a label map onto `grid` as fuzzy (or crisp) memberships, sparsely.

    With ``method="linear"`` (the default): equal (to float32 rounding) to ``sitk.Resample``
    of the float32 one-hot vector image of `label_map` (one channel per value of `values`)
    through `transform` onto `grid` with ``sitk.sitkLinear`` and default value 0, border
    behaviour included (module docstring), without ever building the one-hot image.

    Parameters
    ----------
    label_map : sitk.Image
        Scalar label map of any integer pixel type (or a floating type holding only
        integers), 2D or 3D, any origin, spacing and
        direction cosines.
    transform : sitk.Transform
        Grid (reference) points -> label-map points, physical mm, LPS: any SimpleITK
        transform of the same dimension (affine, displacement field, B-spline, composite).
    grid : Geometry or sitk.Image
        Where the memberships are sampled (voxel centres); an image gives its grid.
    values : sequence of int, optional
        The label values, one channel each, in this order (no repeats). Default: the sorted
        values present in `label_map`. A requested value absent from the map gets an empty
        channel; a value present but not requested contributes to no channel, so the
        memberships of the requested labels then sum to less than 1 near it.
    method : {"linear", "nearest", "gaussian"}
        How memberships are interpolated. ``"linear"``: the one-hot channels linearly
        interpolated (partial memberships within a voxel of every boundary). ``"nearest"``:
        crisp memberships of the label map resampled with ``sitk.sitkNearestNeighbor``
        (0 or 1; a boundary moves by up to half a voxel). ``"gaussian"``: each one-hot
        channel smoothed by a Gaussian of standard deviation `sigma_mm` (mm, the same on
        every axis, in the label map's space) and then linearly interpolated (memberships
        below 1e-6 are not stored, so they sum to 1 within about 1e-5); costs one
        resampling of the grid per label.
    sigma_mm : float, optional
        The Gaussian's standard deviation in mm; only with, and required by,
        ``method="gaussian"``.

    Returns
    -------
    SparseMemberships
        On `grid`'s numpy shape; memberships in (0, 1], summing to 1 over all values present
        at every grid point whose image lies inside the label map's buffer, 0 outside it.

    Raises
    ------
    InputError
        Not a scalar integer label map, dimensions that differ or are not 2 or 3, repeated
        or non-integer `values`.

    Notes
    -----
    For ``"linear"``, the grid is processed in slabs of whole planes along its slowest numpy
    axis (z in 3D), about a million voxels each, so that the mapped points are never held
    for the whole grid at once. The result takes 12 bytes per stored entry (about 1.1
    entries per voxel for a brain parcellation at its own resolution); while it is built,
    up to 8 more per entry and about 60 MB of per-slab buffers, plus one byte per grid voxel
    when ITK is asked about the border. ``"nearest"`` and ``"gaussian"`` resample whole
    grids with ITK (4 bytes per grid voxel at a time).
    """
    g = grid if isinstance(grid, Geometry) else Geometry.from_image(grid)
    labels = _checked_labels(label_map, transform, g, method, sigma_mm)
    dim = g.dimension
    labels3 = labels.reshape((1,) * (3 - dim) + labels.shape)  # 2D as one plane of 3D
    labels3, vmin, lut, values = _label_table(labels3, values)
    if method != "linear":
        # Channel numbers + 1 as an image (0: no channel), so that ITK resamples channels.
        codes = _channel_codes(labels3, vmin, lut).reshape(labels.shape)
        code_image = sitk.GetImageFromArray(codes)
        code_image.CopyInformation(label_map)
        if method == "nearest":
            return _nearest_memberships(code_image, transform, g, values)
        return _gaussian_memberships(code_image, transform, g, values, float(sigma_mm))

    image_grid = Geometry.from_image(label_map)
    return _linear_memberships(image_grid, labels3, vmin, lut, values, transform, g)[0]


def resample_image_and_memberships(
    image: sitk.Image,
    label_map: sitk.Image | None,
    transform: sitk.Transform | Callable[[], sitk.Transform] | TransformPieces,
    grid: Geometry | sitk.Image,
    *,
    values: Sequence[int] | None = None,
    displacement: np.ndarray | PointMap | None = None,
) -> tuple[np.ndarray, SparseMemberships | None]:
    """An image and its label map (on the same grid) resampled linearly through one
    sampling of `transform`; or the image alone (`label_map` None), by the same kernels.

    The transform is sampled once per grid point for both, where resampling the image with
    ``sitk.Resample`` would sample it again (a third of a 1 mm image's resampling cost);
    with `displacement` a :class:`~itk_nrreval.transforms.PointMap`, an image alone costs
    about half of ``sitk.Resample`` through the composite (which, for a transform held as
    its pieces, must be built first: a copy of every field).

    Parameters
    ----------
    image : sitk.Image
        Scalar, on `label_map`'s grid (:func:`shares_grid`).
    label_map, transform, grid, values
        As :func:`resample_label_memberships` (``method="linear"``); `label_map` None for
        the image alone (`values` then unused). With `displacement`,
        `transform` may be a function of no arguments that returns it: called only where
        ITK's own inside-buffer decisions are needed (a point within 1e-6 voxel of the
        image's border), for a transform costly to build (a composite copies its fields); or
        its pieces (:class:`~itk_nrreval.transforms.TransformPieces`), which ITK then maps
        point by point without a composite.
    displacement : ndarray of shape ``(*grid.shape, dim)`` or PointMap, optional
        ``transform(p) - p`` already sampled on `grid` (mm, ITK order last; what
        ``sitk.GetArrayViewFromImage`` of ``sitk.TransformToDisplacementField`` gives) when
        the caller has it, or the transform as a
        :class:`~itk_nrreval.transforms.PointMap` for the compiled kernels to sample slab
        by slab (no array of the whole grid); default: sampled here by ITK, slab by slab.

    Returns
    -------
    image : ndarray of shape (n_voxels,), float64
        Flat, C order on `grid`: ``sitk.Resample`` of the image cast to float64 with
        ``sitk.sitkLinear`` (to about 1e-15 of its range: the same neighbours and weights,
        in another order of operations), NaN where ITK finds the point outside the image's
        buffer.
    memberships : SparseMemberships or None
        What :func:`resample_label_memberships` returns, to the bit; None without a label
        map.

    Raises
    ------
    ValueError
        `image` is not on `label_map`'s grid, or not scalar, or (without a label map) not of
        the grid's dimension; `transform` a function without `displacement`.
    InputError
        As :func:`resample_label_memberships`.
    """
    if image.GetNumberOfComponentsPerPixel() != 1 or (
        label_map is not None and not shares_grid(image, label_map)
    ):
        raise ValueError("image: expected a scalar image on the label map's grid")
    built = isinstance(transform, sitk.Transform)
    if not built and displacement is None:
        raise ValueError("transform: a function or pieces only with displacement=")
    g = grid if isinstance(grid, Geometry) else Geometry.from_image(grid)
    lead = (1,) * (3 - g.dimension)  # 2D as one plane of 3D
    labels3, vmin, lut = None, 0, None
    if label_map is not None:
        labels = _checked_labels(label_map, transform if built else None, g, "linear", None)
        labels3, vmin, lut, values = _label_table(labels.reshape(lead + labels.shape), values)
    elif image.GetDimension() != g.dimension:
        raise ValueError(f"image: {image.GetDimension()}D on a {g.dimension}D grid")
    pixels = sitk.GetArrayViewFromImage(image)
    pixels = np.asarray(pixels, dtype=np.float64).reshape(lead + pixels.shape)
    if isinstance(displacement, np.ndarray) and displacement.shape != (*g.shape, g.dimension):
        raise ValueError(f"displacement: shape {displacement.shape}, not the grid's")
    image_grid = Geometry.from_image(image)
    memberships, resampled = _linear_memberships(
        image_grid, labels3, vmin, lut, values, transform, g, image=pixels, sampled=displacement
    )
    return resampled, memberships


def shares_grid(image: sitk.Image, label_map: sitk.Image) -> bool:
    """Whether `image` and `label_map` have the same grid: size, origin, spacing and
    direction equal to the bit (then one continuous index serves both)."""
    return (
        image.GetSize() == label_map.GetSize()
        and image.GetOrigin() == label_map.GetOrigin()
        and image.GetSpacing() == label_map.GetSpacing()
        and image.GetDirection() == label_map.GetDirection()
    )


def _checked_labels(
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


def _linear_memberships(
    image_grid: Geometry,
    labels3: np.ndarray | None,
    vmin: int,
    lut: np.ndarray | None,
    values: np.ndarray | None,
    transform: sitk.Transform | Callable[[], sitk.Transform] | TransformPieces,
    g: Geometry,
    image: np.ndarray | None = None,
    sampled: np.ndarray | PointMap | None = None,
) -> tuple[SparseMemberships | None, np.ndarray | None]:
    """The linear memberships of a label map on `image_grid` (`labels3` and its table,
    :func:`_label_table`; None: no label map), slab by slab; with `image` (on that grid,
    numpy order, float64), also the image linearly resampled at the same points (flat
    float64, NaN outside the buffer: :func:`resample_image_and_memberships`). `sampled`: the
    transform's displacement on the whole grid, or its PointMap, when the caller has it
    (then `transform` may be a function that builds it, called only for ITK's decisions
    near the border)."""
    border = _BorderDecisions(transform, g, image_grid)
    pieces = []  # per slab: (first flat voxel, label starts, index, weight)
    resampled = None if image is None else np.empty(int(np.prod(g.shape)))
    plane = int(np.prod(g.shape[1:]))
    for z0, cidx, near_border in _slab_indices(transform, g, border.image_grid, sampled):
        nz = cidx.shape[0] // plane
        mask = np.empty(0, np.uint8)
        if near_border or border.whole is not None:  # ITK's decisions, here or everywhere
            mask = border.slab(z0 * plane, cidx, near_border).view(np.uint8)
        if labels3 is not None:
            pieces.append(
                (z0 * plane, *_slab_memberships(cidx, labels3, vmin, lut, mask, len(values)))
            )
        if image is not None:
            _linear_values(cidx, image, mask, resampled[z0 * plane : (z0 + nz) * plane])
        del cidx
    memberships = None if labels3 is None else _assemble(values, g.shape, pieces)
    return memberships, resampled


def covered_voxels(
    image_grid: Geometry,
    transform: sitk.Transform | Callable[[], sitk.Transform] | TransformPieces,
    grid: Geometry,
    *,
    displacement: np.ndarray | PointMap | None = None,
) -> np.ndarray:
    """Which voxels of `grid` `transform` maps into the field of view of an image on
    `image_grid`, as ITK decides it.

    ITK's ``ResampleImageFilter`` gives a grid point a value when its continuous index in
    the image lies in ``[-0.5, size - 0.5)`` on every axis (``IsInsideBuffer``): these are
    the points where ``sitk.Resample`` and :func:`resample_image_and_memberships` give the
    image a value, found without resampling it. Points within 1e-6 voxel of the border are
    decided by ITK itself, as the resampling does.

    Parameters
    ----------
    image_grid : Geometry
        The image's grid (size, spacing, origin, direction).
    transform : sitk.Transform, callable or TransformPieces
        Grid points -> image points (physical mm, LPS). With `displacement`, it may be a
        function of no arguments that returns it, called only if ITK's decisions are needed,
        or its pieces (ITK's point-by-point decisions then need no composite).
    grid : Geometry
        The grid whose voxels are decided.
    displacement : ndarray of shape ``(*grid.shape, dim)`` or PointMap, optional
        ``transform(p) - p`` already sampled on `grid` (mm, ITK order last) when the
        caller has it, or the transform as a :class:`~itk_nrreval.transforms.PointMap`
        for the compiled kernels to sample slab by slab; default: sampled here by ITK, slab
        by slab.

    Returns
    -------
    ndarray of shape (n_voxels,), bool
        Flat, C order on `grid`: True where the image has a value.
    """
    if displacement is None and not isinstance(transform, sitk.Transform):
        raise ValueError("transform: a function or pieces only with displacement=")
    covered = np.empty(int(np.prod(grid.shape)), np.bool_)
    whole = isinstance(displacement, np.ndarray)  # the caller's sampling of the whole grid
    if whole and displacement.shape != (*grid.shape, grid.dimension):
        raise ValueError(f"displacement: shape {displacement.shape}, not the grid's")
    border = _BorderDecisions(transform, grid, image_grid)
    plane = int(np.prod(grid.shape[1:]))
    if whole:  # one pass over the caller's sampling, no index copy
        maps = _index_maps(grid, image_grid)
        points = displacement.reshape(-1, grid.dimension)
        size = np.asarray(grid.size, np.int64)
        if not _covered_from(points, size, *maps, _BORDER_EPS, covered):
            return covered
    # some points lie on the border (or no whole sampling was given): slab by slab, ITK
    # decides the points on the border
    for z0, cidx, near in _slab_indices(transform, grid, image_grid, displacement):
        start = z0 * plane
        if near or border.whole is not None:
            covered[start : start + cidx.shape[0]] = border.slab(start, cidx, near)
        elif not whole:
            _inside_flags(cidx, *_zyx(image_grid.shape), covered[start : start + cidx.shape[0]])
    return covered


def _zyx(shape: tuple[int, ...]) -> tuple[int, int, int]:
    """(nz, ny, nx) of a 2D (ny, nx) or 3D numpy shape (nz 1 in 2D)."""
    return (1, *shape) if len(shape) == 2 else tuple(shape)


def _slab_indices(
    transform, g: Geometry, image_grid: Geometry, sampled: np.ndarray | PointMap | None
):
    """Per slab of `g`'s planes: (first plane, continuous indices in `image_grid` of the
    slab's voxels ``(m, dim)``, ITK order, the number within 1e-6 voxel of its border). The
    indices are valid until the next slab (one buffer serves them all).

    The points are ``transform(p)``: from `sampled`, ``transform(p) - p`` on `g`, or a
    :class:`~itk_nrreval.transforms.PointMap` the compiled kernels evaluate slab by slab;
    without it, sampled here by ITK, slab by slab.
    """
    dim = g.dimension
    g_origin, g_matrix, l_origin, l_inverse, l_size = _index_maps(g, image_grid)
    plane = int(np.prod(g.shape[1:]))
    if plane >= 2**31:
        raise InputError(f"grid: {plane} voxels per plane, more than this kernel indexes")
    step = max(1, _SLAB_VOXELS // plane)
    rows = min(step, g.shape[0]) * plane
    cidx_buffer = np.empty((rows, dim))
    points_buffer = np.empty((rows, 3)) if isinstance(sampled, PointMap) else None
    for z0 in range(0, g.shape[0], step):
        nz = min(step, g.shape[0] - z0)
        size = (*g.size[:-1], nz)
        origin = g_origin + g_matrix[:, -1] * z0
        cidx = cidx_buffer[: nz * plane]
        if isinstance(sampled, PointMap):
            slab = Geometry(size, g.spacing, tuple(origin.tolist()), g.direction)
            points = sampled.points(slab, z0, out=points_buffer)
            near_border = _point_indices(points, l_origin, l_inverse, l_size, _BORDER_EPS, cidx)
            yield z0, cidx, near_border
            continue
        if sampled is None:
            field = sitk.TransformToDisplacementField(
                transform, sitk.sitkVectorFloat64, size, origin.tolist(), g.spacing, g.direction
            )
            disp = sitk.GetArrayViewFromImage(field).reshape(-1, dim)  # T(p) - p
        else:
            field = None
            disp = sampled[z0 : z0 + nz].reshape(-1, dim)
        near_border = _continuous_indices(
            disp,
            np.asarray(size, np.int64),
            z0,
            g_origin,
            g_matrix,
            l_origin,
            l_inverse,
            l_size,
            _BORDER_EPS,
            cidx,
        )
        del disp, field
        yield z0, cidx, near_border


def _index_maps(g: Geometry, image_grid: Geometry) -> tuple[np.ndarray, ...]:
    """(g's origin, g's index -> point matrix, the image's origin, its point -> continuous
    index matrix, its ITK size): ITK's ImageBase mappings, grid voxel -> physical point:
    origin + D diag(spacing) index; image point -> continuous index: (D diag(spacing))^-1
    (point - origin)."""
    dim = g.dimension
    g_matrix = np.asarray(g.direction, float).reshape(dim, dim) * np.asarray(g.spacing)
    l_direction = np.asarray(image_grid.direction, float).reshape(dim, dim)
    l_inverse = np.linalg.inv(l_direction) / np.asarray(image_grid.spacing)[:, None]
    l_origin = np.asarray(image_grid.origin, float)
    l_size = np.asarray(image_grid.size, np.int64)
    return np.asarray(g.origin, float), g_matrix, l_origin, l_inverse, l_size


@numba.njit(cache=True, parallel=True)
def _covered_from(
    points, size, g_origin, g_matrix, l_origin, l_inverse, l_size, eps, out
):  # pragma: no cover - compiled
    """Into `out` (flat bool): whether ``p + points[f]`` of each grid voxel p (the grid of
    ITK size `size`, C order) lies in the image's buffer, ITK's IsInsideBuffer by the
    arithmetic of :func:`_continuous_indices` and :func:`_inside_at`. Returns the number of
    points within `eps` voxels of the border (ITK decides those)."""
    d = points.shape[1]
    nx = size[0]
    ny = size[1]
    n_planes = size[d - 1]
    per_plane = nx * ny if d == 3 else nx
    near = 0
    for z in numba.prange(n_planes):
        idx = np.zeros(d)
        q = np.empty(d)
        idx[d - 1] = z
        n_mid = ny if d == 3 else 1
        for y in range(n_mid):
            if d == 3:
                idx[1] = y
            for x in range(nx):
                idx[0] = x
                f = z * per_plane + y * nx + x if d == 3 else z * nx + x
                for i in range(d):
                    p = g_origin[i]
                    for j in range(d):
                        p += g_matrix[i, j] * idx[j]
                    q[i] = (points[f, i] + p) - l_origin[i]
                ok = True
                for i in range(d):
                    c = 0.0
                    for j in range(d):
                        c += l_inverse[i, j] * q[j]
                    if abs(c + 0.5) <= eps or abs(c - (l_size[i] - 0.5)) <= eps:
                        near += 1
                    ok = ok and (c >= -0.5 and c < l_size[i] - 0.5)
                out[f] = ok
    return near


@numba.njit(cache=True)
def _inside_flags(cidx, nz, ny, nx, out):  # pragma: no cover - compiled
    """ITK's IsInsideBuffer of each continuous index (:func:`_inside_at`), into `out`."""
    none = np.empty(0, np.uint8)
    for f in range(cidx.shape[0]):
        out[f] = _inside_at(cidx, f, none, nz, ny, nx)[0]


def _label_table(
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
            _mark_present(labels3, lo, seen)
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


@numba.njit(cache=True)
def _mark_present(labels, vmin, seen):  # pragma: no cover - compiled
    flat = labels.ravel()
    for i in range(flat.size):
        seen[np.int64(flat[i]) - vmin] = True


@numba.njit(cache=True)
def _continuous_indices(
    points, size, z0, g_origin, g_matrix, l_origin, l_inverse, l_size, eps, out
):  # pragma: no cover - compiled
    """``T(p) - p`` (mm, `points` (m, dim)) of the slab's voxels -> their continuous indices
    in the label map, into `out` (m, dim) (which may be `points` itself).

    `size` is the slab's ITK size, `z0` its first plane in the grid (the last ITK axis).
    Returns the number of points within `eps` voxels of the buffer border on some axis.
    """
    d = points.shape[1]
    n_mid = size[1] if d == 3 else 1
    idx = np.zeros(d)
    q = np.empty(d)
    near = 0
    f = 0
    for z in range(size[d - 1]):
        idx[d - 1] = z0 + z
        for y in range(n_mid):
            if d == 3:
                idx[1] = y
            for x in range(size[0]):
                idx[0] = x
                for i in range(d):
                    p = g_origin[i]
                    for j in range(d):
                        p += g_matrix[i, j] * idx[j]
                    q[i] = (points[f, i] + p) - l_origin[i]
                near += _index_into(q, l_inverse, l_size, eps, out, f)
                f += 1
    return near


@numba.njit(cache=True)
def _point_indices(points, l_origin, l_inverse, l_size, eps, out):  # pragma: no cover
    """Physical points (`points` (m, 3), mm; a 2D point's third coordinate 0) -> their
    continuous indices in the label map, ITK's ``(D diag(spacing))^-1 (q - origin)``, into
    `out` (m, dim). Returns the number within `eps` voxels of the buffer border on some
    axis (the test of :func:`_continuous_indices`)."""
    d = out.shape[1]
    q = np.empty(d)
    near = 0
    for f in range(out.shape[0]):
        for i in range(d):
            q[i] = points[f, i] - l_origin[i]
        near += _index_into(q, l_inverse, l_size, eps, out, f)
    return near


@numba.njit(cache=True, inline="always")
def _index_into(q, l_inverse, l_size, eps, out, f):  # pragma: no cover - compiled
    """Row f of `out` = ``l_inverse @ q`` (q: a point less the label map's origin, mm): its
    continuous index. Returns on how many axes it lies within `eps` of the buffer border."""
    near = 0
    for i in range(q.shape[0]):
        c = 0.0
        for j in range(q.shape[0]):
            c += l_inverse[i, j] * q[j]
        out[f, i] = c
        if abs(c + 0.5) <= eps or abs(c - (l_size[i] - 0.5)) <= eps:
            near += 1
    return near


def _slab_memberships(
    cidx: np.ndarray,
    labels: np.ndarray,
    vmin: int,
    lut: np.ndarray,
    inside: np.ndarray,
    n_labels: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One slab's nonzero memberships, label-major.

    Returns
    -------
    starts : ndarray of shape (n_labels + 1,), int64
        Label k's entries are ``[starts[k], starts[k + 1])``.
    index : ndarray of int32
        Slab-local flat voxel numbers, ascending within each label.
    weight : ndarray of float32
    """
    m = cidx.shape[0]
    # Voxel-major entries first (one pass over the points), then a counting sort by label.
    # Most points see one label only, so ~1.1 entries per point is the usual need; the buffer
    # grows when a slab has more boundary than that.
    cap = m + m // 4 + 64
    code = np.empty(cap, np.int32)
    index = np.empty(cap, np.int32)
    weight = np.empty(cap, np.float32)
    f = n = 0
    while True:
        f, n = _point_entries(cidx, labels, vmin, lut, inside, _SNAP, f, n, code, index, weight)
        if f == m:
            break
        cap = max(cap + cap // 2, n + 8 * 1024)
        code, index, weight = (np.resize(a, cap) for a in (code, index, weight))
    return _by_label(code[:n], index[:n], weight[:n], n_labels)


@numba.njit(cache=True)
def _point_entries(
    cidx, labels, vmin, lut, inside, snap, f, n, out_code, out_index, out_weight
):  # pragma: no cover - compiled
    """Nonzero memberships of the slab's points from point `f` on, appended at entry `n`.

    cidx : (m, dim) continuous indices (x, y[, z]) of the points in the label map.
    labels : (nz, ny, nx) label values (a 2D map as one plane); channel = lut[value - vmin].
    inside : (m,) uint8 ITK's inside-buffer decision, or empty to decide here.
    Stops early when fewer than 8 entries of room are left. Returns (next point, entries).
    """
    m = cidx.shape[0]
    nz, ny, nx = labels.shape
    cap = out_code.size
    val = np.empty(8, np.int64)
    wgt = np.empty(8)
    loc_code = np.empty(8, np.int64)
    loc_w = np.empty(8)
    while f < m:
        if n + 8 > cap:
            break
        ok, cx, cy, cz = _inside_at(cidx, f, inside, nz, ny, nx)
        if not ok:
            f += 1
            continue
        bx, tx = _base(cx, nx, snap)
        by, ty = _base(cy, ny, snap)
        bz, tz = _base(cz, nz, snap)
        # The upper neighbour exists whenever its weight t is nonzero (c was clamped to the
        # outer voxel centres); with t == 0 the base voxel is read again at weight 0.
        ux = bx + 1 if tx > 0.0 else bx
        uy = by + 1 if ty > 0.0 else by
        uz = bz + 1 if tz > 0.0 else bz
        val[0] = labels[bz, by, bx]
        val[1] = labels[bz, by, ux]
        val[2] = labels[bz, uy, bx]
        val[3] = labels[bz, uy, ux]
        val[4] = labels[uz, by, bx]
        val[5] = labels[uz, by, ux]
        val[6] = labels[uz, uy, bx]
        val[7] = labels[uz, uy, ux]
        same = True
        for j in range(1, 8):
            if val[j] != val[0]:
                same = False
                break
        if same:
            # One label all around: exactly 1, as ITK's nested interpolation gives.
            k = lut[val[0] - vmin]
            if k >= 0:
                out_code[n] = k
                out_index[n] = f
                out_weight[n] = 1.0
                n += 1
            f += 1
            continue
        wx0, wy0, wz0 = 1.0 - tx, 1.0 - ty, 1.0 - tz
        wgt[0] = wx0 * wy0 * wz0
        wgt[1] = tx * wy0 * wz0
        wgt[2] = wx0 * ty * wz0
        wgt[3] = tx * ty * wz0
        wgt[4] = wx0 * wy0 * tz
        wgt[5] = tx * wy0 * tz
        wgt[6] = wx0 * ty * tz
        wgt[7] = tx * ty * tz
        nloc = 0
        for j in range(8):
            if wgt[j] == 0.0:
                continue
            k = lut[val[j] - vmin]
            if k < 0:  # a value without a channel
                continue
            i = 0
            while i < nloc and loc_code[i] != k:
                i += 1
            if i == nloc:
                loc_code[i] = k
                loc_w[i] = wgt[j]
                nloc += 1
            else:
                loc_w[i] += wgt[j]
        for i in range(nloc):
            w = np.float32(loc_w[i])
            if w > 0:
                out_code[n] = loc_code[i]
                out_index[n] = f
                out_weight[n] = w
                n += 1
        f += 1
    return f, n


@numba.njit(cache=True, parallel=True)
def _linear_values(cidx, image, inside, out):  # pragma: no cover - compiled
    """``out[f]``: `image` (nz, ny, nx) linearly interpolated at continuous index ``cidx[f]``
    (x, y[, z]) as ITK's linear interpolator does (clamped to the outer voxel centres), NaN
    outside the buffer. `inside` as in :func:`_point_entries` (empty: decide here). Each
    point alone, by the same operations: the numbers do not depend on the threads."""
    nz, ny, nx = image.shape
    for f in numba.prange(cidx.shape[0]):
        ok, cx, cy, cz = _inside_at(cidx, f, inside, nz, ny, nx)
        if not ok:
            out[f] = np.nan
            continue
        bx, tx = _base(cx, nx, 0.0)
        by, ty = _base(cy, ny, 0.0)
        bz, tz = _base(cz, nz, 0.0)
        ux = bx + 1 if tx > 0.0 else bx
        uy = by + 1 if ty > 0.0 else by
        uz = bz + 1 if tz > 0.0 else bz
        # ITK's order: along x, then y, then z, each as a + (b - a) t
        a = image[bz, by, bx] + (image[bz, by, ux] - image[bz, by, bx]) * tx
        b = image[bz, uy, bx] + (image[bz, uy, ux] - image[bz, uy, bx]) * tx
        c = image[uz, by, bx] + (image[uz, by, ux] - image[uz, by, bx]) * tx
        e = image[uz, uy, bx] + (image[uz, uy, ux] - image[uz, uy, bx]) * tx
        lo = a + (b - a) * ty
        hi = c + (e - c) * ty
        out[f] = lo + (hi - lo) * tz


@numba.njit(cache=True, inline="always")
def _inside_at(cidx, f, inside, nz, ny, nx):  # pragma: no cover - compiled
    """Whether point `f` (continuous index ``cidx[f]``, x, y[, z]) is inside a buffer of
    shape (nz, ny, nx), and its index (z 0 in 2D): ITK's decision ``inside[f]`` where given
    (non-empty), else ITK's IsInsideBuffer, ``-0.5 <= c < size - 0.5`` on every axis
    (half-open; NaN is outside)."""
    cx = cidx[f, 0]
    cy = cidx[f, 1]
    cz = cidx[f, 2] if cidx.shape[1] == 3 else 0.0
    if inside.size > 0:
        return inside[f] != 0, cx, cy, cz
    ok = (cx >= -0.5 and cx < nx - 0.5) and (cy >= -0.5 and cy < ny - 0.5)
    return ok and (cz >= -0.5 and cz < nz - 0.5), cx, cy, cz


@numba.njit(cache=True, inline="always")
def _base(c, size, snap):  # pragma: no cover - compiled
    """Lower interpolation neighbour and weight of the upper one along an axis of `size`."""
    c = min(max(c, 0.0), size - 1.0)  # ITK's interpolator clamps to the outer voxel centres
    r = np.floor(c + 0.5)
    if abs(c - r) <= snap:
        c = r
    b = np.floor(c)
    return np.int64(b), c - b


@numba.njit(cache=True)
def _by_label(code, index, weight, n_labels):  # pragma: no cover - compiled
    """Stable counting sort of voxel-major entries by label (voxel order kept per label)."""
    starts = np.zeros(n_labels + 1, np.int64)
    for j in range(code.size):
        starts[code[j] + 1] += 1
    for k in range(n_labels):
        starts[k + 1] += starts[k]
    cursor = starts[:-1].copy()
    out_index = np.empty(code.size, np.int32)
    out_weight = np.empty(code.size, np.float32)
    for j in range(code.size):
        k = code[j]
        out_index[cursor[k]] = index[j]
        out_weight[cursor[k]] = weight[j]
        cursor[k] += 1
    return starts, out_index, out_weight


class _BorderDecisions:
    """ITK's own inside-buffer decisions where the kernels' arithmetic could disagree with it:
    for the points within ``_BORDER_EPS`` voxel of an image's buffer border, one by one
    (:func:`_itk_inside_at`), or, beyond ``_POINTWISE_LIMIT`` such points in a slab or for a
    linear transform (which ITK's resampling maps by increments along each row, not point by
    point), by resampling the whole grid once (:func:`_itk_inside`).

    `transform` may be its pieces (:class:`~itk_nrreval.transforms.TransformPieces`): ITK's
    point-by-point calls are then made piece by piece (what a composite's ``TransformPoint``
    does), and the composite, which copies every field, is built only for the whole grid's
    decisions; or a function that returns it or its pieces, called only when ITK must
    decide.
    """

    def __init__(self, transform, grid: Geometry, image_grid: Geometry):
        self._transform, self.grid, self.image_grid = transform, grid, image_grid
        self.whole: np.ndarray | None = None  # the whole grid's decisions, once taken

    def _pointwise(self) -> sitk.Transform | TransformPieces:
        """The transform or its pieces, the function called if it was given one."""
        if callable(self._transform):
            self._transform = self._transform()
        return self._transform

    def _built(self) -> sitk.Transform:
        """The transform itself (pieces: their composite, built once)."""
        if isinstance(self._pointwise(), TransformPieces):
            self._transform = flatten(self._transform)
        return self._transform

    def slab(self, start: int, cidx: np.ndarray, near: int) -> np.ndarray:
        """Inside-buffer flags (bool) of the voxels from flat index `start` whose continuous
        indices in the image are `cidx` (m, dim); `near` of them (per axis) on the border."""
        m = cidx.shape[0]
        if self.whole is None and (near > _POINTWISE_LIMIT or is_linear(self._pointwise())):
            ones = sitk.Image(list(self.image_grid.size), sitk.sitkUInt8)
            self.image_grid.apply_to(ones)
            self.whole = _itk_inside(ones, self._built(), self.grid).astype(bool)
        if self.whole is not None:
            return self.whole[start : start + m]
        flags = np.empty(m, np.bool_)
        _inside_flags(cidx, *_zyx(self.image_grid.shape), flags)
        doubtful = _near_border_points(cidx, np.asarray(self.image_grid.size), _BORDER_EPS, near)
        flags[doubtful] = _itk_inside_at(
            self._pointwise(), self.grid, self.image_grid, start + doubtful
        )
        return flags


@numba.njit(cache=True)
def _near_border_points(cidx, l_size, eps, capacity):  # pragma: no cover - compiled
    """The rows of `cidx` within `eps` voxels of the buffer border on some axis (the test of
    :func:`_continuous_indices`); at most `capacity` of them."""
    out = np.empty(capacity, np.int64)
    n = 0
    for f in range(cidx.shape[0]):
        for i in range(cidx.shape[1]):
            c = cidx[f, i]
            if abs(c + 0.5) <= eps or abs(c - (l_size[i] - 0.5)) <= eps:
                out[n] = f
                n += 1
                break
    return out[:n]


def _itk_inside_at(
    transform: sitk.Transform | TransformPieces,
    grid: Geometry,
    image_grid: Geometry,
    flat: np.ndarray,
) -> np.ndarray:
    """ITK's inside-buffer decision at the voxels `flat` (flat C-order indices of `grid`)
    for an image on `image_grid`, by the calls ``ResampleImageFilter`` makes for each point
    of a transform that is not linear: the voxel's physical point, `transform` at it (given
    as pieces: each piece's, the last first, as a composite's ``TransformPoint`` calls
    them), its continuous index in the image, and the interpolator's half-open test
    ``-0.5 <= c < size - 0.5``. bool (len(flat),)."""
    dim = grid.dimension
    here = grid.apply_to(sitk.Image([1] * dim, sitk.sitkUInt8))  # the same index -> point
    there = image_grid.apply_to(sitk.Image([1] * dim, sitk.sitkUInt8))  # point -> index
    upper = np.asarray(image_grid.size, float) - 0.5
    pieces = transform[::-1] if isinstance(transform, TransformPieces) else (transform,)
    out = np.empty(len(flat), np.bool_)
    for k, index in enumerate(np.stack(np.unravel_index(flat, grid.shape), axis=1)):
        point = here.TransformIndexToPhysicalPoint(index[::-1].tolist())
        for piece in pieces:
            point = piece.TransformPoint(point)
        c = there.TransformPhysicalPointToContinuousIndex(point)
        out[k] = all(-0.5 <= c[i] < upper[i] for i in range(dim))
    return out


def _itk_inside(label_map: sitk.Image, transform: sitk.Transform, g: Geometry) -> np.ndarray:
    """ITK's own inside-buffer decision per grid voxel: flat uint8 (1 inside), C order."""
    ones = sitk.Image(label_map.GetSize(), sitk.sitkUInt8) + 1
    ones.CopyInformation(label_map)
    # Same filter, transform and grid as the dense reference, so the same continuous indices
    # and the same IsInsideBuffer test; the interpolated value of all-ones is exactly 1.
    out = sitk.Resample(
        ones,
        list(g.size),
        transform,
        sitk.sitkLinear,
        list(g.origin),
        list(g.spacing),
        list(g.direction),
        0,
        sitk.sitkUInt8,
    )
    return sitk.GetArrayFromImage(out).ravel()


def _assemble(values: np.ndarray, shape: tuple[int, ...], pieces) -> SparseMemberships:
    """Join the slabs' per-label runs into one label-major CSR (slabs in order: ascending)."""
    n_labels = len(values)
    counts = np.zeros(n_labels, np.int64)
    for _, starts, _, _ in pieces:
        counts += np.diff(starts)
    ptr = np.zeros(n_labels + 1, np.int64)
    np.cumsum(counts, out=ptr[1:])
    index = np.empty(ptr[-1], np.int64)
    weight = np.empty(ptr[-1], np.float32)
    cursor = ptr[:-1].copy()
    while pieces:
        offset, starts, idx, w = pieces.pop(0)  # drop each slab as soon as it is copied
        for k in range(n_labels):
            lo, hi = starts[k], starts[k + 1]
            at = cursor[k]
            index[at : at + hi - lo] = idx[lo:hi]
            index[at : at + hi - lo] += offset
            weight[at : at + hi - lo] = w[lo:hi]
            cursor[k] += hi - lo
    for a in (values, ptr, index, weight):
        a.setflags(write=False)
    return SparseMemberships(values, tuple(int(s) for s in shape), ptr, index, weight)


def _channel_codes(labels3: np.ndarray, vmin: int, lut: np.ndarray) -> np.ndarray:
    """Channel number + 1 of every voxel (0 where its value has no channel), int32."""
    flat = labels3.astype(np.int64, copy=False).ravel()
    codes = lut[flat - vmin].astype(np.int32) + 1
    return codes.reshape(labels3.shape)


def _resample_onto(image: sitk.Image, transform, g: Geometry, interpolator, pixel) -> np.ndarray:
    """`image` resampled through `transform` onto `g` (default 0): flat C-order array."""
    out = sitk.Resample(
        image,
        list(g.size),
        transform,
        interpolator,
        list(g.origin),
        list(g.spacing),
        list(g.direction),
        0,
        pixel,
    )
    return sitk.GetArrayFromImage(out).ravel()


def _csr(values: np.ndarray, shape, per_label) -> SparseMemberships:
    """SparseMemberships from per-label (ascending flat index, float32 weight) pairs."""
    ptr = np.zeros(len(values) + 1, np.int64)
    np.cumsum([len(i) for i, _ in per_label], out=ptr[1:])
    index = np.concatenate([i for i, _ in per_label] or [np.empty(0, np.int64)])
    weight = np.concatenate([w for _, w in per_label] or [np.empty(0, np.float32)])
    index, weight = index.astype(np.int64), weight.astype(np.float32)
    for a in (values, ptr, index, weight):
        a.setflags(write=False)
    return SparseMemberships(values, tuple(int(s) for s in shape), ptr, index, weight)


def _nearest_memberships(codes: sitk.Image, transform, g: Geometry, values) -> SparseMemberships:
    """Crisp memberships: the channel codes resampled with ITK's nearest neighbour."""
    resampled = _resample_onto(codes, transform, g, sitk.sitkNearestNeighbor, sitk.sitkInt32)
    order = np.argsort(resampled, kind="stable")  # ascending voxels within each code
    bounds = np.searchsorted(resampled[order], np.arange(1, len(values) + 2))
    per_label = []
    for k in range(len(values)):
        idx = order[bounds[k] : bounds[k + 1]]
        per_label.append((idx, np.ones(idx.size, np.float32)))
    return _csr(values, g.shape, per_label)


def _gaussian_memberships(
    codes: sitk.Image, transform, g: Geometry, values, sigma_mm: float
) -> SparseMemberships:
    """Each one-hot channel smoothed in the label map's space, then linearly resampled."""
    array = sitk.GetArrayViewFromImage(codes)
    dim = codes.GetDimension()
    # Beyond 4 sigma a Gaussian is below 3.4e-4 of its peak: crop each channel there.
    pad = [int(np.ceil(4.0 * sigma_mm / s)) + 1 for s in codes.GetSpacing()]  # ITK order
    # Every channel's bounding box in one pass (numpy order; None for an absent channel).
    boxes = ndimage.find_objects(array, max_label=len(values))
    per_label = []
    for k, box_np in enumerate(boxes):
        if box_np is None:
            per_label.append((np.empty(0, np.int64), np.empty(0, np.float32)))
            continue
        bounds = box_np[::-1]  # ITK order
        lo = [max(0, b.start - p) for b, p in zip(bounds, pad, strict=True)]
        hi = [min(n, b.stop + p) for b, p, n in zip(bounds, pad, codes.GetSize(), strict=True)]
        box = sitk.RegionOfInterest(codes, [b - a for a, b in zip(lo, hi, strict=True)], lo)
        channel = sitk.Cast(box == k + 1, sitk.sitkFloat32)
        smooth = sitk.SmoothingRecursiveGaussian(channel, [sigma_mm] * dim)
        w = _resample_onto(smooth, transform, g, sitk.sitkLinear, sitk.sitkFloat32)
        idx = np.flatnonzero(w > _GAUSSIAN_FLOOR)
        per_label.append((idx, np.minimum(w[idx], 1.0).astype(np.float32)))
    return _csr(values, g.shape, per_label)


# -- membership files ----------------------------------------------------------------------


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
