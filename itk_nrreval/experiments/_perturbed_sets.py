"""The perturbed sets of the validation experiment (:mod:`itk_nrreval.experiments.perturbation`).

Every image of the registered set gets its own random clamped-plate-spline warp of exactly
the mean displacement ``d`` (:func:`itk_nrreval.experiments.warps.random_cps`), drawn from a seed of
its own (the run's seed, ``d``, the repeat and the image: the same warp whatever else is run),
and its image and label memberships are warped through it (:class:`Perturbation`); the whole
set at one ``d`` and repeat is one :class:`PerturbedSet`, which the experiment measures.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .._errors import InputError
from .._executors import Executor
from ._perturbation_inputs import Inputs
from .warps import CPSWarp, FoldingError, random_cps, warp_stack

__all__ = ["PerturbedSet", "Perturbation"]


@dataclass(frozen=True)
class PerturbedSet:
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
class Perturbation:
    """The random CPS warps of a validation run: image i's warp in repeat r at displacement
    d, and the perturbed set of (d, r)."""

    inputs: Inputs
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

    def instance(self, d: float, r: int, executor: Executor) -> PerturbedSet:
        """The whole set perturbed at `d` in repeat `r` (its images warped by `executor`)."""
        inputs = self.inputs
        if d == 0.0:  # the identity: no resampling at all
            members = _onehot(inputs.labels, inputs.n_labels)
            return PerturbedSet(d, r, inputs.images, members, 1.0, 0.0)
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
        return PerturbedSet(d, r, warped, members, float(jacobians.min()), float(np.mean(mms)))


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


def _onehot(lab: np.ndarray, n_labels: int) -> np.ndarray:
    if np.issubdtype(lab.dtype, np.floating):
        return lab
    out = np.empty((lab.shape[0], n_labels, *lab.shape[1:]), dtype=np.float32)
    for k in range(n_labels):
        out[:, k] = lab == k
    return out
