"""Dense diffeomorphic ("fluid") repeated-pairwise registration to one reference.

Engine ``"simpleitk"``: after the affine stage, each image is resampled onto the reference
grid, histogram-matched to the reference, and registered with SimpleITK's
``DiffeomorphicDemonsRegistrationFilter``, coarse to fine. The demons field ``D`` maps a
reference point p to a point of the affinely resampled image, whose value came from the
image at ``A(p')``; the transform reference -> image is therefore ``A(D(p))``, which is
``sitk.CompositeTransform([A, D])`` (SimpleITK applies the last of its list first).

Engine ``"ants"``: antspyx SyN (``"SyNOnly"``) on the same affinely resampled images, when
antspyx is installed (``pip install itk-nrreval[ants]``).

Units
-----
ITK's demons filters take the standard deviations of their Gaussian field smoothing in
**pixels** of the images they are given, one per axis (``SetStandardDeviations``: "The
values are set with respect to pixel coordinates"; ``PDEDeformableRegistrationFilter::
SmoothDisplacementField`` builds a ``GaussianOperator`` of variance ``sd[j]**2`` along index
axis ``j`` and never reads the spacing). :class:`FluidOptions` states the smoothing in mm;
:func:`demons_register` converts it to pixels for every level and every axis, so a coarse
level, an anisotropic voxel or another sampling of the same anatomy is smoothed by the same
physical width. ITK caps an update at ``MaximumUpdateStepLength`` times the root-mean-square
voxel size; :attr:`FluidOptions.max_step` is in voxels of the smallest voxel dimension, and
converted. The coarse levels are the images smoothed and linearly resampled at the centres
of blocks of voxels (``sitk.Shrink`` would pick voxels by rounding half-integer indices, which
depends on the float error of an oblique direction matrix).
"""

from __future__ import annotations

import inspect
import math
import numbers
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass

import SimpleITK as sitk

from ..._errors import InputError, readable
from ..._progress import progress_bar
from ...io.transforms import chain_transform, field_transform
from ._common import EngineError, engine_seed, resample

__all__ = [
    "FluidOptions",
    "MAX_PIXEL_SIGMA",
    "ants_syn",
    "demons_pixel_sigmas",
    "demons_register",
    "fluid_to_reference",
    "import_ants",
    "seeded_ants_registration",
]

#: Mass of the Gaussian kernel that ITK may leave out when it truncates it (ITK's default
#: 0.1 cuts the kernel at about 1.6 standard deviations, which shrinks the effective
#: standard deviation to about 0.82 of the one asked for; 0.001 keeps it within 1%).
_KERNEL_MAXIMUM_ERROR = 0.001
#: Widest smoothing (pixels) handed to ITK. Its ``GaussianOperator`` computes
#: ``exp(-s**2) * I_n(s**2)``, which overflows to ``0 * inf`` from about 26.6 pixels and fills
#: the whole field with NaN without an error; wider smoothing is refused.
MAX_PIXEL_SIGMA = 25.0


@dataclass(frozen=True)
class FluidOptions:
    """Settings of the diffeomorphic demons stage.

    Attributes
    ----------
    shrink_factors : tuple of int
        Down-sampling per level, coarse to fine (the same factor on every axis).
    iterations : tuple of int
        Demons iterations per level.
    smoothing_mm : float or tuple of float
        Standard deviation, in mm, of the Gaussian that smooths the displacement field after
        every iteration (the "elastic" regularisation), the same physical width on every
        axis whatever the voxel size (ITK receives ``mm / spacing`` pixels per axis of the
        level's images, :func:`demons_pixel_sigmas`). A number ``s`` is the width at full
        resolution; a level shrunk by ``f`` uses ``f * s`` mm, the same number of its (``f``
        times larger) voxels, as ITK's own multi-resolution demons do. A tuple gives the mm of
        every level, coarse to fine, used as given. The default, 5 mm (20, 10, 5 mm at
        shrink 4, 2, 1), gave the smallest true correspondence error, or one within 3% of
        it, of the widths tried (1-8 mm, scaled or the same at every level) on generated
        2D phantom (1.6 mm and 1.6 x 3.2 mm voxels), 2D MNI (1.4 mm) and 3D phantom (3 mm)
        populations (``benchmarks/bench_demons_smoothing.py``).
    update_smoothing_mm : float
        Standard deviation, in mm, of the Gaussian that smooths each iteration's *update*
        field before it is composed in (the "fluid" regularisation of demons), scaled per
        level like a number given as `smoothing_mm`. 0, the default, does not smooth the
        update (ITK's default too), so the field smoothing alone regularises.
    max_step : float
        Largest update per iteration, in voxels of the level's smallest voxel dimension
        (``max_step * min(spacing)`` mm). ITK's ``MaximumUpdateStepLength`` is in units of
        the root-mean-square voxel size, which on anisotropic voxels exceeds a voxel along
        the fine axis; :func:`demons_register` converts.
    histogram_levels : int
        Histogram bins for the histogram matching (7 match points, threshold at the mean).
    """

    shrink_factors: tuple[int, ...] = (4, 2, 1)
    iterations: tuple[int, ...] = (100, 60, 40)
    smoothing_mm: float | tuple[float, ...] = 5.0
    update_smoothing_mm: float = 0.0
    max_step: float = 1.0
    histogram_levels: int = 256

    def smoothing_per_level(self) -> tuple[float, ...]:
        """The smoothing standard deviation (mm) of each level, coarse to fine."""
        if isinstance(self.smoothing_mm, (tuple, list)):
            return tuple(float(s) for s in self.smoothing_mm)
        return tuple(float(f) * float(self.smoothing_mm) for f in self.shrink_factors)

    def update_smoothing_per_level(self) -> tuple[float, ...]:
        """The update-field smoothing standard deviation (mm) of each level (0: none)."""
        return tuple(float(f) * float(self.update_smoothing_mm) for f in self.shrink_factors)

    def check(self) -> None:
        """Raise InputError naming the first inconsistent or out-of-range option."""
        if len(self.shrink_factors) != len(self.iterations) or not self.iterations:
            raise InputError(
                "fluid options: shrink_factors and iterations need the same number of levels, "
                f"got {self.shrink_factors} and {self.iterations}"
            )
        if any(_bad_int(f, 1) for f in self.shrink_factors):
            raise InputError(
                f"fluid options: shrink_factors must be integers >= 1, got {self.shrink_factors}"
            )
        if any(_bad_int(n, 0) for n in self.iterations):
            raise InputError(
                f"fluid options: iterations must be integers >= 0, got {self.iterations}"
            )
        values = self.smoothing_mm
        if isinstance(values, (tuple, list)):
            if len(values) != len(self.iterations):
                raise InputError(
                    f"fluid options: smoothing_mm gives {len(values)} values for "
                    f"{len(self.iterations)} levels ({tuple(values)})"
                )
        else:
            values = (values,)
        if any(not _positive(s) for s in values):
            raise InputError(
                f"fluid options: smoothing_mm must be finite numbers > 0 (mm), got "
                f"{readable(self.smoothing_mm)}"
            )
        u = self.update_smoothing_mm
        if isinstance(u, bool) or not isinstance(u, (int, float)) or not (0 <= u < math.inf):
            raise InputError(
                f"fluid options: update_smoothing_mm must be a finite number >= 0 (mm), "
                f"got {readable(u)}"
            )
        if not _positive(self.max_step):
            raise InputError(
                f"fluid options: max_step must be > 0 voxels, got {readable(self.max_step)}"
            )
        if _bad_int(self.histogram_levels, 2):
            raise InputError(
                f"fluid options: histogram_levels must be an integer >= 2, "
                f"got {readable(self.histogram_levels)}"
            )


def _bad_int(value, low: int) -> bool:
    return isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < low


def _positive(value) -> bool:
    return (
        not isinstance(value, bool)
        and isinstance(value, numbers.Real)
        and math.isfinite(value)
        and value > 0
    )


def _shrink(image: sitk.Image, factor: int) -> sitk.Image:
    """`image` smoothed and sampled at the centres of blocks of `factor` voxels per axis.

    ``sitk.Shrink`` is not used: for even factors it picks the voxel at a half-integer index
    by rounding, and the float error of the direction matrix decides the rounding, so an
    oblique copy of the same image is shrunk one voxel apart. Linear resampling at the block
    centres is the same on every grid orientation.
    """
    if factor == 1:
        return image
    sigma = [0.5 * factor * s for s in image.GetSpacing()]  # mm (the filter uses the spacing)
    smooth = sitk.SmoothingRecursiveGaussian(image, sigma)
    dim = image.GetDimension()
    grid = sitk.Image([max(n // factor, 1) for n in image.GetSize()], image.GetPixelID())
    grid.SetSpacing([factor * s for s in image.GetSpacing()])
    grid.SetDirection(image.GetDirection())
    grid.SetOrigin(image.TransformContinuousIndexToPhysicalPoint([(factor - 1) / 2.0] * dim))
    return sitk.Resample(smooth, grid, sitk.Transform(), sitk.sitkLinear, 0.0)


def demons_pixel_sigmas(sigma_mm: float, spacing: Sequence[float]) -> list[float]:
    """ITK demons ``StandardDeviations`` (pixels, one per axis) for a width of `sigma_mm` mm.

    Parameters
    ----------
    sigma_mm : float
        Standard deviation of the Gaussian smoothing in mm.
    spacing : sequence of float, length dim
        Voxel size (mm) of the images given to the filter, ITK (x, y[, z]) order.

    Returns
    -------
    list of float, length dim
        ``sigma_mm / spacing[j]`` for every axis ``j``.

    Raises
    ------
    InputError
        A width above :data:`MAX_PIXEL_SIGMA` pixels on some axis (ITK would return NaN).
    """
    sigmas = [float(sigma_mm) / float(s) for s in spacing]
    if max(sigmas) > MAX_PIXEL_SIGMA:
        raise InputError(
            f"fluid options: a smoothing of {float(sigma_mm):g} mm is {max(sigmas):.1f} voxels "
            f"of {min(spacing):g} mm; ITK's demons smoothing fails (NaN fields) above "
            f"{MAX_PIXEL_SIGMA:g} voxels: give a smaller smoothing_mm or resample the images "
            "to larger voxels"
        )
    return sigmas


def demons_register(
    fixed: sitk.Image, moving: sitk.Image, *, options: FluidOptions = FluidOptions()
) -> sitk.Image:
    """Diffeomorphic demons field on `fixed`'s grid mapping fixed points to `moving` points.

    Both images must lie on the same grid (resample `moving` first). Each level smooths
    the field by its width of :meth:`FluidOptions.smoothing_per_level` (mm, the same on
    every axis, converted to the level's pixels).

    Returns
    -------
    sitk.Image
        Vector image (float64, mm, ITK component order) on `fixed`'s grid (on the grid of
        the last level when its shrink factor is not 1): fixed point p corresponds to the
        moving point ``p + field(p)``.
    """
    options.check()
    field = None
    levels = zip(
        options.shrink_factors,
        options.iterations,
        options.smoothing_per_level(),
        options.update_smoothing_per_level(),
        strict=True,
    )
    for factor, iterations, sigma_mm, update_mm in levels:
        f, m = _shrink(fixed, factor), _shrink(moving, factor)
        if field is None:
            field = sitk.Image(f.GetSize(), sitk.sitkVectorFloat64, f.GetDimension())
            field.CopyInformation(f)
        else:
            field = sitk.Resample(field, f, sitk.Transform(), sitk.sitkLinear, 0.0)
        sigmas = demons_pixel_sigmas(sigma_mm, f.GetSpacing())
        demons = sitk.DiffeomorphicDemonsRegistrationFilter()
        demons.SetNumberOfIterations(int(iterations))
        demons.SetSmoothDisplacementField(True)
        demons.SetStandardDeviations(sigmas)  # pixels of this level, per axis (see module doc)
        widest = max(sigmas)
        if update_mm > 0:
            update_sigmas = demons_pixel_sigmas(update_mm, f.GetSpacing())
            demons.SetSmoothUpdateField(True)
            demons.SetUpdateFieldStandardDeviations(update_sigmas)
            widest = max(widest, max(update_sigmas))
        demons.SetMaximumError(_KERNEL_MAXIMUM_ERROR)
        # Room for the whole kernel (ITK silently truncates it at 30 coefficients a side).
        demons.SetMaximumKernelWidth(max(30, int(math.ceil(4.0 * widest)) + 2))
        spacing = f.GetSpacing()
        rms = math.sqrt(sum(v * v for v in spacing) / len(spacing))
        demons.SetMaximumUpdateStepLength(float(options.max_step) * min(spacing) / rms)
        demons.SetUseGradientType(demons.Symmetric)
        try:
            field = demons.Execute(f, m, field)
        except RuntimeError as exc:
            raise EngineError(f"SimpleITK demons failed: {str(exc).strip()[-200:]}") from None
    return field


def _match_histogram(moving: sitk.Image, reference: sitk.Image, levels: int) -> sitk.Image:
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
    progress: bool = True,
) -> list[sitk.Transform]:
    """Per image the transform reference -> image ``[A_i, field_i]`` (``A_i(D_i(p))``).

    Parameters
    ----------
    images : sequence of sitk.Image, length n_images
        Scalar images (any grids) of the reference's dimension.
    reference : sitk.Image
        The fixed image: the transforms map its points (mm) to each image's.
    affines : sequence of sitk.Transform, length n_images
        Each image's affine reference -> image ``A_i``.
    options : FluidOptions
    engine : {"simpleitk", "ants"}
        Diffeomorphic demons, or ANTs SyN (needs antspyx).
    seed : int
        Engine ``"ants"`` seeds antsRegistration of image ``i`` with ``seed + i``; demons
        is deterministic.
    reference_index : int, optional
        The reference's index in `images`: that image keeps its identity affine.
    progress : bool
        A progress bar on stderr.

    Returns
    -------
    list of sitk.Transform, length n_images
        Reference points -> image points (mm, LPS).
    """
    if engine == "ants":
        ants = import_ants()
    else:  # refuse options or a smoothing ITK cannot do before any work
        options.check()
        levels = zip(options.shrink_factors, options.smoothing_per_level(), strict=True)
        for factor, sigma_mm in levels:
            demons_pixel_sigmas(sigma_mm, [factor * s for s in reference.GetSpacing()])
    out = []
    for i, (img, aff) in progress_bar(
        list(enumerate(zip(images, affines, strict=True))),
        desc="fluid",
        total=len(images),
        enabled=progress,
    ):
        if i == reference_index:
            out.append(aff)
            continue
        pre = _match_histogram(resample(img, reference, aff), reference, options.histogram_levels)
        if engine == "ants":
            warp = ants_syn(ants, reference, pre, seed=seed + i)
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


def seeded_ants_registration(ants, fixed, moving, *, seed: int, **kwargs) -> dict:
    """``ants.registration(fixed, moving, **kwargs)`` with antsRegistration's random seed set.

    ANTs reads a seed of 0 as "seed from the clock", so it receives ``engine_seed(seed)``
    (``seed + 1``). antspyx 0.6 ignores a ``random_seed`` argument (it disappears into
    ``**kwargs``) and reads the seed that it passes as ``--random-seed`` from
    ``ants.config``; its public ``set_ants_deterministic`` changes process-wide settings and
    refuses non-"Repro" transforms. The seed is therefore set on ``ants.config`` for this
    call only and restored afterwards; versions whose ``registration`` takes
    ``random_seed`` get it there.

    Raises
    ------
    EngineError
        This antspyx offers no way to seed antsRegistration, or the registration failed.
    """
    seed = engine_seed(seed)
    try:
        if "random_seed" in inspect.signature(ants.registration).parameters:
            return ants.registration(fixed, moving, random_seed=seed, **kwargs)
        config = getattr(ants, "config", None)
        if config is None or not hasattr(config, "_random_seed"):
            raise EngineError(
                f"antspyx {getattr(ants, '__version__', '?')}: no way to seed antsRegistration "
                "(expected ants.config._random_seed or a random_seed argument)"
            )
        saved = config._random_seed
        config._random_seed = seed
        try:
            return ants.registration(fixed, moving, **kwargs)
        finally:
            config._random_seed = saved
    except (RuntimeError, ValueError) as exc:
        raise EngineError(f"antsRegistration failed: {str(exc).strip()[-200:]}") from None


def ants_syn(ants, fixed: sitk.Image, moving: sitk.Image, *, seed: int) -> sitk.Transform:
    """SyN of `moving` to `fixed` (same grid) with antspyx, as one SimpleITK transform.

    Returns
    -------
    sitk.Transform
        Maps `fixed` points to `moving` points (mm, LPS): antspyx's ``fwdtransforms``
        chain, whose first file acts first (:func:`itk_nrreval.io.transforms.chain_transform`).
    """
    with tempfile.TemporaryDirectory(prefix="nrreval-ants-") as tmp:
        paths = []
        for name, img in (("fixed", fixed), ("moving", moving)):
            paths.append(f"{tmp}/{name}.nii.gz")
            sitk.WriteImage(img, paths[-1])
        out = seeded_ants_registration(
            ants,
            ants.image_read(paths[0]),
            ants.image_read(paths[1]),
            seed=seed,
            type_of_transform="SyNOnly",
            outprefix=f"{tmp}/out_",
        )
        return chain_transform(out["fwdtransforms"])  # read before the folder goes
