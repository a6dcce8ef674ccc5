"""The paper's validation experiment (Section IV): perturb a registered set, track specificity.

Start from N registered images with labels on one grid. For every mean displacement ``d``
and every repeat, each image (and its labels, as one-hot memberships) is perturbed by its own
independent random clamped-plate-spline warp of exactly that mean displacement
(:mod:`itk_nrreval.warps`); the specificity of the perturbed set's texture model and the
generalized Tanimoto overlap of its labels are recorded. Specificity should rise as overlap
falls: the paper finds a straight line for ``d >= 0.375`` pixels (Fig. 2) and a dip below the
unperturbed value at sub-pixel ``d`` (interpolation smoothing).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from ._errors import InputError
from ._images import image_stack, mask_array
from ._progress import progress as _progress
from .overlap import WEIGHTINGS, overlap_table
from .specificity import specificity
from .warps import random_cps, warp_stack

__all__ = [
    "DEFAULT_DISPLACEMENTS",
    "FIT_FROM",
    "ValidationRow",
    "ValidationSummary",
    "ValidationResult",
    "validate",
    "synthetic_set",
    "manifest_set",
]

#: The mean displacements (pixels) of the default run: 12 values from 0 to the paper's 3.0.
DEFAULT_DISPLACEMENTS = (0.0, 0.125, 0.25, 0.375, 0.5, 0.75, 1.0, 1.25, 1.5, 2.0, 2.5, 3.0)
#: The straight-line fit and the correlations use ``d >= FIT_FROM`` (the paper's 0.375).
FIT_FROM = 0.375
_KINDS = ("phantom", "mni")


@dataclass(frozen=True)
class ValidationRow:
    """One perturbed instance.

    Attributes
    ----------
    displacement : float
        ``d``, the exact mean pixel displacement of every image's warp.
    repeat : int
    specificity, specificity_stderr : float
        Of the perturbed set's texture model (intensity units).
    overlap : dict of str to float
        Generalized Tanimoto overlap of the perturbed memberships, per weighting.
    min_jacobian : float
        The smallest Jacobian determinant over the N warps (at pixel centres).
    """

    displacement: float
    repeat: int
    specificity: float
    specificity_stderr: float
    overlap: dict[str, float]
    min_jacobian: float

    def to_dict(self) -> dict:
        d = {
            "displacement": self.displacement,
            "repeat": self.repeat,
            "specificity": self.specificity,
            "specificity_stderr": self.specificity_stderr,
        }
        d.update({f"overlap_{w}": v for w, v in self.overlap.items()})
        d["min_jacobian"] = self.min_jacobian
        return d


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
    """

    pearson_r: dict[str, float]
    spearman: float
    slope: float
    sensitivity: float
    monotonic: bool
    unperturbed: float | None

    def to_dict(self) -> dict:
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


@dataclass(frozen=True)
class ValidationResult:
    """The table of a validation run: one row per (d, repeat), plus its summary."""

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

    def column(self, name: str) -> np.ndarray:
        """A column as an array: ``"displacement"``, ``"specificity"``, ``"overlap_<w>"``..."""
        return np.array([r.to_dict()[name] for r in self.rows], dtype=float)

    def means(self) -> dict[str, np.ndarray]:
        """Per distinct ``d``: mean and standard deviation over repeats of each measure."""
        d = self.column("displacement")
        levels = np.unique(d)
        out = {"displacement": levels}
        names = ["specificity", "specificity_stderr", *(f"overlap_{w}" for w in self.weightings)]
        for name in names:
            col = self.column(name)
            out[name] = np.array([col[d == v].mean() for v in levels])
            out[name + "_sd"] = np.array([col[d == v].std() for v in levels])
        return out

    def to_dict(self) -> dict:
        return {
            "source": self.source,
            "n_images": self.n_images,
            "shape": list(self.shape),
            "n_samples": self.n_samples,
            "n_knots": self.n_knots,
            "seed": self.seed,
            "weightings": list(self.weightings),
            "parameters": dict(self.parameters),
            "summary": self.summary.to_dict(),
            "rows": [r.to_dict() for r in self.rows],
        }

    def to_csv(self) -> str:
        """The rows as CSV text (header line first)."""
        dicts = [r.to_dict() for r in self.rows]
        header = list(dicts[0]) if dicts else []
        lines = [",".join(header)]
        lines += [
            ",".join(repr(float(d[k])) if k != "repeat" else str(d[k]) for k in header)
            for d in dicts
        ]
        return "\n".join(lines) + "\n"


def synthetic_set(kind: str = "phantom", *, n_images: int = 10, seed: int = 0):
    """Generated brain-like images and crisp labels in one frame (perfect registration).

    Uses :func:`data_synth.make_population` (2D, 141 x 141) and resamples every subject into
    the template frame through its true transform.

    Returns
    -------
    images : ndarray of shape (n_images, 141, 141), float64
    labels : ndarray of int of shape (n_images, 141, 141)
    """
    if kind not in _KINDS:
        raise ValueError(f"kind must be one of {_KINDS}, got {kind!r}")
    import SimpleITK as sitk

    from data_synth import make_population, perfect_registration

    reg = perfect_registration(make_population(kind, dim=2, n=n_images, seed=seed))
    images = np.stack([sitk.GetArrayFromImage(i) for i in reg.images]).astype(np.float64)
    labels = np.stack([sitk.GetArrayFromImage(i) for i in reg.labels]).astype(np.int64)
    return images, labels


def manifest_set(manifest):
    """The images and label memberships of a manifest, resampled into its common frame.

    Uses the common-frame registration's transforms (the registered set the paper perturbs).

    Returns
    -------
    images : ndarray of shape (n_images, *spatial), float64
    memberships : ndarray of shape (n_images, n_labels, *spatial), float64
        Component 0 is the background.
    geometry : Geometry
        The common grid.

    Raises
    ------
    InputError
        A bad manifest, or one without labels.
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
    if m.labels is None:
        raise InputError(
            f"{m.source or 'manifest'}: validation needs label maps ('labels:' in the manifest)"
        )
    grid = Geometry.from_image(common_reference(m))
    chains = read_chains(m, m.common_frame)
    images = resample_images(m.images, chains, grid, desc="resampling images")
    found = [int(v) for v in label_values(m.labels) if v != 0]
    members = resample_memberships(m.labels, chains, grid, values=[0, *found])
    return images, members.astype(np.float64), grid


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
        Their label maps on the same grid: integers (n_images, *spatial), or floating
        memberships (n_images, n_labels, *spatial) with component 0 the background.
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
    max_tries : int
        Redraws of a folding warp before :class:`~itk_nrreval.warps.FoldingError`.
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

    Notes
    -----
    Perturbed images follow the paper's ``I~(psi(p)) = I(p)``, resampled bilinearly
    (trilinearly); labels are warped as one-hot memberships, so the overlap is fuzzy
    (Crum et al.). Twining et al., IEEE TMI, Section IV.
    """
    ds, weightings = _check(displacements, repeats, n_samples, weightings, n_knots)
    stack = image_stack(images, what="image")
    data = stack.data
    n, spatial = data.shape[0], data.shape[1:]
    if n < 3:
        raise InputError(f"validation needs at least 3 images, got {n}")
    if len(spatial) not in (2, 3):
        raise InputError(f"images must be 2D or 3D, got spatial shape {spatial}")
    lab = _labels(labels, n, spatial)
    mask_arr = mask_array(mask, shape=spatial, geometry=stack.geometry)
    spacing = None if stack.geometry is None else stack.geometry.spacing

    def perturb(d: float, r: int, i: int):
        warp = random_cps(
            spatial,
            d,
            n_knots=n_knots,
            seed=np.random.default_rng([seed, round(d * 1e6), r, i]),
            max_tries=max_tries,
        )
        img, mem = warp_stack(data[i : i + 1], [warp], labels=lab[i : i + 1])
        return img[0], mem[0], warp.min_jacobian

    rows = []
    todo = [(d, r) for d in ds for r in range(repeats)]
    pool = ThreadPoolExecutor(n_jobs) if n_jobs > 1 else None
    try:
        for d, r in _progress(todo, desc="validate", total=len(todo), enabled=progress):
            if d == 0.0:  # the identity: no resampling at all
                warped, members, min_jac = data, _onehot(lab), 1.0
            else:
                jobs = [(d, r, i) for i in range(n)]
                done = list(
                    pool.map(lambda a: perturb(*a), jobs) if pool else (perturb(*a) for a in jobs)
                )
                warped = np.stack([x[0] for x in done])
                members = np.stack([x[1] for x in done])
                min_jac = min(x[2] for x in done)
            spec = specificity(warped, n_samples=n_samples, seed=seed, mask=mask_arr)
            table = overlap_table(members, spacing=spacing)
            rows.append(
                ValidationRow(
                    displacement=d,
                    repeat=r,
                    specificity=spec.value,
                    specificity_stderr=spec.stderr,
                    overlap={w: table.generalized(w) for w in weightings},
                    min_jacobian=min_jac,
                )
            )
    finally:
        if pool is not None:
            pool.shutdown()
    return ValidationResult(
        rows=tuple(rows),
        summary=summarize(rows, weightings),
        weightings=weightings,
        n_images=n,
        shape=tuple(spatial),
        n_samples=int(n_samples),
        n_knots=int(n_knots),
        seed=int(seed),
        source=source,
        parameters={"repeats": int(repeats), "displacements": ds, "fit_from": FIT_FROM},
    )


def _labels(labels, n: int, spatial: tuple[int, ...]) -> np.ndarray:
    if isinstance(labels, np.ndarray) and np.issubdtype(labels.dtype, np.floating):
        if labels.ndim == len(spatial) + 2:
            if labels.shape[0] != n or labels.shape[2:] != spatial:
                raise InputError(
                    f"memberships shape {labels.shape} does not match {n} images of {spatial}"
                )
            return labels.astype(np.float64)
    arr = image_stack(labels, what="label map", dtype=None).data
    if arr.shape != (n, *spatial):
        raise InputError(f"label maps shape {arr.shape} does not match the images' {(n, *spatial)}")
    if not np.all(arr == np.round(arr)) or arr.min() < 0:
        raise InputError("label maps must hold non-negative integer values")
    return arr.astype(np.int64)


def _onehot(lab: np.ndarray) -> np.ndarray:
    if np.issubdtype(lab.dtype, np.floating):
        return lab
    n_labels = int(lab.max()) + 1
    return np.stack([(lab == v) for v in range(n_labels)], axis=1).astype(np.float64)


def _pearson(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a - a.mean(), b - b.mean()
    den = math.sqrt(float(a @ a) * float(b @ b))
    return float(a @ b) / den if den > 0 else math.nan


def _ranks(x: np.ndarray) -> np.ndarray:
    order = np.argsort(x, kind="stable")
    ranks = np.empty(len(x))
    ranks[order] = np.arange(len(x), dtype=float)
    for v in np.unique(x):  # average ranks of ties
        tie = x == v
        ranks[tie] = ranks[tie].mean()
    return ranks


def summarize(rows: Sequence[ValidationRow], weightings: Sequence[str]) -> ValidationSummary:
    """Pearson r, Spearman, slope and sensitivity of a table (rows with ``d >= FIT_FROM``)."""
    d = np.array([r.displacement for r in rows])
    s = np.array([r.specificity for r in rows])
    se = np.array([r.specificity_stderr for r in rows])
    fit = d >= FIT_FROM
    zero = d == 0
    unperturbed = float(s[zero].mean()) if zero.any() else None
    levels = np.unique(d[fit])
    if levels.size < 2:
        nan = math.nan
        return ValidationSummary({w: nan for w in weightings}, nan, nan, nan, False, unperturbed)
    pearson = {w: _pearson(s[fit], np.array([r.overlap[w] for r in rows])[fit]) for w in weightings}
    mean_s = np.array([s[d == v].mean() for v in levels])
    spearman = _pearson(_ranks(levels), _ranks(mean_s))
    slope = float(np.polyfit(d[fit], s[fit], 1)[0])
    return ValidationSummary(
        pearson_r=pearson,
        spearman=spearman,
        slope=slope,
        sensitivity=slope / float(se[fit].mean()),
        monotonic=bool(np.all(np.diff(mean_s) > 0)),
        unperturbed=unperturbed,
    )
