"""Label maps resampled as sparse fuzzy memberships: exactly ITK's linear one-hot resampling.

The dense way of resampling a label map onto a grid as fuzzy memberships builds a one-hot
vector image (one float channel per label) and passes it through ``sitk.Resample`` with
``sitk.sitkLinear``: cost and memory grow with the number of labels L, although each grid
point only ever receives weight from the at most ``2**dim`` label-map voxels around it.

:func:`resample_label_memberships` computes the same numbers label-free: the grid's points
are mapped once, the ``2**dim`` interpolation weights of each point are computed once, and
each weight is added to the membership of the label of its corner. Only nonzero memberships
are stored (:class:`SparseMemberships`, per label a sorted list of voxels and weights).

Beside this module: the compiled kernels (:mod:`itk_nrreval.io._membership_kernels`), the label
values as channels (:mod:`itk_nrreval.io._label_channels`) and the membership images on disk
(:mod:`itk_nrreval.io._membership_files`).

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

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import SimpleITK as sitk
from scipy import ndimage

from .._errors import InputError
from ._images import Geometry
from ._label_channels import LABEL_INTERPOLATIONS, channel_codes, checked_labels, label_table
from ._membership_files import write_membership_image
from ._membership_kernels import (
    by_label,
    continuous_indices,
    covered_from,
    inside_flags,
    near_border_points,
    point_entries,
    point_indices,
)

# bound under this name: benchmarks/bench_image_task.py times the image's resampling here
from ._membership_kernels import linear_values as _linear_values
from .transforms import PointMap, TransformPieces, flatten, is_linear

# LABEL_INTERPOLATIONS (_label_channels) and write_membership_image (_membership_files) are
# where the rest of the package has imported them from
__all__ = [
    "LABEL_INTERPOLATIONS",
    "SparseMemberships",
    "covered_voxels",
    "resample_label_memberships",
    "write_membership_image",
]

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
    labels = checked_labels(label_map, transform, g, method, sigma_mm)
    dim = g.dimension
    labels3 = labels.reshape((1,) * (3 - dim) + labels.shape)  # 2D as one plane of 3D
    labels3, vmin, lut, values = label_table(labels3, values)
    if method != "linear":
        # Channel numbers + 1 as an image (0: no channel), so that ITK resamples channels.
        codes = channel_codes(labels3, vmin, lut).reshape(labels.shape)
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
    with `displacement` a :class:`~itk_nrreval.io.transforms.PointMap`, an image alone costs
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
        its pieces (:class:`~itk_nrreval.io.transforms.TransformPieces`), which ITK then maps
        point by point without a composite.
    displacement : ndarray of shape ``(*grid.shape, dim)`` or PointMap, optional
        ``transform(p) - p`` already sampled on `grid` (mm, ITK order last; what
        ``sitk.GetArrayViewFromImage`` of ``sitk.TransformToDisplacementField`` gives) when
        the caller has it, or the transform as a
        :class:`~itk_nrreval.io.transforms.PointMap` for the compiled kernels to sample slab
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
        labels = checked_labels(label_map, transform if built else None, g, "linear", None)
        labels3, vmin, lut, values = label_table(labels.reshape(lead + labels.shape), values)
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
    :func:`label_table`; None: no label map), slab by slab; with `image` (on that grid,
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
        caller has it, or the transform as a :class:`~itk_nrreval.io.transforms.PointMap`
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
        if not covered_from(points, size, *maps, _BORDER_EPS, covered):
            return covered
    # some points lie on the border (or no whole sampling was given): slab by slab, ITK
    # decides the points on the border
    for z0, cidx, near in _slab_indices(transform, grid, image_grid, displacement):
        start = z0 * plane
        if near or border.whole is not None:
            covered[start : start + cidx.shape[0]] = border.slab(start, cidx, near)
        elif not whole:
            inside_flags(cidx, *_zyx(image_grid.shape), covered[start : start + cidx.shape[0]])
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
    :class:`~itk_nrreval.io.transforms.PointMap` the compiled kernels evaluate slab by slab;
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
            near_border = point_indices(points, l_origin, l_inverse, l_size, _BORDER_EPS, cidx)
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
        near_border = continuous_indices(
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
        f, n = point_entries(cidx, labels, vmin, lut, inside, _SNAP, f, n, code, index, weight)
        if f == m:
            break
        cap = max(cap + cap // 2, n + 8 * 1024)
        code, index, weight = (np.resize(a, cap) for a in (code, index, weight))
    return by_label(code[:n], index[:n], weight[:n], n_labels)


class _BorderDecisions:
    """ITK's own inside-buffer decisions where the kernels' arithmetic could disagree with it:
    for the points within ``_BORDER_EPS`` voxel of an image's buffer border, one by one
    (:func:`_itk_inside_at`), or, beyond ``_POINTWISE_LIMIT`` such points in a slab or for a
    linear transform (which ITK's resampling maps by increments along each row, not point by
    point), by resampling the whole grid once (:func:`_itk_inside`).

    `transform` may be its pieces (:class:`~itk_nrreval.io.transforms.TransformPieces`): ITK's
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
        inside_flags(cidx, *_zyx(self.image_grid.shape), flags)
        doubtful = near_border_points(cidx, np.asarray(self.image_grid.size), _BORDER_EPS, near)
        flags[doubtful] = _itk_inside_at(
            self._pointwise(), self.grid, self.image_grid, start + doubtful
        )
        return flags


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
