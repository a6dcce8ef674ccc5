"""Pairwise cubic B-spline free-form deformation, coarse to fine, to one reference.

Engine ``"elastix"`` (itk-elastix, in a worker process): elastix's default B-spline map for
``levels`` resolutions and the final control-point spacing ``grid_spacing`` (mm), the metric
of ``metric`` (mean squares by default; ``"mattes"``: elastix's
``AdvancedMattesMutualInformation``, for images of different contrasts), started from the
SimpleITK affine (given to elastix as its initial transform). elastix composes that as
``B(A(p))``: the result is ``CompositeTransform([B, A])`` with elastix's B-spline rebuilt as
a SimpleITK ``BSplineTransform``.

Engine ``"simpleitk"``: SimpleITK's B-spline with the affine as moving initial transform
(result ``[A, B]``: ``A(B(p))``), the mesh refined by 2 per level, the same ``metric``;
optimised by gradient descent with line search (LBFGSB fails with a refined mesh).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import SimpleITK as sitk

from ..._errors import InputError
from ..._progress import progress_bar
from ._common import (
    METRICS,
    EngineError,
    engine_seed,
    mesh_size,
    reproducible_threads,
    resample,
    set_metric,
)

__all__ = [
    "BSplineOptions",
    "sitk_bspline",
    "bspline_register",
    "bspline_to_reference",
    "ELASTIX_METRICS",
    "elastix_parameters",
]

#: elastix's metric for each of :data:`METRICS`.
ELASTIX_METRICS = {
    "mean_squares": "AdvancedMeanSquares",
    "correlation": "AdvancedNormalizedCorrelation",
    "mattes": "AdvancedMattesMutualInformation",
}


@dataclass(frozen=True)
class BSplineOptions:
    """Settings of the B-spline stage (pairwise and groupwise).

    Attributes
    ----------
    grid_spacing : float
        Final control-point spacing in mm; level ``k`` of ``levels`` uses
        ``grid_spacing * 2 ** (levels - 1 - k)``.
    levels : int
        Coarse-to-fine levels (image pyramid and mesh together).
    iterations : int
        Optimiser iterations per level.
    samples : int
        elastix: random spatial samples per iteration.
    sampling : float
        SimpleITK: fraction of voxels sampled by the metric, in (0, 1].
    elastix_parameters : dict
        elastix parameters overriding the default map (``{"Metric": "AdvancedMeanSquares"}``);
        they win over `metric`.
    metric : {"mean_squares", "correlation", "mattes"}
        Similarity: mean squared difference (same contrast), normalised correlation, or
        Mattes mutual information (images of different contrasts, e.g. T1 against T2);
        elastix: ``AdvancedMeanSquares``, ``AdvancedNormalizedCorrelation``,
        ``AdvancedMattesMutualInformation``; SimpleITK: 50 histogram bins.
    bending_weight : float
        elastix: weight of the bending-energy penalty of the B-spline
        (``TransformBendingEnergyPenalty``, a second metric beside the similarity, whose
        weight is 1), the engine's regularisation weight. 0, the default, adds no penalty
        (elastix's default map has one of weight 1; this package has always left it out).
        SimpleITK's B-spline registration has no such term: a weight > 0 is refused there.
    """

    grid_spacing: float = 16.0
    levels: int = 3
    iterations: int = 200
    samples: int = 2048
    sampling: float = 0.25
    elastix_parameters: Mapping[str, object] = field(default_factory=dict)
    metric: str = "mean_squares"
    bending_weight: float = 0.0

    def check(self) -> None:
        if self.levels < 1 or self.iterations < 1 or self.grid_spacing <= 0:
            raise InputError(
                "pairwise options: levels and iterations must be >= 1 and grid_spacing > 0, "
                f"got {self.levels}, {self.iterations}, {self.grid_spacing}"
            )
        if not 0 < self.sampling <= 1:
            raise InputError(f"pairwise options: sampling must be in (0, 1], got {self.sampling}")
        if self.metric not in METRICS:
            raise InputError(
                f"pairwise options: metric must be one of {METRICS}, got {self.metric!r}"
            )
        w = self.bending_weight
        if isinstance(w, bool) or not isinstance(w, (int, float)) or not 0 <= w < float("inf"):
            raise InputError(f"pairwise options: bending_weight must be a number >= 0, got {w!r}")


def sitk_bspline(
    fixed: sitk.Image,
    moving: sitk.Image,
    *,
    initial: sitk.Transform,
    grid_spacing: float,
    levels: int,
    shrink_factors: Sequence[int] | None = None,
    iterations: int,
    sampling: float,
    seed: int,
    max_step: float = 1.0,
    metric: str = "mean_squares",
) -> sitk.BSplineTransform:
    """SimpleITK B-spline ``B`` such that ``initial(B(p))`` maps `fixed` points to `moving` points.

    The mesh starts at ``grid_spacing * 2**(levels-1)`` mm and is refined by 2 per level;
    images are shrunk by ``shrink_factors`` (default ``2**(levels-1-k)``) and smoothed by
    half the shrink factor (voxels). `metric` is one of :data:`METRICS` (``"mattes"``:
    Mattes mutual information, for images of different contrasts).
    """
    dim = fixed.GetDimension()
    coarse = mesh_size(fixed, grid_spacing * 2 ** (levels - 1))
    tx = sitk.BSplineTransformInitializer(fixed, coarse, 3)
    if shrink_factors is None:
        shrink_factors = [2 ** (levels - 1 - k) for k in range(levels)]
    reg = sitk.ImageRegistrationMethod()
    set_metric(reg, metric)
    reg.SetMetricSamplingStrategy(reg.RANDOM)
    reg.SetMetricSamplingPercentage(float(sampling), engine_seed(seed))
    reg.SetInterpolator(sitk.sitkLinear)
    if levels == 1:
        # One mesh: L-BFGS-B is robust and fast (it fails on a refined mesh).
        reg.SetOptimizerAsLBFGSB(
            gradientConvergenceTolerance=1e-5,
            numberOfIterations=int(iterations),
            maximumNumberOfCorrections=5,
            maximumNumberOfFunctionEvaluations=4 * int(iterations),
            costFunctionConvergenceFactor=1e7,
        )
    else:
        # B-spline parameters are all displacements in mm, so unit scales are right; the
        # step is bounded in physical units (a runaway line search can otherwise map every
        # sample outside the image, where the metric is blind).
        spacing = min(fixed.GetSpacing())
        reg.SetOptimizerAsGradientDescentLineSearch(
            learningRate=1.0,
            numberOfIterations=int(iterations),
            convergenceMinimumValue=1e-6,
            convergenceWindowSize=5,
            lineSearchUpperLimit=2.0,
            estimateLearningRate=reg.EachIteration,
            maximumStepSizeInPhysicalUnits=spacing * max_step,
        )
        reg.SetOptimizerScalesFromPhysicalShift()
    reg.SetShrinkFactorsPerLevel(list(shrink_factors))
    reg.SetSmoothingSigmasPerLevel([0.5 * f if f > 1 else 0.0 for f in shrink_factors])
    reg.SmoothingSigmasAreSpecifiedInPhysicalUnitsOff()
    reg.SetMovingInitialTransform(initial)
    reg.SetInitialTransformAsBSpline(tx, inPlace=True, scaleFactors=[2**k for k in range(levels)])
    try:
        with reproducible_threads(metric):
            out = reg.Execute(fixed, moving)
    except RuntimeError as exc:
        raise EngineError(
            f"SimpleITK B-spline registration failed: {str(exc).strip()[-200:]}"
        ) from None
    out = out.Downcast()
    if not isinstance(out, sitk.BSplineTransform):  # pragma: no cover - SimpleITK version guard
        out = sitk.BSplineTransform(tx)
    assert out.GetDimension() == dim
    return out


def elastix_parameters(options: BSplineOptions, *, seed: int) -> dict[str, list[str]]:
    """The overrides of elastix's default B-spline map used here."""
    params = {
        "Metric": [ELASTIX_METRICS[options.metric]],
        "Metric0Weight": ["1.0"],
        "MaximumNumberOfIterations": [str(options.iterations)],
        "NumberOfSpatialSamples": [str(options.samples)],
        "FinalBSplineInterpolationOrder": ["1"],
        "RandomSeed": [str(seed)],
        "WriteResultImage": ["true"],
        "ResultImagePixelType": ["float"],
    }
    if options.bending_weight > 0:
        params["Metric"].append("TransformBendingEnergyPenalty")
        params["Metric1Weight"] = [repr(float(options.bending_weight))]
    for key, value in dict(options.elastix_parameters).items():
        params[str(key)] = (
            [str(v) for v in value] if isinstance(value, (list, tuple)) else [str(value)]
        )
    return params


def bspline_register(
    reference: sitk.Image,
    image: sitk.Image,
    initial: sitk.Transform,
    *,
    options: BSplineOptions,
    engine: str,
    seed: int,
    worker=None,
    what: str,
) -> tuple[sitk.Transform, sitk.Image | None]:
    """One image's B-spline transform reference -> image, the affine `initial` included.

    Parameters
    ----------
    reference, image : sitk.Image
        The fixed and the moving image.
    initial : sitk.Transform
        The affine stage, reference points -> image points (mm, LPS).
    options : BSplineOptions, keyword-only
    engine : {"elastix", "simpleitk"}, keyword-only
    seed : int, keyword-only
        The seed of this image's registration.
    worker : ElastixWorker, keyword-only
        A running worker (engine ``"elastix"``; not used by ``"simpleitk"``).
    what : str, keyword-only
        The job's name in elastix's error messages (e.g. ``"image 3"``).

    Returns
    -------
    transform : sitk.Transform
        Reference points -> image points: SimpleITK ``CompositeTransform([initial, B])``;
        elastix its own result (module docstring).
    resampled : sitk.Image or None
        elastix: the image as elastix resampled it on the reference grid; SimpleITK: None.
    """
    if engine == "simpleitk":
        b = sitk_bspline(
            reference,
            image,
            initial=initial,
            grid_spacing=options.grid_spacing,
            levels=options.levels,
            iterations=options.iterations,
            sampling=options.sampling,
            seed=seed,
            metric=options.metric,
        )
        return sitk.CompositeTransform([initial, b]), None
    return worker.bspline(
        reference,
        image,
        initial=initial,
        levels=options.levels,
        grid_spacing=options.grid_spacing,
        parameters=elastix_parameters(options, seed=seed),
        what=what,
    )


def bspline_to_reference(
    images: Sequence[sitk.Image],
    reference: sitk.Image,
    affines: Sequence[sitk.Transform],
    *,
    options: BSplineOptions,
    engine: str,
    seed: int,
    reference_index: int | None = None,
    progress: bool = True,
    worker=None,
    numbers: Sequence[int] | None = None,
    desc: str = "pairwise",
) -> tuple[list[sitk.Transform], list[sitk.Image] | None]:
    """Per image the B-spline transform reference -> image (affine included).

    Parameters
    ----------
    images : sequence of sitk.Image, length n_images
        Scalar images (any grids) of the reference's dimension.
    reference : sitk.Image
        The fixed image: the transforms map its points (mm) to each image's.
    affines : sequence of sitk.Transform, length n_images
        Each image's affine reference -> image, the B-spline's start.
    options : BSplineOptions
    engine : {"elastix", "simpleitk"}
    seed : int
        Image ``i`` uses the seed ``seed + numbers[i]``.
    reference_index : int, optional
        The reference's index in `images`: that image keeps its identity affine.
    progress : bool
        A progress bar on stderr, labelled `desc` and the engine.
    worker : ElastixWorker, optional
        A running elastix worker to reuse; without one, elastix runs in one started for
        this call.
    numbers : sequence of int, length n_images, optional
        The images' numbers in a larger group (default ``0 .. n_images - 1``): image ``i``
        is called ``image numbers[i]`` in messages.
    desc : str
        The progress bar's label.

    Returns
    -------
    transforms : list of sitk.Transform, length n_images
        Reference points -> image points (mm, LPS), affine included.
    resampled : list of sitk.Image or None
        elastix's own resampled images on the reference grid; None with ``"simpleitk"``.
    """
    numbers = list(range(len(images))) if numbers is None else [int(k) for k in numbers]
    items = list(enumerate(zip(images, affines, strict=True)))
    bar = progress_bar(items, desc=f"{desc} ({engine})", total=len(items), enabled=progress)
    by_elastix = engine != "simpleitk"
    if not by_elastix and options.bending_weight > 0:
        raise InputError(
            "pairwise options: bending_weight needs the elastix engine (SimpleITK's "
            "B-spline registration has no bending-energy term)"
        )
    from ._elastix_worker import elastix_worker_for  # noqa: PLC0415

    transforms, resampled = [], []
    with elastix_worker_for(worker, needed=by_elastix) as running:
        for i, (img, aff) in bar:
            if i == reference_index:
                transforms.append(aff)
                # elastix resampled the others; the reference itself is resampled here
                resampled.append(resample(img, reference, aff) if by_elastix else None)
                continue
            transform, result = bspline_register(
                reference,
                img,
                aff,
                options=options,
                engine=engine,
                seed=seed + numbers[i],
                worker=running,
                what=f"image {numbers[i]}",
            )
            transforms.append(transform)
            resampled.append(result)
    return transforms, resampled if by_elastix else None
