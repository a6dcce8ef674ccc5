"""Evaluate's subject-level confidence step: a grouped jackknife over the subjects.

Which subjects each replicate leaves out (:func:`jackknife_plan`: a subject is an image, or
the images the manifest gives one subject's name), every registration's replicates of every
measure (each specificity replicate's model from the Gram matrix, the overlap's exact from
its per-image sums), and from them the 95% intervals, the paired comparisons, the
probability of being best and the rank stability (:func:`subject_level`); the statistics
themselves are :mod:`itk_nrreval.measures.confidence`'s.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ._progress import progress_bar
from .io.manifest import Manifest
from .measures._ranks import higher_is_better
from .measures.confidence import (
    Comparison,
    RankStability,
    bootstrap_ranks,
    compare,
    jackknife_groups,
    jackknife_interval,
    measure_bounds,
    overlap_replicates,
    probability_best,
    specificity_replicates,
)

__all__ = ["JackknifePlan", "jackknife_plan", "SubjectLevel", "subject_level"]


@dataclass(frozen=True)
class JackknifePlan:
    """What the subject-level jackknife leaves out, in indices of the scored images."""

    left_out: list[np.ndarray]  # the images each specificity replicate leaves out
    overlap_left_out: list[np.ndarray]  # one subject each (the overlap's are exact)
    image_groups: list[str] | None  # each scored image's group (a mixture), or None


def jackknife_plan(
    m: Manifest, scored: Sequence[int], resamples: int | None, *, asked: bool
) -> JackknifePlan | None:
    """The jackknife over the subjects of the scored images, or None where it cannot run:
    fewer than 4 subjects, or groups without ``subjects`` (a warning says why, when
    confidence was `asked` for)."""
    subjects = None if m.subjects is None else [m.subjects[i] for i in scored]
    image_groups = None if m.groups is None else [m.groups[i] for i in scored]
    if image_groups is not None and subjects is None:
        if asked:
            # Leaving out images is not leaving out subjects when a subject has one image
            # per group (modality), and it can leave a group with fewer than 2 images.
            warnings.warn(
                "subject-level intervals are not computed for a manifest with groups and no "
                "subjects (the jackknife would leave out images, not subjects; the manifest's "
                "'subjects' names each image's subject); the specificity's standard error is "
                "Monte-Carlo error only",
                UserWarning,
                stacklevel=4,
            )
        return None
    n_subjects = len(set(subjects)) if subjects is not None else len(scored)
    if n_subjects < 4:
        return None
    left_out = jackknife_groups(
        len(scored), resamples if resamples is not None else min(n_subjects, 50), subjects=subjects
    )
    if image_groups is not None:
        for out in left_out:
            gone = set(out.tolist())
            kept = [g for i, g in enumerate(image_groups) if i not in gone]
            short = [g for g in dict.fromkeys(image_groups) if kept.count(g) < 2]
            if short:
                if asked:
                    warnings.warn(
                        f"subject-level intervals are not computed: leaving subjects out "
                        f"leaves group {short[0]!r} with fewer than 2 images",
                        UserWarning,
                        stacklevel=4,
                    )
                return None
    one_each = jackknife_groups(len(scored), None, subjects=subjects)
    return JackknifePlan(left_out, one_each, image_groups)


@dataclass(frozen=True)
class SubjectLevel:
    """Subject-level confidence: per registration and measure the 95% interval and the
    probability of being best, and the paired comparisons."""

    intervals: dict[str, dict]
    best_p: dict[str, dict]
    comparisons: tuple[Comparison, ...]
    rank_stability: dict[str, RankStability] = field(default_factory=dict)

    @classmethod
    def empty(cls, names) -> SubjectLevel:
        return cls({n: {} for n in names}, {n: {} for n in names}, ())


def subject_level(
    run, values, weightings, plan: JackknifePlan, n_samples, distance, seed, progress
) -> SubjectLevel:
    """Jackknife intervals, paired comparisons and probabilities of being best, for every
    measure and registration of `run`."""
    regs = run.registrations
    level = SubjectLevel.empty(regs)
    comparisons: list[Comparison] = []
    reps = _replicates(run, weightings, plan, n_samples, distance, seed, progress)
    for measure, by_name in reps.items():
        vals = {name: values[name][measure] for name in regs}
        for name in regs:
            level.intervals[name][measure] = jackknife_interval(
                vals[name], by_name[name], bounds=measure_bounds(measure)
            )
        comparisons += compare(measure, vals, by_name)
        pb = probability_best(vals, by_name, higher_is_better=higher_is_better(measure), seed=seed)
        for name in regs:
            level.best_p[name][measure] = pb[name]
        # the subjects' contributions resampled: how firmly each holds its rank
        level.rank_stability[measure] = bootstrap_ranks(
            measure, vals, by_name, higher_is_better=higher_is_better(measure), seed=seed
        )
    return dataclasses.replace(level, comparisons=tuple(comparisons))


def _replicates(run, weightings, plan: JackknifePlan, n_samples, distance, seed, progress):
    """Per measure, per registration, the jackknife replicates (the same subjects left out
    for all)."""
    regs = run.registrations
    out: dict[str, dict[str, np.ndarray]] = {"specificity": {}, "generalization": {}}
    for name, r in progress_bar(regs.items(), desc="confidence", total=len(regs), enabled=progress):
        spec, gen = specificity_replicates(
            r.gram,
            groups=plan.left_out,
            image_groups=plan.image_groups,
            n_samples=n_samples,
            distance=distance,
            seed=seed,
        )
        out["specificity"][name], out["generalization"][name] = spec, gen
    if all(r.overlap_sums is not None for r in regs.values()):
        for name, r in regs.items():
            sums = dict(r.overlap_sums)
            labels = sums.pop("labels")
            by_w = overlap_replicates(
                **sums,
                labels=labels,
                spacing=run.grid.spacing,
                weightings=weightings,
                left_out=plan.overlap_left_out,
            )
            for w, arr in by_w.items():
                out.setdefault(f"overlap.{w}", {})[name] = arr
    return out
