"""Subject-level confidence: would the scores, and their order, hold for other subjects?

The standard error of :class:`SpecificityResult` is Monte-Carlo error only: it shrinks as
M grows and says nothing about the N subjects being a sample. Here the *subjects* are
resampled by the jackknife: the score is recomputed with each subject (or group of
subjects) left out, and the spread of those replicates estimates the subject-level standard
error (Efron & Tibshirani, *An Introduction to the Bootstrap*, 1993, ch. 11; Shao & Wu,
Ann. Stat. 17(3), 1989, for deleting groups).

Why the jackknife rather than the bootstrap: a bootstrap set repeats subjects, and a
repeated image is a training point at distance 0 from itself; the model of such a set has
fewer modes and its nearest-training distances are biased by the copies. Leaving subjects
out keeps every replicate a set of distinct subjects, costs exactly one model per replicate
(each from the N x N Gram matrix: no image is resampled again), and is deterministic.

- **Specificity and generalization**: grouped jackknife with G groups (subject i in group
  ``i mod G``; G = N is leave-one-out); each replicate's model comes from the Gram matrix
  with the group's rows and columns removed and re-centred, and its samples use the same
  seed as every other replicate and registration (common random numbers), so Monte-Carlo
  noise largely cancels in differences.
- **Overlap**: leave-one-subject-out, exact and free from the per-image sums: leaving
  subject k out removes ``target_sums[k]`` from the pair sums of minima and
  ``(N - 2) vol_k + sum_j vol_j - target_sums[k]`` from those of maxima.
- **Subjects with several images** (a manifest's ``subjects``: contrasts of one subject, in
  a mixture's groups, or repeat scans): a subject is left out with all its images, so the
  replicates resample subjects, not images. The overlap then needs, besides the per-image
  sums, the pair sum of minima of each two images of one subject.

Intervals are ``score +- t_{0.975, G-1} SE`` with ``SE^2 = (G - 1) / G sum_g (r_g - r_bar)^2``,
computed on a scale that respects what the score can be (:func:`measure_bounds`): on the log
scale for specificity and generalization (distances, never negative), on the logit scale for
the overlap (0 to 1), then mapped back -- so no interval reaches a value the score cannot take,
and where the jackknife is well behaved (small relative spread) the interval is the linear one
to first order (Efron & Tibshirani 1993, ch. 12-14, on transformed intervals). A difference
between two registrations is computed on the linear scale from the paired replicates (same
subjects left out), and two registrations are *separable* when its interval excludes 0.
The probability that a registration is best is that of a normal with the replicates'
covariance across registrations (an approximation: it treats the jackknife covariance as
exact).

**Rank stability** (challengeR's bootstrap ranking, Wiesenfarth et al., Sci. Rep. 11, 2021;
:func:`bootstrap_ranks`): the subjects' contributions are the jackknife pseudo-values
``G score - (G - 1) r_g`` of each leave-out group g (Efron & Tibshirani 1993, ch. 11.5),
whose mean is the score's jackknife estimate and whose standard error is the jackknife's.
A bootstrap resamples the groups with replacement, the same draw for every registration
(paired, as the subjects are shared), and moves each score by the resampled mean of its
pseudo-values; the registrations are ranked in every draw. No image is resampled and no
model refitted (which a bootstrap of the images themselves would need, with the repeated
images this module's jackknife avoids): it costs B draws of G numbers per registration.
"""

from __future__ import annotations

import math
from collections.abc import Hashable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy import special, stats

from .._errors import readable
from .._output import json_number
from .model import TextureModel
from .overlap import OverlapTable
from .specificity import texture_measures

__all__ = [
    "Interval",
    "Comparison",
    "jackknife_groups",
    "jackknife_interval",
    "measure_bounds",
    "specificity_replicates",
    "overlap_replicates",
    "compare",
    "probability_best",
    "tie_groups",
    "TIE_Z",
    "RankStability",
    "BOOTSTRAP_RANKS",
    "bootstrap_ranks",
    "significance_map",
    "LEVEL",
]

LEVEL = 0.95

#: A difference within this many combined standard errors is noise (two-sided 95%).
TIE_Z = 1.96


@dataclass(frozen=True)
class Interval:
    """A score with its subject-level standard error and 95% interval.

    Attributes
    ----------
    value : float
        The score on all subjects.
    stderr : float
        Jackknife standard error over subjects (linear scale).
    lo, hi : float
        ``value -+ t_{0.975, G-1} stderr`` on the scale of :func:`jackknife_interval`'s
        `bounds` (linear without bounds), so never outside them.
    n_replicates : int
        G, the number of leave-out replicates.
    """

    value: float
    stderr: float
    lo: float
    hi: float
    n_replicates: int

    def to_list(self) -> list[float | None]:
        return [json_number(self.lo), json_number(self.hi)]


@dataclass(frozen=True)
class Comparison:
    """The difference ``a - b`` of one measure between two registrations.

    Attributes
    ----------
    measure : str
        ``"specificity"``, ``"generalization"`` or ``"overlap.<weighting>"``.
    a, b : str
        The registrations.
    difference : float
        ``score(a) - score(b)`` on all subjects.
    ci95 : tuple of float
        Its subject-level 95% interval.
    separable : bool
        The interval excludes 0.
    """

    measure: str
    a: str
    b: str
    difference: float
    ci95: tuple[float, float]
    separable: bool

    def to_dict(self) -> dict:
        return {
            "measure": self.measure,
            "a": self.a,
            "b": self.b,
            "difference": json_number(self.difference),
            "ci95": [json_number(v) for v in self.ci95],
            "separable": self.separable,
        }


def jackknife_groups(
    n_images: int, n_groups: int | None = None, *, subjects: Sequence[Hashable] | None = None
) -> list[np.ndarray]:
    """Image indices of each leave-out group: subject j in group ``j mod G``.

    Parameters
    ----------
    n_images : int
        N; with at least 4 subjects (every replicate keeps at least 3 images for a model).
    n_groups : int, optional
        G; default one group per subject (leave one subject out). Clipped to the number of
        subjects.
    subjects : sequence of hashable, length n_images, optional
        Each image's subject, where a subject has several images (contrasts or repeat
        scans, the manifest's ``subjects``): a group leaves out all of its subjects' images.
        Subjects are numbered in order of first appearance. Default: each image is its own
        subject.

    Returns
    -------
    list of ndarray of int, length G
        The images each replicate leaves out, in increasing order.
    """
    if subjects is None:
        unit = np.arange(n_images)
    else:
        if len(subjects) != n_images:
            raise ValueError(f"subjects: length {len(subjects)} for {n_images} images")
        index: dict[Hashable, int] = {}
        unit = np.array([index.setdefault(s, len(index)) for s in subjects], dtype=np.int64)
    n_units = int(unit.max()) + 1 if n_images else 0
    if n_units < 4:
        what = "images" if subjects is None else "subjects"
        raise ValueError(f"the jackknife needs at least 4 {what}, got {n_units}")
    g = n_units if n_groups is None else min(int(n_groups), n_units)
    if g < 2:
        raise ValueError(f"n_groups: expected at least 2, got {readable(n_groups)}")
    groups = [np.flatnonzero(unit % g == k) for k in range(g)]
    if n_images - max(grp.size for grp in groups) < 3:
        raise ValueError(f"n_groups: {g} groups of {n_images} images leave fewer than 3 images")
    return groups


def measure_bounds(measure: str) -> tuple[float, float]:
    """The values a measure can take: ``(0, inf)`` for specificity and generalization
    (mean distances), ``(0, 1)`` for ``overlap.<weighting>``."""
    if measure.startswith("overlap."):
        return (0.0, 1.0)
    if measure in ("specificity", "generalization"):
        return (0.0, math.inf)
    raise ValueError(
        f"measure: {measure!r} is not 'specificity', 'generalization' or 'overlap.<weighting>'"
    )


def _scale(lo: float, hi: float):
    """An increasing map of the open interval (lo, hi) onto the real line, and its inverse."""
    if math.isfinite(lo) and math.isfinite(hi):
        return (
            lambda x: np.log(x - lo) - np.log(hi - x),
            lambda y: lo + (hi - lo) * special.expit(y),
        )
    if math.isfinite(lo):
        return (lambda x: np.log(x - lo), lambda y: lo + np.exp(y))
    if math.isfinite(hi):
        return (lambda x: -np.log(hi - x), lambda y: hi - np.exp(-y))
    return (lambda x: x, lambda y: y)


def jackknife_interval(
    value: float,
    replicates: np.ndarray,
    *,
    level: float = LEVEL,
    bounds: tuple[float, float] = (-math.inf, math.inf),
) -> Interval:
    """The jackknife standard error of `value` from its leave-out `replicates`, and interval.

    Parameters
    ----------
    value : float
        The statistic on all subjects.
    replicates : ndarray of shape (n_groups,)
        The statistic with each group left out.
    level : float
        Coverage of the interval (t quantile with G - 1 degrees of freedom).
    bounds : tuple of float
        ``(lower, upper)``: the values the statistic can take (:func:`measure_bounds`);
        default the real line.

    Returns
    -------
    Interval
        Its ``stderr`` is on the linear scale; ``lo, hi`` inside `bounds`.

    Notes
    -----
    With a finite bound the interval is computed on a scale that maps the open range onto
    the real line -- ``log(x - lower)`` for ``(lower, inf)``, the logit of
    ``(x - lower) / (upper - lower)`` for a finite range -- as ``h(value) -+ t SE_h`` with
    ``SE_h`` the jackknife standard error of the replicates ``h(r_g)``, and mapped back. A
    score of 0.13 with replicates spread by 0.001 gets the linear interval to four digits;
    a skewed one gets an asymmetric interval above 0 instead of a negative lower end. The
    transform is undefined when the value or a replicate sits on a bound (an overlap of
    exactly 1, a distance of 0): then the linear interval is used, clipped to `bounds` (the
    values it would reach past them are impossible).
    """
    r = np.asarray(replicates, dtype=np.float64)
    g = r.size
    if g < 2 or not np.all(np.isfinite(r)):
        return Interval(float(value), math.nan, math.nan, math.nan, g)
    lower, upper = (float(b) for b in bounds)
    value = float(value)
    se = _jackknife_se(r)
    t = float(stats.t.ppf(0.5 + level / 2, g - 1))
    inside = lower < min(value, r.min()) and max(value, r.max()) < upper
    if not inside or (math.isinf(lower) and math.isinf(upper)):
        lo = min(max(value - t * se, lower), value)
        hi = max(min(value + t * se, upper), value)
        return Interval(value, se, lo, hi, g)
    forward, back = _scale(lower, upper)
    centre, se_h = float(forward(value)), _jackknife_se(forward(r))
    with np.errstate(over="ignore"):  # exp past the float range: the interval is unbounded
        lo = min(float(back(centre - t * se_h)), value)  # min/max: round-trip rounding
        hi = max(float(back(centre + t * se_h)), value)
    return Interval(value, se, max(lo, lower), min(hi, upper), g)


def _jackknife_se(r: np.ndarray) -> float:
    """``sqrt((G - 1) / G sum_g (r_g - r_bar)^2)`` of the replicates `r`."""
    return math.sqrt((r.size - 1) / r.size * float(np.sum((r - r.mean()) ** 2)))


def _centred(gram: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """The Gram matrix of the images `keep`, centred on their own mean (from the full one).

    With ``y_i`` centred on the full mean, ``y_i - mean_S(y) = x_i - mean_S(x)``, so the
    subset's Gram matrix is ``H G[S, S] H`` with ``H = I - 1 1^T / |S|``.
    """
    sub = gram[np.ix_(keep, keep)]
    row = sub.mean(axis=0)
    return sub - row[None, :] - row[:, None] + row.mean()


def specificity_replicates(
    gram: np.ndarray,
    *,
    groups: Sequence[np.ndarray],
    n_samples: int,
    distance: str,
    seed: int,
    image_groups: Sequence[Hashable] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Specificity and generalization of each leave-group-out model.

    Parameters
    ----------
    gram : ndarray of shape (n_images, n_images)
        Gram matrix of the centred images (:meth:`TextureModel.from_gram`).
    groups : sequence of ndarray of int
        The images each replicate leaves out, from :func:`jackknife_groups`.
    n_samples, distance, seed
        As :func:`itk_nrreval.texture_measures`; the same seed for every replicate.
    image_groups : sequence of hashable, length n_images, optional
        Each image's group (modality) where the model is a mixture, one Gaussian per group
        (:class:`~itk_nrreval.measures.model.MixtureModel`); each replicate is the mixture of the
        images it keeps.

    Returns
    -------
    specificity, generalization : ndarray of shape (n_groups,)
    """
    n = gram.shape[0]
    spec = np.empty(len(groups))
    gen = np.empty(len(groups))
    for k, out in enumerate(groups):
        keep = np.setdiff1d(np.arange(n), out)
        model = TextureModel.from_gram(_centred(gram, keep))
        s, g = texture_measures(
            model,
            groups=None if image_groups is None else [image_groups[i] for i in keep],
            n_samples=n_samples,
            distance=distance,
            seed=seed,
        )
        spec[k], gen[k] = s.value, g.value
    return spec, gen


def overlap_replicates(
    volume: np.ndarray,
    target_sums: np.ndarray,
    gradient_sums: np.ndarray,
    pair_min: np.ndarray,
    pair_max: np.ndarray,
    *,
    labels: np.ndarray,
    spacing: Sequence[float],
    weightings: Sequence[str],
    left_out: Sequence[np.ndarray] | None = None,
    subject_pairs: np.ndarray | None = None,
    subject_pair_min: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """The generalized overlap with each subject (or group of images) left out, from sums.

    Parameters
    ----------
    volume, target_sums, gradient_sums : ndarray of shape (n_images, n_labels)
        As :meth:`OverlapTable.from_sums` (voxel units).
    pair_min, pair_max : ndarray of shape (n_labels,)
    labels : ndarray of shape (n_labels,)
    spacing : sequence of float
        Voxel size in mm, ITK order.
    weightings : sequence of str
    left_out : sequence of ndarray of int, optional
        The images each replicate leaves out (:func:`jackknife_groups`); default each image
        alone.
    subject_pairs : ndarray of int, shape (n_pairs, 2), optional
        Pairs of images left out together (a subject's images), needed for every pair of
        images that one replicate leaves out.
    subject_pair_min : ndarray of shape (n_pairs, n_labels), optional
        ``sum_v min(A_i, A_j)`` of each of `subject_pairs` (voxel units, over the mask).

    Returns
    -------
    dict of str to ndarray of shape (n_replicates,)
        Per weighting, the overlap of the images each replicate keeps.

    Raises
    ------
    ValueError
        A replicate leaves out two images whose pair is not in `subject_pairs`.

    Notes
    -----
    Leaving image k out removes the pairs (k, j): ``sum_j min(A_k, A_j)`` is
    ``target_sums[k]``, and ``sum_j max(A_k, A_j) = sum_j (A_k + A_j - min(A_k, A_j))``
    is ``(N - 1) vol_k + (sum_j vol_j - vol_k) - target_sums[k]``. Leaving out a set K
    removes each pair inside K twice by that count, so its min (from `subject_pair_min`)
    and max (``vol_k + vol_l - min``) are added back once. Labels no remaining image
    carries drop out.
    """
    vol = np.asarray(volume, np.float64)
    n = vol.shape[0]
    total = vol.sum(axis=0)
    if left_out is None:
        left_out = [np.array([k]) for k in range(n)]
    inside: dict[tuple[int, int], np.ndarray] = {}
    if subject_pairs is not None:
        for (a, b), row in zip(subject_pairs, subject_pair_min, strict=True):
            inside[(min(int(a), int(b)), max(int(a), int(b)))] = row
    out = {w: np.empty(len(left_out)) for w in weightings}
    for r, gone in enumerate(left_out):
        gone = np.sort(np.asarray(gone, dtype=np.int64))
        keep = np.ones(n, bool)
        keep[gone] = False
        p = pair_min - target_sums[gone].sum(axis=0)
        q = pair_max - ((n - 2) * vol[gone] + total - target_sums[gone]).sum(axis=0)
        for i, a in enumerate(gone):
            for b in gone[i + 1 :]:
                both = inside.get((int(a), int(b)))
                if both is None:
                    raise ValueError(
                        f"left_out: images {a} and {b} are left out together, but their "
                        "pair is not in subject_pairs"
                    )
                p = p + both
                q = q + (vol[a] + vol[b] - both)
        present = vol[keep].sum(axis=0) > 0
        table = OverlapTable.from_sums(
            labels[present],
            vol[keep][:, present],
            None,
            gradient_sums[keep][:, present],
            p[present],
            q[present],
            spacing=spacing,
            fuzzy=True,
        )
        for w in weightings:
            out[w][r] = table.generalized(w)
    return out


def compare(
    measure: str,
    values: Mapping[str, float],
    replicates: Mapping[str, np.ndarray],
    *,
    level: float = LEVEL,
) -> list[Comparison]:
    """Every pairwise difference of one measure, with its paired jackknife interval.

    Parameters
    ----------
    measure : str
    values : dict of str to float
        Each registration's score on all subjects.
    replicates : dict of str to ndarray of shape (n_groups,)
        Each registration's leave-out replicates (the same groups for all).
    level : float

    Returns
    -------
    list of Comparison
        One per unordered pair (a before b in the order of `values`).
    """
    names = list(values)
    out = []
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            diff = values[a] - values[b]
            iv = jackknife_interval(diff, replicates[a] - replicates[b], level=level)
            separable = bool(math.isfinite(iv.lo) and (iv.lo > 0 or iv.hi < 0))
            out.append(Comparison(measure, a, b, diff, (iv.lo, iv.hi), separable))
    return out


def probability_best(
    values: Mapping[str, float],
    replicates: Mapping[str, np.ndarray],
    *,
    higher_is_better: bool,
    n_draws: int = 20_000,
    seed: int = 0,
) -> dict[str, float]:
    """Probability that each registration has the best score, over subject samples.

    Draws from a normal centred on the scores with the jackknife covariance of the
    replicates across registrations (paired: the same subjects left out), and counts how
    often each registration is best.

    Parameters
    ----------
    values : dict of str to float
    replicates : dict of str to ndarray of shape (n_groups,)
    higher_is_better : bool
    n_draws : int
    seed : int

    Returns
    -------
    dict of str to float
        Sums to 1 (NaN for all when a replicate is not finite).
    """
    names = list(values)
    r = np.stack([np.asarray(replicates[k], np.float64) for k in names])  # (R, G)
    mu = np.array([values[k] for k in names], np.float64)
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(mu))):
        return {k: math.nan for k in names}
    g = r.shape[1]
    dev = r - r.mean(axis=1, keepdims=True)
    cov = (g - 1) / g * dev @ dev.T
    rng = np.random.default_rng(seed)
    # eigh rather than cholesky: the covariance may be singular (identical registrations)
    w, v = np.linalg.eigh(cov)
    draws = mu + (rng.standard_normal((n_draws, len(names))) * np.sqrt(np.clip(w, 0, None))) @ v.T
    best = np.argmax(draws, axis=1) if higher_is_better else np.argmin(draws, axis=1)
    counts = np.bincount(best, minlength=len(names))
    return {k: float(c) / n_draws for k, c in zip(names, counts, strict=True)}


def tie_groups(
    scores: Mapping[str, float],
    *,
    higher_is_better: bool,
    stderr: Mapping[str, float] | None = None,
    comparisons: Sequence[Comparison] = (),
) -> list[tuple[str, ...]]:
    """The registrations in order, best first, in groups whose scores are not told apart.

    Parameters
    ----------
    scores : dict of str to float
        One measure's score per registration.
    higher_is_better : bool
    stderr : dict of str to float, optional
        Each score's standard error (same units as the scores), e.g. the Monte-Carlo
        standard error of specificity. Missing or NaN: not used.
    comparisons : sequence of Comparison
        This measure's pairwise comparisons (:func:`compare`); a pair not among them is
        judged by `stderr` alone.

    Returns
    -------
    list of tuple of str
        Best group first; NaN scores are in no group.

    Notes
    -----
    A pair with a comparison is told apart exactly when the comparison is separable (its
    subject-level 95% interval excludes 0): the verdict's test
    (:func:`itk_nrreval.measures.verdict.verdict`), so a rank never ties two registrations the
    verdict may decide between by this measure, nor separates two it calls not separable.
    A pair without one is tied when its scores are equal or
    ``|a - b| <= 1.96 sqrt(se_a^2 + se_b^2)`` (:data:`TIE_Z`).

    A group is a run in score order: every registration between two tied ones joins their
    group, and ties chain, except across a separable pair: a group never holds two
    registrations whose comparison is separable. A run ends before the first registration
    separable from one already in it, or where nothing in it is tied with anything after
    it. (Chaining across a separable pair tied two registrations that the verdict decided
    between by this measure, 1.28x apart; issue 44.)
    """
    valid = {k: float(v) for k, v in scores.items() if not math.isnan(float(v))}
    order = sorted(valid, key=lambda k: -valid[k] if higher_is_better else valid[k])
    se = {k: float(v) for k, v in (stderr or {}).items() if v is not None and math.isfinite(v)}
    separable = {frozenset((c.a, c.b)): c.separable for c in comparisons}

    def tied(a: str, b: str) -> bool:
        pair = frozenset((a, b))
        if pair in separable:
            return not separable[pair]
        if valid[a] == valid[b]:
            return True
        if a in se and b in se:
            return abs(valid[a] - valid[b]) <= TIE_Z * math.hypot(se[a], se[b])
        return False

    def last_tied(i: int) -> int:
        """The last position tied with position i (i itself when none after it is)."""
        return max((j for j in range(i + 1, len(order)) if tied(order[i], order[j])), default=i)

    groups: list[tuple[str, ...]] = []
    start = 0
    while start < len(order):
        end, reach = start, last_tied(start)
        while end < reach:
            nxt = order[end + 1]
            if any(separable.get(frozenset((m, nxt)), False) for m in order[start : end + 1]):
                break  # it is told apart from one in the run: it starts the next run
            end += 1
            reach = max(reach, last_tied(end))
        groups.append(tuple(order[start : end + 1]))
        start = end + 1
    return groups


#: Bootstrap draws of the subjects for the rank stability (:func:`bootstrap_ranks`).
BOOTSTRAP_RANKS = 200


@dataclass(frozen=True, eq=False)
class RankStability:
    """How often each registration takes each rank of one measure over subject bootstraps.

    Attributes
    ----------
    measure : str
        ``"specificity"``, ``"generalization"`` or ``"overlap.<weighting>"``.
    names : tuple of str
        The registrations, the rows.
    frequencies : ndarray of float64, shape (n_registrations, n_registrations)
        ``frequencies[i, k]``: the share of the draws in which registration ``names[i]``
        has rank ``k + 1`` (1 is best; tied scores share the better rank, so a row sums to
        1 and a column need not).
    n_bootstrap : int
        B, the draws.
    seed : int
        Of the draws.
    ranks : tuple of int
        Each registration's rank on all subjects by the same rule (its score alone; equal
        scores share the better rank), where the draws are centred. The scores table's
        ranks also tie scores within their noise (:func:`tie_groups`).
    """

    measure: str
    names: tuple[str, ...]
    frequencies: np.ndarray
    n_bootstrap: int
    seed: int
    ranks: tuple[int, ...] = ()

    def median_rank(self, name: str) -> float:
        """The median of `name`'s rank over the draws (the lower median)."""
        cdf = np.cumsum(self.frequencies[self.names.index(name)])
        return float(np.searchsorted(cdf, 0.5 - 1e-12) + 1)

    def to_dict(self) -> dict:
        """JSON-ready: per registration the share of draws at each rank 1..R, its median
        rank and its rank on all subjects; the draws and their seed."""
        return {
            "n_bootstrap": int(self.n_bootstrap),
            "seed": int(self.seed),
            "rank": dict(zip(self.names, (int(r) for r in self.ranks), strict=True)),
            "frequencies": {
                n: [float(v) for v in row]
                for n, row in zip(self.names, self.frequencies, strict=True)
            },
            "median_rank": {n: self.median_rank(n) for n in self.names},
        }


def _min_ranks(scores: np.ndarray, higher_is_better: bool) -> np.ndarray:
    """Ranks (1 = best) of each row's scores, ties sharing the better rank ("1, 2, 2, 4").

    `scores` (B, R); returns int (B, R)."""
    x = -scores if higher_is_better else scores
    # rank = 1 + how many are strictly better
    return 1 + (x[:, None, :] < x[:, :, None]).sum(axis=2)


def bootstrap_ranks(
    measure: str,
    values: Mapping[str, float],
    replicates: Mapping[str, np.ndarray],
    *,
    higher_is_better: bool,
    n_bootstrap: int = BOOTSTRAP_RANKS,
    seed: int = 0,
) -> RankStability:
    """The distribution of every registration's rank over bootstraps of the subjects.

    Parameters
    ----------
    measure : str
    values : dict of str to float
        Each registration's score on all subjects.
    replicates : dict of str to ndarray of shape (n_groups,)
        Each registration's leave-out replicates, the same groups for all
        (:func:`specificity_replicates`, :func:`overlap_replicates`).
    higher_is_better : bool, keyword-only
    n_bootstrap : int, keyword-only
        B, the draws.
    seed : int, keyword-only
        Of the draws (``np.random.default_rng``).

    Returns
    -------
    RankStability
        All NaN frequencies when a score or replicate is not finite.

    Notes
    -----
    With ``p_g = G score - (G - 1) r_g`` the pseudo-value of group g, draw b's score is
    ``score + mean(p[draw_b]) - mean(p)``: the subjects' contributions resampled, centred on
    the score itself. Every registration uses the same draws of the groups.
    """
    names = tuple(values)
    r = np.stack([np.asarray(replicates[n], np.float64) for n in names])  # (R, G)
    mu = np.array([float(values[n]) for n in names])
    observed = tuple(int(k) for k in _min_ranks(mu[None, :], higher_is_better)[0])
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(mu))) or r.shape[1] < 2:
        freq = np.full((len(names), len(names)), np.nan)
        return RankStability(measure, names, freq, int(n_bootstrap), int(seed), observed)
    g = r.shape[1]
    pseudo = g * mu[:, None] - (g - 1) * r
    draws = np.random.default_rng(seed).integers(0, g, size=(int(n_bootstrap), g))
    scores = mu[None, :] + pseudo[:, draws].mean(axis=2).T - pseudo.mean(axis=1)[None, :]
    ranks = _min_ranks(scores, higher_is_better)  # (B, R)
    freq = np.stack([np.bincount(ranks[:, i] - 1, minlength=len(names)) for i in range(len(names))])
    freq = freq / float(n_bootstrap)
    return RankStability(measure, names, freq, int(n_bootstrap), int(seed), observed)


def significance_map(
    comparisons: Sequence[Comparison], measure: str, names: Sequence[str]
) -> dict[str, dict[str, str]]:
    """Which registration is told apart from which by one measure, and which way.

    Parameters
    ----------
    comparisons : sequence of Comparison
        The paired comparisons (:func:`compare`), of any measures.
    measure : str
    names : sequence of str
        The registrations.

    Returns
    -------
    dict of str to dict of str to str
        ``out[a][b]`` for every ``a != b``: ``"better"`` or ``"worse"`` when the pair is
        separable (the subject-level 95% interval of the difference excludes 0) and `a`'s
        score is the better or the worse; ``"not separable"``; ``"not compared"`` when no
        comparison of the pair was computed.
    """
    up = measure.startswith("overlap.")  # evaluation.higher_is_better's rule
    out = {a: {b: "not compared" for b in names if b != a} for a in names}
    for c in comparisons:
        if c.measure != measure or c.a not in out or c.b not in out:
            continue
        if not c.separable:
            out[c.a][c.b] = out[c.b][c.a] = "not separable"
            continue
        a_better = (c.difference > 0) == up
        out[c.a][c.b] = "better" if a_better else "worse"
        out[c.b][c.a] = "worse" if a_better else "better"
    return out
