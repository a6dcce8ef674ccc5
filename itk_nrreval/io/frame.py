"""The common frame: every registration's results resampled onto one reference grid.

Each registration R of the N images has its own reference frame (its ``reference`` image's
grid) and per image i a transform ``T_i^R`` from that frame into image i (reference points
to image points, mm, LPS). One registration, C, is the common frame (paper, Section V-D).
R is brought into it by a transform F from the common frame into R's frame; image i is then
resampled onto the common grid with ``T_i^R o F`` -- in SimpleITK list order
``CompositeTransform([T_i^R, F])`` (F acts first; ANTs order ``[F, T_i^R]``).

F comes from, in order (:func:`frame_mapping`):

1. ``frame_transform``: a file given in the manifest;
2. ``reference_index: k``: R's reference is training image k, so F = ``T_k^C``;
3. otherwise the mean over the group of the per-image estimates
   ``F_i = (T_i^R)^-1 o T_i^C``, realised as a displacement field on the common grid (the
   per-image point maps ``F_i(p)`` are averaged voxel by voxel).

Whichever way F is obtained, the spread of the per-image estimates about it,
``|F_i(p) - F(p)|`` in mm, is reported (mean and max over images and voxels of the common
grid, inside the mask when one is given) as the registration's frame consistency.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass

import numba
import numpy as np
import SimpleITK as sitk

from .._errors import InputError
from .._progress import progress_bar
from ._images import Geometry, InMemoryImage, read_image
from ._memberships import resample_label_memberships
from .manifest import Manifest, ManifestRegistration
from .transforms import (
    PointwiseInverse,
    TransformPieces,
    chain_transform,
    composed_displacement,
    displacement_field,
    field_transform,
    flatten,
    has_only_fields,
    is_linear,
    leaves,
    transform_pieces,
)

__all__ = [
    "FrameMapping",
    "common_reference",
    "read_chains",
    "frame_estimates",
    "frame_estimate",
    "frame_method",
    "frame_mapping",
    "needs_inversion_grid",
    "points_minus_grid",
    "distance_sums",
    "in_steps",
    "from_steps",
    "resampling_transform",
    "resample_onto",
    "resample_images",
    "resample_memberships",
    "label_values",
    "ESTIMATE_FIELD_STEP",
    "ESTIMATE_REFINE_STEPS",
]

_INTERPOLATORS = {"linear": sitk.sitkLinear, "bspline": sitk.sitkBSpline}
#: Each frame estimate inverts the displacement fields of ``T_i^R`` on every
#: ``ESTIMATE_FIELD_STEP``-th node of their grids and refines that inverse by
#: ``ESTIMATE_REFINE_STEPS`` fixed-point steps at every voxel of the common grid it is
#: evaluated at (``field_step`` and ``refine_steps`` of
#: :class:`itk_nrreval.io.transforms.PointwiseInverse`): at 1 mm about 3 s of one core instead
#: of 13 s (``benchmarks/bench_image_task.py``). On a smooth 3 mm field on an oblique,
#: anisotropic grid, ``T^R(F(p)) = T^C(p)`` to 0.01 mm at every voxel whose preimage lies in
#: the field's grid (tests/test_frame.py; issue 30). Every fourth node would save another
#: second at 1 mm, but on small grids (a 2D 32-pixel phantom) its frame estimates missed by
#: 0.017 mm (0.015 mm with five refinement steps) against the tests' 0.015 mm.
ESTIMATE_FIELD_STEP = 2
ESTIMATE_REFINE_STEPS = 3
_METHODS = ("common", "frame_transform", "reference_index", "mean")


@dataclass(frozen=True)
class FrameMapping:
    """How one registration's frame is reached from the common frame.

    Attributes
    ----------
    name : str
        The registration.
    method : {"common", "frame_transform", "reference_index", "mean"}
        Where F came from (see the module docstring).
    transform : sitk.Transform
        F: common-frame points -> this registration's reference-frame points (mm, LPS).
    spread_mean_mm, spread_max_mm : float
        Mean and max of ``|F_i(p) - F(p)|`` (mm) over images i and common-grid voxels p;
        0 for the common registration itself; NaN when not computed.
    per_image_mm : tuple of float
        Each image's mean of ``|F_i(p) - F(p)|`` over the voxels p (mm), in manifest order
        (a subject whose estimate stands out: :mod:`itk_nrreval.measures.subject_qc`); empty for the
        common registration.
    """

    name: str
    method: str
    transform: sitk.Transform
    spread_mean_mm: float
    spread_max_mm: float
    per_image_mm: tuple[float, ...] = ()

    def to_dict(self) -> dict:
        return {
            "method": self.method,
            "spread_mean_mm": self.spread_mean_mm,
            "spread_max_mm": self.spread_max_mm,
        }


def common_reference(manifest: Manifest) -> sitk.Image:
    """The common registration's reference image (its grid is the common grid)."""
    return read_image(
        manifest.registrations[manifest.common_frame].reference, what="reference image"
    )


def read_chains(manifest: Manifest, name: str) -> list[sitk.Transform]:
    """Registration `name`'s per-image transforms ``T_i^R``, one sitk transform per image."""
    return [chain_transform(c) for c in manifest.registrations[name].transforms]


def _identity(dim: int) -> sitk.Transform:
    return sitk.TranslationTransform(dim)


def points_minus_grid(transform: sitk.Transform, grid: Geometry) -> np.ndarray:
    """``T(p) - p`` on `grid`: numpy array of shape (*spatial_zyx, dim), mm, (x, y, z) last."""
    return sitk.GetArrayFromImage(displacement_field(transform, grid))


def frame_estimates(
    common: Sequence[sitk.Transform],
    other: Sequence[sitk.Transform],
    grid: sitk.Image | Geometry,
    *,
    other_grid: sitk.Image | Geometry | None = None,
) -> np.ndarray:
    """Per-image estimates ``F_i = (T_i^R)^-1 o T_i^C`` sampled on the common grid.

    Parameters
    ----------
    common : sequence of sitk.Transform, length n_images
        ``T_i^C``: common frame -> image i.
    other : sequence of sitk.Transform, length n_images
        ``T_i^R``: R's frame -> image i (inverted here; fields first on every second node
        of their own grids, :data:`ESTIMATE_FIELD_STEP`, then refined at each voxel's
        point).
    grid : sitk.Image or Geometry
        The common grid.
    other_grid : sitk.Image or Geometry, optional
        R's reference grid, where pieces of ``T_i^R`` that are neither linear nor fields
        (B-splines) are sampled before inversion.

    Returns
    -------
    ndarray of shape (n_images, *spatial_zyx, dim)
        ``F_i(p) - p`` in mm, vector components in ITK (x, y[, z]) order.
    """
    g = grid if isinstance(grid, Geometry) else Geometry.from_image(grid)
    if len(common) != len(other):
        raise InputError(f"frame: {len(other)} transforms for {len(common)} images")
    out = np.empty((len(common), *g.shape, g.dimension))
    for i, (tc, tr) in enumerate(zip(common, other, strict=True)):
        out[i] = frame_estimate(tc, tr, g, other_grid=other_grid)
    return out


def frame_estimate(
    common,
    other,
    grid: Geometry,
    *,
    other_grid: sitk.Image | Geometry | None = None,
) -> np.ndarray:
    """One image's ``F_i(p) - p`` on the common grid (:func:`frame_estimates` for one
    image, without the stacked copy): ndarray of shape (*spatial_zyx, dim), float64, mm.
    `common` (``T_i^C``) and `other` (``T_i^R``) may also be paths or chains (ANTs order),
    read here. ``T_i^C`` of linear pieces and displacement fields is sampled by the compiled
    kernels, any other by ITK (:func:`~itk_nrreval.io.transforms.composed_displacement`)."""
    inverse = PointwiseInverse(
        other,
        grid=other_grid,
        field_step=ESTIMATE_FIELD_STEP,
        refine_steps=ESTIMATE_REFINE_STEPS,
    )
    pieces = transform_pieces(common)  # read as pieces: no composite built, none copied
    first = pieces if has_only_fields(pieces) else flatten(pieces)
    del pieces
    return composed_displacement(inverse, first, grid)  # R^-1(C(p)) - p


def needs_inversion_grid(transform: sitk.Transform) -> bool:
    """Whether inverting `transform` needs a grid (it has a B-spline or similar piece)."""
    return not has_only_fields(transform)


def _spread(
    estimates: np.ndarray, f_disp: np.ndarray, mask: np.ndarray | None
) -> tuple[float, float]:
    total, largest, count = 0.0, 0.0, 0
    for estimate in estimates:
        t, m, c = distance_sums(estimate, f_disp, mask)
        total, largest, count = total + t, max(largest, m), count + c
    return total / count, largest


def distance_sums(
    a: np.ndarray, b: np.ndarray, mask: np.ndarray | None
) -> tuple[float, float, int]:
    """Sum and max of ``|a(p) - b(p)|`` over the voxels of `mask` (all when None), and their
    count.

    Parameters
    ----------
    a, b : ndarray, shape ``(*spatial, d)``
        Two displacement fields on one grid (mm; float32 or float64), vectors last.
    mask : ndarray of bool, shape ``spatial`` or flat, optional

    Returns
    -------
    (float, float, int)
        In float64, without the full-size temporaries of ``np.linalg.norm(a - b)`` (two of
        216 MB at 1 mm).
    """
    d = a.shape[-1]
    flat_mask = np.empty(0, np.bool_) if mask is None else np.asarray(mask, bool).reshape(-1)
    total, largest, count = _distance_sums(a.reshape(-1, d), b.reshape(-1, d), flat_mask)
    return float(total), float(largest), int(count)


@numba.njit(cache=True, nogil=True)
def _distance_sums(a, b, mask):  # pragma: no cover - compiled
    # partial sums of 4096 voxels, added up: rounding as a pairwise sum's, not a long loop's
    use_mask = mask.size > 0
    total = partial = largest = 0.0
    count = 0
    for i in range(a.shape[0]):
        if use_mask and not mask[i]:
            continue
        s = 0.0
        for c in range(a.shape[1]):
            x = np.float64(a[i, c]) - np.float64(b[i, c])
            s += x * x
        dist = np.sqrt(s)
        partial += dist
        largest = max(largest, dist)
        count += 1
        if count % 4096 == 0:
            total += partial
            partial = 0.0
    return total + partial, largest, count


def in_steps(
    disp: np.ndarray, *, levels: int = 65535
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """A displacement field in equal steps: each vector component as integers from 0 to
    `levels` between its least and largest value (a quarter of float64's bytes in uint16).

    Parameters
    ----------
    disp : ndarray of shape (..., dim)
        Displacements in mm, components last (any float dtype).
    levels : int
        The number of steps (65535: uint16; 255: uint8).

    Returns
    -------
    (q, low, step) or None
        `q` (disp's shape; uint16, or uint8 for ``levels <= 255``) with ``low + q * step``
        (:func:`from_steps`) within half a step, ``(max - min) / (2 * levels)``, of every
        value; `low` and `step` (dim,) float64 (a constant component: step 1, exact).
        None when `disp` is not finite everywhere.
    """
    flat = np.ascontiguousarray(disp).reshape(-1, disp.shape[-1])
    lows, highs, finite = _chunk_ranges(flat, max(1, min(256, flat.shape[0])))
    if not finite.all():
        return None
    low, high = lows.min(axis=0), highs.max(axis=0)
    step = np.where(high > low, (high - low) / levels, 1.0)
    q = np.empty(flat.shape, np.uint8 if levels <= 255 else np.uint16)
    _to_steps(flat, low, step, float(levels), q)
    return q.reshape(disp.shape), low, step


def from_steps(q: np.ndarray, low: np.ndarray, step: np.ndarray) -> np.ndarray:
    """A displacement field back from :func:`in_steps`: ``low + q * step``.

    Parameters
    ----------
    q : ndarray of shape (..., dim), unsigned integers
    low, step : ndarray of shape (dim,)
        As :func:`in_steps` returns them.

    Returns
    -------
    ndarray of float64, `q`'s shape
        mm.
    """
    out = np.empty(q.shape, np.float64)
    _from_steps(q.reshape(-1, q.shape[-1]), low, step, out.reshape(-1, q.shape[-1]))
    return out


@numba.njit(cache=True, parallel=True)
def _chunk_ranges(flat, n_chunks):  # pragma: no cover - compiled
    m, d = flat.shape
    lows = np.full((n_chunks, d), np.inf)
    highs = np.full((n_chunks, d), -np.inf)
    finite = np.ones(n_chunks, np.bool_)
    size = (m + n_chunks - 1) // n_chunks
    for c in numba.prange(n_chunks):
        for f in range(c * size, min(m, (c + 1) * size)):
            for k in range(d):
                v = np.float64(flat[f, k])
                if not np.isfinite(v):
                    finite[c] = False
                lows[c, k] = min(lows[c, k], v)
                highs[c, k] = max(highs[c, k], v)
    return lows, highs, finite


@numba.njit(cache=True, parallel=True)
def _to_steps(flat, low, step, levels, out):  # pragma: no cover - compiled
    for f in numba.prange(flat.shape[0]):
        for k in range(flat.shape[1]):
            v = np.rint((np.float64(flat[f, k]) - low[k]) / step[k])
            out[f, k] = min(max(v, 0.0), levels)


@numba.njit(cache=True, parallel=True)
def _from_steps(q, low, step, out):  # pragma: no cover - compiled
    for f in numba.prange(q.shape[0]):
        for k in range(q.shape[1]):
            out[f, k] = low[k] + q[f, k] * step[k]


def frame_method(registration: ManifestRegistration) -> str:
    """How F is obtained for a registration other than the common one.

    Returns
    -------
    {"frame_transform", "reference_index", "mean"}
        The first available, in that order (see the module docstring).
    """
    if registration.frame_transform is not None:
        return "frame_transform"
    if registration.reference_index is not None:
        return "reference_index"
    return "mean"


def frame_mapping(
    manifest: Manifest,
    name: str,
    *,
    grid: sitk.Image | Geometry | None = None,
    transforms: Sequence[sitk.Transform] | None = None,
    common_transforms: Sequence[sitk.Transform] | None = None,
    mask: np.ndarray | None = None,
    method: str | None = None,
    consistency: bool = True,
) -> FrameMapping:
    """The transform F from the common frame into registration `name`'s frame.

    Parameters
    ----------
    manifest : Manifest
    name : str
        A registration of `manifest`.
    grid : sitk.Image or Geometry, optional
        The common grid (default: read the common registration's reference).
    transforms, common_transforms : sequence of sitk.Transform, optional
        Already-read ``T_i^R`` and ``T_i^C`` (read from the manifest when omitted).
    mask : ndarray of bool, numpy shape of the grid, optional
        Voxels over which the spread is measured.
    method : {"frame_transform", "reference_index", "mean"}, optional
        Force one way of obtaining F (default: the first available, in that order).
    consistency : bool
        Compute the spread of the per-image estimates (N field inversions). False leaves
        it NaN, except for method "mean", which needs the estimates anyway.

    Returns
    -------
    FrameMapping

    Raises
    ------
    ValueError
        `method` is not one of the accepted values or not available for `name`.
    """
    reg = manifest.registrations[name]
    if grid is None:
        grid = common_reference(manifest)
    g = grid if isinstance(grid, Geometry) else Geometry.from_image(grid)
    if name == manifest.common_frame:
        return FrameMapping(name, "common", _identity(g.dimension), 0.0, 0.0)
    if method is None:
        method = frame_method(reg)
    if method not in _METHODS[1:]:
        raise ValueError(f"method: {method!r} is not one of {_METHODS[1:]}")
    if method == "frame_transform" and reg.frame_transform is None:
        raise ValueError(f"method: registration {name!r} has no frame_transform")
    if method == "reference_index" and reg.reference_index is None:
        raise ValueError(f"method: registration {name!r} has no reference_index")
    if common_transforms is None:
        common_transforms = read_chains(manifest, manifest.common_frame)
    estimates = None
    if consistency or method == "mean":
        if transforms is None:
            transforms = read_chains(manifest, name)
        reg_grid = None
        if any(needs_inversion_grid(t) for t in transforms):
            reg_grid = Geometry.from_image(read_image(reg.reference, what="reference image"))
        estimates = frame_estimates(common_transforms, transforms, g, other_grid=reg_grid)
    if method == "frame_transform":
        f = chain_transform(reg.frame_transform)
    elif method == "reference_index":
        f = common_transforms[reg.reference_index]
    else:
        mean = estimates.mean(axis=0)
        img = sitk.GetImageFromArray(mean, isVector=True)
        g.apply_to(img)
        f = field_transform(img)
    if estimates is None:
        return FrameMapping(name, method, f, float("nan"), float("nan"))
    f_disp = points_minus_grid(f, g)
    return FrameMapping(name, method, f, *_spread(estimates, f_disp, mask))


def resampling_transform(
    transform: sitk.Transform | TransformPieces, frame: sitk.Transform
) -> sitk.Transform | TransformPieces:
    """Image i's transform from the common frame: ``T_i^R o F`` (F acts first).

    Returns ``sitk.CompositeTransform([T_i^R, F])`` (SimpleITK applies its list from the back),
    or `transform` itself when F is the identity (a zero translation) and T_i^R is not linear:
    the same map to the bit, without the copy of every displacement field a composite makes
    (~0.1 s per 1 mm field). A linear T_i^R keeps the composite, so that ITK's resampler takes
    the same (non-linear) path as before. Given T_i^R as its pieces
    (:class:`~itk_nrreval.io.transforms.TransformPieces`), the same map as pieces: F's last,
    since it acts first, and no composite built.
    """
    f = frame.Downcast()
    if (
        not is_linear(transform)
        and isinstance(f, sitk.TranslationTransform)
        and not any(f.GetOffset())
    ):
        return transform
    if isinstance(transform, TransformPieces):
        return TransformPieces((*transform, *leaves(frame)))
    return sitk.CompositeTransform([transform, frame])


def _as_image(item, what: str) -> sitk.Image:
    if isinstance(item, sitk.Image):
        return item
    if isinstance(item, (str, os.PathLike, InMemoryImage)):
        return read_image(item, what=what)
    raise InputError(f"{what}: expected a SimpleITK image or a path, got {type(item).__name__}")


def resample_images(
    images: Sequence,
    transforms: Sequence[sitk.Transform],
    grid: sitk.Image | Geometry,
    *,
    interpolation: str = "linear",
    progress: bool = True,
    desc: str = "resampling",
    outside: float = 0.0,
) -> np.ndarray:
    """Resample each image onto `grid` through its transform (grid points -> image points).

    Parameters
    ----------
    images : sequence of sitk.Image or path, length n_images
    transforms : sequence of sitk.Transform, length n_images
    grid : sitk.Image or Geometry
    interpolation : {"linear", "bspline"}
    progress : bool
        A progress bar on stderr, labelled `desc`.
    desc : str
        The progress bar's label.
    outside : float
        The value of grid points mapped outside an image's field of view (NaN marks them).

    Returns
    -------
    ndarray of shape (n_images, *spatial_zyx), float64
        `outside` (0 by default) outside each image's field of view.
    """
    if interpolation not in _INTERPOLATORS:
        raise ValueError(f"interpolation: {interpolation!r} is not one of {tuple(_INTERPOLATORS)}")
    g = grid if isinstance(grid, Geometry) else Geometry.from_image(grid)
    out = np.empty((len(images), *g.shape))
    pairs = zip(images, transforms, strict=True)
    for i, (item, t) in enumerate(
        progress_bar(pairs, desc=desc, total=len(images), enabled=progress)
    ):
        img = sitk.Cast(_as_image(item, "image"), sitk.sitkFloat64)
        res = resample_onto(img, t, g, _INTERPOLATORS[interpolation], outside=outside)
        out[i] = sitk.GetArrayFromImage(res)
    return out


def resample_onto(
    img: sitk.Image, t: sitk.Transform, g: Geometry, interpolator: int, *, outside: float = 0.0
) -> sitk.Image:
    """`img` resampled onto grid `g` through `t` (grid points -> image points).

    `interpolator` is a SimpleITK interpolator (``sitk.sitkLinear``...); the pixel type
    stays the input's. Grid points that `t` maps outside the image's field of view (beyond
    half a voxel past its outer voxel centres, ITK's rule) get the value `outside`.
    """
    return sitk.Resample(
        img,
        size=list(g.size),
        transform=t,
        interpolator=interpolator,
        outputOrigin=list(g.origin),
        outputSpacing=list(g.spacing),
        outputDirection=list(g.direction),
        defaultPixelValue=float(outside),
        outputPixelType=img.GetPixelID(),
    )


def label_values(labels: Sequence) -> np.ndarray:
    """Sorted union of the values found in the label maps (background 0 included if present).

    Returns
    -------
    ndarray of int64
        The label values.

    Raises
    ------
    InputError
        A label map that is not scalar, or holds a value that is not an integer (an
        intensity image given as a label map, most likely); the message names the file.
    """
    values = set()
    for i, item in enumerate(labels):
        name = f"label map[{i}]" if isinstance(item, sitk.Image) else str(item)  # path or item
        img = _as_image(item, "label map")
        if img.GetNumberOfComponentsPerPixel() != 1:
            raise InputError(f"{name}: a label map must be a scalar image")
        arr = sitk.GetArrayViewFromImage(img)
        found = np.unique(arr)
        if found.dtype.kind == "f":
            bad = found[~np.isfinite(found) | (found != np.round(found))]
            if bad.size:
                raise InputError(
                    f"{name}: label map holds non-integer values (e.g. {float(bad[0]):g}; "
                    f"{bad.size} of {found.size} distinct values): is it an intensity image?"
                )
        values.update(int(v) for v in found)
    return np.array(sorted(values), dtype=np.int64)


def resample_memberships(
    labels: Sequence,
    transforms: Sequence[sitk.Transform],
    grid: sitk.Image | Geometry,
    *,
    values: Sequence[int],
    progress: bool = True,
    desc: str = "resampling labels",
) -> np.ndarray:
    """Resample label maps as one-hot memberships, linearly, onto `grid` (dense).

    The dense form of :func:`itk_nrreval.io._memberships.resample_label_memberships` for a
    few small images; the evaluate pipeline keeps the sparse form.

    Parameters
    ----------
    labels : sequence of sitk.Image or path, length n_images
        Integer label maps, each in its image's space.
    transforms : sequence of sitk.Transform, length n_images
        Grid points -> image points.
    grid : sitk.Image or Geometry
    values : sequence of int, length n_labels
        The label values, one membership channel each, in this order.
    progress : bool
        A progress bar on stderr, labelled `desc`.
    desc : str
        The progress bar's label.

    Returns
    -------
    ndarray of shape (n_images, n_labels, *spatial_zyx), float32
        Fuzzy memberships in [0, 1] (they sum to 1 inside the field of view, 0 outside),
        equal to SimpleITK's linear resampling of the one-hot channels.
    """
    g = grid if isinstance(grid, Geometry) else Geometry.from_image(grid)
    values = [int(v) for v in values]
    out = np.empty((len(labels), len(values), *g.shape), dtype=np.float32)
    pairs = zip(labels, transforms, strict=True)
    for i, (item, t) in enumerate(
        progress_bar(pairs, desc=desc, total=len(labels), enabled=progress)
    ):
        lab = _as_image(item, "label map")
        out[i] = resample_label_memberships(lab, t, g, values=values).dense()
    return out
