"""Helpers shared by the registration methods: options, image loading, resampling, means."""

from __future__ import annotations

import contextlib
import dataclasses
import os
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import SimpleITK as sitk

from ..._errors import EngineError, InputError
from ...io._images import read_image

__all__ = [
    "EngineError",
    "check_choice",
    "check_engine_options",
    "input_settings",
    "engine_seed",
    "with_options",
    "load_images",
    "resample",
    "group_mean",
    "mesh_size",
    "METRICS",
    "set_metric",
    "reproducible_threads",
]

#: The similarity metrics of the SimpleITK stages (affine and B-spline).
METRICS = ("mean_squares", "correlation", "mattes")

S = TypeVar("S")


def engine_seed(seed: int) -> int:
    """The seed handed to SimpleITK / ITK / ANTs for the toolkit's `seed`: never 0.

    SimpleITK's ``SetMetricSamplingPercentage`` reads a seed of 0 as ``sitkWallClock`` (seed
    from the clock), and ANTs' ``--random-seed`` wants "any nonzero int value" (its help);
    so the engines get ``seed + 1`` (seeds 0 .. 2**32 - 2 map one to one onto 1 .. 2**32 - 1,
    the range of SimpleITK's unsigned 32-bit seed).
    """
    return int(seed) % (2**32 - 1) + 1


def with_options(defaults: S, options: Mapping[str, Any] | None, *, what: str) -> S:
    """`defaults` (a frozen dataclass) with the fields named in `options` replaced.

    Sequences are turned into tuples so the settings stay hashable and JSON-friendly.

    Raises
    ------
    InputError
        An option name that the method does not have (the message lists the accepted ones).
    """
    if not options:
        return defaults
    names = [f.name for f in dataclasses.fields(defaults)]
    unknown = [k for k in options if k not in names]
    if unknown:
        raise InputError(
            f"{what} options: unknown {', '.join(map(repr, unknown))} "
            f"(accepted: {', '.join(names)})"
        )
    clean = {k: tuple(v) if isinstance(v, (list, tuple)) else v for k, v in options.items()}
    return dataclasses.replace(defaults, **clean)


def check_choice(name: str, value: Any, accepted: Sequence) -> None:
    """Refuse `value` unless it is one of `accepted` (InputError naming `name`)."""
    if value not in accepted:
        raise InputError(f"{name}: {value!r} is not one of {', '.join(map(repr, accepted))}")


def load_images(images: Sequence) -> tuple[list[sitk.Image], list[str | None]]:
    """Float32 SimpleITK images from images or paths; also each one's path (or None).

    Images may lie on different grids (each is registered in physical space).
    """
    if isinstance(images, (str, os.PathLike, sitk.Image)) or not isinstance(images, Sequence):
        raise InputError(
            f"images: expected a sequence of images or paths, got {type(images).__name__}"
        )
    if len(images) < 2:
        raise InputError(f"images: a group needs at least 2 images, got {len(images)}")
    out, paths = [], []
    for i, item in enumerate(images):
        if isinstance(item, sitk.Image):
            img, path = item, None
        elif isinstance(item, (str, os.PathLike)):
            img, path = read_image(item), str(Path(item))
        else:
            raise InputError(
                f"images[{i}]: expected a SimpleITK image or a path, got {type(item).__name__}"
            )
        if img.GetNumberOfComponentsPerPixel() != 1:
            raise InputError(f"{path or f'images[{i}]'}: expected a scalar image")
        if img.GetDimension() not in (2, 3):
            raise InputError(f"{path or f'images[{i}]'}: expected a 2D or 3D image")
        out.append(sitk.Cast(img, sitk.sitkFloat32))
        paths.append(path)
    dims = {im.GetDimension() for im in out}
    if len(dims) > 1:
        raise InputError("images: mixed 2D and 3D images")
    return out, paths


def input_settings(*, seed: int, paths: Sequence[str | None]) -> dict[str, Any]:
    """The settings every registration records about its input: seed, images and their paths.

    Parameters
    ----------
    seed : int, keyword-only
        The registration's seed.
    paths : sequence of (str or None), length n_images, keyword-only
        Each image's path as :func:`load_images` returns it (None: given as an image).

    Returns
    -------
    dict
        ``{"seed", "n_images", "images"}``; ``"images"`` is None unless every image was
        given as a path (the record then names the files a rerun needs).
    """
    return {
        "seed": seed,
        "n_images": len(paths),
        "images": paths if all(p is not None for p in paths) else None,
    }


def resample(image: sitk.Image, reference: sitk.Image, transform: sitk.Transform) -> sitk.Image:
    """`image` on `reference`'s grid through `transform` (reference -> image), linear, 0 outside."""
    return sitk.Resample(
        image,
        reference,
        transform,
        sitk.sitkLinear,
        0.0,
        sitk.sitkFloat32,
    )


def group_mean(
    images: Sequence[sitk.Image], reference: sitk.Image, transforms: Sequence
) -> sitk.Image:
    """Voxel-wise mean of the images resampled onto `reference`'s grid (float32)."""
    acc = None
    for img, t in zip(images, transforms, strict=True):
        arr = sitk.GetArrayFromImage(resample(img, reference, t)).astype(np.float64)
        acc = arr if acc is None else acc + arr
    mean = sitk.GetImageFromArray((acc / len(images)).astype(np.float32))
    mean.CopyInformation(reference)
    return mean


def set_metric(reg: sitk.ImageRegistrationMethod, metric: str) -> None:
    """Give `reg` the similarity `metric` (one of :data:`METRICS`).

    ``"mean_squares"``: mean squared intensity difference (same contrast); ``"correlation"``:
    normalised correlation (intensities related linearly); ``"mattes"``: Mattes mutual
    information with 50 histogram bins (any intensity relation, e.g. T1 against T2).
    """
    if metric == "mean_squares":
        reg.SetMetricAsMeanSquares()
    elif metric == "correlation":
        reg.SetMetricAsCorrelation()
    elif metric == "mattes":
        reg.SetMetricAsMattesMutualInformation(numberOfHistogramBins=50)
    else:
        raise InputError(f"metric must be one of {METRICS}, got {metric!r}")


@contextlib.contextmanager
def reproducible_threads(metric: str) -> Iterator[None]:
    """Run SimpleITK single-threaded inside the block when `metric` is ``"mattes"``.

    ITK's Mattes mutual information sums its per-thread joint histograms in an order that
    varies from run to run, so a multi-threaded registration is not reproducible: the same
    seed gave affine parameters differing by up to 0.004 (matrix) and 0.03 mm (translation)
    on a 141 x 141 T1 / T2 pair with 2 threads, and identical ones with 1 (at about 1.4x
    the time). The other metrics are reproducible threaded and are left alone. The global
    default is restored afterwards.
    """
    if metric != "mattes":
        yield
        return
    before = sitk.ProcessObject.GetGlobalDefaultNumberOfThreads()
    sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(1)
    try:
        yield
    finally:
        sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(before)


def mesh_size(reference: sitk.Image, grid_spacing: float) -> list[int]:
    """B-spline mesh cells per axis giving control points about `grid_spacing` mm apart."""
    extent = [n * s for n, s in zip(reference.GetSize(), reference.GetSpacing(), strict=True)]
    return [max(1, int(round(e / grid_spacing))) for e in extent]


def check_engine_options(method: str, engine: str, options) -> None:
    """Refuse options that `engine` cannot honour (InputError), before any work.

    Parameters
    ----------
    method, engine : str
        As :func:`register` (`engine` resolved: not None).
    options : dataclass
        The method's options (e.g. :class:`BSplineOptions`).
    """
    if getattr(options, "bending_weight", 0) > 0 and engine != "elastix":
        raise InputError(
            f"{method} options: bending_weight needs the elastix engine, not {engine!r} "
            "(its B-spline registration has no bending-energy term)"
        )
