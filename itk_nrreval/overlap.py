"""Generalized Tanimoto overlap of a group of (fuzzy) label images (paper, Sections II-B, V-C).

The ground-truth reference measure: for N label images with memberships ``A[i, l, v]`` in
[0, 1] (image i, label l, voxel v),

        sum_{i<j} sum_l alpha_l sum_v min(A_il, A_jl)
    O = ---------------------------------------------
        sum_{i<j} sum_l alpha_l sum_v max(A_il, A_jl)

with the sums over all unordered pairs taken separately in numerator and denominator (never an
average of per-pair ratios). Crum, Camara & Hill, "Generalized overlap measures for evaluation
and validation in medical image analysis", IEEE TMI 25(11), 2006, eq. (4) without pair weights;
doi:10.1109/TMI.2006.880587.

Everything is read from one per-label table (:class:`OverlapTable`) built in one sweep over the
voxels: the pair sums of minima and maxima, the volumes and the boundary complexity. Every
weighting, and the per-label Jaccard, Dice and target overlap, come from that table.
"""

from __future__ import annotations

import functools
import math
import os
import warnings
from dataclasses import dataclass, field

import numba
import numba.extending
import numpy as np
import SimpleITK as sitk
from llvmlite import ir as llvm_ir

from ._errors import InputError
from ._images import image_stack, mask_array
from ._progress import progress

__all__ = ["WEIGHTINGS", "OverlapTable", "overlap_table", "generalized_overlap"]

#: The label weightings, in the order reports list them.
WEIGHTINGS = (
    "volume",
    "inverse_volume",
    "inverse_volume_squared",
    "complexity",
    "inverse_volume_complexity",
)

_BLOCK = 256  # voxels per block of fuzzy memberships: (N, _BLOCK) float64 scratch fits L2
_INDEX_BITS = 29  # float32 -> float64 leaves 29 zero mantissa bits to carry an image index
_NETWORK_FRACTION = 0.5  # above this share of values strictly in (0, 1), sort by network
_MAX_LUT = 1 << 22  # largest label-value range mapped through a lookup table
_PROGRESS_MIN_WORK = 50_000_000  # image-label-voxels above which fuzzy input shows progress


def _check_weighting(weighting: str) -> None:
    if weighting not in WEIGHTINGS:
        raise ValueError(f"weighting must be one of {WEIGHTINGS}, got {weighting!r}")


@dataclass(frozen=True)
class OverlapTable:
    """Per-label pair sums, volumes and complexities of a group of label images.

    Built once by :func:`overlap_table`; every scalar measure is read from it, so asking for
    all five weightings costs one pass over the voxels.

    Attributes
    ----------
    labels : ndarray of int, shape (n_labels,)
        The label values kept, ascending (for fuzzy input: the component indices).
    n_images : int
        N, the number of label images; there are N (N - 1) / 2 unordered pairs.
    pair_min, pair_max : ndarray of float, shape (n_labels,)
        ``sum_{i<j} sum_v min(A_il, A_jl)`` and the same with max, in voxels (memberships
        summed; exact integers for crisp input).
    volume : ndarray of float, shape (n_labels,)
        V_l, the mean over images of the label's volume ``sum_v A_il``, in mm^3 (voxel units
        when no spacing is known).
    complexity : ndarray of float, shape (n_labels,)
        The mean over the images that carry the label of ``sum_v |grad A_il| / sum_v A_il``,
        in mm^-1: boundary per unit volume. Zero for a label that fills the whole grid.
    target_overlap : ndarray of float, shape (n_labels,)
        Klein's target overlap ``|A_i ∩ A_j| / |A_j|`` averaged over the ordered pairs
        (i != j) whose target j carries the label (intersection as sum of minima).
    spacing : tuple of float
        Voxel size used for the gradients, mm, ITK order (x, y[, z]).
    fuzzy : bool
        True when the input was memberships rather than crisp label maps.
    skipped_labels : tuple of int
        Requested (or fuzzy) labels absent from every image, left out of every sum.
    """

    labels: np.ndarray
    n_images: int
    pair_min: np.ndarray
    pair_max: np.ndarray
    volume: np.ndarray
    complexity: np.ndarray
    target_overlap: np.ndarray
    spacing: tuple[float, ...]
    fuzzy: bool
    skipped_labels: tuple[int, ...] = field(default=())

    @property
    def jaccard(self) -> np.ndarray:
        """Group Jaccard (Tanimoto) per label, ``pair_min / pair_max``, shape (n_labels,)."""
        return self.pair_min / self.pair_max

    @property
    def dice(self) -> np.ndarray:
        """Group Dice per label, ``2 pair_min / (pair_min + pair_max)``, shape (n_labels,).

        Equal to ``2 J / (1 + J)``: the pair sums of ``A_i + A_j`` are min plus max.
        """
        return 2.0 * self.pair_min / (self.pair_min + self.pair_max)

    def weights(self, weighting: str = "inverse_volume") -> np.ndarray:
        """The label weights alpha_l, shape (n_labels,), unnormalized.

        Parameters
        ----------
        weighting : {"volume", "inverse_volume", "inverse_volume_squared", "complexity", \
"inverse_volume_complexity"}
            ``"volume"``: 1 (implicit volume weighting); ``"inverse_volume"``: 1 / V_l (mm^-3);
            ``"inverse_volume_squared"``: 1 / V_l^2; ``"complexity"``: the complexity C_l
            (mm^-1); ``"inverse_volume_complexity"``: C_l / V_l.
        """
        _check_weighting(weighting)
        if weighting == "volume":
            return np.ones_like(self.volume)
        if weighting == "inverse_volume":
            return 1.0 / self.volume
        if weighting == "inverse_volume_squared":
            return 1.0 / self.volume**2
        if weighting == "complexity":
            return self.complexity.copy()
        return self.complexity / self.volume

    def generalized(self, weighting: str = "inverse_volume") -> float:
        """The generalized overlap ``sum_l alpha_l pair_min_l / sum_l alpha_l pair_max_l``.

        In [0, 1]; 1 when every image carries every label on the same voxels. NaN (with a
        warning) when every weight is zero, e.g. complexity weighting of labels without
        boundary. `weighting` as in :meth:`weights`.
        """
        alpha = self.weights(weighting)
        den = float(alpha @ self.pair_max)
        if not den > 0:
            warnings.warn(
                f"generalized overlap with weighting {weighting!r} is undefined: every label "
                "weight is zero",
                RuntimeWarning,
                stacklevel=2,
            )
            return math.nan
        return float(alpha @ self.pair_min) / den

    def to_dict(self) -> dict:
        """Plain-Python form: the generalized overlap per weighting and one row per label."""
        return {
            "n_images": self.n_images,
            "fuzzy": self.fuzzy,
            "spacing": list(self.spacing),
            "skipped_labels": [int(v) for v in self.skipped_labels],
            "generalized": {w: self.generalized(w) for w in WEIGHTINGS},
            "labels": self.rows(),
        }

    def rows(self) -> list[dict]:
        """One dict per label: value, volume, complexity, Jaccard, Dice, target overlap, sums."""
        jac, dice = self.jaccard, self.dice
        return [
            {
                "label": int(self.labels[k]),
                "volume": float(self.volume[k]),
                "complexity": float(self.complexity[k]),
                "jaccard": float(jac[k]),
                "dice": float(dice[k]),
                "target_overlap": float(self.target_overlap[k]),
                "pair_min": float(self.pair_min[k]),
                "pair_max": float(self.pair_max[k]),
            }
            for k in range(len(self.labels))
        ]


def generalized_overlap(
    labels,
    *,
    weighting: str = "inverse_volume",
    label_values=None,
    include_background: bool = False,
    mask=None,
    spacing=None,
) -> float:
    """Generalized Tanimoto overlap of a group of label images (Crum et al. 2006, eq. 4).

    A thin wrapper: ``overlap_table(labels, ...).generalized(weighting)``. To read several
    weightings, build the table once with :func:`overlap_table`.

    Parameters
    ----------
    labels : ndarray or sequence of sitk.Image or paths
        See :func:`overlap_table`.
    weighting : {"volume", "inverse_volume", "inverse_volume_squared", "complexity", \
"inverse_volume_complexity"}
        The label weights alpha_l (see :meth:`OverlapTable.weights`). The paper's main choice
        is ``"inverse_volume"`` (every label counts equally, whatever its size).
    label_values, include_background, mask, spacing
        See :func:`overlap_table`.

    Returns
    -------
    float
        The overlap in [0, 1]; higher is better.

    Examples
    --------
    >>> import numpy as np, itk_nrreval as nr
    >>> a = np.array([[0, 1, 1, 0], [0, 0, 1, 1]])
    >>> nr.generalized_overlap(a)  # |{2}| / |{1, 2, 3}|
    0.3333333333333333
    """
    _check_weighting(weighting)
    table = overlap_table(
        labels,
        label_values=label_values,
        include_background=include_background,
        mask=mask,
        spacing=spacing,
    )
    return table.generalized(weighting)


def overlap_table(
    labels,
    *,
    label_values=None,
    include_background: bool = False,
    mask=None,
    spacing=None,
) -> OverlapTable:
    """The per-label pair sums, volumes and complexities of N label images, in one pass.

    Parameters
    ----------
    labels : ndarray or sequence of sitk.Image or paths
        N >= 2 label images on one grid, as one of

        - an integer (or bool) array of shape (n_images, *spatial): crisp label maps;
        - a floating array of shape (n_images, n_components, *spatial): fuzzy memberships in
          [0, 1], component k being the membership of label k;
        - a sequence of scalar SimpleITK images or files: crisp label maps (a floating pixel
          type is accepted when every value is an integer);
        - a sequence of multi-component images or files (one per subject, components as
          above): fuzzy memberships.

        The dtype of a bare array decides: crisp label maps must have an integer dtype.
    label_values : sequence of int, optional
        The labels to evaluate. Default: every value present in any image (crisp), or every
        component with a nonzero membership somewhere (fuzzy), less background 0 unless
        `include_background`. When given, they are used as given (`include_background` has
        no effect); fuzzy label values must be component indices. Values absent from every
        image are skipped with a warning.
    include_background : bool
        Keep label 0 (component 0 for fuzzy input) in the default label set.
    mask : ndarray of bool of shape (*spatial), sitk.Image, path, or None
        Sum only over voxels inside the mask. Gradients are still taken on the full grid.
    spacing : sequence of float, optional
        Voxel size in mm, ITK order (x, y[, z]) -- the reverse of the numpy axes -- for bare
        arrays only (images bring their own; passing both is an error). Default 1 along every
        axis. Only the complexity weights depend on it.

    Returns
    -------
    OverlapTable

    Raises
    ------
    InputError
        Fewer than two images, images on different grids, non-integer values in a crisp label
        map, memberships outside [0, 1], a mixture of scalar and multi-component images, or no
        label to evaluate.
    ValueError
        Bad `spacing` or `label_values`.

    Notes
    -----
    With ``p_l = sum_{i<j} sum_v min(A_il, A_jl)`` and ``q_l`` the same with max, the
    generalized overlap is ``sum_l alpha_l p_l / sum_l alpha_l q_l``; per label,
    Jaccard ``p_l / q_l`` and Dice ``2 p_l / (p_l + q_l)``. Limit cases: two images and one
    label give the plain Jaccard index; identical images give 1; disjoint labels give 0.

    The pair sums avoid the O(N^2 n) loop over pairs. For crisp maps, if c of the N images
    carry label l at a voxel, the voxel adds C(c, 2) to p_l and C(N, 2) - C(N - c, 2) to q_l:
    O(N n) in all, in exact integer arithmetic. For fuzzy memberships sorted ascending at a
    voxel, a_(1) <= ... <= a_(N), it adds ``sum_k a_(k) (N - k)`` to p_l and
    ``sum_k a_(k) (k - 1)`` to q_l. The sort is Batcher's odd-even merge network,
    O(N log^2 N) branch-free comparators run across blocks of voxels at once (268 for
    N = 36, against 630 pairs); voxels where every membership of a label is zero are skipped.
    Everything streams over the voxels, one label at a time for fuzzy input.

    Complexity: ``|grad A_il|`` by central differences (one-sided at the grid's faces, as
    :func:`numpy.gradient` with ``edge_order=1``; axes of length 1 contribute nothing), in
    physical units, of the label's indicator (crisp) or membership (fuzzy).

    Paper, Sections II-B and V-C; Crum, Camara & Hill, IEEE TMI 25(11):1451-1461, 2006, eq. (4)
    without pair weights. Target overlap: Klein et al., NeuroImage 46(3), 2009.
    """
    _check_components(labels)
    stack = image_stack(labels, what="label map", dtype=None, allow_vector=True)
    data, names = stack.data, stack.names
    n_images = data.shape[0]
    if n_images < 2:
        raise InputError(f"label maps: need at least 2 to form a pair, got {n_images}")
    fuzzy = _is_fuzzy(stack)
    spatial = data.shape[2:] if fuzzy else data.shape[1:]
    if len(spatial) == 0:
        raise InputError(f"label maps: no spatial axis in an array of shape {data.shape}")
    spacing_itk = _spacing(spacing, stack.geometry, len(spatial))
    mask_flat = mask_array(mask, shape=spatial, geometry=stack.geometry)
    mask_flat = np.zeros(0, np.bool_) if mask_flat is None else mask_flat.reshape(-1)
    shape = np.asarray(spatial, dtype=np.int64)
    inv_h = 1.0 / np.asarray(spacing_itk[::-1], dtype=np.float64)

    if fuzzy:
        values, skipped, vol, s_pairs, gsum, p, q = _fuzzy_sums(
            data, names, label_values, include_background, mask_flat, shape, inv_h
        )
    else:
        values, skipped, vol, s_pairs, gsum, p, q = _crisp_sums(
            data, names, label_values, include_background, mask_flat, shape, inv_h
        )
    if skipped:
        warnings.warn(
            f"labels {list(skipped)} are absent from every image and are skipped",
            UserWarning,
            stacklevel=2,
        )
    return _table(
        values, vol, s_pairs, gsum, p, q, spacing=spacing_itk, fuzzy=fuzzy, skipped=skipped
    )


def _table(values, vol, s_pairs, gsum, p, q, *, spacing, fuzzy, skipped) -> OverlapTable:
    """The table from its sums: vol, s_pairs, gsum of shape (N, L) in voxel units, p, q (L,).

    Shared with :mod:`itk_nrreval.scaleout`, which adds the sums up over voxel blocks.
    """
    n_images = vol.shape[0]
    present = vol > 0  # (N, L)
    with np.errstate(divide="ignore", invalid="ignore"):
        complexity = np.where(present, gsum / np.where(present, vol, 1.0), 0.0).sum(0)
        complexity = complexity / present.sum(0)
        target = np.where(present, s_pairs / np.where(present, vol, 1.0), 0.0).sum(0)
        target = target / (present.sum(0) * (n_images - 1))
    return OverlapTable(
        labels=values,
        n_images=n_images,
        pair_min=p,
        pair_max=q,
        volume=vol.mean(axis=0) * float(np.prod(spacing)),
        complexity=complexity,
        target_overlap=target,
        spacing=tuple(spacing),
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


def _check_components(labels) -> None:
    """Refuse a mixture of scalar and multi-component images (naming the first odd one)."""
    if isinstance(labels, (np.ndarray, str, os.PathLike, sitk.Image)):
        return
    first = None
    for i, item in enumerate(labels):
        try:
            if isinstance(item, sitk.Image):
                n = item.GetNumberOfComponentsPerPixel()
            else:
                reader = sitk.ImageFileReader()
                reader.SetFileName(str(item))
                reader.ReadImageInformation()
                n = reader.GetNumberOfComponents()
        except (RuntimeError, TypeError):  # unreadable: image_stack reports it properly
            return
        if first is None:
            first = (n, str(item) if not isinstance(item, sitk.Image) else f"label map[{i}]")
        elif n != first[0]:
            name = str(item) if not isinstance(item, sitk.Image) else f"label map[{i}]"
            raise InputError(f"{name}: has {n} components per voxel, but {first[1]} has {first[0]}")


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
            f"spacing must be {ndim} positive numbers in ITK order (x, y[, z]), got {spacing!r}"
        )
    return tuple(float(s) for s in sp)


def _explicit_values(label_values) -> np.ndarray:
    vals = np.asarray(label_values)
    if vals.ndim != 1 or vals.size == 0:
        raise ValueError(
            f"label_values must be a non-empty sequence of integers, got {label_values!r}"
        )
    if not np.issubdtype(vals.dtype, np.integer):
        if not (np.issubdtype(vals.dtype, np.floating) and np.all(vals == np.round(vals))):
            raise ValueError(f"label_values must be integers, got {label_values!r}")
    vals = vals.astype(np.int64)
    if np.unique(vals).size != vals.size:
        raise ValueError(f"label_values must not repeat a value, got {label_values!r}")
    return np.sort(vals)


def _no_labels(names, include_background: bool) -> InputError:
    which = f"{names[0]} .. {names[-1]}"
    extra = "" if include_background else " other than background 0"
    return InputError(f"{which}: no label{extra} in any of the {len(names)} label maps")


# -- crisp label maps ----------------------------------------------------------------------


def _crisp_sums(data, names, label_values, include_background, mask_flat, shape, inv_h):
    n_images = data.shape[0]
    flat = data.reshape(n_images, -1)
    if data.dtype == np.bool_:
        flat = flat.view(np.uint8)
    elif np.issubdtype(data.dtype, np.floating):  # a crisp map from a floating-point file
        for i in range(n_images):
            row = flat[i]
            bad = row != np.round(row)
            if bad.any():
                raise InputError(
                    f"{names[i]}: non-integer values in a crisp label map "
                    f"(e.g. {row[np.argmax(bad)]!r}); pass memberships as one "
                    "multi-component image per subject"
                )
        flat = flat.astype(np.int64)
    has_mask = mask_flat.size > 0
    lo, hi = int(flat.min()), int(flat.max())
    use_lut = hi - lo < _MAX_LUT
    if use_lut:
        seen = np.zeros(hi - lo + 1, dtype=bool)
        for i in range(n_images):
            row = flat[i][mask_flat] if has_mask else flat[i]
            seen |= np.bincount((row.astype(np.int64) - lo), minlength=hi - lo + 1) > 0
        present_values = np.flatnonzero(seen).astype(np.int64) + lo
    else:
        present_values = np.unique(
            np.concatenate(
                [np.unique(flat[i][mask_flat] if has_mask else flat[i]) for i in range(n_images)]
            )
        ).astype(np.int64)

    if label_values is None:
        values = present_values if include_background else present_values[present_values != 0]
        skipped: tuple[int, ...] = ()
        if values.size == 0:
            raise _no_labels(names, include_background)
    else:
        wanted = _explicit_values(label_values)
        keep = np.isin(wanted, present_values)
        values = wanted[keep]
        skipped = tuple(int(v) for v in wanted[~keep])
        if values.size == 0:
            raise InputError(
                f"{names[0]} .. {names[-1]}: none of the labels {wanted.tolist()} is present"
            )

    n_labels = values.size
    idx = np.empty((flat.shape[1], n_images), dtype=np.int32)  # voxel-major for the kernel
    if use_lut:
        lut = np.full(hi - lo + 1, -1, dtype=np.int32)
        lut[values - lo] = np.arange(n_labels, dtype=np.int32)
        for i in range(n_images):
            idx[:, i] = lut[flat[i].astype(np.int64) - lo]
    else:
        for i in range(n_images):
            row = flat[i].astype(np.int64)
            pos = np.clip(np.searchsorted(values, row), 0, n_labels - 1)
            idx[:, i] = np.where(values[pos] == row, pos, -1)

    vol, s_pairs, gsum = _crisp_kernel(idx, n_labels, mask_flat, shape, inv_h)
    # sum over images of (c - 1) at their voxels = sum over ordered pairs of intersections.
    p_int = s_pairs.sum(axis=0) // 2
    q_int = (n_images - 1) * vol.sum(axis=0) - p_int  # pair sums of a_i + a_j are min + max
    return (
        values,
        skipped,
        vol.astype(np.float64),
        s_pairs.astype(np.float64),
        gsum,
        p_int.astype(np.float64),
        q_int.astype(np.float64),
    )


@numba.njit(cache=True, nogil=True)
def _crisp_kernel(idx, n_labels, mask, shape, inv_h):  # pragma: no cover - compiled
    """Per image and label: voxel count, sum of (c - 1) over its voxels, sum of |grad|.

    ``idx`` is (n_voxels, N) of dense label indices (-1: not evaluated), voxels in C order of
    `shape`; ``c`` is the number of images carrying the label at the voxel. ``mask`` is a
    flat boolean array, or empty for no mask. Gradients as numpy.gradient, edge_order=1:
    along an axis with neighbours p and m (the voxel itself at a face), the indicator of
    label l changes by ``[p == l] - [m == l]``, so only labels p and m get a component, of
    squared size ``f^2`` (f = 1 / (2 h) inside, 1 / h at a face).
    """
    n_vox, n_img = idx.shape
    ndim = shape.size
    strides = np.ones(ndim, np.int64)
    for d in range(ndim - 2, -1, -1):
        strides[d] = strides[d + 1] * shape[d + 1]
    has_mask = mask.size > 0
    vol = np.zeros((n_img, n_labels), np.int64)
    spair = np.zeros((n_img, n_labels), np.int64)
    gsum = np.zeros((n_img, n_labels), np.float64)
    gpart = np.zeros((n_img, n_labels), np.float64)
    cnt = np.zeros(n_labels, np.int64)
    gsq = np.zeros(n_labels, np.float64)
    touched = np.empty(2 * ndim, np.int64)
    coords = np.zeros(ndim, np.int64)
    plus = np.empty(ndim, np.int64)
    minus = np.empty(ndim, np.int64)
    fac2 = np.empty(ndim, np.float64)
    for v in range(n_vox):
        if v > 0:  # advance the C-order coordinates of v
            d = ndim - 1
            coords[d] += 1
            while coords[d] == shape[d] and d > 0:
                coords[d] = 0
                d -= 1
                coords[d] += 1
        if has_mask and not mask[v]:
            continue
        if v % 4096 == 0:  # blocked summation keeps float rounding small
            for i in range(n_img):
                for k in range(n_labels):
                    gsum[i, k] += gpart[i, k]
                    gpart[i, k] = 0.0
        # pair counts
        for i in range(n_img):
            k = idx[v, i]
            if k >= 0:
                cnt[k] += 1
        for i in range(n_img):
            k = idx[v, i]
            if k >= 0:
                vol[i, k] += 1
                spair[i, k] += cnt[k] - 1
        for i in range(n_img):
            k = idx[v, i]
            if k >= 0:
                cnt[k] = 0
        # neighbours along each axis, with numpy.gradient's edge rule
        n_ax = 0
        for d in range(ndim):
            if shape[d] == 1:
                continue
            if coords[d] == 0:
                plus[n_ax] = v + strides[d]
                minus[n_ax] = v
                fac2[n_ax] = inv_h[d] * inv_h[d]
            elif coords[d] == shape[d] - 1:
                plus[n_ax] = v
                minus[n_ax] = v - strides[d]
                fac2[n_ax] = inv_h[d] * inv_h[d]
            else:
                plus[n_ax] = v + strides[d]
                minus[n_ax] = v - strides[d]
                fac2[n_ax] = 0.25 * inv_h[d] * inv_h[d]
            n_ax += 1
        for i in range(n_img):
            n_t = 0
            for d in range(n_ax):
                a = idx[plus[d], i]
                b = idx[minus[d], i]
                if a != b:
                    if a >= 0:
                        if gsq[a] == 0.0:
                            touched[n_t] = a
                            n_t += 1
                        gsq[a] += fac2[d]
                    if b >= 0:
                        if gsq[b] == 0.0:
                            touched[n_t] = b
                            n_t += 1
                        gsq[b] += fac2[d]
            for t in range(n_t):
                c = touched[t]
                gpart[i, c] += math.sqrt(gsq[c])
                gsq[c] = 0.0
    gsum += gpart
    return vol, spair, gsum


# -- fuzzy memberships ---------------------------------------------------------------------


def _fuzzy_sums(data, names, label_values, include_background, mask_flat, shape, inv_h):
    n_images, n_comp = data.shape[:2]
    flat = data.reshape(n_images, n_comp, -1)
    if flat.dtype not in (np.float32, np.float64):
        flat = flat.astype(np.float64)
    lows, highs, present = _membership_stats(flat, mask_flat)
    for i in range(n_images):
        lo, hi = float(lows[i]), float(highs[i])
        if lo < 0.0 or hi > 1.0:
            raise InputError(
                f"{names[i]}: membership values outside [0, 1] (min {lo:.6g}, max {hi:.6g}); "
                "crisp label maps must have an integer type"
            )
    comp_present = present.any(axis=0)
    if label_values is None:
        candidates = np.arange(0 if include_background else 1, n_comp, dtype=np.int64)
    else:
        candidates = _explicit_values(label_values)
        if candidates[0] < 0 or candidates[-1] >= n_comp:
            raise ValueError(
                f"label_values of fuzzy input must be component indices 0..{n_comp - 1}, "
                f"got {label_values!r}"
            )
    keep = comp_present[candidates]
    values = candidates[keep]
    skipped = tuple(int(v) for v in candidates[~keep])
    if values.size == 0:
        raise _no_labels(names, include_background or label_values is not None)

    n_labels = values.size
    vol = np.zeros((n_images, n_labels))
    s_pairs = np.zeros((n_images, n_labels))
    gsum = np.zeros((n_images, n_labels))
    p = np.zeros(n_labels)
    q = np.zeros(n_labels)
    active = np.empty(flat.shape[2], dtype=bool)
    net_lo, net_hi = _sorting_network(n_images)
    # float32 memberships carry the image index in the low bits of their float64 sort key
    packed = flat.dtype == np.float32 and n_images <= 1 << _INDEX_BITS
    work = n_images * n_labels * flat.shape[2]
    for k in progress(
        range(n_labels), desc="overlap", total=n_labels, enabled=work > _PROGRESS_MIN_WORK
    ):
        comp = int(values[k])
        _active_voxels(flat, comp, mask_flat, active)
        voxels = np.flatnonzero(active)  # where some image has a nonzero membership
        _gradient_sums(flat, comp, mask_flat, shape, inv_h, gsum[:, k])
        p[k], q[k] = _pair_sums(
            flat, comp, voxels, net_lo, net_hi, _NETWORK_FRACTION, packed, vol[:, k], s_pairs[:, k]
        )
    return values, skipped, vol, s_pairs, gsum, p, q


@numba.njit(cache=True, parallel=True)
def _membership_stats(flat, mask):  # pragma: no cover - compiled
    """Per image the smallest and largest membership (whole grid), and per image and
    component whether a membership is nonzero inside the mask: one pass, one image per
    thread."""
    n_img, n_comp, n = flat.shape
    lows = np.empty(n_img)
    highs = np.empty(n_img)
    present = np.zeros((n_img, n_comp), np.bool_)
    has_mask = mask.size > 0
    for i in numba.prange(n_img):
        lo = np.inf
        hi = -np.inf
        for k in range(n_comp):
            row = flat[i, k]
            nonzero = False
            for v in range(n):
                a = row[v]
                lo = min(lo, a)
                hi = max(hi, a)
                nonzero |= a != 0 and (not has_mask or mask[v])
            present[i, k] = nonzero
        lows[i] = lo
        highs[i] = hi
    return lows, highs, present


@numba.njit(cache=True, parallel=True)
def _active_voxels(flat, comp, mask, active):  # pragma: no cover - compiled
    """``active[v]``: some image has a nonzero membership of `comp` at v inside the mask."""
    n_img, _, n = flat.shape
    n_chunks = (n + 4095) // 4096
    for c in numba.prange(n_chunks):
        start = c * 4096
        stop = min(start + 4096, n)
        act = active[start:stop]
        act[:] = False
        for i in range(n_img):
            row = flat[i, comp, start:stop]
            for t in range(stop - start):
                act[t] |= row[t] != 0
        if mask.size > 0:
            mk = mask[start:stop]
            for t in range(stop - start):
                act[t] &= mk[t]


@numba.njit(cache=True, parallel=True)
def _pair_sums(
    flat, comp, voxels, net_lo, net_hi, dense_share, packed, vol, spair
):  # pragma: no cover - compiled
    """Pair sums of component `comp` of the memberships `flat` (N, n_comp, n_vox) over
    `voxels`, in blocks of ``_BLOCK`` voxels shared among the threads.

    A block where more than `dense_share` of the values lie strictly in (0, 1) is sorted by
    the network (:func:`_packed_network_kernel` for float32 input when `packed`, else
    :func:`_network_pair_kernel`), any other by :func:`_sparse_pair_kernel`. Each block
    writes its own partial sums, added up in block order afterwards: the result does not
    depend on the number of threads. Adds to ``vol`` and ``spair`` (N,); returns (sum of
    pairwise minima, sum of maxima).
    """
    n_img = flat.shape[0]
    n_blocks = (voxels.size + _BLOCK - 1) // _BLOCK
    pmin = np.zeros(n_blocks)
    pmax = np.zeros(n_blocks)
    vparts = np.zeros((n_blocks, n_img))
    sparts = np.zeros((n_blocks, n_img))
    for b in numba.prange(n_blocks):
        start = b * _BLOCK
        stop = min(start + _BLOCK, voxels.size)
        block = np.empty((n_img, stop - start))
        fractional = _gather(flat, comp, voxels[start:stop], block)
        if fractional > dense_share * block.size:
            if packed:
                pk, qk = _packed_network_kernel(block, net_lo, net_hi, vparts[b], sparts[b])
            else:
                pk, qk = _network_pair_kernel(block, net_lo, net_hi, vparts[b], sparts[b])
        else:
            pk, qk = _sparse_pair_kernel(block, vparts[b], sparts[b])
        pmin[b] = pk
        pmax[b] = qk
    for b in range(n_blocks):
        for i in range(n_img):
            vol[i] += vparts[b, i]
            spair[i] += sparts[b, i]
    return pmin.sum(), pmax.sum()


@numba.njit(cache=True, parallel=True)
def _gradient_sums(flat, comp, mask, shape, inv_h, out):  # pragma: no cover - compiled
    """``out[i] = sum_v |grad flat[i, comp]|`` over the mask, one image per thread.

    Computed only on the slabs (along the first axis) within two of a nonzero one: farther
    out the gradient is zero, and two zero slabs on each side make the cut-out's face rule
    give the full grid's values.
    """
    n_img = flat.shape[0]
    n = flat.shape[2]
    plane = n // shape[0]
    for i in numba.prange(n_img):
        row = flat[i, comp]
        first = -1
        for v in range(n):
            if row[v] != 0:
                first = v
                break
        if first < 0:
            out[i] = 0.0
            continue
        last = first
        for v in range(n - 1, first, -1):
            if row[v] != 0:
                last = v
                break
        lo = max(first // plane - 2, 0)
        hi = min(last // plane + 3, shape[0])
        sub_shape = shape.copy()
        sub_shape[0] = hi - lo
        sub_mask = mask[lo * plane : hi * plane] if mask.size > 0 else mask
        out[i] = _grad_sum_kernel(row[lo * plane : hi * plane], sub_mask, sub_shape, inv_h)


@numba.njit(cache=True, nogil=True)
def _gather(flat, comp, voxels, out):  # pragma: no cover - compiled
    """Copy ``flat[:, comp, voxels]`` into ``out[:, :len(voxels)]`` (as float64); return how
    many of the values lie strictly between 0 and 1."""
    fractional = 0
    for i in range(flat.shape[0]):
        for t in range(voxels.size):
            a = np.float64(flat[i, comp, voxels[t]])
            out[i, t] = a
            if 0.0 < a < 1.0:
                fractional += 1
    return fractional


@functools.lru_cache(maxsize=16)
def _sorting_network(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Batcher's odd-even merge sort for `n` keys as comparator pairs (lo, hi), lo < hi.

    Built for the next power of two and pruned of comparators that reach past `n` (those
    keys would be +inf, so the pruned comparators never swap). 268 comparators for n = 36.
    """
    pairs = []
    p = 1
    while p < n:
        k = p
        while k >= 1:
            for j in range(k % p, n - k, 2 * k):
                for i in range(min(k, n - j - k)):
                    if (i + j) // (2 * p) == (i + j + k) // (2 * p):
                        pairs.append((i + j, i + j + k))
            k //= 2
        p *= 2
    lo = np.array([a for a, _ in pairs], dtype=np.int64)
    hi = np.array([b for _, b in pairs], dtype=np.int64)
    return lo, hi


def _float_minmax(name: str):
    """A numba intrinsic for ``llvm.minnum`` / ``llvm.maxnum`` on float64 (inputs not NaN).

    Unlike ``min(x, y)`` (compare and select, which LLVM turns into masked stores when the
    result goes back where x came from) these vectorize to plain ``vminpd`` / ``vmaxpd``.
    """

    @numba.extending.intrinsic
    def fn(typingctx, x, y):
        def codegen(context, builder, signature, args):
            dbl = llvm_ir.DoubleType()
            f = builder.module.declare_intrinsic(name, [dbl], llvm_ir.FunctionType(dbl, [dbl, dbl]))
            return builder.call(f, args, fastmath=("nnan",))

        return numba.types.float64(numba.types.float64, numba.types.float64), codegen

    return fn


_fmin = _float_minmax("llvm.minnum")
_fmax = _float_minmax("llvm.maxnum")


@numba.njit(cache=True, nogil=True)
def _packed_network_kernel(block, net_lo, net_hi, vol, spair):  # pragma: no cover - compiled
    """As :func:`_network_pair_kernel`, for float32 memberships (held in `block` as float64,
    which it overwrites).

    Layout: the sort keys are an (N, m) float64 array, row i holding image i's memberships
    of the m voxels of the block, so every comparator (lo, hi) of the network is one
    branch-free pass ``x = min(row lo, row hi), row hi = max(...)`` over m contiguous values
    (SIMD across voxels). The image index rides along inside the key: a float32 value as
    float64 has its low 29 mantissa bits zero, and writing i there keeps the order of the
    values (nonnegative floats order like their bit patterns; ties break by image), so the
    sort moves keys only, instead of keys and a separate index array. After the sort, rank
    row k is split back into the exact value and the image index.
    """
    n_img, m = block.shape
    keys = block  # sorted in place
    bits = keys.view(np.int64)
    for i in range(n_img):
        bi = bits[i]
        for t in range(m):
            bi[t] |= i
    for c in range(net_lo.size):
        va = keys[net_lo[c]]
        vb = keys[net_hi[c]]
        for t in range(m):
            x = va[t]
            y = vb[t]
            va[t] = _fmin(x, y)
            vb[t] = _fmax(x, y)
    low = np.int64((1 << _INDEX_BITS) - 1)
    img = np.empty(m, np.int64)
    below = np.zeros(m)
    pmin = 0.0
    pmax = 0.0
    for k in range(n_img):
        bk = bits[k]
        for t in range(m):
            i = bk[t] & low
            img[t] = i
            bk[t] -= i  # keys[k, t] is now the membership itself
        vk = keys[k]
        up = n_img - 1 - k
        total = 0.0
        for t in range(m):
            a = vk[t]
            total += a
            spair[img[t]] += a * up + below[t]
            vol[img[t]] += a
            below[t] += a
        pmin += total * up
        pmax += total * k
    return pmin, pmax


@numba.njit(cache=True, nogil=True)
def _network_pair_kernel(block, net_lo, net_hi, vol, spair):  # pragma: no cover - compiled
    """Pair sums of the memberships `block` (N, n_voxels) by sorting every voxel's column.

    The columns are sorted ascending with the comparator network (net_lo, net_hi), run on
    whole rows at once (branch-free, vectorized across voxels), carrying each value's image
    index. With a_(k) the k-th smallest (k = 0..N-1), a voxel adds ``a_(k) (N - 1 - k)`` to
    the sum of pairwise minima, ``a_(k) k`` to the maxima, and ``sum_{m<k} a_(m) +
    a_(k) (N - 1 - k)`` (= ``sum_{j != i} min(a_i, a_j)``) to ``spair`` of its image i; ties
    do not matter. Adds memberships to ``vol``; returns (sum of minima, sum of maxima).
    """
    n_img, m = block.shape
    val = np.empty((n_img, m), np.float64)
    img = np.empty((n_img, m), np.int64)
    for i in range(n_img):
        for t in range(m):
            val[i, t] = block[i, t]
            img[i, t] = i
    for c in range(net_lo.size):
        va = val[net_lo[c]]
        vb = val[net_hi[c]]
        ia = img[net_lo[c]]
        ib = img[net_hi[c]]
        for t in range(m):
            x = va[t]
            y = vb[t]
            i1 = ia[t]
            i2 = ib[t]
            swap = y < x
            va[t] = y if swap else x
            vb[t] = x if swap else y
            ia[t] = i2 if swap else i1
            ib[t] = i1 if swap else i2
    below = np.zeros(m)
    vpart = np.zeros(n_img)
    spart = np.zeros(n_img)
    pmin = 0.0
    pmax = 0.0
    for k in range(n_img):
        vk = val[k]
        ik = img[k]
        up = n_img - 1 - k
        total = 0.0
        for t in range(m):
            a = vk[t]
            total += a
            spart[ik[t]] += a * up + below[t]
            vpart[ik[t]] += a
            below[t] += a
        pmin += total * up
        pmax += total * k
    for i in range(n_img):
        vol[i] += vpart[i]
        spair[i] += spart[i]
    return pmin, pmax


@numba.njit(cache=True, nogil=True)
def _sparse_pair_kernel(block, vol, spair):  # pragma: no cover - compiled
    """As :func:`_network_pair_kernel`, for memberships that are mostly exactly 0 or 1.

    Per voxel, zeros take the lowest ranks and add nothing, the o ones take the top ranks,
    and only the fractional values in between are sorted (insertion sort, carrying the
    image index): O(N) for a voxel without fractional values.
    """
    n_img, m = block.shape
    vals = np.empty(n_img, np.float64)
    ids = np.empty(n_img, np.int64)
    ones = np.empty(n_img, np.int64)
    vpart = np.zeros(n_img, np.float64)
    spart = np.zeros(n_img, np.float64)
    pmin = 0.0
    pmax = 0.0
    for t in range(m):
        n_frac = 0
        n_one = 0
        for i in range(n_img):
            a = np.float64(block[i, t])
            if a == 0.0:
                continue
            if a == 1.0:
                ones[n_one] = i
                n_one += 1
                continue
            j = n_frac
            while j > 0 and vals[j - 1] > a:
                vals[j] = vals[j - 1]
                ids[j] = ids[j - 1]
                j -= 1
            vals[j] = a
            ids[j] = i
            n_frac += 1
        if n_frac + n_one == 0:
            continue
        first = n_img - n_one - n_frac  # 0-based rank of the smallest nonzero value
        below = 0.0
        for r in range(n_frac):
            rank = first + r
            a = vals[r]
            up = a * (n_img - 1 - rank)
            pmin += up
            pmax += a * rank
            spart[ids[r]] += up + below
            vpart[ids[r]] += a
            below += a
        if n_one > 0:
            top = n_img - n_one  # ones hold ranks top .. N - 1
            pmin += n_one * (n_one - 1) / 2.0
            pmax += (top + n_img - 1) * n_one / 2.0
            for r in range(n_one):  # min with the other ones (1 each) and every smaller value
                spart[ones[r]] += (n_one - 1) + below
                vpart[ones[r]] += 1.0
    for i in range(n_img):
        vol[i] += vpart[i]
        spair[i] += spart[i]
    return pmin, pmax


@numba.njit(cache=True, nogil=True, fastmath={"reassoc", "nsz"})
def _grad_sum_kernel(row, mask, shape, inv_h):  # pragma: no cover - compiled
    """``sum_v |grad row|`` over the masked voxels; `row` flat in C order of `shape`.

    One pass, line by line along the last (contiguous) axis: the squared differences of
    every axis go into a line of scratch (the neighbouring lines along the other axes are
    whole lines too, so every inner loop is contiguous and vectorizes), then the line's
    square roots are summed. ``mask`` is flat boolean or empty (no mask).
    """
    n = row.size
    ndim = shape.size
    nx = shape[ndim - 1]
    strides = np.ones(ndim, np.int64)
    for d in range(ndim - 2, -1, -1):
        strides[d] = strides[d + 1] * shape[d + 1]
    coords = np.zeros(ndim, np.int64)
    g = np.zeros(nx)
    fx1 = inv_h[ndim - 1]
    fx2 = 0.5 * fx1
    total = 0.0
    for base in range(0, n, nx):
        r = row[base : base + nx]
        if nx > 1:  # last axis: one-sided at the ends, central inside
            e = (np.float64(r[1]) - np.float64(r[0])) * fx1
            g[0] = e * e
            e = (np.float64(r[nx - 1]) - np.float64(r[nx - 2])) * fx1
            g[nx - 1] = e * e
            hi = r[2:]
            lo = r[: nx - 2]
            mid = g[1 : nx - 1]
            for t in range(nx - 2):
                e = (np.float64(hi[t]) - np.float64(lo[t])) * fx2
                mid[t] = e * e
        else:
            g[0] = 0.0
        for d in range(ndim - 1):  # the other axes: whole neighbouring lines
            size = shape[d]
            if size == 1:
                continue
            c = coords[d]
            f = inv_h[d] if c == 0 or c == size - 1 else 0.5 * inv_h[d]
            up = base + strides[d] if c < size - 1 else base
            down = base - strides[d] if c > 0 else base
            rp = row[up : up + nx]
            rm = row[down : down + nx]
            for t in range(nx):
                e = (np.float64(rp[t]) - np.float64(rm[t])) * f
                g[t] += e * e
        for start in range(0, nx, 4096):  # blocked summation keeps float rounding small
            part = 0.0
            stop = min(start + 4096, nx)
            if mask.size > 0:
                mk = mask[base : base + nx]
                for t in range(start, stop):
                    part += math.sqrt(g[t]) if mk[t] else 0.0
            else:
                for t in range(start, stop):
                    part += math.sqrt(g[t])
            total += part
        for d in range(ndim - 2, -1, -1):  # advance the coordinates of the line
            coords[d] += 1
            if coords[d] < shape[d]:
                break
            coords[d] = 0
    return total
