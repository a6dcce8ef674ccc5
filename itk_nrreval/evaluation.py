"""Score several registrations of the same images side by side in one common frame.

For every registration of a manifest (:mod:`itk_nrreval.io.manifest`), the N images are
resampled into the common frame (:mod:`itk_nrreval.io.frame`), and scored by the specificity
and generalization of their shape-free texture model (paper, Sections III and V-D; lower is
better) and, when label maps exist, by the generalized Tanimoto overlap of their resampled
fuzzy memberships for each label weighting (higher is better). The same seed -- the same
model samples in standardized parameter space -- is used for every registration (common
random numbers), so differences between registrations are not sampling noise.

:func:`evaluate` computes and returns an :class:`EvaluationResult`; it writes nothing.
Writing is the result's: :meth:`EvaluationResult.write` (the reports), and
:func:`export_resampled` (the resampled images, from the evaluation's cache).

Here: the result types (:class:`RegistrationScores`, :class:`EvaluationResult`), evaluate,
and the assembly of its result from the pipeline's run (:mod:`itk_nrreval._pipeline`). Its
steps and parts live in private modules beside it, their public names re-exported here: the
option groups (``_evaluation_options``), the per-subject quality control
(``_evaluation_subjects``), the subject-level jackknife (``_evaluation_jackknife``), the
ranks (``_ranks``) and the resampled images' record and export (``_resampled_images``).
"""

from __future__ import annotations

import dataclasses
import os
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ._errors import InputError
from ._evaluation_jackknife import SubjectLevel, jackknife_plan, subject_level
from ._evaluation_options import (
    Confidence,
    Execution,
    Resampling,
    check_options,
    confidence_settings,
    option_or_default,
)
from ._evaluation_subjects import subject_assessor
from ._executors import default_threads, local_executor
from ._output import json_number
from ._pipeline import Coverage, run_pipeline
from .io._resampled_images import ResampledImages, export_resampled
from .io.frame import FrameMapping
from .io.manifest import Manifest, load_manifest
from .io.plausibility import (
    Plausibility,
    SubjectThresholds,
    Thresholds,
    combine,
    flags,
    smallest_extent_mm,
)
from .measures._ranks import higher_is_better, ranks, relative_ranks
from .measures.confidence import TIE_Z as TIE_Z  # read from here before tie_groups moved there
from .measures.confidence import Comparison, Interval, RankStability, significance_map, tie_groups
from .measures.description_length import DescriptionLength
from .measures.label_metrics import LabelMetrics
from .measures.specificity import GeneralizationResult, SpecificityResult
from .measures.subject_qc import SubjectQC, across_registrations
from .measures.verdict import Decision, OpenPair, Verdict, verdict
from .report import FLAGGED_SUBJECTS_SHOWN, write_evaluation

__all__ = [
    "Resampling",
    "Confidence",
    "Execution",
    "RegistrationScores",
    "EvaluationResult",
    "ResampledImages",
    "Verdict",
    "Decision",
    "OpenPair",
    "evaluate",
    "export_resampled",
    "verdict",
    "ranks",
    "relative_ranks",
    "tie_groups",
    "higher_is_better",
]


@dataclass(frozen=True)
class RegistrationScores:
    """One registration's scores in an :class:`EvaluationResult`: its measures, intervals, flags.

    Attributes
    ----------
    name : str
    specificity : SpecificityResult
        Lower is better. Its ``stderr`` is Monte-Carlo error only; the subject-level
        interval is ``intervals["specificity"]``.
    generalization : GeneralizationResult
        Lower is better.
    overlap : dict of str to float
        Generalized Tanimoto overlap per weighting (empty without labels); higher is better.
    frame : FrameMapping
        How the registration's frame was reached, and the spread (mm) of its estimates.
    plausibility : Plausibility
        Its transforms' deformation plausibility, combined over the images
        (:func:`itk_nrreval.io.plausibility.combine`), on its own reference grid.
    flags : tuple of str
        Why the registration is implausible, in words; empty when it is plausible.
    intervals : dict of str to Interval
        Subject-level 95% interval per measure (``specificity``, ``generalization``,
        ``overlap.<weighting>``); empty when confidence was not computed.
    probability_best : dict of str to float
        Per measure, the probability that this registration is the best of those compared
        (:func:`itk_nrreval.measures.confidence.probability_best`).
    coverage : Coverage or None
        How much of the common grid its images cover; the scores are taken where every
        image covers it under every registration (:class:`itk_nrreval.Coverage`).
    subjects : tuple of SubjectQC
        Every subject's quality control under this registration, in manifest order
        (:mod:`itk_nrreval.measures.subject_qc`): which subjects stand out from the cohort, and why.
    label_metrics : LabelMetrics or None
        The numbers registration papers report from labels: Dice and HD95 (mm) per label
        and case in the common frame, against the registration's reference subject or
        over every pair (:mod:`itk_nrreval.measures.label_metrics`); None without labels.
    description_length : DescriptionLength or None
        Bits per subject to code the registered group, shape and texture priced in one
        currency (:mod:`itk_nrreval.measures.description_length`); lower is better. None
        unless ``evaluate(description_length=True)``.
    family : tuple of str or None
        ``(method, engine)`` from the manifest's ``parameters`` of the registration, where
        it gives both: the verdict reads the description length only between registrations
        of one family.
    """

    name: str
    specificity: SpecificityResult
    generalization: GeneralizationResult
    overlap: Mapping[str, float]
    frame: FrameMapping
    plausibility: Plausibility
    flags: tuple[str, ...] = ()
    intervals: Mapping[str, Interval] = field(default_factory=dict)
    probability_best: Mapping[str, float] = field(default_factory=dict)
    coverage: Coverage | None = None
    subjects: tuple[SubjectQC, ...] = ()
    label_metrics: LabelMetrics | None = None
    description_length: DescriptionLength | None = None
    family: tuple[str, str] | None = None

    @property
    def flagged_subjects(self) -> tuple[SubjectQC, ...]:
        """The subjects with a flag, in manifest order."""
        return tuple(s for s in self.subjects if s.flags)

    @property
    def folded_fraction(self) -> float:
        """Mean over images of the fraction of voxels where the transform folds."""
        return self.plausibility.folded_fraction

    @property
    def folded_max(self) -> float:
        """The largest per-image folded fraction."""
        return self.plausibility.folded_max

    def measures(self) -> dict[str, float]:
        """Every scalar score by measure name (``specificity``, ``overlap.<weighting>``...)."""
        out = {"specificity": self.specificity.value, "generalization": self.generalization.value}
        out.update({f"overlap.{w}": v for w, v in self.overlap.items()})
        return out

    def to_dict(self) -> dict:
        def ci(measure):
            iv = self.intervals.get(measure)
            return iv.to_list() if iv is not None else None

        def se(measure):
            iv = self.intervals.get(measure)
            return json_number(iv.stderr) if iv is not None else None

        plaus = self.plausibility.to_dict()
        plaus["flags"] = list(self.flags)
        return {
            "specificity": {
                "value": self.specificity.value,
                "stderr": self.specificity.stderr,
                "stderr_subjects": se("specificity"),
                "ci95": ci("specificity"),
                **(
                    {"mixture": self.specificity.mixture.to_dict()}
                    if self.specificity.mixture is not None
                    else {}
                ),
            },
            "generalization": {
                "value": self.generalization.value,
                "stderr": self.generalization.stderr,
                "stderr_subjects": se("generalization"),
                "ci95": ci("generalization"),
            },
            "overlap": {w: json_number(v) for w, v in self.overlap.items()},
            "overlap_ci95": {w: ci(f"overlap.{w}") for w in self.overlap},
            "plausibility": plaus,
            "probability_best": {m: json_number(v) for m, v in self.probability_best.items()},
            "frame": self.frame.to_dict(),
            "coverage": self.coverage.to_dict() if self.coverage is not None else None,
            "folded_fraction": self.folded_fraction,
            "folded_max": self.folded_max,
            "n_modes": self.specificity.n_modes,
            "subjects": [q.to_dict() for q in self.subjects],
            "label_metrics": (
                self.label_metrics.to_dict() if self.label_metrics is not None else None
            ),
            "description_length": (
                self.description_length.to_dict() if self.description_length is not None else None
            ),
            "family": list(self.family) if self.family is not None else None,
        }


@dataclass(frozen=True)
class EvaluationResult:
    """Every registration's scores, ranks, confidence and the verdict.

    Attributes
    ----------
    scores : dict of str to RegistrationScores
        In the manifest's order.
    ranks : dict of str to dict of str to int
        ``ranks[measure][registration]``: 1 is best; scores tied within noise
        (:func:`~itk_nrreval.measures.confidence.tie_groups`) share the best rank (:meth:`tied_with`
        names them).
    relative_ranks : dict of str to dict of str to float
        ``relative_ranks[measure][registration]`` in percent: best 100, worst 0, linear
        between (paper, Section V-E); tied scores share one (:func:`relative_ranks`).
    common_frame : str
        The registration whose reference frame is the common frame.
    mean_images : dict of str to ndarray of shape (*spatial_zyx,)
        Each registration's mean resampled image on the common grid.
    inputs : dict
        The manifest's description (:meth:`Manifest.describe`).
    options : dict
        n_samples, seed, distance, interpolation, weightings, confidence settings, flag
        thresholds.
    version : str
        The toolkit version.
    run : dict
        How the run was executed: ``scheduler`` (None: in this process), ``workers``, and
        how many per-image results were reused from the cache (``cache_reused``) or
        computed (``cache_computed``).
    comparisons : tuple of Comparison
        Every pairwise difference per measure with its subject-level interval.
    verdict : Verdict or None
    thumbnails : dict of str to dict of str to ndarray
        Per registration, the small arrays the HTML report draws (middle slices of two
        subjects, of subject 0's labels and det J, the log det J histogram over all
        subjects; :attr:`itk_nrreval._pipeline.ReducedRegistration.thumbnails`). Not in
        ``results.json``.
    rank_stability : dict of str to RankStability
        Per measure, how often each registration takes each rank over bootstraps of the
        subjects' jackknife contributions (:func:`itk_nrreval.measures.confidence.bootstrap_ranks`);
        empty when confidence was not computed. In ``results.json`` beside
        ``significance``: per measure (and ``verdict``), which registration is told apart
        from which (:meth:`significance`).
    resampled : ResampledImages or None
        Where every registration's resampled images are in the evaluation's cache, and the
        evaluated region: what :func:`itk_nrreval.evaluation.export_resampled` writes as
        NIfTI. Not in ``results.json``.
    """

    scores: Mapping[str, RegistrationScores]
    ranks: Mapping[str, Mapping[str, int]]
    relative_ranks: Mapping[str, Mapping[str, float]]
    common_frame: str
    mean_images: Mapping[str, np.ndarray] = field(repr=False)
    inputs: Mapping[str, Any] = field(repr=False)
    options: Mapping[str, Any]
    version: str
    run: Mapping[str, Any] = field(default_factory=dict)
    comparisons: tuple[Comparison, ...] = ()
    verdict: Verdict | None = None
    thumbnails: Mapping[str, Mapping[str, np.ndarray]] = field(default_factory=dict, repr=False)
    rank_stability: Mapping[str, RankStability] = field(default_factory=dict, repr=False)
    resampled: ResampledImages | None = field(default=None, repr=False, compare=False)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self.scores)

    @property
    def measures(self) -> tuple[str, ...]:
        """Measure names, in report order."""
        return tuple(self.ranks)

    def tied_with(self, measure: str, name: str) -> tuple[str, ...]:
        """The other registrations whose `measure` is tied with `name`'s (the same rank)."""
        rank = self.ranks[measure][name]
        if rank is None:
            return ()
        return tuple(n for n, r in self.ranks[measure].items() if r == rank and n != name)

    def write(self, out_dir: str | os.PathLike, *, figures: bool = True) -> list[Path]:
        """Write the reports ``nrreval evaluate`` writes into `out_dir` (created if needed).

        ``results.json`` (:meth:`to_dict`), ``results.csv``, ``metrics.csv`` (the numbers
        registration papers report: Dice and HD95 per label, SDlogJ, folding),
        ``summary.md`` (the verdict, the paper's Table 3 layout and the flagged
        subjects), ``subjects.csv`` (every
        subject's quality control) and, with `figures`, ``specificity.png``,
        ``specificity_vs_overlap.png``, ``mean_images.png``, ``subjects.png`` (every
        subject's z-score) and ``report.html`` (one self-contained page to read: the
        verdict, the scores with their legend, per registration its flagged subjects with
        their pictures, its images, deformation and frame, the inputs and options; it
        embeds the same figures), through :func:`itk_nrreval.report.write_evaluation`. Each
        file is written under a temporary name and renamed when complete; files of other
        names in `out_dir` are left alone (``nrreval evaluate --out DIR`` writes into a
        staged copy of DIR and swaps it in whole: :func:`itk_nrreval._output.staged_folder`).

        Parameters
        ----------
        out_dir : path
            The folder to write into.
        figures : bool, keyword-only
            Also the PNG figures and ``report.html``; False: the text files only.

        Returns
        -------
        list of Path
            The files written.
        """
        return write_evaluation(self, out_dir, figures=figures)

    def to_dict(self) -> dict:
        """The content of ``results.json``."""
        regs = {}
        for name, s in self.scores.items():
            d = s.to_dict()
            d["rank"] = {m: self.ranks[m][name] for m in self.ranks}
            d["relative_rank"] = {m: self.relative_ranks[m][name] for m in self.ranks}
            d["tied_with"] = {m: list(self.tied_with(m, name)) for m in self.ranks}
            regs[name] = d
        out = {
            "version": self.version,
            "common_frame": self.common_frame,
            "options": dict(self.options),
            "inputs": dict(self.inputs),
            "registrations": regs,
            "comparisons": [c.to_dict() for c in self.comparisons],
            "verdict": self.verdict.to_dict() if self.verdict is not None else None,
            "rank_stability": {m: rs.to_dict() for m, rs in self.rank_stability.items()},
            "significance": self.significance(),
        }
        if self.run:
            out["run"] = dict(self.run)
        return out

    def significance(self) -> dict[str, dict[str, dict[str, str]]]:
        """Which registration is told apart from which: per measure with paired comparisons
        (:func:`itk_nrreval.measures.confidence.significance_map`: ``"better"``, ``"worse"``, ``"not
        separable"``), and under ``"verdict"`` what the verdict decides (``"decided better"``,
        ``"decided worse"``, ``"open"``). ``out[key][a][b]`` says it of `a` against `b`."""
        names = list(self.names)
        measured = dict.fromkeys(c.measure for c in self.comparisons)
        out = {m: significance_map(self.comparisons, m, names) for m in measured}
        if self.verdict is not None:
            decided = {a: {b: "open" for b in names if b != a} for a in names}
            for d in self.verdict.decisions:
                decided[d.better][d.worse] = "decided better"
                decided[d.worse][d.better] = "decided worse"
            out["verdict"] = decided
        return out


def evaluate(
    manifest: Manifest | Mapping | str | os.PathLike,
    *,
    n_samples: int = 100_000,
    seed: int = 0,
    distance: str = "l1",
    weightings: Sequence[str] | None = None,
    resampling: Resampling | None = None,
    confidence: bool | Confidence = True,
    thresholds: Thresholds | None = None,
    subject_thresholds: SubjectThresholds | None = None,
    inverse_consistency: bool = True,
    description_length: bool = False,
    execution: Execution | None = None,
    progress: bool = True,
) -> EvaluationResult:
    """Resample every registration into the common frame and score it; write nothing.

    The cache (`execution`'s, else a temporary folder removed at the end) is the only
    place it writes to. Write the result with :meth:`EvaluationResult.write`, and its
    resampled images with :func:`export_resampled`.

    Parameters
    ----------
    manifest : Manifest, dict or path
        See :mod:`itk_nrreval.io.manifest`; checked in full before any heavy work. In a dict,
        every image and transform may be an object in memory (``sitk.Image``, ITK Python
        images and transforms, ``sitk.Transform``, an array with its grid), mixed with paths.
    n_samples : int
        M, the model samples for specificity (the same M and seed for every registration).
    seed : int
        Seed of the model samples (common random numbers across registrations).
    distance : {"l1", "l2"}
        Parameter-space distance (the paper's Table 3 uses L1).
    weightings : sequence of {"volume", "inverse_volume", "inverse_volume_squared", \
"complexity", "inverse_volume_complexity"}
        Overlap label weightings to report (all read from one overlap table); default all
        five, in that order.
    resampling : Resampling, optional
        How images and label maps are resampled into the common frame (:class:`Resampling`;
        default ``Resampling()``, linear for both).
    confidence : bool or Confidence
        Subject-level confidence intervals, comparisons and probabilities of being best:
        True (the default) with the settings of ``Confidence()``, a :class:`Confidence`
        with its settings, or False (off).
    thresholds : Thresholds, optional
        Deformation-plausibility flag thresholds (:class:`itk_nrreval.io.plausibility.Thresholds`,
        whose docstring gives the defaults and their rationale). A flagged registration keeps
        its scores; the flag is a warning in the verdict, not a decision
        (:mod:`itk_nrreval.measures.verdict`: only severe folding decides against it).
    subject_thresholds : SubjectThresholds, optional
        When a subject of a registration is flagged as failed
        (:class:`itk_nrreval.io.plausibility.SubjectThresholds`; results in
        ``RegistrationScores.subjects``). A subject whose field of view covers less of the
        common grid than ``off_grid_coverage`` times the median subject's is also left out
        of every registration's scores (a warning names it).
    inverse_consistency : bool
        Measure each transform's inverse consistency (one numerical inversion per image).
    description_length : bool
        Each registration's description length (``RegistrationScores.description_length``,
        :mod:`itk_nrreval.measures.description_length`): label-free evidence the verdict
        reads between settings of one registration method. Off by default: it samples every
        transform's displacement on the common grid twice and takes 2 (dim + 1) Fourier
        transforms of the grid per image. Not for a manifest whose images form groups.
    execution : Execution, optional
        Where the tasks run and the per-image cache (:class:`Execution`; default
        ``Execution()``: in this process, cache in a temporary folder).
    progress : bool
        Progress bars on stderr (resampling, model, specificity search).

    Returns
    -------
    EvaluationResult

    Raises
    ------
    InputError
        A bad manifest (every problem listed in one message).
    ValueError
        An option outside its accepted values, or of the wrong type (`resampling` not a
        :class:`Resampling`, ...).

    Warns
    -----
    RuntimeWarning
        When a registration is flagged as implausible (folding, rough fields, a frame
        that the registrations disagree about).
    """
    weightings = check_options(n_samples, distance, weightings)
    resampling = option_or_default("resampling", resampling, Resampling)
    execution = option_or_default("execution", execution, Execution)
    thresholds = option_or_default("thresholds", thresholds, Thresholds)
    subject_thresholds = option_or_default(
        "subject_thresholds", subject_thresholds, SubjectThresholds
    )
    asked, settings = confidence_settings(confidence)
    m = load_manifest(manifest)
    run, run_info = _execute(
        m, n_samples=int(n_samples), seed=seed, distance=distance, progress=progress,
        resampling=resampling, execution=execution, subject_thresholds=subject_thresholds,
        inverse_consistency=inverse_consistency, description_length=bool(description_length),
        assess_subjects=subject_assessor(m, subject_thresholds),
        flagged_pictured=FLAGGED_SUBJECTS_SHOWN,  # the report's pictures of flagged subjects
    )  # fmt: skip
    return _assembled(
        m, run, run_info, weightings=weightings, n_samples=n_samples, seed=seed,
        distance=distance, resampling=resampling, asked=asked, settings=settings,
        thresholds=thresholds, subject_thresholds=subject_thresholds,
        inverse_consistency=inverse_consistency, progress=progress,
    )  # fmt: skip


def _assembled(
    m: Manifest, run, run_info, *, weightings, n_samples, seed, distance,
    resampling: Resampling, asked: bool, settings: Confidence, thresholds, subject_thresholds,
    inverse_consistency, progress,
) -> EvaluationResult:  # fmt: skip
    """The pipeline's `run` turned into the result: every registration's scores with their
    subject-level confidence (where `asked` for and possible), flags and subjects
    (assessed while the pipeline ran), ranked, with the options recorded."""
    # the default depends on n_samples: resolved here, not in Confidence
    confidence_samples = settings.samples
    if confidence_samples is None:
        confidence_samples = min(int(n_samples), 100_000)
    regs = run.registrations
    values = {name: _values(r, weightings) for name, r in regs.items()}
    # the jackknife runs over the subjects in the scores
    plan = jackknife_plan(m, _scored_images(run), settings.resamples, asked=asked)
    confidence = asked and plan is not None
    level = SubjectLevel.empty(regs)
    if confidence:
        level = subject_level(
            run, values, weightings, plan, confidence_samples, distance, seed, progress
        )
    extent = smallest_extent_mm(run.grid)
    scores = _registration_scores(
        run,
        values,
        level,
        across_registrations(
            {name: r.subjects for name, r in regs.items()}, thresholds=subject_thresholds
        ),
        weightings=weightings,
        thresholds=thresholds,
        extent_mm=extent,
        label_names=m.label_names,
        families={name: _registration_family(reg) for name, reg in m.registrations.items()},
    )
    _warn_if_flagged(scores)
    options = _recorded_options(
        m,
        run,
        plan,
        confidence=confidence,
        confidence_samples=confidence_samples,
        resampling=resampling,
        inverse_consistency=inverse_consistency,
        thresholds=thresholds,
        subject_thresholds=subject_thresholds,
        extent_mm=extent,
    )
    return _result(
        m,
        scores,
        {name: r.mean_image for name, r in regs.items()},
        run.label_values,
        weightings,
        n_samples,
        seed,
        distance,
        resampling.interpolation,
        run=run_info,
        comparisons=level.comparisons,
        rank_stability=level.rank_stability,
        extra_options=options,
        thumbnails={name: r.thumbnails for name, r in regs.items()},
        resampled=run.resampled,
    )


def _recorded_options(
    m: Manifest, run, plan, *, confidence, confidence_samples, resampling: Resampling,
    inverse_consistency, thresholds, subject_thresholds, extent_mm,
) -> dict:  # fmt: skip
    """The options a result records besides the sampling's (``results.json``'s
    ``options``, in this order)."""
    return {
        "confidence": confidence,
        "confidence_samples": int(confidence_samples),
        "resamples": None if plan is None else len(plan.left_out),
        "inverse_consistency": bool(inverse_consistency),
        "description_length": any(
            r.description_length is not None for r in run.registrations.values()
        ),
        "label_interpolation": resampling.label_interpolation,
        "label_sigma_mm": (
            None if resampling.label_sigma_mm is None else float(resampling.label_sigma_mm)
        ),
        "thresholds": dataclasses.asdict(thresholds),
        "subject_thresholds": dataclasses.asdict(subject_thresholds),
        # whose voxels are scored: the registered images, or the manifest's other scans
        "scored_images": "images" if m.evaluation_images is None else "evaluation_images",
        # images off the common grid: in no registration's scores (manifest indices)
        "left_out_of_scores": [i for i in range(m.n_images) if i not in set(_scored_images(run))],
        # what frame_spread_fraction is a fraction of: the reports state the limit in mm
        "field_of_view_mm": extent_mm,
        "manifest_warnings": list(m.notes),  # the manifest check's, as it gave them
    }


def _execute(m: Manifest, *, execution: Execution, **options):
    """Run the per-image tasks and their reductions, in this process or on Dask (where
    `execution` says, with its cache): the pipeline's run (`options`: the rest of
    :func:`~itk_nrreval._pipeline.run_pipeline`'s), and what ran it
    (``{"scheduler", "workers", "threads", "cache_reused", "cache_computed"}``)."""
    scheduler, workers, threads = execution.scheduler, execution.workers, execution.threads
    if scheduler is None:
        executor = local_executor(default_threads() if threads is None else threads)
        run = run_pipeline(m, executor, execution=execution, **options)
        run_info = {"scheduler": None, "workers": 1, "threads": executor.n_workers}
    else:
        from ._scaleout import DaskExecutor, check_scheduler, cluster_client

        check_scheduler(scheduler, workers)
        job, cache = execution._job_resources(), execution.cache
        with cluster_client(scheduler, workers=workers, cache=cache, job=job) as client:
            executor = DaskExecutor(client)
            run = run_pipeline(m, executor, execution=execution, **options)
        run_info = {"scheduler": scheduler, "workers": executor.n_workers, "threads": 1}
    run_info.update(cache_reused=run.cache_reused, cache_computed=run.cache_computed)
    return run, run_info


def _values(r, weightings) -> dict[str, float]:
    """One registration run's scores by measure name."""
    overlap = {}
    if r.overlap is not None:
        overlap = {f"overlap.{w}": r.overlap.generalized(w) for w in weightings}
    return {
        "specificity": r.specificity.value,
        "generalization": r.generalization.value,
        **overlap,
    }


def _registration_scores(
    run,
    values,
    level: SubjectLevel,
    subjects,
    *,
    weightings,
    thresholds,
    extent_mm,
    label_names: Mapping[int, str] | None = None,
    families: Mapping[str, tuple[str, str] | None] | None = None,
) -> dict[str, RegistrationScores]:
    """Every registration's scores, plausibility, flags and subjects (its label metrics
    carrying the manifest's `label_names`), with its description length (where computed)
    and `families`' entry."""
    families = families or {}
    regs = run.registrations
    plaus = {name: combine(r.plausibility) for name, r in regs.items()}
    reg_flags = flags(
        plaus,
        frame_spread_mm={name: r.frame.spread_mean_mm for name, r in regs.items()},
        extent_mm=extent_mm,
        thresholds=thresholds,
    )
    scores = {}
    for name, r in regs.items():
        overlap = {w: values[name][f"overlap.{w}"] for w in weightings} if r.overlap else {}
        scores[name] = RegistrationScores(
            name,
            r.specificity,
            r.generalization,
            overlap,
            r.frame,
            plaus[name],
            tuple(reg_flags[name]),
            level.intervals[name],
            level.best_p[name],
            r.coverage,
            subjects[name],
            label_metrics=_named(r.label_metrics, label_names),
            description_length=r.description_length,
            family=families.get(name),
        )
    return scores


def _registration_family(reg) -> tuple[str, str] | None:
    """``(method, engine)`` of a manifest registration's ``parameters``, where it gives both
    (as ``nrreval register`` and the benchmarks record them); else None."""
    p = reg.parameters or {}
    method, engine = p.get("method"), p.get("engine")
    if method is None or engine is None:
        return None
    return (str(method), str(engine))


def _named(lm: LabelMetrics | None, names: Mapping[int, str] | None) -> LabelMetrics | None:
    """`lm` carrying the labels' names (the values shown beside them), where both exist."""
    return lm if lm is None or names is None else dataclasses.replace(lm, names=names)


def _scored_images(run) -> tuple[int, ...]:
    """The images in the scores (the same for every registration of a run)."""
    return next(iter(run.registrations.values())).scored


def _warn_if_flagged(scores: Mapping[str, RegistrationScores]) -> None:
    for name, s in scores.items():
        if s.flags:
            warnings.warn(
                f"registration {name!r} is flagged as implausible: {'; '.join(s.flags)}",
                RuntimeWarning,
                stacklevel=4,
            )


def _own_stderr(scores, measure, comparisons) -> dict[str, float] | None:
    """The standard errors that tie `measure`'s scores besides the paired comparisons.

    Specificity: its Monte-Carlo standard error, always (the paired jackknife shares the
    model samples, so it does not see them). Generalization: its standard error over the
    images, only when no paired subject-level interval was computed (that interval measures
    the same subject-level noise, paired, hence more sharply). Overlap: none.
    """
    if measure == "specificity":
        return {n: s.specificity.stderr for n, s in scores.items()}
    if measure == "generalization" and not any(c.measure == measure for c in comparisons):
        return {n: s.generalization.stderr for n, s in scores.items()}
    return None


def _judged(scores, comparisons, *, has_labels: bool) -> Verdict:
    """The verdict on `scores`, in the images' dimension (the benchmark re-judges saved
    evaluations through this, with and without labels)."""
    dimension = next(iter(scores.values())).frame.transform.GetDimension()
    return verdict(scores, comparisons, has_labels=has_labels, dimension=dimension)


def _result(
    m,
    scores,
    means,
    values,
    weightings,
    n_samples,
    seed,
    distance,
    interpolation,
    run,
    comparisons=(),
    extra_options=None,
    thumbnails=None,
    rank_stability=None,
    resampled=None,
) -> EvaluationResult:
    """Ranks and relative ranks of every measure, and the result object."""
    from ._version import __version__

    measures = ["specificity", "generalization"]
    if m.labels is not None:
        measures += [f"overlap.{w}" for w in weightings]
    rank_table, rel_table = {}, {}
    for measure in measures:
        values_by_name = {n: s.measures()[measure] for n, s in scores.items()}
        noise = dict(
            higher_is_better=higher_is_better(measure),
            stderr=_own_stderr(scores, measure, comparisons),
            comparisons=[c for c in comparisons if c.measure == measure],
        )
        rank_table[measure] = ranks(values_by_name, **noise)
        rel_table[measure] = relative_ranks(values_by_name, **noise)
    options = {
        "n_samples": int(n_samples),
        "seed": int(seed),
        "distance": distance,
        "interpolation": interpolation,
        "weightings": list(weightings),
        "label_values": values,
        **(extra_options or {}),
    }
    if not scores:  # pragma: no cover - the manifest has at least one registration
        raise InputError("manifest: no registrations")
    return EvaluationResult(
        scores,
        rank_table,
        rel_table,
        m.common_frame,
        means,
        m.describe(),
        options,
        __version__,
        run=dict(run),
        comparisons=tuple(comparisons),
        verdict=_judged(scores, comparisons, has_labels=m.labels is not None),
        thumbnails=dict(thumbnails or {}),
        rank_stability=dict(rank_stability or {}),
        resampled=resampled,
    )
