"""The per-voxel-block reductions of the evaluate pipeline, and what they add up to.

Each block task (:func:`_block_task`) reads one voxel block of every scored image back from
the cache and returns its share of the Gram matrix of the centred images, the mean image
and the overlap's pair sums; :func:`reduce_to_scores` adds the blocks up in block order (so
the numbers do not depend on the order tasks finish in) and turns them into the texture
model's specificity and generalization and the overlap table: a
:class:`ReducedRegistration`. :func:`alternative_products` reduces images resampled through
changed transforms against the scored ones, for the subjects' quality control.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import SimpleITK as sitk

from .._errors import InputError, readable
from ..io._brain_masks import BrainMaskDice
from ..io._images import Geometry, read_image
from ..io.frame import FrameMapping, resample_images, resampling_transform
from ..io.manifest import Manifest
from ..io.plausibility import AffineFit, Plausibility
from ..io.transforms import chain_transform, invert
from ..measures._overlap_kernels import membership_pair_sums
from ..measures.description_length import DescriptionLength
from ..measures.label_metrics import LabelMetrics
from ..measures.model import TextureModel
from ..measures.overlap import OverlapTable
from ..measures.specificity import GeneralizationResult, SpecificityResult, texture_measures
from ..measures.subject_qc import SubjectQC
from ._common_frame import frame_transform
from ._coverage import Coverage
from ._task_keys import TaskContext

_BLOCK_BYTES = 1 << 26  # float64 bytes of one voxel block over all N images (64 MiB)

#: Bytes of changed images (float64, over the region) the subject checks of
#: :func:`alternative_products` hold at once: 64 alternatives of a 1 mm brain region would
#: otherwise take 2.5 GB.
ALTERNATIVE_CHUNK_BYTES = 256 * 2**20


@dataclass(frozen=True)
class ReducedRegistration:
    """One registration after the evaluate pipeline's reductions: its measures and their sums.

    Internal to :func:`~itk_nrreval.evaluation.evaluate`, which turns it into the public
    :class:`~itk_nrreval.evaluation.RegistrationScores`; the driver's inputs to a report.

    Attributes
    ----------
    name : str
    specificity : SpecificityResult
    generalization : GeneralizationResult
    overlap : OverlapTable or None
        None without labels.
    frame : FrameMapping
        Its transform is None for an estimated frame until :func:`run_pipeline` returns
        (the driver does not hold the field while it resamples and reduces).
    plausibility : list of Plausibility, length n_images
        Each transform's deformation plausibility on the registration's reference grid
        (every image, those left out of the scores too).
    coverage : Coverage
        How much of the common grid (inside the mask) its images cover.
    mean_image : ndarray of shape (*spatial_zyx,)
        The mean resampled image on the common grid (until :func:`run_pipeline` returns,
        once the registration is reduced, the key of its cache entry: the driver does not
        hold it while the next registrations' images are resampled).
    gram : ndarray of shape (n_scored, n_scored)
        Gram matrix of the centred resampled images in the scores (`scored`; inside the
        region): the model of any subset of them follows from it
        (:mod:`itk_nrreval.measures.confidence`).
    overlap_sums : dict of str to ndarray, or None
        The per-image sums the overlap table was built from (``labels``, ``volume``,
        ``target_sums``, ``gradient_sums``, ``pair_min``, ``pair_max``; see
        :meth:`OverlapTable.from_sums`), rows in `scored` order, and the sums of minima of
        each two images of one subject (``subject_pairs``, ``subject_pair_min``; see
        :func:`~itk_nrreval.measures.confidence.overlap_replicates`); None without labels.
    thumbnails : dict of str to ndarray
        Small arrays for the HTML report, whatever N
        (:func:`~itk_nrreval.io._resampled_images.thumbnails`): middle slices of two subjects'
        resampled images (and of the flagged subjects :func:`run_pipeline` pictures,
        ``image_<i>``), of the first subject's labels and of its
        det J, and the log det J histogram over all subjects.
    affine_fits : list of AffineFit, length n_images
        Each transform's closest affine map on the reference grid
        (:func:`itk_nrreval.io.plausibility.affine_fit`).
    scored : tuple of int
        The images in the scores (manifest indices, ascending; every image but those off
        the common grid, :func:`off_grid_subjects`): the rows of `gram` and `overlap_sums`.
    brain_masks : BrainMaskDice or None
        Every subject's brain-mask Dice in the common frame against the common mask
        (:class:`~._image_tasks.ResampleBrainMask`,
        :func:`~itk_nrreval.io._brain_masks.subject_mask_dice`); None when the manifest has no
        ``masks``.
    label_metrics : LabelMetrics or None
        Dice and HD95 (mm) per label and case in the common frame
        (:mod:`itk_nrreval.measures.label_metrics`, :func:`~._label_metrics.label_metrics`); None
        without labels.
    description_length : DescriptionLength or None
        Bits per subject to code the registered group, shape and texture
        (:mod:`itk_nrreval.measures.description_length`); None unless asked for.
    subjects : tuple of SubjectQC
        Every subject's quality control under this registration, by `assess_subjects` of
        :func:`run_pipeline` (empty without it).
    corrected_squares : ndarray of shape (n_scored,) or None
        Per scored image, the sum over the region of its bias-corrected image's squared
        difference from their mean
        (:func:`~itk_nrreval.measures._subject_measures.others_mean_distances`); None when not
        computed.
    """

    name: str
    specificity: SpecificityResult
    generalization: GeneralizationResult
    overlap: OverlapTable | None
    frame: FrameMapping
    plausibility: list[Plausibility]
    coverage: Coverage
    mean_image: np.ndarray = field(repr=False)
    gram: np.ndarray = field(repr=False)
    overlap_sums: Mapping[str, np.ndarray] | None = field(repr=False)
    thumbnails: Mapping[str, np.ndarray] = field(default_factory=dict, repr=False)
    affine_fits: list[AffineFit] = field(default_factory=list, repr=False)
    scored: tuple[int, ...] = ()
    brain_masks: BrainMaskDice | None = None
    label_metrics: LabelMetrics | None = None
    description_length: DescriptionLength | None = None
    subjects: tuple[SubjectQC, ...] = ()
    corrected_squares: np.ndarray | None = field(default=None, repr=False)


def reduce_to_scores(
    executor,
    ctx,
    name,
    keys,
    metas,
    frame,
    values,
    mask,
    coverage,
    *,
    groups,
    subjects,
    n_samples,
    seed,
    distance,
    progress,
    bias_keys=None,
) -> ReducedRegistration:
    """Block sums -> model -> specificity and generalization; pair sums -> overlap table;
    with `bias_keys` (each scored image's ``bias_corrected`` entry), the bias-corrected sums."""
    grid = ctx.grid
    n = len(keys)
    n_vox = int(np.prod(grid.shape))
    bounds = _block_bounds(n, n_vox)
    components = values[1:] if values is not None else []
    pairs = _subject_pairs(subjects)
    calls = [(ctx, keys, a, b, components, pairs, bias_keys) for a, b in bounds]
    gram = np.zeros((n, n))
    corrected = np.zeros(n) if bias_keys is not None else None
    mean = np.empty(n_vox)
    n_lab = len(components)
    p, q = np.zeros(n_lab), np.zeros(n_lab)
    vol, spair = np.zeros((n, n_lab)), np.zeros((n, n_lab))
    pair_min = np.zeros((len(pairs), n_lab))
    # Sums are taken in block order, whatever order the blocks finish in, so that a run's
    # numbers do not depend on the executor's timing.
    pending: dict[int, dict] = {}
    next_block = 0
    for b, res in executor.map(_block_task, calls, desc=f"{name}: model", progress=progress):
        pending[b] = res
        while next_block in pending:
            res = pending.pop(next_block)
            gram += res["gram"]
            mean[bounds[next_block][0] : bounds[next_block][1]] = res["mean"]
            p += res["p"]
            q += res["q"]
            vol += res["vol"]
            spair += res["spair"]
            pair_min += res["subject_pair_min"]
            if corrected is not None:
                corrected += res["corrected"]
            next_block += 1
    model = TextureModel.from_gram(
        gram,
        mean=mean[mask.reshape(-1)] if mask is not None else mean,
        mask=mask,
        geometry=grid,
    )
    spec, gen = texture_measures(
        model,
        groups=groups,  # a mixture, one Gaussian per group, when the manifest has groups
        n_samples=n_samples,
        distance=distance,
        seed=seed,
        progress=progress,
        desc=f"{name}: specificity",
    )
    table = sums = None
    if values is not None:
        present = np.zeros(n_lab, bool)
        gsum = np.zeros((n, n_lab))
        for i, meta in enumerate(metas):
            own = {v: j for j, v in enumerate(meta["labels"])}
            for k, v in enumerate(components):
                if v in own:
                    present[k] |= meta["present"][own[v]]
                    gsum[i, k] = meta["gsum"][own[v]]
        comps = np.arange(1, len(values), dtype=np.int64)  # indices into values
        if not present.any():
            raise InputError("label maps: no label other than background 0 in the mask")
        skipped = tuple(int(c) for c in comps[~present])
        if skipped:
            warnings.warn(
                f"labels {readable([values[c] for c in skipped])} are absent from every image and "
                "are skipped",
                UserWarning,
                stacklevel=5,
            )
        sums = {
            "labels": comps[present],
            "volume": vol[:, present],
            "target_sums": spair[:, present],
            "gradient_sums": gsum[:, present],
            "pair_min": p[present],
            "pair_max": q[present],
            "subject_pairs": pairs,
            "subject_pair_min": pair_min[:, present],
        }
        table = OverlapTable.from_sums(
            sums["labels"],
            sums["volume"],
            sums["target_sums"],
            sums["gradient_sums"],
            sums["pair_min"],
            sums["pair_max"],
            spacing=grid.spacing,
            fuzzy=True,
            skipped_labels=skipped,
        )
    plaus = [Plausibility.from_dict(meta["plausibility"]) for meta in metas]
    return ReducedRegistration(
        name, spec, gen, table, frame, plaus, coverage, mean.reshape(grid.shape), gram, sums,
        corrected_squares=corrected,
    )  # fmt: skip


def _block_bounds(n_images: int, n_voxels: int) -> list[tuple[int, int]]:
    size = max(4096, _BLOCK_BYTES // (8 * n_images)) // 4096 * 4096
    size = min(size, n_voxels)
    return [(a, min(a + size, n_voxels)) for a in range(0, n_voxels, size)]


def _subject_pairs(subjects: Sequence[str] | None) -> np.ndarray:
    """The pairs (a, b), a < b, of images of one subject: shape (n_pairs, 2)."""
    if subjects is None:
        return np.zeros((0, 2), dtype=np.int64)
    pairs = [
        (a, b)
        for a in range(len(subjects))
        for b in range(a + 1, len(subjects))
        if subjects[a] == subjects[b]
    ]
    return np.array(pairs, dtype=np.int64).reshape(-1, 2)


def _corrected_block(cache, bias_keys, start: int, stop: int, mask) -> np.ndarray:
    """Per image, the block's sum of squares of its bias-corrected image minus their mean
    (inside the mask), shape (N,)."""
    h = np.empty((len(bias_keys), stop - start))
    for i, k in enumerate(bias_keys):
        h[i] = cache.open("bias_corrected", k).array("image", mmap=True)[start:stop]
    if mask is not None:
        h = h[:, mask]
    h -= h.mean(axis=0)
    return np.einsum("iv,iv->i", h, h)


def _block_task(
    ctx: TaskContext,
    keys: Sequence[str],
    start: int,
    stop: int,
    components: Sequence[int],
    subject_pairs: np.ndarray,
    bias_keys: Sequence[str] | None = None,
) -> dict:
    """One voxel block [start, stop) of the flattened grid, over all N images.

    Returns the block's Gram matrix of the centred masked intensities (N, N), the mean
    image on the block (stop - start,), and per label value of `components` the pair sums
    p, q (L,), per image the volume and target-overlap sums (N, L), and for each of
    `subject_pairs` (n_pairs, 2) its sum of minima (n_pairs, L), voxel units; with
    `bias_keys`, per image its bias-corrected sum of squares on the block (N,)
    (:func:`_corrected_block`).
    """
    cache = ctx.cache()
    entries = [cache.open("resampled", k) for k in keys]
    n = len(entries)
    x = np.empty((n, stop - start))
    for i, e in enumerate(entries):
        x[i] = e.array("image", mmap=True)[start:stop]
    mask = ctx.mask_flat()
    mask = mask[start:stop] if mask is not None else None
    mean = x.mean(axis=0)
    # centred in place: one block in memory, not three (two tasks at once at 1 mm)
    if mask is not None:
        x = x[:, mask]
        x -= x.mean(axis=0)
    else:
        x -= mean
    out = {"gram": x @ x.T, "mean": mean}
    del x
    if bias_keys is not None:
        out["corrected"] = _corrected_block(cache, bias_keys, start, stop, mask)
    n_labels = len(components)
    p, q = np.zeros(n_labels), np.zeros(n_labels)
    vol, spair = np.zeros((n, n_labels)), np.zeros((n, n_labels))
    pair_min = np.zeros((len(subject_pairs), n_labels))
    if n_labels:
        lookups = [{v: j for j, v in enumerate(e.meta["labels"])} for e in entries]
        arrays = [
            (e.array("lab_ptr"), e.array("lab_idx", mmap=True), e.array("lab_val", mmap=True))
            for e in entries
        ]
        block = np.zeros((n, stop - start), np.float32)
        for k, value in enumerate(components):
            block[:] = 0
            for i, (ptr, idx, val) in enumerate(arrays):
                j = lookups[i].get(int(value))
                if j is None:
                    continue
                own = idx[ptr[j] : ptr[j + 1]]
                lo, hi = np.searchsorted(own, [start, stop])
                block[i, np.asarray(own[lo:hi]) - start] = val[ptr[j] + lo : ptr[j] + hi]
            p[k], q[k], vol[:, k], spair[:, k] = membership_pair_sums(block, mask=mask)
            for j, (a, b) in enumerate(subject_pairs):
                both = np.minimum(block[a], block[b])
                pair_min[j, k] = (both[mask] if mask is not None else both).sum(dtype=np.float64)
    out.update(p=p, q=q, vol=vol, spair=spair, subject_pair_min=pair_min)
    return out


def alternative_products(
    ctx: TaskContext,
    m: Manifest,
    name: str,
    frame_spec: tuple,
    reg_grid: Geometry,
    keys: Sequence[str],
    mean_image: np.ndarray,
    interpolation: str,
    alternatives: Sequence,
) -> tuple[np.ndarray, np.ndarray]:
    """Resample images through changed transforms; their inner products with the scores'.

    On the driver, after the per-image tasks, for the few subjects the quality control asks
    about (:func:`itk_nrreval.measures.subject_qc.transform_mixups`).

    Parameters
    ----------
    ctx : TaskContext
        The run's context with the evaluated region as its mask.
    m : Manifest
    name : str
        The registration.
    frame_spec : tuple
        Its frame F (:func:`frame_transform`).
    reg_grid : Geometry
        Its reference grid (where a transform that is neither linear nor a displacement
        field is sampled to be inverted).
    keys : sequence of str, length n
        The cache entries of the scored subjects' resampled images.
    mean_image : ndarray of shape (*spatial_zyx,)
        Their mean, which centred the Gram matrix.
    interpolation : str
        As the resampled entries.
    alternatives : sequence of Alternative
        ``image`` resampled through subject ``transform``'s transform of registration
        `name` (its inverse with ``inverse``: :func:`itk_nrreval.io.transforms.invert`, exact
        for linear maps), as the per-image task resamples (0 outside the field of view).

    Returns
    -------
    cross : ndarray of shape (n_alternatives, n)
        Inner products of the centred alternatives with the centred scored images, inside
        the region (squared intensity units, as the Gram matrix).
    squared : ndarray of shape (n_alternatives,)
        Each centred alternative's squared norm there.
    """
    cache = ctx.cache()
    grid = ctx.grid
    region = ctx.mask_flat()
    frame = frame_transform(frame_spec, grid, cache)
    transforms = m.registrations[name].transforms
    centre = mean_image.reshape(-1)
    centre = centre[region] if region is not None else centre
    # by transform, so that each transform is read (and inverted) once
    order = sorted(range(len(alternatives)), key=lambda c: alternatives[c].transform)
    per_chunk = max(1, ALTERNATIVE_CHUNK_BYTES // (8 * max(centre.size, 1)))
    cross = np.empty((len(alternatives), len(keys)))
    squared = np.empty(len(alternatives))
    raw: dict[int, sitk.Image] = {}
    current: tuple[int, sitk.Transform] | None = None
    for start in range(0, len(order), per_chunk):
        chunk = order[start : start + per_chunk]
        changed = np.empty((len(chunk), centre.size))
        for row, c in enumerate(chunk):
            alt = alternatives[c]
            if current is None or current[0] != alt.transform:
                current = (alt.transform, chain_transform(transforms[alt.transform]))
            t = invert(current[1], grid=reg_grid) if alt.inverse else current[1]
            if alt.image not in raw:
                raw[alt.image] = read_image(m.scored_images[alt.image], what="image")
            values = resample_images(
                [raw[alt.image]],
                [resampling_transform(t, frame)],
                grid,
                interpolation=interpolation,
                progress=False,
            )[0].reshape(-1)
            changed[row] = (values[region] if region is not None else values) - centre
        for k, key in enumerate(keys):  # one scored image in memory at a time
            x = np.asarray(cache.open("resampled", key).array("image", mmap=True))
            cross[chunk, k] = changed @ ((x[region] if region is not None else x) - centre)
        squared[chunk] = np.einsum("ij,ij->i", changed, changed)
        del changed
    return cross, squared
