"""How subject quality control judges a subject against its cohort
(:mod:`itk_nrreval.measures.subject_qc`).

The cohort's statistics (:class:`Cohort`, :func:`cohort_statistics`): the subjects' measures
with their medians and robust z-scores, each z-score's scale floored in its measure's units;
the flags a subject earns against them and their thresholds
(:class:`~itk_nrreval.io.plausibility.SubjectThresholds`), with the common causes of failure
that would explain them (:func:`flags_and_causes`); and which kinds of flag are the
registration's rather than its subjects' (:data:`FLAG_KINDS`, :func:`shared_kinds`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..io._brain_masks import BRAIN_MASK_DICE_MIN
from ._subject_measures import (
    leave_one_out_distances,
    others_mean_distances,
    pair_distances,
    robust_z,
    subject_concern,
    subject_overlaps,
)

if TYPE_CHECKING:  # pragma: no cover
    from ..io.plausibility import SubjectThresholds

__all__ = [
    "FLAG_KINDS",
    "Cohort",
    "cohort_statistics",
    "concern_of",
    "flags_and_causes",
    "shared_kinds",
]

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
#: registration flag (:func:`~itk_nrreval.measures.subject_qc.registration_flags`: "k of the n
#: subjects <words>").
FLAG_KINDS = {
    "off_grid": "cover too little of the common grid, and are left out of the scores",
    "left_out": "are left out of the scores: another registration maps them off the common grid",
    "duplicate": "have a resampled image (almost) identical to another subject's",
    "mirrored": "have a transform whose linear part mirrors space",
    "model_distance": "are far from the model of the others",
    "corrected_distance": "are far from the others once gain and bias are taken away",
    "folding": "fold",  # said with the threshold and the range instead (shared_kinds)
    "sdlogj": "have an SDlogJ far above the cohort's",
    "nonlinear_rms_mm": "have a non-linear displacement far above the cohort's",
    "inverse_consistency_mm": "have an inverse-consistency error far above the cohort's",
    "affine_only": "have almost no non-linear displacement",
    "overlap": "have a label overlap with the others far below the cohort's",
    "brain_mask": "have a brain mask that matches the common mask poorly in the common frame",
    "concern": "have a concern above the threshold",
}


_DEFORMATION_FLAGS = (
    ("sdlogj", "SDlogJ"),
    ("nonlinear_rms_mm", "non-linear displacement (mm RMS)"),
    ("inverse_consistency_mm", "inverse-consistency error (mm)"),
)


@dataclass(frozen=True)
class Cohort:
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
    corrected_distance: np.ndarray | None = None
    corrected_z: np.ndarray | None = None


def cohort_statistics(
    *, n_all, scored, gram, deformation, coverage, overlap_sums, judged, brain_mask_dice=None,
    corrected_squares=None,
) -> Cohort:  # fmt: skip
    """The statistics every subject is judged against (see
    :func:`~itk_nrreval.measures.subject_qc.assess_subjects`): the medians and MADs over the
    subjects
    `judged` (boolean, length N) alone."""
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
        score[scored] = dist
        z[scored] = _log_distance_z(dist, rows)
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
    corrected_distance = corrected_z = None
    if corrected_squares is not None:
        corrected_distance, corrected_z = _corrected_distances(
            corrected_squares, n_all, scored, rows
        )
        medians["corrected_distance"] = _median(corrected_distance[judged])
    dice = None
    if brain_mask_dice is not None:
        dice = np.array([math.nan if v is None else float(v) for v in brain_mask_dice])
    return Cohort(
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
        corrected_distance,
        corrected_z,
    )


def _median(values) -> float:
    """The median of the finite values; NaN (without a warning) when there is none."""
    x = np.asarray(values, np.float64)
    x = x[np.isfinite(x)]
    return float(np.median(x)) if x.size else math.nan


def flags_and_causes(
    i: int, c: Cohort, images, th: SubjectThresholds, shared: Mapping[str, str] | None = None
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
    corrected = _corrected_flag(i, c, th)
    if corrected:
        add("corrected_distance", corrected)
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
    if concern := _concern_flag(i, c, th):  # last: it sums up the z-scores judged above
        add("concern", concern)
    return flags, causes, theirs


def concern_of(i: int, c: Cohort) -> tuple[float | None, str | None]:
    """Subject `i`'s concern (:func:`~._subject_measures.subject_concern`, from its robust
    z-scores against the cohort `c`) and the term contributing most; (None, None) where no
    term was measured."""

    def z(values: np.ndarray | None) -> float | None:
        return None if values is None or math.isnan(values[i]) else float(values[i])

    return subject_concern(
        {
            "overlap_z": z(c.overlap_z),
            "corrected_z": z(c.corrected_z),
            "sdlogj_z": z(c.deformation_z["sdlogj"]),
            "inverse_consistency_z": z(c.deformation_z["inverse_consistency_mm"]),
        }
    )


def _concern_flag(i: int, c: Cohort, th: SubjectThresholds) -> str | None:
    """Subject `i`'s flag on its concern, in words, or None: above `th.concern` where its
    label overlap was measured, `th.concern_without_labels` where not (None: off). Not
    measured (no z-score at all) never flags."""
    concern, concern_from = concern_of(i, c)
    labelled = c.overlap_z is not None and not math.isnan(c.overlap_z[i])
    threshold = th.concern if labelled else th.concern_without_labels
    if threshold is None or concern is None or not concern > threshold:
        return None
    return (
        f"among the worst of its cohort: concern {concern:+.2f} (above {threshold:g}; most "
        f"from its {concern_from})"
    )


def _corrected_flag(i: int, c: Cohort, th: SubjectThresholds) -> str | None:
    """Subject `i`'s flag on its bias-corrected distance, in words, or None.

    A material distance, not an unusual one: a ratio to the judged subjects' median, as the
    failures it is for (true errors above 1.5x their registration's median) lie at 1.0-1.5x
    that median distance (issue 42). Not computed (NaN, or fewer than four subjects scored)
    never flags; nor does anything while `th.corrected_ratio` is None (off, the default)."""
    z = math.nan if c.corrected_z is None else c.corrected_z[i]
    median = c.medians.get("corrected_distance", math.nan)
    if th.corrected_ratio is None or not (math.isfinite(z) and median > 0):
        return None
    ratio = c.corrected_distance[i] / median
    if ratio <= th.corrected_ratio:
        return None
    return (
        f"far from the others once gain and bias are taken away: bias-corrected distance "
        f"{_fmt(c.corrected_distance[i])}, {ratio:.2f}x the cohort's median"
    )


def _fmt(v: float, digits: int = 3) -> str:
    return f"{v:.{digits}g}"


def _z_words(z: float) -> str:
    return "z = +inf" if z == math.inf else "z = -inf" if z == -math.inf else f"z = {z:+.1f}"


def shared_kinds(
    first: Mapping[int, Sequence[tuple[str, str]]], c: Cohort, th: SubjectThresholds
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


def _corrected_distances(squares, n_all: int, scored, rows) -> tuple[np.ndarray, np.ndarray]:
    """Every subject's bias-corrected distance (:func:`others_mean_distances`) and its robust z of
    the log over the judged `rows` (as the model distance's), NaN for those not scored."""
    distance = others_mean_distances(squares)
    values = np.full(n_all, np.nan)
    z = np.full(n_all, np.nan)
    values[scored] = distance
    if len(scored) >= 4:
        z[scored] = _log_distance_z(distance, rows)
    return values, z


def _log_distance_z(distance: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """The robust z-scores of the log of the scored subjects' `distance` (shape (n,)),
    over the judged `rows`, with a least spread of 1% of their median distance. A duplicate
    is at distance 0 from the others: the log of a tiny floor, not -inf."""
    tiny = max(float(np.max(distance)), 1.0) * 1e-12
    least = _LEAST_SPREAD_OF_SCORE * float(np.median(distance[rows]))
    return robust_z(distance, log=True, floor=tiny, least_spread=least, among=rows)
