"""Evaluation of large cohorts on a Dask cluster, with a per-image disk cache.

:func:`itk_nrreval.evaluate` with ``scheduler=`` runs here. The work is cut so that no
process ever holds the N x n data (N images, n voxels):

1. **per image** (N tasks per registration): the frame estimate ``F_i`` (registrations
   other than the common one), then the resampled image and its fuzzy label memberships,
   with the per-image sums the overlap needs (label gradients, presence) and the folded
   fraction of the transform. Each result is written to the disk cache under a digest of
   everything it depends on (input file contents, transforms, the frame, grid, mask,
   settings; :mod:`itk_nrreval.cache`), and a later run finds it there instead of
   recomputing it;
2. **per voxel block** (a few tasks per registration): every image's block is read back
   (memory-mapped) to add that block's contribution to the N x N Gram matrix of the centred
   images, the mean image, and the overlap pair sums;
3. **on the driver**: the blocks' sums are added up; the texture model comes from the Gram
   matrix (:meth:`TextureModel.from_gram`), specificity and generalization from the model
   (they need only its N x (N - 1) parameters), the overlap from its per-label sums.

The cache folder must be visible to the driver and to every worker (a shared filesystem on
a cluster). The numbers equal the single-process path's up to the order of floating-point
sums (tested to 1e-10).
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import tempfile
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from ._errors import InputError
from ._images import Geometry, mask_array, read_image
from ._progress import progress
from .cache import DiskCache, digest_of
from .manifest import Manifest

__all__ = ["evaluate_scaled", "cluster_client", "check_scheduler"]

_FORMAT = 1  # bump when what an entry holds changes
_BLOCK_BYTES = 1 << 27  # float64 bytes of one voxel block over all N images (128 MiB)


# ----------------------------------------------------------------------------- the cluster


@contextlib.contextmanager
def cluster_client(scheduler: str, *, workers: int | None = None) -> Iterator:
    """A ``dask.distributed.Client``: a new local cluster, or one already running.

    Parameters
    ----------
    scheduler : str
        ``"local"`` starts a ``LocalCluster`` of `workers` processes with one thread each
        (closed on exit); anything else is a scheduler address (``tcp://host:8786``) of a
        running cluster (dask-jobqueue, Kubernetes, ``dask scheduler``...).
    workers : int, optional
        Local: the number of worker processes (default: the CPU count). Address: wait until
        that many workers have joined.
    """
    try:
        from dask.distributed import Client, LocalCluster
    except ImportError as exc:  # pragma: no cover - the dask extra is part of [all]
        raise InputError(
            "scheduler: dask.distributed is not installed (pip install 'itk-nrreval[dask]')"
        ) from exc
    check_scheduler(scheduler, workers)
    if scheduler == "local":
        cluster = LocalCluster(
            n_workers=workers or os.cpu_count() or 1,
            threads_per_worker=1,
            processes=True,
            dashboard_address=":0",
            silence_logs=logging.ERROR,
        )
        try:
            with Client(cluster) as client:
                yield client
        finally:
            cluster.close()
        return
    try:
        client = Client(scheduler, timeout="30s")
    except OSError as exc:
        raise InputError(f"scheduler: cannot connect to {scheduler!r} ({exc})") from exc
    try:
        if workers:
            client.wait_for_workers(workers)
        yield client
    finally:
        client.close()


def check_scheduler(scheduler: str, workers: int | None) -> None:
    """Raise InputError for a scheduler that is neither "local" nor an address."""
    host, _, port = str(scheduler).rpartition(":")
    if scheduler != "local" and "://" not in scheduler and not (host and port.isdigit()):
        raise InputError(
            f"scheduler: {scheduler!r} is neither 'local' nor an address like tcp://host:8786"
        )
    if workers is not None and (isinstance(workers, bool) or workers < 1):
        raise ValueError(f"workers: expected a positive integer, got {workers!r}")


def _gather_each(client, futures: Sequence, *, desc: str, show: bool) -> Iterator:
    """(index, result) of each future as it completes, released as soon as it is read."""
    from dask.distributed import as_completed

    index = {f.key: i for i, f in enumerate(futures)}
    for fut in progress(as_completed(futures), desc=desc, total=len(futures), enabled=show):
        yield index[fut.key], fut.result()
        fut.release()


def _single_threaded() -> None:
    # Each task owns one core: the worker runs as many tasks as it has threads.
    import numba

    sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(1)
    numba.set_num_threads(1)


# ----------------------------------------------------------------------------- tasks


@dataclass(frozen=True)
class _Context:
    """What every task of one run needs (small, pickled into each task)."""

    root: str
    grid: Geometry
    mask_key: str | None

    def cache(self) -> DiskCache:
        return DiskCache(self.root)

    def mask_flat(self) -> np.ndarray:
        """The mask over the flattened grid (numpy order), or an empty array for none."""
        if self.mask_key is None:
            return np.zeros(0, np.bool_)
        return self.cache().open("mask", self.mask_key).array("mask")


def _frame_transform(spec: tuple, grid: Geometry, cache: DiskCache) -> sitk.Transform:
    """F from its description: ("identity",), ("chain", item) or ("field", key)."""
    from .transforms import chain_transform, field_transform

    if spec[0] == "identity":
        return sitk.TranslationTransform(grid.dimension)
    if spec[0] == "chain":
        return chain_transform(spec[1])
    disp = cache.open("frame", spec[1]).array("disp")
    img = sitk.GetImageFromArray(disp, isVector=True)
    grid.apply_to(img)
    return field_transform(img)


def _estimate_task(ctx: _Context, common_item, item, reference: Path) -> tuple[str, bool]:
    """Cache ``F_i(p) - p`` on the common grid; return (key, reused)."""
    from .frame import _sampled_before_inversion, frame_estimates
    from .transforms import chain_transform

    _single_threaded()
    cache = ctx.cache()
    key = digest_of(["estimate", _FORMAT, ctx.grid, common_item, item, reference])
    if cache.get("estimate", key) is not None:
        return key, True
    tr = chain_transform(item)
    reg_grid = None
    if _sampled_before_inversion(tr):
        reg_grid = Geometry.from_image(read_image(reference, what="reference image"))
    disp = frame_estimates([chain_transform(common_item)], [tr], ctx.grid, other_grid=reg_grid)[0]
    cache.put("estimate", key, {"disp": disp})
    return key, False


def _spread_task(ctx: _Context, key: str, frame_disp_key: str) -> tuple[float, float, int]:
    """Sum and max over the mask of ``|F_i(p) - F(p)|`` (mm), and the voxel count."""
    _single_threaded()
    cache = ctx.cache()
    est = cache.open("estimate", key).array("disp")
    f_disp = cache.open("frame_disp", frame_disp_key).array("disp")
    dist = np.linalg.norm(est - f_disp, axis=-1).reshape(-1)
    mask = ctx.mask_flat()
    if mask.size:
        dist = dist[mask]
    return float(dist.sum()), float(dist.max()), int(dist.size)


def _resample_task(
    ctx: _Context,
    image: Path,
    labels: Path | None,
    item,
    frame: tuple,
    frame_digest: str,
    reference: Path,
    interpolation: str,
) -> tuple[str, bool, dict]:
    """Resample one image (and its label memberships) into the common frame; cache it.

    The entry holds ``image`` (n,) float64 over the whole grid, and for the labels the
    nonzero memberships per label of the image's own label values in compressed form:
    ``lab_ptr`` (K + 1,), ``lab_idx`` (flat voxel indices, ascending per label), ``lab_val``
    (float32). Its metadata holds per label the gradient sum (over the mask) and whether the
    label is present inside the mask, and the transform's folded fraction.
    """
    from .frame import label_values, resample_images, resample_memberships, resampling_transform
    from .overlap import _gradient_sums
    from .transforms import chain_transform, folded_fraction

    _single_threaded()
    cache = ctx.cache()
    g = ctx.grid
    key = digest_of(
        [
            "resampled",
            _FORMAT,
            g,
            ctx.mask_key,
            image,
            labels,
            item,
            frame_digest,
            reference,
            interpolation,
        ]
    )
    entry = cache.get("resampled", key)
    if entry is not None:
        return key, True, dict(entry.meta)
    t = chain_transform(item)
    full = resampling_transform(t, _frame_transform(frame, g, cache))
    arrays = {
        "image": resample_images(
            [image], [full], g, interpolation=interpolation, show_progress=False
        )[0].reshape(-1)
    }
    reg_grid = Geometry.from_image(read_image(reference, what="reference image"))
    meta: dict = {"folded": folded_fraction(t, reg_grid)}
    if labels is not None:
        lab = read_image(labels, what="label map")
        own = [int(v) for v in label_values([lab])]
        memb = resample_memberships([lab], [full], g, values=own, show_progress=False)
        flat = memb.reshape(1, len(own), -1)
        mask = ctx.mask_flat()
        shape = np.asarray(g.shape, dtype=np.int64)
        inv_h = 1.0 / np.asarray(g.spacing[::-1], dtype=np.float64)
        gsum = np.zeros(len(own))
        idx, val, ptr = [], [], [0]
        for k in range(len(own)):
            _gradient_sums(flat, k, mask, shape, inv_h, gsum[k : k + 1])
            nz = np.flatnonzero(flat[0, k])
            idx.append(nz.astype(np.int64))
            val.append(flat[0, k, nz])
            ptr.append(ptr[-1] + nz.size)
        present = [
            bool(np.any(flat[0, k][mask] != 0)) if mask.size else bool(ptr[k + 1] > ptr[k])
            for k in range(len(own))
        ]
        arrays.update(
            lab_ptr=np.asarray(ptr, np.int64),
            lab_idx=np.concatenate(idx),
            lab_val=np.concatenate(val).astype(np.float32),
        )
        meta.update(labels=own, gsum=gsum.tolist(), present=present)
    cache.put("resampled", key, arrays, meta)
    return key, False, meta


def _block_task(
    ctx: _Context, keys: Sequence[str], start: int, stop: int, components: Sequence[int]
) -> dict:
    """One voxel block [start, stop) of the flattened grid, over all N images.

    Returns the block's Gram matrix of the centred masked intensities (N, N), the mean
    image on the block (stop - start,), and per label of `components` (label values) the
    pair sums p, q (L,) and per image volume and target-overlap sums (N, L), voxel units.
    """
    from .overlap import (
        _INDEX_BITS,
        _NETWORK_FRACTION,
        _active_voxels,
        _pair_sums,
        _sorting_network,
    )

    _single_threaded()
    cache = ctx.cache()
    entries = [cache.open("resampled", k) for k in keys]
    n = len(entries)
    x = np.empty((n, stop - start))
    for i, e in enumerate(entries):
        x[i] = e.array("image", mmap=True)[start:stop]
    mask = ctx.mask_flat()
    mask = mask[start:stop] if mask.size else mask
    mean = x.mean(axis=0)
    xm = x[:, mask] if mask.size else x
    centred = xm - xm.mean(axis=0)
    out = {"gram": centred @ centred.T, "mean": mean}
    del x, xm, centred
    n_labels = len(components)
    p, q = np.zeros(n_labels), np.zeros(n_labels)
    vol, spair = np.zeros((n, n_labels)), np.zeros((n, n_labels))
    if n_labels:
        net_lo, net_hi = _sorting_network(n)
        packed = n <= 1 << _INDEX_BITS
        lookups = [{v: j for j, v in enumerate(e.meta["labels"])} for e in entries]
        arrays = [
            (e.array("lab_ptr"), e.array("lab_idx", mmap=True), e.array("lab_val", mmap=True))
            for e in entries
        ]
        block = np.zeros((n, 1, stop - start), np.float32)
        active = np.empty(stop - start, dtype=bool)
        for k, value in enumerate(components):
            block[:] = 0
            for i, (ptr, idx, val) in enumerate(arrays):
                j = lookups[i].get(int(value))
                if j is None:
                    continue
                own = idx[ptr[j] : ptr[j + 1]]
                lo, hi = np.searchsorted(own, [start, stop])
                block[i, 0, np.asarray(own[lo:hi]) - start] = val[ptr[j] + lo : ptr[j] + hi]
            _active_voxels(block, 0, mask, active)
            voxels = np.flatnonzero(active)
            p[k], q[k] = _pair_sums(
                block, 0, voxels, net_lo, net_hi, _NETWORK_FRACTION, packed, vol[:, k], spair[:, k]
            )
    out.update(p=p, q=q, vol=vol, spair=spair)
    return out


# ----------------------------------------------------------------------------- the driver


@dataclass
class _Counts:
    reused: int = 0
    computed: int = 0

    def add(self, reused: bool) -> None:
        if reused:
            self.reused += 1
        else:
            self.computed += 1


def _block_size(n_images: int, n_voxels: int) -> int:
    size = max(4096, _BLOCK_BYTES // (8 * n_images)) // 4096 * 4096
    return min(size, n_voxels)


def evaluate_scaled(
    m: Manifest,
    *,
    scheduler: str,
    workers: int | None,
    cache: str | os.PathLike | None,
    n_samples: int,
    seed: int,
    distance: str,
    weightings: Sequence[str],
    interpolation: str,
    progress: bool,
):
    """The body of :func:`itk_nrreval.evaluate` for ``scheduler=`` (see there).

    Returns the RegistrationScores by name, the mean images, the label values, and the
    run's description (scheduler, workers, reuse counts). Warns of folding transforms.
    """
    from .evaluation import RegistrationScores, _warn_if_folded
    from .frame import common_reference, label_values
    from .model import TextureModel
    from .overlap import _table
    from .specificity import texture_measures

    check_scheduler(scheduler, workers)
    ref_img = common_reference(m)
    grid = Geometry.from_image(ref_img)
    mask = mask_array(m.mask, shape=grid.shape, geometry=grid) if m.mask is not None else None
    with contextlib.ExitStack() as stack:
        if cache is None:
            cache = stack.enter_context(tempfile.TemporaryDirectory(prefix="nrreval-cache-"))
        disk = DiskCache(cache)
        disk.remove_stale()
        mask_key = None
        if mask is not None:
            flat_mask = mask.reshape(-1).astype(np.bool_)
            mask_key = digest_of(["mask", flat_mask])
            if disk.get("mask", mask_key) is None:
                disk.put("mask", mask_key, {"mask": flat_mask})
        ctx = _Context(str(Path(cache).resolve()), grid, mask_key)
        client = stack.enter_context(cluster_client(scheduler, workers=workers))
        counts = _Counts()
        n_workers = len(client.scheduler_info()["workers"])

        values = None
        if m.labels is not None:
            futs = client.map(label_values, [[p] for p in m.labels], pure=False)
            found: set[int] = set()
            for _, vals in _gather_each(client, futs, desc="label values", show=progress):
                found.update(vals)
            values = [0] + sorted(v for v in found if v != 0)  # channel 0 is background
        components = values[1:] if values is not None else []

        scores = {}
        means = {}
        common_items = m.registrations[m.common_frame].transforms
        for name, reg in m.registrations.items():
            frame_spec, frame_digest, frame = _frame(
                client, ctx, disk, m, name, reg, common_items, counts, progress
            )
            n = m.n_images
            futs = [
                client.submit(
                    _resample_task,
                    ctx,
                    m.images[i],
                    m.labels[i] if m.labels is not None else None,
                    reg.transforms[i],
                    frame_spec,
                    frame_digest,
                    reg.reference,
                    interpolation,
                    pure=False,
                )
                for i in range(n)
            ]
            keys: list[str] = [""] * n
            metas: list[dict] = [{}] * n
            for i, (key, reused, meta) in _gather_each(
                client, futs, desc=f"{name}: resampling", show=progress
            ):
                keys[i], metas[i] = key, meta
                counts.add(reused)
            n_vox = int(np.prod(grid.shape))
            size = _block_size(n, n_vox)
            bounds = [(a, min(a + size, n_vox)) for a in range(0, n_vox, size)]
            futs = [
                client.submit(_block_task, ctx, keys, a, b, components, pure=False)
                for a, b in bounds
            ]
            gram = np.zeros((n, n))
            mean = np.empty(n_vox)
            n_lab = len(components)
            p, q = np.zeros(n_lab), np.zeros(n_lab)
            vol, spair = np.zeros((n, n_lab)), np.zeros((n, n_lab))
            # Sums are taken in block order, whatever order the blocks finish in, so that a
            # run's numbers do not depend on the cluster's timing.
            pending: dict[int, dict] = {}
            next_block = 0
            for b, res in _gather_each(client, futs, desc=f"{name}: blocks", show=progress):
                pending[b] = res
                while next_block in pending:
                    res = pending.pop(next_block)
                    gram += res["gram"]
                    mean[bounds[next_block][0] : bounds[next_block][1]] = res["mean"]
                    p += res["p"]
                    q += res["q"]
                    vol += res["vol"]
                    spair += res["spair"]
                    next_block += 1
            model = TextureModel.from_gram(
                gram,
                mean=mean[mask.reshape(-1)] if mask is not None else mean,
                mask=mask,
                geometry=grid,
            )
            spec, gen = texture_measures(model, n_samples=n_samples, distance=distance, seed=seed)
            overlap = {}
            if values is not None:
                present = np.zeros(n_lab, bool)
                gsum = np.zeros((n, n_lab))
                for i, meta in enumerate(metas):
                    own = {v: j for j, v in enumerate(meta["labels"])}
                    for k, v in enumerate(components):
                        if v in own:
                            present[k] |= meta["present"][own[v]]
                            gsum[i, k] = meta["gsum"][own[v]]
                comps = np.arange(1, len(values), dtype=np.int64)  # component indices
                if not present.any():
                    raise InputError("label maps: no label other than background 0 in the mask")
                skipped = tuple(int(c) for c in comps[~present])
                if skipped:
                    warnings.warn(
                        f"labels {list(skipped)} are absent from every image and are skipped",
                        UserWarning,
                        stacklevel=3,
                    )
                table = _table(
                    comps[present],
                    vol[:, present],
                    spair[:, present],
                    gsum[:, present],
                    p[present],
                    q[present],
                    spacing=grid.spacing,
                    fuzzy=True,
                    skipped=skipped,
                )
                overlap = {w: table.generalized(w) for w in weightings}
            folds = [float(meta["folded"]) for meta in metas]
            _warn_if_folded(name, folds, stacklevel=5)
            scores[name] = RegistrationScores(
                name, spec, gen, overlap, frame, float(np.mean(folds)), float(max(folds))
            )
            means[name] = mean.reshape(grid.shape)
        run = {
            "scheduler": scheduler,
            "workers": n_workers,
            "cache_reused": counts.reused,
            "cache_computed": counts.computed,
        }
    return scores, means, values, run


def _frame(client, ctx, disk, m: Manifest, name, reg, common_items, counts, show):
    """F for registration `name`: its task description, the digest of that, its FrameMapping."""
    from .frame import FrameMapping, _points_minus_grid

    if name == m.common_frame:
        spec = ("identity",)
        f = _frame_transform(spec, ctx.grid, disk)
        return spec, digest_of([spec[0], spec[1:]]), FrameMapping(name, "common", f, 0.0, 0.0)
    if reg.frame_transform is not None:
        method, spec = "frame_transform", ("chain", reg.frame_transform)
    elif reg.reference_index is not None:
        method, spec = "reference_index", ("chain", common_items[reg.reference_index])
    else:
        method, spec = "mean", None
    futs = [
        client.submit(
            _estimate_task, ctx, common_items[i], reg.transforms[i], reg.reference, pure=False
        )
        for i in range(m.n_images)
    ]
    keys = [""] * m.n_images
    for i, (key, reused) in _gather_each(client, futs, desc=f"{name}: frame", show=show):
        keys[i] = key
        counts.add(reused)
    if spec is None:
        key = digest_of(["frame", _FORMAT, keys])
        if disk.get("frame", key) is None:
            total = None
            for k in keys:  # streamed: one field in memory at a time
                est = disk.open("estimate", k).array("disp")
                total = est.copy() if total is None else total + est
            disk.put("frame", key, {"disp": total / len(keys)})
        spec = ("field", key)
    digest = digest_of([spec[0], spec[1:]])
    f = _frame_transform(spec, ctx.grid, disk)
    # F(p) - p on the common grid, once, for every image's spread task
    disp_key = digest_of(["frame_disp", _FORMAT, ctx.grid, digest])
    if disk.get("frame_disp", disp_key) is None:
        disk.put("frame_disp", disp_key, {"disp": _points_minus_grid(f, ctx.grid)})
    futs = [client.submit(_spread_task, ctx, k, disp_key, pure=False) for k in keys]
    parts = [(0.0, 0.0, 0)] * len(keys)
    for i, part in _gather_each(client, futs, desc=f"{name}: spread", show=show):
        parts[i] = part
    count = sum(part[2] for part in parts)
    mean_mm = math.fsum(part[0] for part in parts) / count if count else math.nan
    max_mm = max(part[1] for part in parts) if count else math.nan
    return spec, digest, FrameMapping(name, method, f, mean_mm, max_mm)
