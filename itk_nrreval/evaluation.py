"""Score several registrations of the same images side by side in one common frame.

For every registration of a manifest (:mod:`itk_nrreval.manifest`), the N images are
resampled into the common frame (:mod:`itk_nrreval.frame`), and scored by the specificity
and generalization of their shape-free texture model (paper, Sections III and V-D; lower is
better) and, when label maps exist, by the generalized Tanimoto overlap of their resampled
fuzzy memberships for each label weighting (higher is better). The same seed -- the same
model samples in standardized parameter space -- is used for every registration (common
random numbers), so differences between registrations are not sampling noise.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ._errors import InputError, readable
from ._executors import default_threads, local_executor
from ._memberships import LABEL_INTERPOLATIONS
from ._output import check_output_folder, json_number, staged_folder
from ._pipeline import Coverage, run_pipeline
from ._progress import progress_bar
from .confidence import TIE_Z as TIE_Z  # read from here before tie_groups moved there
from .confidence import (
    Comparison,
    Interval,
    RankStability,
    bootstrap_ranks,
    compare,
    jackknife_groups,
    jackknife_interval,
    measure_bounds,
    overlap_replicates,
    probability_best,
    significance_map,
    specificity_replicates,
    tie_groups,
)
from .frame import FrameMapping
from .label_metrics import LabelMetrics
from .manifest import Manifest, load_manifest
from .overlap import WEIGHTINGS
from .plausibility import (
    Plausibility,
    SubjectThresholds,
    Thresholds,
    combine,
    flags,
    smallest_extent_mm,
)
from .report import FLAGGED_SUBJECTS_SHOWN, write_evaluation
from .specificity import GeneralizationResult, SpecificityResult
from .subject_qc import (
    SubjectQC,
    across_registrations,
    assess_subjects,
    ranked,
    reference_subject,
    transform_mixups,
)
from .verdict import Decision, OpenPair, Verdict, verdict

__all__ = [
    "Resampling",
    "Confidence",
    "Execution",
    "RegistrationScores",
    "EvaluationResult",
    "Verdict",
    "Decision",
    "OpenPair",
    "evaluate",
    "verdict",
    "ranks",
    "relative_ranks",
    "tie_groups",
    "higher_is_better",
]

_DISTANCES = ("l1", "l2")
_INTERPOLATIONS = ("linear", "bspline")


@dataclass(frozen=True, kw_only=True)
class Resampling:
    """How :func:`evaluate` resamples the images and label maps into the common frame.

    Attributes
    ----------
    interpolation : {"linear", "bspline"}
        Intensity interpolation (default ``"linear"``).
    label_interpolation : {"linear", "nearest", "gaussian"}
        How label maps become the overlap's fuzzy memberships in the common frame
        (:func:`itk_nrreval._memberships.resample_label_memberships`): one-hot memberships
        resampled linearly (partial memberships within a voxel of every boundary; the
        default), crisp nearest-neighbour labels, or one-hot memberships smoothed by a
        Gaussian of `label_sigma_mm` mm and then resampled linearly. Recorded in the
        result's options. A perfect registration does not reach overlap 1 with any of them
        (each subject's labels sit on its own grid, so boundaries land between common-frame
        voxels at different places), and the choice moves the ceiling (``docs/outputs.md``).
    label_sigma_mm : float, optional
        The Gaussian's standard deviation (mm); only with, and required by,
        ``label_interpolation="gaussian"``.

    Raises
    ------
    ValueError
        A value outside its accepted ones (the message names the attribute).
    """

    interpolation: str = "linear"
    label_interpolation: str = "linear"
    label_sigma_mm: float | None = None

    def __post_init__(self) -> None:
        if self.interpolation not in _INTERPOLATIONS:
            raise ValueError(
                f"interpolation: {self.interpolation!r} is not one of {_INTERPOLATIONS}"
            )
        method, sigma_mm = self.label_interpolation, self.label_sigma_mm
        if method not in LABEL_INTERPOLATIONS:
            raise ValueError(
                f"label_interpolation: {method!r} is not one of {LABEL_INTERPOLATIONS}"
            )
        if method == "gaussian":
            ok = isinstance(sigma_mm, (int, float)) and not isinstance(sigma_mm, bool)
            if not ok or not 0 < sigma_mm < math.inf:
                raise ValueError(
                    f"label_sigma_mm: label_interpolation='gaussian' needs a finite sigma > 0 "
                    f"mm, got {readable(sigma_mm)}"
                )
        elif sigma_mm is not None:
            raise ValueError(
                f"label_sigma_mm: only with label_interpolation='gaussian', not {method!r}"
            )


@dataclass(frozen=True, kw_only=True)
class Confidence:
    """The settings of :func:`evaluate`'s subject-level confidence.

    Subject-level 95% intervals of every score and every pairwise difference, and the
    probability that each registration is best (:mod:`itk_nrreval.confidence`): a grouped
    jackknife over the subjects, each replicate's model from the Gram matrix. Giving
    ``evaluate(confidence=Confidence(...))`` turns it on with these settings;
    ``confidence=True`` is ``Confidence()``.

    Attributes
    ----------
    samples : int, optional
        Model samples per jackknife replicate (default ``min(n_samples, 100_000)`` of the
        evaluation's `n_samples`); the same seed as the main run (common random numbers).
    resamples : int, optional
        Jackknife groups G for specificity and generalization (default ``min(S, 50)`` for
        S subjects; G = S leaves one subject out at a time). The overlap always leaves one
        subject out (exact and free from the per-image sums). A subject is an image, or
        the images the manifest's ``subjects`` gives one name (a manifest with ``groups``
        needs ``subjects`` for subject-level confidence).

    Raises
    ------
    ValueError
        A count that is not an integer >= 2 (the message names the attribute).
    """

    samples: int | None = None
    resamples: int | None = None

    def __post_init__(self) -> None:
        for name in ("samples", "resamples"):
            if getattr(self, name) is not None:
                _check_positive(name, getattr(self, name), 2)


@dataclass(frozen=True, kw_only=True)
class Execution:
    """Where :func:`evaluate`'s per-image tasks run, and where their results are cached.

    Attributes
    ----------
    scheduler : str, optional
        Run the tasks on a Dask cluster (``docs/large-cohorts.md``): ``"local"`` starts a
        local cluster of `workers` single-threaded processes; ``"slurm"``, ``"pbs"`` or
        ``"sge"`` submits batch jobs running `workers` single-threaded workers, through
        dask-jobqueue (the `job_*` attributes; `cache` required); otherwise the address of
        a running scheduler. Default: in this process. Either way the same tasks run, no
        process holds all the images, and the numbers are the same.
    workers : int, optional
        With ``scheduler="local"``, the number of worker processes (default: CPU count);
        with a job queue (required), the number of workers, in ``ceil(workers /
        job_cores)`` jobs (work starts when the first has joined); with an address, wait
        until that many workers have joined.
    threads : int, optional
        Without a scheduler, how many tasks run at once on threads of this process
        (default: 2 on two or more cores, else 1). Each task uses every core itself; a
        second one at once keeps them busy while the first reads files. Each running task
        holds one image's fields (``docs/speed.md``). Where numba has neither OpenMP nor
        TBB (its ``workqueue`` threading layer cannot run kernels on several threads at
        once), tasks run one at a time, with a warning when more were asked for. The
        numbers do not depend on it.
    cache : path, optional
        The folder of the per-image result cache (with a scheduler: shared by driver and
        workers): a rerun -- after an interruption, or with more images or registrations --
        recomputes only what changed, and resamples the images again unless
        `keep_resampled`. Entries are keyed by the inputs' content (voxel values,
        grids, transform parameters), so objects in memory find the entries of the same
        images and transforms given as files, and the same objects find them again in a new
        process. Default: ``out/cache`` with evaluate's `out`, else a temporary folder,
        removed afterwards.
    keep_resampled : bool
        Keep every registration's resampled images and memberships in the cache (about
        50 MB per image and registration at 1 mm: 9.7 GB for 36 subjects and five
        registrations), so that a rerun finds them. By default a registration's resampled
        images leave the cache once its scores are taken: the cache holds one
        registration's at a time, and keeps what is costly to redo and small (the frames,
        each transform's coverage and plausibility); a rerun resamples the images again.
    job_cores, job_memory, job_walltime, job_queue, job_directives
        With a job queue, what each job asks the batch system for
        (:class:`itk_nrreval._scaleout.JobResources`): cores (one single-threaded worker
        each; default 1), memory per job (``"8GiB"``; default 4 GiB per core), walltime
        ``"HH:MM:SS"``, partition or queue, further header lines (``("--account=lab",)``).
        Left out: Dask's jobqueue configuration, where it has them.

    Raises
    ------
    ValueError
        `workers` without a `scheduler`, `threads` with one, or either not a positive
        integer; `keep_resampled` not a bool; a job queue without `workers` or `cache`; a
        `job_*` attribute without a job queue, or not a value of its kind.
    """

    scheduler: str | None = None
    workers: int | None = None
    threads: int | None = None
    cache: str | os.PathLike | None = None
    keep_resampled: bool = False
    job_cores: int | None = None
    job_memory: str | None = None
    job_walltime: str | None = None
    job_queue: str | None = None
    job_directives: Sequence[str] = ()

    def __post_init__(self) -> None:
        from ._scaleout import JOB_QUEUES

        job = self._job_resources()  # checks each job_* value
        object.__setattr__(self, "job_directives", job.directives)  # a list becomes a tuple
        if self.scheduler in JOB_QUEUES:
            needed = {
                "workers": "how many workers to submit jobs for",
                "cache": "a folder every job sees, on a shared filesystem",
            }
            for name, what in needed.items():
                if getattr(self, name) is None:
                    raise ValueError(f"{name}: required with scheduler={self.scheduler!r} ({what})")
        elif job != type(job)():
            raise ValueError(
                f"job_*: only with a job-queue scheduler ({', '.join(map(repr, JOB_QUEUES))})"
            )
        if not isinstance(self.keep_resampled, bool):
            raise ValueError(f"keep_resampled: expected True or False, got {self.keep_resampled!r}")
        if self.threads is not None:
            if self.scheduler is not None:
                raise ValueError("threads: only without a scheduler (a Dask worker runs one task)")
            _check_positive("threads", self.threads, 1)
        if self.workers is None:
            return
        if self.scheduler is None:
            raise ValueError("workers: only with a scheduler (local or an address)")
        _check_positive("workers", self.workers, 1)

    def _job_resources(self):
        """The `job_*` attributes as a :class:`itk_nrreval._scaleout.JobResources`."""
        from ._scaleout import JobResources

        return JobResources(
            cores=self.job_cores,
            memory=self.job_memory,
            walltime=self.job_walltime,
            queue=self.job_queue,
            directives=self.job_directives,
        )


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
        (:func:`itk_nrreval.plausibility.combine`), on its own reference grid.
    flags : tuple of str
        Why the registration is implausible, in words; empty when it is plausible.
    intervals : dict of str to Interval
        Subject-level 95% interval per measure (``specificity``, ``generalization``,
        ``overlap.<weighting>``); empty when confidence was not computed.
    probability_best : dict of str to float
        Per measure, the probability that this registration is the best of those compared
        (:func:`itk_nrreval.confidence.probability_best`).
    coverage : Coverage or None
        How much of the common grid its images cover; the scores are taken where every
        image covers it under every registration (:class:`itk_nrreval.Coverage`).
    subjects : tuple of SubjectQC
        Every subject's quality control under this registration, in manifest order
        (:mod:`itk_nrreval.subject_qc`): which subjects stand out from the cohort, and why.
    label_metrics : LabelMetrics or None
        The numbers registration papers report from labels: Dice and HD95 (mm) per label
        and case in the common frame, against the registration's reference subject or
        over every pair (:mod:`itk_nrreval.label_metrics`); None without labels.
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
        (:func:`tie_groups`) share the best rank (:meth:`tied_with` names them).
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
        subjects' jackknife contributions (:func:`itk_nrreval.confidence.bootstrap_ranks`);
        empty when confidence was not computed. In ``results.json`` beside
        ``significance``: per measure (and ``verdict``), which registration is told apart
        from which (:meth:`significance`).
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
        names in `out_dir` are left alone (``evaluate(..., out=DIR)`` swaps a whole folder
        in instead).

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
        (:func:`itk_nrreval.confidence.significance_map`: ``"better"``, ``"worse"``, ``"not
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


def higher_is_better(measure: str) -> bool:
    """Overlap measures: higher is better; specificity and generalization: lower is better."""
    return measure.startswith("overlap")


def ranks(
    scores: Mapping[str, float],
    *,
    higher_is_better: bool,
    stderr: Mapping[str, float] | None = None,
    comparisons: Sequence[Comparison] = (),
) -> dict[str, int | None]:
    """Rank order (1 = best); tied scores share the better rank ("1, 2, 2, 4").

    Parameters
    ----------
    scores : dict of str to float
    higher_is_better : bool
    stderr, comparisons
        What tells scores apart from noise (:func:`tie_groups`); default: only equal scores
        are tied.

    Returns
    -------
    dict of str to int
        Same keys; NaN scores get None and do not take a rank.

    Examples
    --------
    >>> ranks({"a": 0.61, "b": 0.52, "c": 0.52, "d": 0.3}, higher_is_better=True)
    {'a': 1, 'b': 2, 'c': 2, 'd': 4}
    >>> ranks({"a": 0.61, "b": 0.60, "c": 0.3}, higher_is_better=True,
    ...       stderr={"a": 0.01, "b": 0.01, "c": 0.01})
    {'a': 1, 'b': 1, 'c': 3}
    """
    groups = tie_groups(
        scores, higher_is_better=higher_is_better, stderr=stderr, comparisons=comparisons
    )
    out: dict[str, int | None] = dict.fromkeys(scores)
    better = 0
    for group in groups:
        for k in group:
            out[k] = 1 + better
        better += len(group)
    return out


def relative_ranks(
    scores: Mapping[str, float],
    *,
    higher_is_better: bool,
    stderr: Mapping[str, float] | None = None,
    comparisons: Sequence[Comparison] = (),
) -> dict[str, float | None]:
    """Quantitative relative rank in percent: the best score 100, the worst 0, linear between.

    Scores not told apart from noise are tied (:func:`tie_groups`) and get one relative
    rank, that of their group's mean score, so a spread within the scores' errors is never
    stretched over the 0-100% range.

    Parameters
    ----------
    scores : dict of str to float
    higher_is_better : bool
    stderr : dict of str to float, optional
        Each score's standard error (e.g. the Monte-Carlo standard error of specificity).
    comparisons : sequence of Comparison
        This measure's pairwise comparisons with their subject-level intervals.

    Returns
    -------
    dict of str to float
        ``100 (g - worst) / (best - worst)`` with ``g`` the mean score of the registration's
        tie group and ``best``, ``worst`` those of the best and worst groups; 100 for all
        when every score is tied with the others (one group); None for NaN scores.

    Examples
    --------
    >>> relative_ranks({"fluid": 0.131, "mid": 0.249, "affine": 0.367}, higher_is_better=False)
    {'fluid': 100.0, 'mid': 50.0, 'affine': 0.0}
    >>> relative_ranks({"sitk": 0.13104, "itk": 0.13100}, higher_is_better=False,
    ...                stderr={"sitk": 0.0005, "itk": 0.0005})
    {'sitk': 100.0, 'itk': 100.0}
    """
    groups = tie_groups(
        scores, higher_is_better=higher_is_better, stderr=stderr, comparisons=comparisons
    )
    out: dict[str, float | None] = dict.fromkeys(scores)
    if not groups:
        return out
    means = [math.fsum(float(scores[k]) for k in g) / len(g) for g in groups]
    best, worst = means[0], means[-1]
    for group, g in zip(groups, means, strict=True):
        for k in group:
            if len(groups) == 1:
                out[k] = 100.0
            else:
                out[k] = round(100.0 * (g - worst) / (best - worst), 10) + 0.0  # no -0.0
    return out


def _check_options(n_samples, distance, weightings) -> tuple[str, ...]:
    if distance not in _DISTANCES:
        raise ValueError(f"distance: {distance!r} is not one of {_DISTANCES}")
    if isinstance(n_samples, bool) or not isinstance(n_samples, (int, np.integer)) or n_samples < 2:
        raise ValueError(f"n_samples: expected an integer >= 2, got {readable(n_samples)}")
    if weightings is None:
        weightings = WEIGHTINGS
    if isinstance(weightings, str):
        weightings = (weightings,)
    weightings = tuple(weightings)
    for w in weightings:
        if w not in WEIGHTINGS:
            raise ValueError(f"weightings: {w!r} is not one of {WEIGHTINGS}")
    return weightings


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
    execution: Execution | None = None,
    progress: bool = True,
    save_resampled: str | os.PathLike | bool | None = None,
    out: str | os.PathLike | None = None,
    figures: bool = True,
) -> EvaluationResult:
    """Resample every registration into the common frame and score it.

    Parameters
    ----------
    manifest : Manifest, dict or path
        See :mod:`itk_nrreval.manifest`; checked in full before any heavy work. In a dict,
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
        Deformation-plausibility flag thresholds (:class:`itk_nrreval.plausibility.Thresholds`,
        whose docstring gives the defaults and their rationale). A flagged registration keeps
        its scores; the flag is a warning in the verdict, not a decision
        (:mod:`itk_nrreval.verdict`: only severe folding decides against it).
    subject_thresholds : SubjectThresholds, optional
        When a subject of a registration is flagged as failed
        (:class:`itk_nrreval.plausibility.SubjectThresholds`; results in
        ``RegistrationScores.subjects``). A subject whose field of view covers less of the
        common grid than ``off_grid_coverage`` times the median subject's is also left out
        of every registration's scores (a warning names it).
    inverse_consistency : bool
        Measure each transform's inverse consistency (one numerical inversion per image).
    execution : Execution, optional
        Where the tasks run and the per-image cache (:class:`Execution`; default
        ``Execution()``: in this process, cache in ``out/cache`` or a temporary folder).
    progress : bool
        Progress bars on stderr (resampling, model, specificity search).
    save_resampled : path or bool, optional
        Folder to write each registration's resampled images and label memberships
        (NIfTI; one component per nonzero label value); True: ``out/resampled`` (with
        `out`).
    out : path, optional
        Also write the reports :meth:`EvaluationResult.write` writes into this folder, as
        ``nrreval evaluate --out`` does (:func:`itk_nrreval._output.staged_folder`): the
        run writes into a temporary folder whose entries replace the previous run's only
        when complete (the cache carried over), so `out` holds one complete result or the
        previous one, never a mix. `out` must be new, empty or a folder this toolkit made,
        and must not hold an input; files the toolkit did not write are never touched.
    figures : bool
        With `out`: also write the PNG figures and ``report.html``, the self-contained HTML
        report that embeds them (:meth:`EvaluationResult.write`).

    Returns
    -------
    EvaluationResult

    Raises
    ------
    InputError
        A bad manifest (every problem listed in one message), or an `out` that cannot be a
        folder.
    ValueError
        An option outside its accepted values, or of the wrong type (`resampling` not a
        :class:`Resampling`, ...).

    Warns
    -----
    RuntimeWarning
        When a registration is flagged as implausible (folding, rough fields, a frame
        that the registrations disagree about).
    """
    weightings = _check_options(n_samples, distance, weightings)
    resampling = _option("resampling", resampling, Resampling)
    execution = _option("execution", execution, Execution)
    thresholds = _option("thresholds", thresholds, Thresholds)
    subject_thresholds = _option("subject_thresholds", subject_thresholds, SubjectThresholds)
    asked, settings = _confidence_settings(confidence)
    # the default depends on n_samples: resolved here, not in Confidence
    confidence_samples = settings.samples
    if confidence_samples is None:
        confidence_samples = min(int(n_samples), 100_000)
    if isinstance(save_resampled, bool) and save_resampled and out is None:
        raise ValueError("save_resampled=True: only with out= (it means out/resampled)")
    cache = execution.cache
    m = load_manifest(manifest)
    if out is not None:
        out = check_output_folder(out, inputs=m.files, option="out", command="evaluate")
    # with `out`, everything is written into a temporary sibling swapped in at the end
    stage_or_none = (
        staged_folder(out, command="evaluate") if out is not None else contextlib.nullcontext()
    )
    with stage_or_none as stage:
        if stage is not None:
            cache = out / "cache" if cache is None else cache
            save_resampled = stage / "resampled" if save_resampled is True else save_resampled
        assessed: dict[str, tuple[SubjectQC, ...]] = {}
        run, run_info = _execute(
            m,
            execution=execution,
            inverse_consistency=inverse_consistency,
            cache=cache,
            n_samples=int(n_samples),
            seed=seed,
            distance=distance,
            interpolation=resampling.interpolation,
            label_interpolation=resampling.label_interpolation,
            label_sigma_mm=resampling.label_sigma_mm,
            progress=progress,
            save_resampled=save_resampled or None,
            off_grid_coverage=subject_thresholds.off_grid_coverage,
            pictured_subjects=_subject_assessor(m, subject_thresholds, assessed),
            keep_resampled=execution.keep_resampled,
        )
        regs = run.registrations
        values = {name: _values(r, weightings) for name, r in regs.items()}
        # the jackknife runs over the subjects in the scores
        plan = _jackknife_plan(m, _scored(run), settings.resamples, asked=asked)
        confidence = asked and plan is not None
        level = _SubjectLevel.empty(regs)
        if confidence:
            level = _subject_level(
                run, values, weightings, plan, confidence_samples, distance, seed, progress
            )
        extent = smallest_extent_mm(run.grid)
        scores = _registration_scores(
            run,
            values,
            level,
            across_registrations(assessed, thresholds=subject_thresholds),
            weightings=weightings,
            thresholds=thresholds,
            extent_mm=extent,
            label_names=m.label_names,
        )
        _warn_if_flagged(scores)
        options = {
            "confidence": confidence,
            "confidence_samples": int(confidence_samples),
            "resamples": None if plan is None else len(plan.left_out),
            "inverse_consistency": bool(inverse_consistency),
            "label_interpolation": resampling.label_interpolation,
            "label_sigma_mm": (
                None if resampling.label_sigma_mm is None else float(resampling.label_sigma_mm)
            ),
            "thresholds": dataclasses.asdict(thresholds),
            "subject_thresholds": dataclasses.asdict(subject_thresholds),
            # whose voxels are scored: the registered images, or the manifest's other scans
            "scored_images": "images" if m.evaluation_images is None else "evaluation_images",
            # images off the common grid: in no registration's scores (manifest indices)
            "left_out_of_scores": [i for i in range(m.n_images) if i not in set(_scored(run))],
            # what frame_spread_fraction is a fraction of: the reports state the limit in mm
            "field_of_view_mm": extent,
            "manifest_warnings": list(m.notes),  # the manifest check's, as it gave them
        }
        result = _result(
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
        )
        if stage is not None:
            result.write(stage, figures=figures)
    return result


@dataclass(frozen=True)
class _JackknifePlan:
    """What the subject-level jackknife leaves out, in indices of the scored images."""

    left_out: list[np.ndarray]  # the images each specificity replicate leaves out
    overlap_left_out: list[np.ndarray]  # one subject each (the overlap's are exact)
    image_groups: list[str] | None  # each scored image's group (a mixture), or None


def _jackknife_plan(
    m: Manifest, scored: Sequence[int], resamples: int | None, *, asked: bool
) -> _JackknifePlan | None:
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
                stacklevel=3,
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
                        stacklevel=3,
                    )
                return None
    one_each = jackknife_groups(len(scored), None, subjects=subjects)
    return _JackknifePlan(left_out, one_each, image_groups)


def _execute(m: Manifest, *, execution: Execution, **options):
    """Run the per-image tasks and their reductions, in this process or on Dask (where
    `execution` says; its cache is ``options["cache"]``): the pipeline's run, and what ran it
    (``{"scheduler", "workers", "threads", "cache_reused", "cache_computed"}``)."""
    scheduler, workers, threads = execution.scheduler, execution.workers, execution.threads
    if scheduler is None:
        executor = local_executor(default_threads() if threads is None else threads)
        run = run_pipeline(m, executor, **options)
        run_info = {"scheduler": None, "workers": 1, "threads": executor.n_workers}
    else:
        from ._scaleout import DaskExecutor, check_scheduler, cluster_client

        check_scheduler(scheduler, workers)
        job, cache = execution._job_resources(), options["cache"]
        with cluster_client(scheduler, workers=workers, cache=cache, job=job) as client:
            executor = DaskExecutor(client)
            run = run_pipeline(m, executor, **options)
        run_info = {"scheduler": scheduler, "workers": executor.n_workers, "threads": 1}
    run_info.update(cache_reused=run.cache_reused, cache_computed=run.cache_computed)
    return run, run_info


def _subject_assessor(m: Manifest, thresholds: SubjectThresholds, assessed: dict):
    """The pipeline's ``pictured_subjects`` callback: it assesses each registration's
    subjects once, while the pipeline still has the cache, into `assessed`, and returns the
    flagged subjects the report pictures, worst first (read from the cache)."""

    def pictured(r, products) -> list[int]:
        first = _subjects(m, r, thresholds)
        # an inverted or another subject's transform is looked for among the flagged
        # subjects only: it takes resampling them through changed transforms
        mixups = transform_mixups(
            first,
            images=[str(p) for p in m.images],
            scored=r.scored,
            gram=r.gram,
            products=products,
        )
        assessed[r.name] = _subjects(m, r, thresholds, mixups) if mixups else first
        return [q.index for q in ranked(assessed[r.name]) if q.flags][:FLAGGED_SUBJECTS_SHOWN]

    return pictured


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


@dataclass(frozen=True)
class _SubjectLevel:
    """Subject-level confidence: per registration and measure the 95% interval and the
    probability of being best, and the paired comparisons."""

    intervals: dict[str, dict]
    best_p: dict[str, dict]
    comparisons: tuple[Comparison, ...]
    rank_stability: dict[str, RankStability] = field(default_factory=dict)

    @classmethod
    def empty(cls, names) -> _SubjectLevel:
        return cls({n: {} for n in names}, {n: {} for n in names}, ())


def _subject_level(
    run, values, weightings, plan: _JackknifePlan, n_samples, distance, seed, progress
) -> _SubjectLevel:
    """Jackknife intervals, paired comparisons and probabilities of being best, for every
    measure and registration of `run`."""
    regs = run.registrations
    level = _SubjectLevel.empty(regs)
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


def _registration_scores(
    run,
    values,
    level: _SubjectLevel,
    subjects,
    *,
    weightings,
    thresholds,
    extent_mm,
    label_names: Mapping[int, str] | None = None,
) -> dict[str, RegistrationScores]:
    """Every registration's scores, plausibility, flags and subjects (its label metrics
    carrying the manifest's `label_names`)."""
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
        )
    return scores


def _named(lm: LabelMetrics | None, names: Mapping[int, str] | None) -> LabelMetrics | None:
    """`lm` carrying the labels' names (the values shown beside them), where both exist."""
    return lm if lm is None or names is None else dataclasses.replace(lm, names=names)


def _scored(run) -> tuple[int, ...]:
    """The images in the scores (the same for every registration of a run)."""
    return next(iter(run.registrations.values())).scored


def _subjects(
    m: Manifest,
    r,
    thresholds: SubjectThresholds,
    mixups: dict[int, tuple[float, str]] | None = None,
) -> tuple[SubjectQC, ...]:
    """Every subject's quality control under registration run `r` (`mixups`: flagged
    subjects resampled through changed transforms,
    :func:`itk_nrreval.subject_qc.transform_mixups`)."""
    fits = [f.to_dict() for f in r.affine_fits]
    plaus = [p.to_dict() for p in r.plausibility]
    deformation = {
        k: [row[k] for row in plaus]
        for k in (
            "folded_fraction",
            "nondiffeomorphic_fraction",
            "nondiffeomorphic_volume",
            "sdlogj",
            "jacobian_min",
            "jacobian_max",
        )
    }
    deformation["inverse_consistency_mm"] = [row["inverse_consistency_mm"] for row in plaus]
    for k in ("linear_det", "nonlinear_rms_mm", "displacement_rms_mm"):
        deformation[k] = [row[k] for row in fits]
    # where this registration's frame was estimated from the group (not the common one)
    deformation["frame_deviation_mm"] = list(r.frame.per_image_mm) or [None] * m.n_images
    sums = r.overlap_sums
    registration = m.registrations[r.name]
    return assess_subjects(
        images=[str(p) for p in m.images],
        scored=r.scored,
        gram=r.gram,
        deformation=deformation,
        coverage=r.coverage.per_image,
        overlap_volume=None if sums is None else sums["volume"],
        overlap_target_sums=None if sums is None else sums["target_sums"],
        overlap_weights=None if r.overlap is None else r.overlap.weights("volume"),
        mixups=mixups,
        # a subject registered to itself (reference_index, or the reference's own image with
        # the identity): not judged
        reference=reference_subject(
            registration.reference,
            m.images,
            reference_index=registration.reference_index,
            displacement_rms_mm=deformation["displacement_rms_mm"],
        ),
        brain_mask_dice=None if r.brain_masks is None else r.brain_masks.dice,
        thresholds=thresholds,
    )


def _option(name: str, value, kind: type):
    """`value`, or ``kind()`` (its defaults) for None; ValueError naming `name` for a value
    of another type (a check here, not a failure deep in the run)."""
    if value is None:
        return kind()
    if not isinstance(value, kind):
        raise ValueError(
            f"{name}: expected {kind.__name__}(...) or None, got {type(value).__name__}"
        )
    return value


def _confidence_settings(confidence) -> tuple[bool, Confidence]:
    """Whether subject-level confidence is asked for, and its settings (``Confidence()`` for
    True and False: the settings of an unasked run are still recorded in its options)."""
    if isinstance(confidence, Confidence):
        return True, confidence
    if isinstance(confidence, (bool, np.bool_)):
        return bool(confidence), Confidence()
    raise ValueError(
        f"confidence: expected True, False or a Confidence, got {type(confidence).__name__}"
    )


def _check_positive(name: str, value, minimum: int) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"{name}: expected an integer >= {minimum}, got {readable(value)}")


def _replicates(run, weightings, plan: _JackknifePlan, n_samples, distance, seed, progress):
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


def _warn_if_flagged(scores: Mapping[str, RegistrationScores]) -> None:
    for name, s in scores.items():
        if s.flags:
            warnings.warn(
                f"registration {name!r} is flagged as implausible: {'; '.join(s.flags)}",
                RuntimeWarning,
                stacklevel=3,
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
        verdict=verdict(scores, comparisons, has_labels=m.labels is not None),
        thumbnails=dict(thumbnails or {}),
        rank_stability=dict(rank_stability or {}),
    )
