"""Which subjects' registrations failed: per-subject quality control of a registered cohort.

The verdict (:func:`itk_nrreval.evaluation.verdict`) says which registration of a group is
best; this module asks, per registration, which of its subjects stand out from the rest of
the cohort, and why. The measures are computed from numbers the evaluation already has --
nothing is resampled again for them:

* **model distance** (``score``, the images' intensity units): the subject's leave-one-out
  reconstruction error, the Euclidean distance of its resampled image (inside the evaluated
  region) to the texture model of the other N - 1 subjects with all their modes, i.e. to the
  affine span of the others (:func:`itk_nrreval.specificity.loo_generalization`, from the
  N x N Gram matrix alone);
* **deformation**: its transform's folded fraction, SDlogJ, det J range and inverse
  consistency (:class:`itk_nrreval.plausibility.Plausibility`), and the affine map closest
  to it (:class:`itk_nrreval.plausibility.AffineFit`: the determinant of the linear part,
  the non-linear displacement beyond it);
* **overlap** (with labels): the generalized Tanimoto overlap of its label memberships with
  the others', pooled over its N - 1 pairs (the per-image sums hold each subject's sums over
  its pairs, not each pair: the mean of its N - 1 pairwise overlaps is not available), with
  volume weighting (every voxel counts alike: under the inverse-volume weighting a
  structure of a few voxels, whose overlap is mostly partial-volume noise, decided most
  subjects' overlap on generated cohorts);
* **coverage**: the fraction of the common grid (inside the mask) its field of view covers.

Each measure is compared with the cohort by a robust z-score, ``z = (x - median) / (1.4826
MAD)`` over the subjects (the median and MAD of a normal sample estimate its mean and
standard deviation, and a few failed subjects barely move them); scale-like measures
(distances, SDlogJ, displacement, inverse consistency) are compared on the log scale, where
their spread is about symmetric. Each z-score's scale has a floor in its measure's units
(a tenth of a mm for lengths, 0.01 for SDlogJ and the overlap, 1% of the median model
distance: :func:`robust_z`'s `least_spread`), so a cohort that barely varies never makes
a departure too small to matter infinitely many standard deviations; and an
inverse-consistency error below a tenth of a mm counts as a tenth of a mm.
:class:`itk_nrreval.plausibility.SubjectThresholds` says when a subject is flagged, and a
common cause of failure that explains the flags is named in words (the diagnosis): left off
the common grid, duplicated image, mirrored, stopped early / affine only, scaled
displacements.

**The reference.** When a registration's reference is one of the cohort's own images -- the
manifest's ``reference_index: i``, or a reference that is image i's file (or the same voxels
on the same grid) while subject i's transform is the identity (:func:`reference_subject`) --
subject i was registered to itself: its transform says nothing about the registration, and
an identity among deformable transforms looks like one that "stopped early". It is reported
as the reference of the registration (:attr:`SubjectQC.reference`), never flagged, and left
out of the cohort statistics (the medians and MADs) the other subjects are judged by; its
image stays in the texture model, as in the scores.

**Subject flags and registration flags.** A flag is a subject's when it sets the subject
apart from its cohort. A kind of flag (:data:`FLAG_KINDS`: folding, a mirrored linear part,
...) carried by at least half of the subjects judged under a registration (every subject
but its reference), and by at least two, is a property of the registration, not of those
subjects: it is the registration's flag, said once (:func:`registration_flags`), and kept
out of those subjects' :attr:`~SubjectQC.flags` (each of them names it in
:attr:`~SubjectQC.registration_flags`). The z-score flags cannot reach half of a cohort (a
robust z above 3.5 is far above the median); the flags on absolute limits can (a B-spline
registration that folds more than 1% of the voxels in 13 of 16 subjects).

**Concern, the ranking.** Each subject's :attr:`~SubjectQC.concern` is a weighted mean of
its robust z-scores, each signed so that positive is worse (:data:`CONCERN_TERMS`,
:func:`concern_scores`): minus the overlap z (with labels) with weight 3, and the log
distance to the model of the others (``z``), the log SDlogJ z and the log
inverse-consistency z with weight 1 each; the two deformation terms count only above zero
(a field smoother than its cohort's is no sign that the subject was registered well: an
affine-only transform has the least SDlogJ of all). With labels the overlap is half of it
and the three image-only terms share the other half; without labels it is their mean; a
term not measured (NaN) is left out and the weights of the others renormalised. It was
chosen on the tuning split of the genuine registrations alone
(``benchmarks/bench_subject_qc_genuine.py``, ``docs/subject-qc.md``), where it tracked
the subjects' true errors better than the largest of the z-scores it replaced (Spearman
mean over the deformable registrations 0.80 against 0.68 with labels, 0.63 against 0.53
without): a mean is not decided by one noisy deformation term. Every subject is listed
worst first by it (:func:`ranked`), so the few most unlike their cohort can be looked at
even when none crosses a threshold. It ranks, it does not flag: the flags on absolute limits
(folding, mirroring, a duplicate, off the grid) are not in it, so a subject flagged for one
of them may rank below unflagged subjects (its flags say why it is listed).
:attr:`~SubjectQC.concern_from` names the term contributing most to it. The reference has
no concern and is listed last.

Two causes need images resampled through changed transforms, and are looked for among the
flagged subjects only (:func:`transform_mixups`, at most :data:`MAX_MIXUP_SUBJECTS` of them,
on the driver after the per-image work): an **inverted transform** (the subject's image
through the inverse of its transform is much closer to the model of the others) and
**another subject's transform** (another flagged subject's image fits it much better than
its own: two subjects' transforms swapped or mixed up).
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from ._brain_masks import BRAIN_MASK_DICE_MIN
from ._output import json_number

if TYPE_CHECKING:  # pragma: no cover
    from .plausibility import SubjectThresholds

__all__ = [
    "SubjectQC",
    "FLAG_KINDS",
    "CONCERN_TERMS",
    "ConcernTerm",
    "concern_scores",
    "IDENTITY_MM",
    "reference_subject",
    "registration_flags",
    "ranked",
    "Alternative",
    "transform_mixups",
    "MAX_MIXUP_SUBJECTS",
    "robust_z",
    "leave_one_out_distances",
    "pair_distances",
    "subject_overlaps",
    "assess_subjects",
    "across_registrations",
    "MAD_TO_SD",
]

#: The MAD of a normal sample times this estimates its standard deviation.
MAD_TO_SD = 1.4826

#: Below this cohort median (mm) of the non-linear displacement, the cohort itself is affine
#: and "affine only" says nothing about one subject.
_AFFINE_COHORT_MM = 1e-3

#: Floors of the log-scale measures: values below are no variation at all (SDlogJ of a
#: linear map), and are compared as the floor, in the z-scores and as the least median a
#: subject is measured against. An inverse-consistency error below a tenth of a mm means
#: nothing: a smooth field, inverted pointwise, measures 1e-4 to 0.007 mm (generated 2D
#: cohorts; issue 30), and a B-spline registration's transforms a few hundredths of a mm
#: (issue 44), all far below the 1-2 mm voxels of the images compared; at the floor of a
#: hundredth of a mm that issue's cohort scored 16 of 36 such subjects z = +inf.
_LOG_FLOORS = {
    "sdlogj": 1e-3,
    "nonlinear_rms_mm": 1e-3,
    "inverse_consistency_mm": 0.1,
    "frame_deviation_mm": 1e-3,
}

#: The least spread a z-score is taken over, in each measure's units: a cohort whose values
#: lie closer together than this is as spread as this for its z-scores, so a departure far
#: below any meaningful size is never many "standard deviations" (a MAD of 0, over half the
#: cohort at one value, made every other subject z = +inf; issue 44). Lengths a tenth of a
#: mm (a tenth of the voxel of 1 mm images, the finest here; the inverse-consistency floor
#: above); SDlogJ 0.01 (log det J varying by 1%: a volume change of 1%, which no
#: registration's quality turns on); the overlap 0.01 (the spread of a clean cohort's
#: overlaps: 0.889 to 0.899 over the clean 3D cohorts of 12 at 2 mm, docs/subject-qc.md);
#: the model distance, in intensity units of no known scale, 1% of the cohort's median.
_LEAST_SPREAD = {
    "sdlogj": 0.01,
    "nonlinear_rms_mm": 0.1,
    "inverse_consistency_mm": 0.1,
    "frame_deviation_mm": 0.1,
    "overlap": 0.01,
}
_LEAST_SPREAD_OF_SCORE = 0.01  # times the cohort's median model distance

#: The kinds of flag, and what the subjects carrying one have, in the words of a
#: registration flag (:func:`registration_flags`: "k of the n subjects <words>").
FLAG_KINDS = {
    "off_grid": "cover too little of the common grid, and are left out of the scores",
    "left_out": "are left out of the scores: another registration maps them off the common grid",
    "duplicate": "have a resampled image (almost) identical to another subject's",
    "mirrored": "have a transform whose linear part mirrors space",
    "model_distance": "are far from the model of the others",
    "folding": "fold",  # said with the threshold and the range instead (_shared_kinds)
    "sdlogj": "have an SDlogJ far above the cohort's",
    "nonlinear_rms_mm": "have a non-linear displacement far above the cohort's",
    "inverse_consistency_mm": "have an inverse-consistency error far above the cohort's",
    "affine_only": "have almost no non-linear displacement",
    "overlap": "have a label overlap with the others far below the cohort's",
    "brain_mask": "have a brain mask that matches the common mask poorly in the common frame",
}


class ConcernTerm(NamedTuple):
    """One term of :attr:`SubjectQC.concern` (:data:`CONCERN_TERMS`)."""

    #: The term in words (:attr:`SubjectQC.concern_from`).
    words: str
    #: Where its z-score is: :func:`concern_scores`'s key.
    key: str
    #: +1 where a larger value is worse, -1 for the overlap, where a smaller one is.
    sign: float
    #: Its weight in the mean.
    weight: float
    #: Only above zero counts (a term below zero counts as zero).
    worse_only: bool


#: The terms of :attr:`SubjectQC.concern` (:func:`concern_scores`). Chosen on the tuning
#: split of the genuine registrations alone (issue 42: ``benchmarks/bench_subject_qc_genuine.py``,
#: ``docs/subject-qc.md``), among the largest of the five signed z-scores (the concern
#: before), the overlap z alone, the model-distance z alone, and means of the model-distance
#: and overlap z with the deformation z-scores added or not (counted above zero only or
#: not) and overlap weights of 1, 2 and 3. Spearman with the true error, mean over the
#: deformable registrations: with labels 0.80 (second scan 0.82), the highest of the
#: combinations and as high as the overlap z alone (0.81), against 0.68 (0.67) before;
#: without labels 0.63 (0.65) against 0.53 (0.49) before and 0.57 (0.59) for the model
#: distance alone. The non-linear displacement z lowered every mean it was added to (0.60
#: without labels), and is left out.
CONCERN_TERMS = (
    ConcernTerm("overlap", "overlap_z", -1.0, 3.0, False),
    ConcernTerm("model distance", "z", 1.0, 1.0, False),
    ConcernTerm("SDlogJ", "sdlogj_z", 1.0, 1.0, True),
    ConcernTerm("inverse consistency", "inverse_consistency_z", 1.0, 1.0, True),
)

#: A subject whose transform moves the points of the grid by less than this RMS (mm) is
#: registered by the identity, for :func:`reference_subject`: a registration of an image to
#: itself returns the identity to round-off (a zero gradient everywhere: the optimizer
#: never moves), while a hundredth of a mm is a hundredth of the 1 mm voxels, the finest
#: here, and far below what any registration of two different images leaves.
IDENTITY_MM = 0.01


@dataclass(frozen=True)
class SubjectQC:
    """One subject's quality control under one registration.

    Attributes
    ----------
    index : int
        The subject's (image's) position in the manifest.
    image : str
        Its image, as the manifest names it.
    score : float or None
        Its distance to the texture model of the other subjects (the images' intensity
        units); None when it was left out of the scores (or N < 4).
    z : float or None
        The robust z-score of its log `score` over the cohort (positive: farther than the
        typical subject).
    deformation : dict of str to float or None
        ``folded_fraction``, ``sdlogj``, ``jacobian_min``, ``jacobian_max``,
        ``inverse_consistency_mm``, ``linear_det``, ``nonlinear_rms_mm``,
        ``displacement_rms_mm``, and the robust z-scores ``sdlogj_z``, ``nonlinear_rms_z``,
        ``inverse_consistency_z`` (log scale).
    overlap : float or None
        Its label overlap with the others (in [0, 1]); None without labels or when left out.
    overlap_z : float or None
        Its robust z-score over the cohort (negative: less overlap than the typical subject).
    coverage : float
        The fraction of the common grid (inside the mask) its field of view covers.
    brain_mask_dice : float or None
        The Dice of its brain mask, brought into the common frame through its transform,
        with the common mask (:func:`itk_nrreval._brain_masks.subject_mask_dice`); None
        where the inputs have no brain masks.
    in_scores : bool
        False when it was left out of every registration's scores (off the common grid).
    flags : tuple of str
        Why it stands out, in words; empty when it does not.
    better_fit : float or None
        For a flagged subject checked by :func:`transform_mixups`: how many times closer to
        the model of the others its image through the inverse of its transform, or another
        flagged subject's image through its transform, is than its own resampled image (the
        best of them); None when not checked.
    diagnosis : str or None
        A common cause of failure that explains the flags, in words; None when none is
        recognised (or nothing is flagged).
    reference : bool
        It is the registration's reference (:func:`reference_subject`): registered to
        itself, never flagged, and out of the cohort statistics the others are judged by.
    registration_flags : tuple of str
        The registration's flags it shares (at least half of the subjects judged carry
        them; :func:`registration_flags`), in words; not among its `flags`.
    concern : float or None
        The weighted mean of its robust z-scores, each signed so that positive is worse
        (:data:`CONCERN_TERMS`, :func:`concern_scores`: minus the overlap z with weight 3,
        the log model distance, log SDlogJ and log inverse-consistency z with weight 1, the
        last two counted above zero only; unitless, in robust standard deviations): what the
        subjects are ranked by (:func:`ranked`). None for the reference, or when none of
        them was measured.
    concern_from : str or None
        Which term contributes most to it (the largest weighted term), in words (e.g.
        ``"model distance"``).
    """

    index: int
    image: str
    score: float | None
    z: float | None
    deformation: Mapping[str, float | None] = field(default_factory=dict)
    overlap: float | None = None
    overlap_z: float | None = None
    coverage: float = math.nan
    brain_mask_dice: float | None = None
    in_scores: bool = True
    flags: tuple[str, ...] = ()
    diagnosis: str | None = None
    better_fit: float | None = None
    reference: bool = False
    registration_flags: tuple[str, ...] = ()
    concern: float | None = None
    concern_from: str | None = None

    @property
    def flagged(self) -> bool:
        """It has a flag of its own (a subject flag; the registration's are not its own)."""
        return bool(self.flags)

    def to_dict(self) -> dict[str, Any]:
        """The ``results.json`` entry: numbers JSON-safe (NaN and infinities as None)."""
        return {
            "index": self.index,
            "image": self.image,
            "score": json_number(self.score),
            "z": json_number(self.z),
            "plausibility": {k: json_number(v) for k, v in self.deformation.items()},
            "overlap": (
                None
                if self.overlap is None
                else {"value": json_number(self.overlap), "z": json_number(self.overlap_z)}
            ),
            "coverage": json_number(self.coverage),
            "brain_mask_dice": json_number(self.brain_mask_dice),
            "in_scores": self.in_scores,
            "flags": list(self.flags),
            "registration_flags": list(self.registration_flags),
            "diagnosis": self.diagnosis,
            "better_fit": json_number(self.better_fit),
            "reference": self.reference,
            "concern": json_number(self.concern),
            "concern_from": self.concern_from,
        }


def robust_z(
    values,
    *,
    log: bool = False,
    floor: float = 0.0,
    least_spread: float = 0.0,
    among: np.ndarray | Sequence[bool] | None = None,
) -> np.ndarray:
    """Robust z-scores over a cohort: ``(x - median) / max(1.4826 MAD, least spread)``.

    Parameters
    ----------
    values : array_like of float, shape (n,)
        One value per subject; NaN values get NaN and are left out of the median and MAD.
    log : bool
        Score ``log(max(x, floor))`` instead of x (for positive, scale-like measures).
    floor : float
        With `log`, values below it are taken as it (must then be > 0).
    least_spread : float
        The least spread, in the units of `values`, the z-scores are taken over: the scale
        is at least this (linear) or, with `log`, at least ``log(1 + least_spread / m)``,
        ``m`` the median (in the units of `values`) or `least_spread` if larger -- the log
        distance from the median to a value `least_spread` above it, at most ``log 2``.
    among : array_like of bool, shape (n,), optional
        The values the median and MAD are taken over (default: every one); every value
        gets its z against them (a registration's reference is scored against the others).

    Returns
    -------
    ndarray of float, shape (n,)
        Finite for finite values when `least_spread` > 0. With `least_spread` 0 and a MAD of
        0 (over half of the cohort share one value), values at the median score 0 and any
        other +-inf: a cohort that does not vary at all makes any departure from it extreme.
    """
    x = np.asarray(values, np.float64).copy()
    if log:
        x = np.log(np.maximum(x, floor))  # NaN stays NaN
    ok = np.isfinite(x)
    z = np.full(x.shape, np.nan)
    cohort = ok if among is None else ok & np.asarray(among, bool)
    if not cohort.any():
        return z
    median = float(np.median(x[cohort]))
    scale = MAD_TO_SD * float(np.median(np.abs(x[cohort] - median)))
    if least_spread > 0:
        if log:
            at = max(math.exp(median), least_spread)
            scale = max(scale, math.log1p(least_spread / at))
        else:
            scale = max(scale, least_spread)
    if scale > 0:
        z[ok] = (x[ok] - median) / scale
    else:
        diff = x[ok] - median
        z[ok] = np.where(diff == 0, 0.0, np.copysign(np.inf, diff))
    return z


def leave_one_out_distances(gram: np.ndarray) -> np.ndarray:
    """Each image's distance to the texture model of the others, from their Gram matrix.

    Parameters
    ----------
    gram : ndarray of shape (n, n)
        Gram matrix of the centred images (:meth:`TextureModel.from_gram`), n >= 4.

    Returns
    -------
    ndarray of shape (n,)
        Image k's Euclidean distance (intensity units) to its reconstruction by the model
        of the n - 1 others with all their modes: its distance to their affine span
        (:func:`itk_nrreval.specificity.loo_generalization`).
    """
    gram = np.asarray(gram, dtype=float)
    n = gram.shape[0]
    centring = np.eye(n) - 1.0 / n
    values, vectors = np.linalg.eigh(centring @ gram @ centring)
    # n points span at most n - 1 dimensions: the centred Gram matrix has one zero
    # eigenvalue, and n - 1 positive ones where the points are affinely independent
    kept = values[1:]
    if kept[0] <= kept[-1] * n * 1e-12:
        # a duplicate or a degenerate cohort: the images in an affine dependency are at
        # distance 0 (refitting each model instead cost n SVDs, O(n^4): half an hour or more at
        # n = 1,000)
        spans = _AffineSpans(gram)
        return np.array([spans.member_distance(k, [k]) for k in range(n)])
    # the distance from point k to the affine span of the others is 1 / sqrt(G+_kk), G+ the
    # pseudo-inverse of the centred Gram matrix: one eigendecomposition for all k, where
    # refitting n models costs n of them
    inverse_diagonal = np.einsum("ij,j,ij->i", vectors[:, 1:], 1.0 / kept, vectors[:, 1:])
    return 1.0 / np.sqrt(inverse_diagonal)


def pair_distances(gram: np.ndarray) -> np.ndarray:
    """The Euclidean distances between the images, shape (n, n), from their Gram matrix.

    ``|x_i - x_j|^2 = G_ii + G_jj - 2 G_ij`` (centring moves every image alike); round-off
    below zero is taken as 0.
    """
    g = np.asarray(gram, np.float64)
    diag = np.diag(g)
    return np.sqrt(np.maximum(diag[:, None] + diag[None, :] - 2 * g, 0.0))


def subject_overlaps(volume, target_sums, weights) -> np.ndarray:
    """Each subject's generalized overlap with the others, from the per-image sums.

    Parameters
    ----------
    volume, target_sums : array_like, shape (n, n_labels)
        ``sum_v A_il`` and ``sum_v sum_{j != i} min(A_il, A_jl)`` (voxel units), as
        :meth:`itk_nrreval.overlap.OverlapTable.from_sums` takes them.
    weights : array_like, shape (n_labels,)
        The label weights alpha_l (e.g. the cohort table's inverse-volume weights).

    Returns
    -------
    ndarray of shape (n,)
        ``sum_l alpha_l sum_{j != i} min(A_il, A_jl) / sum_l alpha_l sum_{j != i} max(A_il,
        A_jl)``: the generalized Tanimoto overlap of the N - 1 pairs (i, j), where
        ``sum_{j != i} max = (N - 2) vol_i + sum_j vol_j - target_sums_i``
        (``max(a, b) = a + b - min(a, b)``). NaN where the denominator is 0.
    """
    vol = np.asarray(volume, np.float64)
    mins = np.asarray(target_sums, np.float64)
    alpha = np.asarray(weights, np.float64)
    n = vol.shape[0]
    maxs = (n - 2) * vol + vol.sum(axis=0) - mins
    num, den = mins @ alpha, maxs @ alpha
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / np.where(den > 0, den, 1.0), np.nan)


def _median(values) -> float:
    """The median of the finite values; NaN (without a warning) when there is none."""
    x = np.asarray(values, np.float64)
    x = x[np.isfinite(x)]
    return float(np.median(x)) if x.size else math.nan


def _fmt(v: float, digits: int = 3) -> str:
    return f"{v:.{digits}g}"


def _z_words(z: float) -> str:
    return "z = +inf" if z == math.inf else "z = -inf" if z == -math.inf else f"z = {z:+.1f}"


def assess_subjects(
    *,
    images: Sequence[str],
    scored: Sequence[int],
    gram: np.ndarray,
    deformation: Mapping[str, Sequence[float | None]],
    coverage: Sequence[float],
    overlap_volume: np.ndarray | None = None,
    overlap_target_sums: np.ndarray | None = None,
    overlap_weights: np.ndarray | None = None,
    mixups: Mapping[int, tuple[float, str]] | None = None,
    reference: int | None = None,
    brain_mask_dice: Sequence[float] | None = None,
    thresholds: SubjectThresholds,
) -> tuple[SubjectQC, ...]:
    """Every subject's quality control under one registration: scores, z, flags, diagnosis.

    Parameters
    ----------
    images : sequence of str, length N
        Every subject's image, in manifest order.
    scored : sequence of int, length n
        The subjects in the scores (indices into `images`, ascending): the rows of `gram`
        and of the overlap sums. The others were left out (off the common grid).
    gram : ndarray of shape (n, n)
        Gram matrix of the scored subjects' centred resampled images (inside the region).
    deformation : mapping of str to sequence of float, each of length N
        Per subject: ``folded_fraction``, ``sdlogj``, ``jacobian_min``, ``jacobian_max``,
        ``inverse_consistency_mm`` (None: not measured), ``linear_det``,
        ``nonlinear_rms_mm``, ``displacement_rms_mm`` (mm); optionally
        ``frame_deviation_mm``, the subject's mean distance between its own estimate of the
        registration's frame and the group's (:class:`~itk_nrreval.frame.FrameMapping`;
        None where the frame was not estimated), reported with its robust z but not flagged:
        a deviation says the subject's transforms under this registration and the common
        one disagree, not which of the two is wrong.
    coverage : sequence of float, length N
        Each subject's covered fraction of the common grid (inside the mask).
    overlap_volume, overlap_target_sums : ndarray of shape (n, n_labels), optional
        The scored subjects' per-label sums (:func:`subject_overlaps`); None without labels.
    overlap_weights : ndarray of shape (n_labels,), optional
        The label weights of the overlap.
    mixups : mapping of int to (float, str), optional
        Flagged subjects resampled through changed transforms (:func:`transform_mixups` on
        this function's first answer): subject index -> (how many times closer the best
        alternative fits, the cause it points to in words).
    reference : int, optional
        The subject that is the registration's reference (:func:`reference_subject`):
        reported as such, never flagged, and left out of the medians and MADs the others
        are judged by.
    brain_mask_dice : sequence of float, length N, optional
        Each subject's brain-mask Dice with the common mask in the common frame
        (:func:`itk_nrreval._brain_masks.subject_mask_dice`; NaN: not measured); None where
        the inputs have no brain masks.
    thresholds : SubjectThresholds

    Returns
    -------
    tuple of SubjectQC
        One per subject, in manifest order.

    Notes
    -----
    A subject is flagged when (thresholds ``th``):

    * it covers less than ``th.off_grid_coverage`` times the cohort's median coverage
      (then it is not in `scored`, and only its deformation is judged);
    * another subject's resampled image lies within ``th.duplicate_distance`` times the
      cohort's median pairwise distance;
    * the linear part of its transform mirrors space (determinant < 0) while the cohort's
      median does not;
    * its log model distance has z > ``th.outlier_z``;
    * it folds more than ``th.folded`` of its voxels;
    * its log SDlogJ, log non-linear displacement or log inverse consistency has z >
      ``th.deformation_z`` and is above ``th.deformation_ratio`` times the cohort's median
      (or the measure's floor, when the median is below it: 0.001 for SDlogJ and mm of
      displacement, 0.1 mm of inverse consistency);
    * its non-linear displacement is below ``th.affine_only_ratio`` times the cohort's
      median (when that median is above 0.001 mm);
    * its overlap has z < ``-th.overlap_z`` and its mismatch ``1 - overlap`` is above
      ``th.overlap_ratio`` times the cohort's median mismatch;
    * its brain mask's Dice with the common mask is below
      :data:`~itk_nrreval._brain_masks.BRAIN_MASK_DICE_MIN` (0.8).

    Every z-score's scale has a floor in its measure's units (:func:`robust_z`'s
    `least_spread`: :data:`_LEAST_SPREAD`), so none is infinite.

    A kind of flag (:data:`FLAG_KINDS`) that at least half of the subjects judged (every
    subject but the `reference`), and at least two, carry is the registration's: each of
    them names it, once in the same words, in ``registration_flags`` instead of ``flags``,
    and it explains nothing of theirs (no diagnosis rests on it).

    The diagnosis is the first that applies of: off the common grid; duplicated image;
    mirrored; stopped early or affine only; scaled displacements (a deformation flag with a
    non-linear displacement above ``th.scaled_ratio`` times the median); an inverted
    transform or another subject's transform (a `mixups` ratio of ``th.better_fit_ratio``
    or more).
    """
    n_all = len(images)
    judged = np.ones(n_all, bool)
    if reference is not None:
        judged[int(reference)] = False
    cohort = _cohort(
        n_all=n_all,
        scored=[int(i) for i in scored],
        gram=gram,
        deformation=deformation,
        coverage=coverage,
        overlap_sums=None
        if overlap_volume is None
        else (overlap_volume, overlap_target_sums, overlap_weights),
        judged=judged,
        brain_mask_dice=brain_mask_dice,
    )
    who = [i for i in range(n_all) if judged[i]]
    # a first pass finds the kinds most subjects share; the second says them once
    first = {i: _flags_and_causes(i, cohort, images, thresholds)[0] for i in who}
    shared = _shared_kinds(first, cohort, thresholds)
    out = []
    for i in range(n_all):
        if not judged[i]:
            out.append(_subject_qc(i, cohort, images, [], [], None, reference=True))
            continue
        flags, causes, theirs = _flags_and_causes(i, cohort, images, thresholds, shared)
        # after the causes read off the transform itself: the inverse of an affine-only or a
        # scaled transform can fit somewhat better too (up to 1.5x on generated cohorts)
        better_fit = mixups[i][0] if mixups and i in mixups else None
        if better_fit is not None and better_fit >= thresholds.better_fit_ratio:
            causes.append(mixups[i][1])
        out.append(_subject_qc(i, cohort, images, flags, causes, better_fit, registration=theirs))
    return tuple(out)


def reference_subject(
    reference: Any,
    images: Sequence[Any],
    *,
    reference_index: int | None = None,
    displacement_rms_mm: Sequence[float | None] | None = None,
) -> int | None:
    """Which subject is a registration's reference, if one is: registered to itself.

    Parameters
    ----------
    reference : path or InMemoryImage
        The registration's reference (:attr:`ManifestRegistration.reference
        <itk_nrreval.manifest.ManifestRegistration.reference>`).
    images : sequence of (path or InMemoryImage)
        The registered images, in manifest order (:attr:`Manifest.images
        <itk_nrreval.manifest.Manifest.images>`).
    reference_index : int, optional, keyword-only
        The manifest's ``reference_index``: it names the reference, whatever the transforms.
    displacement_rms_mm : sequence of float or None, optional, keyword-only
        Per subject, the RMS of ``|T(p) - p|`` over the evaluated voxels of the reference
        grid (mm; :class:`~itk_nrreval.plausibility.AffineFit`); None or NaN: not measured.

    Returns
    -------
    int or None
        `reference_index` when given; else the first subject whose transform is the
        identity (an RMS displacement of at most :data:`IDENTITY_MM`) and whose image is
        the reference: the same file, through any link or spelling, or the same voxels on
        the same grid (the content digest of :func:`itk_nrreval._cache.content_digest`,
        which the manifest's check has computed for the images already); else None.
    """
    if reference_index is not None:
        return int(reference_index)
    if displacement_rms_mm is None:
        return None
    # the identity first: only those subjects' files are compared (as a rule, none)
    still = [
        i for i, d in enumerate(displacement_rms_mm) if d is not None and d <= IDENTITY_MM
    ]  # NaN <= x is False: not measured is not the identity
    if not still:
        return None
    same_file = _file_identity(reference)
    if same_file is not None:
        for i in still:
            if _file_identity(images[i]) == same_file:
                return i
    digest = _content_digest(reference)
    for i in still:
        if _content_digest(images[i]) == digest:
            return i
    return None


def _file_identity(item) -> tuple[int, int] | None:
    """(device, inode) of an image file, the same through links and spellings; None for an
    object in memory (or a file that cannot be read: then its digest says nothing either)."""
    if not isinstance(item, (str, os.PathLike)):
        return None
    try:
        stat = os.stat(item)
    except OSError:
        return None
    return stat.st_dev, stat.st_ino


def _content_digest(item) -> str | None:
    """The digest of the voxels and grid an image holds (a file's or an object's)."""
    if not isinstance(item, (str, os.PathLike)):
        return getattr(item, "content_digest", None)
    from ._cache import content_digest

    try:
        return content_digest(item)
    except (OSError, RuntimeError):
        return None


def registration_flags(subjects: Sequence[SubjectQC]) -> tuple[str, ...]:
    """A registration's flags: the kinds of flag most of its subjects share, each said once.

    Parameters
    ----------
    subjects : sequence of SubjectQC
        Every subject under one registration, in manifest order (:func:`assess_subjects`).

    Returns
    -------
    tuple of str
        Each registration flag in words (:attr:`SubjectQC.registration_flags`), once, in
        the order the subjects first name them; empty when there is none.
    """
    return tuple(dict.fromkeys(f for q in subjects for f in q.registration_flags))


def ranked(subjects: Sequence[SubjectQC]) -> list[SubjectQC]:
    """Subjects worst first, as every report lists them.

    Parameters
    ----------
    subjects : sequence of SubjectQC
        Subjects under one registration (:func:`assess_subjects`), all or some of them.

    Returns
    -------
    list of SubjectQC
        By :attr:`SubjectQC.concern`, largest first, ties in manifest order; those without
        a concern (nothing measured) after them, and the registration's reference last.
    """
    return sorted(
        subjects,
        key=lambda q: (q.reference, q.concern is None, -(q.concern or 0.0), q.index),
    )


_DEFORMATION_FLAGS = (
    ("sdlogj", "SDlogJ"),
    ("nonlinear_rms_mm", "non-linear displacement (mm RMS)"),
    ("inverse_consistency_mm", "inverse-consistency error (mm)"),
)


@dataclass(frozen=True)
class _Cohort:
    """One registration's cohort statistics, every array of length N (manifest order; NaN
    for a subject not in the scores)."""

    scored: frozenset[int]
    coverage: np.ndarray
    deformation: dict[str, np.ndarray]
    score: np.ndarray
    z: np.ndarray
    nearest: dict[int, tuple[int, float]]  # subject -> (nearest other, distance / median)
    deformation_z: dict[str, np.ndarray]
    medians: dict[str, float]
    overlap: np.ndarray | None
    overlap_z: np.ndarray
    brain_mask_dice: np.ndarray | None = None


def _cohort(
    *, n_all, scored, gram, deformation, coverage, overlap_sums, judged, brain_mask_dice=None
) -> _Cohort:
    """The statistics every subject is judged against (see :func:`assess_subjects`): the
    medians and MADs over the subjects `judged` (boolean, length N) alone."""
    rows = judged[scored]  # the judged among the scored, by row of `gram`
    cov = np.asarray(coverage, np.float64)
    defo = {
        k: np.array([math.nan if v is None else float(v) for v in vals], np.float64)
        for k, vals in deformation.items()
    }
    score = np.full(n_all, np.nan)
    z = np.full(n_all, np.nan)
    if len(scored) >= 4:
        dist = leave_one_out_distances(gram)
        # a duplicate is at distance 0 from the others' span: log of a tiny floor, not -inf
        tiny = max(float(np.max(dist)), 1.0) * 1e-12
        score[scored] = dist
        least = _LEAST_SPREAD_OF_SCORE * float(np.median(dist[rows]))
        z[scored] = robust_z(dist, log=True, floor=tiny, least_spread=least, among=rows)
    nearest = {}
    if len(scored) >= 3:
        pairs = pair_distances(gram)
        off = pairs[~np.eye(len(scored), dtype=bool)]
        median_pair = float(np.median(off))
        np.fill_diagonal(pairs, np.inf)
        for row, i in enumerate(scored):
            j = int(np.argmin(pairs[row]))
            ratio = pairs[row, j] / median_pair if median_pair > 0 else math.nan
            nearest[i] = (scored[j], ratio)
    names = [name for name, _ in _DEFORMATION_FLAGS]
    names += ["frame_deviation_mm"] if "frame_deviation_mm" in defo else []
    deformation_z = {
        name: robust_z(
            defo[name],
            log=True,
            floor=_LOG_FLOORS[name],
            least_spread=_LEAST_SPREAD[name],
            among=judged,
        )
        for name in names
    }
    medians = {name: _median(defo[name][judged]) for name in defo}
    medians["coverage"] = float(np.median(cov[judged]))
    overlap = None
    overlap_z = np.full(n_all, np.nan)
    if overlap_sums is not None:
        overlap = np.full(n_all, np.nan)
        values = subject_overlaps(*overlap_sums)
        overlap[scored] = values
        overlap_z[scored] = robust_z(values, least_spread=_LEAST_SPREAD["overlap"], among=rows)
        medians["overlap"] = _median(overlap[judged])
    dice = None
    if brain_mask_dice is not None:
        dice = np.array([math.nan if v is None else float(v) for v in brain_mask_dice])
    return _Cohort(
        frozenset(scored),
        cov,
        defo,
        score,
        z,
        nearest,
        deformation_z,
        medians,
        overlap,
        overlap_z,
        dice,
    )


def _flags_and_causes(
    i: int, c: _Cohort, images, th: SubjectThresholds, shared: Mapping[str, str] | None = None
) -> tuple[list[tuple[str, str]], list[str], list[str]]:
    """Subject `i`'s flags as (kind, words), the causes that would explain them, in order,
    and the registration flags it shares: a flag of a kind in `shared` (kind -> the
    registration flag's words) is the registration's, and explains nothing of the subject."""
    shared = shared or {}
    flags: list[tuple[str, str]] = []
    causes: list[str] = []
    theirs: list[str] = []

    def add(kind: str, words: str) -> bool:
        """Record a flag; whether it is the subject's own."""
        if kind in shared:
            if shared[kind] not in theirs:
                theirs.append(shared[kind])
            return False
        flags.append((kind, words))
        return True

    cov, median_cov = c.coverage[i], c.medians["coverage"]
    if i not in c.scored and cov < th.off_grid_coverage * median_cov:
        if add(
            "off_grid",
            f"covers {cov:.0%} of the common grid (cohort median {median_cov:.0%}): "
            "left out of the scores",
        ):
            causes.append(
                "its transform maps the image (almost) off the common grid: wrong transform, "
                "wrong reference or a unit/axis mix-up"
            )
    elif i not in c.scored:  # the scores of every registration share one region
        add(
            "left_out",
            f"left out of the scores: another registration maps it off the common grid "
            f"(it covers {cov:.0%} here)",
        )
    if i in c.nearest and c.nearest[i][1] < th.duplicate_distance:
        j, ratio = c.nearest[i]
        if add(
            "duplicate",
            f"its resampled image is identical to subject {j}'s"
            if ratio < 1e-6  # "0x the median distance" says it less plainly
            else f"its resampled image is {ratio:.2g}x the median pairwise distance from "
            f"subject {j}'s",
        ):
            causes.append(f"duplicated image: the same as subject {j}'s ({images[j]})")
    defo = c.deformation
    det = defo["linear_det"][i]
    if det < 0 and c.medians["linear_det"] > 0:
        if add("mirrored", f"the linear part of its transform has determinant {_fmt(det)} < 0"):
            causes.append("mirrored: its transform flips an axis (left-right swapped?)")
    if c.z[i] > th.outlier_z:
        add(
            "model_distance",
            f"far from the model of the others: distance {_fmt(c.score[i])} ({_z_words(c.z[i])})",
        )
    folded = defo["folded_fraction"][i]
    folds = folded > th.folded and add("folding", f"{folded:.1%} of its voxels fold (det J <= 0)")
    # folds between grid points, which central differences miss (issue 42): NaN never flags
    stencils = (
        defo["nondiffeomorphic_fraction"][i] if "nondiffeomorphic_fraction" in defo else math.nan
    )
    if not folds and stencils > th.folded:
        folds = add(
            "folding",
            f"{stencils:.1%} of its voxels fold by some finite-difference stencil (det J <= 0 "
            f"on a one-sided or tetrahedral stencil; central differences: {folded:.2%})",
        )
    rough = False
    for name, words in _DEFORMATION_FLAGS:
        median, zi = c.medians[name], c.deformation_z[name][i]
        least = max(median, _LOG_FLOORS[name])  # below the floor, no variation at all
        if zi > th.deformation_z and defo[name][i] > th.deformation_ratio * least:
            rough |= add(
                name,
                f"{words} {_fmt(defo[name][i])} against the cohort's median "
                f"{_fmt(median)} ({_z_words(zi)})",
            )
    nonlinear, median_nonlinear = defo["nonlinear_rms_mm"][i], c.medians["nonlinear_rms_mm"]
    if median_nonlinear > _AFFINE_COHORT_MM and nonlinear < th.affine_only_ratio * (
        median_nonlinear
    ):
        if add(
            "affine_only",
            f"almost no non-linear displacement: {_fmt(nonlinear, 2)} mm RMS beyond "
            f"the best affine map (cohort median {_fmt(median_nonlinear)} mm)",
        ):
            causes.append("stopped early or affine only: no non-linear deformation")
    if (rough or folds) and nonlinear > th.scaled_ratio * median_nonlinear:
        causes.append(
            f"displacements scaled: {nonlinear / median_nonlinear:.1f}x the cohort's "
            "median non-linear displacement (a unit or scale mix-up?)"
        )
    if c.overlap_z[i] < -th.overlap_z and (1.0 - c.overlap[i]) > th.overlap_ratio * (
        1.0 - c.medians["overlap"]
    ):
        add(
            "overlap",
            f"label overlap with the others {c.overlap[i]:.3f} (cohort median "
            f"{c.medians['overlap']:.3f}, {_z_words(c.overlap_z[i])})",
        )
    dice = math.nan if c.brain_mask_dice is None else c.brain_mask_dice[i]
    if dice < BRAIN_MASK_DICE_MIN:  # NaN (no mask) compares False
        add(
            "brain_mask",
            f"its brain mask has Dice {dice:.3f} with the common mask in the common frame "
            f"(below {BRAIN_MASK_DICE_MIN})",
        )
    return flags, causes, theirs


def _shared_kinds(
    first: Mapping[int, Sequence[tuple[str, str]]], c: _Cohort, th: SubjectThresholds
) -> dict[str, str]:
    """The kinds of flag that are the registration's, with its words: those carried by at
    least half of the subjects judged (the keys of `first`, each with its flags), and by at
    least two (with two subjects judged, one is no majority of anything)."""
    n = len(first)
    carriers: dict[str, list[int]] = {}
    for i, flags in first.items():
        for kind in dict.fromkeys(k for k, _ in flags):
            carriers.setdefault(kind, []).append(i)
    out = {}
    for kind, who in carriers.items():
        if len(who) < 2 or 2 * len(who) < n:
            continue
        if kind == "folding":
            folded = c.deformation["folded_fraction"][who]
            low, high = f"{folded.min():.1%}", f"{folded.max():.1%}"
            out[kind] = (
                f"{len(who)} of the {n} subjects fold more than {100 * th.folded:g}% of their "
                f"voxels ({low if low == high else f'{low} to {high}'}; det J <= 0)"
            )
        else:
            # a kind without its words yet (a flag added later) is still said once
            words = FLAG_KINDS.get(kind, f"carry the flag {kind!r}")
            out[kind] = f"{len(who)} of the {n} subjects {words}"
    return out


def concern_scores(z_scores: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """The subjects' concern: the weighted mean of their signed z-scores.

    Parameters
    ----------
    z_scores : mapping of str to array_like of shape (n,)
        Per key of :data:`CONCERN_TERMS` (``overlap_z``, ``z``, ``sdlogj_z``,
        ``inverse_consistency_z``), the subjects' robust z-scores as :func:`assess_subjects`
        computes them (unsigned); NaN, or a key left out, where a term was not measured.

    Returns
    -------
    concern : ndarray of shape (n,)
        Per subject, ``sum_k w_k t_k / sum_k w_k`` over the terms ``k`` measured, with
        ``t_k`` the z-score times the term's sign, taken as ``max(t_k, 0)`` for a
        `worse_only` term, and ``w_k`` its weight; NaN where no term was measured.
    largest : ndarray of int, shape (n,)
        Per subject, the index into :data:`CONCERN_TERMS` of the term contributing most
        (the largest ``w_k t_k``; the first such term in a tie); -1 where no term was
        measured.
    """
    columns = [np.atleast_1d(np.asarray(v, np.float64)) for v in z_scores.values()]
    n = max((len(c) for c in columns), default=0)
    weighted = np.full((len(CONCERN_TERMS), n), -np.inf)
    weights = np.zeros((len(CONCERN_TERMS), n))
    for k, term in enumerate(CONCERN_TERMS):
        values = z_scores.get(term.key)
        if values is None:
            continue
        signed = term.sign * np.broadcast_to(np.asarray(values, np.float64), (n,))
        if term.worse_only:
            signed = np.maximum(signed, 0.0)  # NaN stays NaN
        measured = ~np.isnan(signed)
        weighted[k, measured] = term.weight * signed[measured]
        weights[k, measured] = term.weight
    total = weights.sum(axis=0)
    found = total > 0
    concern = np.full(n, np.nan)
    concern[found] = np.where(weights > 0, weighted, 0.0).sum(axis=0)[found] / total[found]
    largest = np.where(found, np.argmax(weighted, axis=0), -1)
    return concern, largest


def _concern(values: Mapping[str, float | None]) -> tuple[float | None, str | None]:
    """One subject's concern (:func:`concern_scores`) and the term contributing most, in
    words; (None, None) when none was measured."""
    z_scores = {
        t.key: math.nan if values.get(t.key) is None else float(values[t.key])
        for t in CONCERN_TERMS
    }
    concern, largest = concern_scores(z_scores)
    if largest[0] < 0:
        return None, None
    return float(concern[0]), CONCERN_TERMS[int(largest[0])].words


def _subject_qc(
    i: int,
    c: _Cohort,
    images,
    flags: Sequence[tuple[str, str]],
    causes: Sequence[str],
    better_fit: float | None,
    *,
    reference: bool = False,
    registration: Sequence[str] = (),
) -> SubjectQC:
    def number(v: float) -> float | None:
        return None if math.isnan(v) else float(v)

    deformation = {
        **{k: number(v[i]) for k, v in c.deformation.items()},
        "sdlogj_z": float(c.deformation_z["sdlogj"][i]),
        "nonlinear_rms_z": float(c.deformation_z["nonlinear_rms_mm"][i]),
        "inverse_consistency_z": float(c.deformation_z["inverse_consistency_mm"][i]),
        **(
            {"frame_deviation_z": number(c.deformation_z["frame_deviation_mm"][i])}
            if "frame_deviation_mm" in c.deformation_z
            else {}
        ),
    }
    z, overlap_z = number(c.z[i]), number(c.overlap_z[i])
    concern, concern_from = (
        (None, None) if reference else _concern({**deformation, "z": z, "overlap_z": overlap_z})
    )
    return SubjectQC(
        index=i,
        image=str(images[i]),
        score=number(c.score[i]),
        z=z,
        deformation=deformation,
        overlap=None if c.overlap is None else number(c.overlap[i]),
        overlap_z=overlap_z,
        coverage=float(c.coverage[i]),
        brain_mask_dice=(
            None
            if c.brain_mask_dice is None or math.isnan(c.brain_mask_dice[i])
            else float(c.brain_mask_dice[i])
        ),
        in_scores=i in c.scored,
        flags=tuple(words for _, words in flags),
        diagnosis=causes[0] if causes and flags else None,
        better_fit=better_fit,
        reference=reference,
        registration_flags=tuple(registration),
        concern=concern,
        concern_from=concern_from,
    )


@dataclass(frozen=True)
class Alternative:
    """One subject's image resampled through a changed transform (:func:`transform_mixups`).

    Attributes
    ----------
    image : int
        Whose image (manifest index).
    transform : int
        Through whose transform under the same registration (manifest index).
    inverse : bool
        Through the inverse of that transform.
    """

    image: int
    transform: int
    inverse: bool = False


#: At most this many flagged subjects (the farthest from the model first) are resampled
#: through changed transforms: k subjects cost k inversions and k (k - 1) resamplings.
MAX_MIXUP_SUBJECTS = 8


class _AffineSpans:
    """Distances to the affine span of n images but a few left out, from their Gram matrix.

    One eigendecomposition of the centred Gram matrix serves every query; refitting the
    model of the remaining images for each query cost one per query (O(n^3) each, minutes
    for 64 queries at n = 1,000).

    Parameters
    ----------
    gram : ndarray of shape (n, n)
        Gram matrix of the images (squared intensity units); centred here on their mean
        (affine spans do not move with it).

    Notes
    -----
    With ``Gc = V L V^T`` the centred Gram matrix (the eigenvalues above ``n 1e-12`` times
    the largest kept), ``Gc^+`` its pseudo-inverse and ``c`` a vector's centred inner
    products with the images, the vector's squared distance to the span of all n images is
    ``|a|^2 - c^T Gc^+ c`` (the part outside it), and leaving out the images R adds
    ``b^T (Gc^+_RR)^-1 b`` with ``b = (Gc^+ c)_R + 1/n``: its component along the
    normals, within the span of all, of the span of the others (``(Gc^+)_k.`` is image k's
    dual vector, orthogonal to every other image's offset). For c = image k's own inner
    products and R = {k} this is ``1 / Gc^+_kk``, the leave-one-out distance. An affine
    dependency among the images (a duplicate) that involves left-out images keeps their
    directions in the span of the others: only the combinations of R's normals that no
    dependency involves count.
    """

    def __init__(self, gram: np.ndarray):
        g = np.asarray(gram, np.float64)
        self.n = n = g.shape[0]
        self._row_means = g.mean(axis=0)
        self._mean = float(self._row_means.mean())
        centred = g - self._row_means[:, None] - self._row_means[None, :] + self._mean
        self._centred = centred
        values, vectors = np.linalg.eigh(centred)
        kept = values > values[-1] * n * 1e-12
        self._pinv = (vectors[:, kept] / values[kept]) @ vectors[:, kept].T
        # the affine dependencies: the dropped directions but the constant one (the centring)
        dropped = vectors[:, ~kept] - vectors[:, ~kept].mean(axis=0)
        basis, weights, _ = np.linalg.svd(dropped, full_matrices=False)
        self._dependencies = basis[:, weights > 0.5]

    def distance(self, cross: np.ndarray, squared: float, left_out: Sequence[int]) -> float:
        """The distance (intensity units) of one more image to the affine span of the
        images but rows `left_out`, from its inner products with them `cross` (n,) and with
        itself `squared` (in the Gram matrix's centring)."""
        c = np.asarray(cross, np.float64)
        c_mean = float(c.mean())
        c = c - c_mean - self._row_means + self._mean
        own = squared - 2 * c_mean + self._mean
        dual = self._pinv @ c
        outside = max(own - float(c @ dual), 0.0)  # round-off below 0: in the span
        return self._distance(dual, outside, left_out)

    def member_distance(self, k: int, left_out: Sequence[int]) -> float:
        """The distance (intensity units) of image (row) `k` to the affine span of the
        images but rows `left_out` (which may hold k)."""
        # it lies in the span of all images: nothing outside it (|a|^2 - c^T Gc^+ c would
        # leave round-off whose square root is 1e-8 |a|)
        return self._distance(self._pinv @ self._centred[:, k], 0.0, left_out)

    def _distance(self, dual: np.ndarray, outside: float, left_out: Sequence[int]) -> float:
        rows = sorted(set(left_out))
        # combinations of the left-out images' normals that no affine dependency involves
        normals = np.eye(len(rows))
        if self._dependencies.shape[1]:
            u, s, _ = np.linalg.svd(self._dependencies[rows], full_matrices=True)
            normals = u[:, int(np.sum(s > 1e-6)) :]
        if not normals.shape[1]:
            return math.sqrt(outside)
        along = normals.T @ (dual[rows] + 1.0 / self.n)
        metric = normals.T @ self._pinv[np.ix_(rows, rows)] @ normals
        return math.sqrt(outside + max(float(along @ np.linalg.solve(metric, along)), 0.0))


def transform_mixups(
    subjects: Sequence[SubjectQC],
    *,
    images: Sequence[str],
    scored: Sequence[int],
    gram: np.ndarray,
    products: Callable[[Sequence[Alternative]], tuple[np.ndarray, np.ndarray]],
) -> dict[int, tuple[float, str]]:
    """How much better flagged subjects fit with their transform inverted or exchanged.

    For each flagged subject i in the scores (at most :data:`MAX_MIXUP_SUBJECTS`, largest
    z first), its image is resampled through the inverse of its transform, and every other
    such subject j's image through i's transform. Each is measured as the leave-one-out
    score is: its distance to the affine span of the other subjects' resampled images, the
    others being all scored subjects but i (and j), and compared with i's own resampled
    image's distance to the same model (the same units). :func:`assess_subjects` names the
    cause when the best of them is ``thresholds.better_fit_ratio`` times closer or more.

    Parameters
    ----------
    subjects : sequence of SubjectQC
        Every subject under one registration, in manifest order (:func:`assess_subjects`).
    images : sequence of str
        Every subject's image, as the manifest names it.
    scored, gram
        As :func:`assess_subjects`: the subjects in the scores and the Gram matrix (n, n) of
        their centred resampled images.
    products : callable
        Given alternatives, their resampled images' inner products (centred as `gram`,
        inside the same region) with every scored subject's, shape (n_alternatives, n), and
        with themselves, shape (n_alternatives,).

    Returns
    -------
    dict of int to (float, str)
        Per subject checked: own distance / the best alternative's distance, and the cause
        that alternative points to, in words (``mixups=`` of :func:`assess_subjects`); empty
        when no subject is flagged, or fewer than 5 subjects are in the scores.
    """
    row = {int(i): r for r, i in enumerate(scored)}
    if len(row) < 5:
        return {}
    gram = np.asarray(gram, np.float64)
    flagged = [q for q in subjects if q.flags and q.index in row and q.z is not None]
    flagged.sort(key=lambda q: -q.z)
    chosen = [q.index for q in flagged[:MAX_MIXUP_SUBJECTS]]
    alternatives = [Alternative(i, i, inverse=True) for i in chosen]
    alternatives += [Alternative(j, i) for i in chosen for j in chosen if j != i]
    if not alternatives:
        return {}
    cross, squared = products(alternatives)
    spans = _AffineSpans(gram)
    best: dict[int, tuple[float, Alternative]] = {}
    for c, alt in enumerate(alternatives):
        i = alt.transform
        left_out = [row[alt.image], row[i]]
        own = spans.member_distance(row[i], left_out)
        changed = spans.distance(cross[c], float(squared[c]), left_out)
        ratio = own / changed if changed > 0 else math.inf
        if i not in best or ratio > best[i][0]:
            best[i] = (ratio, alt)
    out = {}
    for i, (ratio, alt) in best.items():
        if alt.inverse:
            out[i] = (
                ratio,
                (
                    f"inverted transform: its inverse brings the image {ratio:.1f}x closer to the "
                    "model of the others (a transform of the wrong direction: image to reference "
                    "points?)"
                ),
            )
        else:
            j = alt.image
            out[i] = (
                ratio,
                (
                    f"its transform looks like another subject's: subject {j}'s image "
                    f"({images[j]}) fits it {ratio:.1f}x better than its own (transforms swapped "
                    "or mixed up?)"
                ),
            )
    return out


def across_registrations(
    assessed: Mapping[str, Sequence[SubjectQC]], *, thresholds: SubjectThresholds
) -> dict[str, tuple[SubjectQC, ...]]:
    """Name the subjects whose image stands out under every registration.

    A subject far from the model of the others (``z > thresholds.outlier_z``) under one
    registration may be badly registered; under every registration of two or more, the
    affine one included, it is the image itself that differs from the cohort (anatomy,
    contrast, an artefact, a header), not one registration of it. Such a subject's diagnosis
    says so wherever no other cause was named; its flags are unchanged. A registration whose
    reference the subject is does not judge it: "every registration" is every other one
    (still two or more), and its entry as the reference is left as it is.

    Parameters
    ----------
    assessed : mapping of str to sequence of SubjectQC
        Per registration, every subject in manifest order (:func:`assess_subjects`).
    thresholds : SubjectThresholds, keyword-only

    Returns
    -------
    dict of str to tuple of SubjectQC
        The same, with those diagnoses.
    """
    names = list(assessed)
    out = {name: tuple(assessed[name]) for name in names}
    if len(names) < 2:
        return out
    n = len(out[names[0]])
    judging = [[name for name in names if not out[name][i].reference] for i in range(n)]
    everywhere = [
        len(judging[i]) >= 2
        and all(
            out[name][i].z is not None and out[name][i].z > thresholds.outlier_z
            for name in judging[i]
        )
        for i in range(n)
    ]

    def words(k: int) -> str:
        return (
            f"far from the model under every registration ({k} of {k}): the image itself "
            "stands out from the cohort (anatomy, contrast, an artefact or its header), not "
            "one registration of it"
        )

    return {
        name: tuple(
            replace(q, diagnosis=words(len(judging[i])))
            if everywhere[i] and q.diagnosis is None and not q.reference
            else q
            for i, q in enumerate(subjects)
        )
        for name, subjects in out.items()
    }
