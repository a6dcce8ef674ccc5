"""The paper's validation experiment (Section IV): perturb a registered set, track specificity.

Start from N registered images with labels on one grid. For every mean displacement ``d``
and every repeat, each image (and its labels, as one-hot memberships) is perturbed by its own
independent random clamped-plate-spline warp of exactly that mean displacement
(:mod:`itk_nrreval.warps`: biharmonic in 2D as in the paper, triharmonic in 3D; the ball in
mm); the specificity of the perturbed set's texture model and the generalized Tanimoto
overlap of its labels are recorded. Specificity should rise as overlap falls: the paper finds
a straight line for ``d >= 0.375`` pixels (Fig. 2) and a dip below the unperturbed value at
sub-pixel ``d`` (interpolation smoothing).

The paper worked on 2D mid-brain slices of registered 3D images "at an equivalent level
across the set"; ``section="z"`` (``nrreval validate --slice z``) does the same with a slice
of the common frame, and without it the experiment runs in full 3D.

Full 3D reaches smaller ``d`` than 2D before warps fold: the ball covers a smaller part of
the grid (52 % of a cube against 79 % of a square) and a 3D bump folds sooner (see
:func:`~itk_nrreval.warps.random_cps`); an unreachable ``d`` is refused with the largest
one that is reachable.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ._errors import InputError
from ._executors import Executor, local_executor
from ._images import image_stack, mask_array
from ._output import claim_entries, json_number, write_json, write_text
from ._progress import progress_bar
from .overlap import WEIGHTINGS, overlap_table
from .report.validation import OUTPUT_FILES, write_validation
from .specificity import specificity
from .warps import MEMBERSHIP_TOLERANCE, CPSWarp, FoldingError, random_cps, warp_stack

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
_AXES = ("x", "y", "z")
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
        from ._version import __version__

        out = claim_entries(out_dir, OUTPUT_FILES, command="validate")
        paths = [out / name for name in OUTPUT_FILES[:2]]
        write_text(paths[0], self.to_csv())
        write_json(paths[1], {"version": __version__, **self.to_dict()})
        return paths + write_validation(self, out, version=__version__)


# ----------------------------------------------------------------------------------------
# Inputs
# ----------------------------------------------------------------------------------------


def parse_section(section) -> tuple[str, int | None] | None:
    """``"z"``, ``"z:47"``, ``("z", 47)`` or None -> ``(axis, index or None)`` or None.

    The axis names the common grid's ITK axis (``x``, ``y`` or ``z``; ``z`` is the first
    numpy axis); no index means the middle slice.

    Raises
    ------
    InputError
        Anything else (the message quotes it).
    """
    if section is None:
        return None
    if isinstance(section, str):
        axis, _, index = section.strip().partition(":")
    else:
        try:
            axis, index = section
        except (TypeError, ValueError):
            raise InputError(
                f"slice: expected AXIS[:INDEX] such as z or z:40, got {section!r}"
            ) from None
    axis = str(axis).strip().lower()
    if axis not in _AXES:
        raise InputError(f"slice: axis must be x, y or z, got {section!r}")
    if index is None or (isinstance(index, str) and not index.strip()):
        return axis, None
    try:
        value = int(str(index).strip())
    except ValueError:
        raise InputError(f"slice: index must be an integer >= 0, got {section!r}") from None
    if value < 0:
        raise InputError(f"slice: index must be an integer >= 0, got {section!r}")
    return axis, value


def _section_index(section, size_itk: Sequence[int]) -> tuple[int, int]:
    """(ITK axis, index) of a parsed section on a grid of ITK size `size_itk` (3D)."""
    axis, index = section
    a = _AXES.index(axis)
    n = int(size_itk[a])
    index = n // 2 if index is None else index
    if index >= n:
        raise InputError(
            f"slice {axis}:{index}: out of range, the grid has {n} slices along {axis}"
        )
    return a, index


def _without_axis(spacing: Sequence[float], axis: int) -> tuple[float, ...]:
    """The spacing (mm, ITK order) of a slice across ITK axis `axis`."""
    return tuple(float(s) for k, s in enumerate(spacing) if k != axis)


def take_section(images, labels, spacing, section, *, mask=None):
    """The 2D slice of 3D arrays at one level of their common grid.

    Parameters
    ----------
    images : ndarray of shape (n_images, nz, ny, nx)
    labels : ndarray of shape (n_images, nz, ny, nx) or (n_images, n_labels, nz, ny, nx)
    spacing : sequence of 3 float or None
        mm, ITK order.
    section : str or (str, int)
        ``AXIS[:INDEX]`` (:func:`parse_section`); default index the middle slice.
    mask : ndarray of shape (nz, ny, nx), optional

    Returns
    -------
    images, labels, spacing, mask, (axis, index)
        The slices (2D spatial axes, numpy order), the 2D spacing (ITK order of the two
        remaining axes), and the slice taken.
    """
    section = parse_section(section)
    images = np.asarray(images)
    if images.ndim != 4:
        raise InputError(f"slice: needs 3D images, got spatial shape {images.shape[1:]}")
    size_itk = images.shape[1:][::-1]
    a, index = _section_index(section, size_itk)
    np_axis = 2 - a  # spatial numpy axis
    images = np.take(images, index, axis=1 + np_axis)
    labels = np.asarray(labels)
    lab_axis = labels.ndim - 3 + np_axis
    labels = np.take(labels, index, axis=lab_axis)
    if mask is not None:
        mask = np.take(np.asarray(mask), index, axis=np_axis)
    if spacing is not None:
        spacing = _without_axis(spacing, a)
    return images, labels, spacing, mask, (_AXES[a], index)


def manifest_set(manifest, *, section=None, progress: bool = True):
    """The images and label memberships of a manifest, resampled into its common frame.

    Uses the common-frame registration's transforms (the registered set the paper perturbs).

    Parameters
    ----------
    manifest : path, mapping or Manifest
    section : str or (str, int), optional
        ``AXIS[:INDEX]`` (:func:`parse_section`): resample only that slice of the common
        grid (default index: the middle slice), the paper's "2D slices at an equivalent
        level across the set". The grid must be 3D.
    progress : bool

    Returns
    -------
    images : ndarray of shape (n_images, *spatial), float64
    memberships : ndarray of shape (n_images, n_labels, *spatial), float32
        Component 0 is the background (label value 0); components 1.. are the nonzero label
        values present in the (sliced) maps, ascending.
    geometry : Geometry
        The grid resampled onto (a one-voxel-thick 3D grid for a section).

    Raises
    ------
    InputError
        A bad manifest, one without labels, or a section of a 2D grid / out of range.
    """
    images, members, grid, _, _ = _manifest_arrays(manifest, section, progress)
    return images, members, grid


def _manifest_arrays(manifest, section, progress: bool):
    """:func:`manifest_set`, the section taken (``(axis, index)`` or None), and the coverage.

    The coverage is ``(region, fraction of the mask it keeps, name, masked)``; the region
    (bool, the images' spatial shape) is where the texture model is taken, as in
    :func:`itk_nrreval.evaluate`: inside the manifest's mask, where every image covers the
    common grid (voxels outside an image's field of view hold no value, and 0 there would
    read as texture).
    """
    from ._images import Geometry
    from .frame import (
        common_reference,
        label_values,
        read_chains,
        resample_images,
        resample_memberships,
    )
    from .manifest import load_manifest

    m = load_manifest(manifest)
    name = str(m.source) if m.source is not None else "manifest"
    if m.labels is None:
        raise InputError(f"{name}: validation needs label maps ('labels:' in the manifest)")
    grid = full_grid = Geometry.from_image(common_reference(m))
    mask = mask_array(m.mask, shape=full_grid.shape, geometry=full_grid)
    taken = None
    if section is not None:
        if grid.dimension != 3:
            raise InputError(f"{name}: a slice needs a 3D common frame, got a 2D one")
        a, index = _section_index(parse_section(section), grid.size)
        taken = (_AXES[a], index)
        if mask is not None:  # the slice of it, one voxel thick as the sliced grid
            mask = np.take(mask, [index], axis=2 - a)
        direction = np.array(grid.direction).reshape(3, 3)
        offset = np.zeros(3)
        offset[a] = index * grid.spacing[a]
        size = list(grid.size)
        size[a] = 1
        grid = Geometry(
            tuple(size),
            grid.spacing,
            tuple(float(v) for v in np.array(grid.origin) + direction @ offset),
            grid.direction,
        )
    chains = read_chains(m, m.common_frame)
    images = resample_images(
        m.scored_images,
        chains,
        grid,
        desc="resampling images",
        progress=progress,
        outside=np.nan,
    )
    covered = ~np.isnan(images).any(axis=0)
    images[np.isnan(images)] = 0.0  # outside the region only: the inputs are checked finite
    found = [int(v) for v in label_values(m.labels) if v != 0]
    values = np.array([0, *found], dtype=np.int64)
    members = resample_memberships(m.labels, chains, grid, values=values, progress=progress)
    members = _drop_absent(members)
    if mask is None:
        mask = np.ones(covered.shape, dtype=bool)
    region = covered & mask
    if taken is not None:  # drop the one-voxel axis: 2D arrays
        np_axis = 2 - _AXES.index(taken[0])
        images = np.take(images, 0, axis=1 + np_axis)
        members = np.take(members, 0, axis=2 + np_axis)
        region = np.take(region, 0, axis=np_axis)
    where = f"{name}" + (f", slice {taken[0]}:{taken[1]}" if taken is not None else "")
    if not region.any():
        raise InputError(
            f"{where}: no voxel of the common grid is inside the mask and covered by every image"
        )
    coverage = (region, float(region.sum() / mask.sum()), where, m.mask is not None)
    return images, members, grid, taken, coverage


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
    from .manifest import load_manifest

    for key in ("spacing", "section", "mask"):
        if key in options:
            raise TypeError(f"validate_manifest() got an unexpected keyword argument {key!r}")
    from ._pipeline import COVERAGE_WARNING

    given = manifest
    manifest = load_manifest(manifest)  # once (a Manifest: as it is): its checks read every image
    source = str(given) if given is not manifest else str(manifest.source or "manifest")
    images, members, grid, taken, (region, fraction, where, masked) = _manifest_arrays(
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
        spacing = _without_axis(spacing, _AXES.index(taken[0]))
    options.setdefault("source", source)
    result = validate(images, members, spacing=spacing, mask=region, **options)
    parameters = {**result.parameters, "registration": manifest.common_frame}
    if taken is not None:
        parameters["section"] = _section_record(taken)
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


# ----------------------------------------------------------------------------------------
# The experiment
# ----------------------------------------------------------------------------------------


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
    inputs = _read_inputs(images, labels, mask=mask, spacing=spacing, section=section)
    perturbation = _Perturbation(inputs, n_knots=n_knots, seed=seed, max_tries=max_tries)
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
            "section": _section_record(inputs.section),
        },
        spacing=None if inputs.spacing is None else tuple(float(s) for s in inputs.spacing),
    )


@dataclass(frozen=True)
class _Inputs:
    """The registered set to perturb, checked (and sliced when a section was asked for).

    Attributes
    ----------
    images : ndarray of shape (n_images, *spatial)
    labels : ndarray
        Channel codes, int32 of shape (n_images, *spatial) (:func:`_compact`), or
        memberships, float of shape (n_images, n_labels, *spatial) (:func:`_drop_absent`).
    n_labels : int
        Channels of the memberships, the background 0 included.
    spacing : tuple of float or None
        mm, ITK order; None for bare arrays given without one.
    mask : ndarray of bool of shape spatial, or None
    section : (str, int) or None
        The slice taken (axis, index).
    """

    images: np.ndarray
    labels: np.ndarray
    n_labels: int
    spacing: tuple[float, ...] | None
    mask: np.ndarray | None
    section: tuple[str, int] | None

    @property
    def n_images(self) -> int:
        return self.images.shape[0]

    @property
    def spatial(self) -> tuple[int, ...]:
        return tuple(self.images.shape[1:])

    @property
    def fuzzy(self) -> bool:
        """Whether the labels are memberships (warped as given) rather than channel codes."""
        return np.issubdtype(self.labels.dtype, np.floating)


def _read_inputs(images, labels, *, mask, spacing, section) -> _Inputs:
    """:func:`validate`'s images, labels, mask and spacing read and checked, the section taken.

    Raises
    ------
    InputError
        Fewer than 3 images, not 2D or 3D, a bad spacing, labels or mask, a mask empty on
        the section, or fewer than 3 voxels along an axis.
    """
    stack = image_stack(images, what="image")
    data = stack.data
    n, spatial = data.shape[0], data.shape[1:]
    if n < 3:
        raise InputError(f"validation needs at least 3 images, got {n}")
    if len(spatial) not in (2, 3):
        raise InputError(f"images must be 2D or 3D, got spatial shape {spatial}")
    if stack.geometry is not None:
        if spacing is not None:
            raise ValueError("spacing: the images bring their own; give it for bare arrays only")
        spacing = stack.geometry.spacing
    elif spacing is not None:
        spacing = tuple(float(s) for s in spacing)
        if len(spacing) != len(spatial) or not all(math.isfinite(s) and s > 0 for s in spacing):
            raise InputError(f"spacing: expected {len(spatial)} positive mm, got {spacing!r}")
    lab = _labels(labels, n, spatial)
    mask_arr = mask_array(mask, shape=spatial, geometry=stack.geometry)
    taken = None
    if section is not None:
        data, lab, spacing, mask_arr, taken = take_section(
            data, lab, spacing, section, mask=mask_arr
        )
        spatial = data.shape[1:]
        if mask_arr is not None and not mask_arr.any():
            raise InputError(f"mask: empty on slice {taken[0]}:{taken[1]}")
    if min(spatial) < 3:
        raise InputError(f"images must have at least 3 voxels per axis, got {spatial}")
    if np.issubdtype(lab.dtype, np.floating):
        lab = _drop_absent(lab)
        n_labels = lab.shape[1]
    else:
        lab, n_labels = _compact(lab)
    return _Inputs(data, lab, n_labels, spacing, mask_arr, taken)


@dataclass(frozen=True)
class _Instance:
    """One perturbed set: its mean pixel displacement ``d`` and repeat, the warped images
    (n_images, *spatial), their memberships (n_images, n_labels, *spatial), the smallest
    Jacobian determinant of the N warps and their mean displacement in mm."""

    displacement: float
    repeat: int
    images: np.ndarray
    memberships: np.ndarray
    min_jacobian: float
    displacement_mm: float


@dataclass(frozen=True)
class _Perturbation:
    """The random CPS warps of a validation run: image i's warp in repeat r at displacement
    d, and the perturbed set of (d, r)."""

    inputs: _Inputs
    n_knots: int
    seed: int
    max_tries: int

    def warp(self, d: float, r: int, i: int) -> CPSWarp:
        """Image i's warp from its own seed (independent of the other values of d).

        Raises
        ------
        InputError
            No warp of mean displacement `d` without folding (:func:`_unreachable`).
        """
        spatial = self.inputs.spatial
        try:
            return random_cps(
                spatial,
                d,
                spacing=self.inputs.spacing,
                n_knots=self.n_knots,
                seed=np.random.default_rng([self.seed, round(d * 1e6), r, i]),
                max_tries=self.max_tries,
            )
        except FoldingError as exc:
            raise _unreachable(d, exc, spatial, self.max_tries) from None

    def image(self, d: float, r: int, i: int):
        """Image i and its memberships warped: (image, memberships, min Jacobian, mm)."""
        inputs = self.inputs
        warp = self.warp(d, r, i)
        try:
            img, mem = warp_stack(
                inputs.images[i : i + 1],
                [warp],
                labels=inputs.labels[i : i + 1],
                n_labels=None if inputs.fuzzy else inputs.n_labels,
            )
        except FoldingError as exc:
            raise _unreachable(d, exc, inputs.spatial, self.max_tries) from None
        return img[0], mem[0], warp.min_jacobian, warp.mean_displacement_mm

    def instance(self, d: float, r: int, executor: Executor) -> _Instance:
        """The whole set perturbed at `d` in repeat `r` (its images warped by `executor`)."""
        inputs = self.inputs
        if d == 0.0:  # the identity: no resampling at all
            members = _onehot(inputs.labels, inputs.n_labels)
            return _Instance(d, r, inputs.images, members, 1.0, 0.0)
        calls = [(d, r, i) for i in range(inputs.n_images)]
        done = executor.map(self.image, calls, desc="warp", progress=False)
        warped = np.empty(inputs.images.shape)
        # memberships are stored as float32 (N x labels x voxels: the largest array here);
        # their overlap sums accumulate in float64
        members = np.empty((inputs.n_images, inputs.n_labels, *inputs.spatial), dtype=np.float32)
        jacobians, mms = np.empty(inputs.n_images), np.empty(inputs.n_images)
        for i, (img, mem, jacobian, mm) in done:  # in any order: placed by index
            warped[i], members[i] = img, mem
            jacobians[i], mms[i] = jacobian, mm
        return _Instance(d, r, warped, members, float(jacobians.min()), float(np.mean(mms)))


def _measure(
    instance: _Instance,
    inputs: _Inputs,
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


def _section_record(section: tuple[str, int] | None) -> dict | None:
    """A section taken as ``ValidationResult.parameters["section"]`` records it."""
    return None if section is None else {"axis": section[0], "index": int(section[1])}


def _unreachable(d: float, exc: FoldingError, spatial, max_tries: int) -> InputError:
    """The one-line message for a displacement that no warp reaches without folding."""
    grid = "x".join(map(str, spatial[::-1]))
    safe, safe_mm = exc.largest_safe, exc.largest_safe_mm
    per_px = safe_mm / safe if safe > 0 and math.isfinite(safe_mm) else math.nan
    if math.isfinite(safe):
        hint = (
            f"the largest safe d seen is {safe:.3g} px ({safe_mm:.3g} mm); "
            "lower the largest displacement"
        )
    else:
        hint = "lower the largest displacement"
    mm = f" ({d * per_px:.3g} mm)" if math.isfinite(per_px) else ""
    return InputError(
        f"displacements: d = {d:g} px{mm} cannot be reached without folding on the "
        f"{grid} grid ({max_tries} random CPS warps tried); {hint}"
    )


def _labels(labels, n: int, spatial: tuple[int, ...]) -> np.ndarray:
    """Integer label maps (n, *spatial) as int64, or memberships (n, L, *spatial) clipped
    to [0, 1] (float32 kept as float32)."""
    if isinstance(labels, np.ndarray) and np.issubdtype(labels.dtype, np.floating):
        if labels.ndim == len(spatial) + 2:
            if labels.shape[0] != n or labels.shape[2:] != spatial:
                raise InputError(
                    f"memberships shape {labels.shape} does not match {n} images of {spatial}"
                )
            if not np.all(np.isfinite(labels)):
                raise InputError("memberships hold NaN or infinite values")
            lo, hi = float(labels.min()), float(labels.max())
            if lo < -MEMBERSHIP_TOLERANCE or hi > 1.0 + MEMBERSHIP_TOLERANCE:
                raise InputError(
                    f"memberships must lie in [0, 1] (up to {MEMBERSHIP_TOLERANCE:g} of "
                    f"rounding), got values from {lo:.9g} to {hi:.9g}"
                )
            out = labels if labels.dtype in (np.float32, np.float64) else labels.astype(float)
            return np.clip(out, 0.0, 1.0) if lo < 0.0 or hi > 1.0 else out
    arr = image_stack(labels, what="label map", dtype=None).data
    if arr.shape != (n, *spatial):
        raise InputError(f"label maps shape {arr.shape} does not match the images' {(n, *spatial)}")
    if arr.dtype.kind not in "iub":
        if not np.all(np.isfinite(arr)) or not np.all(arr == np.round(arr)):
            raise InputError("label maps must hold non-negative integer values")
    if arr.size and arr.min() < 0:
        raise InputError("label maps must hold non-negative integer values")
    return arr.astype(np.int64)


def _compact(lab: np.ndarray) -> tuple[np.ndarray, int]:
    """Integer label maps -> channel codes: 0 for the background value 0 (present or not),
    then one code per nonzero value present in any map, ascending. Codes as int32."""
    values = np.unique(lab)
    values = np.concatenate([[0], values[values != 0]])
    codes = np.searchsorted(values, lab).astype(np.int32)  # values sorted: 0 first
    return codes, len(values)


def _drop_absent(members: np.ndarray) -> np.ndarray:
    """Memberships without the components (other than 0) that are zero in every image."""
    n, n_comp = members.shape[:2]
    keep = np.ones(n_comp, dtype=bool)
    keep[1:] = members[:, 1:].reshape(n, n_comp - 1, -1).any(axis=(0, 2))
    return members if keep.all() else members[:, keep]


def _onehot(lab: np.ndarray, n_labels: int) -> np.ndarray:
    if np.issubdtype(lab.dtype, np.floating):
        return lab
    out = np.empty((lab.shape[0], n_labels, *lab.shape[1:]), dtype=np.float32)
    for k in range(n_labels):
        out[:, k] = lab == k
    return out


# ----------------------------------------------------------------------------------------
# Summary
# ----------------------------------------------------------------------------------------


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
