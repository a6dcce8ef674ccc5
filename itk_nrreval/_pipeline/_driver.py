"""The driver of the evaluate pipeline: :func:`run_pipeline`.

It is the one place that runs tasks. For each step it lists the step's tasks (a plan:
frozen task objects, from :mod:`._common_frame`, :mod:`._image_tasks`,
:mod:`._label_metrics`), runs the plan through the content-keyed cache on its executor
(:func:`_run`: in this process, on threads or on Dask), then the step's reductions. It
measures every registration's transforms first (frames, coverage, plausibility), finds the
region the scores are taken on, then, one registration at a time (so that the cache holds
one registration's resampled images at a time), resamples its images, reduces them to its
scores, its subjects' quality control and its label metrics, and returns a
:class:`PipelineRun`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import tempfile
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._evaluation_options import Execution, Resampling
from .._executors import Executor
from ..io._brain_masks import BrainMaskDice, subject_mask_dice
from ..io._cache import DiskCache, digest_of
from ..io._images import Geometry, mask_array, read_image, warn_label_like
from ..io._resampled_images import ResampledImages, image_slice, thumbnails
from ..io.frame import FrameMapping, common_reference, frame_method, label_values
from ..io.manifest import Manifest
from ..io.plausibility import AffineFit, Plausibility, SubjectThresholds
from ..measures.label_metrics import LabelMetrics
from ..measures.subject_qc import SubjectQC, ranked
from ._common_frame import (
    ESTIMATE_ENTRIES,
    FrameMean,
    FrameSpread,
    MeanOfEstimates,
    RegistrationMask,
    digest_of_frame,
    estimate_plan,
    frame_spread,
    frame_transform,
    given_frame,
)
from ._coverage import check_region_covered, evaluated_region, left_out_of_scores
from ._description_length import image_statistics, registration_description_length
from ._image_tasks import (
    CachedMasks,
    Measured,
    Resampled,
    bias_plan,
    brain_mask_plan,
    label_sums_plan,
    measure_plan,
    resample_plan,
)
from ._label_metrics import crisp_plan, distances_plan, label_cases, label_metrics
from ._reduction import ReducedRegistration, alternative_products, reduce_to_scores
from ._task_keys import TaskContext
from ._tasks import Task, cached, key_of, plan_keys, run_plan


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
    description_length: bool = False,
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
        again, and :func:`itk_nrreval.io._resampled_images.export_resampled` can write them. By
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
        the scored images (:func:`alternative_products`, its first arguments bound; for
        :func:`itk_nrreval.measures.subject_qc.transform_mixups`), every subject's quality control
        (:class:`~itk_nrreval.measures.subject_qc.SubjectQC`): run while the cache still holds the
        registration's images, kept in its ``subjects``.
    flagged_pictured : int
        How many of the flagged subjects, worst first, the thumbnails also picture
        (``image_<i>``: read from the cache before it goes, a few slices rather than all N).
    description_length : bool
        Each registration's description length
        (:func:`~._description_length.registration_description_length`), read while the
        cache holds its images; not for a manifest whose images form groups (a mixture).

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
        ctx = TaskContext(str(Path(cache).resolve()), grid, mask_key, inverse_consistency)
        counts = _Counts()
        values, own_values = _label_values(m, executor, progress)
        # Every transform measured first (frames, coverage, plausibility): the region the
        # scores are taken on is known before any image is resampled.
        measured = {
            name: _measure(
                executor, ctx, disk, m, name, mask=mask, counts=counts, progress=progress
            )
            for name in m.registrations
        }
        entries = {k: (r.keys, r.metas, r.frame) for k, r in measured.items()}
        left_out = left_out_of_scores(m, entries, off_grid)
        scored = tuple(i for i in range(m.n_images) if i not in left_out)
        region, coverage = evaluated_region(disk, grid, mask, m, entries, left_out)
        statistics = None
        if description_length and m.groups is None:
            statistics = image_statistics(m, scored)
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
            flagged_pictured=flagged_pictured, statistics=statistics,
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


@dataclass
class _Counts:
    reused: int = 0
    computed: int = 0

    def add(self, reused: bool) -> None:
        if reused:
            self.reused += 1
        else:
            self.computed += 1


def _run(
    executor: Executor,
    ctx: TaskContext,
    plan: Sequence[Task],
    *,
    desc: str,
    progress: bool,
    counts: _Counts | None = None,
) -> tuple[list[str], list[dict]]:
    """Run `plan` through the cache on `executor` (:func:`~._tasks.run_plan`): every task's
    key and metadata, in plan order; each task counted as found or computed in `counts`
    (None: not counted, for work derived cheaply from other entries)."""
    keys: list[str] = [""] * len(plan)
    metas: list[dict] = [{}] * len(plan)
    for i, key, meta, reused in run_plan(executor, ctx.root, plan, desc=desc, progress=progress):
        keys[i], metas[i] = key, meta
        if counts is not None:
            counts.add(reused)
    return keys, metas


def _frame(
    executor, ctx, disk, m, name, reg_grid, *, counts, progress
) -> tuple[tuple, str, FrameMapping]:  # fmt: skip
    """F for registration `name`: its description (:func:`frame_transform`), the digest of
    that, its FrameMapping with the spread of the images' estimates about it.

    Unless the manifest gives F (:func:`given_frame`), it is the mean of the estimates
    (:func:`estimate_plan`), added up as their tasks finish (:class:`MeanOfEstimates`) and
    cached under :class:`FrameMean`'s key; the spread under :class:`FrameSpread`'s. Both
    outlive the estimates: a rerun finds them and runs no estimate."""
    given = given_frame(m, name)
    if name == m.common_frame:
        f = frame_transform(given, ctx.grid, disk)
        return given, digest_of_frame(given), FrameMapping(name, "common", f, 0.0, 0.0)
    plan = estimate_plan(ctx, m, name, reg_grid, for_mean=given is None)
    keys = plan_keys(executor, plan, desc=f"{name}: frame")
    mean_key = None if given is not None else key_of(FrameMean(estimates=tuple(keys)))
    spread_key = key_of(FrameSpread(estimates=tuple(keys), frame=given, mask_key=ctx.mask_key))
    kept = disk.get("frame_spread", spread_key)
    reused = kept is not None and (mean_key is None or disk.get("frame", mean_key) is not None)
    if reused:  # F and its spread outlive the per-image estimates they were made from
        for _ in keys:
            counts.add(True)
    else:
        mean = None if mean_key is None else MeanOfEstimates(disk, keys)
        for i, _key, _meta, was_cached in run_plan(
            executor, ctx.root, plan, desc=f"{name}: frame", progress=progress
        ):
            counts.add(was_cached)
            if mean is not None:
                mean.arrived(i)
        if mean is not None and disk.get("frame", mean_key) is None:
            disk.put("frame", mean_key, mean.stored())
    spec = given if mean_key is None else ("field", mean_key)
    digest = digest_of_frame(spec)
    f = frame_transform(spec, ctx.grid, disk)
    if reused:
        spread = kept.meta
    else:
        spread = frame_spread(
            executor, ctx, disk, keys, f, digest, desc=f"{name}: frame spread", progress=progress
        )
        disk.put("frame_spread", spread_key, {}, spread)
        # The estimates are full-grid fields, a registration's N of them the largest thing
        # in the cache, and nothing else reads them: a rerun takes F and its spread from
        # their own entries.
        for k in keys:
            for kind in ESTIMATE_ENTRIES:
                disk.remove(kind, k)
    method = frame_method(m.registrations[name])
    per_image = tuple(spread["per_image_mm"])
    return (
        spec,
        digest,
        FrameMapping(name, method, f, spread["mean_mm"], spread["max_mm"], per_image),
    )


def _measure(executor, ctx, disk, m, name, *, mask, counts, progress) -> Measured:
    """Registration `name`'s frame F (:func:`_frame`) and every image's transform measured
    (:func:`measure_plan`: coverage of the common grid, plausibility), cached."""
    reg_grid = Geometry.from_image(
        read_image(m.registrations[name].reference, what="reference image")
    )
    spec, digest, frame = _frame(
        executor, ctx, disk, m, name, reg_grid, counts=counts, progress=progress
    )
    reg_mask_key = None
    if mask is not None:  # the mask in the registration's reference frame
        task = RegistrationMask(
            mask_key=ctx.mask_key, frame_digest=digest, grid=ctx.grid, reg_grid=reg_grid,
            mask=mask, frame=frame,
        )  # fmt: skip
        reg_mask_key, _meta, _reused = cached(task, disk)
    if spec[0] == "field":
        # The tasks read F from the cache; the driver holds its transform (a full-size
        # field, 0.2 GB at 1 mm per registration) only once the reductions are done
        # (:func:`_with_held_arrays`).
        frame = dataclasses.replace(frame, transform=None)
    plan = measure_plan(
        ctx, m, name, frame_spec=spec, frame_digest=digest, reg_grid=reg_grid,
        reg_mask_key=reg_mask_key,
    )  # fmt: skip
    keys, metas = _run(
        executor, ctx, plan, desc=f"{name}: measures", progress=progress, counts=counts
    )
    return Measured(keys, metas, frame, spec, digest, reg_grid)


def _resample(
    executor, ctx, disk, m, name, reg: Measured, *, counts, warned, own_values, resampling,
    progress,
) -> Resampled:  # fmt: skip
    """Every image of registration `name` resampled into the common frame
    (:func:`resample_plan`), cached, with its labels' memberships; label-like images warned
    once (`warned`: those warned already); the thumbnails."""
    plan = resample_plan(
        ctx, m, name, reg, own_values=own_values, interpolation=resampling.interpolation,
        labels=(resampling.label_interpolation, resampling.label_sigma_mm),
    )  # fmt: skip
    keys, found = _run(
        executor, ctx, plan, desc=f"{name}: resampling", progress=progress, counts=counts
    )
    metas = [{**measured, **meta} for measured, meta in zip(reg.metas, found, strict=True)]
    for i, meta in enumerate(found):
        if meta.get("label_like") and i not in warned:
            warned.add(i)
            warn_label_like(str(m.scored_images[i]), meta["label_like"], stacklevel=5)
    pictures = thumbnails(disk, ctx.grid, reg.reference_grid, keys, reg.keys[0], metas)
    return Resampled(keys, metas, reg.frame, reg.frame_spec, reg.reference_grid, pictures)


def _brain_masks(
    executor, ctx, disk, m, name, reg: Measured, *, mask, counts, label_interpolation,
    progress,
) -> BrainMaskDice | None:  # fmt: skip
    """Every subject's brain mask (the manifest's ``masks``) in the common frame under
    registration `name` (:func:`brain_mask_plan`), and its Dice against the common mask:
    the manifest's `mask` (on the common grid) where given, else the majority vote of the
    resampled masks (:func:`~itk_nrreval.io._brain_masks.subject_mask_dice`). None without
    ``masks``."""
    if m.masks is None:
        return None
    plan = brain_mask_plan(ctx, m, name, reg, label_interpolation=label_interpolation)
    keys, _ = _run(
        executor, ctx, plan, desc=f"{name}: brain masks", progress=progress, counts=counts
    )
    return subject_mask_dice(CachedMasks(disk, keys, ctx.grid.shape), common=mask)


def _label_metrics(
    executor, ctx, disk, m, name, r: Resampled, *, scored, values, keep, progress
) -> LabelMetrics | None:  # fmt: skip
    """Registration `name`'s Dice and HD95 (mm) per label and case in the common frame
    (:mod:`itk_nrreval.measures.label_metrics`), from its resampled entries (`r`): each scored
    subject's crisp map (:func:`crisp_plan`), then its side of its cases
    (:func:`distances_plan`; the cases: :func:`label_cases`). The crisp maps leave the
    cache afterwards unless `keep`. None without labels."""
    if values is None:
        return None
    cases = label_cases(m, name, r, scored=scored, values=values)
    plan = crisp_plan(ctx, r, cases)
    crisp_keys, voxels = _run(executor, ctx, plan, desc=f"{name}: label maps", progress=progress)
    crisp = dict(zip(cases.codes, crisp_keys, strict=True))
    plan = distances_plan(ctx, crisp, cases)
    _, sides = _run(executor, ctx, plan, desc=f"{name}: Dice and HD95", progress=progress)
    if not keep:
        for key in set(crisp_keys):
            disk.remove("crisp_labels", key)
    subjects = list(cases.codes)  # the plans' order
    return label_metrics(
        cases, dict(zip(subjects, voxels, strict=True)), dict(zip(subjects, sides, strict=True))
    )


def _score_registration(
    executor, ctx, region_ctx, disk, m, name, reg: Measured, *, coverage, counts, warned,
    own_values, mask, scored, values, region, n_samples, seed, distance, resampling,
    keep_resampled, progress, assess_subjects, flagged_pictured, statistics,
) -> tuple[ReducedRegistration, Resampled]:  # fmt: skip
    """Registration `name` resampled, reduced to its scores, and its label metrics; its
    resampled images leave the cache unless `keep_resampled`, its mean image goes to the
    cache until the end (:func:`_with_held_arrays`)."""
    r = _resample(
        executor, ctx, disk, m, name, reg, counts=counts, warned=warned,
        own_values=own_values, resampling=resampling, progress=progress,
    )  # fmt: skip
    check_region_covered(disk, name, r.keys, scored, region, ctx.grid)
    # before the reduction: the subjects' assessment (assess_subjects) reads them
    brain_masks = _brain_masks(
        executor, ctx, disk, m, name, reg, mask=mask, counts=counts,
        label_interpolation=resampling.label_interpolation, progress=progress,
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
    metrics = _label_metrics(
        executor, region_ctx, disk, m, name, r, scored=scored, values=values,
        keep=keep_resampled, progress=progress,
    )  # fmt: skip
    run = dataclasses.replace(run, label_metrics=metrics)
    if statistics is not None:  # (sigma, g2): the description length was asked for
        dl = registration_description_length(
            disk, m, name, keys=r.keys, frame_spec=r.frame_spec, grid=ctx.grid,
            region=region, scored=scored, statistics=statistics,
        )  # fmt: skip
        run = dataclasses.replace(run, description_length=dl)
    if not keep_resampled:
        for key in set(r.keys):
            disk.remove("resampled", key)
    # on disk until the end, not in memory while the next registrations' tasks run
    mean_key = digest_of([name, r.keys])
    disk.put("mean_image", mean_key, {"mean": run.mean_image})
    return dataclasses.replace(run, mean_image=mean_key), r


def _reduce_registration(
    executor, region_ctx, disk, m, name, r: Resampled, *, brain_masks, scored, values, region,
    coverage, n_samples, seed, distance, interpolation, progress, assess_subjects,
    flagged_pictured,
) -> ReducedRegistration:  # fmt: skip
    """Registration `name`'s scores from its cache entries inside the region, with every
    image's deformation, and the thumbnails of the subjects the report pictures."""
    metas = r.metas
    if values is not None:
        # cheap and derived from the resampled entries: not in the counts
        plan = label_sums_plan(region_ctx, r.keys)
        _, sums = _run(executor, region_ctx, plan, desc=f"{name}: label sums", progress=progress)
        metas = [{**meta, **s} for meta, s in zip(metas, sums, strict=True)]
    plan = bias_plan(region_ctx, [r.keys[i] for i in scored])
    bias_keys, _ = _run(
        executor, region_ctx, plan, desc=f"{name}: bias correction", progress=progress
    )
    run = reduce_to_scores(
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
        bias_keys=bias_keys,
    )
    for key in set(bias_keys):  # derived and cheap: not kept
        disk.remove("bias_corrected", key)
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
        alternative_products,
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
            f = frame_transform(measured[name].frame_spec, grid, disk)
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
