"""The registered set the perturbation experiment perturbs
(:mod:`itk_nrreval.experiments.perturbation`).

Read from arrays, images or files and checked (:func:`read_inputs`: the images, their label
maps or memberships, mask and spacing), or resampled from a manifest into its common frame
(:func:`manifest_set`); in either case optionally cut to one 2D slice of the common grid,
the paper's "2D slices at an equivalent level across the set" (:func:`parse_section`,
:func:`take_section`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .._errors import InputError
from ..io._images import image_stack, mask_array
from .warps import MEMBERSHIP_TOLERANCE

__all__ = [
    "AXES",
    "parse_section",
    "section_index",
    "without_axis",
    "take_section",
    "section_record",
    "manifest_set",
    "manifest_arrays",
    "Inputs",
    "read_inputs",
    "drop_absent",
]

#: The common grid's ITK axes by name (``z`` is the first numpy axis).
AXES = ("x", "y", "z")


def parse_section(section) -> tuple[str, int | None] | None:
    """``"z"``, ``"z:47"``, ``("z", 47)`` or None -> ``(axis, index or None)`` or None.

    The axis names the common grid's ITK axis (``x``, ``y`` or ``z``; ``z`` is the first
    numpy axis); no index means the middle slice.

    Raises
    ------
    InputError
        Anything else (the message quotes it).
    """
    if section is None:
        return None
    if isinstance(section, str):
        axis, _, index = section.strip().partition(":")
    else:
        try:
            axis, index = section
        except (TypeError, ValueError):
            raise InputError(
                f"slice: expected AXIS[:INDEX] such as z or z:40, got {section!r}"
            ) from None
    axis = str(axis).strip().lower()
    if axis not in AXES:
        raise InputError(f"slice: axis must be x, y or z, got {section!r}")
    if index is None or (isinstance(index, str) and not index.strip()):
        return axis, None
    try:
        value = int(str(index).strip())
    except ValueError:
        raise InputError(f"slice: index must be an integer >= 0, got {section!r}") from None
    if value < 0:
        raise InputError(f"slice: index must be an integer >= 0, got {section!r}")
    return axis, value


def section_index(section, size_itk: Sequence[int]) -> tuple[int, int]:
    """(ITK axis, index) of a parsed section on a grid of ITK size `size_itk` (3D)."""
    axis, index = section
    a = AXES.index(axis)
    n = int(size_itk[a])
    index = n // 2 if index is None else index
    if index >= n:
        raise InputError(
            f"slice {axis}:{index}: out of range, the grid has {n} slices along {axis}"
        )
    return a, index


def without_axis(spacing: Sequence[float], axis: int) -> tuple[float, ...]:
    """The spacing (mm, ITK order) of a slice across ITK axis `axis`."""
    return tuple(float(s) for k, s in enumerate(spacing) if k != axis)


def take_section(images, labels, spacing, section, *, mask=None):
    """The 2D slice of 3D arrays at one level of their common grid.

    Parameters
    ----------
    images : ndarray of shape (n_images, nz, ny, nx)
    labels : ndarray of shape (n_images, nz, ny, nx) or (n_images, n_labels, nz, ny, nx)
    spacing : sequence of 3 float or None
        mm, ITK order.
    section : str or (str, int)
        ``AXIS[:INDEX]`` (:func:`parse_section`); default index the middle slice.
    mask : ndarray of shape (nz, ny, nx), optional

    Returns
    -------
    images, labels, spacing, mask, (axis, index)
        The slices (2D spatial axes, numpy order), the 2D spacing (ITK order of the two
        remaining axes), and the slice taken.
    """
    section = parse_section(section)
    images = np.asarray(images)
    if images.ndim != 4:
        raise InputError(f"slice: needs 3D images, got spatial shape {images.shape[1:]}")
    size_itk = images.shape[1:][::-1]
    a, index = section_index(section, size_itk)
    np_axis = 2 - a  # spatial numpy axis
    images = np.take(images, index, axis=1 + np_axis)
    labels = np.asarray(labels)
    lab_axis = labels.ndim - 3 + np_axis
    labels = np.take(labels, index, axis=lab_axis)
    if mask is not None:
        mask = np.take(np.asarray(mask), index, axis=np_axis)
    if spacing is not None:
        spacing = without_axis(spacing, a)
    return images, labels, spacing, mask, (AXES[a], index)


def section_record(section: tuple[str, int] | None) -> dict | None:
    """A section taken as ``ValidationResult.parameters["section"]`` records it."""
    return None if section is None else {"axis": section[0], "index": int(section[1])}


def manifest_set(manifest, *, section=None, progress: bool = True):
    """The images and label memberships of a manifest, resampled into its common frame.

    Uses the common-frame registration's transforms (the registered set the paper perturbs).

    Parameters
    ----------
    manifest : path, mapping or Manifest
    section : str or (str, int), optional
        ``AXIS[:INDEX]`` (:func:`parse_section`): resample only that slice of the common
        grid (default index: the middle slice), the paper's "2D slices at an equivalent
        level across the set". The grid must be 3D.
    progress : bool

    Returns
    -------
    images : ndarray of shape (n_images, *spatial), float64
    memberships : ndarray of shape (n_images, n_labels, *spatial), float32
        Component 0 is the background (label value 0); components 1.. are the nonzero label
        values present in the (sliced) maps, ascending.
    geometry : Geometry
        The grid resampled onto (a one-voxel-thick 3D grid for a section).

    Raises
    ------
    InputError
        A bad manifest, one without labels, or a section of a 2D grid / out of range.
    """
    images, members, grid, _, _ = manifest_arrays(manifest, section, progress)
    return images, members, grid


def manifest_arrays(manifest, section, progress: bool):
    """:func:`manifest_set`, the section taken (``(axis, index)`` or None), and the coverage.

    The coverage is ``(region, fraction of the mask it keeps, name, masked)``; the region
    (bool, the images' spatial shape) is where the texture model is taken, as in
    :func:`itk_nrreval.evaluate`: inside the manifest's mask, where every image covers the
    common grid (voxels outside an image's field of view hold no value, and 0 there would
    read as texture).
    """
    from ..io._images import Geometry
    from ..io.frame import (
        common_reference,
        label_values,
        read_chains,
        resample_images,
        resample_memberships,
    )
    from ..io.manifest import load_manifest

    m = load_manifest(manifest)
    name = str(m.source) if m.source is not None else "manifest"
    if m.labels is None:
        raise InputError(f"{name}: validation needs label maps ('labels:' in the manifest)")
    grid = full_grid = Geometry.from_image(common_reference(m))
    mask = mask_array(m.mask, shape=full_grid.shape, geometry=full_grid)
    taken = None
    if section is not None:
        if grid.dimension != 3:
            raise InputError(f"{name}: a slice needs a 3D common frame, got a 2D one")
        a, index = section_index(parse_section(section), grid.size)
        taken = (AXES[a], index)
        if mask is not None:  # the slice of it, one voxel thick as the sliced grid
            mask = np.take(mask, [index], axis=2 - a)
        direction = np.array(grid.direction).reshape(3, 3)
        offset = np.zeros(3)
        offset[a] = index * grid.spacing[a]
        size = list(grid.size)
        size[a] = 1
        grid = Geometry(
            tuple(size),
            grid.spacing,
            tuple(float(v) for v in np.array(grid.origin) + direction @ offset),
            grid.direction,
        )
    chains = read_chains(m, m.common_frame)
    images = resample_images(
        m.scored_images,
        chains,
        grid,
        desc="resampling images",
        progress=progress,
        outside=np.nan,
    )
    covered = ~np.isnan(images).any(axis=0)
    images[np.isnan(images)] = 0.0  # outside the region only: the inputs are checked finite
    found = [int(v) for v in label_values(m.labels) if v != 0]
    values = np.array([0, *found], dtype=np.int64)
    members = resample_memberships(m.labels, chains, grid, values=values, progress=progress)
    members = drop_absent(members)
    if mask is None:
        mask = np.ones(covered.shape, dtype=bool)
    region = covered & mask
    if taken is not None:  # drop the one-voxel axis: 2D arrays
        np_axis = 2 - AXES.index(taken[0])
        images = np.take(images, 0, axis=1 + np_axis)
        members = np.take(members, 0, axis=2 + np_axis)
        region = np.take(region, 0, axis=np_axis)
    where = f"{name}" + (f", slice {taken[0]}:{taken[1]}" if taken is not None else "")
    if not region.any():
        raise InputError(
            f"{where}: no voxel of the common grid is inside the mask and covered by every image"
        )
    coverage = (region, float(region.sum() / mask.sum()), where, m.mask is not None)
    return images, members, grid, taken, coverage


@dataclass(frozen=True)
class Inputs:
    """The registered set to perturb, checked (and sliced when a section was asked for).

    Attributes
    ----------
    images : ndarray of shape (n_images, *spatial)
    labels : ndarray
        Channel codes, int32 of shape (n_images, *spatial) (:func:`_compact`), or
        memberships, float of shape (n_images, n_labels, *spatial) (:func:`drop_absent`).
    n_labels : int
        Channels of the memberships, the background 0 included.
    spacing : tuple of float or None
        mm, ITK order; None for bare arrays given without one.
    mask : ndarray of bool of shape spatial, or None
    section : (str, int) or None
        The slice taken (axis, index).
    """

    images: np.ndarray
    labels: np.ndarray
    n_labels: int
    spacing: tuple[float, ...] | None
    mask: np.ndarray | None
    section: tuple[str, int] | None

    @property
    def n_images(self) -> int:
        return self.images.shape[0]

    @property
    def spatial(self) -> tuple[int, ...]:
        return tuple(self.images.shape[1:])

    @property
    def fuzzy(self) -> bool:
        """Whether the labels are memberships (warped as given) rather than channel codes."""
        return np.issubdtype(self.labels.dtype, np.floating)


def read_inputs(images, labels, *, mask, spacing, section) -> Inputs:
    """:func:`validate`'s images, labels, mask and spacing read and checked, the section taken.

    Raises
    ------
    InputError
        Fewer than 3 images, not 2D or 3D, a bad spacing, labels or mask, a mask empty on
        the section, or fewer than 3 voxels along an axis.
    """
    stack = image_stack(images, what="image")
    data = stack.data
    n, spatial = data.shape[0], data.shape[1:]
    if n < 3:
        raise InputError(f"validation needs at least 3 images, got {n}")
    if len(spatial) not in (2, 3):
        raise InputError(f"images must be 2D or 3D, got spatial shape {spatial}")
    if stack.geometry is not None:
        if spacing is not None:
            raise ValueError("spacing: the images bring their own; give it for bare arrays only")
        spacing = stack.geometry.spacing
    elif spacing is not None:
        spacing = tuple(float(s) for s in spacing)
        if len(spacing) != len(spatial) or not all(math.isfinite(s) and s > 0 for s in spacing):
            raise InputError(f"spacing: expected {len(spatial)} positive mm, got {spacing!r}")
    lab = _checked_labels(labels, n, spatial)
    mask_arr = mask_array(mask, shape=spatial, geometry=stack.geometry)
    taken = None
    if section is not None:
        data, lab, spacing, mask_arr, taken = take_section(
            data, lab, spacing, section, mask=mask_arr
        )
        spatial = data.shape[1:]
        if mask_arr is not None and not mask_arr.any():
            raise InputError(f"mask: empty on slice {taken[0]}:{taken[1]}")
    if min(spatial) < 3:
        raise InputError(f"images must have at least 3 voxels per axis, got {spatial}")
    if np.issubdtype(lab.dtype, np.floating):
        lab = drop_absent(lab)
        n_labels = lab.shape[1]
    else:
        lab, n_labels = _compact(lab)
    return Inputs(data, lab, n_labels, spacing, mask_arr, taken)


def _checked_labels(labels, n: int, spatial: tuple[int, ...]) -> np.ndarray:
    """Integer label maps (n, *spatial) as int64, or memberships (n, L, *spatial) clipped
    to [0, 1] (float32 kept as float32)."""
    if isinstance(labels, np.ndarray) and np.issubdtype(labels.dtype, np.floating):
        if labels.ndim == len(spatial) + 2:
            if labels.shape[0] != n or labels.shape[2:] != spatial:
                raise InputError(
                    f"memberships shape {labels.shape} does not match {n} images of {spatial}"
                )
            if not np.all(np.isfinite(labels)):
                raise InputError("memberships hold NaN or infinite values")
            lo, hi = float(labels.min()), float(labels.max())
            if lo < -MEMBERSHIP_TOLERANCE or hi > 1.0 + MEMBERSHIP_TOLERANCE:
                raise InputError(
                    f"memberships must lie in [0, 1] (up to {MEMBERSHIP_TOLERANCE:g} of "
                    f"rounding), got values from {lo:.9g} to {hi:.9g}"
                )
            out = labels if labels.dtype in (np.float32, np.float64) else labels.astype(float)
            return np.clip(out, 0.0, 1.0) if lo < 0.0 or hi > 1.0 else out
    arr = image_stack(labels, what="label map", dtype=None).data
    if arr.shape != (n, *spatial):
        raise InputError(f"label maps shape {arr.shape} does not match the images' {(n, *spatial)}")
    if arr.dtype.kind not in "iub":
        if not np.all(np.isfinite(arr)) or not np.all(arr == np.round(arr)):
            raise InputError("label maps must hold non-negative integer values")
    if arr.size and arr.min() < 0:
        raise InputError("label maps must hold non-negative integer values")
    return arr.astype(np.int64)


def _compact(lab: np.ndarray) -> tuple[np.ndarray, int]:
    """Integer label maps -> channel codes: 0 for the background value 0 (present or not),
    then one code per nonzero value present in any map, ascending. Codes as int32."""
    values = np.unique(lab)
    values = np.concatenate([[0], values[values != 0]])
    codes = np.searchsorted(values, lab).astype(np.int32)  # values sorted: 0 first
    return codes, len(values)


def drop_absent(members: np.ndarray) -> np.ndarray:
    """Memberships without the components (other than 0) that are zero in every image."""
    n, n_comp = members.shape[:2]
    keep = np.ones(n_comp, dtype=bool)
    keep[1:] = members[:, 1:].reshape(n, n_comp - 1, -1).any(axis=(0, 2))
    return members if keep.all() else members[:, keep]
