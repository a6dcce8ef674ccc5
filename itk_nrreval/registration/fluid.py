"""Dense diffeomorphic ("fluid") repeated-pairwise registration to one reference.

Engine ``"simpleitk"``: after the affine stage, each image is resampled onto the reference
grid, histogram-matched to the reference, and registered with SimpleITK's
``DiffeomorphicDemonsRegistrationFilter``, coarse to fine. The demons field ``D`` maps a
reference point p to a point of the affinely resampled image, whose value came from the
image at ``A(p')``; the transform reference -> image is therefore ``A(D(p))``, which is
``sitk.CompositeTransform([A, D])`` (SimpleITK applies the last of its list first).

Engine ``"ants"``: antspyx SyN (``"SyNOnly"``) on the same affinely resampled images, when
antspyx is installed.
"""

from __future__ import annotations

import tempfile
from collections.abc import Sequence
from dataclasses import dataclass

import SimpleITK as sitk

from .._errors import InputError
from .._progress import progress
from ..transforms import field_transform, read_transform
from ._common import EngineError, resample

__all__ = ["FluidOptions", "demons_register", "fluid_to_reference", "import_ants"]


@dataclass(frozen=True)
class FluidOptions:
    """Settings of the diffeomorphic demons stage.

    Attributes
    ----------
    shrink_factors : tuple of int
        Down-sampling per level, coarse to fine.
    iterations : tuple of int
        Demons iterations per level.
    smoothing_sigma : float
        Standard deviation (voxels of each level) of the Gaussian smoothing of the
        displacement field after each iteration (the "elastic" regularisation). 2.5 was
        chosen on generated phantoms, where 1.0-2.0 tore homogeneous regions apart.
    max_step : float
        Largest update per iteration (voxels).
    histogram_levels : int
        Histogram bins for the histogram matching (7 match points, threshold at the mean).
    """

    shrink_factors: tuple[int, ...] = (4, 2, 1)
    iterations: tuple[int, ...] = (100, 60, 40)
    smoothing_sigma: float = 2.5
    max_step: float = 1.0
    histogram_levels: int = 256

    def check(self) -> None:
        if len(self.shrink_factors) != len(self.iterations) or not self.iterations:
            raise InputError(
                "fluid options: shrink_factors and iterations need the same number of levels, "
                f"got {self.shrink_factors} and {self.iterations}"
            )


def _shrink(image: sitk.Image, factor: int) -> sitk.Image:
    if factor == 1:
        return image
    sigma = [0.5 * factor * s for s in image.GetSpacing()]
    return sitk.Shrink(
        sitk.SmoothingRecursiveGaussian(image, sigma), [factor] * image.GetDimension()
    )


def demons_register(
    fixed: sitk.Image, moving: sitk.Image, *, options: FluidOptions = FluidOptions()
) -> sitk.Image:
    """Diffeomorphic demons field on `fixed`'s grid mapping fixed points to `moving` points.

    Both images must lie on the same grid (resample `moving` first).

    Returns
    -------
    sitk.Image
        Vector image (float64, mm, ITK component order): fixed point p corresponds to the
        moving point ``p + field(p)``.
    """
    field = None
    for factor, iterations in zip(options.shrink_factors, options.iterations, strict=True):
        f, m = _shrink(fixed, factor), _shrink(moving, factor)
        if field is None:
            field = sitk.Image(f.GetSize(), sitk.sitkVectorFloat64, f.GetDimension())
            field.CopyInformation(f)
        else:
            field = sitk.Resample(field, f, sitk.Transform(), sitk.sitkLinear, 0.0)
        demons = sitk.DiffeomorphicDemonsRegistrationFilter()
        demons.SetNumberOfIterations(int(iterations))
        demons.SetSmoothDisplacementField(True)
        # ITK takes the smoothing width in mm (it uses the image spacing): convert from voxels
        # of this level, so that coarse levels are regularised as much as fine ones.
        demons.SetStandardDeviations([float(options.smoothing_sigma) * s for s in f.GetSpacing()])
        demons.SetMaximumUpdateStepLength(float(options.max_step))
        demons.SetUseGradientType(demons.Symmetric)
        try:
            field = demons.Execute(f, m, field)
        except RuntimeError as exc:
            raise EngineError(f"SimpleITK demons failed: {str(exc).strip()[-200:]}") from None
    return field


def match_histogram(moving: sitk.Image, reference: sitk.Image, levels: int) -> sitk.Image:
    """`moving`'s intensities mapped onto `reference`'s histogram (7 match points)."""
    return sitk.HistogramMatching(
        moving,
        reference,
        numberOfHistogramLevels=int(levels),
        numberOfMatchPoints=7,
        thresholdAtMeanIntensity=True,
    )


def fluid_to_reference(
    images: Sequence[sitk.Image],
    reference: sitk.Image,
    affines: Sequence[sitk.Transform],
    *,
    options: FluidOptions,
    engine: str = "simpleitk",
    seed: int = 0,
    reference_index: int | None = None,
    show_progress: bool = True,
) -> list[sitk.Transform]:
    """Per image the transform reference -> image ``[A_i, field_i]`` (``A_i(D_i(p))``).

    The reference image itself (`reference_index`) keeps its identity affine.
    """
    if engine == "ants":
        ants = import_ants()
    out = []
    for i, (img, aff) in progress(
        list(enumerate(zip(images, affines, strict=True))),
        desc="fluid",
        total=len(images),
        enabled=show_progress,
    ):
        if i == reference_index:
            out.append(aff)
            continue
        pre = match_histogram(resample(img, reference, aff), reference, options.histogram_levels)
        if engine == "ants":
            warp = _ants_syn(ants, reference, pre, seed=seed + i)
        else:
            warp = field_transform(demons_register(reference, pre, options=options))
        out.append(sitk.CompositeTransform([aff, warp]))
    return out


def import_ants():
    """The ``ants`` module (antspyx), or an InputError saying how to install it."""
    try:
        import ants  # noqa: PLC0415
    except ImportError:
        raise InputError(
            "antspyx is not installed: pip install antspyx (or use --engine simpleitk)"
        ) from None
    return ants


def _ants_syn(ants, fixed: sitk.Image, moving: sitk.Image, *, seed: int) -> sitk.Transform:
    """SyN of `moving` to `fixed` (same grid) with antspyx, as one SimpleITK transform."""
    with tempfile.TemporaryDirectory(prefix="nrreval-ants-") as tmp:
        paths = []
        for name, img in (("fixed", fixed), ("moving", moving)):
            paths.append(f"{tmp}/{name}.nii.gz")
            sitk.WriteImage(img, paths[-1])
        out = ants.registration(
            ants.image_read(paths[0]),
            ants.image_read(paths[1]),
            type_of_transform="SyNOnly",
            outprefix=f"{tmp}/out_",
            random_seed=seed,
        )
        # fwdtransforms act first-listed first: give SimpleITK the reversed list.
        parts = [read_transform(p) for p in out["fwdtransforms"]]
        return parts[0] if len(parts) == 1 else sitk.CompositeTransform(parts[::-1])
