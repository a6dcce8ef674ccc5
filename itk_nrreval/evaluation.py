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

import math
import os
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ._errors import InputError
from .frame import FrameMapping
from .manifest import Manifest, load_manifest
from .overlap import WEIGHTINGS
from .pipeline import InProcessExecutor, run_pipeline
from .specificity import GeneralizationResult, SpecificityResult

__all__ = ["RegistrationScores", "EvaluationResult", "evaluate", "ranks", "relative_ranks"]

_DISTANCES = ("l1", "l2")
_INTERPOLATIONS = ("linear", "bspline")


@dataclass(frozen=True)
class RegistrationScores:
    """The scores of one registration.

    Attributes
    ----------
    name : str
    specificity : SpecificityResult
        Lower is better.
    generalization : GeneralizationResult
        Lower is better.
    overlap : dict of str to float
        Generalized Tanimoto overlap per weighting (empty without labels); higher is better.
    frame : FrameMapping
        How the registration's frame was reached, and the spread (mm) of its estimates.
    folded_fraction : float
        Mean over images of the fraction of the registration's reference-grid voxels where
        the image's transform folds (Jacobian determinant <= 0).
    folded_max : float
        The largest per-image folded fraction.
    """

    name: str
    specificity: SpecificityResult
    generalization: GeneralizationResult
    overlap: Mapping[str, float]
    frame: FrameMapping
    folded_fraction: float
    folded_max: float

    def measures(self) -> dict[str, float]:
        """Every scalar score by measure name (``specificity``, ``overlap.<weighting>``...)."""
        out = {"specificity": self.specificity.value, "generalization": self.generalization.value}
        out.update({f"overlap.{w}": v for w, v in self.overlap.items()})
        return out

    def to_dict(self) -> dict:
        return {
            "specificity": {"value": self.specificity.value, "stderr": self.specificity.stderr},
            "generalization": {
                "value": self.generalization.value,
                "stderr": self.generalization.stderr,
            },
            "overlap": dict(self.overlap),
            "frame": self.frame.to_dict(),
            "folded_fraction": self.folded_fraction,
            "folded_max": self.folded_max,
            "n_modes": self.specificity.n_modes,
        }


@dataclass(frozen=True)
class EvaluationResult:
    """Every registration's scores, ranks and relative ranks.

    Attributes
    ----------
    scores : dict of str to RegistrationScores
        In the manifest's order.
    ranks : dict of str to dict of str to int
        ``ranks[measure][registration]``: 1 is best; equal scores share the best rank.
    relative_ranks : dict of str to dict of str to float
        ``relative_ranks[measure][registration]`` in percent: best 100, worst 0, linear
        between (paper, Section V-E).
    common_frame : str
        The registration whose reference frame is the common frame.
    mean_images : dict of str to ndarray of shape (*spatial_zyx,)
        Each registration's mean resampled image on the common grid.
    inputs : dict
        The manifest's description (:meth:`Manifest.describe`).
    options : dict
        n_samples, seed, distance, interpolation, weightings.
    version : str
        The toolkit version.
    run : dict
        How the run was executed: ``scheduler`` (None: in this process), ``workers``, and
        how many per-image results were reused from the cache (``cache_reused``) or
        computed (``cache_computed``).
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

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self.scores)

    @property
    def measures(self) -> tuple[str, ...]:
        """Measure names, in report order."""
        return tuple(self.ranks)

    def to_dict(self) -> dict:
        """The content of ``results.json``."""
        regs = {}
        for name, s in self.scores.items():
            d = s.to_dict()
            d["rank"] = {m: self.ranks[m][name] for m in self.ranks}
            d["relative_rank"] = {m: self.relative_ranks[m][name] for m in self.ranks}
            regs[name] = d
        out = {
            "version": self.version,
            "common_frame": self.common_frame,
            "options": dict(self.options),
            "inputs": dict(self.inputs),
            "registrations": regs,
        }
        if self.run:
            out["run"] = dict(self.run)
        return out


def higher_is_better(measure: str) -> bool:
    """Overlap measures: higher is better; specificity and generalization: lower is better."""
    return measure.startswith("overlap")


def ranks(scores: Mapping[str, float], *, higher_is_better: bool) -> dict[str, int | None]:
    """Rank order (1 = best); equal scores share the better rank ("1, 2, 2, 4").

    Parameters
    ----------
    scores : dict of str to float
    higher_is_better : bool

    Returns
    -------
    dict of str to int
        Same keys; NaN scores get None and do not take a rank.

    Examples
    --------
    >>> ranks({"a": 0.61, "b": 0.52, "c": 0.52, "d": 0.3}, higher_is_better=True)
    {'a': 1, 'b': 2, 'c': 2, 'd': 4}
    """
    valid = {k: float(v) for k, v in scores.items() if not math.isnan(float(v))}
    sign = -1.0 if higher_is_better else 1.0
    out: dict[str, int | None] = {}
    for k in scores:
        if k not in valid:
            out[k] = None
        else:
            out[k] = 1 + sum(sign * v < sign * valid[k] for v in valid.values())
    return out


def relative_ranks(
    scores: Mapping[str, float], *, higher_is_better: bool
) -> dict[str, float | None]:
    """Quantitative relative rank in percent: the best score 100, the worst 0, linear between.

    Parameters
    ----------
    scores : dict of str to float
    higher_is_better : bool

    Returns
    -------
    dict of str to float
        ``100 (s - worst) / (best - worst)``; 100 for all when every score is equal; None for
        NaN scores.

    Examples
    --------
    >>> relative_ranks({"fluid": 0.131, "mid": 0.249, "affine": 0.367}, higher_is_better=False)
    {'fluid': 100.0, 'mid': 50.0, 'affine': 0.0}
    """
    valid = {k: float(v) for k, v in scores.items() if not math.isnan(float(v))}
    if not valid:
        return {k: None for k in scores}
    best = max(valid.values()) if higher_is_better else min(valid.values())
    worst = min(valid.values()) if higher_is_better else max(valid.values())
    out: dict[str, float | None] = {}
    for k in scores:
        if k not in valid:
            out[k] = None
        elif best == worst:
            out[k] = 100.0
        else:
            out[k] = round(100.0 * (valid[k] - worst) / (best - worst), 10) + 0.0  # no -0.0
    return out


def _check_options(n_samples, distance, interpolation, weightings) -> tuple[str, ...]:
    if distance not in _DISTANCES:
        raise ValueError(f"distance: {distance!r} is not one of {_DISTANCES}")
    if interpolation not in _INTERPOLATIONS:
        raise ValueError(f"interpolation: {interpolation!r} is not one of {_INTERPOLATIONS}")
    if isinstance(n_samples, bool) or not isinstance(n_samples, (int, np.integer)) or n_samples < 2:
        raise ValueError(f"n_samples: expected an integer >= 2, got {n_samples!r}")
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
    interpolation: str = "linear",
    progress: bool = True,
    save_resampled: str | os.PathLike | None = None,
    scheduler: str | None = None,
    workers: int | None = None,
    cache: str | os.PathLike | None = None,
) -> EvaluationResult:
    """Resample every registration into the common frame and score it.

    Parameters
    ----------
    manifest : Manifest, dict or path
        See :mod:`itk_nrreval.manifest`; checked in full before any heavy work.
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
    interpolation : {"linear", "bspline"}
        Intensity interpolation; labels are always one-hot memberships resampled linearly.
    progress : bool
        Progress bars on stderr (resampling, model, specificity search).
    save_resampled : path, optional
        Folder to write each registration's resampled images and label memberships
        (NIfTI; one component per nonzero label value).
    scheduler : str, optional
        Run the tasks on a Dask cluster (:mod:`itk_nrreval.scaleout`): ``"local"`` starts a
        local cluster of `workers` single-threaded processes; otherwise the address of a
        running scheduler. Default: in this process. Either way the same tasks run
        (:mod:`itk_nrreval.pipeline`), no process holds all the images, and the numbers
        are the same.
    workers : int, optional
        With ``scheduler="local"``, the number of worker processes (default: CPU count);
        with an address, wait until that many workers have joined.
    cache : path, optional
        The folder of the per-image result cache (with a scheduler: shared by driver and
        workers): a rerun -- after an interruption, or with more images or registrations --
        recomputes only what changed. Default: a temporary folder, removed afterwards.

    Returns
    -------
    EvaluationResult

    Raises
    ------
    InputError
        A bad manifest (every problem listed in one message).
    ValueError
        An option outside its accepted values.

    Warns
    -----
    RuntimeWarning
        When a registration's transforms fold (Jacobian determinant <= 0 somewhere).
    """
    weightings = _check_options(n_samples, distance, interpolation, weightings)
    m = load_manifest(manifest)
    options = dict(
        cache=cache,
        n_samples=int(n_samples),
        seed=seed,
        distance=distance,
        interpolation=interpolation,
        show_progress=progress,
        save_resampled=save_resampled,
    )
    if scheduler is None:
        if workers is not None:
            raise ValueError("workers: only with a scheduler (local or an address)")
        executor = InProcessExecutor()
        run = run_pipeline(m, executor, **options)
        run_info = {"scheduler": None, "workers": 1}
    else:
        from .scaleout import DaskExecutor, check_scheduler, cluster_client

        check_scheduler(scheduler, workers)
        with cluster_client(scheduler, workers=workers) as client:
            executor = DaskExecutor(client)
            run = run_pipeline(m, executor, **options)
        run_info = {"scheduler": scheduler, "workers": executor.n_workers}
    run_info.update(cache_reused=run.cache_reused, cache_computed=run.cache_computed)
    scores = {}
    for name, r in run.registrations.items():
        overlap = {w: r.overlap.generalized(w) for w in weightings} if r.overlap else {}
        _warn_if_folded(name, r.folded)
        scores[name] = RegistrationScores(
            name,
            r.specificity,
            r.generalization,
            overlap,
            r.frame,
            float(np.mean(r.folded)),
            float(np.max(r.folded)),
        )
    means = {name: r.mean_image for name, r in run.registrations.items()}
    return _result(
        m,
        scores,
        means,
        run.label_values,
        weightings,
        n_samples,
        seed,
        distance,
        interpolation,
        run=run_info,
    )


def _warn_if_folded(name: str, folds: Sequence[float]) -> None:
    if max(folds) > 0:
        warnings.warn(
            f"registration {name!r}: transforms fold (Jacobian determinant <= 0) on "
            f"{np.mean(folds):.2%} of its reference grid on average, {max(folds):.2%} at "
            "worst: they are not invertible there",
            RuntimeWarning,
            stacklevel=3,
        )


def _result(
    m, scores, means, values, weightings, n_samples, seed, distance, interpolation, run
) -> EvaluationResult:
    """Ranks and relative ranks of every measure, and the result object."""
    from ._version import __version__

    measures = ["specificity", "generalization"]
    if m.labels is not None:
        measures += [f"overlap.{w}" for w in weightings]
    rank_table, rel_table = {}, {}
    for measure in measures:
        values_by_name = {n: s.measures()[measure] for n, s in scores.items()}
        hib = higher_is_better(measure)
        rank_table[measure] = ranks(values_by_name, higher_is_better=hib)
        rel_table[measure] = relative_ranks(values_by_name, higher_is_better=hib)
    options = {
        "n_samples": int(n_samples),
        "seed": int(seed),
        "distance": distance,
        "interpolation": interpolation,
        "weightings": list(weightings),
        "label_values": values,
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
    )
