"""The option groups of :func:`itk_nrreval.evaluate`, each checked once where it is made.

:class:`Resampling` (how images and label maps reach the common frame), :class:`Confidence`
(the subject-level jackknife's settings) and :class:`Execution` (where the per-image tasks
run, and their cache), and the checks of evaluate's plain options (`n_samples`, `distance`,
`weightings`). All are re-exported by :mod:`itk_nrreval.evaluation`.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ._errors import readable
from .io._memberships import LABEL_INTERPOLATIONS
from .measures.overlap import WEIGHTINGS

__all__ = [
    "Resampling",
    "Confidence",
    "Execution",
    "check_options",
    "option_or_default",
    "confidence_settings",
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
        (:func:`itk_nrreval.io._memberships.resample_label_memberships`): one-hot memberships
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
    probability that each registration is best (:mod:`itk_nrreval.measures.confidence`): a grouped
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
        process. Default: a temporary folder, removed afterwards (``nrreval evaluate``
        uses ``DIR/cache``).
    keep_resampled : bool
        Keep every registration's resampled images and memberships in the cache (about
        50 MB per image and registration at 1 mm: 9.7 GB for 36 subjects and five
        registrations), so that a rerun finds them. By default a registration's resampled
        images leave the cache once its scores are taken: the cache holds one
        registration's at a time, and keeps what is costly to redo and small (the frames,
        each transform's coverage and plausibility); a rerun resamples the images again.
        :func:`itk_nrreval.evaluation.export_resampled` writes them from a cache that kept
        them (``--save-resampled``).
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


def check_options(n_samples, distance, weightings) -> tuple[str, ...]:
    """Refuse a `distance` or `n_samples` outside its accepted values; the `weightings`
    asked for, as a tuple (default: all of :data:`itk_nrreval.measures.overlap.WEIGHTINGS`)."""
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


def option_or_default(name: str, value, kind: type):
    """`value`, or ``kind()`` (its defaults) for None; ValueError naming `name` for a value
    of another type (a check here, not a failure deep in the run)."""
    if value is None:
        return kind()
    if not isinstance(value, kind):
        raise ValueError(
            f"{name}: expected {kind.__name__}(...) or None, got {type(value).__name__}"
        )
    return value


def confidence_settings(confidence) -> tuple[bool, Confidence]:
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
