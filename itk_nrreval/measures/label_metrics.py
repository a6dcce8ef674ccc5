"""The numbers registration papers report, computed right: Dice and HD95 per label, in mm.

Learn2Reg (Hering et al., IEEE TMI 2023) and LUMIR after it report, per registration, the
Dice overlap and the 95th-percentile Hausdorff distance (HD95) of each label, SDlogJ, the
fraction of folding voxels, and a *robustness* aggregate: the 30% worst cases. This module
gives the label measures (SDlogJ and folding are the deformation's:
:class:`itk_nrreval.io.plausibility.Plausibility`), measured where the evaluation compares the
subjects, the common frame:

* each subject's labels become a **crisp label map** in the common frame
  (:func:`crisp_labels`): the label of largest membership among the fuzzy memberships the
  evaluation resamples anyway (one-hot maps resampled linearly, or as chosen), background
  where one minus their sum is at least as large; outside the evaluated region, background;
* **cases**: where the registration has a reference among its subjects (``reference_index``,
  or the reference's own image registered by the identity:
  :func:`itk_nrreval.measures.subject_qc.reference_subject`), each other subject against the
  reference, as a pairwise registration is scored against its fixed image; otherwise
  **every pair of subjects**, once each (the group has no fixed image, and every pair is a
  comparison the group registration claims);
* **Dice** per label and case, ``2 |A ∩ B| / (|A| + |B|)``, voxels counted inside the
  evaluated region;
* **HD95** per label and case, in mm on the common grid's physical spacing (anisotropic
  spacing honoured, direction cosines do not change distances): the larger of the two
  directed 95th percentiles (``np.percentile``, linear) of the distances from one label's
  boundary voxels to the other's nearest boundary voxel -- the definition of DeepMind's
  ``surface_distance`` that Learn2Reg calls, without its voxel units. A label's boundary
  is its voxels that have a face neighbour in the evaluated region with another label
  (:func:`label_boundary`): the region's own edge is not a boundary, since both maps share
  it and it would add distances of 0. Distances come from an exact Euclidean distance
  transform (``scipy.ndimage.distance_transform_edt`` with the grid's spacing) of one
  boundary, cropped to the box holding both boundaries (:func:`directed_percentiles`);
* a label that one of the two label maps does not have at all (before resampling) gives
  no value for the case (NaN), as in Learn2Reg; a label both have but one loses in the
  common frame gets Dice 0 and no HD95 (no boundary to measure from);
* the **worst-case aggregate** (:func:`worst_tail_mean`) is the mean over the 30% worst
  cases, at least one, on the side that is worse: the lowest Dice, the **largest** HD95.

Where this differs from the published evaluation script (MDL-UzL/L2R, ``evaluation.py``
and ``utils.py``; raised in its tracker as issues #6, #7 and #8): it takes the log
Jacobian of ``det J + 3``, counts folds after clipping ``det J`` at 1e-9 (so it always counts
0), measures HD95 in voxels (``np.ones(3)`` as the spacing), and takes its ``'30'`` aggregate
as ``np.quantile(values, 0.3)`` for every measure, which for HD95 is the best tail
(``docs/label-metrics.md``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import ndimage

from .._output import json_number
from ..io._memberships import SparseMemberships

__all__ = [
    "WORST_FRACTION",
    "HD_PERCENTILE",
    "crisp_labels",
    "label_boundary",
    "LabelSurfaces",
    "label_surfaces",
    "directed_percentiles",
    "dice",
    "hausdorff95",
    "worst_tail_mean",
    "MetricSummary",
    "summarize",
    "LabelMetrics",
]

#: The share of cases the worst-case aggregate averages (Learn2Reg's "30").
WORST_FRACTION = 0.3
#: The percentile of the surface distances HD95 takes.
HD_PERCENTILE = 95.0


def _code_dtype(n_codes: int) -> np.dtype:
    """The smallest unsigned integer type that holds codes ``0 .. n_codes - 1``."""
    for dtype in (np.uint8, np.uint16, np.uint32):
        if n_codes - 1 <= np.iinfo(dtype).max:
            return np.dtype(dtype)
    return np.dtype(np.uint64)  # pragma: no cover - more than 4e9 labels


def crisp_labels(
    memberships: SparseMemberships,
    *,
    codes: Sequence[int] | None = None,
    n_codes: int | None = None,
    region: np.ndarray | None = None,
) -> np.ndarray:
    """The label of largest membership at every voxel: a crisp label map.

    Parameters
    ----------
    memberships : SparseMemberships
        One subject's fuzzy memberships on the grid, one channel per nonzero label.
    codes : sequence of int, optional, keyword-only
        The code written for each channel (length ``memberships.n_labels``, each >= 1);
        default the label values.
    n_codes : int, optional, keyword-only
        One more than the largest code any map of the group uses: the dtype holds it
        (default one more than the largest of `codes`).
    region : ndarray of bool, shape ``memberships.shape``, optional, keyword-only
        The evaluated region; background (0) outside it.

    Returns
    -------
    ndarray of shape ``memberships.shape``, unsigned integer
        The code of the channel of largest membership; 0 (background) where the
        background's membership, one minus the sum of the channels', is at least as large
        (ties between channels: the first). The smallest unsigned dtype that holds
        `n_codes` codes.
    """
    codes = [int(v) for v in (memberships.values if codes is None else codes)]
    if len(codes) != memberships.n_labels:
        raise ValueError(f"codes: {len(codes)} codes for {memberships.n_labels} channels")
    if codes and min(codes) < 1:
        raise ValueError("codes: a channel's code must be at least 1 (0 is the background)")
    n = math.prod(memberships.shape)
    top = max(codes, default=0) + 1 if n_codes is None else int(n_codes)
    best = np.zeros(n, np.float32)
    total = np.zeros(n, np.float32)
    out = np.zeros(n, _code_dtype(top))
    for k, code in enumerate(codes):
        idx, w = memberships.label(k)
        idx = np.asarray(idx)
        total[idx] += w  # indices are unique within a channel
        better = w > best[idx]
        best[idx[better]] = w[better]
        out[idx[better]] = code
    out[best <= np.float32(1.0) - total] = 0
    if region is not None:
        out[~np.asarray(region, bool).reshape(-1)] = 0
    return out.reshape(memberships.shape)


def _boundary_of(inside: np.ndarray, region: np.ndarray | None) -> np.ndarray:
    """The voxels of `inside` with a face neighbour in `region` (everywhere: None) that is
    not in `inside`; same shape, bool."""
    out = np.zeros(inside.shape, bool)
    for axis in range(inside.ndim):
        lo = [slice(None)] * inside.ndim
        hi = [slice(None)] * inside.ndim
        lo[axis], hi[axis] = slice(None, -1), slice(1, None)
        lo, hi = tuple(lo), tuple(hi)
        other_hi = ~inside[hi] if region is None else region[hi] & ~inside[hi]
        other_lo = ~inside[lo] if region is None else region[lo] & ~inside[lo]
        out[lo] |= inside[lo] & other_hi
        out[hi] |= inside[hi] & other_lo
    return out


def label_boundary(
    labels: np.ndarray, code: int, *, region: np.ndarray | None = None
) -> np.ndarray:
    """A label's boundary voxels: those of the label with a face neighbour in the region
    that has another label.

    Parameters
    ----------
    labels : ndarray of int, any dimension
        A crisp label map (numpy order).
    code : int
        The label.
    region : ndarray of bool, shape ``labels.shape``, optional, keyword-only
        Neighbours outside it do not count (the grid's edge never does).

    Returns
    -------
    ndarray of bool, shape ``labels.shape``
    """
    inside = np.asarray(labels) == code
    if region is not None:
        region = np.asarray(region, bool)
        inside &= region
    return _boundary_of(inside, region)


@dataclass(frozen=True, eq=False)
class LabelSurfaces:
    """One crisp label map's voxel counts and boundary voxels, per label code.

    Attributes
    ----------
    counts : ndarray of int64, shape (n_codes,)
        Voxels of each code (code 0: background) in the map.
    ptr : ndarray of int64, shape (n_codes + 1,)
        Code c's boundary voxels are ``index[ptr[c]:ptr[c + 1]]``.
    index : ndarray of int64, shape (n_boundary,)
        Flat C-order voxel indices of the boundaries, ascending per code (none for code 0).
    """

    counts: np.ndarray
    ptr: np.ndarray
    index: np.ndarray

    def boundary(self, code: int) -> np.ndarray:
        """Code `code`'s boundary voxels (flat indices, ascending)."""
        return self.index[self.ptr[code] : self.ptr[code + 1]]


def label_surfaces(
    labels: np.ndarray, n_codes: int, *, region: np.ndarray | None = None
) -> LabelSurfaces:
    """Every label's voxel count and boundary (:func:`label_boundary`) in a crisp map.

    Each label's boundary is found in its bounding box grown by one voxel
    (``scipy.ndimage.find_objects``: one pass over the map for every label), so the cost
    is one pass plus each label's own box.

    Parameters
    ----------
    labels : ndarray of unsigned int, any dimension
        A crisp map of codes ``0 .. n_codes - 1`` (:func:`crisp_labels`), background 0
        outside `region`.
    n_codes : int
    region : ndarray of bool, shape ``labels.shape``, optional, keyword-only

    Returns
    -------
    LabelSurfaces
    """
    labels = np.asarray(labels)
    counts = np.bincount(labels.reshape(-1), minlength=n_codes).astype(np.int64)[:n_codes]
    region = None if region is None else np.asarray(region, bool)
    ptr = np.zeros(n_codes + 1, np.int64)
    parts: list[np.ndarray] = []
    boxes = ndimage.find_objects(labels, max_label=n_codes - 1) if n_codes > 1 else []
    for code in range(1, n_codes):
        box = boxes[code - 1]
        found = np.zeros(0, np.int64)
        if box is not None:
            grown = tuple(
                slice(max(s.start - 1, 0), min(s.stop + 1, n))
                for s, n in zip(box, labels.shape, strict=True)
            )
            inside = labels[grown] == code
            if region is not None:
                inside &= region[grown]
            edge = _boundary_of(inside, None if region is None else region[grown])
            local = np.nonzero(edge)
            found = np.ravel_multi_index(
                tuple(c + s.start for c, s in zip(local, grown, strict=True)), labels.shape
            ).astype(np.int64)
            found.sort()
        parts.append(found)
        ptr[code + 1] = ptr[code] + found.size
    index = np.concatenate(parts) if parts else np.zeros(0, np.int64)
    return LabelSurfaces(counts, ptr, index)


def _numpy_spacing(spacing: Sequence[float], ndim: int) -> tuple[float, ...]:
    """ITK-order spacing (x, y[, z]) in numpy order, checked."""
    if len(spacing) != ndim:
        raise ValueError(f"spacing: {len(spacing)} values for a {ndim}D grid")
    return tuple(float(s) for s in reversed(spacing))


def directed_percentiles(
    own: np.ndarray,
    targets: Sequence[np.ndarray],
    *,
    shape: Sequence[int],
    spacing: Sequence[float],
    q: float = HD_PERCENTILE,
) -> np.ndarray:
    """The q-th percentile of the distances (mm) from each target's points to the nearest
    of `own`.

    One exact Euclidean distance transform of `own` (``scipy.ndimage.distance_transform_edt``
    with the grid's spacing), cropped to the box that holds `own` and every target, is
    read at each target's points.

    Parameters
    ----------
    own : ndarray of int, shape (n_own,)
        Flat C-order voxel indices (one label's boundary in one map).
    targets : sequence of ndarray of int
        Flat voxel indices of each target (the same label's boundary in other maps).
    shape : sequence of int, keyword-only
        The grid's numpy shape.
    spacing : sequence of float, keyword-only
        The grid's voxel size in mm, ITK order (x, y[, z]).
    q : float, keyword-only
        The percentile (``np.percentile``'s linear interpolation).

    Returns
    -------
    ndarray of float64, shape (len(targets),)
        NaN for a target without points, and for every target when `own` has none.
    """
    shape = tuple(int(n) for n in shape)
    sampling = _numpy_spacing(spacing, len(shape))
    out = np.full(len(targets), np.nan)
    own = np.asarray(own, np.int64)
    present = [k for k, t in enumerate(targets) if np.asarray(t).size]
    if not own.size or not present:
        return out
    points = [np.stack(np.unravel_index(own, shape), axis=1)]
    points += [np.stack(np.unravel_index(np.asarray(targets[k], np.int64), shape), axis=1)
               for k in present]  # fmt: skip
    lo = np.min([p.min(axis=0) for p in points], axis=0)
    hi = np.max([p.max(axis=0) for p in points], axis=0) + 1
    features = np.ones(tuple(hi - lo), bool)
    features[tuple((points[0] - lo).T)] = False  # the transform's zeros: own's voxels
    dist = ndimage.distance_transform_edt(features, sampling=sampling)
    for k, p in zip(present, points[1:], strict=True):
        out[k] = np.percentile(dist[tuple((p - lo).T)], q)
    return out


def dice(a: np.ndarray, b: np.ndarray) -> float:
    """``2 |A ∩ B| / (|A| + |B|)`` of two boolean masks of one shape; NaN when both are
    empty."""
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    total = int(a.sum()) + int(b.sum())
    return 2.0 * int(np.count_nonzero(a & b)) / total if total else math.nan


def hausdorff95(
    a: np.ndarray,
    b: np.ndarray,
    *,
    spacing: Sequence[float],
    region: np.ndarray | None = None,
    q: float = HD_PERCENTILE,
) -> float:
    """HD95 (mm) of two boolean masks: the larger of the two directed q-th percentiles of
    the distances between their boundaries (:func:`label_boundary`).

    Parameters
    ----------
    a, b : ndarray of bool, one shape (numpy order)
    spacing : sequence of float, keyword-only
        Voxel size in mm, ITK order (x, y[, z]).
    region : ndarray of bool, optional, keyword-only
        The region the masks are compared in (its edge is not a boundary).
    q : float, keyword-only

    Returns
    -------
    float
        NaN when either mask has no boundary.
    """
    shape = np.asarray(a).shape
    edges = []
    for m in (a, b):
        lab = np.asarray(m, bool).astype(np.uint8)
        edges.append(np.flatnonzero(label_boundary(lab, 1, region=region)))
    ab = directed_percentiles(edges[1], [edges[0]], shape=shape, spacing=spacing, q=q)[0]
    ba = directed_percentiles(edges[0], [edges[1]], shape=shape, spacing=spacing, q=q)[0]
    return float(max(ab, ba)) if math.isfinite(ab) and math.isfinite(ba) else math.nan


def worst_tail_mean(
    values: Sequence[float] | np.ndarray,
    *,
    higher_is_better: bool,
    fraction: float = WORST_FRACTION,
) -> float:
    """The mean over the worst `fraction` of the cases: Learn2Reg's robustness aggregate,
    taken on the side that is worse.

    Parameters
    ----------
    values : sequence of float
        One value per case; NaN values are not cases.
    higher_is_better : bool, keyword-only
        True for Dice (the lowest values are the worst), False for HD95 (the largest are).
    fraction : float, keyword-only
        Of the cases, in (0, 1]: the mean is over the ``ceil(fraction * n)`` worst (at least
        one).

    Returns
    -------
    float
        NaN without a case.
    """
    if not 0 < fraction <= 1:
        raise ValueError(f"fraction: expected a value in (0, 1], got {fraction!r}")
    v = np.asarray(values, np.float64).reshape(-1)
    v = np.sort(v[np.isfinite(v)])
    if not v.size:
        return math.nan
    k = max(1, math.ceil(fraction * v.size - 1e-9))  # 0.3 * 10 is 3.0000000000000004
    return float(v[:k].mean() if higher_is_better else v[-k:].mean())


@dataclass(frozen=True)
class MetricSummary:
    """One measure over the cases.

    Attributes
    ----------
    mean, std : float
        Over the cases where the measure is defined (``std``: population, ``ddof=0``, as
        Learn2Reg's); NaN without one.
    worst30 : float
        :func:`worst_tail_mean`: the mean of the 30% worst cases.
    n_cases : int
        The cases where it is defined.
    """

    mean: float
    std: float
    worst30: float
    n_cases: int

    def to_dict(self) -> dict[str, Any]:
        return {
            "mean": json_number(self.mean),
            "std": json_number(self.std),
            "worst30": json_number(self.worst30),
            "n_cases": int(self.n_cases),
        }


def summarize(values: Sequence[float] | np.ndarray, *, higher_is_better: bool) -> MetricSummary:
    """:class:`MetricSummary` of one measure's values over the cases (NaN: not a case)."""
    v = np.asarray(values, np.float64).reshape(-1)
    v = v[np.isfinite(v)]
    if not v.size:
        return MetricSummary(math.nan, math.nan, math.nan, 0)
    return MetricSummary(
        float(v.mean()),
        float(v.std()),
        worst_tail_mean(v, higher_is_better=higher_is_better),
        int(v.size),
    )


def _case_means(values: np.ndarray) -> np.ndarray:
    """Per case (row), the mean over the labels where it is defined; NaN where none is."""
    finite = np.isfinite(values)
    n = finite.sum(axis=1)
    total = np.where(finite, values, 0.0).sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, total / np.maximum(n, 1), np.nan)


@dataclass(frozen=True, eq=False)
class LabelMetrics:
    """One registration's Dice and HD95 per label and case, in the common frame.

    Attributes
    ----------
    labels : tuple of int
        The label values (nonzero), the columns.
    cases : tuple of (int, int)
        Each case's two subjects (manifest indices): ``(subject, reference)`` against a
        reference, ``(a, b)`` with ``a < b`` for every pair.
    reference : int or None
        The registration's reference subject the cases are taken against; None: every
        pair of subjects.
    dice : ndarray of float64, shape (n_cases, n_labels)
        NaN where the label is not compared (one of the two label maps does not have it, or
        neither has a voxel of it in the evaluated region).
    hd95_mm : ndarray of float64, shape (n_cases, n_labels)
        mm; NaN where not compared or where either map has no boundary of the label.
    names : dict of int to str, or None
        The labels' names (the manifest's ``label_names``), shown beside the values; None:
        values only.
    """

    labels: tuple[int, ...]
    cases: tuple[tuple[int, int], ...]
    reference: int | None
    dice: np.ndarray = field(repr=False)
    hd95_mm: np.ndarray = field(repr=False)
    names: Mapping[int, str] | None = None

    @property
    def against(self) -> str:
        """``"reference"`` or ``"pairs"``: what the cases compare."""
        return "pairs" if self.reference is None else "reference"

    def per_label(self) -> dict[int, tuple[MetricSummary, MetricSummary]]:
        """Per label value: (Dice, HD95 in mm) over the cases."""
        return {
            v: (
                summarize(self.dice[:, k], higher_is_better=True),
                summarize(self.hd95_mm[:, k], higher_is_better=False),
            )
            for k, v in enumerate(self.labels)
        }

    def overall(self) -> tuple[MetricSummary, MetricSummary]:
        """(Dice, HD95 in mm) over the cases, each case the mean over its labels (as
        Learn2Reg aggregates: a case's mean, then the cases)."""
        return (
            summarize(_case_means(self.dice), higher_is_better=True),
            summarize(_case_means(self.hd95_mm), higher_is_better=False),
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: what the cases compare, how many, and every summary (not the per-case
        values, which grow as N^2 for pairs)."""
        d, h = self.overall()
        return {
            "against": self.against,
            "reference": self.reference,
            "n_cases": len(self.cases),
            "worst_fraction": WORST_FRACTION,
            "dice": d.to_dict(),
            "hd95_mm": h.to_dict(),
            "labels": {
                str(v): {
                    **({"name": self.names[v]} if self.names and v in self.names else {}),
                    "dice": ld.to_dict(),
                    "hd95_mm": lh.to_dict(),
                }
                for v, (ld, lh) in self.per_label().items()
            },
        }
