"""The paper's validation experiment (Section IV): perturb a registered set, track specificity.

Start from N registered images with labels on one grid. For every mean displacement ``d``
and every repeat, each image (and its labels, as one-hot memberships) is perturbed by its own
independent random clamped-plate-spline warp of exactly that mean displacement
(:mod:`itk_nrreval.experiments.warps`: biharmonic in 2D as in the paper, triharmonic in 3D; the ball
in mm); the specificity of the perturbed set's texture model and the generalized Tanimoto
overlap of its labels are recorded. Specificity should rise as overlap falls: the paper finds
a straight line for ``d >= 0.375`` pixels (Fig. 2) and a dip below the unperturbed value at
sub-pixel ``d`` (interpolation smoothing).

The paper worked on 2D mid-brain slices of registered 3D images "at an equivalent level
across the set"; ``section="z"`` (``nrreval validate --slice z``) does the same with a slice
of the common frame, and without it the experiment runs in full 3D.

Full 3D reaches smaller ``d`` than 2D before warps fold: the ball covers a smaller part of
the grid (52 % of a cube against 79 % of a square) and a 3D bump folds sooner (see
:func:`~itk_nrreval.experiments.warps.random_cps`); an unreachable ``d`` is refused with the largest
one that is reachable.

The experiment's inputs -- arrays or a manifest's registered set, a 2D section of it -- are
read in :mod:`itk_nrreval.experiments._perturbation_inputs`, and its perturbed sets drawn in
:mod:`itk_nrreval.experiments._perturbed_sets`; this module runs the experiment, measures each
perturbed set and summarizes the table (:func:`summarize`) into its result types.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from .._executors import local_executor
from .._output import claim_entries, json_number, write_json, write_text
from .._progress import progress_bar
from ..measures.overlap import WEIGHTINGS, overlap_table
from ..measures.specificity import specificity
from ..report.validation import OUTPUT_FILES, write_validation
from ._perturbation_inputs import (
    AXES,
    Inputs,
    manifest_arrays,
    manifest_set,
    parse_section,
    read_inputs,
    section_record,
    take_section,
    without_axis,
)
from ._perturbed_sets import Perturbation, PerturbedSet

__all__ = [
    "DEFAULT_DISPLACEMENTS",
    "FIT_FROM",
    "OUTPUT_FILES",
    "ValidationRow",
    "ValidationSummary",
    "ValidationResult",
    "validate",
    "summarize",
    "manifest_set",
    "validate_manifest",
    "parse_section",
    "take_section",
]

#: The mean displacements (pixels) of the default run: 12 values from 0 to the paper's 3.0.
DEFAULT_DISPLACEMENTS = (0.0, 0.125, 0.25, 0.375, 0.5, 0.75, 1.0, 1.25, 1.5, 2.0, 2.5, 3.0)
#: The straight-line fit and the correlations use ``d >= FIT_FROM`` (the paper's 0.375).
FIT_FROM = 0.375
_Z975 = 1.959963984540054  # standard normal 97.5 % quantile


def _clean(value):
    """JSON-ready: NaN / inf -> None, numpy scalars -> Python, recursively."""
    if isinstance(value, dict):
        return {k: _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    return json_number(value)


@dataclass(frozen=True)
class ValidationRow:
    """One perturbed instance.

    Attributes
    ----------
    displacement : float
        ``d``, the exact mean pixel displacement of every image's warp (pixel index units).
    repeat : int
    specificity, specificity_stderr : float
        Of the perturbed set's texture model (intensity units).
    overlap : dict of str to float
        Generalized Tanimoto overlap of the perturbed memberships, per weighting.
    min_jacobian : float
        The smallest Jacobian determinant over the N warps (at the fold check's points).
    displacement_mm : float or None
        The mean over the N warps of their mean displacement in mm (``d`` times the voxel
        size for isotropic voxels; 1 mm voxels when the grid had none).
    """

    displacement: float
    repeat: int
    specificity: float
    specificity_stderr: float
    overlap: dict[str, float]
    min_jacobian: float
    displacement_mm: float | None = None

    def to_dict(self) -> dict:
        """Plain Python, JSON-ready (an undefined value is None, never NaN)."""
        d = {
            "displacement": self.displacement,
            "repeat": self.repeat,
            "specificity": self.specificity,
            "specificity_stderr": self.specificity_stderr,
        }
        d.update({f"overlap_{w}": v for w, v in self.overlap.items()})
        d["min_jacobian"] = self.min_jacobian
        d["displacement_mm"] = self.displacement_mm
        return _clean(d)


@dataclass(frozen=True)
class ValidationSummary:
    """Summary figures of a validation run (rows with ``d >= FIT_FROM`` unless stated).

    Attributes
    ----------
    pearson_r : dict of str to float
        Per weighting, Pearson r between specificity and overlap over the instances (the
        paper's Fig. 2 relation; strongly negative is good).
    spearman : float
        Spearman rank correlation between ``d`` and the mean specificity at each ``d``.
    slope : float
        Least-squares slope of specificity against ``d`` (intensity units per pixel).
    sensitivity : float
        ``slope / mean stderr``: the change in specificity per pixel of ``d`` in units of its
        standard error.
    monotonic : bool
        Whether the mean specificity rises strictly with ``d``.
    unperturbed : float or None
        Mean specificity at ``d = 0`` (None when 0 was not run).
    pearson_ci : dict of str to (float, float)
        Per weighting, the 95 % confidence interval of Pearson r (Fisher's z,
        ``tanh(atanh r -+ 1.96 / sqrt(n - 3))``; NaN with fewer than 4 instances).
    fit : dict of str to (float, float)
        Per weighting, the least-squares line ``specificity = a * overlap + b`` as
        ``(a, b)``: Fig. 2's grey line.
    slope_mm, sensitivity_mm : float
        As `slope` and `sensitivity`, per mm of ``d`` (``d`` in mm per instance).
    n_fit : int
        Instances with ``d >= FIT_FROM``.

    NaN marks a figure that is undefined (fewer than two values of ``d >= FIT_FROM``, no
    spread); :meth:`to_dict` gives None for it.
    """

    pearson_r: dict[str, float]
    spearman: float
    slope: float
    sensitivity: float
    monotonic: bool
    unperturbed: float | None
    pearson_ci: dict[str, tuple[float, float]] = field(default_factory=dict)
    fit: dict[str, tuple[float, float]] = field(default_factory=dict)
    slope_mm: float = math.nan
    sensitivity_mm: float = math.nan
    n_fit: int = 0

    def to_dict(self) -> dict:
        """Plain Python, JSON-ready (an undefined value is None, never NaN)."""
        return _clean({k: getattr(self, k) for k in self.__dataclass_fields__})


@dataclass(frozen=True)
class ValidationResult:
    """The table of a validation run: one row per (d, repeat), plus its summary.

    Attributes
    ----------
    spacing : tuple of float or None
        Voxel size (mm, ITK order) of the grid the warps and overlaps were computed on.
    parameters : dict
        ``repeats``, ``displacements`` (pixels), ``fit_from``, and ``section`` (the slice,
        e.g. ``{"axis": "z", "index": 47}``, or None for the full grid).
    """

    rows: tuple[ValidationRow, ...]
    summary: ValidationSummary
    weightings: tuple[str, ...]
    n_images: int
    shape: tuple[int, ...]
    n_samples: int
    n_knots: int
    seed: int
    source: str
    parameters: dict = field(default_factory=dict)
    spacing: tuple[float, ...] | None = None

    def column(self, name: str) -> np.ndarray:
        """A column as an array: ``"displacement"``, ``"specificity"``, ``"overlap_<w>"``...

        Undefined values are NaN.
        """
        values = [r.to_dict()[name] for r in self.rows]
        return np.array([math.nan if v is None else v for v in values], dtype=float)

    def means(self) -> dict[str, np.ndarray]:
        """Per distinct ``d``: mean and standard deviation over repeats of each measure."""
        d = self.column("displacement")
        levels = np.unique(d)
        out = {"displacement": levels}
        names = [
            "specificity",
            "specificity_stderr",
            "displacement_mm",
            *(f"overlap_{w}" for w in self.weightings),
        ]
        for name in names:
            col = self.column(name)
            out[name] = np.array([col[d == v].mean() for v in levels])
            out[name + "_sd"] = np.array([col[d == v].std() for v in levels])
        return out

    def to_dict(self) -> dict:
        """Plain Python, JSON-ready (an undefined value is None, never NaN)."""
        return _clean(
            {
                "source": self.source,
                "n_images": self.n_images,
                "shape": list(self.shape),
                "spacing": None if self.spacing is None else list(self.spacing),
                "n_samples": self.n_samples,
                "n_knots": self.n_knots,
                "seed": self.seed,
                "weightings": list(self.weightings),
                "parameters": dict(self.parameters),
                "summary": self.summary.to_dict(),
                "rows": [r.to_dict() for r in self.rows],
            }
        )

    def to_csv(self) -> str:
        """The rows as CSV text (header line first); an undefined value is an empty field."""
        dicts = [r.to_dict() for r in self.rows]
        header = list(dicts[0]) if dicts else []

        def cell(k, v):
            if v is None:
                return ""
            return str(v) if k == "repeat" else repr(float(v))

        lines = [",".join(header)]
        lines += [",".join(cell(k, d[k]) for k in header) for d in dicts]
        return "\n".join(lines) + "\n"

    def write(self, out_dir) -> list[Path]:
        """Write :data:`OUTPUT_FILES` into `out_dir` (created if needed).

        ``validation.csv`` (:meth:`to_csv`), ``validation.json`` (the package version and
        :meth:`to_dict`), ``validation_fig2.png`` (the paper's Fig. 2, the first weighting),
        ``validation_vs_d.png`` (specificity and overlap against d) and ``report.html`` (one
        self-contained page: the verdict in words, the table by ``d``, the figures embedded,
        Fig. 2 for every weighting; :func:`itk_nrreval.report.validation.write_validation`).
        Each file is written under a temporary name and renamed into place, so a file is
        complete or absent; other files in `out_dir` are left alone.

        Returns
        -------
        list of Path
            The files written, in :data:`OUTPUT_FILES` order.
        """
        from .._version import __version__

        out = claim_entries(out_dir, OUTPUT_FILES, command="validate")
        paths = [out / name for name in OUTPUT_FILES[:2]]
        write_text(paths[0], self.to_csv())
        write_json(paths[1], {"version": __version__, **self.to_dict()})
        return paths + write_validation(self, out, version=__version__)


def validate_manifest(manifest, *, section=None, **options) -> ValidationResult:
    """:func:`validate` on a manifest's registered set (its common frame, with labels).

    Specificity is taken where :func:`itk_nrreval.evaluate` takes it: inside the manifest's
    mask, on the voxels every image covers (a warning says so below 90%); the overlap is
    unaffected by fields of view (no membership outside them).

    Parameters
    ----------
    manifest : path, mapping or Manifest
    section : str or (str, int), optional
        ``AXIS[:INDEX]``: only that slice of the common grid is resampled and validated
        (default index the middle slice); None: the full grid.
    **options
        Keyword options of :func:`validate` (not `spacing`, `section` or `mask`).

    Returns
    -------
    ValidationResult
        ``source`` the manifest; ``parameters["registration"]`` the registration whose
        registered set was perturbed (the common frame); ``parameters["section"]`` the
        slice taken.
    """
    from ..io.manifest import load_manifest

    for key in ("spacing", "section", "mask"):
        if key in options:
            raise TypeError(f"validate_manifest() got an unexpected keyword argument {key!r}")
    from .._pipeline import COVERAGE_WARNING

    given = manifest
    manifest = load_manifest(manifest)  # once (a Manifest: as it is): its checks read every image
    source = str(given) if given is not manifest else str(manifest.source or "manifest")
    images, members, grid, taken, (region, fraction, where, masked) = manifest_arrays(
        manifest, section, options.get("progress", True)
    )
    if fraction < COVERAGE_WARNING:
        warnings.warn(
            f"{where}: specificity is taken on the {fraction:.0%} of the voxels "
            f"{'of the mask' if masked else 'of the common grid'} that every image covers",
            UserWarning,
            stacklevel=2,
        )
    spacing = grid.spacing
    if taken is not None:
        spacing = without_axis(spacing, AXES.index(taken[0]))
    options.setdefault("source", source)
    result = validate(images, members, spacing=spacing, mask=region, **options)
    parameters = {**result.parameters, "registration": manifest.common_frame}
    if taken is not None:
        parameters["section"] = section_record(taken)
    return replace(result, parameters=parameters)


def _check(displacements, repeats, n_samples, weightings, n_knots):
    d = np.asarray(displacements, dtype=float).ravel()
    if d.size == 0 or not np.all(np.isfinite(d)) or np.any(d < 0):
        raise ValueError(f"displacements must be finite numbers >= 0, got {displacements!r}")
    if not (isinstance(repeats, (int, np.integer)) and repeats >= 1):
        raise ValueError(f"repeats must be a positive integer, got {repeats!r}")
    if not (isinstance(n_samples, (int, np.integer)) and n_samples >= 2):
        raise ValueError(f"n_samples must be an integer >= 2, got {n_samples!r}")
    weightings = (weightings,) if isinstance(weightings, str) else tuple(weightings)
    if not weightings:
        raise ValueError("weightings must name at least one weighting")
    for w in weightings:
        if w not in WEIGHTINGS:
            raise ValueError(f"weighting must be one of {WEIGHTINGS}, got {w!r}")
    if not (isinstance(n_knots, (int, np.integer)) and n_knots >= 1):
        raise ValueError(f"n_knots must be a positive integer, got {n_knots!r}")
    return sorted(set(float(v) for v in d)), weightings


def validate(
    images,
    labels,
    *,
    displacements: Sequence[float] = DEFAULT_DISPLACEMENTS,
    repeats: int = 5,
    n_samples: int = 50_000,
    weightings: str | Sequence[str] = ("complexity", "inverse_volume"),
    n_knots: int = 25,
    seed: int = 0,
    mask=None,
    spacing: Sequence[float] | None = None,
    section=None,
    max_tries: int = 100,
    n_jobs: int = 2,
    progress: bool = True,
    source: str = "arrays",
) -> ValidationResult:
    """Run the paper's perturbation experiment on a registered, labelled set.

    Parameters
    ----------
    images : ndarray of shape (n_images, *spatial), or sequence of sitk.Image or paths
        N >= 3 registered images on one 2D or 3D grid (numpy order).
    labels : ndarray or sequence of sitk.Image or paths
        Their label maps on the same grid: non-negative integers (n_images, *spatial) of
        any values (FreeSurfer's up to 14175: one channel per value present, plus the
        background 0; an image may lack labels others have), or floating memberships
        (n_images, n_labels, *spatial) in [0, 1] with component 0 the background (rounding
        up to ``1e-6`` outside is clipped).
    displacements : sequence of float
        Mean pixel displacements ``d`` (run in ascending order; duplicates dropped).
    repeats : int
        Independent perturbations of the whole set per ``d``.
    n_samples : int
        M, the specificity samples (the paper's 50,000).
    weightings : str or sequence of {"volume", "inverse_volume", "inverse_volume_squared", \
"complexity", "inverse_volume_complexity"}
        Overlap weightings to record; all are read from one overlap table per instance.
        The paper's Fig. 2 uses ``"complexity"``.
    n_knots : int
        CPS knots per warp.
    seed : int
        Seeds everything: image i's warp in repeat r at displacement d draws from
        ``default_rng([seed, round(d * 1e6), r, i])`` (so it does not depend on the other
        values of ``d``), and specificity uses `seed` for every instance (common random
        numbers across instances).
    mask : ndarray of bool, sitk.Image, path or None
        Restrict the texture model (specificity) to these voxels.
    spacing : sequence of float, optional
        Voxel size in mm, ITK order, for bare arrays (images bring their own; default 1 mm).
        The warps' ball is round in mm; overlap complexities are in mm.
    section : str or (str, int), optional
        ``AXIS[:INDEX]``: run on that 2D slice of 3D inputs (:func:`take_section`; default
        index the middle slice), as the paper's slices. None: the full grid.
    max_tries : int
        Redraws of a folding warp before giving up.
    n_jobs : int
        Threads warping the N images of an instance in parallel (results do not depend on it).
    progress : bool
        A progress bar on stderr.
    source : str
        A description of the input, kept in the result.

    Returns
    -------
    ValidationResult
        One row per (d, repeat), in that order, and a :class:`ValidationSummary`.

    Raises
    ------
    InputError
        Bad images or labels, or a ``d`` that no warp reaches without folding (checked for
        the largest ``d`` before any other work; the message gives the largest safe ``d``
        in pixels and mm).

    Notes
    -----
    Perturbed images follow the paper's ``I~(psi(p)) = I(p)``, resampled bilinearly
    (trilinearly); labels are warped as one-hot memberships, so the overlap is fuzzy
    (Crum et al.). Twining et al., IEEE TMI, Section IV.
    """
    ds, weightings = _check(displacements, repeats, n_samples, weightings, n_knots)
    inputs = read_inputs(images, labels, mask=mask, spacing=spacing, section=section)
    perturbation = Perturbation(inputs, n_knots=n_knots, seed=seed, max_tries=max_tries)
    if ds[-1] > 0:  # the largest d first: an unreachable request fails before any work
        perturbation.warp(ds[-1], 0, 0)
    todo = [(d, r) for d in ds for r in range(repeats)]
    rows = []
    executor = local_executor(n_jobs)
    for d, r in progress_bar(todo, desc="validate", total=len(todo), enabled=progress):
        instance = perturbation.instance(d, r, executor)
        rows.append(
            _measure(instance, inputs, n_samples=n_samples, seed=seed, weightings=weightings)
        )
    return ValidationResult(
        rows=tuple(rows),
        summary=summarize(rows, weightings),
        weightings=weightings,
        n_images=inputs.n_images,
        shape=inputs.spatial,
        n_samples=int(n_samples),
        n_knots=int(n_knots),
        seed=int(seed),
        source=source,
        parameters={
            "repeats": int(repeats),
            "displacements": ds,
            "fit_from": FIT_FROM,
            "section": section_record(inputs.section),
        },
        spacing=None if inputs.spacing is None else tuple(float(s) for s in inputs.spacing),
    )


def _measure(
    instance: PerturbedSet,
    inputs: Inputs,
    *,
    n_samples: int,
    seed: int,
    weightings: tuple[str, ...],
) -> ValidationRow:
    """Specificity (inside the mask, seeded by `seed`: common random numbers) and the
    overlaps of one perturbed set: its row of the table."""
    spec = specificity(instance.images, n_samples=n_samples, seed=seed, mask=inputs.mask)
    table = overlap_table(instance.memberships, spacing=inputs.spacing)
    return ValidationRow(
        displacement=instance.displacement,
        repeat=instance.repeat,
        specificity=spec.value,
        specificity_stderr=spec.stderr,
        overlap={w: table.generalized(w) for w in weightings},
        min_jacobian=instance.min_jacobian,
        displacement_mm=instance.displacement_mm,
    )


def _pearson(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a - a.mean(), b - b.mean()
    den = math.sqrt(float(a @ a) * float(b @ b))
    return float(a @ b) / den if den > 0 else math.nan


def _fisher_ci(r: float, n: int) -> tuple[float, float]:
    """95 % confidence interval of a Pearson r from n pairs (Fisher's z)."""
    if not math.isfinite(r) or n < 4:
        return math.nan, math.nan
    z = math.atanh(min(max(r, -1.0 + 1e-15), 1.0 - 1e-15))
    h = _Z975 / math.sqrt(n - 3)
    return math.tanh(z - h), math.tanh(z + h)


def _line(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Least-squares ``y = a x + b`` (NaN when x has no spread)."""
    if x.size < 2 or not np.all(np.isfinite(x)) or not np.all(np.isfinite(y)):
        return math.nan, math.nan
    xc = x - x.mean()
    sxx = float(xc @ xc)
    if not sxx > 0:
        return math.nan, math.nan
    a = float(xc @ (y - y.mean())) / sxx
    return a, float(y.mean()) - a * float(x.mean())


def _ranks(x: np.ndarray) -> np.ndarray:
    order = np.argsort(x, kind="stable")
    ranks = np.empty(len(x))
    ranks[order] = np.arange(len(x), dtype=float)
    for v in np.unique(x):  # average ranks of ties
        tie = x == v
        ranks[tie] = ranks[tie].mean()
    return ranks


def summarize(rows: Sequence[ValidationRow], weightings: Sequence[str]) -> ValidationSummary:
    """Pearson r (with its CI), Spearman, fits and sensitivities of a table (``d >= FIT_FROM``)."""
    d = np.array([r.displacement for r in rows], dtype=float)
    s = np.array([r.specificity for r in rows], dtype=float)
    se = np.array([r.specificity_stderr for r in rows], dtype=float)
    d_mm = np.array(
        [math.nan if r.displacement_mm is None else r.displacement_mm for r in rows], dtype=float
    )
    fit = d >= FIT_FROM
    zero = d == 0
    unperturbed = float(s[zero].mean()) if zero.any() else None
    levels = np.unique(d[fit])
    n_fit = int(fit.sum())
    nan = math.nan
    if levels.size < 2:
        return ValidationSummary(
            {w: nan for w in weightings},
            nan,
            nan,
            nan,
            False,
            unperturbed,
            pearson_ci={w: (nan, nan) for w in weightings},
            fit={w: (nan, nan) for w in weightings},
            n_fit=n_fit,
        )
    overlaps = {w: np.array([r.overlap[w] for r in rows], dtype=float)[fit] for w in weightings}
    pearson = {w: _pearson(s[fit], overlaps[w]) for w in weightings}
    mean_s = np.array([s[d == v].mean() for v in levels])
    spearman = _pearson(_ranks(levels), _ranks(mean_s))
    slope = _line(d[fit], s[fit])[0]
    slope_mm = _line(d_mm[fit], s[fit])[0]
    mean_se = float(se[fit].mean())
    return ValidationSummary(
        pearson_r=pearson,
        spearman=spearman,
        slope=slope,
        sensitivity=slope / mean_se if mean_se > 0 else nan,
        monotonic=bool(np.all(np.diff(mean_s) > 0)),
        unperturbed=unperturbed,
        pearson_ci={w: _fisher_ci(pearson[w], n_fit) for w in weightings},
        fit={w: _line(overlaps[w], s[fit]) for w in weightings},
        slope_mm=slope_mm,
        sensitivity_mm=slope_mm / mean_se if mean_se > 0 else nan,
        n_fit=n_fit,
    )
