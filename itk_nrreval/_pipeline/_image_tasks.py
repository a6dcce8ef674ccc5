"""The per-image tasks of the evaluate pipeline, and their plans over one registration.

Per image and registration, each a frozen task object whose fields are its inputs, run
through the content-keyed cache (:func:`~itk_nrreval._pipeline._tasks.cached`): the
transform's measures (:class:`MeasureTransform`: the common-grid voxels it brings the
image's field of view to, and the deformation's plausibility) before any image is
resampled; then the image resampled into the common frame with its label memberships
(:class:`ResampleImage`); the per-label sums the overlap needs (:class:`LabelSums`); the
image divided by its local mean (:class:`BiasCorrect`); the subject's brain mask in the
common frame (:class:`ResampleBrainMask`). :func:`measure_plan`, :func:`resample_plan`,
:func:`label_sums_plan`, :func:`bias_plan` and :func:`brain_mask_plan` list them over a
registration's images (computing nothing); the driver runs the plans.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
import SimpleITK as sitk

from ..io._brain_masks import resample_mask
from ..io._cache import DiskCache
from ..io._images import (
    Geometry,
    InMemoryImage,
    label_like_values,
    read_header,
    read_image,
)
from ..io._memberships import (
    SparseMemberships,
    covered_voxels,
    resample_image_and_memberships,
    resample_label_memberships,
    shares_grid,
)
from ..io._resampled_images import stored_memberships
from ..io.frame import resample_images, resampling_transform
from ..io.manifest import Manifest
from ..io.plausibility import deformation_measures
from ..io.transforms import (
    PointMap,
    TransformPieces,
    displacement_array,
    displacement_field,
    flatten,
    has_only_fields,
    transform_pieces,
)
from ..measures._overlap_kernels import membership_gradient_sum
from ..measures._subject_measures import BIAS_SCALE_MM, bias_corrected
from ._common_frame import frame_transform
from ._task_keys import TaskContext, mask_flat
from ._tasks import NOT_KEYED, Task

#: The dtype of the resampled images in the cache: float32 halves the entries (68 -> 34 MB at
#: 1 mm) and changes the scores by parts in 1e7 (the reductions add up in float64;
#: tests/test_pipeline.py bounds it against float64 entries).
_STORED_IMAGE = np.float32


@dataclass(frozen=True)
class Measured:
    """One registration's frame and its transforms' measures (cache entries, metadata)."""

    keys: list[str]
    metas: list[dict]
    frame: Any
    frame_spec: tuple
    frame_digest: str
    reference_grid: Geometry


@dataclass(frozen=True)
class Resampled:
    """One registration's resampled images (cache entries; metadata with its measures')
    and what resampling it again needs."""

    keys: list[str]
    metas: list[dict]
    frame: Any
    frame_spec: tuple
    reference_grid: Geometry
    thumbnails: dict[str, np.ndarray]


def measure_plan(
    ctx: TaskContext,
    m: Manifest,
    name: str,
    *,
    frame_spec: tuple,
    frame_digest: str,
    reg_grid: Geometry,
    reg_mask_key: str | None,
) -> list[MeasureTransform]:
    """Every image's transform of registration `name` to measure (:class:`MeasureTransform`),
    in image order: F described by `frame_spec` (its content `frame_digest`), the
    registration's reference grid `reg_grid` and the mask there (`reg_mask_key`, from
    :class:`~._common_frame.RegistrationMask`)."""
    reg = m.registrations[name]
    return [
        MeasureTransform(
            grid=ctx.grid,
            mask_key=ctx.mask_key,
            image=m.scored_images[i],
            item=reg.transforms[i],
            frame=frame_spec,
            frame_digest=frame_digest,
            reg_grid=reg_grid,
            reg_mask_key=reg_mask_key,
            inverse_consistency=ctx.inverse_consistency,
        )
        for i in range(m.n_images)
    ]


@dataclass(frozen=True)
class MeasureTransform(Task):
    """One image's transform, measured without resampling the image.

    The entry holds ``covered``: the common-grid voxels that ``T_i^R o F`` maps into the
    image's field of view (``np.packbits`` of a bool (n,); ITK's decisions,
    :func:`~itk_nrreval.io._memberships.covered_voxels`, where the resampled image has a
    value), and ``detj_middle`` (float32: det J on the middle slice of `reg_grid`, NaN
    outside its mask, for the report). Its metadata holds the fraction of the mask (or grid)
    covered, the deformation's plausibility measures and the transform's closest affine map
    (:func:`~itk_nrreval.io.plausibility.affine_fit`, from the same sampling of the transform:
    ``deformation_measures(..., affine=True)``) on the registration's reference grid
    `reg_grid` (inside the mask mapped there, `reg_mask_key`), and the fixed-bin counts of
    log det J over the same voxels (``log_jacobian_histogram``).

    Every image's coverage is known before any image is resampled, so each registration's
    resampled images can leave the cache once its scores are taken (:func:`run_pipeline`).
    `frame` is F's description, `frame_digest` its content (keyed).
    """

    kind: ClassVar[str] = "measures"
    grid: Geometry
    mask_key: str | None
    image: Any
    item: Any
    frame: tuple = field(metadata=NOT_KEYED)
    frame_digest: str
    reg_grid: Geometry
    reg_mask_key: str | None
    inverse_consistency: bool

    def compute(self, cache: DiskCache) -> tuple[dict, dict]:
        g, reg_grid = self.grid, self.reg_grid
        pieces = transform_pieces(self.item)
        # with F the identity on T's own grid, T's displacement on the whole common grid (an
        # array) also serves the plausibility
        full, sampled = _sampling(
            pieces, self.frame, g, reg_grid, cache, one_sampling=True, whole=True
        )
        covered = covered_voxels(_image_grid(self.image), full, g, displacement=sampled)
        mask = mask_flat(cache, self.mask_key)
        inside = covered[mask] if mask is not None else covered
        arrays = {"covered": np.packbits(covered)}
        meta: dict = {"coverage": float(inside.mean()) if inside.size else 0.0}
        shared = sampled if isinstance(sampled, np.ndarray) else None  # T's own on g
        del covered, inside, full
        if shared is None:  # freed before the plausibility samples T on its own grid
            sampled = None
        reg_mask = None
        if self.reg_mask_key is not None:
            reg_mask = cache.open("reg_mask", self.reg_mask_key).array("mask")
            reg_mask = reg_mask.reshape(reg_grid.shape)
        # the affine fit from the measures' own sampling of the transform (one pass, not two)
        measures = deformation_measures(
            pieces,
            reg_grid,
            mask=reg_mask,
            inverse_consistency=self.inverse_consistency,
            affine=True,
            displacement=shared,
        )
        del shared, sampled, pieces
        # for the report: one slice, det J on reg_grid
        arrays["detj_middle"] = measures.jacobian.middle
        meta.update(
            plausibility=measures.plausibility.to_dict(),
            affine_fit=measures.affine.to_dict(),
            log_jacobian_histogram=measures.jacobian.histogram(),
        )
        return arrays, meta


def _image_grid(image) -> Geometry:
    """An image's grid from its header (a manifest's in-memory image: its own)."""
    if isinstance(image, InMemoryImage):
        return Geometry.from_image(image.image)
    return Geometry.from_image(read_header(image))


def resample_plan(
    ctx: TaskContext,
    m: Manifest,
    name: str,
    reg: Measured,
    *,
    own_values: Sequence[Sequence[int] | None],
    interpolation: str,
    labels: tuple[str, float | None],
) -> list[ResampleImage]:
    """Every image of registration `name` to resample into the common frame, with its
    labels' memberships (:class:`ResampleImage`), in image order: through the frame `reg`
    measured; `own_values`, each label map's nonzero values (None without labels);
    `labels`, ``(method, sigma_mm)`` of the label resampling."""
    items = m.registrations[name].transforms
    return [
        ResampleImage(
            grid=ctx.grid,
            image=m.scored_images[i],
            labels=m.labels[i] if m.labels is not None else None,
            item=items[i],
            frame=reg.frame_spec,
            frame_digest=reg.frame_digest,
            reg_grid=reg.reference_grid,
            interpolation=interpolation,
            label_resampling=tuple(labels),
            own_values=None if own_values[i] is None else tuple(own_values[i]),
        )
        for i in range(m.n_images)
    ]


@dataclass(frozen=True)
class ResampleImage(Task):
    """One image (and its label memberships) resampled into the common frame.

    The entry holds ``image`` (n,) over the whole grid (``_STORED_IMAGE``, float32; 0 outside
    the image's field of view), ``covered`` (the voxels inside that field of view,
    ``np.packbits`` of a bool (n,)), and for the labels the nonzero memberships of the image's
    own nonzero label values, in compressed form: ``lab_ptr`` (K + 1,), ``lab_idx`` (flat
    voxel indices, ascending per label; uint32 below 2**32 voxels, else int64), ``lab_val``
    (float32). Its metadata holds the label values and the image's label-like values
    (:func:`~itk_nrreval.io._images.label_like_values`). `own_values` are the label map's own
    nonzero values (found once by the driver from `labels`, so not keyed);
    `label_resampling` is ``(method, sigma_mm)`` of
    :func:`~itk_nrreval.io._memberships.resample_label_memberships`. `reg_grid`, the
    registration's reference grid, only says whether T's displacement on the common grid
    can be sampled whole (:func:`_sampling`). The transform's measures are
    :class:`MeasureTransform`'s.
    """

    kind: ClassVar[str] = "resampled"
    grid: Geometry
    image: Any
    labels: Any
    item: Any
    frame: tuple = field(metadata=NOT_KEYED)
    frame_digest: str
    reg_grid: Geometry
    interpolation: str
    label_resampling: tuple
    # read when the task is made (a test stores float64), so that its key and what it
    # stores name one dtype
    stored: str = field(default_factory=lambda: np.dtype(_STORED_IMAGE).str)
    own_values: tuple | None = field(default=None, metadata=NOT_KEYED)

    def compute(self, cache: DiskCache) -> tuple[dict, dict]:
        g = self.grid
        pieces = transform_pieces(self.item)
        raw = read_image(self.image, what="image")
        lab = None if self.labels is None else read_image(self.labels, what="label map")
        own = None if self.labels is None else [int(v) for v in self.own_values]
        method = self.label_resampling[0]
        one_sampling = _shares_sampling(raw, lab, self.interpolation, method)
        full, sampled = _sampling(
            pieces, self.frame, g, self.reg_grid, cache, one_sampling=one_sampling
        )
        del pieces  # `full` holds them where it needs them
        values, memb = _resampled_image_and_memberships(
            raw,
            lab,
            full,
            g,
            interpolation=self.interpolation,
            values=own,
            labels=self.label_resampling,
            one_sampling=one_sampling,
            displacement=sampled,
        )
        del full, sampled
        covered = ~np.isnan(values)  # inputs are checked finite, so NaN marks outside only
        values[~covered] = 0.0
        arrays = {"image": values.astype(self.stored), "covered": np.packbits(covered)}
        meta: dict = {"label_like": label_like_values(raw)}
        if memb is not None:
            # flat voxel indices fit 32 bits below 4 G voxels (half the bytes of int64)
            index = memb.index.astype(np.uint32) if values.size < 2**32 else memb.index
            arrays.update(lab_ptr=memb.ptr, lab_idx=index, lab_val=memb.weight)
            meta.update(labels=own)
        return arrays, meta


def _sampling(
    pieces: TransformPieces, frame: tuple, g: Geometry, reg_grid: Geometry,
    cache: DiskCache, *, one_sampling: bool, whole: bool = False,
) -> tuple:  # fmt: skip
    """Image i's transform from the common frame, ``T_i^R o F`` (:func:`resampling_transform`),
    T given as its pieces (:func:`~itk_nrreval.io.transforms.transform_pieces`), and, where one
    sampling of it on the common grid `g` serves more than one use (`one_sampling`), that
    sampling: ``(transform, sampling or None)``; otherwise the memberships sample the
    transform slab by slab.

    When T is linear maps and displacement fields, the compiled kernels sample it (to about
    1e-13 mm of ITK's): a slab of `g` at a time, as a
    :class:`~itk_nrreval.io.transforms.PointMap` of T after F's displacement (F a field the
    pipeline estimated, frame ``("field", key)``, read from its cache entry) or after none
    (F the identity); with `whole`, F the identity and T on the common grid, as T's
    displacement on the whole grid, which also serves the plausibility. The transform
    returned with it is then a function that gives ``T_i^R o F`` as its pieces, called only
    if ITK's own decisions are needed at a buffer's border: ITK maps those points piece by
    piece, and builds the composite, which copies every field (0.1 to 0.25 s and 0.2 GB
    per 1 mm field), only to resample the whole grid.
    """

    def from_common() -> TransformPieces:
        return resampling_transform(pieces, frame_transform(frame, g, cache))

    if one_sampling and has_only_fields(pieces):
        if frame[0] == "field":
            return from_common, PointMap(pieces, cache.open("frame", frame[1]).array("disp"))
        if frame[0] == "identity" and whole and reg_grid == g:
            return from_common, displacement_array(pieces, g)
        if frame[0] == "identity":
            return from_common, PointMap(pieces)
    if one_sampling and frame[0] == "identity" and reg_grid == g:
        t = flatten(pieces)
        return t, sitk.GetArrayFromImage(displacement_field(t, g))  # F: the identity
    return flatten(from_common()), None


def _resampled_image_and_memberships(
    raw: sitk.Image,
    lab: sitk.Image | None,
    full: sitk.Transform,
    g: Geometry,
    *,
    interpolation: str,
    values: list[int] | None,
    labels: tuple[str, float | None],
    one_sampling: bool,
    displacement: np.ndarray | PointMap | None = None,
) -> tuple[np.ndarray, SparseMemberships | None]:
    """The image on `g` (flat float64, NaN outside its field of view) and the label map's
    memberships (None without one): through one sampling of `full` with `one_sampling`
    (:func:`_shares_sampling`; `displacement`, that sampling when the caller has it), else
    one resampling each."""
    method, sigma_mm = labels
    if one_sampling:
        return resample_image_and_memberships(
            raw, lab, full, g, values=values, displacement=displacement
        )
    image = resample_images(
        [raw], [full], g, interpolation=interpolation, progress=False, outside=np.nan
    )
    memb = None
    if lab is not None:
        memb = resample_label_memberships(
            lab, full, g, values=values, method=method, sigma_mm=sigma_mm
        )
    return image[0].reshape(-1), memb


def _shares_sampling(
    raw: sitk.Image, lab: sitk.Image | None, interpolation: str, label_method: str
) -> bool:
    """Whether a scalar image, and its label map if it has one, can be resampled linearly
    through one sampling of the transform by the compiled kernels
    (:func:`resample_image_and_memberships`): the image linear, the labels linear and on its
    grid."""
    if interpolation != "linear" or raw.GetNumberOfComponentsPerPixel() != 1:
        return False
    return lab is None or (label_method == "linear" and shares_grid(raw, lab))


@dataclass(frozen=True)
class LabelSums(Task):
    """Per label of one resampled image (the ``resampled`` entry `resampled`): its gradient
    sum and its presence in the region (`mask_key`: the voxels every image covers, inside
    the mask).

    Metadata only, whether computed or found (:func:`~._tasks.cached`):
    ``{"gsum": list of float, "present": list of bool}``, each of length K, the image's own
    labels in the order of its entry's ``labels``: ``sum_v |grad A_k|`` over the region
    (mm^-1 x voxels, :func:`~itk_nrreval.measures._overlap_kernels.membership_gradient_sum`), and
    whether A_k is nonzero anywhere in it."""

    kind: ClassVar[str] = "label_sums"
    resampled: str
    mask_key: str | None
    grid: Geometry = field(metadata=NOT_KEYED)  # the resampled entry's (in its key)

    def compute(self, cache: DiskCache) -> tuple[dict, dict]:
        g = self.grid
        entry = cache.open("resampled", self.resampled)
        memb = stored_memberships(entry, g.shape, entry.meta["labels"])
        mask = mask_flat(cache, self.mask_key)
        gsum, present = [], []
        row = np.zeros(int(np.prod(g.shape)), np.float32)
        for k in range(len(memb.values)):
            idx, val = memb.label(k)
            row[idx] = val
            gsum.append(membership_gradient_sum(row, shape=g.shape, spacing=g.spacing, mask=mask))
            row[idx] = 0
            present.append(bool(mask[idx].any()) if mask is not None else bool(idx.size))
        return {}, {"gsum": gsum, "present": present}


@dataclass(frozen=True)
class BiasCorrect(Task):
    """One resampled image (the ``resampled`` entry `resampled`) divided by its local mean
    in the region (`mask_key`), where
    :func:`~itk_nrreval.measures._subject_measures.bias_corrected` takes it: the entry holds
    ``image`` (float32, over the whole grid, 0 outside the region)."""

    kind: ClassVar[str] = "bias_corrected"
    resampled: str
    mask_key: str | None
    grid: Geometry = field(metadata=NOT_KEYED)  # the resampled entry's (in its key)
    scale_mm: float = BIAS_SCALE_MM

    def compute(self, cache: DiskCache) -> tuple[dict, dict]:
        g = self.grid
        image = cache.open("resampled", self.resampled).array("image").reshape(g.shape)
        mask = mask_flat(cache, self.mask_key)
        region = np.ones(g.shape, bool) if mask is None else mask.reshape(g.shape)
        corrected = bias_corrected(image, region, spacing=g.spacing, scale_mm=self.scale_mm)
        return {"image": corrected.reshape(-1).astype(np.float32)}, {}


def label_sums_plan(ctx: TaskContext, keys: Sequence[str]) -> list[LabelSums]:
    """The per-label sums (:class:`LabelSums`) of each resampled image of `keys`, in the
    region (``ctx.mask_key``)."""
    return [LabelSums(resampled=k, mask_key=ctx.mask_key, grid=ctx.grid) for k in keys]


def bias_plan(ctx: TaskContext, keys: Sequence[str]) -> list[BiasCorrect]:
    """Each resampled image of `keys` divided by its local mean in the region
    (:class:`BiasCorrect`), for the subjects' bias-corrected distances."""
    return [BiasCorrect(resampled=k, mask_key=ctx.mask_key, grid=ctx.grid) for k in keys]


def brain_mask_plan(
    ctx: TaskContext, m: Manifest, name: str, reg: Measured, *, label_interpolation: str
) -> list[ResampleBrainMask]:
    """Every subject's brain mask (the manifest's ``masks``) to bring into the common frame
    under registration `name` (:class:`ResampleBrainMask`), resampled as the label maps are:
    nearest neighbour for ``label_interpolation="nearest"``, else linear and inside at 0.5.
    Empty without ``masks``."""
    if m.masks is None:
        return []
    items = m.registrations[name].transforms
    method = "nearest" if label_interpolation == "nearest" else "linear"
    return [
        ResampleBrainMask(
            grid=ctx.grid,
            mask=m.masks[i],
            item=items[i],
            frame=reg.frame_spec,
            frame_digest=reg.frame_digest,
            method=method,
        )
        for i in range(m.n_images)
    ]


@dataclass(frozen=True)
class ResampleBrainMask(Task):
    """One subject's brain mask brought into the common frame through ``T_i^R o F`` (as its
    image is): the entry holds ``mask``, ``np.packbits`` of a bool (n,) over the common grid
    (numpy order). `method` is :func:`~itk_nrreval.io._brain_masks.resample_mask`'s."""

    kind: ClassVar[str] = "brain_mask"
    grid: Geometry
    mask: Any
    item: Any
    frame: tuple = field(metadata=NOT_KEYED)
    frame_digest: str
    method: str

    def compute(self, cache: DiskCache) -> tuple[dict, dict]:
        g = self.grid
        frame = frame_transform(self.frame, g, cache)
        full = flatten(resampling_transform(transform_pieces(self.item), frame))
        inside = resample_mask(
            read_image(self.mask, what="brain mask"), full, g, method=self.method
        )
        return {"mask": np.packbits(inside.reshape(-1))}, {}


class CachedMasks(Sequence):
    """The subjects' resampled brain masks read from the cache one at a time (bool, the
    common grid's numpy shape): N masks are never held at once."""

    def __init__(self, disk: DiskCache, keys: Sequence[str], shape: tuple[int, ...]):
        self._disk, self._keys, self._shape = disk, list(keys), tuple(shape)

    def __len__(self) -> int:
        return len(self._keys)

    def __getitem__(self, i):
        bits = self._disk.open("brain_mask", self._keys[i]).array("mask")
        n = math.prod(self._shape)
        return np.unpackbits(bits, count=n).astype(bool).reshape(self._shape)
