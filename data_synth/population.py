"""Populations of brain-like images with known true correspondence.

Each subject is the template moved by a known transform and given its own intensities:

* a random diffeomorphism ``phi = exp(v)``: a smooth stationary velocity field ``v`` (white
  noise smoothed by a Gaussian of `smoothness_mm`, tapered to zero near the grid border and
  scaled to an RMS length of `warp_mm`) integrated by scaling and squaring, with
  ``phi^-1 = exp(-v)`` from the same integration of ``-v`` (then polished by three fixed-point
  steps, so the round trip is exact to a small fraction of a voxel);
* a random pose ``A`` (affine: small rotation, per-axis scale and translation about the grid
  centre);
* intensity changes: a global scale, a smooth multiplicative bias field and Rician noise.

With several ``contrasts`` (``("t1", "t2")``: :data:`data_synth.phantom.CONTRASTS`) every
subject is imaged in each: the same anatomy, warp and pose (one true transform for all its
images), each contrast painted from its own template of the same anatomy and given its own
global scale, bias field and noise, as separate acquisitions would be. The geometry and the
T1 intensities are drawn from the subject's stream exactly as for a T1-only population (so
adding a contrast changes no T1 image); contrast c's intensities come from the child stream
``SeedSequence(entropy, spawn_key=(*subject_key, c))``, c its index in ``CONTRASTS``, so a
subject's image in one contrast does not depend on which other contrasts are made.

Transform convention (ITK): a transform maps reference points to image points. The subject's
``template_to_subject`` transform ``T = A o phi`` maps a template point ``p`` to the
corresponding subject point, so that ``subject(T(p)) = template(p)``; resampling the subject
through ``T`` on the template grid is the perfect registration. ``subject_to_template`` is
``T^-1 = phi^-1 o A^-1``; the subject is made by resampling the template through it on the
subject grid. As SimpleITK composites: ``CompositeTransform([A, phi])`` (the last acts first).

Arrays follow SimpleITK's numpy order, ``(z, y, x)``; displacement vectors hold (x, y[, z])
components in mm; physical space is LPS.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType

import numba
import numpy as np
import SimpleITK as sitk

from .mni import make_mni
from .phantom import CONTRASTS, Phantom, make_phantom

__all__ = [
    "Subject",
    "Population",
    "PerfectRegistration",
    "make_population",
    "perfect_registration",
    "perfectly_registered_arrays",
    "velocity_exponential",
]

_KINDS = ("phantom", "mni")


@dataclass(frozen=True)
class Subject:
    """One synthetic subject.

    Attributes
    ----------
    image : sitk.Image
        ``sitkFloat32`` intensities on the subject's grid (same size, spacing and origin as the
        template grid; the pose moves the anatomy within it), in the population's first
        contrast (``images[contrasts[0]]``).
    labels : sitk.Image
        ``sitkUInt8`` label map on the same grid (values of :attr:`Population.label_names`).
    template_to_subject : sitk.CompositeTransform
        ``A o phi``: maps template points (mm) to subject points; resample the subject through
        it onto the template grid to bring it into the template frame.
    subject_to_template : sitk.CompositeTransform
        ``phi^-1 o A^-1``: maps subject points to template points.
    images : Mapping[str, sitk.Image]
        Contrast -> the subject's image in it, for every contrast of the population; all on
        the same grid, of the same anatomy, related to the template by the same transforms.
    """

    image: sitk.Image
    labels: sitk.Image
    template_to_subject: sitk.CompositeTransform
    subject_to_template: sitk.CompositeTransform
    images: Mapping[str, sitk.Image]


@dataclass(frozen=True)
class Population:
    """A template and N subjects made from it with known transforms.

    Attributes
    ----------
    kind : {"phantom", "mni"}
    template : sitk.Image
        ``sitkFloat32`` template image (the common frame of the true correspondence), in the
        first contrast.
    template_labels : sitk.Image
        ``sitkUInt8`` template label map.
    label_names : Mapping[int, str]
        Label value -> name, for the labels present in the template.
    subjects : tuple of Subject
    seed : int
    parameters : Mapping[str, float]
        The generation parameters (``warp_mm``, ``smoothness_mm``, ...) for the record.
    contrasts : tuple of str
        The contrasts every subject is imaged in (``("t1",)`` by default).
    templates : Mapping[str, sitk.Image]
        Contrast -> the template in that contrast (one anatomy, one grid).
    """

    kind: str
    template: sitk.Image
    template_labels: sitk.Image
    label_names: Mapping[int, str]
    subjects: tuple[Subject, ...]
    seed: int
    parameters: Mapping[str, float]
    contrasts: tuple[str, ...]
    templates: Mapping[str, sitk.Image]

    def __len__(self) -> int:
        return len(self.subjects)


@dataclass(frozen=True)
class PerfectRegistration:
    """Every subject resampled into the template frame through its true transform.

    Attributes
    ----------
    images : tuple of sitk.Image
        ``sitkFloat32``, on the template grid.
    labels : tuple of sitk.Image
        ``sitkUInt8``, on the template grid (nearest-neighbour resampling).
    """

    images: tuple[sitk.Image, ...]
    labels: tuple[sitk.Image, ...]


def make_population(
    kind: str = "phantom",
    *,
    dim: int = 2,
    n: int = 36,
    seed: int = 0,
    spacing: float | None = None,
    size: int | tuple[int, ...] | None = None,
    warp_mm: float = 4.0,
    smoothness_mm: float = 20.0,
    rotation_deg: float = 4.0,
    scale_sd: float = 0.04,
    translation_mm: float = 4.0,
    intensity_sd: float = 0.1,
    bias_sd: float = 0.1,
    noise: float = 0.02,
    contrasts: tuple[str, ...] | list[str] = ("t1",),
) -> Population:
    """Make a template and `n` subjects with known true transforms.

    Parameters
    ----------
    kind : {"phantom", "mni"}
        The analytic phantom (:func:`data_synth.phantom.make_phantom`, 26 structures in 3D,
        14 in the 2D slice) or the MNI152 2009a template with grey matter / white matter /
        CSF-other labels (:func:`data_synth.mni.make_mni`).
    dim : {2, 3}
        2D axial slice (141 x 141 by default) or 3D volume (2 mm voxels by default).
    n : int
        Number of subjects, >= 1.
    seed : int
        Seed of the whole population; subject ``i`` draws from its own stream
        (``SeedSequence(seed).spawn(n)[i]``), so subject ``i`` does not depend on `n`.
    spacing, size
        The template grid (isotropic voxel size in mm; voxels in (x, y[, z]) order); defaults
        depend on `kind` and `dim`.
    warp_mm : float
        RMS length (mm) of the velocity field over the untapered interior of the grid; the
        displacements of ``exp(v)`` are about this size. 0 gives no non-rigid warp.
    smoothness_mm : float
        Standard deviation (mm) of the Gaussian smoothing the velocity noise.
    rotation_deg, scale_sd, translation_mm : float
        Standard deviations of the pose: rotation angles (degrees, one in 2D, three in 3D),
        log per-axis scale factors, and translations (mm per axis).
    intensity_sd, bias_sd : float
        Standard deviations of the log global intensity scale and of the log bias field.
    noise : float
        Rician noise level as a fraction of the template's 99th-percentile intensity (each
        contrast's own template).
    contrasts : sequence of {"t1", "t2"}
        The contrasts to image every subject in (module docstring); the first is
        ``Subject.image`` and ``Population.template``.

    Returns
    -------
    Population

    Raises
    ------
    ValueError
        An unknown `kind`, a `dim` other than 2 or 3, ``n < 1``, a negative / non-finite
        amplitude, or `contrasts` empty, repeated or unknown; the message names the argument
        and the accepted values.
    FileNotFoundError
        ``kind="mni"`` without nilearn's data files.
    """
    _check_sizes(kind, dim, n, seed)
    params = {
        "warp_mm": warp_mm,
        "smoothness_mm": smoothness_mm,
        "rotation_deg": rotation_deg,
        "scale_sd": scale_sd,
        "translation_mm": translation_mm,
        "intensity_sd": intensity_sd,
        "bias_sd": bias_sd,
        "noise": noise,
    }
    for name, value in params.items():
        if not (
            isinstance(value, (int, float, np.floating)) and math.isfinite(value) and value >= 0
        ):
            raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
    if smoothness_mm <= 0:
        raise ValueError(f"smoothness_mm must be > 0, got {smoothness_mm!r}")
    contrasts = _check_contrasts(contrasts)

    maker = make_phantom if kind == "phantom" else make_mni
    tmpls: dict[str, Phantom] = {
        c: maker(dim=dim, spacing=spacing, size=size, contrast=c) for c in contrasts
    }
    ref_values = {
        c: float(np.percentile(sitk.GetArrayViewFromImage(t.image), 99)) for c, t in tmpls.items()
    }
    first = tmpls[contrasts[0]]
    streams = np.random.SeedSequence(int(seed)).spawn(int(n))
    subjects = tuple(
        _make_subject(
            {c: t.image for c, t in tmpls.items()},
            first.labels,
            s,
            ref_values=ref_values,
            **params,
        )
        for s in streams
    )
    return Population(
        kind=kind,
        template=first.image,
        template_labels=first.labels,
        label_names=first.label_names,
        subjects=subjects,
        seed=int(seed),
        parameters=MappingProxyType({k: float(v) for k, v in params.items()}),
        contrasts=contrasts,
        templates=MappingProxyType({c: t.image for c, t in tmpls.items()}),
    )


def _check_sizes(kind, dim, n, seed) -> None:
    """Refuse an unknown `kind`, a `dim` other than 2 or 3, ``n < 1`` or a negative seed."""
    if kind not in _KINDS:
        raise ValueError(f"kind must be one of {_KINDS}, got {kind!r}")
    if dim not in (2, 3) or isinstance(dim, bool):
        raise ValueError(f"dim must be 2 or 3, got {dim!r}")
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"n must be a positive number of subjects, got {n!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")


def _check_contrasts(contrasts) -> tuple[str, ...]:
    if isinstance(contrasts, str):
        contrasts = (contrasts,)
    out = tuple(contrasts)
    if not out or len(set(out)) != len(out) or not set(out) <= set(CONTRASTS):
        raise ValueError(
            f"contrasts must be distinct names from {CONTRASTS}, at least one, got {contrasts!r}"
        )
    return tuple(str(c) for c in out)


def perfect_registration(
    population: Population, *, contrast: str | None = None
) -> PerfectRegistration:
    """Resample every subject into the template frame through its true transform.

    Images are resampled linearly, labels by nearest neighbour, both onto the template grid
    with ``subject.template_to_subject`` (the paper's starting point for Section IV).
    `contrast` picks the subjects' images (default: the population's first contrast).
    """
    if contrast is not None and contrast not in population.contrasts:
        raise ValueError(
            f"contrast must be one of the population's {population.contrasts}, got {contrast!r}"
        )
    contrast = population.contrasts[0] if contrast is None else contrast
    ref = population.template
    images, labels = [], []
    for s in population.subjects:
        moving = s.images[contrast]
        images.append(sitk.Resample(moving, ref, s.template_to_subject, sitk.sitkLinear, 0.0))
        labels.append(
            sitk.Resample(
                s.labels, ref, s.template_to_subject, sitk.sitkNearestNeighbor, 0, sitk.sitkUInt8
            )
        )
    return PerfectRegistration(tuple(images), tuple(labels))


def perfectly_registered_arrays(
    kind: str = "phantom",
    *,
    n: int = 10,
    seed: int = 0,
    dim: int = 2,
    with_spacing: bool = False,
):
    """A generated population's :func:`perfect_registration` as numpy arrays.

    The registered, labelled set the paper perturbs in Section IV
    (:func:`itk_nrreval.experiments.perturbation.validate`): :func:`make_population` (2D 141 x 141,
    or 3D at 2 mm), every subject resampled into the template frame through its true transform.

    Parameters
    ----------
    kind : {"phantom", "mni"}
    n : int
        Number of subjects, >= 1.
    seed : int
        Seed of the population (as :func:`make_population`).
    dim : {2, 3}
    with_spacing : bool
        Also return the template grid's voxel size.

    Returns
    -------
    images : ndarray of shape (n, *spatial), float64
        Numpy order ``(z, y, x)``; intensities as the population's.
    labels : ndarray of int64 of shape (n, *spatial)
    spacing : tuple of float
        Only with `with_spacing`: the voxel size, mm, ITK order ``(x, y[, z])``.
    """
    population = make_population(kind, dim=dim, n=n, seed=seed)
    registered = perfect_registration(population)
    images = np.stack([sitk.GetArrayFromImage(i) for i in registered.images]).astype(np.float64)
    labels = np.stack([sitk.GetArrayFromImage(i) for i in registered.labels]).astype(np.int64)
    if with_spacing:
        return images, labels, tuple(float(s) for s in population.template.GetSpacing())
    return images, labels


# --------------------------------------------------------------------------------------------
# Random fields and the velocity exponential


def _smooth_noise(
    rng: np.random.Generator, grid: sitk.Image, *, n_components: int, sigma_mm: float
) -> np.ndarray:
    """Gaussian-smoothed white noise on `grid`, unit RMS per component.

    Noise is drawn on a coarse grid (spacing ``sigma_mm / 2``, at least the grid's, with a
    margin of ``3 sigma``), smoothed there, and interpolated onto `grid` with a separable cubic
    (Keys) kernel, so the cost does not grow with the smoothness. Assumes an identity direction.

    Returns
    -------
    ndarray of shape (*numpy_shape, n_components)
    """
    from scipy.ndimage import gaussian_filter

    spacing = np.asarray(grid.GetSpacing())
    size = np.asarray(grid.GetSize())
    coarse_h = max(sigma_mm / 2.0, float(spacing.min()))
    margin = 3.0 * sigma_mm
    csize = np.ceil(((size - 1) * spacing + 2 * margin) / coarse_h).astype(int) + 1
    # One interpolation matrix per axis, numpy order: fine positions in coarse index units.
    mats = [
        _cubic_matrix((margin + spacing[ax] * np.arange(size[ax])) / coarse_h, int(csize[ax]))
        for ax in reversed(range(len(size)))
    ]
    out = np.empty((*reversed(size.tolist()), n_components))
    for c in range(n_components):
        field = gaussian_filter(
            rng.standard_normal(tuple(reversed(csize.tolist()))), sigma_mm / coarse_h
        )
        for ax, m in enumerate(mats):
            field = np.moveaxis(np.tensordot(m, field, axes=([1], [ax])), 0, ax)
        out[..., c] = field / max(float(np.sqrt(np.mean(field**2))), 1e-12)
    return out


def _cubic_matrix(positions: np.ndarray, n: int) -> np.ndarray:
    """Keys cubic interpolation weights (a = -0.5), shape ``(len(positions), n)``."""
    base = np.floor(positions).astype(int)
    m = np.zeros((len(positions), n))
    rows = np.arange(len(positions))
    for offset in (-1, 0, 1, 2):
        t = np.abs(positions - (base + offset))
        w = np.where(
            t <= 1,
            1.5 * t**3 - 2.5 * t**2 + 1,
            np.where(t < 2, -0.5 * t**3 + 2.5 * t**2 - 4 * t + 2, 0),
        )
        np.add.at(m, (rows, np.clip(base + offset, 0, n - 1)), w)
    return m


def _taper(grid: sitk.Image, *, fraction: float = 0.2) -> np.ndarray:
    """A window, numpy shape, equal to 1 inside and falling smoothly to 0 at the grid border.

    Each axis contributes ``sin^2`` ramps over the outer `fraction` of its length.
    """
    w = np.ones(tuple(reversed(grid.GetSize())))
    for axis_np, n in enumerate(reversed(grid.GetSize())):
        t = np.arange(n) / max(n - 1, 1)
        edge = np.minimum(t, 1.0 - t) / fraction
        ramp = np.sin(0.5 * np.pi * np.clip(edge, 0.0, 1.0)) ** 2
        shape = [1] * w.ndim
        shape[axis_np] = n
        w = w * ramp.reshape(shape)
    return w


def _field_image(u: np.ndarray, grid: sitk.Image) -> sitk.Image:
    img = sitk.GetImageFromArray(u, isVector=True)
    img.CopyInformation(grid)
    return img


def _compose(a: np.ndarray, b: np.ndarray, grid: sitk.Image) -> np.ndarray:
    """``a`` sampled at ``x + b(x)`` for every node ``x`` of `grid` (linear; zero outside).

    This is what ITK's ``DisplacementFieldTransform`` does with a linear interpolator, so the
    fields built from it are exactly the ones the written transforms apply. Assumes an
    identity direction (the grids of this module).
    """
    inv_spacing = 1.0 / np.asarray(grid.GetSpacing(), dtype=np.float64)  # ITK order
    a = np.ascontiguousarray(a)
    b = np.ascontiguousarray(b)
    return _compose2(a, b, inv_spacing) if a.ndim == 3 else _compose3(a, b, inv_spacing)


@numba.njit(cache=True)
def _compose2(a, b, inv_spacing):  # pragma: no cover - compiled
    ny, nx, nc = a.shape
    out = np.zeros_like(a)
    for i in range(ny):
        for j in range(nx):
            y = i + b[i, j, 1] * inv_spacing[1]
            x = j + b[i, j, 0] * inv_spacing[0]
            if y < 0 or x < 0 or y > ny - 1 or x > nx - 1:
                continue
            i0 = min(int(y), ny - 2)
            j0 = min(int(x), nx - 2)
            fy = y - i0
            fx = x - j0
            for c in range(nc):
                out[i, j, c] = (1 - fy) * ((1 - fx) * a[i0, j0, c] + fx * a[i0, j0 + 1, c]) + fy * (
                    (1 - fx) * a[i0 + 1, j0, c] + fx * a[i0 + 1, j0 + 1, c]
                )
    return out


@numba.njit(cache=True)
def _compose3(a, b, inv_spacing):  # pragma: no cover - compiled
    nz, ny, nx, nc = a.shape
    out = np.zeros_like(a)
    for k in range(nz):
        for i in range(ny):
            for j in range(nx):
                z = k + b[k, i, j, 2] * inv_spacing[2]
                y = i + b[k, i, j, 1] * inv_spacing[1]
                x = j + b[k, i, j, 0] * inv_spacing[0]
                if z < 0 or y < 0 or x < 0 or z > nz - 1 or y > ny - 1 or x > nx - 1:
                    continue
                k0 = min(int(z), nz - 2)
                i0 = min(int(y), ny - 2)
                j0 = min(int(x), nx - 2)
                fz = z - k0
                fy = y - i0
                fx = x - j0
                for c in range(nc):
                    v0 = (1 - fy) * (
                        (1 - fx) * a[k0, i0, j0, c] + fx * a[k0, i0, j0 + 1, c]
                    ) + fy * ((1 - fx) * a[k0, i0 + 1, j0, c] + fx * a[k0, i0 + 1, j0 + 1, c])
                    v1 = (1 - fy) * (
                        (1 - fx) * a[k0 + 1, i0, j0, c] + fx * a[k0 + 1, i0, j0 + 1, c]
                    ) + fy * (
                        (1 - fx) * a[k0 + 1, i0 + 1, j0, c] + fx * a[k0 + 1, i0 + 1, j0 + 1, c]
                    )
                    out[k, i, j, c] = (1 - fz) * v0 + fz * v1
    return out


def velocity_exponential(
    velocity: np.ndarray, grid: sitk.Image, *, polish: int = 3
) -> tuple[np.ndarray, np.ndarray]:
    """Integrate a stationary velocity field by scaling and squaring, both ways.

    Parameters
    ----------
    velocity : ndarray of shape (*numpy_shape, dim)
        Velocity in mm, components in ITK order (x, y[, z]), on `grid` (numpy order).
    grid : sitk.Image
        The grid (size, spacing, origin, direction) of the field.
    polish : int
        Fixed-point steps ``w <- -u(x + w(x))`` refining the inverse after integration.

    Returns
    -------
    forward, inverse : ndarray of shape (*numpy_shape, dim)
        Displacements (mm) of ``exp(v)`` and ``exp(-v)``: ``exp(v)(x) = x + forward(x)``.

    Notes
    -----
    ``exp(v) = (id + v / 2^K)^(2^K)``, with ``K`` chosen so that ``max |v| / 2^K`` is below a
    half voxel; each squaring is ``u <- u + u(x + u(x))`` with linear interpolation.
    Points mapped outside the grid see zero displacement, so `velocity` should vanish near
    the border.
    """
    h = float(min(grid.GetSpacing()))
    vmax = float(np.sqrt((velocity**2).sum(axis=-1)).max()) if velocity.size else 0.0
    steps = int(math.ceil(math.log2(max(vmax / (0.5 * h), 1.0))))
    results = []
    for sign in (1.0, -1.0):
        u = sign * velocity / 2.0**steps
        for _ in range(steps):
            u = u + _compose(u, u, grid)
        results.append(u)
    forward, inverse = results
    for _ in range(polish):
        inverse = -_compose(forward, inverse, grid)
    return forward, inverse


# --------------------------------------------------------------------------------------------
# One subject


def _random_pose(
    rng: np.random.Generator, grid: sitk.Image, *, rotation_deg, scale_sd, translation_mm
) -> sitk.AffineTransform:
    dim = grid.GetDimension()
    if dim == 2:
        (a,) = np.deg2rad(rng.normal(0.0, rotation_deg, 1))
        rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    else:
        angles = np.deg2rad(rng.normal(0.0, rotation_deg, 3))
        rot = np.eye(3)
        for axis, a in enumerate(angles):
            i, j = [k for k in range(3) if k != axis]
            r = np.eye(3)
            r[i, i] = r[j, j] = np.cos(a)
            r[i, j], r[j, i] = -np.sin(a), np.sin(a)
            rot = r @ rot
    scales = np.exp(rng.normal(0.0, scale_sd, dim))
    shift = rng.normal(0.0, translation_mm, dim)
    pose = sitk.AffineTransform(dim)
    size = np.asarray(grid.GetSize())
    center = grid.TransformContinuousIndexToPhysicalPoint(((size - 1) / 2.0).tolist())
    pose.SetCenter(center)
    pose.SetMatrix((rot @ np.diag(scales)).ravel().tolist())
    pose.SetTranslation(shift.tolist())
    return pose


def _field_grid(grid: sitk.Image, *, smoothness_mm: float) -> sitk.Image:
    """The grid of the displacement fields: the image grid's box, spacing ``min(voxel, sigma / 8)``.

    The fields are smooth on the scale of `smoothness_mm` (sigma), so nodes ``sigma / 8`` apart
    carry them to well within the round-trip tolerance while linear interpolation between
    nodes (as ITK applies them) stays accurate; for fine images the field shares the image
    grid. The box starts at the image origin and covers the whole image grid.
    """
    spacing = np.asarray(grid.GetSpacing())
    size = np.asarray(grid.GetSize())
    h = np.minimum(spacing, smoothness_mm / 8.0)
    n = np.ceil((size - 1) * spacing / h - 1e-9).astype(int) + 1
    out = sitk.Image(n.tolist(), sitk.sitkFloat32)
    out.SetSpacing(h.tolist())
    out.SetOrigin(grid.GetOrigin())
    out.SetDirection(grid.GetDirection())
    return out


def _displacement_transform(u: np.ndarray, grid: sitk.Image) -> sitk.DisplacementFieldTransform:
    # The transform takes its image over: hand it a fresh float64 copy.
    return sitk.DisplacementFieldTransform(sitk.Cast(_field_image(u, grid), sitk.sitkVectorFloat64))


def _make_subject(
    templates: Mapping[str, sitk.Image],
    template_labels: sitk.Image,
    stream: np.random.SeedSequence,
    *,
    ref_values: Mapping[str, float],
    warp_mm: float,
    smoothness_mm: float,
    rotation_deg: float,
    scale_sd: float,
    translation_mm: float,
    intensity_sd: float,
    bias_sd: float,
    noise: float,
) -> Subject:
    rng = np.random.default_rng(stream)
    grid = next(iter(templates.values()))
    dim = grid.GetDimension()
    field_grid = _field_grid(grid, smoothness_mm=smoothness_mm)
    # Draw everything first, in a fixed order, so the stream does not depend on the options:
    # the geometry, then the T1 intensity changes (drawn even when T1 is not asked for).
    vel_noise = _smooth_noise(rng, field_grid, n_components=dim, sigma_mm=smoothness_mm)
    pose = _random_pose(
        rng, grid, rotation_deg=rotation_deg, scale_sd=scale_sd, translation_mm=translation_mm
    )
    draws = {}
    for c, name in enumerate(CONTRASTS):
        crng = rng if c == 0 else _contrast_rng(stream, c)
        if c == 0 or name in templates:
            gain = float(np.exp(crng.normal(0.0, intensity_sd)))
            bias = _smooth_noise(crng, grid, n_components=1, sigma_mm=60.0)[..., 0]
            draws[name] = (gain, bias, crng.integers(2**32))

    window = _taper(field_grid)
    velocity = vel_noise * window[..., None]
    interior = window >= 1.0 - 1e-12
    rms = float(np.sqrt(np.mean(np.sum(velocity[interior] ** 2, axis=-1))))
    velocity *= warp_mm / max(rms, 1e-12)
    forward, inverse = velocity_exponential(velocity, field_grid)

    t_to_s = sitk.CompositeTransform([pose, _displacement_transform(forward, field_grid)])
    s_to_t = sitk.CompositeTransform(
        [_displacement_transform(inverse, field_grid), pose.GetInverse()]
    )

    images = {}
    for name, template in templates.items():
        gain, bias, noise_seed = draws[name]
        moved = sitk.Resample(template, grid, s_to_t, sitk.sitkLinear, 0.0, sitk.sitkFloat32)
        arr = np.clip(sitk.GetArrayFromImage(moved).astype(np.float64), 0.0, None)
        arr *= gain * np.exp(bias_sd * bias)
        nrng = np.random.default_rng(noise_seed)
        sd = noise * ref_values[name]
        arr = np.sqrt(
            (arr + sd * nrng.standard_normal(arr.shape)) ** 2
            + (sd * nrng.standard_normal(arr.shape)) ** 2
        )
        image = sitk.GetImageFromArray(arr.astype(np.float32))
        image.CopyInformation(grid)
        images[name] = image
    labels = _warp_labels(template_labels, s_to_t)
    first = next(iter(images.values()))
    return Subject(first, labels, t_to_s, s_to_t, MappingProxyType(images))


def _contrast_rng(stream: np.random.SeedSequence, index: int) -> np.random.Generator:
    """The intensity stream of contrast number `index` (>= 1) of a subject: a child stream."""
    child = np.random.SeedSequence(stream.entropy, spawn_key=(*stream.spawn_key, index))
    return np.random.default_rng(child)


def _warp_labels(labels: sitk.Image, transform: sitk.Transform) -> sitk.Image:
    """Resample a label map through `transform` onto its own grid, without blocky aliasing.

    Equivalent to resampling the one-hot membership of every label linearly and taking the
    argmax per voxel (the label with the largest total interpolation weight among the
    surrounding template voxels; outside the template grid counts as background), computed
    from the corner labels only so the cost does not grow with the number of labels.
    """
    dim = labels.GetDimension()
    disp = sitk.TransformToDisplacementField(
        transform,
        sitk.sitkVectorFloat64,
        labels.GetSize(),
        labels.GetOrigin(),
        labels.GetSpacing(),
        labels.GetDirection(),
    )
    shape_np = tuple(reversed(labels.GetSize()))
    # Mapped points as continuous indices, numpy axis order (identity direction assumed).
    spacing = np.asarray(labels.GetSpacing()[::-1])
    offset = np.moveaxis(np.indices(shape_np, dtype=np.float64), 0, -1)
    cidx = offset + sitk.GetArrayViewFromImage(disp)[..., ::-1] / spacing
    arr = np.ascontiguousarray(sitk.GetArrayViewFromImage(labels))
    flat = np.ascontiguousarray(cidx.reshape(-1, dim))
    best = _vote(arr.reshape(-1), np.asarray(shape_np, dtype=np.int64), flat)
    out = sitk.GetImageFromArray(best.reshape(shape_np).astype(np.uint8))
    out.CopyInformation(labels)
    return out


@numba.njit(cache=True)
def _vote(labels, shape, cidx):  # pragma: no cover - compiled
    """Per point, the label with the largest total linear-interpolation weight (0 outside)."""
    n, dim = cidx.shape
    ncorner = 1 << dim
    out = np.zeros(n, dtype=labels.dtype)
    labs = np.zeros(ncorner, dtype=labels.dtype)
    ws = np.zeros(ncorner)
    strides = np.ones(dim, dtype=np.int64)
    for d in range(dim - 2, -1, -1):
        strides[d] = strides[d + 1] * shape[d + 1]
    for p in range(n):
        for c in range(ncorner):
            w = 1.0
            flat = 0
            inside = True
            for d in range(dim):
                x = cidx[p, d]
                i0 = int(np.floor(x))
                f = x - i0
                i = i0 + ((c >> d) & 1)
                w *= f if (c >> d) & 1 else 1.0 - f
                if i < 0 or i >= shape[d]:
                    inside = False
                else:
                    flat += i * strides[d]
            ws[c] = w
            labs[c] = labels[flat] if inside else 0
        best_score = -1.0
        for c in range(ncorner):
            score = 0.0
            for c2 in range(ncorner):
                if labs[c2] == labs[c]:
                    score += ws[c2]
            if score > best_score:
                best_score = score
                out[p] = labs[c]
    return out
