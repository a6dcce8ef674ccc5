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
from pathlib import Path
from typing import Any

import numpy as np
import SimpleITK as sitk

from ._errors import InputError
from ._images import Geometry, mask_array, read_image
from ._output import atomic_path
from .frame import (
    FrameMapping,
    common_reference,
    frame_mapping,
    label_values,
    read_chains,
    resample_images,
    resample_memberships,
    resampling_transform,
)
from .manifest import Manifest, load_manifest
from .specificity import GeneralizationResult, SpecificityResult, texture_measures
from .transforms import folded_fraction

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
        How the run was executed: empty for the single-process path; with a scheduler, the
        scheduler, the number of workers, and how many per-image results were reused from the
        cache (``cache_reused``) or computed (``cache_computed``).
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
    from .overlap import WEIGHTINGS

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


def _save_stack(folder: Path, stem: str, arrays: np.ndarray, grid: Geometry, vector: bool):
    folder.mkdir(parents=True, exist_ok=True)
    for i, arr in enumerate(arrays):
        img = sitk.GetImageFromArray(np.moveaxis(arr, 0, -1) if vector else arr, isVector=vector)
        grid.apply_to(img)
        with atomic_path(folder / f"{stem}_{i:03d}.nii.gz") as tmp:
            sitk.WriteImage(img, str(tmp), True)


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
        Progress bars on stderr during resampling.
    save_resampled : path, optional
        Folder to write each registration's resampled images and membership maps (NIfTI).
        Single-process path only.
    scheduler : str, optional
        Run on a Dask cluster (:mod:`itk_nrreval.scaleout`): ``"local"`` starts a local
        cluster of `workers` single-threaded processes; otherwise the address of a running
        scheduler. Per-image work and voxel-block sums run as tasks, and no process holds
        all the images. Default: the single-process path (the numbers agree to round-off).
    workers : int, optional
        With ``scheduler="local"``, the number of worker processes (default: CPU count);
        with an address, wait until that many workers have joined.
    cache : path, optional
        With a scheduler, the folder of the per-image result cache (shared by driver and
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
    from .overlap import overlap_table

    weightings = _check_options(n_samples, distance, interpolation, weightings)
    m = load_manifest(manifest)
    if scheduler is not None:
        return _evaluate_scaled(
            m,
            scheduler=scheduler,
            workers=workers,
            cache=cache,
            n_samples=int(n_samples),
            seed=seed,
            distance=distance,
            weightings=weightings,
            interpolation=interpolation,
            progress=progress,
            save_resampled=save_resampled,
        )
    ref_img = common_reference(m)
    grid = Geometry.from_image(ref_img)
    mask = mask_array(m.mask, shape=grid.shape, geometry=grid) if m.mask is not None else None
    images = [sitk.Cast(read_image(p, what="image"), sitk.sitkFloat64) for p in m.images]
    labels = values = None
    if m.labels is not None:
        labels = [read_image(p, what="label map") for p in m.labels]
        found = label_values(labels)
        values = [0] + [int(v) for v in found if v != 0]  # channel 0 is background
    common_chains = read_chains(m, m.common_frame)
    scores: dict[str, RegistrationScores] = {}
    means: dict[str, np.ndarray] = {}
    for name, reg in m.registrations.items():
        chains = common_chains if name == m.common_frame else read_chains(m, name)
        frame = frame_mapping(
            m, name, grid=grid, transforms=chains, common_transforms=common_chains, mask=mask
        )
        full = [resampling_transform(t, frame.transform) for t in chains]
        stack = resample_images(
            images,
            full,
            grid,
            interpolation=interpolation,
            show_progress=progress,
            desc=f"{name}: images",
        )
        spec, gen = texture_measures(
            stack, n_samples=int(n_samples), distance=distance, seed=seed, mask=mask
        )
        overlap: dict[str, float] = {}
        memberships = None
        if labels is not None:
            memberships = resample_memberships(
                labels,
                full,
                grid,
                values=values,
                show_progress=progress,
                desc=f"{name}: labels",
            )
            table = overlap_table(memberships, mask=mask, spacing=grid.spacing)
            overlap = {w: table.generalized(w) for w in weightings}
        reg_grid = Geometry.from_image(read_image(reg.reference, what="reference image"))
        folds = [folded_fraction(t, reg_grid) for t in chains]
        _warn_if_folded(name, folds)
        if save_resampled is not None:
            folder = Path(save_resampled) / name
            _save_stack(folder, "image", stack, grid, vector=False)
            if memberships is not None:
                _save_stack(folder, "memberships", memberships, grid, vector=True)
        means[name] = stack.mean(axis=0)
        scores[name] = RegistrationScores(
            name, spec, gen, overlap, frame, float(np.mean(folds)), float(max(folds))
        )
        del stack, memberships
    return _result(m, scores, means, values, weightings, n_samples, seed, distance, interpolation)


def _warn_if_folded(name: str, folds: Sequence[float], *, stacklevel: int = 3) -> None:
    if max(folds) > 0:
        warnings.warn(
            f"registration {name!r}: transforms fold (Jacobian determinant <= 0) on "
            f"{np.mean(folds):.2%} of its reference grid on average, {max(folds):.2%} at "
            "worst: they are not invertible there",
            RuntimeWarning,
            stacklevel=stacklevel,
        )


def _evaluate_scaled(m: Manifest, *, save_resampled, weightings, **kwargs) -> EvaluationResult:
    from .scaleout import evaluate_scaled

    if save_resampled is not None:
        raise ValueError("save_resampled: only the single-process path writes resampled images")
    scores, means, values, run = evaluate_scaled(m, weightings=weightings, **kwargs)
    keys = ("n_samples", "seed", "distance", "interpolation")
    return _result(m, scores, means, values, weightings, *(kwargs[k] for k in keys), run=run)


def _result(
    m, scores, means, values, weightings, n_samples, seed, distance, interpolation, run=None
) -> EvaluationResult:
    """Ranks and relative ranks of every measure, and the result object."""
    from . import __version__

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
        run=dict(run or {}),
    )
