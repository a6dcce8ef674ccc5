"""Which subjects' registrations failed: per-subject quality control of a registered cohort.

The verdict (:func:`itk_nrreval.evaluation.verdict`) says which registration of a group is
best; this module asks, per registration, which of its subjects stand out from the rest of
the cohort, and why. The measures are computed from numbers the evaluation already has --
nothing is resampled again for them:

* **model distance** (``score``, the images' intensity units): the subject's leave-one-out
  reconstruction error, the Euclidean distance of its resampled image (inside the evaluated
  region) to the texture model of the other N - 1 subjects with all their modes, i.e. to the
  affine span of the others (:func:`itk_nrreval.measures.specificity.loo_generalization`, from the
  N x N Gram matrix alone);
* **bias-corrected distance** (``corrected_distance``): the distance of its image, divided
  by its own 10 mm local mean (which takes away a scanner gain and a smooth bias field), to
  the mean of the others' so divided
  (:func:`~itk_nrreval.measures._subject_measures.bias_corrected`);
* **deformation**: its transform's folded fraction, SDlogJ, det J range and inverse
  consistency (:class:`itk_nrreval.io.plausibility.Plausibility`), and the affine map closest
  to it (:class:`itk_nrreval.io.plausibility.AffineFit`: the determinant of the linear part,
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
:class:`itk_nrreval.io.plausibility.SubjectThresholds` says when a subject is flagged, and a
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
bias-corrected distance z, the log SDlogJ z and the log inverse-consistency z with weight 1
each; the two deformation terms count only above zero
(a field smoother than its cohort's is no sign that the subject was registered well: an
affine-only transform has the least SDlogJ of all). With labels the overlap is half of it
and the three image-only terms share the other half; without labels it is their mean; a
term not measured (NaN) is left out and the weights of the others renormalised. It was
chosen on the tuning split of the genuine registrations alone
(``benchmarks/bench_subject_qc_genuine.py``, ``docs/subject-qc.md``), where it tracked
the subjects' true errors better than the largest of the z-scores it replaced (Spearman
mean over the deformable registrations 0.80 against 0.68 with labels, 0.63 against 0.53
without): a mean is not decided by one noisy deformation term. Its image term was the
model distance until the bias-corrected distance replaced it (chosen on the same tuning split:
0.84 with labels, 0.83 without), because gain and bias dominate raw intensities' distances.
Every subject is listed worst first by it (:func:`ranked`), so the few most unlike their
cohort can be looked at even when none crosses a threshold. Above
``SubjectThresholds.concern`` (1.75 by default; ``concern_without_labels``, 1.25, without
labels) it also flags the subject ("among the worst of its cohort"; set on splits of the
genuine registrations, and made the default by a split declared before it ran:
``docs/subject-qc.md``). The flags on absolute limits (folding, mirroring, a duplicate, off
the grid) are not in it, so a subject flagged for one of them may rank below unflagged
subjects (its flags say why it is listed). :attr:`~SubjectQC.concern_from` names the term
contributing most to it. The reference has no concern and is listed last.

Two causes need images resampled through changed transforms, and are looked for among the
flagged subjects only (:func:`transform_mixups`, at most :data:`MAX_MIXUP_SUBJECTS` of them,
on the driver after the per-image work): an **inverted transform** (the subject's image
through the inverse of its transform is much closer to the model of the others) and
**another subject's transform** (another flagged subject's image fits it much better than
its own: two subjects' transforms swapped or mixed up).

Where each part lives: this module holds the result (:class:`SubjectQC`) and what the
evaluation calls (:func:`assess_subjects`, :func:`transform_mixups`,
:func:`across_registrations`), and the order the reports list subjects in (:func:`ranked`,
:func:`registration_flags`); the numbers -- Gram-matrix distances, overlaps, robust
z-scores, the concern -- are in :mod:`itk_nrreval.measures._subject_measures`; the cohort
statistics, the flags, their thresholds and causes in :mod:`itk_nrreval.measures._subject_flags`;
finding the reference in :mod:`itk_nrreval.measures._reference_subject`; the alternatives resampled
for a mix-up in :mod:`itk_nrreval.measures._transform_mixups`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from .._output import json_number
from ._reference_subject import IDENTITY_MM, reference_subject
from ._subject_flags import (
    FLAG_KINDS,
    Cohort,
    cohort_statistics,
    concern_of,
    flags_and_causes,
    shared_kinds,
)
from ._subject_measures import (
    CONCERN_TERMS,
    MAD_TO_SD,
    ConcernTerm,
    concern_scores,
    leave_one_out_distances,
    pair_distances,
    robust_z,
    subject_overlaps,
)
from ._transform_mixups import MAX_MIXUP_SUBJECTS, Alternative, better_fits

if TYPE_CHECKING:  # pragma: no cover
    from ..io.plausibility import SubjectThresholds

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
        with the common mask (:func:`itk_nrreval.io._brain_masks.subject_mask_dice`); None
        where the inputs have no brain masks.
    corrected_distance : float or None
        Its bias-corrected distance: the distance of its bias-corrected image
        (:func:`~itk_nrreval.measures._subject_measures.bias_corrected`: divided by its 10 mm local
        mean, which takes away gain and smooth bias) to the mean of the others' (intensity
        ratio units); None where not measured.
    corrected_z : float or None
        The robust z-score of its log `corrected_distance` over the cohort: the image term of its
        `concern`.
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
        the log bias-corrected distance, log SDlogJ and log inverse-consistency z with weight 1, the
        last two counted above zero only; unitless, in robust standard deviations): what the
        subjects are ranked by (:func:`ranked`). None for the reference, or when none of
        them was measured.
    concern_from : str or None
        Which term contributes most to it (the largest weighted term), in words (e.g.
        ``"bias-corrected distance"``).
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
    corrected_distance: float | None = None
    corrected_z: float | None = None
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
            "corrected_distance": (
                None
                if self.corrected_distance is None
                else {
                    "value": json_number(self.corrected_distance),
                    "z": json_number(self.corrected_z),
                }
            ),
            "in_scores": self.in_scores,
            "flags": list(self.flags),
            "registration_flags": list(self.registration_flags),
            "diagnosis": self.diagnosis,
            "better_fit": json_number(self.better_fit),
            "reference": self.reference,
            "concern": json_number(self.concern),
            "concern_from": self.concern_from,
        }


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
    corrected_squares: Sequence[float] | None = None,
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
        registration's frame and the group's (:class:`~itk_nrreval.io.frame.FrameMapping`;
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
        (:func:`itk_nrreval.io._brain_masks.subject_mask_dice`; NaN: not measured); None where
        the inputs have no brain masks.
    corrected_squares : sequence of float, length n, optional
        Per scored subject, what :func:`~._subject_measures.others_mean_distances` takes:
        the concern's image term. None: not measured (the concern rests on the others).
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
    * its transform's linear part mirrors space (det < 0), the cohort's median's does not;
    * its log model distance has z > ``th.outlier_z``;
    * its bias-corrected distance is above ``th.corrected_ratio`` times the cohort's median;
    * it folds more than ``th.folded`` of its voxels;
    * its log SDlogJ, log non-linear displacement or log inverse consistency has z >
      ``th.deformation_z`` and is above ``th.deformation_ratio`` times the cohort's median
      (or the measure's floor, when the median is below it: 0.001 for SDlogJ and mm of
      displacement, 0.1 mm of inverse consistency);
    * its non-linear displacement is below ``th.affine_only_ratio`` times the cohort's
      median (when that median is above 0.001 mm);
    * its overlap has z < ``-th.overlap_z`` and its mismatch ``1 - overlap`` is above
      ``th.overlap_ratio`` times the cohort's median mismatch;
    * its brain mask's Dice with the common mask is below ``BRAIN_MASK_DICE_MIN`` (0.8);
    * its concern (:func:`concern_scores`) is above ``th.concern`` where its overlap was
      measured, ``th.concern_without_labels`` where not (None: never).

    Every z-score's scale has a floor in its measure's units (:func:`robust_z`'s
    `least_spread`: :mod:`itk_nrreval.measures._subject_flags`), so none is infinite.

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
    cohort = cohort_statistics(
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
        corrected_squares=corrected_squares,
    )
    return _judged_against(cohort, images, judged, mixups, thresholds)


def _judged_against(
    cohort: Cohort,
    images: Sequence[str],
    judged: np.ndarray,
    mixups: Mapping[int, tuple[float, str]] | None,
    thresholds: SubjectThresholds,
) -> tuple[SubjectQC, ...]:
    """Every subject's quality control against the `cohort` statistics (:func:`assess_subjects`):
    the `judged` subjects flagged, the one not judged (the reference) reported as such."""
    n_all = len(images)
    who = [i for i in range(n_all) if judged[i]]
    # a first pass finds the kinds most subjects share; the second says them once
    first = {i: flags_and_causes(i, cohort, images, thresholds)[0] for i in who}
    shared = shared_kinds(first, cohort, thresholds)
    out = []
    for i in range(n_all):
        if not judged[i]:
            out.append(_subject_qc(i, cohort, images, [], [], None, reference=True))
            continue
        flags, causes, theirs = flags_and_causes(i, cohort, images, thresholds, shared)
        # after the causes read off the transform itself: the inverse of an affine-only or a
        # scaled transform can fit somewhat better too (up to 1.5x on generated cohorts)
        better_fit = mixups[i][0] if mixups and i in mixups else None
        if better_fit is not None and better_fit >= thresholds.better_fit_ratio:
            causes.append(mixups[i][1])
        out.append(_subject_qc(i, cohort, images, flags, causes, better_fit, registration=theirs))
    return tuple(out)


def _subject_qc(
    i: int,
    c: Cohort,
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
    corrected_z = None if c.corrected_z is None else number(c.corrected_z[i])
    concern, concern_from = (None, None) if reference else concern_of(i, c)
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
        corrected_distance=None
        if c.corrected_distance is None
        else number(c.corrected_distance[i]),
        corrected_z=corrected_z,
        in_scores=i in c.scored,
        flags=tuple(words for _, words in flags),
        diagnosis=causes[0] if causes and flags else None,
        better_fit=better_fit,
        reference=reference,
        registration_flags=tuple(registration),
        concern=concern,
        concern_from=concern_from,
    )


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
    return better_fits(chosen, row=row, gram=gram, products=products, images=images)


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
