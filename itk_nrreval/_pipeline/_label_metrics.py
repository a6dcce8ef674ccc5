"""Dice and HD95 per label in the common frame, as tasks of the evaluate pipeline.

Two small tasks per scored subject, each a frozen task object run through the
content-keyed cache (:func:`~itk_nrreval._pipeline._tasks.cached`): its crisp label map and
label boundaries in the evaluated region (:class:`CrispLabels`), then its side of its
cases: the directed HD95 distances and the Dice counts against the subjects it is compared
with (:class:`LabelDistances`). :func:`label_cases` says which subjects are compared,
:func:`crisp_plan` and :func:`distances_plan` list the tasks, and :func:`label_metrics`
assembles the registration's :class:`~itk_nrreval.measures.label_metrics.LabelMetrics` from their
metadata; the driver runs the plans.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from .._output import json_number
from ..io._cache import DiskCache
from ..io._images import Geometry
from ..io._resampled_images import stored_memberships
from ..io.manifest import Manifest
from ..measures.label_metrics import (
    LabelMetrics,
    crisp_labels,
    directed_percentiles,
    label_surfaces,
)
from ..measures.subject_qc import reference_subject
from ._image_tasks import Resampled
from ._task_keys import TaskContext, mask_flat
from ._tasks import NOT_KEYED, Task


@dataclass(frozen=True)
class LabelCases:
    """The cases a registration's Dice and HD95 are taken on, and what each scored
    subject's tasks compare.

    Attributes
    ----------
    values : list of int
        The run's label values, ``[0, *labels]``; a code is an index into it.
    codes : dict of int to list of int
        Each scored subject's own label codes.
    reference : int or None
        The registration's reference subject among the scored
        (:func:`~itk_nrreval.measures.subject_qc.reference_subject`), or None.
    cases : list of (int, int)
        Each scored subject against the reference where there is one, else every pair of
        scored subjects (subject indices).
    targets, dice_with : dict of int to list of int
        Per scored subject, the subjects whose boundaries its distance map is read at, and
        those it counts shared voxels with (each pair once).
    """

    values: list[int]
    codes: dict[int, list[int]]
    reference: int | None
    cases: list[tuple[int, int]]
    targets: dict[int, list[int]]
    dice_with: dict[int, list[int]]


def label_cases(
    m: Manifest, name: str, r: Resampled, *, scored: Sequence[int], values: Sequence[int]
) -> LabelCases:
    """The :class:`LabelCases` of registration `name` from its resampled entries' metadata
    (`r`) and its scored subjects (`scored`, indices)."""
    code_of = {int(v): c for c, v in enumerate(values)}
    codes = {i: [code_of[int(v)] for v in r.metas[i]["labels"]] for i in scored}
    reg = m.registrations[name]
    ref = reference_subject(
        reg.reference,
        m.images,
        reference_index=reg.reference_index,
        displacement_rms_mm=[
            (meta.get("affine_fit") or {}).get("displacement_rms_mm") for meta in r.metas
        ],
    )
    if ref not in scored:
        ref = None  # off the common grid, or none: every pair
    if ref is None:
        cases = [(a, b) for ka, a in enumerate(scored) for b in scored[ka + 1 :]]
        targets = {i: [j for j in scored if j != i] for i in scored}
        dice_with = {i: [j for j in scored if j > i] for i in scored}
    else:
        cases = [(i, ref) for i in scored if i != ref]
        targets = {i: [ref] for i in scored if i != ref}
        targets[ref] = [i for i in scored if i != ref]
        dice_with = {i: [ref] for i in scored if i != ref}
        dice_with[ref] = []
    return LabelCases(list(values), codes, ref, cases, targets, dice_with)


def crisp_plan(ctx: TaskContext, r: Resampled, cases: LabelCases) -> list[CrispLabels]:
    """Each scored subject's crisp label map (:class:`CrispLabels`) from its resampled
    entry (`r`), in the order of ``cases.codes``."""
    return [
        CrispLabels(
            resampled=r.keys[i],
            mask_key=ctx.mask_key,
            codes=tuple(codes),
            n_codes=len(cases.values),
            grid=ctx.grid,
        )
        for i, codes in cases.codes.items()
    ]


def distances_plan(
    ctx: TaskContext, crisp: Mapping[int, str], cases: LabelCases
) -> list[LabelDistances]:
    """Each scored subject's side of its cases (:class:`LabelDistances`), from the keys of
    the crisp label maps (`crisp`, by subject), in the order of ``cases.codes``."""
    return [
        LabelDistances(
            grid=ctx.grid,
            subject=crisp[i],
            targets=tuple(crisp[j] for j in cases.targets[i]),
            dice_with=tuple(crisp[j] for j in cases.dice_with[i]),
            n_codes=len(cases.values),
        )
        for i in cases.codes
    ]


def label_metrics(
    cases: LabelCases, counts: Mapping[int, dict], sides: Mapping[int, dict]
) -> LabelMetrics:
    """Dice and HD95 (mm) per label and case from each scored subject's :class:`CrispLabels`
    metadata (`counts`) and :class:`LabelDistances` metadata (`sides`), by subject."""
    values, own = cases.values, cases.codes
    n_codes = len(values)
    voxels = {i: np.asarray(meta["counts"], np.int64) for i, meta in counts.items()}
    at = {i: {j: row for row, j in enumerate(cases.targets[i])} for i in own}
    shared = {i: {j: row for row, j in enumerate(cases.dice_with[i])} for i in own}
    dice = np.full((len(cases.cases), n_codes), np.nan)
    hd95 = np.full((len(cases.cases), n_codes), np.nan)
    for row, (a, b) in enumerate(cases.cases):
        # a's boundary read in b's distance map, and b's in a's
        to_b = np.array(sides[b]["d95"][at[b][a]], np.float64)
        to_a = np.array(sides[a]["d95"][at[a][b]], np.float64)
        first, second = (a, b) if b in shared[a] else (b, a)
        inter = np.asarray(sides[first]["inter"][shared[first][second]], np.float64)
        for c in set(own[a]) & set(own[b]):  # a label both label maps have
            total = voxels[a][c] + voxels[b][c]
            if total:
                dice[row, c] = 2.0 * inter[c] / total
            if np.isfinite(to_a[c]) and np.isfinite(to_b[c]):
                hd95[row, c] = max(to_a[c], to_b[c])
    compared = [c for c in range(1, n_codes) if np.isfinite(dice[:, c]).any()]
    return LabelMetrics(
        labels=tuple(int(values[c]) for c in compared),
        cases=tuple((int(a), int(b)) for a, b in cases.cases),
        reference=None if cases.reference is None else int(cases.reference),
        dice=dice[:, compared],
        hd95_mm=hd95[:, compared],
    )


@dataclass(frozen=True)
class CrispLabels(Task):
    """One subject's crisp label map in the evaluated region, and its label boundaries.

    From the resampled entry `resampled`'s memberships (:func:`~itk_nrreval.measures.label_metrics.
    crisp_labels`, channel k written as ``codes[k]``, an index into the run's label values;
    background outside `mask_key`'s region) and
    :func:`~itk_nrreval.measures.label_metrics.label_surfaces`. The entry holds ``labels`` (n,) in
    the smallest unsigned dtype for `n_codes`, ``b_ptr`` (n_codes + 1,) and ``b_idx`` (flat
    voxel indices of every code's boundary; uint32 below 2**32 voxels); its metadata
    ``counts``, each code's voxels in the region.

    Costs one pass over the grid per label for the memberships' maximum (as the label sums
    do), one ``find_objects`` pass and each label's box: about 0.2 s at 1 mm (9 labels,
    docs/label-metrics.md), and n bytes in the cache until the registration is done.
    """

    kind: ClassVar[str] = "crisp_labels"
    resampled: str
    mask_key: str | None
    codes: tuple[int, ...]
    n_codes: int
    grid: Geometry = field(metadata=NOT_KEYED)  # the resampled entry's (in its key)

    def compute(self, cache: DiskCache) -> tuple[dict, dict]:
        g = self.grid
        entry = cache.open("resampled", self.resampled)
        memb = stored_memberships(entry, g.shape, entry.meta["labels"])
        mask = mask_flat(cache, self.mask_key)
        region = None if mask is None else mask.reshape(g.shape)
        codes, n_codes = list(self.codes), self.n_codes
        labels = crisp_labels(memb, codes=codes, n_codes=n_codes, region=region)
        surfaces = label_surfaces(labels, n_codes, region=region)
        index = surfaces.index.astype(np.uint32) if labels.size < 2**32 else surfaces.index
        meta = {"counts": surfaces.counts.tolist()}
        arrays = {"labels": labels.reshape(-1), "b_ptr": surfaces.ptr, "b_idx": index}
        return arrays, meta


@dataclass(frozen=True)
class LabelDistances(Task):
    """One subject's side of its cases, from the ``crisp_labels`` entries of the subject
    (`subject`), of its `targets` and of its `dice_with` partners.

    Metadata only: ``{"d95": (len(targets), n_codes), "inter": (len(dice_with), n_codes)}``
    as lists: per target, per code, the 95th percentile of the distances (mm) from the
    target's boundary to the subject's nearest boundary voxel (None: no boundary in one of
    them; one distance transform of the subject's boundary per code,
    :func:`~itk_nrreval.measures.label_metrics.directed_percentiles`, read at every target's); per
    partner of `dice_with`, per code, the voxels where both maps have it.
    """

    kind: ClassVar[str] = "label_distances"
    grid: Geometry
    subject: str
    targets: tuple[str, ...]
    dice_with: tuple[str, ...]
    n_codes: int = field(metadata=NOT_KEYED)  # the crisp entries' (in their keys)

    def compute(self, cache: DiskCache) -> tuple[dict, dict]:
        g, n_codes = self.grid, self.n_codes
        own = cache.open("crisp_labels", self.subject)
        ptr, idx = own.array("b_ptr"), own.array("b_idx", mmap=True)
        others = []
        for key in self.targets:
            e = cache.open("crisp_labels", key)
            others.append((e.array("b_ptr"), e.array("b_idx", mmap=True)))
        d95 = np.full((len(self.targets), n_codes), np.nan)
        for code in range(1, n_codes):
            mine = np.asarray(idx[ptr[code] : ptr[code + 1]], np.int64)
            if mine.size:
                d95[:, code] = directed_percentiles(
                    mine,
                    [np.asarray(t[p[code] : p[code + 1]], np.int64) for p, t in others],
                    shape=g.shape,
                    spacing=g.spacing,
                )
        del others
        inter = np.zeros((len(self.dice_with), n_codes), np.int64)
        if self.dice_with:
            labels = own.array("labels")
            for row, key in enumerate(self.dice_with):  # one other map in memory at a time
                other = cache.open("crisp_labels", key).array("labels", mmap=True)
                both = labels[labels == np.asarray(other)]
                inter[row] = np.bincount(both, minlength=n_codes)[:n_codes]
        meta = {
            "d95": [[json_number(v) for v in row] for row in d95],
            "inter": inter.tolist(),
        }
        return {}, meta
