"""True correspondence error: how far a registration of generated data is from the truth.

Only data with known true transforms have it (generated populations: :mod:`data_synth`);
the demo, sweeps with ``truth=`` and the benchmarks report it beside the scores, which
never use it.
"""

from __future__ import annotations

import numpy as np
import SimpleITK as sitk

from ..evaluation import EvaluationResult
from ..io._images import Geometry, read_image
from ..io.frame import read_chains, resampling_transform
from ..io.manifest import load_manifest
from ..io.transforms import displacement_field

__all__ = ["correspondence_error", "spread_of_correspondence"]


def correspondence_error(
    evaluation: EvaluationResult,
    manifest,
    subject_to_template: list[sitk.Transform],
    *,
    mask: np.ndarray | None = None,
) -> dict[str, float]:
    """True mean correspondence error of each registration, in mm.

    A registration puts the points ``x_i = T_i(F(p))`` of the N images in correspondence
    for every point p of the common frame. The true correspondence sends each ``x_i`` to the
    template point ``y_i = S_i(x_i)`` (``S_i``: subject -> template); a perfect registration
    gives the same ``y_i`` for every i. The error is the mean over p (inside `mask`) and i
    of ``|y_i - mean_j y_j|``: it does not depend on which frame is common.

    Parameters
    ----------
    evaluation : EvaluationResult
        Gives each registration's frame transform F.
    manifest : Manifest or path
        The manifest that was evaluated.
    subject_to_template : list of sitk.Transform, length n_images
        True transforms, subject points -> template points (mm, LPS).
    mask : ndarray of bool, shape of the common grid (numpy order), optional
        The points p to average over; default all.
    """
    m = load_manifest(manifest)
    grid = Geometry.from_image(
        read_image(m.registrations[m.common_frame].reference, what="reference image")
    )
    return {
        name: spread_of_correspondence(
            [resampling_transform(t, scores.frame.transform) for t in read_chains(m, name)],
            subject_to_template,
            grid,
            mask=mask,
        )
        for name, scores in evaluation.scores.items()
    }


def spread_of_correspondence(
    transforms: list[sitk.Transform],
    subject_to_template: list[sitk.Transform],
    grid: Geometry,
    *,
    mask: np.ndarray | None = None,
) -> float:
    """Mean distance (mm) of ``y_i = S_i(T_i(p))`` from ``mean_j y_j``, over p and i.

    The true correspondence error of one registration (:func:`correspondence_error`) whose
    transforms `transforms` map the points p of `grid` (the common frame) to image points;
    ``S_i`` = `subject_to_template` [i], subject points -> template points. `mask` (bool,
    the grid's numpy shape) selects the points p; default all.
    """
    points = []
    for t, s in zip(transforms, subject_to_template, strict=True):
        d = sitk.GetArrayFromImage(displacement_field(sitk.CompositeTransform([s, t]), grid))
        points.append(d[mask] if mask is not None else d.reshape(-1, d.shape[-1]))
    # The grid points themselves cancel in y_i - mean_j y_j.
    y = np.stack(points)
    return float(np.linalg.norm(y - y.mean(axis=0), axis=-1).mean())
