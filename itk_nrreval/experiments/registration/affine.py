"""Affine registration with SimpleITK: the control method and the start of all the others.

Multi-resolution (shrink factors with Gaussian smoothing), a randomly sampled metric seeded
per image, regular-step gradient descent with scales from physical shifts, initialised by
matching the images' centres of mass (image moments).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import SimpleITK as sitk

from ..._errors import InputError
from ..._progress import progress_bar
from ._common import (
    METRICS,
    EngineError,
    engine_seed,
    reproducible_threads,
    resample,
    set_metric,
)

__all__ = ["AffineOptions", "affine_register", "affine_to_reference", "choose_reference"]


@dataclass(frozen=True)
class AffineOptions:
    """Settings of the affine stage.

    Attributes
    ----------
    shrink_factors : tuple of int
        Image down-sampling per level, coarse to fine.
    smoothing_sigmas : tuple of float
        Gaussian smoothing per level, in voxels.
    iterations : int
        Maximum optimiser iterations per level.
    sampling : float
        Fraction of voxels sampled (randomly, seeded) by the metric, in (0, 1].
    metric : {"mean_squares", "correlation", "mattes"}
        Similarity: mean squared difference (same contrast), normalised correlation, or
        Mattes mutual information (50 bins).
    """

    shrink_factors: tuple[int, ...] = (4, 2, 1)
    smoothing_sigmas: tuple[float, ...] = (2.0, 1.0, 0.0)
    iterations: int = 200
    sampling: float = 0.25
    metric: str = "mean_squares"

    def check(self) -> None:
        if len(self.shrink_factors) != len(self.smoothing_sigmas) or not self.shrink_factors:
            raise InputError(
                "affine options: shrink_factors and smoothing_sigmas need the same number "
                f"of levels, got {self.shrink_factors} and {self.smoothing_sigmas}"
            )
        if not 0 < self.sampling <= 1:
            raise InputError(f"affine options: sampling must be in (0, 1], got {self.sampling}")
        if self.metric not in METRICS:
            raise InputError(
                f"affine options: metric must be one of {METRICS}, got {self.metric!r}"
            )


def affine_register(
    fixed: sitk.Image,
    moving: sitk.Image,
    *,
    options: AffineOptions = AffineOptions(),
    seed: int = 0,
    initial: sitk.Transform | None = None,
) -> sitk.AffineTransform:
    """Affine transform mapping `fixed` (reference) points to `moving` points (mm, LPS).

    Parameters
    ----------
    fixed, moving : sitk.Image
        Scalar images (any grids) of the same dimension.
    options : AffineOptions
    seed : int
        Seed of the metric's random sampling.
    initial : sitk.Transform, optional
        Starting affine; by default the centres of mass are matched.

    Returns
    -------
    sitk.AffineTransform
        ``moving`` resampled on ``fixed``'s grid through it is aligned with ``fixed``.
    """
    dim = fixed.GetDimension()
    if initial is None:
        initial = sitk.CenteredTransformInitializer(
            fixed,
            moving,
            sitk.AffineTransform(dim),
            sitk.CenteredTransformInitializerFilter.MOMENTS,
        )
    reg = sitk.ImageRegistrationMethod()
    set_metric(reg, options.metric)
    reg.SetMetricSamplingStrategy(reg.RANDOM)
    reg.SetMetricSamplingPercentage(float(options.sampling), engine_seed(seed))
    reg.SetInterpolator(sitk.sitkLinear)
    reg.SetOptimizerAsRegularStepGradientDescent(
        learningRate=1.0,
        minStep=1e-4,
        numberOfIterations=int(options.iterations),
        gradientMagnitudeTolerance=1e-8,
        relaxationFactor=0.5,
    )
    reg.SetOptimizerScalesFromPhysicalShift()
    reg.SetShrinkFactorsPerLevel(list(options.shrink_factors))
    reg.SetSmoothingSigmasPerLevel(list(options.smoothing_sigmas))
    reg.SmoothingSigmasAreSpecifiedInPhysicalUnitsOff()
    start = sitk.AffineTransform(dim)
    start.SetFixedParameters(initial.GetFixedParameters())
    start.SetParameters(initial.GetParameters())
    reg.SetInitialTransform(start, inPlace=True)
    try:
        with reproducible_threads(options.metric):
            reg.Execute(fixed, moving)
    except RuntimeError as exc:
        raise EngineError(
            f"SimpleITK affine registration failed: {str(exc).strip()[-200:]}"
        ) from None
    return start


def _compose_affines(
    outer: sitk.AffineTransform, inner: sitk.AffineTransform
) -> sitk.AffineTransform:
    """The affine p -> outer(inner(p))."""
    dim = outer.GetDimension()
    mo = np.reshape(outer.GetMatrix(), (dim, dim))
    mi = np.reshape(inner.GetMatrix(), (dim, dim))
    zero = np.zeros(dim)
    bo = np.asarray(outer.TransformPoint(tuple(zero)))
    bi = np.asarray(inner.TransformPoint(tuple(zero)))
    out = sitk.AffineTransform(dim)
    out.SetMatrix(tuple((mo @ mi).ravel()))
    out.SetTranslation(tuple(mo @ bi + bo))
    return out


def affine_to_reference(
    images: Sequence[sitk.Image],
    reference: sitk.Image,
    *,
    options: AffineOptions,
    seed: int,
    reference_index: int | None = None,
    initial: Sequence[sitk.Transform | None] | None = None,
    progress: bool = True,
    numbers: Sequence[int] | None = None,
    desc: str = "affine",
) -> list[sitk.AffineTransform]:
    """Affine of every image to `reference` (reference -> image); identity for the reference itself.

    Parameters
    ----------
    images : sequence of sitk.Image, length n_images
        Scalar images (any grids) of the reference's dimension.
    reference : sitk.Image
        The fixed image: the transforms map its points (mm) to each image's.
    options : AffineOptions
    seed : int
        Image ``i`` uses the metric sampling seed ``seed + numbers[i]``.
    reference_index : int, optional
        The reference's index in `images`: that image keeps the identity, unregistered.
    initial : sequence of sitk.Transform or None, length n_images, optional
        Each image's starting affine (None: centres of mass matched).
    progress : bool
        A progress bar on stderr, labelled `desc`.
    numbers : sequence of int, length n_images, optional
        The images' numbers in a larger group (default ``0 .. n_images - 1``).
    desc : str
        The progress bar's label.

    Returns
    -------
    list of sitk.AffineTransform, length n_images
        Reference points -> image points (mm, LPS).
    """
    numbers = range(len(images)) if numbers is None else numbers
    out = []
    for i, img in progress_bar(
        list(enumerate(images)), desc=desc, total=len(images), enabled=progress
    ):
        if i == reference_index:
            out.append(sitk.AffineTransform(img.GetDimension()))
            continue
        start = None if initial is None else initial[i]
        out.append(
            affine_register(
                reference, img, options=options, seed=seed + int(numbers[i]), initial=start
            )
        )
    return out


def choose_reference(
    images: Sequence[sitk.Image],
    choice: str,
    *,
    options: AffineOptions,
    seed: int,
    progress: bool = True,
) -> tuple[int, list[sitk.AffineTransform], np.ndarray]:
    """Pick the training image nearest to / farthest from the group mean after affine alignment.

    All images are affinely registered to image 0; the aligned images' mean is formed on
    image 0's grid, and each aligned image's root-mean-square difference from it measured.

    Parameters
    ----------
    images : sequence of sitk.Image, length n_images
        Scalar images (any grids) of one dimension.
    choice : {"near-mean", "far-from-mean"}
    options : AffineOptions
        The alignment's settings.
    seed : int
        Image ``i``'s alignment to image 0 uses the metric sampling seed ``seed + i``.
    progress : bool
        A progress bar on stderr.

    Returns
    -------
    index : int
        The chosen image.
    affines : list of sitk.AffineTransform
        Initial affines reference -> image ``i`` for the chosen reference, composed from the
        alignment to image 0 (``T_0i o T_0r^-1``).
    distances : ndarray of shape (n_images,)
        RMS difference of each aligned image from the mean (intensity units).
    """
    if choice not in ("near-mean", "far-from-mean"):
        raise InputError(f"reference_choice must be 'near-mean' or 'far-from-mean', got {choice!r}")
    to0 = affine_to_reference(
        images,
        images[0],
        options=options,
        seed=seed,
        reference_index=0,
        progress=progress,
    )
    aligned = [
        sitk.GetArrayFromImage(resample(im, images[0], t)).astype(np.float64)
        for im, t in zip(images, to0, strict=True)
    ]
    stack = np.stack(aligned)
    mean = stack.mean(axis=0)
    distances = np.sqrt(((stack - mean) ** 2).reshape(len(images), -1).mean(axis=1))
    index = int(np.argmin(distances) if choice == "near-mean" else np.argmax(distances))
    inv_r = to0[index].GetInverse()
    inv_r = sitk.AffineTransform(inv_r) if not isinstance(inv_r, sitk.AffineTransform) else inv_r
    affines = [_compose_affines(t, inv_r) for t in to0]
    return index, affines, distances
