"""Groupwise registration to an evolving mean (the paper's fourth method, after Cootes et al.).

Start: every image affinely aligned to the near-mean training image, whose grid is the
frame. Two engines share the B-spline representation of the pairwise method:

* ``"elastix"`` (default): for each of ``sweeps`` sweeps, form the mean of the currently
  registered set and register every image to it afresh from its affine with elastix's
  multi-resolution B-spline (as :func:`bspline_to_reference`, coarse to fine); then remove
  the group's mean non-affine displacement ``u = mean_i (A_i^-1 o T_i - id)`` by composing
  every transform with ``(id + u)^-1``, so the frame does not drift.
* ``"simpleitk"``: for each mesh level (coarse to fine) and sweep, register every image to
  the mean with a new cubic B-spline layer composed after its current transform
  (``T_i <- T_i o B_i``), and subtract the mean of the new layers' coefficients.

* ``"elastix-stack"`` (2D only): elastix's own groupwise registration. The images,
  resampled onto the frame through their affines, are stacked along a third axis and
  registered in one run with ``VarianceOverLastDimensionMetric`` (the variance across the
  images at every frame point) and a ``BSplineStackTransform`` (one 2D B-spline per image,
  coarse to fine, no smoothing or motion along the stack axis). Each image's B-spline
  ``B_i`` is rebuilt from elastix's parameter map (not from transformix fields) and its
  transform is ``A_i(B_i(p))``. The metric subtracts the mean gradient over the images, so
  the group's mean deformation stays near zero: the frame is the group's mean frame.

The reference returned is the final mean image.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import SimpleITK as sitk

from ..._errors import InputError
from ..._progress import progress_bar
from ...io.transforms import displacement_field, field_transform, invert
from ._common import group_mean, resample
from .bspline import BSplineOptions, elastix_parameters, sitk_bspline

__all__ = [
    "GroupwiseOptions",
    "groupwise_register",
    "groupwise_register_elastix",
    "groupwise_register_elastix_stack",
]


@dataclass(frozen=True)
class GroupwiseOptions:
    """Settings of the groupwise method.

    Attributes
    ----------
    grid_spacing : float
        Final control-point spacing (mm), as for pairwise.
    levels : int
        Mesh levels; level ``k`` has spacing ``grid_spacing * 2 ** (levels - 1 - k)`` and
        works on images shrunk by ``2 ** (levels - 1 - k)``.
    sweeps : int
        Mean updates per level (not used by elastix-stack, which has no explicit mean).
    iterations : int
        SimpleITK: L-BFGS-B iterations per image per sweep.
    sampling : float
        SimpleITK: fraction of voxels sampled by the metric, in (0, 1].
    elastix_levels : int
        elastix: resolutions of each registration to the mean (elastix-stack: of the one
        groupwise registration).
    elastix_iterations : int
        elastix, elastix-stack: iterations per resolution.
    samples : int
        elastix: random spatial samples per iteration.
    """

    grid_spacing: float = 16.0
    levels: int = 2
    sweeps: int = 2
    iterations: int = 40
    sampling: float = 0.25
    elastix_levels: int = 3
    elastix_iterations: int = 200
    samples: int = 2048

    def check(self) -> None:
        if min(self.levels, self.sweeps, self.iterations) < 1 or self.grid_spacing <= 0:
            raise InputError(
                "groupwise options: levels, sweeps and iterations must be >= 1 and "
                f"grid_spacing > 0, got {self.levels}, {self.sweeps}, {self.iterations}, "
                f"{self.grid_spacing}"
            )
        if not 0 < self.sampling <= 1:
            raise InputError(f"groupwise options: sampling must be in (0, 1], got {self.sampling}")


def groupwise_register(
    images: Sequence[sitk.Image],
    frame: sitk.Image,
    affines: Sequence[sitk.Transform],
    *,
    options: GroupwiseOptions,
    seed: int,
    progress: bool = True,
) -> tuple[list[sitk.Transform], sitk.Image]:
    """Register `images` to their evolving mean on the grid of `frame`.

    Parameters
    ----------
    images : sequence of sitk.Image, length n_images
        Scalar images (any grids) of the frame's dimension.
    frame : sitk.Image
        The grid of the group mean and of the transforms' reference points.
    affines : sequence of sitk.Transform, length n_images
        Each image's affine frame -> image, the start.
    options : GroupwiseOptions
    seed : int
        Seeds the metric sampling of every image at every sweep and level.
    progress : bool
        A progress bar on stderr (one step per sweep of each level).

    Returns
    -------
    transforms : list of sitk.CompositeTransform
        ``[A_i, B_i1, ..., B_iK]``: reference point p maps to ``A_i(B_i1(...B_iK(p)))``.
    mean : sitk.Image
        The final group mean on `frame`'s grid.
    """
    layers: list[list[sitk.Transform]] = [[a] for a in affines]
    steps = [(k, s) for k in range(options.levels) for s in range(options.sweeps)]
    bar = progress_bar(steps, desc="groupwise", total=len(steps), enabled=progress)
    for k, s in bar:
        mean = group_mean(images, frame, [sitk.CompositeTransform(t) for t in layers])
        factor = 2 ** (options.levels - 1 - k)
        spacing = options.grid_spacing * factor
        new = []
        for i, img in enumerate(images):
            # SimpleITK cannot use a B-spline inside a moving initial transform (no Jacobian
            # with respect to position): register to the image resampled through T_i instead;
            # pre(B(p)) = img(T_i(B(p))), so the new layer composes after T_i exactly.
            pre = resample(img, frame, sitk.CompositeTransform(layers[i]))
            b = sitk_bspline(
                mean,
                pre,
                initial=sitk.Transform(frame.GetDimension(), sitk.sitkIdentity),
                grid_spacing=spacing,
                levels=1,
                shrink_factors=[factor],
                iterations=options.iterations,
                sampling=options.sampling,
                seed=seed + 1000 * (k * options.sweeps + s + 1) + i,
            )
            new.append(b)
        params = np.array([b.GetParameters() for b in new])
        centred = params - params.mean(axis=0)
        for i, b in enumerate(new):
            b.SetParameters(tuple(centred[i]))
            layers[i].append(b)
    transforms = [sitk.CompositeTransform(t) for t in layers]
    return transforms, group_mean(images, frame, transforms)


def groupwise_register_elastix(
    images: Sequence[sitk.Image],
    frame: sitk.Image,
    affines: Sequence[sitk.Transform],
    *,
    options: GroupwiseOptions,
    seed: int,
    worker,
    progress: bool = True,
) -> tuple[list[sitk.Transform], sitk.Image]:
    """Register `images` to their evolving mean on the grid of `frame` with elastix.

    Parameters
    ----------
    images : sequence of sitk.Image, length n_images
        Scalar images (any grids) of the frame's dimension.
    frame : sitk.Image
        The grid of the group mean and of the transforms' reference points.
    affines : sequence of sitk.Transform, length n_images
        Each image's affine frame -> image, the start.
    options : GroupwiseOptions
    seed : int
        Seeds elastix's sampling of every image at every sweep.
    worker : ElastixWorker
        The running elastix worker.
    progress : bool
        A progress bar on stderr (one step per image and sweep).

    Returns
    -------
    transforms : list of sitk.DisplacementFieldTransform
        Reference point p maps to image point ``p + field_i(p)`` (affine included), on
        `frame`'s grid.
    mean : sitk.Image
        The final group mean on `frame`'s grid.
    """
    bspline = BSplineOptions(
        grid_spacing=options.grid_spacing,
        levels=options.elastix_levels,
        iterations=options.elastix_iterations,
        samples=options.samples,
    )
    transforms: list[sitk.Transform] = list(affines)
    steps = [(s, i) for s in range(options.sweeps) for i in range(len(images))]
    bar = iter(progress_bar(steps, desc="groupwise (elastix)", total=len(steps), enabled=progress))
    for sweep in range(options.sweeps):
        mean = group_mean(images, frame, transforms)
        fields = []
        for i, (img, aff) in enumerate(zip(images, affines, strict=True)):
            next(bar)
            transform, _ = worker.bspline(
                mean,
                img,
                initial=aff,
                levels=bspline.levels,
                grid_spacing=bspline.grid_spacing,
                parameters=elastix_parameters(bspline, seed=seed + 1000 * (sweep + 1) + i),
                what=f"image {i} (sweep {sweep + 1})",
            )
            fields.append(transform)
        # The group's mean non-affine displacement, in the frame: remove it.
        drift = np.mean(
            [
                sitk.GetArrayFromImage(
                    displacement_field(sitk.CompositeTransform([invert(a), f]), frame)
                )
                for a, f in zip(affines, fields, strict=True)
            ],
            axis=0,
        )
        drift_img = sitk.GetImageFromArray(drift, isVector=True)
        drift_img.CopyInformation(frame)
        undo = invert(field_transform(drift_img))
        transforms = [
            field_transform(displacement_field(sitk.CompositeTransform([f, undo]), frame))
            for f in fields
        ]
    for _ in bar:  # close the bar
        pass
    return transforms, group_mean(images, frame, transforms)


def _stack_parameters(options: GroupwiseOptions, *, seed: int) -> dict[str, list[str]]:
    """elastix's groupwise map for a 2D + image-index stack (overrides of its defaults)."""
    levels = options.elastix_levels
    schedule = []
    for k in range(levels):  # smoothing in the image plane only, none across images
        f = 2 ** (levels - 1 - k)
        schedule += [str(f), str(f), "0"]
    return {
        "Registration": ["MultiResolutionRegistration"],
        "Metric": ["VarianceOverLastDimensionMetric"],
        "SubtractMean": ["true"],
        "Transform": ["BSplineStackTransform"],
        "HowToCombineTransforms": ["Compose"],
        "FinalGridSpacingInPhysicalUnits": [str(options.grid_spacing)] * 2,
        "Optimizer": ["AdaptiveStochasticGradientDescent"],
        "MaximumNumberOfIterations": [str(options.elastix_iterations)],
        "ImageSampler": ["RandomCoordinate"],
        "NumberOfSpatialSamples": [str(options.samples)],
        "NewSamplesEveryIteration": ["true"],
        "MaximumNumberOfSamplingAttempts": ["8"],
        "CheckNumberOfSamples": ["true"],
        "Interpolator": ["ReducedDimensionBSplineInterpolator"],
        "BSplineInterpolationOrder": ["1"],
        "ResampleInterpolator": ["FinalReducedDimensionBSplineInterpolator"],
        "FinalBSplineInterpolationOrder": ["1"],
        "Resampler": ["DefaultResampler"],
        "FixedImagePyramid": ["FixedSmoothingImagePyramid"],
        "MovingImagePyramid": ["MovingSmoothingImagePyramid"],
        "FixedImagePyramidSchedule": schedule,
        "MovingImagePyramidSchedule": schedule,
        "MovingImageDerivativeScales": ["1", "1", "0"],
        "FixedInternalImagePixelType": ["float"],
        "MovingInternalImagePixelType": ["float"],
        "DefaultPixelValue": ["0"],
        "WriteResultImage": ["true"],
        "ResultImagePixelType": ["float"],
        "RandomSeed": [str(seed)],
    }


def groupwise_register_elastix_stack(
    images: Sequence[sitk.Image],
    frame: sitk.Image,
    affines: Sequence[sitk.Transform],
    *,
    options: GroupwiseOptions,
    seed: int,
    worker,
) -> tuple[list[sitk.Transform], sitk.Image, list[sitk.Image]]:
    """Register 2D `images` groupwise with elastix's stack metric on the grid of `frame`.

    Returns
    -------
    transforms : list of sitk.CompositeTransform
        ``[A_i, B_i]``: reference point p maps to ``A_i(B_i(p))``.
    mean : sitk.Image
        The group mean on `frame`'s grid.
    resampled : list of sitk.Image
        elastix's own registered slices (each affinely resampled image through ``B_i``).

    Raises
    ------
    InputError
        The images are not 2D.
    """
    if frame.GetDimension() != 2:
        raise InputError("elastix-stack supports 2D images only")
    pre = [resample(img, frame, a) for img, a in zip(images, affines, strict=True)]
    stack = sitk.JoinSeries(pre)  # last axis: image index, spacing 1
    bsplines, result = worker.stack(
        stack,
        levels=options.elastix_levels,
        grid_spacing=options.grid_spacing,
        parameters=_stack_parameters(options, seed=seed),
        what=f"the stack of {len(images)} images",
    )
    size = list(result.GetSize())
    resampled = []
    for i in range(len(images)):
        piece = sitk.Extract(result, [size[0], size[1], 0], [0, 0, i])
        piece.CopyInformation(frame)
        resampled.append(piece)
    transforms = [sitk.CompositeTransform([a, b]) for a, b in zip(affines, bsplines, strict=True)]
    return transforms, group_mean(images, frame, transforms), resampled
