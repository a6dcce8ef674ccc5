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
:mod:`itk_nrreval.registration.multimodal`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import SimpleITK as sitk

from .._errors import InputError
from ..transforms import flatten
from ._common import EngineError, check_engine_options, load_images, resample, with_options
from ._elastix_worker import ElastixWorker
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


def _check_choice(name: str, value, accepted) -> None:
    if value not in accepted:
        raise InputError(f"{name}: {value!r} is not one of {', '.join(map(repr, accepted))}")


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
    _check_choice("method", method, tuple(ENGINES))
    engine = ENGINES[method][0] if engine is None else engine
    _check_choice(f"engine for method {method!r}", engine, ENGINES[method])
    if reference_choice is not None:
        _check_choice("reference_choice", reference_choice, REFERENCE_CHOICES)
    if reference is not None and reference_choice is not None:
        raise InputError("give either reference or reference_choice, not both")
    if method == "groupwise" and reference is not None:
        raise InputError("groupwise registers to the evolving group mean: do not give a reference")
    if method == "fluid" and engine == "ants":
        import_ants()  # fail before any work when antspyx is missing
    imgs, paths = load_images(images)
    n = len(imgs)
    if engine == "elastix-stack" and imgs[0].GetDimension() != 2:
        raise InputError(
            f"elastix-stack supports 2D images only, got {imgs[0].GetDimension()}D images"
        )
    if affine is not None:
        if affine.method != "affine" or affine.n_images != n:
            raise InputError(
                f"affine: expected an affine registration of these {n} images, got a "
                f"{affine.method} registration of {affine.n_images}"
            )
        if reference is not None or reference_choice is not None:
            raise InputError("affine: its reference is used; do not give reference or choice")
    aff_opts = with_options(
        AffineOptions(), options if method == "affine" else affine_options, what="affine"
    )
    aff_opts.check()
    opts = aff_opts if method == "affine" else with_options(_OPTIONS[method], options, what=method)
    if hasattr(opts, "check"):
        opts.check()
    check_engine_options(method, engine, opts)
    t0 = time.perf_counter()

    # The reference, and the affines to it.
    ref_index: int | None = None
    initial = None
    if affine is not None:
        choice = affine.settings.get("reference_choice")
        ref_index, ref_image = affine.reference_index, affine.reference
        affines = [sitk.AffineTransform(t) for t in affine.transforms]
    elif reference is None:
        choice = reference_choice or "near-mean"
        ref_index, initial, _ = choose_reference(
            imgs, choice, options=aff_opts, seed=seed, show_progress=progress
        )
        ref_image = imgs[ref_index]
    else:
        choice = None
        ref_index, ref_image = _resolve_reference(reference, imgs, paths)
    if affine is None:
        affines = affine_to_reference(
            imgs,
            ref_image,
            options=aff_opts,
            seed=seed,
            reference_index=ref_index,
            initial=initial,
            show_progress=progress,
        )

    engine_resampled = None
    if method == "affine":
        transforms: list[sitk.Transform] = list(affines)
    elif method == "fluid":
        transforms = fluid_to_reference(
            imgs,
            ref_image,
            affines,
            options=opts,
            engine=engine,
            seed=seed,
            reference_index=ref_index,
            show_progress=progress,
        )
    elif method == "pairwise":
        transforms, engine_resampled = bspline_to_reference(
            imgs,
            ref_image,
            affines,
            options=opts,
            engine=engine,
            seed=seed,
            reference_index=ref_index,
            show_progress=progress,
            worker=elastix_worker,
        )
    elif engine == "elastix-stack":
        with contextlib.nullcontext(elastix_worker) if elastix_worker else ElastixWorker() as w:
            transforms, ref_image, engine_resampled = groupwise_register_elastix_stack(
                imgs, ref_image, affines, options=opts, seed=seed, worker=w
            )
        ref_index = None
    elif engine == "elastix":
        with contextlib.nullcontext(elastix_worker) if elastix_worker else ElastixWorker() as w:
            transforms, ref_image = groupwise_register_elastix(
                imgs, ref_image, affines, options=opts, seed=seed, worker=w, show_progress=progress
            )
        ref_index = None
    else:
        transforms, ref_image = groupwise_register(
            imgs, ref_image, affines, options=opts, seed=seed, show_progress=progress
        )
        ref_index = None
    transforms = [flatten(t) for t in transforms]
    if engine_resampled is None:
        engine_resampled = [
            resample(im, ref_image, t) for im, t in zip(imgs, transforms, strict=True)
        ]
    seconds = time.perf_counter() - t0
    settings = {
        "method": method,
        "engine": engine,
        "seed": seed,
        "n_images": n,
        "images": paths if all(p is not None for p in paths) else None,
        "reference_choice": choice if method != "groupwise" else "group mean (near-mean frame)",
        "affine_options": dataclasses.asdict(aff_opts),
        "affine_stage": "reused" if affine is not None else "computed",
        "options": dataclasses.asdict(opts),
    }
    json.dumps(settings)  # settings must stay JSON-ready
    result = RegistrationResult(
        method=method,
        engine=engine,
        transforms=tuple(transforms),
        reference=ref_image,
        reference_index=ref_index,
        resampled=tuple(engine_resampled),
        settings=settings,
        seconds=seconds,
    )
    if out is not None:
        result.write(out)
    return result


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
