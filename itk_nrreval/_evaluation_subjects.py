"""Evaluate's per-subject quality control step, taken while the pipeline still has the cache.

For every registration, :func:`registration_subjects` assesses each subject against its
cohort (:func:`itk_nrreval.measures.subject_qc.assess_subjects`: distance to the model of the
others, deformation, overlap, coverage, brain mask), and :func:`subject_assessor` makes the
pipeline's ``assess_subjects``, which does so once per registration and looks for inverted
or swapped transforms among the flagged subjects (which takes resampling them again).
"""

from __future__ import annotations

from .io.manifest import Manifest
from .io.plausibility import SubjectThresholds
from .measures.subject_qc import (
    SubjectQC,
    assess_subjects,
    reference_subject,
    transform_mixups,
)

__all__ = ["subject_assessor", "registration_subjects"]


def subject_assessor(m: Manifest, thresholds: SubjectThresholds):
    """The pipeline's ``assess_subjects``: each registration's subjects assessed once, while
    the pipeline still has the cache (an inverted or swapped transform is looked for among
    the flagged subjects, through `products`)."""

    def assess(r, products) -> tuple[SubjectQC, ...]:
        first = registration_subjects(m, r, thresholds)
        # an inverted or another subject's transform is looked for among the flagged
        # subjects only: it takes resampling them through changed transforms
        mixups = transform_mixups(
            first,
            images=[str(p) for p in m.images],
            scored=r.scored,
            gram=r.gram,
            products=products,
        )
        return registration_subjects(m, r, thresholds, mixups) if mixups else first

    return assess


def registration_subjects(
    m: Manifest,
    r,
    thresholds: SubjectThresholds,
    mixups: dict[int, tuple[float, str]] | None = None,
) -> tuple[SubjectQC, ...]:
    """Every subject's quality control under registration run `r` (`mixups`: flagged
    subjects resampled through changed transforms,
    :func:`itk_nrreval.measures.subject_qc.transform_mixups`)."""
    fits = [f.to_dict() for f in r.affine_fits]
    plaus = [p.to_dict() for p in r.plausibility]
    deformation = {
        k: [row[k] for row in plaus]
        for k in (
            "folded_fraction",
            "nondiffeomorphic_fraction",
            "nondiffeomorphic_volume",
            "sdlogj",
            "jacobian_min",
            "jacobian_max",
        )
    }
    deformation["inverse_consistency_mm"] = [row["inverse_consistency_mm"] for row in plaus]
    for k in ("linear_det", "nonlinear_rms_mm", "displacement_rms_mm"):
        deformation[k] = [row[k] for row in fits]
    # where this registration's frame was estimated from the group (not the common one)
    deformation["frame_deviation_mm"] = list(r.frame.per_image_mm) or [None] * m.n_images
    sums = r.overlap_sums
    registration = m.registrations[r.name]
    return assess_subjects(
        images=[str(p) for p in m.images],
        scored=r.scored,
        gram=r.gram,
        deformation=deformation,
        coverage=r.coverage.per_image,
        overlap_volume=None if sums is None else sums["volume"],
        overlap_target_sums=None if sums is None else sums["target_sums"],
        overlap_weights=None if r.overlap is None else r.overlap.weights("volume"),
        corrected_squares=r.corrected_squares,
        mixups=mixups,
        # a subject registered to itself (reference_index, or the reference's own image with
        # the identity): not judged
        reference=reference_subject(
            registration.reference,
            m.images,
            reference_index=registration.reference_index,
            displacement_rms_mm=deformation["displacement_rms_mm"],
        ),
        brain_mask_dice=None if r.brain_masks is None else r.brain_masks.dice,
        thresholds=thresholds,
    )
