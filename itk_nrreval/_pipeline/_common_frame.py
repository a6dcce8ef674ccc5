"""The common frame F of each registration, as the pipeline estimates and caches it.

A registration that is not the common one is brought into the common frame by ``F``:
a transform of the manifest (``frame_transform`` or a reference image's transform), or the
mean over the images of ``F_i = (T_i^R)^-1 o T_i^C`` (:func:`itk_nrreval.frame.frame_estimate`),
one task per image (:func:`_estimate_task`), added up as the tasks finish
(:class:`_MeanOfEstimates`); and how far each estimate lies from F (its spread, reported).
Here too: F read back from its description (:func:`frame_transform`) and the mask carried
into a registration's reference frame (:func:`registration_mask`).
"""

from __future__ import annotations

import collections
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import SimpleITK as sitk

from .._cache import DiskCache, digest_of
from .._images import Geometry
from ..frame import (
    FrameMapping,
    distance_sums,
    frame_estimate,
    frame_method,
    from_steps,
    in_steps,
    points_minus_grid,
    resample_onto,
)
from ..manifest import Manifest
from ..transforms import chain_transform, field_transform, invert
from ._task_keys import TaskContext, task_key
from ._tasks import NOT_KEYED, Task, cached

#: How the frame estimates ``F_i(p) - p`` (mm) are cached for their spread, until it is
#: kept: ``np.uint16``, each vector component in 65535 equal steps between its least and
#: largest value (54 MB at 1 mm, a quarter of float64: a registration's N estimates are the
#: largest thing the cache holds at once), within half a step, ``(max - min) / 131070`` mm
#: (8e-4 mm over a 100 mm range; the coarse inverse's own error is about 1e-2 mm,
#: ``frame.ESTIMATE_FIELD_STEP``); or a float dtype, stored as that
#: (:func:`_stored_estimate`). The mean F is added up from the estimates as F is stored
#: (``_STORED_FRAME``), each removed once added (:class:`_MeanOfEstimates`).
_STORED_ESTIMATE = np.uint16

#: The dtype of the frame F (mean of the estimates, ``F(p) - p``, mm) in the cache, and of
#: the estimates it is added up from: float32 halves the entries (216 -> 108 MB at 1 mm)
#: and rounds a displacement of up to 100 mm by less than 1e-5 mm.
_STORED_FRAME = np.float32


def frame_transform(spec: tuple, grid: Geometry, cache: DiskCache) -> sitk.Transform:
    """F from its description: ("identity",), ("chain", item) or ("field", key)."""
    if spec[0] == "identity":
        return sitk.TranslationTransform(grid.dimension)
    if spec[0] == "chain":
        return chain_transform(spec[1])
    disp = cache.open("frame", spec[1]).array("disp")
    img = sitk.GetImageFromArray(disp, isVector=True)
    grid.apply_to(img)
    return field_transform(img)


def registration_frame(executor, ctx, disk, m: Manifest, name, reg_grid, counts, progress):
    """F for registration `name`: its task description, the digest of that, its FrameMapping."""
    reg = m.registrations[name]
    common_items = m.registrations[m.common_frame].transforms
    if name == m.common_frame:
        spec = ("identity",)
        f = frame_transform(spec, ctx.grid, disk)
        return spec, digest_of([spec[0], spec[1:]]), FrameMapping(name, "common", f, 0.0, 0.0)
    method = frame_method(reg)
    if method == "frame_transform":
        spec = ("chain", reg.frame_transform)
    elif method == "reference_index":
        spec = ("chain", common_items[reg.reference_index])
    else:
        spec = None
    calls = [(ctx, common_items[i], reg.transforms[i], reg_grid) for i in range(m.n_images)]
    keys = [""] * m.n_images
    # on the workers: a key digests its transform files' content (kept per process)
    for i, key in executor.map(_estimate_key, calls, desc=f"{name}: frame", progress=False):
        keys[i] = key
    frame_key = task_key("frame", keys) if spec is None else None
    spread_key = task_key("frame_spread", keys, spec, ctx.mask_key)
    kept = disk.get("frame_spread", spread_key)
    reused = kept is not None and (frame_key is None or disk.get("frame", frame_key) is not None)
    if reused:  # F and its spread outlive the per-image estimates they were made from
        for _ in keys:
            counts.add(True)
    else:
        for_mean = frame_key is not None
        tasks = [
            (ctx, keys[i], common_items[i], reg.transforms[i], reg_grid, for_mean)
            for i in range(m.n_images)
        ]
        mean = _MeanOfEstimates(disk, keys) if for_mean else None
        for i, was_cached in executor.map(
            _estimate_task, tasks, desc=f"{name}: frame", progress=progress
        ):
            counts.add(was_cached)
            if mean is not None:
                mean.arrived(i)
        if mean is not None and disk.get("frame", frame_key) is None:
            disk.put("frame", frame_key, {"disp": mean.result().astype(_STORED_FRAME)})
    if frame_key is not None:
        spec = ("field", frame_key)
    digest = digest_of([spec[0], spec[1:]])
    f = frame_transform(spec, ctx.grid, disk)
    if reused:
        spread = kept.meta
    else:
        spread = _frame_spread(executor, ctx, disk, keys, f, digest, progress, name)
        disk.put("frame_spread", spread_key, {}, spread)
        # The estimates are full-grid fields, a registration's N of them the largest thing
        # in the cache, and nothing else reads them: a rerun takes F and its spread from
        # their own entries.
        for k in keys:
            disk.remove("estimate_steps", k)
            disk.remove("estimate", k)
    return (
        spec,
        digest,
        FrameMapping(
            name,
            method,
            f,
            spread["mean_mm"],
            spread["max_mm"],
            tuple(spread["per_image_mm"]),
        ),
    )


def registration_mask(
    disk: DiskCache,
    ctx: TaskContext,
    mask: np.ndarray | None,
    frame: FrameMapping,
    frame_digest: str,
    reg_grid: Geometry,
) -> str | None:
    """Cache the mask carried into the registration's reference frame
    (:class:`RegistrationMask`); return its key. None without a mask."""
    if mask is None:
        return None
    task = RegistrationMask(
        mask_key=ctx.mask_key,
        frame_digest=frame_digest,
        grid=ctx.grid,
        reg_grid=reg_grid,
        mask=mask,
        frame=frame,
    )
    key, _meta, _reused = cached(task, disk)
    return key


@dataclass(frozen=True)
class RegistrationMask(Task):
    """The mask carried into a registration's reference frame: ``mask``, bool over
    `reg_grid` (flattened, numpy order).

    The mask lives on the common grid `grid` (stored under `mask_key`, the array `mask`); a
    registration's transforms are defined on its own reference grid, where the plausibility
    measures are taken. A reference voxel q is inside when ``F^-1(q)`` falls in the mask
    (nearest neighbour), F the registration's frame (`frame`; its content `frame_digest`).
    """

    kind: ClassVar[str] = "reg_mask"
    mask_key: str | None
    frame_digest: str
    grid: Geometry
    reg_grid: Geometry
    mask: np.ndarray = field(metadata=NOT_KEYED, compare=False, repr=False)
    frame: FrameMapping = field(metadata=NOT_KEYED, compare=False, repr=False)

    def compute(self, cache: DiskCache) -> tuple[dict, dict]:
        img = sitk.GetImageFromArray(self.mask.astype(np.uint8))
        self.grid.apply_to(img)
        back = sitk.TranslationTransform(self.grid.dimension)
        if self.frame.method != "common":
            back = invert(self.frame.transform, grid=self.grid)
        res = resample_onto(img, back, self.reg_grid, sitk.sitkNearestNeighbor)
        return {"mask": sitk.GetArrayFromImage(res).reshape(-1).astype(bool)}, {}


def _estimate_key(ctx: TaskContext, common_item, item, reg_grid: Geometry) -> str:
    return task_key(
        "estimate", ctx.grid, common_item, item, reg_grid, np.dtype(_STORED_ESTIMATE).str
    )


def _estimate_task(
    ctx: TaskContext, key: str, common_item, item, reg_grid: Geometry, for_mean: bool
) -> bool:
    """Cache ``F_i(p) - p`` on the common grid (mm) under `key` (:func:`_estimate_key`):
    in 16-bit steps for the spread (kind ``"estimate_steps"``, :func:`_stored_estimate`)
    and, `for_mean`, as F is stored (kind ``"estimate"``, ``_STORED_FRAME``) for the mean,
    which the driver adds up and removes as the tasks finish (:class:`_MeanOfEstimates`).
    Return whether it was cached already."""
    cache = ctx.cache()
    if cache.get("estimate_steps", key) is not None and (
        not for_mean or cache.get("estimate", key) is not None
    ):
        return True
    # the chains read where they are used: a composite held here too would keep a second
    # copy of its fields (0.2 GB at 1 mm) while the inverse and the sampling hold its pieces
    disp = frame_estimate(common_item, item, ctx.grid, other_grid=reg_grid)
    cache.put("estimate_steps", key, _stored_estimate(disp))
    if for_mean:
        cache.put("estimate", key, {"disp": disp.astype(_STORED_FRAME)})
    return False


def _stored_estimate(disp: np.ndarray) -> dict[str, np.ndarray]:
    """The arrays of a frame estimate's entry for the spread (``_STORED_ESTIMATE``):
    ``disp``, and when in steps, ``low`` and ``step`` (dim,)
    (:func:`~itk_nrreval.frame.in_steps`; :func:`_estimate_values`). A field that is not
    finite everywhere is stored as float32."""
    stored = np.dtype(_STORED_ESTIMATE)
    steps = in_steps(disp, levels=int(np.iinfo(stored).max)) if stored.kind == "u" else None
    if steps is None:
        return {"disp": disp.astype(np.float32 if stored.kind == "u" else stored)}
    q, low, step = steps
    return {"disp": q, "low": low, "step": step}


def _estimate_values(entry) -> np.ndarray:
    """A frame estimate's ``F_i(p) - p`` (mm, float64) from its entry for the spread."""
    disp = entry.array("disp")
    if entry.has("step"):
        return from_steps(disp, entry.array("low"), entry.array("step"))
    return np.asarray(disp, np.float64)


class _MeanOfEstimates:
    """The mean of a registration's frame estimates ``F_i(p) - p``, added up in float64 in
    image order (whatever order the tasks finish in: the same bits as adding them up after
    the last) as they arrive; each estimate's ``"estimate"`` entry goes once added, so that
    only the few that arrived before an earlier one are on disk at once."""

    def __init__(self, disk: DiskCache, keys: Sequence[str]):
        self._disk, self._keys = disk, list(keys)
        self._total: np.ndarray | None = None
        self._arrived: set[int] = set()
        self._next = 0
        # images with the same inputs share an entry: it goes when the last is added
        self._uses = collections.Counter(self._keys)

    def arrived(self, i: int) -> None:
        """Estimate i is in the cache: add it, and every later one already there, in order."""
        self._arrived.add(i)
        while self._next in self._arrived:
            key = self._keys[self._next]
            est = self._disk.open("estimate", key).array("disp", mmap=True)
            if self._total is None:
                self._total = np.zeros(est.shape, np.float64)
            self._total += est
            del est
            self._uses[key] -= 1
            if not self._uses[key]:
                self._disk.remove("estimate", key)
            self._next += 1

    def result(self) -> np.ndarray:
        """F(p) - p (float64, mm), once every estimate has arrived."""
        if self._next != len(self._keys):
            raise RuntimeError(f"frame: {self._next} of {len(self._keys)} estimates arrived")
        return self._total / len(self._keys)


def _frame_spread(executor, ctx, disk, keys, f, digest, progress, name) -> dict:
    """How far each image's estimate `keys` lies from F (`f`): ``{"mean_mm", "max_mm",
    "per_image_mm"}`` over the mask (mm)."""
    # F(p) - p on the common grid, once, for every image's spread task; dropped after
    disp_key = task_key("frame_disp", ctx.grid, digest)
    if disk.get("frame_disp", disp_key) is None:
        disk.put("frame_disp", disp_key, {"disp": points_minus_grid(f, ctx.grid)})
    calls = [(ctx, k, disp_key) for k in keys]
    parts = [(0.0, 0.0, 0)] * len(keys)
    for i, part in executor.map(
        _spread_task, calls, desc=f"{name}: frame spread", progress=progress
    ):
        parts[i] = part
    disk.remove("frame_disp", disp_key)
    count = sum(part[2] for part in parts)
    return {
        "mean_mm": math.fsum(part[0] for part in parts) / count if count else math.nan,
        "max_mm": max(part[1] for part in parts) if count else math.nan,
        "per_image_mm": [part[0] / part[2] if part[2] else math.nan for part in parts],
    }


def _spread_task(ctx: TaskContext, key: str, frame_disp_key: str) -> tuple[float, float, int]:
    """Sum and max over the mask of ``|F_i(p) - F(p)|`` (mm), and the voxel count."""
    cache = ctx.cache()
    est = _estimate_values(cache.open("estimate_steps", key))
    f_disp = cache.open("frame_disp", frame_disp_key).array("disp")
    return distance_sums(est, f_disp, ctx.mask_flat())
