"""The per-label sums behind an overlap table, from N label images: the input read as crisp
label maps or fuzzy memberships (labels named by membership files where they say), the labels
chosen, and the compiled kernels' sums (:mod:`itk_nrreval.measures._overlap_kernels`).

:func:`table_sums` is what :func:`itk_nrreval.measures.overlap.overlap_table` builds its
:class:`~itk_nrreval.measures.overlap.OverlapTable` from.

How the pair sums are taken
---------------------------
The pair sums avoid the O(N^2 n) loop over pairs. For crisp maps, if c of the N images carry
label l at a voxel, the voxel adds C(c, 2) to p_l and C(N, 2) - C(N - c, 2) to q_l: O(N n) in
all, in exact integer arithmetic, every label in one pass over the maps
(:func:`._overlap_kernels.label_map_sums`). For fuzzy memberships sorted ascending at a voxel,
a_(1) <= ... <= a_(N), it adds ``sum_k a_(k) (N - k)`` to p_l and ``sum_k a_(k) (k - 1)`` to
q_l. The sort is Batcher's odd-even merge network, O(N log^2 N) branch-free comparators run
across blocks of voxels at once (268 for N = 36, against 630 pairs); voxels where every
membership of a label is zero are skipped. Everything streams over the voxels, one label at a
time for fuzzy input (:func:`._overlap_kernels.membership_pair_sums`).

Complexity: ``|grad A_il|`` by central differences (one-sided at the grid's faces, as
:func:`numpy.gradient` with ``edge_order=1``; axes of length 1 contribute nothing), in
physical units, of the label's indicator (crisp) or membership (fuzzy).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from .._errors import InputError, readable
from .._progress import progress_bar
from ..io._images import check_components, image_stack, mask_array
from ..io._membership_files import membership_file_labels
from ._overlap_kernels import (
    label_map_gradient_sums,
    label_map_sums,
    membership_gradient_sums,
    membership_pair_sums,
    membership_stats,
)

__all__ = ["TableSums", "table_sums"]

_PROGRESS_MIN_WORK = 50_000_000  # image-label-voxels above which fuzzy input shows progress


@dataclass(frozen=True)
class TableSums:
    """The arguments of :meth:`~itk_nrreval.measures.overlap.OverlapTable.from_sums`, as
    :func:`table_sums` finds them (their meaning and shapes are documented there)."""

    labels: np.ndarray
    volume: np.ndarray
    target_sums: np.ndarray | None
    gradient_sums: np.ndarray | None
    pair_min: np.ndarray
    pair_max: np.ndarray
    spacing: tuple[float, ...]
    fuzzy: bool
    skipped_labels: tuple[int, ...]


def table_sums(
    labels,
    *,
    label_values,
    include_background: bool,
    mask,
    spacing,
    complexity: bool,
    target_overlap: bool,
    progress: bool,
) -> TableSums:
    """The per-label sums of N label images, in one pass: the work of
    :func:`itk_nrreval.measures.overlap.overlap_table`, whose parameters and exceptions these
    are."""
    check_components(labels)
    stack = image_stack(labels, what="label map", dtype=None, allow_vector=True)
    data, names = stack.data, stack.names
    n_images = data.shape[0]
    if n_images < 2:
        raise InputError(f"label maps: need at least 2 to form a pair, got {n_images}")
    component_labels = _component_labels(labels, names)
    fuzzy = component_labels is not None or _is_fuzzy(stack)
    if component_labels is not None and data.ndim == stack.geometry.dimension + 1:
        # one label: NIfTI has no one-component vector image, the file is scalar
        data = data[:, np.newaxis]
    spatial = data.shape[2:] if fuzzy else data.shape[1:]
    if len(spatial) == 0:
        raise InputError(f"label maps: no spatial axis in an array of shape {data.shape}")
    spacing_itk = _spacing(spacing, stack.geometry, len(spatial))
    mask_flat = mask_array(mask, shape=spatial, geometry=stack.geometry)
    mask_flat = None if mask_flat is None else mask_flat.reshape(-1)
    if fuzzy:
        sums = functools.partial(_fuzzy_sums, component_labels=component_labels)
    else:
        sums = _crisp_sums
    values, skipped, vol, s_pairs, gsum, p, q = sums(
        data,
        names,
        label_values,
        include_background,
        mask_flat,
        spatial,
        spacing_itk,
        complexity=complexity,
        target_overlap=target_overlap,
        progress=progress,
    )
    return TableSums(
        values,
        vol,
        s_pairs,
        gsum,
        p,
        q,
        spacing=spacing_itk,
        fuzzy=fuzzy,
        skipped_labels=skipped,
    )


# -- input parsing -------------------------------------------------------------------------


def _is_fuzzy(stack) -> bool:
    """Bare arrays: floating dtype means memberships. Images: a component axis does."""
    data = stack.data
    if stack.geometry is not None:
        return data.ndim == stack.geometry.dimension + 2
    if np.issubdtype(data.dtype, np.floating):
        return True
    if np.issubdtype(data.dtype, np.integer) or data.dtype == np.bool_:
        return False
    raise InputError(f"label maps: unsupported array dtype {data.dtype}")


def _component_labels(labels, names) -> tuple[int, ...] | None:
    """The labels every file names for its components (one list for all), or None when no
    file names them; a mixture, or different lists, is an error naming the odd file."""
    if isinstance(labels, np.ndarray):
        return None
    named = [membership_file_labels(item, name=n) for item, n in zip(labels, names, strict=True)]
    first = named[0]
    for n, own in zip(names[1:], named[1:], strict=True):
        if own == first:
            continue
        if own is None or first is None:
            says, silent = (names[0], n) if own is None else (n, names[0])
            raise InputError(
                f"{silent}: does not say which labels its components are, but {says} does; "
                "pass membership files written the same way"
            )
        raise InputError(
            f"{n}: its components are labels {list(own)}, but those of {names[0]} are "
            f"labels {list(first)}"
        )
    return first


def _spacing(spacing, geometry, ndim: int) -> tuple[float, ...]:
    if geometry is not None:
        if spacing is not None:
            raise ValueError(
                "spacing is taken from the images' geometry; pass spacing only with bare arrays"
            )
        return tuple(float(s) for s in geometry.spacing)
    if spacing is None:
        return (1.0,) * ndim
    sp = np.atleast_1d(np.asarray(spacing, dtype=np.float64))
    if sp.shape != (ndim,) or not np.all(np.isfinite(sp)) or not np.all(sp > 0):
        raise ValueError(
            f"spacing must be {ndim} positive numbers in ITK order (x, y[, z]), "
            f"got {readable(spacing)}"
        )
    return tuple(float(s) for s in sp)


def _explicit_values(label_values) -> np.ndarray:
    vals = np.asarray(label_values)
    if vals.ndim != 1 or vals.size == 0:
        raise ValueError(
            f"label_values must be a non-empty sequence of integers, got {readable(label_values)}"
        )
    if not np.issubdtype(vals.dtype, np.integer):
        if not (np.issubdtype(vals.dtype, np.floating) and np.all(vals == np.round(vals))):
            raise ValueError(f"label_values must be integers, got {readable(label_values)}")
    vals = vals.astype(np.int64)
    if np.unique(vals).size != vals.size:
        raise ValueError(f"label_values must not repeat a value, got {readable(label_values)}")
    return np.sort(vals)


def _no_labels(names, include_background: bool) -> InputError:
    which = f"{names[0]} .. {names[-1]}"
    extra = "" if include_background else " other than background 0"
    return InputError(f"{which}: no label{extra} in any of the {len(names)} label maps")


# -- crisp label maps ----------------------------------------------------------------------


def _crisp_sums(
    data,
    names,
    label_values,
    include_background,
    mask_flat,
    spatial,
    spacing_itk,
    *,
    complexity: bool,
    target_overlap: bool,
    progress: bool = False,
):
    """Label values, skipped values, and the sums of
    :meth:`~itk_nrreval.measures.overlap.OverlapTable.from_sums`."""
    n_images = data.shape[0]
    flat = data.reshape(n_images, -1)
    if np.issubdtype(data.dtype, np.floating):  # a crisp map from a floating-point file
        for i in range(n_images):
            row = flat[i]
            bad = row != np.round(row)
            if bad.any():
                raise InputError(
                    f"{names[i]}: non-integer values in a crisp label map "
                    f"(e.g. {readable(row[np.argmax(bad)])}); pass memberships as one "
                    "multi-component image per subject"
                )
        flat = flat.astype(np.int64)

    if label_values is None:
        exclude = () if include_background else (0,)
        values, pm, vol, s_pairs = label_map_sums(
            flat, exclude=exclude, mask=mask_flat, target_overlap=target_overlap
        )
        skipped: tuple[int, ...] = ()
        if values.size == 0:
            raise _no_labels(names, include_background)
    else:
        wanted = _explicit_values(label_values)
        _, pm, vol, s_pairs = label_map_sums(
            flat, values=wanted, mask=mask_flat, target_overlap=target_overlap
        )
        keep = vol.sum(axis=0) > 0  # present inside the mask in some image
        values = wanted[keep]
        skipped = tuple(int(v) for v in wanted[~keep])
        if values.size == 0:
            raise InputError(
                f"{names[0]} .. {names[-1]}: none of the labels {wanted.tolist()} is present"
            )
        pm, vol = pm[keep], vol[:, keep]
        s_pairs = None if s_pairs is None else s_pairs[:, keep]

    gsum = None
    if complexity:
        gsum = label_map_gradient_sums(
            flat, values, shape=spatial, spacing=spacing_itk, mask=mask_flat
        )
    q = (n_images - 1) * vol.sum(axis=0) - pm  # pair sums of a_i + a_j are min + max
    return (
        values,
        skipped,
        vol.astype(np.float64),
        None if s_pairs is None else s_pairs.astype(np.float64),
        gsum,
        pm.astype(np.float64),
        q.astype(np.float64),
    )


# -- fuzzy memberships ---------------------------------------------------------------------


def _named_candidates(component_labels, comp_present, label_values, include_background, names):
    """Components to evaluate, their label values (ascending) and the skipped label values,
    for files that name the label of each component."""
    named = np.asarray(component_labels, dtype=np.int64)
    if label_values is None:
        if include_background and 0 not in component_labels:
            raise InputError(
                f"{names[0]}: no background component (its components are labels "
                f"{list(component_labels)}): background cannot be included"
            )
        wanted = np.sort(named if include_background else named[named != 0])
    else:
        wanted = _explicit_values(label_values)
    where = {int(v): k for k, v in enumerate(named)}
    components = np.array([where.get(int(v), -1) for v in wanted], dtype=np.int64)
    keep = components >= 0  # a label no file has a component for is absent from every image
    keep[keep] = comp_present[components[keep]]
    skipped = tuple(int(v) for v in wanted[~keep])
    return components[keep], wanted[keep], skipped


def _fuzzy_sums(
    data,
    names,
    label_values,
    include_background,
    mask_flat,
    spatial,
    spacing_itk,
    *,
    component_labels: tuple[int, ...] | None,
    complexity: bool,
    target_overlap: bool,
    progress: bool = False,
):
    """Label values, skipped values, and the sums of
    :meth:`~itk_nrreval.measures.overlap.OverlapTable.from_sums`.

    Without `component_labels`, component k is label k (0: background); with them, it is
    label ``component_labels[k]``.
    """
    n_images, n_comp = data.shape[:2]
    flat = data.reshape(n_images, n_comp, -1)
    if flat.dtype not in (np.float32, np.float64):
        flat = flat.astype(np.float64)
    lows, highs, present = membership_stats(flat, mask=mask_flat)
    for i in range(n_images):
        lo, hi = float(lows[i]), float(highs[i])
        if lo < 0.0 or hi > 1.0:
            raise InputError(
                f"{names[i]}: membership values outside [0, 1] (min {lo:.6g}, max {hi:.6g}); "
                "crisp label maps must have an integer type"
            )
    comp_present = present.any(axis=0)
    if component_labels is not None:
        components, values, skipped = _named_candidates(
            component_labels, comp_present, label_values, include_background, names
        )
    else:
        if label_values is None:
            candidates = np.arange(0 if include_background else 1, n_comp, dtype=np.int64)
        else:
            candidates = _explicit_values(label_values)
            if candidates[0] < 0 or candidates[-1] >= n_comp:
                raise ValueError(
                    f"label_values of fuzzy input must be component indices 0..{n_comp - 1}, "
                    f"got {readable(label_values)}"
                )
        keep = comp_present[candidates]
        components = values = candidates[keep]
        skipped = tuple(int(v) for v in candidates[~keep])
    if values.size == 0:
        raise _no_labels(names, include_background or label_values is not None)

    n_labels = values.size
    vol = np.zeros((n_images, n_labels))
    s_pairs = np.zeros((n_images, n_labels))
    gsum = np.zeros((n_images, n_labels))
    p = np.zeros(n_labels)
    q = np.zeros(n_labels)
    work = n_images * n_labels * flat.shape[2]
    for k in progress_bar(
        range(n_labels),
        desc="overlap",
        total=n_labels,
        enabled=progress and work > _PROGRESS_MIN_WORK,
    ):
        rows = flat[:, int(components[k])]  # (N, n_voxels), rows adjacent in memory
        if complexity:
            gsum[:, k] = membership_gradient_sums(
                rows, shape=spatial, spacing=spacing_itk, mask=mask_flat
            )
        p[k], q[k], vol[:, k], s_pairs[:, k] = membership_pair_sums(rows, mask=mask_flat)
    return (
        values,
        skipped,
        vol,
        s_pairs if target_overlap else None,
        gsum if complexity else None,
        p,
        q,
    )
