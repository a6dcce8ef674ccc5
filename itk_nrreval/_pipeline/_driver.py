"""The driver of the evaluate pipeline: :func:`run_pipeline`.

It measures every registration's transforms first (frames, coverage, plausibility), finds
the region the scores are taken on, then, one registration at a time (so that the cache
holds one registration's resampled images at a time), resamples its images, reduces them
to its scores, its subjects' quality control and its label metrics, and returns a
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

from .._cache import DiskCache, digest_of
from .._evaluation_options import Execution, Resampling
from .._executors import Executor
from .._images import Geometry, mask_array
from .._resampled_images import ResampledImages, image_slice
from ..frame import common_reference, label_values
from ..manifest import Manifest
from ..plausibility import AffineFit, Plausibility, SubjectThresholds
from ..subject_qc import SubjectQC, ranked
from ._common_frame import frame_transform
from ._coverage import check_region_covered, evaluated_region, left_out_of_scores
from ._image_tasks import (
    Measured,
    Resampled,
    bias_corrected_images,
    brain_mask_dice,
    label_sums,
    measure_registration,
    resample_registration,
)
from ._label_metrics import registration_label_metrics
from ._reduction import ReducedRegistration, alternative_products, reduce_to_scores
from ._task_keys import TaskContext


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
        the scored images (:func:`alternative_products`, its first arguments bound; for
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
        ctx = TaskContext(str(Path(cache).resolve()), grid, mask_key, inverse_consistency)
        counts = _Counts()
        values, own_values = _label_values(m, executor, progress)
        # Every transform measured first (frames, coverage, plausibility): the region the
        # scores are taken on is known before any image is resampled.
        measured = {
            name: measure_registration(
                executor, ctx, disk, m, name, mask=mask, counts=counts, progress=progress
            )
            for name in m.registrations
        }
        entries = {k: (r.keys, r.metas, r.frame) for k, r in measured.items()}
        left_out = left_out_of_scores(m, entries, off_grid)
        scored = tuple(i for i in range(m.n_images) if i not in left_out)
        region, coverage = evaluated_region(disk, grid, mask, m, entries, left_out)
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


@dataclass
class _Counts:
    reused: int = 0
    computed: int = 0

    def add(self, reused: bool) -> None:
        if reused:
            self.reused += 1
        else:
            self.computed += 1


def _score_registration(
    executor, ctx, region_ctx, disk, m, name, reg: Measured, *, coverage, counts, warned,
    own_values, mask, scored, values, region, n_samples, seed, distance, resampling,
    keep_resampled, progress, assess_subjects, flagged_pictured,
) -> tuple[ReducedRegistration, Resampled]:  # fmt: skip
    """Registration `name` resampled, reduced to its scores, and its label metrics; its
    resampled images leave the cache unless `keep_resampled`, its mean image goes to the
    cache until the end (:func:`_with_held_arrays`)."""
    method = resampling.label_interpolation
    r = resample_registration(
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
    check_region_covered(disk, name, r.keys, scored, region, ctx.grid)
    # before the reduction: the subjects' assessment (assess_subjects) reads them
    brain_masks = brain_mask_dice(
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
    label_metrics = registration_label_metrics(
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
        sums = label_sums(executor, region_ctx, name, r.keys, progress)
        metas = [{**meta, **s} for meta, s in zip(metas, sums, strict=True)]
    scored_keys = [r.keys[i] for i in scored]
    bias_keys = bias_corrected_images(executor, region_ctx, name, scored_keys, progress)
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
