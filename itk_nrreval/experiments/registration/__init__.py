"""Register a group of images with one of the paper's five algorithms (Section V-B).

:func:`register` runs one method over N images and returns a :class:`RegistrationResult`
holding, per image, a SimpleITK transform that maps **reference points to image points**
(mm, LPS, ITK convention: resample image ``i`` on the reference grid through
``transforms[i]``), the reference image, and the settings used.

Methods
-------
``"affine"``
    SimpleITK affine, multi-resolution with a sampled metric: the control, and the start of
    every other method.
``"fluid"``
    Dense diffeomorphic repeated-pairwise registration to one reference: SimpleITK
    diffeomorphic demons after affine and histogram matching (engine ``"simpleitk"``), or
    ANTs SyN (engine ``"ants"``, needs antspyx).
``"pairwise"``
    Cubic B-spline free-form deformation, coarse to fine, repeated pairwise to one
    reference: elastix (engine ``"elastix"``, run in a worker process) or SimpleITK
    (engine ``"simpleitk"``).
``"groupwise"``
    Registration to an evolving mean: every image is registered to the mean of the current
    registered set and the mean is updated, with the B-spline representation of
    ``"pairwise"`` (engine ``"elastix"``, or ``"simpleitk"`` with a mesh refined coarse to
    fine); the group's mean deformation is removed after each sweep so the frame does not
    drift. Engine ``"elastix-stack"`` (2D only) instead runs elastix's own groupwise
    registration once: the affinely aligned images stacked along a third axis, the
    variance over the images as metric, one B-spline per image.

The reference of ``affine``, ``fluid`` and ``pairwise`` is a training image (or an image
given by the caller); ``reference_choice="near-mean"`` / ``"far-from-mean"`` picks the
training image closest to / farthest from the group mean after affine alignment (the
paper's two pairwise references). ``groupwise`` returns the final group mean as its
reference, on the grid of the near-mean training image.

A group mixing modalities (each image with a group label, e.g. T1 / T2) is registered by
:func:`register_multimodal` instead: all images to one reference with mutual information
(``strategy="joint"``), or each group to its own reference linked to the reference group's
by one mutual-information registration (``strategy="per-group"``); see
:mod:`itk_nrreval.experiments.registration.multimodal`.
"""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import SimpleITK as sitk

from ..._errors import InputError
from ...io.transforms import flatten
from ._common import (
    EngineError,
    check_choice,
    check_engine_options,
    input_settings,
    load_images,
    with_options,
)
from ._elastix_worker import ElastixWorker, elastix_worker_for
from .affine import AffineOptions, affine_to_reference, choose_reference
from .bspline import BSplineOptions, bspline_to_reference
from .fluid import FluidOptions, fluid_to_reference, import_ants
from .groupwise import (
    GroupwiseOptions,
    groupwise_register,
    groupwise_register_elastix,
    groupwise_register_elastix_stack,
)
from .multimodal import STRATEGIES, MultimodalResult, register_multimodal
from .result import RegistrationResult

__all__ = [
    "METHODS",
    "ENGINES",
    "register",
    "check_engine_options",
    "RegistrationResult",
    "register_multimodal",
    "MultimodalResult",
    "STRATEGIES",
    "ElastixWorker",
    "EngineError",
    "AffineOptions",
    "FluidOptions",
    "BSplineOptions",
    "GroupwiseOptions",
    "REFERENCE_CHOICES",
]

#: The methods, in the order of the paper's Table 3.
METHODS = ("fluid", "groupwise", "pairwise", "affine")
#: Engines per method; the first is the default.
ENGINES = {
    "affine": ("simpleitk",),
    "fluid": ("simpleitk", "ants"),
    "pairwise": ("elastix", "simpleitk"),
    "groupwise": ("elastix", "simpleitk", "elastix-stack"),
}
_OPTIONS = {
    "affine": AffineOptions(),
    "fluid": FluidOptions(),
    "pairwise": BSplineOptions(),
    "groupwise": GroupwiseOptions(),
}
REFERENCE_CHOICES = ("near-mean", "far-from-mean")


def register(
    images: Sequence[sitk.Image | str | os.PathLike],
    *,
    method: str,
    reference: int | sitk.Image | str | os.PathLike | None = None,
    reference_choice: str | None = None,
    engine: str | None = None,
    options: Mapping[str, Any] | None = None,
    affine_options: Mapping[str, Any] | None = None,
    out: str | os.PathLike | None = None,
    seed: int = 0,
    progress: bool = True,
    elastix_worker=None,
    affine: RegistrationResult | None = None,
) -> RegistrationResult:
    """Register a group of images with one of the paper's methods.

    Parameters
    ----------
    images : sequence of sitk.Image or path, length n_images >= 2
        Scalar 2D or 3D images (grids may differ; registration works in physical space).
    method : {"affine", "fluid", "pairwise", "groupwise"}
    reference : int, sitk.Image or path, optional
        The reference of affine / fluid / pairwise: an index into `images`, or another
        image. Not accepted by groupwise.
    reference_choice : {"near-mean", "far-from-mean"}, optional
        Pick the reference among `images` after affine alignment (default ``"near-mean"``
        when `reference` is not given; groupwise always starts from the near-mean image's
        frame).
    engine : str, optional
        affine: ``{"simpleitk"}``; fluid: ``{"simpleitk", "ants"}``; pairwise:
        ``{"elastix", "simpleitk"}``; groupwise: ``{"elastix", "simpleitk",
        "elastix-stack"}`` (elastix-stack: 2D images only). Default the first.
    options : mapping, optional
        Fields of the method's options dataclass to override (:class:`FluidOptions`,
        :class:`BSplineOptions`, :class:`GroupwiseOptions`, or :class:`AffineOptions` for
        ``method="affine"``).
    affine_options : mapping, optional
        Fields of :class:`AffineOptions` for the affine stage of the other methods.
    out : path, optional
        Also write the result there (:meth:`RegistrationResult.write`).
    seed : int
        Seeds every random choice: metric sampling of image ``i`` uses ``seed + i``.
    progress : bool
        Show progress bars on stderr.
    elastix_worker : ElastixWorker, optional
        A running worker to reuse (saves elastix's ~10 s start-up across calls); by
        default one is started and stopped for this call.
    affine : RegistrationResult, optional
        An earlier ``method="affine"`` result for the same images: its reference and
        transforms are this method's affine stage, which is then skipped (then give neither
        `reference` nor `reference_choice`). Saves the affine work when several methods
        share a reference, as in the paper's comparison.

    Returns
    -------
    RegistrationResult

    Raises
    ------
    InputError
        Unknown method / engine / option, unreadable images, a missing optional engine
        (antspyx, itk-elastix), 3D images with engine ``"elastix-stack"``.
    EngineError
        The engine failed or its worker process crashed (the message says which image).
    """
    engine = _check_method(method, engine, reference=reference, reference_choice=reference_choice)
    imgs, paths = load_images(images)
    _check_images(
        imgs, engine=engine, affine=affine, reference=reference, reference_choice=reference_choice
    )
    plan = _plan(method, engine, options=options, affine_options=affine_options)
    started = time.perf_counter()
    stage = _affine_stage(
        imgs,
        paths,
        plan.affine_options,
        reference=reference,
        reference_choice=reference_choice,
        affine=affine,
        seed=seed,
        progress=progress,
    )
    registered = _run_method(
        imgs, stage, plan, seed=seed, progress=progress, elastix_worker=elastix_worker
    )
    result = RegistrationResult.from_transforms(
        imgs,
        [flatten(t) for t in registered.transforms],
        reference=registered.reference,
        reference_index=registered.reference_index,
        resampled=registered.resampled,
        settings=_settings(plan, stage, seed=seed, paths=paths),
        started=started,
        method=method,
        engine=engine,
    )
    if out is not None:
        result.write(out)
    return result


@dataclasses.dataclass(frozen=True)
class _Plan:
    """What one :func:`register` call runs: the method, its engine and their options."""

    method: str
    engine: str
    affine_options: AffineOptions
    #: The method's own options (:class:`AffineOptions` again for ``"affine"``).
    options: AffineOptions | FluidOptions | BSplineOptions | GroupwiseOptions


@dataclasses.dataclass(frozen=True)
class _AffineStage:
    """The reference and every image's affine to it (reference points -> image points)."""

    reference: sitk.Image
    #: The reference's index among the images, or None (an image given by the caller).
    reference_index: int | None
    affines: list[sitk.Transform]
    #: How the reference was chosen ("near-mean", "far-from-mean"), None when given.
    reference_choice: str | None
    #: Taken from an earlier affine registration rather than computed.
    reused: bool


@dataclasses.dataclass(frozen=True)
class _Registered:
    """A method's transforms (reference -> image) and its frame, before they are flattened."""

    transforms: list[sitk.Transform]
    reference: sitk.Image
    reference_index: int | None
    #: The engine's own resampled images; None: resampled through the transforms.
    resampled: list[sitk.Image] | None = None


def _check_method(method: str, engine: str | None, *, reference, reference_choice) -> str:
    """The engine (default: the method's first) once the arguments that need no image are
    checked; InputError before any image is read."""
    check_choice("method", method, tuple(ENGINES))
    engine = ENGINES[method][0] if engine is None else engine
    check_choice(f"engine for method {method!r}", engine, ENGINES[method])
    if reference_choice is not None:
        check_choice("reference_choice", reference_choice, REFERENCE_CHOICES)
    if reference is not None and reference_choice is not None:
        raise InputError("give either reference or reference_choice, not both")
    if method == "groupwise" and reference is not None:
        raise InputError("groupwise registers to the evolving group mean: do not give a reference")
    if method == "fluid" and engine == "ants":
        import_ants()  # fail before any work when antspyx is missing
    return engine


def _check_images(
    imgs: list[sitk.Image],
    *,
    engine: str,
    affine: RegistrationResult | None,
    reference,
    reference_choice: str | None,
) -> None:
    """Refuse images the engine cannot take, and an `affine` stage that is not theirs."""
    if engine == "elastix-stack" and imgs[0].GetDimension() != 2:
        raise InputError(
            f"elastix-stack supports 2D images only, got {imgs[0].GetDimension()}D images"
        )
    if affine is None:
        return
    if affine.method != "affine" or affine.n_images != len(imgs):
        raise InputError(
            f"affine: expected an affine registration of these {len(imgs)} images, got a "
            f"{affine.method} registration of {affine.n_images}"
        )
    if reference is not None or reference_choice is not None:
        raise InputError("affine: its reference is used; do not give reference or choice")


def _plan(
    method: str,
    engine: str,
    *,
    options: Mapping[str, Any] | None,
    affine_options: Mapping[str, Any] | None,
) -> _Plan:
    """The affine stage's options and the method's, checked (InputError before any work)."""
    affine_stage = with_options(
        AffineOptions(), options if method == "affine" else affine_options, what="affine"
    )
    affine_stage.check()
    if method == "affine":
        own = affine_stage
    else:
        own = with_options(_OPTIONS[method], options, what=method)
    own.check()
    check_engine_options(method, engine, own)
    return _Plan(method, engine, affine_stage, own)


def _affine_stage(
    imgs: list[sitk.Image],
    paths: list[str | None],
    options: AffineOptions,
    *,
    reference,
    reference_choice: str | None,
    affine: RegistrationResult | None,
    seed: int,
    progress: bool,
) -> _AffineStage:
    """The reference and the affines to it: those of `affine`, else computed to `reference`,
    else to the training image `reference_choice` picks (default near-mean)."""
    if affine is not None:
        return _AffineStage(
            reference=affine.reference,
            reference_index=affine.reference_index,
            affines=[sitk.AffineTransform(t) for t in affine.transforms],
            reference_choice=affine.settings.get("reference_choice"),
            reused=True,
        )
    initial = None  # the reference choice's affines, a start for the final ones
    if reference is None:
        choice = reference_choice or "near-mean"
        ref_index, initial, _ = choose_reference(
            imgs, choice, options=options, seed=seed, progress=progress
        )
        ref_image = imgs[ref_index]
    else:
        choice = None
        ref_index, ref_image = _resolve_reference(reference, imgs, paths)
    affines = affine_to_reference(
        imgs,
        ref_image,
        options=options,
        seed=seed,
        reference_index=ref_index,
        initial=initial,
        progress=progress,
    )
    return _AffineStage(ref_image, ref_index, affines, choice, reused=False)


def _run_method(
    imgs: list[sitk.Image],
    stage: _AffineStage,
    plan: _Plan,
    *,
    seed: int,
    progress: bool,
    elastix_worker: ElastixWorker | None,
) -> _Registered:
    """The method's transforms, each starting from the image's affine of `stage`."""
    if plan.method == "affine":
        return _Registered(list(stage.affines), stage.reference, stage.reference_index)
    to_reference = {
        "seed": seed,
        "reference_index": stage.reference_index,
        "progress": progress,
        "options": plan.options,
        "engine": plan.engine,
    }
    if plan.method == "fluid":
        transforms = fluid_to_reference(imgs, stage.reference, stage.affines, **to_reference)
        return _Registered(transforms, stage.reference, stage.reference_index)
    if plan.method == "pairwise":
        transforms, resampled = bspline_to_reference(
            imgs, stage.reference, stage.affines, **to_reference, worker=elastix_worker
        )
        return _Registered(transforms, stage.reference, stage.reference_index, resampled)
    return _groupwise(imgs, stage, plan, seed=seed, progress=progress, worker=elastix_worker)


def _groupwise(
    imgs: list[sitk.Image],
    stage: _AffineStage,
    plan: _Plan,
    *,
    seed: int,
    progress: bool,
    worker: ElastixWorker | None,
) -> _Registered:
    """Groupwise registration from the affine stage; the final group mean is the reference
    (on the grid of the affine stage's reference)."""
    start = (imgs, stage.reference, stage.affines)
    if plan.engine == "simpleitk":
        transforms, mean = groupwise_register(
            *start, options=plan.options, seed=seed, progress=progress
        )
        return _Registered(transforms, mean, None)
    with elastix_worker_for(worker) as running:
        if plan.engine == "elastix-stack":
            transforms, mean, resampled = groupwise_register_elastix_stack(
                *start, options=plan.options, seed=seed, worker=running
            )
            return _Registered(transforms, mean, None, resampled)
        transforms, mean = groupwise_register_elastix(
            *start, options=plan.options, seed=seed, worker=running, progress=progress
        )
        return _Registered(transforms, mean, None)


def _settings(plan: _Plan, stage: _AffineStage, *, seed: int, paths) -> dict[str, Any]:
    """The result's settings (JSON-ready): method, engine, input, reference, options."""
    if plan.method == "groupwise":
        reference_choice = "group mean (near-mean frame)"
    else:
        reference_choice = stage.reference_choice
    return {
        "method": plan.method,
        "engine": plan.engine,
        **input_settings(seed=seed, paths=paths),
        "reference_choice": reference_choice,
        "affine_options": dataclasses.asdict(plan.affine_options),
        "affine_stage": "reused" if stage.reused else "computed",
        "options": dataclasses.asdict(plan.options),
    }


def _resolve_reference(reference, imgs, paths) -> tuple[int | None, sitk.Image]:
    if isinstance(reference, bool):
        raise InputError(f"reference: expected an index, image or path, got {reference!r}")
    if isinstance(reference, int):
        if not 0 <= reference < len(imgs):
            raise InputError(f"reference: index {reference} out of range for {len(imgs)} images")
        return reference, imgs[reference]
    if isinstance(reference, sitk.Image):
        return None, sitk.Cast(reference, sitk.sitkFloat32)
    if isinstance(reference, (str, os.PathLike)):
        target = Path(reference).resolve()
        for i, p in enumerate(paths):
            if p is not None and Path(p).resolve() == target:
                return i, imgs[i]
        ref, _ = load_images([reference, reference])
        return None, ref[0]
    raise InputError(f"reference: expected an index, image or path, got {type(reference).__name__}")
