"""The common frame F of each registration: its description, its tasks and their keys.

A registration that is not the common one is brought into the common frame by ``F``:
a transform of the manifest (``frame_transform`` or a reference image's transform:
:func:`given_frame`), or the mean over the images of ``F_i = (T_i^R)^-1 o T_i^C``
(:func:`itk_nrreval.io.frame.frame_estimate`), one task per image (:class:`EstimateFrame`,
listed by :func:`estimate_plan`), added up as the tasks finish (:class:`MeanOfEstimates`,
its entry under :class:`FrameMean`'s key); and how far each estimate lies from F (its
spread, reported: :func:`frame_spread`, from F(p) - p, :class:`FrameDisplacement`; its
entry under :class:`FrameSpread`'s key). The driver runs the tasks and these reductions.
Here too: F read back from its description (:func:`frame_transform`) and the mask carried
into a registration's reference frame (:class:`RegistrationMask`).
"""

from __future__ import annotations

import collections
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import SimpleITK as sitk

from ..io._cache import DiskCache, digest_of
from ..io._images import Geometry
from ..io.frame import (
    FrameMapping,
    distance_sums,
    frame_estimate,
    frame_method,
    from_steps,
    in_steps,
    points_minus_grid,
    resample_onto,
)
from ..io.manifest import Manifest
from ..io.transforms import chain_transform, field_transform, invert
from ._task_keys import TaskContext
from ._tasks import NOT_KEYED, Entry, Keyed, Task, cached

#: How the frame estimates ``F_i(p) - p`` (mm) are cached for their spread, until it is
#: kept: ``np.uint16``, each vector component in 65535 equal steps between its least and
#: largest value (54 MB at 1 mm, a quarter of float64: a registration's N estimates are the
#: largest thing the cache holds at once), within half a step, ``(max - min) / 131070`` mm
#: (8e-4 mm over a 100 mm range; the coarse inverse's own error is about 1e-2 mm,
#: ``frame.ESTIMATE_FIELD_STEP``); or a float dtype, stored as that
#: (:func:`_stored_estimate`). The mean F is added up from the estimates as F is stored
#: (``_STORED_FRAME``), each removed once added (:class:`MeanOfEstimates`).
_STORED_ESTIMATE = np.uint16

#: The dtype of the frame F (mean of the estimates, ``F(p) - p``, mm) in the cache, and of
#: the estimates it is added up from: float32 halves the entries (216 -> 108 MB at 1 mm)
#: and rounds a displacement of up to 100 mm by less than 1e-5 mm.
_STORED_FRAME = np.float32

#: The kinds of entry of a frame estimate (:class:`EstimateFrame`): for the spread, and for
#: the mean.
ESTIMATE_ENTRIES = ("estimate_steps", "estimate")


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


def given_frame(m: Manifest, name: str) -> tuple | None:
    """F of registration `name` where the manifest gives it, as :func:`frame_transform`
    reads it: ``("identity",)`` for the common frame, ``("chain", item)`` for a
    ``frame_transform`` or a reference image's transform; None when F is the mean of the
    images' estimates (:class:`EstimateFrame`)."""
    if name == m.common_frame:
        return ("identity",)
    reg = m.registrations[name]
    method = frame_method(reg)
    if method == "frame_transform":
        return ("chain", reg.frame_transform)
    if method == "reference_index":
        return ("chain", m.registrations[m.common_frame].transforms[reg.reference_index])
    return None


def digest_of_frame(spec: tuple) -> str:
    """The digest of F's description `spec` (an estimated F's holds its entry's key, a
    digest of its inputs): what the tasks that read F are keyed by."""
    return digest_of([spec[0], spec[1:]])


def estimate_plan(
    ctx: TaskContext, m: Manifest, name: str, reg_grid: Geometry, *, for_mean: bool
) -> list[EstimateFrame]:
    """Every image's estimate of registration `name`'s frame (:class:`EstimateFrame`), in
    image order: for its spread, and `for_mean`, for F itself."""
    reg = m.registrations[name]
    common_items = m.registrations[m.common_frame].transforms
    return [
        EstimateFrame(
            grid=ctx.grid,
            common_item=common_items[i],
            item=reg.transforms[i],
            reg_grid=reg_grid,
            stored=np.dtype(_STORED_ESTIMATE).str,
            for_mean=for_mean,
        )
        for i in range(m.n_images)
    ]


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


@dataclass(frozen=True)
class EstimateFrame(Task):
    """One image's estimate of the frame F, ``F_i(p) - p = (T_i^R)^-1 o T_i^C (p) - p``
    (:func:`~itk_nrreval.io.frame.frame_estimate`), (*grid.shape, dim) in mm over the common
    grid `grid`: `common_item` is the image's transform in the common registration,
    `item` in this one (defined on its reference grid `reg_grid`).

    Stored as `stored` (the dtype of :func:`_stored_estimate`: 16-bit steps) for the
    spread, an entry of kind ``"estimate_steps"``, and, `for_mean`, as F is stored
    (``_STORED_FRAME``, float32) for the mean, kind ``"estimate"``: the driver adds those up
    and removes them as the tasks finish (:class:`MeanOfEstimates`). Both under the one
    key of kind ``"estimate"``; `for_mean` only says which entries to keep (not keyed).
    """

    kind: ClassVar[str] = "estimate"
    grid: Geometry
    common_item: Any
    item: Any
    reg_grid: Geometry
    stored: str
    for_mean: bool = field(default=False, metadata=NOT_KEYED)

    def entry_kinds(self) -> tuple[str, ...]:
        return ESTIMATE_ENTRIES if self.for_mean else ESTIMATE_ENTRIES[:1]

    def compute_entries(self, cache: DiskCache) -> dict[str, Entry]:
        # the chains read where they are used: a composite held here too would keep a
        # second copy of its fields (0.2 GB at 1 mm) while the inverse and the sampling
        # hold its pieces
        disp = frame_estimate(self.common_item, self.item, self.grid, other_grid=self.reg_grid)
        out = {"estimate_steps": (_stored_estimate(disp, self.stored), {})}
        if self.for_mean:
            out["estimate"] = ({"disp": disp.astype(_STORED_FRAME)}, {})
        return out


@dataclass(frozen=True)
class FrameMean(Keyed):
    """The key of the mean frame F (kind ``"frame"``: ``disp``, F(p) - p in mm,
    (*grid.shape, dim), ``_STORED_FRAME``): the mean of the estimates `estimates` (their
    keys, in image order), which the driver adds up as they arrive
    (:class:`MeanOfEstimates`)."""

    kind: ClassVar[str] = "frame"
    estimates: tuple[str, ...]


@dataclass(frozen=True)
class FrameSpread(Keyed):
    """The key of how far each estimate `estimates` lies from F (kind ``"frame_spread"``,
    metadata ``{"mean_mm", "max_mm", "per_image_mm"}``), inside the mask `mask_key`: F is
    the mean of the estimates when `frame` is None, else the transform `frame` describes
    (:func:`frame_transform`)."""

    kind: ClassVar[str] = "frame_spread"
    estimates: tuple[str, ...]
    frame: tuple | None
    mask_key: str | None


@dataclass(frozen=True)
class FrameDisplacement(Task):
    """F(p) - p (mm, (*grid.shape, dim), float64) on the common grid `grid`, for every
    image's spread (kind ``"frame_disp"``: ``disp``); F's content is `frame_digest`, its
    transform `transform` (not keyed)."""

    kind: ClassVar[str] = "frame_disp"
    grid: Geometry
    frame_digest: str
    transform: sitk.Transform = field(metadata=NOT_KEYED, compare=False, repr=False)

    def compute(self, cache: DiskCache) -> Entry:
        return {"disp": points_minus_grid(self.transform, self.grid)}, {}


def _stored_estimate(disp: np.ndarray, stored: str | None = None) -> dict[str, np.ndarray]:
    """The arrays of a frame estimate's entry for the spread, as `stored` (a dtype; default
    ``_STORED_ESTIMATE``): ``disp``, and when in steps, ``low`` and ``step`` (dim,)
    (:func:`~itk_nrreval.io.frame.in_steps`; :func:`_estimate_values`). A field that is not
    finite everywhere is stored as float32."""
    stored = np.dtype(_STORED_ESTIMATE if stored is None else stored)
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


class MeanOfEstimates:
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

    def stored(self) -> dict[str, np.ndarray]:
        """The frame's entry (:class:`FrameMean`): ``disp``, :meth:`result` as the cache
        holds F (``_STORED_FRAME``)."""
        return {"disp": self.result().astype(_STORED_FRAME)}


def frame_spread(
    executor, ctx: TaskContext, disk: DiskCache, keys: Sequence[str], f: sitk.Transform,
    digest: str, *, desc: str, progress: bool,
) -> dict:  # fmt: skip
    """How far each image's estimate (the ``estimate_steps`` entries `keys`) lies from F
    (`f`, its content `digest`): ``{"mean_mm", "max_mm", "per_image_mm"}`` over the mask
    (mm; :class:`FrameSpread`'s metadata). A reduction: F(p) - p once
    (:class:`FrameDisplacement`, dropped after), then each image's sums on `executor`."""
    # F(p) - p on the common grid, once, for every image's spread task; dropped after
    disp_key, _meta, _reused = cached(
        FrameDisplacement(grid=ctx.grid, frame_digest=digest, transform=f), disk
    )
    calls = [(ctx, k, disp_key) for k in keys]
    parts = [(0.0, 0.0, 0)] * len(keys)
    for i, part in executor.map(_spread_task, calls, desc=desc, progress=progress):
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
