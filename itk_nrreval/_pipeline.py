"""The evaluate dataflow, written once: per-image tasks, per-voxel-block sums, the driver.

:func:`itk_nrreval.evaluate` runs here, in this process by default or on a Dask cluster
(:mod:`itk_nrreval._scaleout`); both run the same task functions, the executor only maps
them. The work is cut so that no process holds the N x n data (N images, n voxels):

1. **per image** (N tasks per registration): the frame estimate ``F_i`` (registrations
   other than the common one); the transform's measures (which voxels of the common grid
   it brings the image's field of view to, and the deformation's plausibility,
   :mod:`itk_nrreval.plausibility`, on the registration's own reference grid); then, once
   every transform is measured and the region every image covers under every
   registration is known, registration by registration: the image resampled into the
   common frame, its fuzzy label memberships (sparse: the voxels where each label is
   nonzero) and the per-image sums the overlap needs (label gradients, presence). Each
   result is written to a disk cache under a digest of everything it depends on (input
   file contents, transforms, the frame, grid, mask, settings, and the code version: the
   package's and the task's, ``_TASK_VERSIONS``; :mod:`itk_nrreval._cache`), so a rerun
   -- after an interruption, or with more images or registrations -- finds it there
   instead of recomputing it. A registration's resampled images leave the cache once its
   scores are taken (unless kept: ``keep_resampled``), so that the cache holds one
   registration's images at a time;
2. **per voxel block** (a few tasks per registration): every image's block is read back
   (memory-mapped) to add that block's share of the N x N Gram matrix of the centred
   images, the mean image, and the overlap pair sums per label;
3. **on the driver**: the blocks' sums are added up in block order (so the numbers do not
   depend on the order tasks finish in); the texture model comes from the Gram matrix
   (:meth:`TextureModel.from_gram`), specificity and generalization from the model, the
   overlap from its per-label sums (:meth:`OverlapTable.from_sums`).

Peak memory is therefore independent of N apart from the N x N Gram matrix: one image
and its memberships per task, one voxel block of all N images (``_BLOCK_BYTES``) per
reduction, one mean image per registration on the driver. The cache folder must be visible
to the driver and every worker (a shared filesystem on a cluster).
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import functools
import math
import tempfile
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import SimpleITK as sitk

from . import _version
from ._brain_masks import BrainMaskDice, resample_mask, subject_mask_dice
from ._cache import DiskCache, digest_of
from ._errors import InputError, readable
from ._evaluation_options import Execution, Resampling
from ._executors import Executor
from ._images import (
    Geometry,
    InMemoryImage,
    label_like_values,
    mask_array,
    read_header,
    read_image,
    warn_label_like,
)
from ._memberships import (
    SparseMemberships,
    covered_voxels,
    resample_image_and_memberships,
    resample_label_memberships,
    shares_grid,
)
from ._output import json_number
from ._overlap_kernels import membership_gradient_sum, membership_pair_sums
from ._resampled_images import ResampledImages, image_slice, stored_memberships, thumbnails
from .frame import (
    FrameMapping,
    common_reference,
    distance_sums,
    frame_estimate,
    frame_method,
    from_steps,
    in_steps,
    label_values,
    points_minus_grid,
    resample_images,
    resample_onto,
    resampling_transform,
)
from .label_metrics import LabelMetrics, crisp_labels, directed_percentiles, label_surfaces
from .manifest import Manifest
from .model import TextureModel
from .overlap import OverlapTable
from .plausibility import AffineFit, Plausibility, SubjectThresholds, deformation_measures
from .specificity import GeneralizationResult, SpecificityResult, texture_measures
from .subject_qc import SubjectQC, ranked, reference_subject
from .transforms import (
    PointMap,
    TransformPieces,
    chain_transform,
    displacement_array,
    displacement_field,
    field_transform,
    flatten,
    has_only_fields,
    invert,
    transform_pieces,
)

__all__ = [
    "Coverage",
    "ReducedRegistration",
    "PipelineRun",
    "run_pipeline",
]

_FORMAT = 7  # bump when what a cache entry holds changes
#: The computation version of each cached task: bump a task's number whenever what it
#: computes changes (a fix, a new default), so that entries computed the old way are never
#: reused. Every key also holds the package version (:func:`_task_key`).
_TASK_VERSIONS = {
    "estimate": 4,  # 2: a coarse, refined inverse; stored float32 (issue 30)
    # 3: the coarse inverse refined at the common grid's points (issue 30)
    # 4: float32 for the mean until added up, 16-bit steps for the spread (issue 30)
    "frame": 2,  # 2: stored float32, as its estimates (issue 30)
    "frame_disp": 1,
    "frame_spread": 3,  # the spread of the estimates of F (issue 30); 2: per image (issue 27)
    # 3: from estimates in 16-bit steps (issue 30)
    "reg_mask": 1,
    "resampled": 5,  # 2: inverse consistency no longer read from freed memory (issue 25)
    # 3: the transform's closest affine map (issue 27)
    # 4: inverse consistency from a coarse, refined inverse on every second voxel; float32
    # image, uint32 label indices (issue 30)
    # 5: inverse consistency refined at the round trip's points; the image from the
    # memberships' sampling of the transform (issue 30)
    # 6: the transform's measures in their own entry, "measures" (issue 30)
    "measures": 2,  # coverage and plausibility, before any image is resampled (issue 30)
    # 2: the non-diffeomorphic fraction and volume (issue 42)
    "label_sums": 1,
    "brain_mask": 1,  # a subject's brain mask in the common frame (issue 42)
    "crisp_labels": 1,  # a subject's crisp label map and label boundaries (issue 45)
    "label_distances": 1,  # its Dice counts and directed HD95 against others (issue 45)
}
_BLOCK_BYTES = 1 << 26  # float64 bytes of one voxel block over all N images (64 MiB)
#: The dtype of the resampled images in the cache: float32 halves the entries (68 -> 34 MB at
#: 1 mm) and changes the scores by parts in 1e7 (the reductions add up in float64;
#: tests/test_pipeline.py bounds it against float64 entries).
_STORED_IMAGE = np.float32
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
#: Bytes of changed images (float64, over the region) the subject checks of
#: :func:`_alternative_products` hold at once: 64 alternatives of a 1 mm brain region would
#: otherwise take 2.5 GB.
ALTERNATIVE_CHUNK_BYTES = 256 * 2**20


def _task_key(kind: str, *parts) -> str:
    """The cache key of a `kind` entry: its code version and `parts`.

    `parts` must hold every input and every option the entry's result depends on.
    """
    return digest_of([kind, _FORMAT, _version.__version__, _TASK_VERSIONS[kind], *parts])


# ----------------------------------------------------------------------------- tasks


@dataclass(frozen=True)
class _Context:
    """What every task of one run needs (small; pickled into each task on a cluster)."""

    root: str
    grid: Geometry
    mask_key: str | None
    inverse_consistency: bool = True

    def cache(self) -> DiskCache:
        return DiskCache(self.root)

    def mask_flat(self) -> np.ndarray | None:
        """The mask over the flattened grid (numpy order), or None."""
        if self.mask_key is None:
            return None
        return self.cache().open("mask", self.mask_key).array("mask")


def _frame_transform(spec: tuple, grid: Geometry, cache: DiskCache) -> sitk.Transform:
    """F from its description: ("identity",), ("chain", item) or ("field", key)."""
    if spec[0] == "identity":
        return sitk.TranslationTransform(grid.dimension)
    if spec[0] == "chain":
        return chain_transform(spec[1])
    disp = cache.open("frame", spec[1]).array("disp")
    img = sitk.GetImageFromArray(disp, isVector=True)
    grid.apply_to(img)
    return field_transform(img)


def _estimate_key(ctx: _Context, common_item, item, reg_grid: Geometry) -> str:
    return _task_key(
        "estimate", ctx.grid, common_item, item, reg_grid, np.dtype(_STORED_ESTIMATE).str
    )


def _estimate_task(
    ctx: _Context, key: str, common_item, item, reg_grid: Geometry, for_mean: bool
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


def _spread_task(ctx: _Context, key: str, frame_disp_key: str) -> tuple[float, float, int]:
    """Sum and max over the mask of ``|F_i(p) - F(p)|`` (mm), and the voxel count."""
    cache = ctx.cache()
    est = _estimate_values(cache.open("estimate_steps", key))
    f_disp = cache.open("frame_disp", frame_disp_key).array("disp")
    return distance_sums(est, f_disp, ctx.mask_flat())


def _measures_task(
    ctx: _Context,
    image: Path,
    item,
    frame: tuple,
    frame_digest: str,
    reg_grid: Geometry,
    reg_mask_key: str | None,
) -> tuple[str, bool, dict]:
    """One image's transform, measured without resampling the image; cache it.

    The entry holds ``covered``: the common-grid voxels that ``T_i^R o F`` maps into the
    image's field of view (``np.packbits`` of a bool (n,); ITK's decisions,
    :func:`~itk_nrreval._memberships.covered_voxels`, where the resampled image has a
    value), and ``detj_middle`` (float32: det J on the middle slice of `reg_grid`, NaN
    outside its mask, for the report). Its metadata holds the fraction of the mask (or grid)
    covered, the deformation's plausibility measures and the transform's closest affine map
    (:func:`~itk_nrreval.plausibility.affine_fit`, from the same sampling of the transform:
    ``deformation_measures(..., affine=True)``) on the registration's reference grid
    `reg_grid` (inside the mask mapped there, `reg_mask_key`), and the fixed-bin counts of
    log det J over the same voxels (``log_jacobian_histogram``).

    Every image's coverage is known before any image is resampled, so each registration's
    resampled images can leave the cache once its scores are taken (:func:`run_pipeline`).
    """
    cache = ctx.cache()
    g = ctx.grid
    key = _task_key(
        "measures",
        g,
        ctx.mask_key,
        image,
        item,
        frame_digest,
        reg_grid,
        reg_mask_key,
        ctx.inverse_consistency,
    )
    entry = cache.get("measures", key)
    if entry is not None:
        return key, True, dict(entry.meta)
    pieces = transform_pieces(item)
    # with F the identity on T's own grid, T's displacement on the whole common grid (an
    # array) also serves the plausibility
    full, sampled = _sampling(pieces, frame, g, reg_grid, cache, one_sampling=True, whole=True)
    covered = covered_voxels(_image_grid(image), full, g, displacement=sampled)
    mask = ctx.mask_flat()
    inside = covered[mask] if mask is not None else covered
    arrays = {"covered": np.packbits(covered)}
    meta: dict = {"coverage": float(inside.mean()) if inside.size else 0.0}
    shared = sampled if isinstance(sampled, np.ndarray) else None  # T's own on g
    del covered, inside, full
    if shared is None:  # freed before the plausibility samples T on its own grid
        sampled = None
    reg_mask = None
    if reg_mask_key is not None:
        reg_mask = cache.open("reg_mask", reg_mask_key).array("mask").reshape(reg_grid.shape)
    # the affine fit from the measures' own sampling of the transform (one pass, not two)
    measures = deformation_measures(
        pieces,
        reg_grid,
        mask=reg_mask,
        inverse_consistency=ctx.inverse_consistency,
        affine=True,
        displacement=shared,
    )
    del shared, sampled, pieces
    # for the report: one slice, det J on reg_grid
    arrays["detj_middle"] = measures.jacobian.middle
    meta.update(
        plausibility=measures.plausibility.to_dict(),
        affine_fit=measures.affine.to_dict(),
        log_jacobian_histogram=measures.jacobian.histogram(),
    )
    cache.put("measures", key, arrays, meta)
    return key, False, meta


def _image_grid(image) -> Geometry:
    """An image's grid from its header (a manifest's in-memory image: its own)."""
    if isinstance(image, InMemoryImage):
        return Geometry.from_image(image.image)
    return Geometry.from_image(read_header(image))


def _resample_task(
    ctx: _Context,
    image: Path,
    labels: Path | None,
    item,
    frame: tuple,
    frame_digest: str,
    reg_grid: Geometry,
    interpolation: str,
    own_values: Sequence[int] | None,
    label_resampling: tuple[str, float | None] = ("linear", None),
) -> tuple[str, bool, dict]:
    """Resample one image (and its label memberships) into the common frame; cache it.

    The entry holds ``image`` (n,) over the whole grid (``_STORED_IMAGE``, float32; 0 outside
    the image's field of view), ``covered`` (the voxels inside that field of view,
    ``np.packbits`` of a bool (n,)), and for the labels the nonzero memberships of the image's
    own nonzero label values, in compressed form: ``lab_ptr`` (K + 1,), ``lab_idx`` (flat
    voxel indices, ascending per label; uint32 below 2**32 voxels, else int64), ``lab_val``
    (float32). Its metadata holds the label values and the image's label-like values
    (:func:`~itk_nrreval._images.label_like_values`). `own_values` are the label map's own
    nonzero values (found once by the driver); `label_resampling` is ``(method, sigma_mm)``
    of :func:`~itk_nrreval._memberships.resample_label_memberships`. `reg_grid`, the
    registration's reference grid, only says whether T's displacement on the common grid
    can be sampled whole (:func:`_sampling`). The transform's measures are
    :func:`_measures_task`'s.
    """
    cache = ctx.cache()
    g = ctx.grid
    key = _task_key(
        "resampled",
        g,
        image,
        labels,
        item,
        frame_digest,
        reg_grid,
        interpolation,
        list(label_resampling),
        np.dtype(_STORED_IMAGE).str,
    )
    entry = cache.get("resampled", key)
    if entry is not None:
        return key, True, dict(entry.meta)
    pieces = transform_pieces(item)
    raw = read_image(image, what="image")
    lab = None if labels is None else read_image(labels, what="label map")
    own = None if labels is None else [int(v) for v in own_values]
    one_sampling = _shares_sampling(raw, lab, interpolation, label_resampling[0])
    full, sampled = _sampling(pieces, frame, g, reg_grid, cache, one_sampling=one_sampling)
    del pieces  # `full` holds them where it needs them
    values, memb = _resampled_image_and_memberships(
        raw,
        lab,
        full,
        g,
        interpolation=interpolation,
        values=own,
        labels=label_resampling,
        one_sampling=one_sampling,
        displacement=sampled,
    )
    del full, sampled
    covered = ~np.isnan(values)  # inputs are checked finite, so NaN marks outside only
    values[~covered] = 0.0
    arrays = {"image": values.astype(_STORED_IMAGE), "covered": np.packbits(covered)}
    meta: dict = {"label_like": label_like_values(raw)}
    if memb is not None:
        # flat voxel indices fit 32 bits below 4 G voxels (half the bytes of int64)
        index = memb.index.astype(np.uint32) if values.size < 2**32 else memb.index
        arrays.update(lab_ptr=memb.ptr, lab_idx=index, lab_val=memb.weight)
        meta.update(labels=own)
    cache.put("resampled", key, arrays, meta)
    return key, False, meta


def _sampling(
    pieces: TransformPieces, frame: tuple, g: Geometry, reg_grid: Geometry,
    cache: DiskCache, *, one_sampling: bool, whole: bool = False,
) -> tuple:  # fmt: skip
    """Image i's transform from the common frame, ``T_i^R o F`` (:func:`resampling_transform`),
    T given as its pieces (:func:`~itk_nrreval.transforms.transform_pieces`), and, where one
    sampling of it on the common grid `g` serves more than one use (`one_sampling`), that
    sampling: ``(transform, sampling or None)``; otherwise the memberships sample the
    transform slab by slab.

    When T is linear maps and displacement fields, the compiled kernels sample it (to about
    1e-13 mm of ITK's): a slab of `g` at a time, as a
    :class:`~itk_nrreval.transforms.PointMap` of T after F's displacement (F a field the
    pipeline estimated, frame ``("field", key)``, read from its cache entry) or after none
    (F the identity); with `whole`, F the identity and T on the common grid, as T's
    displacement on the whole grid, which also serves the plausibility. The transform
    returned with it is then a function that gives ``T_i^R o F`` as its pieces, called only
    if ITK's own decisions are needed at a buffer's border: ITK maps those points piece by
    piece, and builds the composite, which copies every field (0.1 to 0.25 s and 0.2 GB
    per 1 mm field), only to resample the whole grid.
    """

    def from_common() -> TransformPieces:
        return resampling_transform(pieces, _frame_transform(frame, g, cache))

    if one_sampling and has_only_fields(pieces):
        if frame[0] == "field":
            return from_common, PointMap(pieces, cache.open("frame", frame[1]).array("disp"))
        if frame[0] == "identity" and whole and reg_grid == g:
            return from_common, displacement_array(pieces, g)
        if frame[0] == "identity":
            return from_common, PointMap(pieces)
    if one_sampling and frame[0] == "identity" and reg_grid == g:
        t = flatten(pieces)
        return t, sitk.GetArrayFromImage(displacement_field(t, g))  # F: the identity
    return flatten(from_common()), None


def _resampled_image_and_memberships(
    raw: sitk.Image,
    lab: sitk.Image | None,
    full: sitk.Transform,
    g: Geometry,
    *,
    interpolation: str,
    values: list[int] | None,
    labels: tuple[str, float | None],
    one_sampling: bool,
    displacement: np.ndarray | PointMap | None = None,
) -> tuple[np.ndarray, SparseMemberships | None]:
    """The image on `g` (flat float64, NaN outside its field of view) and the label map's
    memberships (None without one): through one sampling of `full` with `one_sampling`
    (:func:`_shares_sampling`; `displacement`, that sampling when the caller has it), else
    one resampling each."""
    method, sigma_mm = labels
    if one_sampling:
        return resample_image_and_memberships(
            raw, lab, full, g, values=values, displacement=displacement
        )
    image = resample_images(
        [raw], [full], g, interpolation=interpolation, progress=False, outside=np.nan
    )
    memb = None
    if lab is not None:
        memb = resample_label_memberships(
            lab, full, g, values=values, method=method, sigma_mm=sigma_mm
        )
    return image[0].reshape(-1), memb


def _shares_sampling(
    raw: sitk.Image, lab: sitk.Image | None, interpolation: str, label_method: str
) -> bool:
    """Whether a scalar image, and its label map if it has one, can be resampled linearly
    through one sampling of the transform by the compiled kernels
    (:func:`resample_image_and_memberships`): the image linear, the labels linear and on its
    grid."""
    if interpolation != "linear" or raw.GetNumberOfComponentsPerPixel() != 1:
        return False
    return lab is None or (label_method == "linear" and shares_grid(raw, lab))


def _label_sums_task(ctx: _Context, key: str) -> tuple[dict, bool]:
    """Per label of one resampled image: its gradient sum and its presence, in the region.

    The region is ``ctx.mask_key`` (the voxels every image covers, inside the mask). Returns
    ``({"gsum": [...], "present": [...]}, reused)``, one entry per label of the image.
    """
    cache = ctx.cache()
    sums_key = _task_key("label_sums", key, ctx.mask_key)
    found = cache.get("label_sums", sums_key)
    if found is not None:
        return dict(found.meta), True
    g = ctx.grid
    entry = cache.open("resampled", key)
    memb = stored_memberships(entry, g.shape, entry.meta["labels"])
    mask = ctx.mask_flat()
    gsum, present = [], []
    row = np.zeros(int(np.prod(g.shape)), np.float32)
    for k in range(len(memb.values)):
        idx, val = memb.label(k)
        row[idx] = val
        gsum.append(membership_gradient_sum(row, shape=g.shape, spacing=g.spacing, mask=mask))
        row[idx] = 0
        present.append(bool(mask[idx].any()) if mask is not None else bool(idx.size))
    meta = {"gsum": gsum, "present": present}
    cache.put("label_sums", sums_key, {}, meta)
    return meta, False


def _subject_pairs(subjects: Sequence[str] | None) -> np.ndarray:
    """The pairs (a, b), a < b, of images of one subject: shape (n_pairs, 2)."""
    if subjects is None:
        return np.zeros((0, 2), dtype=np.int64)
    pairs = [
        (a, b)
        for a in range(len(subjects))
        for b in range(a + 1, len(subjects))
        if subjects[a] == subjects[b]
    ]
    return np.array(pairs, dtype=np.int64).reshape(-1, 2)


def _block_task(
    ctx: _Context,
    keys: Sequence[str],
    start: int,
    stop: int,
    components: Sequence[int],
    subject_pairs: np.ndarray,
) -> dict:
    """One voxel block [start, stop) of the flattened grid, over all N images.

    Returns the block's Gram matrix of the centred masked intensities (N, N), the mean
    image on the block (stop - start,), and per label value of `components` the pair sums
    p, q (L,), per image the volume and target-overlap sums (N, L), and for each of
    `subject_pairs` (n_pairs, 2) its sum of minima (n_pairs, L), voxel units.
    """
    cache = ctx.cache()
    entries = [cache.open("resampled", k) for k in keys]
    n = len(entries)
    x = np.empty((n, stop - start))
    for i, e in enumerate(entries):
        x[i] = e.array("image", mmap=True)[start:stop]
    mask = ctx.mask_flat()
    mask = mask[start:stop] if mask is not None else None
    mean = x.mean(axis=0)
    # centred in place: one block in memory, not three (two tasks at once at 1 mm)
    if mask is not None:
        x = x[:, mask]
        x -= x.mean(axis=0)
    else:
        x -= mean
    out = {"gram": x @ x.T, "mean": mean}
    del x
    n_labels = len(components)
    p, q = np.zeros(n_labels), np.zeros(n_labels)
    vol, spair = np.zeros((n, n_labels)), np.zeros((n, n_labels))
    pair_min = np.zeros((len(subject_pairs), n_labels))
    if n_labels:
        lookups = [{v: j for j, v in enumerate(e.meta["labels"])} for e in entries]
        arrays = [
            (e.array("lab_ptr"), e.array("lab_idx", mmap=True), e.array("lab_val", mmap=True))
            for e in entries
        ]
        block = np.zeros((n, stop - start), np.float32)
        for k, value in enumerate(components):
            block[:] = 0
            for i, (ptr, idx, val) in enumerate(arrays):
                j = lookups[i].get(int(value))
                if j is None:
                    continue
                own = idx[ptr[j] : ptr[j + 1]]
                lo, hi = np.searchsorted(own, [start, stop])
                block[i, np.asarray(own[lo:hi]) - start] = val[ptr[j] + lo : ptr[j] + hi]
            p[k], q[k], vol[:, k], spair[:, k] = membership_pair_sums(block, mask=mask)
            for j, (a, b) in enumerate(subject_pairs):
                both = np.minimum(block[a], block[b])
                pair_min[j, k] = (both[mask] if mask is not None else both).sum(dtype=np.float64)
    out.update(p=p, q=q, vol=vol, spair=spair, subject_pair_min=pair_min)
    return out


# ----------------------------------------------------------------------------- the driver


@dataclass(frozen=True)
class Coverage:
    """How much of the common grid a registration's images cover (their fields of view).

    A common-grid voxel that a transform maps outside image i's field of view has no value
    in image i. The scores are therefore taken over the voxels every image covers under
    every registration (inside the mask), the same voxels for every registration so that
    their scores compare.

    Attributes
    ----------
    fraction : float
        The fraction of the mask's (or grid's) voxels covered by every image in the scores
        under this registration (images left off the grid do not count:
        :func:`off_grid_subjects`).
    per_image : tuple of float, length n_images
        Each image's covered fraction of the mask (or grid) under this registration.
    evaluated : float
        The fraction of the mask (or grid) where the scores are taken: covered by every
        image under every registration (the same for every registration of a run).
    """

    fraction: float
    per_image: tuple[float, ...]
    evaluated: float

    def to_dict(self) -> dict:
        return {
            "fraction": self.fraction,
            "evaluated": self.evaluated,
            "per_image_min": min(self.per_image) if self.per_image else None,
        }


COVERAGE_WARNING = 0.9  # warn when the scores are taken on less of the mask than this


def off_grid_subjects(resampled: Mapping, ratio: float) -> tuple[int, ...]:
    """The subjects that cover less of the common grid than `ratio` times the median
    subject, under any registration (ascending indices).

    Such a subject's transform maps it (almost) off the grid; kept, it would empty the region
    every score is taken on (:func:`_region`) for every registration.
    """
    out: set[int] = set()
    for _keys, metas, _frame in resampled.values():
        per_image = np.array([float(meta["coverage"]) for meta in metas])
        out |= set(np.flatnonzero(per_image < ratio * float(np.median(per_image))).tolist())
    return tuple(sorted(out))


def _region(
    disk: DiskCache,
    grid: Geometry,
    mask: np.ndarray | None,
    m: Manifest,
    resampled: Mapping,
    left_out: Sequence[int] = (),
) -> tuple[np.ndarray | None, dict[str, Coverage]]:
    """The voxels every image covers under every registration (inside the mask).

    Images `left_out` (:func:`off_grid_subjects`) do not restrict the region.

    Returns the region (bool, the grid's numpy shape; None when it is the whole grid and
    there is no mask) and each registration's :class:`Coverage`.
    """
    n_vox = int(np.prod(grid.shape))
    base = mask.reshape(-1).astype(bool) if mask is not None else None
    total = int(base.sum()) if base is not None else n_vox
    every = np.ones(n_vox, bool)
    fractions: dict[str, tuple[float, tuple[float, ...]]] = {}
    for name, (keys, metas, _frame) in resampled.items():
        covered = np.ones(n_vox, bool)
        for i, k in enumerate(keys):
            if i in left_out:
                continue
            bits = disk.open("measures", k).array("covered")
            covered &= np.unpackbits(bits, count=n_vox).astype(bool)
        inside = covered[base] if base is not None else covered
        per_image = tuple(float(meta["coverage"]) for meta in metas)
        fractions[name] = (float(inside.sum()) / total if total else 0.0, per_image)
        every &= covered
    region = every & base if base is not None else every
    evaluated = float(region.sum()) / total if total else 0.0
    where = "inside the mask" if mask is not None else "of the common grid"
    if not region.any():
        raise InputError(
            f"no voxel {where} is covered by every image under every registration: "
            "check the images' fields of view and the transforms"
        )
    if evaluated < COVERAGE_WARNING:
        name = min(fractions, key=lambda r: fractions[r][0])
        frac, per_image = fractions[name]
        i = min((j for j in range(len(per_image)) if j not in left_out), key=lambda j: per_image[j])
        warnings.warn(
            f"the scores are taken on the {evaluated:.0%} of the voxels {where} that every "
            f"image covers under every registration; least: registration {name!r} "
            f"({frac:.0%}), its image {m.scored_images[i]} ({per_image[i]:.0%})",
            UserWarning,
            stacklevel=4,
        )
    coverage = {
        name: Coverage(frac, per_image, evaluated) for name, (frac, per_image) in fractions.items()
    }
    if base is None and region.all():
        return None, coverage
    return region.reshape(grid.shape), coverage


@dataclass(frozen=True)
class ReducedRegistration:
    """One registration after the evaluate pipeline's reductions: its measures and their sums.

    Internal to :func:`~itk_nrreval.evaluation.evaluate`, which turns it into the public
    :class:`~itk_nrreval.evaluation.RegistrationScores`; the driver's inputs to a report.

    Attributes
    ----------
    name : str
    specificity : SpecificityResult
    generalization : GeneralizationResult
    overlap : OverlapTable or None
        None without labels.
    frame : FrameMapping
        Its transform is None for an estimated frame until :func:`run_pipeline` returns
        (the driver does not hold the field while it resamples and reduces).
    plausibility : list of Plausibility, length n_images
        Each transform's deformation plausibility on the registration's reference grid
        (every image, those left out of the scores too).
    coverage : Coverage
        How much of the common grid (inside the mask) its images cover.
    mean_image : ndarray of shape (*spatial_zyx,)
        The mean resampled image on the common grid (until :func:`run_pipeline` returns,
        once the registration is reduced, the key of its cache entry: the driver does not
        hold it while the next registrations' images are resampled).
    gram : ndarray of shape (n_scored, n_scored)
        Gram matrix of the centred resampled images in the scores (`scored`; inside the
        region): the model of any subset of them follows from it
        (:mod:`itk_nrreval.confidence`).
    overlap_sums : dict of str to ndarray, or None
        The per-image sums the overlap table was built from (``labels``, ``volume``,
        ``target_sums``, ``gradient_sums``, ``pair_min``, ``pair_max``; see
        :meth:`OverlapTable.from_sums`), rows in `scored` order, and the sums of minima of
        each two images of one subject (``subject_pairs``, ``subject_pair_min``; see
        :func:`~itk_nrreval.confidence.overlap_replicates`); None without labels.
    thumbnails : dict of str to ndarray
        Small arrays for the HTML report, whatever N
        (:func:`~itk_nrreval._resampled_images.thumbnails`): middle slices of two subjects'
        resampled images (and of the flagged subjects :func:`run_pipeline` pictures,
        ``image_<i>``), of the first subject's labels and of its
        det J, and the log det J histogram over all subjects.
    affine_fits : list of AffineFit, length n_images
        Each transform's closest affine map on the reference grid
        (:func:`itk_nrreval.plausibility.affine_fit`).
    scored : tuple of int
        The images in the scores (manifest indices, ascending; every image but those off
        the common grid, :func:`off_grid_subjects`): the rows of `gram` and `overlap_sums`.
    brain_masks : BrainMaskDice or None
        Every subject's brain-mask Dice in the common frame against the common mask
        (:func:`_brain_mask_dice`); None when the manifest has no ``masks``.
    label_metrics : LabelMetrics or None
        Dice and HD95 (mm) per label and case in the common frame
        (:mod:`itk_nrreval.label_metrics`, :func:`_label_metrics`); None without labels.
    subjects : tuple of SubjectQC
        Every subject's quality control under this registration, by `assess_subjects` of
        :func:`run_pipeline` (empty without it).
    """

    name: str
    specificity: SpecificityResult
    generalization: GeneralizationResult
    overlap: OverlapTable | None
    frame: FrameMapping
    plausibility: list[Plausibility]
    coverage: Coverage
    mean_image: np.ndarray = field(repr=False)
    gram: np.ndarray = field(repr=False)
    overlap_sums: Mapping[str, np.ndarray] | None = field(repr=False)
    thumbnails: Mapping[str, np.ndarray] = field(default_factory=dict, repr=False)
    affine_fits: list[AffineFit] = field(default_factory=list, repr=False)
    scored: tuple[int, ...] = ()
    brain_masks: BrainMaskDice | None = None
    label_metrics: LabelMetrics | None = None
    subjects: tuple[SubjectQC, ...] = ()


@dataclass(frozen=True)
class PipelineRun:
    """Every registration's :class:`ReducedRegistration`, the label values, and how it ran.

    Attributes
    ----------
    registrations : dict of str to ReducedRegistration
        In the manifest's order.
    label_values : list of int or None
        ``[0, *labels]``: background then every nonzero label value found (None without
        labels); the overlap table's labels are indices into this list.
    grid : Geometry
        The common grid.
    cache_reused, cache_computed : int
        Per-image results found in the cache, and computed.
    resampled : ResampledImages or None
        Where every registration's resampled images are in the cache (gone from it unless
        ``keep_resampled``), and the evaluated region.
    """

    registrations: Mapping[str, ReducedRegistration]
    label_values: list[int] | None
    grid: Geometry
    cache_reused: int
    cache_computed: int
    resampled: ResampledImages | None = None


@dataclass
class _Counts:
    reused: int = 0
    computed: int = 0

    def add(self, reused: bool) -> None:
        if reused:
            self.reused += 1
        else:
            self.computed += 1


def _block_bounds(n_images: int, n_voxels: int) -> list[tuple[int, int]]:
    size = max(4096, _BLOCK_BYTES // (8 * n_images)) // 4096 * 4096
    size = min(size, n_voxels)
    return [(a, min(a + size, n_voxels)) for a in range(0, n_voxels, size)]


def run_pipeline(
    m: Manifest,
    executor: Executor,
    *,
    n_samples: int,
    seed: int,
    distance: str,
    progress: bool,
    resampling: Resampling | None = None,
    execution: Execution | None = None,
    subject_thresholds: SubjectThresholds | None = None,
    inverse_consistency: bool = True,
    assess_subjects: Callable[[ReducedRegistration, Callable], Sequence[SubjectQC]] | None = None,
    flagged_pictured: int = 0,
) -> PipelineRun:
    """Score every registration of `m` (the body of :func:`itk_nrreval.evaluate`).

    Parameters
    ----------
    m : Manifest
        Already checked.
    executor : Executor
        Where tasks run.
    n_samples, seed, distance
        As :func:`itk_nrreval.evaluate`.
    progress : bool
        Progress bars on stderr.
    resampling : Resampling, optional
        How images and label maps become the common frame's (default ``Resampling()``).
    execution : Execution, optional
        Its `cache` (default: a temporary folder, removed afterwards) and `keep_resampled`:
        keep every registration's resampled images and memberships in the cache (about
        50 MB per image and registration at 1 mm), so that a rerun does not resample them
        again, and :func:`itk_nrreval._resampled_images.export_resampled` can write them. By
        default each registration's go once its scores are taken: the cache then holds one
        registration's at a time, and keeps the frames and every transform's measures.
    subject_thresholds : SubjectThresholds, optional
        Its `off_grid_coverage`: leave out of the scores every image that covers less of the
        common grid than this fraction of the median image, under any registration
        (:func:`off_grid_subjects`); they are named in a warning.
    inverse_consistency : bool
        Measure each transform's inverse consistency (one numerical inversion per image).
    assess_subjects : callable, optional
        Given a registration's finished :class:`ReducedRegistration` and a function that
        resamples images through changed transforms and returns their inner products with
        the scored images (:func:`_alternative_products`, its first arguments bound; for
        :func:`itk_nrreval.subject_qc.transform_mixups`), every subject's quality control
        (:class:`~itk_nrreval.subject_qc.SubjectQC`): run while the cache still holds the
        registration's images, kept in its ``subjects``.
    flagged_pictured : int
        How many of the flagged subjects, worst first, the thumbnails also picture
        (``image_<i>``: read from the cache before it goes, a few slices rather than all N).

    Returns
    -------
    PipelineRun
    """
    resampling = resampling or Resampling()
    execution = execution or Execution()
    off_grid = (subject_thresholds or SubjectThresholds()).off_grid_coverage
    grid = Geometry.from_image(common_reference(m))
    mask = mask_array(m.mask, shape=grid.shape, geometry=grid) if m.mask is not None else None
    with contextlib.ExitStack() as stack:
        cache = execution.cache
        if cache is None:
            cache = stack.enter_context(tempfile.TemporaryDirectory(prefix="nrreval-cache-"))
        disk = stack.enter_context(DiskCache(cache).in_use())
        disk.remove_stale()
        mask_key = None if mask is None else _stored_mask(disk, mask)
        ctx = _Context(str(Path(cache).resolve()), grid, mask_key, inverse_consistency)
        counts = _Counts()
        values, own_values = _label_values(m, executor, progress)
        # Every transform measured first (frames, coverage, plausibility): the region the
        # scores are taken on is known before any image is resampled.
        measured = {
            name: _measure_registration(
                executor, ctx, disk, m, name, mask=mask, counts=counts, progress=progress
            )
            for name in m.registrations
        }
        entries = {k: (r.keys, r.metas, r.frame) for k, r in measured.items()}
        left_out = _left_out_of_scores(m, entries, off_grid)
        scored = tuple(i for i in range(m.n_images) if i not in left_out)
        region, coverage = _region(disk, grid, mask, m, entries, left_out)
        region_ctx = ctx
        if region is not None and (mask is None or not np.array_equal(region, mask)):
            region_ctx = dataclasses.replace(ctx, mask_key=_stored_mask(disk, region))
        score = functools.partial(
            _score_registration,
            executor, ctx, region_ctx, disk, m,
            counts=counts, warned=set(), own_values=own_values, mask=mask, scored=scored,
            values=values, region=region, n_samples=n_samples, seed=seed, distance=distance,
            resampling=resampling, keep_resampled=execution.keep_resampled,
            progress=progress, assess_subjects=assess_subjects,
            flagged_pictured=flagged_pictured,
        )  # fmt: skip
        runs, resampled = {}, {}
        for name, reg in measured.items():  # one registration's images in the cache at a time
            runs[name], resampled[name] = score(name, reg, coverage=coverage[name])
        runs = _with_held_arrays(runs, measured, grid, disk)
    record = ResampledImages(
        grid=grid,
        region=region,
        label_values=None if values is None else tuple(values),
        keys={name: tuple(r.keys) for name, r in resampled.items()},
        labels={
            name: tuple(None if values is None else tuple(meta["labels"]) for meta in r.metas)
            for name, r in resampled.items()
        },
        coverage={name: tuple(runs[name].coverage.per_image) for name in runs},
    )
    return PipelineRun(runs, values, grid, counts.reused, counts.computed, record)


def _score_registration(
    executor, ctx, region_ctx, disk, m, name, reg: _Measured, *, coverage, counts, warned,
    own_values, mask, scored, values, region, n_samples, seed, distance, resampling,
    keep_resampled, progress, assess_subjects, flagged_pictured,
) -> tuple[ReducedRegistration, _Resampled]:  # fmt: skip
    """Registration `name` resampled, reduced to its scores, and its label metrics; its
    resampled images leave the cache unless `keep_resampled`, its mean image goes to the
    cache until the end (:func:`_with_held_arrays`)."""
    method = resampling.label_interpolation
    r = _resample_registration(
        executor,
        ctx,
        disk,
        m,
        name,
        reg,
        counts=counts,
        warned=warned,
        own_values=own_values,
        interpolation=resampling.interpolation,
        labels=(method, resampling.label_sigma_mm),
        progress=progress,
    )
    _check_region_covered(disk, name, r.keys, scored, region, ctx.grid)
    # before the reduction: the subjects' assessment (assess_subjects) reads them
    brain_masks = _brain_mask_dice(
        executor, ctx, disk, m, name, reg, mask=mask, counts=counts,
        method=method, progress=progress,
    )  # fmt: skip
    run = _reduce_registration(
        executor,
        region_ctx,
        disk,
        m,
        name,
        r,
        brain_masks=brain_masks,
        scored=scored,
        values=values,
        region=region,
        coverage=coverage,
        n_samples=n_samples,
        seed=seed,
        distance=distance,
        interpolation=resampling.interpolation,
        progress=progress,
        assess_subjects=assess_subjects,
        flagged_pictured=flagged_pictured,
    )
    label_metrics = _label_metrics(
        executor, region_ctx, disk, m, name, r, scored=scored, values=values,
        keep=keep_resampled, progress=progress,
    )  # fmt: skip
    run = dataclasses.replace(run, label_metrics=label_metrics)
    if not keep_resampled:
        for key in set(r.keys):
            disk.remove("resampled", key)
    # on disk until the end, not in memory while the next registrations' tasks run
    mean_key = digest_of([name, r.keys])
    disk.put("mean_image", mean_key, {"mean": run.mean_image})
    return dataclasses.replace(run, mean_image=mean_key), r


def _with_held_arrays(
    runs: dict[str, ReducedRegistration], measured: Mapping, grid: Geometry, disk: DiskCache
) -> dict[str, ReducedRegistration]:
    """`runs` with what the driver did not hold while the images were resampled and
    reduced read back from the cache: each estimated frame's transform F (a full-size
    field, 0.2 GB at 1 mm) and each mean image (its ``mean_image`` is its entry's key until
    then; the entry goes once read)."""
    out = {}
    for name, run in runs.items():
        mean = disk.open("mean_image", run.mean_image).array("mean")
        disk.remove("mean_image", run.mean_image)
        run = dataclasses.replace(run, mean_image=mean)
        if run.frame.transform is None:
            f = _frame_transform(measured[name].frame_spec, grid, disk)
            run = dataclasses.replace(run, frame=dataclasses.replace(run.frame, transform=f))
        out[name] = run
    return out


def _stored_mask(disk: DiskCache, mask: np.ndarray) -> str:
    """The cache key of a mask (bool, any shape), stored under it once."""
    flat = mask.reshape(-1).astype(np.bool_)
    key = digest_of(["mask", flat])
    if disk.get("mask", key) is None:
        disk.put("mask", key, {"mask": flat})
    return key


def _label_values(m: Manifest, executor: Executor, progress: bool):
    """The label values of every label map (index 0: background), and each image's own
    non-background values; (None, [None] * N) without labels."""
    own_values: list[list[int] | None] = [None] * m.n_images
    if m.labels is None:
        return None, own_values
    calls = [([p],) for p in m.labels]
    for i, vals in executor.map(label_values, calls, desc="label values", progress=progress):
        own_values[i] = [int(v) for v in vals if v != 0]  # background: not evaluated
    found = {v for vals in own_values for v in vals}
    return [0, *sorted(found)], own_values


@dataclass(frozen=True)
class _Measured:
    """One registration's frame and its transforms' measures (cache entries, metadata)."""

    keys: list[str]
    metas: list[dict]
    frame: Any
    frame_spec: tuple
    frame_digest: str
    reference_grid: Geometry


@dataclass(frozen=True)
class _Resampled:
    """One registration's resampled images (cache entries; metadata with its measures')
    and what resampling it again needs."""

    keys: list[str]
    metas: list[dict]
    frame: Any
    frame_spec: tuple
    reference_grid: Geometry
    thumbnails: dict[str, np.ndarray]


def _measure_registration(
    executor, ctx, disk, m, name, *, mask, counts, progress
) -> _Measured:  # fmt: skip
    """Registration `name`'s frame F and every image's transform measured
    (:func:`_measures_task`: coverage of the common grid, plausibility), cached."""
    reg = m.registrations[name]
    reg_grid = Geometry.from_image(read_image(reg.reference, what="reference image"))
    frame_spec, frame_digest, frame = _frame(
        executor, ctx, disk, m, name, reg_grid, counts, progress
    )
    reg_mask_key = _registration_mask(disk, ctx, mask, frame, frame_digest, reg_grid)
    if frame_spec[0] == "field":
        # The tasks read F from the cache; the driver holds its transform (a full-size
        # field, 0.2 GB at 1 mm per registration) only once the reductions are done
        # (:func:`_with_held_arrays`).
        frame = dataclasses.replace(frame, transform=None)
    calls = [
        (
            ctx,
            m.scored_images[i],
            reg.transforms[i],
            frame_spec,
            frame_digest,
            reg_grid,
            reg_mask_key,
        )
        for i in range(m.n_images)
    ]
    keys: list[str] = [""] * m.n_images
    metas: list[dict] = [{}] * m.n_images
    for i, (key, reused, meta) in executor.map(
        _measures_task, calls, desc=f"{name}: measures", progress=progress
    ):
        keys[i], metas[i] = key, meta
        counts.add(reused)
    return _Measured(keys, metas, frame, frame_spec, frame_digest, reg_grid)


def _resample_registration(
    executor, ctx, disk, m, name, reg: _Measured, *, counts, warned, own_values,
    interpolation, labels, progress,
) -> _Resampled:  # fmt: skip
    """Every image of registration `name` resampled into the common frame (cached), with
    its labels' memberships; label-like images warned once."""
    items = m.registrations[name].transforms
    calls = [
        (
            ctx,
            m.scored_images[i],
            m.labels[i] if m.labels is not None else None,
            items[i],
            reg.frame_spec,
            reg.frame_digest,
            reg.reference_grid,
            interpolation,
            own_values[i],
            labels,
        )
        for i in range(m.n_images)
    ]
    keys: list[str] = [""] * m.n_images
    metas: list[dict] = [{}] * m.n_images
    for i, (key, reused, meta) in executor.map(
        _resample_task, calls, desc=f"{name}: resampling", progress=progress
    ):
        keys[i], metas[i] = key, {**reg.metas[i], **meta}
        counts.add(reused)
        if meta.get("label_like") and i not in warned:
            warned.add(i)
            warn_label_like(str(m.scored_images[i]), meta["label_like"], stacklevel=5)
    pictures = thumbnails(disk, ctx.grid, reg.reference_grid, keys, reg.keys[0], metas)
    return _Resampled(keys, metas, reg.frame, reg.frame_spec, reg.reference_grid, pictures)


def _brain_mask_task(
    ctx: _Context, mask, item, frame: tuple, frame_digest: str, method: str
) -> tuple[str, bool]:
    """One subject's brain mask brought into the common frame through ``T_i^R o F`` (as its
    image is), cached as ``mask``: ``np.packbits`` of a bool (n,) over the common grid
    (numpy order). `method` is :func:`~itk_nrreval._brain_masks.resample_mask`'s. Returns
    ``(key, reused)``."""
    cache = ctx.cache()
    g = ctx.grid
    key = _task_key("brain_mask", g, mask, item, frame_digest, method)
    if cache.get("brain_mask", key) is not None:
        return key, True
    full = flatten(resampling_transform(transform_pieces(item), _frame_transform(frame, g, cache)))
    inside = resample_mask(read_image(mask, what="brain mask"), full, g, method=method)
    cache.put("brain_mask", key, {"mask": np.packbits(inside.reshape(-1))})
    return key, False


class _CachedMasks(Sequence):
    """The subjects' resampled brain masks read from the cache one at a time (bool, the
    common grid's numpy shape): N masks are never held at once."""

    def __init__(self, disk: DiskCache, keys: Sequence[str], shape: tuple[int, ...]):
        self._disk, self._keys, self._shape = disk, list(keys), tuple(shape)

    def __len__(self) -> int:
        return len(self._keys)

    def __getitem__(self, i):
        bits = self._disk.open("brain_mask", self._keys[i]).array("mask")
        n = math.prod(self._shape)
        return np.unpackbits(bits, count=n).astype(bool).reshape(self._shape)


def _brain_mask_dice(
    executor, ctx, disk, m, name, reg: _Measured, *, mask, counts, method, progress
) -> BrainMaskDice | None:  # fmt: skip
    """Every subject's brain mask (the manifest's ``masks``) in the common frame under
    registration `name`, and its Dice against the common mask: the manifest's `mask` (on
    the common grid) where given, else the majority vote of the resampled masks
    (:func:`~itk_nrreval._brain_masks.subject_mask_dice`). Resampled as the label maps are:
    nearest neighbour for ``label_interpolation="nearest"``, else linear and inside at 0.5
    (`method`). None without ``masks``."""
    if m.masks is None:
        return None
    items = m.registrations[name].transforms
    method = "nearest" if method == "nearest" else "linear"
    calls = [
        (ctx, m.masks[i], items[i], reg.frame_spec, reg.frame_digest, method)
        for i in range(m.n_images)
    ]
    keys: list[str] = [""] * m.n_images
    for i, (key, reused) in executor.map(
        _brain_mask_task, calls, desc=f"{name}: brain masks", progress=progress
    ):
        keys[i] = key
        counts.add(reused)
    return subject_mask_dice(_CachedMasks(disk, keys, ctx.grid.shape), common=mask)


def _check_region_covered(
    disk: DiskCache,
    name: str,
    keys: Sequence[str],
    scored: Sequence[int],
    region: np.ndarray | None,
    grid: Geometry,
) -> None:
    """Every scored image resampled has a value at every voxel of the region, which was
    found from the measured coverage before any image was resampled (RuntimeError if not:
    the two would disagree, and an image's 0 outside its field of view would be scored)."""
    n_vox = int(np.prod(grid.shape))
    where = None if region is None else region.reshape(-1)
    for i in scored:
        bits = disk.open("resampled", keys[i]).array("covered")
        missing = ~np.unpackbits(bits, count=n_vox).astype(bool)
        n_missing = int(missing.sum() if where is None else missing[where].sum())
        if n_missing:
            raise RuntimeError(
                f"registration {name!r}, image {i}: its resampled image has no value at "
                f"{n_missing} voxels of the evaluated region, which its measured coverage "
                "includes (a defect of this toolkit: please report it)"
            )


def _left_out_of_scores(m: Manifest, entries, off_grid_coverage: float) -> tuple[int, ...]:
    """The images left out of every score: those off the common grid under some
    registration (a warning names them), unless too few would be left (the region check
    reports it). `entries`: per registration (keys, metas, frame)."""
    left_out = off_grid_subjects(entries, off_grid_coverage)
    if not left_out or m.n_images - len(left_out) < 3:
        return ()
    warnings.warn(
        f"{len(left_out)} of {m.n_images} images cover (almost) none of the common "
        f"grid under some registration and are left out of every score: "
        f"{readable([str(m.images[i]) for i in left_out])}",
        UserWarning,
        stacklevel=4,
    )
    return tuple(left_out)


def _reduce_registration(
    executor, region_ctx, disk, m, name, r: _Resampled, *, brain_masks, scored, values, region,
    coverage, n_samples, seed, distance, interpolation, progress, assess_subjects,
    flagged_pictured,
) -> ReducedRegistration:  # fmt: skip
    """Registration `name`'s scores from its cache entries inside the region, with every
    image's deformation, and the thumbnails of the subjects the report pictures."""
    metas = r.metas
    if values is not None:
        calls = [(region_ctx, k) for k in r.keys]
        metas = [dict(meta) for meta in metas]
        # cheap and derived from the resampled entries: not in the counts
        for i, (sums, _reused) in executor.map(
            _label_sums_task, calls, desc=f"{name}: label sums", progress=progress
        ):
            metas[i].update(sums)
    run = _reduce(
        executor,
        region_ctx,
        name,
        [r.keys[i] for i in scored],
        [metas[i] for i in scored],
        r.frame,
        values,
        region,
        coverage,
        groups=None if m.groups is None else [m.groups[i] for i in scored],
        subjects=None if m.subjects is None else [m.subjects[i] for i in scored],
        n_samples=n_samples,
        seed=seed,
        distance=distance,
        progress=progress,
    )
    run = dataclasses.replace(
        run,
        thumbnails=r.thumbnails,
        # every image's deformation, those left out of the scores too
        plausibility=[Plausibility.from_dict(meta["plausibility"]) for meta in metas],
        affine_fits=[AffineFit.from_dict(meta["affine_fit"]) for meta in metas],
        scored=scored,
        brain_masks=brain_masks,
    )
    if assess_subjects is None:
        return run
    products = functools.partial(
        _alternative_products,
        region_ctx,
        m,
        name,
        r.frame_spec,
        r.reference_grid,
        [r.keys[i] for i in scored],
        run.mean_image,
        interpolation,
    )
    subjects = tuple(assess_subjects(run, products))
    worst = [q.index for q in ranked(subjects) if q.flags][:flagged_pictured]
    extra = {
        f"image_{i}": image_slice(disk, region_ctx.grid, r.keys[i])
        for i in worst
        if f"image_{i}" not in r.thumbnails
    }
    return dataclasses.replace(run, thumbnails={**r.thumbnails, **extra}, subjects=subjects)


def _alternative_products(
    ctx: _Context,
    m: Manifest,
    name: str,
    frame_spec: tuple,
    reg_grid: Geometry,
    keys: Sequence[str],
    mean_image: np.ndarray,
    interpolation: str,
    alternatives: Sequence,
) -> tuple[np.ndarray, np.ndarray]:
    """Resample images through changed transforms; their inner products with the scores'.

    On the driver, after the per-image tasks, for the few subjects the quality control asks
    about (:func:`itk_nrreval.subject_qc.transform_mixups`).

    Parameters
    ----------
    ctx : _Context
        The run's context with the evaluated region as its mask.
    m : Manifest
    name : str
        The registration.
    frame_spec : tuple
        Its frame F (:func:`_frame_transform`).
    reg_grid : Geometry
        Its reference grid (where a transform that is neither linear nor a displacement
        field is sampled to be inverted).
    keys : sequence of str, length n
        The cache entries of the scored subjects' resampled images.
    mean_image : ndarray of shape (*spatial_zyx,)
        Their mean, which centred the Gram matrix.
    interpolation : str
        As the resampled entries.
    alternatives : sequence of Alternative
        ``image`` resampled through subject ``transform``'s transform of registration
        `name` (its inverse with ``inverse``: :func:`itk_nrreval.transforms.invert`, exact
        for linear maps), as the per-image task resamples (0 outside the field of view).

    Returns
    -------
    cross : ndarray of shape (n_alternatives, n)
        Inner products of the centred alternatives with the centred scored images, inside
        the region (squared intensity units, as the Gram matrix).
    squared : ndarray of shape (n_alternatives,)
        Each centred alternative's squared norm there.
    """
    cache = ctx.cache()
    grid = ctx.grid
    region = ctx.mask_flat()
    frame = _frame_transform(frame_spec, grid, cache)
    transforms = m.registrations[name].transforms
    centre = mean_image.reshape(-1)
    centre = centre[region] if region is not None else centre
    # by transform, so that each transform is read (and inverted) once
    order = sorted(range(len(alternatives)), key=lambda c: alternatives[c].transform)
    per_chunk = max(1, ALTERNATIVE_CHUNK_BYTES // (8 * max(centre.size, 1)))
    cross = np.empty((len(alternatives), len(keys)))
    squared = np.empty(len(alternatives))
    raw: dict[int, sitk.Image] = {}
    current: tuple[int, sitk.Transform] | None = None
    for start in range(0, len(order), per_chunk):
        chunk = order[start : start + per_chunk]
        changed = np.empty((len(chunk), centre.size))
        for row, c in enumerate(chunk):
            alt = alternatives[c]
            if current is None or current[0] != alt.transform:
                current = (alt.transform, chain_transform(transforms[alt.transform]))
            t = invert(current[1], grid=reg_grid) if alt.inverse else current[1]
            if alt.image not in raw:
                raw[alt.image] = read_image(m.scored_images[alt.image], what="image")
            values = resample_images(
                [raw[alt.image]],
                [resampling_transform(t, frame)],
                grid,
                interpolation=interpolation,
                progress=False,
            )[0].reshape(-1)
            changed[row] = (values[region] if region is not None else values) - centre
        for k, key in enumerate(keys):  # one scored image in memory at a time
            x = np.asarray(cache.open("resampled", key).array("image", mmap=True))
            cross[chunk, k] = changed @ ((x[region] if region is not None else x) - centre)
        squared[chunk] = np.einsum("ij,ij->i", changed, changed)
        del changed
    return cross, squared


def _reduce(
    executor,
    ctx,
    name,
    keys,
    metas,
    frame,
    values,
    mask,
    coverage,
    *,
    groups,
    subjects,
    n_samples,
    seed,
    distance,
    progress,
) -> ReducedRegistration:
    """Block sums -> model -> specificity and generalization; pair sums -> overlap table."""
    grid = ctx.grid
    n = len(keys)
    n_vox = int(np.prod(grid.shape))
    bounds = _block_bounds(n, n_vox)
    components = values[1:] if values is not None else []
    pairs = _subject_pairs(subjects)
    calls = [(ctx, keys, a, b, components, pairs) for a, b in bounds]
    gram = np.zeros((n, n))
    mean = np.empty(n_vox)
    n_lab = len(components)
    p, q = np.zeros(n_lab), np.zeros(n_lab)
    vol, spair = np.zeros((n, n_lab)), np.zeros((n, n_lab))
    pair_min = np.zeros((len(pairs), n_lab))
    # Sums are taken in block order, whatever order the blocks finish in, so that a run's
    # numbers do not depend on the executor's timing.
    pending: dict[int, dict] = {}
    next_block = 0
    for b, res in executor.map(_block_task, calls, desc=f"{name}: model", progress=progress):
        pending[b] = res
        while next_block in pending:
            res = pending.pop(next_block)
            gram += res["gram"]
            mean[bounds[next_block][0] : bounds[next_block][1]] = res["mean"]
            p += res["p"]
            q += res["q"]
            vol += res["vol"]
            spair += res["spair"]
            pair_min += res["subject_pair_min"]
            next_block += 1
    model = TextureModel.from_gram(
        gram,
        mean=mean[mask.reshape(-1)] if mask is not None else mean,
        mask=mask,
        geometry=grid,
    )
    spec, gen = texture_measures(
        model,
        groups=groups,  # a mixture, one Gaussian per group, when the manifest has groups
        n_samples=n_samples,
        distance=distance,
        seed=seed,
        progress=progress,
        desc=f"{name}: specificity",
    )
    table = sums = None
    if values is not None:
        present = np.zeros(n_lab, bool)
        gsum = np.zeros((n, n_lab))
        for i, meta in enumerate(metas):
            own = {v: j for j, v in enumerate(meta["labels"])}
            for k, v in enumerate(components):
                if v in own:
                    present[k] |= meta["present"][own[v]]
                    gsum[i, k] = meta["gsum"][own[v]]
        comps = np.arange(1, len(values), dtype=np.int64)  # indices into values
        if not present.any():
            raise InputError("label maps: no label other than background 0 in the mask")
        skipped = tuple(int(c) for c in comps[~present])
        if skipped:
            warnings.warn(
                f"labels {readable([values[c] for c in skipped])} are absent from every image and "
                "are skipped",
                UserWarning,
                stacklevel=5,
            )
        sums = {
            "labels": comps[present],
            "volume": vol[:, present],
            "target_sums": spair[:, present],
            "gradient_sums": gsum[:, present],
            "pair_min": p[present],
            "pair_max": q[present],
            "subject_pairs": pairs,
            "subject_pair_min": pair_min[:, present],
        }
        table = OverlapTable.from_sums(
            sums["labels"],
            sums["volume"],
            sums["target_sums"],
            sums["gradient_sums"],
            sums["pair_min"],
            sums["pair_max"],
            spacing=grid.spacing,
            fuzzy=True,
            skipped_labels=skipped,
        )
    plaus = [Plausibility.from_dict(meta["plausibility"]) for meta in metas]
    return ReducedRegistration(
        name, spec, gen, table, frame, plaus, coverage, mean.reshape(grid.shape), gram, sums
    )


def _frame(executor, ctx, disk, m: Manifest, name, reg_grid, counts, progress):
    """F for registration `name`: its task description, the digest of that, its FrameMapping."""
    reg = m.registrations[name]
    common_items = m.registrations[m.common_frame].transforms
    if name == m.common_frame:
        spec = ("identity",)
        f = _frame_transform(spec, ctx.grid, disk)
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
    frame_key = _task_key("frame", keys) if spec is None else None
    spread_key = _task_key("frame_spread", keys, spec, ctx.mask_key)
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
    f = _frame_transform(spec, ctx.grid, disk)
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
    disp_key = _task_key("frame_disp", ctx.grid, digest)
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


def _registration_mask(
    disk: DiskCache,
    ctx: _Context,
    mask: np.ndarray | None,
    frame: FrameMapping,
    frame_digest: str,
    reg_grid: Geometry,
) -> str | None:
    """Cache the mask carried into the registration's reference frame; return its key.

    The mask lives on the common grid; a registration's transforms are defined on its own
    reference grid, where the plausibility measures are taken. A reference voxel q is inside
    when ``F^-1(q)`` falls in the mask (nearest neighbour). None without a mask.
    """
    if mask is None:
        return None
    key = _task_key("reg_mask", ctx.mask_key, frame_digest, ctx.grid, reg_grid)
    if disk.get("reg_mask", key) is not None:
        return key
    img = sitk.GetImageFromArray(mask.astype(np.uint8))
    ctx.grid.apply_to(img)
    back = sitk.TranslationTransform(ctx.grid.dimension)
    if frame.method != "common":
        back = invert(frame.transform, grid=ctx.grid)
    res = resample_onto(img, back, reg_grid, sitk.sitkNearestNeighbor)
    disk.put("reg_mask", key, {"mask": sitk.GetArrayFromImage(res).reshape(-1).astype(bool)})
    return key


# ------------------------------------------------------------- Dice and HD95 per label


def _crisp_task(ctx: _Context, key: str, codes: Sequence[int], n_codes: int) -> tuple[str, dict]:
    """One subject's crisp label map in the evaluated region, and its label boundaries.

    From the resampled entry `key`'s memberships (:func:`~itk_nrreval.label_metrics.
    crisp_labels`, channel k written as ``codes[k]``, an index into the run's label values;
    background outside ``ctx.mask_key``'s region) and
    :func:`~itk_nrreval.label_metrics.label_surfaces`. Cached as ``crisp_labels``:
    ``labels`` (n,) in the smallest unsigned dtype for `n_codes`, ``b_ptr`` (n_codes + 1,)
    and ``b_idx`` (flat voxel indices of every code's boundary; uint32 below 2**32 voxels);
    its metadata ``counts``, each code's voxels in the region. Returns ``(crisp key,
    metadata)``.

    Costs one pass over the grid per label for the memberships' maximum (as the label sums
    do), one ``find_objects`` pass and each label's box: about 0.2 s at 1 mm (9 labels,
    docs/label-metrics.md), and n bytes in the cache until the registration is done.
    """
    cache = ctx.cache()
    g = ctx.grid
    crisp_key = _task_key("crisp_labels", key, ctx.mask_key, list(codes), n_codes)
    found = cache.get("crisp_labels", crisp_key)
    if found is not None:
        return crisp_key, dict(found.meta)
    entry = cache.open("resampled", key)
    memb = stored_memberships(entry, g.shape, entry.meta["labels"])
    mask = ctx.mask_flat()
    region = None if mask is None else mask.reshape(g.shape)
    labels = crisp_labels(memb, codes=codes, n_codes=n_codes, region=region)
    surfaces = label_surfaces(labels, n_codes, region=region)
    index = surfaces.index.astype(np.uint32) if labels.size < 2**32 else surfaces.index
    meta = {"counts": surfaces.counts.tolist()}
    arrays = {"labels": labels.reshape(-1), "b_ptr": surfaces.ptr, "b_idx": index}
    cache.put("crisp_labels", crisp_key, arrays, meta)
    return crisp_key, meta


def _distances_task(
    ctx: _Context,
    crisp_keys: Sequence[str],
    subject: int,
    targets: Sequence[int],
    dice_with: Sequence[int],
    n_codes: int,
) -> dict:
    """Subject `subject`'s side of its cases, from the crisp entries `crisp_keys` (by
    manifest index).

    Returns ``{"d95": (len(targets), n_codes), "inter": (len(dice_with), n_codes)}`` as
    lists: per target, per code, the 95th percentile of the distances (mm) from the
    target's boundary to the subject's nearest boundary voxel (None: no boundary in one of
    them; one distance transform of the subject's boundary per code,
    :func:`~itk_nrreval.label_metrics.directed_percentiles`, read at every target's); per
    partner of `dice_with`, per code, the voxels where both maps have it. Cached (metadata
    only) as ``label_distances``.
    """
    cache = ctx.cache()
    g = ctx.grid
    key = _task_key(
        "label_distances",
        g,
        crisp_keys[subject],
        [crisp_keys[j] for j in targets],
        [crisp_keys[j] for j in dice_with],
    )
    found = cache.get("label_distances", key)
    if found is not None:
        return dict(found.meta)
    own = cache.open("crisp_labels", crisp_keys[subject])
    ptr, idx = own.array("b_ptr"), own.array("b_idx", mmap=True)
    others = []
    for j in targets:
        e = cache.open("crisp_labels", crisp_keys[j])
        others.append((e.array("b_ptr"), e.array("b_idx", mmap=True)))
    d95 = np.full((len(targets), n_codes), np.nan)
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
    inter = np.zeros((len(dice_with), n_codes), np.int64)
    if dice_with:
        labels = own.array("labels")
        for row, j in enumerate(dice_with):  # one other map in memory at a time
            other = cache.open("crisp_labels", crisp_keys[j]).array("labels", mmap=True)
            both = labels[labels == np.asarray(other)]
            inter[row] = np.bincount(both, minlength=n_codes)[:n_codes]
    meta = {
        "d95": [[json_number(v) for v in row] for row in d95],
        "inter": inter.tolist(),
    }
    cache.put("label_distances", key, {}, meta)
    return meta


def _label_metrics(
    executor, ctx, disk, m, name, r: _Resampled, *, scored, values, keep, progress
) -> LabelMetrics | None:  # fmt: skip
    """Registration `name`'s Dice and HD95 (mm) per label and case in the common frame
    (:mod:`itk_nrreval.label_metrics`), from its resampled entries (`r`): two small tasks
    per scored subject, its crisp map (:func:`_crisp_task`) then its side of its cases
    (:func:`_distances_task`). The cases: each scored subject against the registration's
    reference subject where it has one among the scored
    (:func:`~itk_nrreval.subject_qc.reference_subject`), else every pair of scored
    subjects. The crisp maps leave the cache afterwards unless `keep`. None without
    labels."""
    if values is None:
        return None
    n_codes = len(values)
    code_of = {int(v): c for c, v in enumerate(values)}
    own = {i: [code_of[int(v)] for v in r.metas[i]["labels"]] for i in scored}
    crisp_keys = [""] * m.n_images
    counts: dict[int, np.ndarray] = {}
    calls = [(ctx, r.keys[i], own[i], n_codes) for i in scored]
    for k, (crisp_key, meta) in executor.map(
        _crisp_task, calls, desc=f"{name}: label maps", progress=progress
    ):
        crisp_keys[scored[k]] = crisp_key
        counts[scored[k]] = np.asarray(meta["counts"], np.int64)
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
    calls = [(ctx, crisp_keys, i, targets[i], dice_with[i], n_codes) for i in scored]
    sides: dict[int, dict] = {}
    for k, side in executor.map(
        _distances_task, calls, desc=f"{name}: Dice and HD95", progress=progress
    ):
        sides[scored[k]] = side
    if not keep:
        for key in set(crisp_keys) - {""}:
            disk.remove("crisp_labels", key)
    at = {i: {j: row for row, j in enumerate(targets[i])} for i in scored}
    shared = {i: {j: row for row, j in enumerate(dice_with[i])} for i in scored}
    dice = np.full((len(cases), n_codes), np.nan)
    hd95 = np.full((len(cases), n_codes), np.nan)
    for row, (a, b) in enumerate(cases):
        # a's boundary read in b's distance map, and b's in a's
        to_b = np.array(sides[b]["d95"][at[b][a]], np.float64)
        to_a = np.array(sides[a]["d95"][at[a][b]], np.float64)
        first, second = (a, b) if b in shared[a] else (b, a)
        inter = np.asarray(sides[first]["inter"][shared[first][second]], np.float64)
        for c in set(own[a]) & set(own[b]):  # a label both label maps have
            total = counts[a][c] + counts[b][c]
            if total:
                dice[row, c] = 2.0 * inter[c] / total
            if np.isfinite(to_a[c]) and np.isfinite(to_b[c]):
                hd95[row, c] = max(to_a[c], to_b[c])
    compared = [c for c in range(1, n_codes) if np.isfinite(dice[:, c]).any()]
    return LabelMetrics(
        labels=tuple(int(values[c]) for c in compared),
        cases=tuple((int(a), int(b)) for a, b in cases),
        reference=None if ref is None else int(ref),
        dice=dice[:, compared],
        hd95_mm=hd95[:, compared],
    )
