"""An evaluation's resampled images, read back from its per-image cache.

A ``resampled`` cache entry holds one image resampled into the common frame (float32, NaN
outside its field of view, with a bit mask of the voxels it covers) and its labels' fuzzy
memberships (sparse, :func:`stored_memberships`). Evaluate reads them back in two ways:

* while it runs, the HTML report's :func:`thumbnails` (a few middle slices, whatever N);
* after it ran, :func:`export_resampled`: every registration's images and memberships as
  NIfTI, with the evaluated region, from the record an
  :class:`~itk_nrreval.evaluation.EvaluationResult` keeps of where they are in the cache
  (:class:`ResampledImages`). Evaluate itself writes nothing.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from .._errors import InputError
from .._output import atomic_path, write_json
from ._cache import DiskCache
from ._images import Geometry
from ._memberships import SparseMemberships, write_membership_image
from .plausibility import LOG_JACOBIAN_BINS, LOG_JACOBIAN_RANGE

__all__ = [
    "ResampledImages",
    "export_resampled",
    "stored_memberships",
    "image_slice",
    "thumbnails",
]


@dataclass(frozen=True)
class ResampledImages:
    """Where an evaluation's resampled images are in its cache: what :func:`export_resampled`
    needs besides the cache itself.

    Attributes
    ----------
    grid : Geometry
        The common grid.
    region : ndarray of bool, shape (*spatial_zyx,), or None
        The voxels the scores were taken on; None: the whole grid.
    label_values : tuple of int, or None
        ``(0, *labels)``, every label value found (None without labels).
    keys : dict of str to tuple of str
        Per registration (manifest order), each image's ``resampled`` cache entry.
    labels : dict of str to tuple
        Per registration, each image's own nonzero label values (None without labels).
    coverage : dict of str to tuple of float
        Per registration, each image's covered fraction of the common grid (or mask).
    """

    grid: Geometry
    region: np.ndarray | None = field(repr=False)
    label_values: tuple[int, ...] | None
    keys: Mapping[str, tuple[str, ...]] = field(repr=False)
    labels: Mapping[str, tuple[tuple[int, ...] | None, ...]] = field(repr=False)
    coverage: Mapping[str, tuple[float, ...]] = field(repr=False)


def export_resampled(
    result, folder: str | os.PathLike, *, cache: str | os.PathLike, keep: bool = True
) -> Path:
    """Write every registration's resampled images and label memberships as NIfTI.

    Into `folder`: ``region.nii.gz`` (uint8, 1 where the scores were taken: ``nrreval overlap
    --mask`` with it reproduces evaluate's overlap from the saved memberships) and, in a
    folder per registration, ``image_###.nii.gz`` and (with labels) ``memberships_###.nii.gz``,
    each with a JSON sidecar that says what it is (:func:`_write_registration`). Read from
    the evaluation's cache, which must still hold them: evaluate with
    ``Execution(cache=..., keep_resampled=True)``.

    Parameters
    ----------
    result : EvaluationResult
        What :func:`itk_nrreval.evaluate` returned (its ``resampled`` record).
    folder : path
        Created where missing; each file is written under a temporary name and renamed when
        complete.
    cache : path, keyword-only
        The evaluation's cache folder (its ``Execution(cache=...)``).
    keep : bool, keyword-only
        Leave the resampled images in the cache (default); False removes them once written,
        as evaluate does without ``keep_resampled``.

    Returns
    -------
    Path
        `folder`.

    Raises
    ------
    InputError
        The result records none, or the cache no longer holds them all (checked before
        anything is written).
    """
    record: ResampledImages | None = result.resampled
    if record is None:
        raise InputError("export_resampled: this result records no resampled images")
    folder = Path(folder)
    with DiskCache(cache).in_use() as disk:
        entries = {key for keys in record.keys.values() for key in keys}
        if any(disk.get("resampled", key) is None for key in sorted(entries)):
            raise InputError(
                f"{cache}: no longer holds the evaluation's resampled images: evaluate with "
                "Execution(cache=..., keep_resampled=True) to export them"
            )
        _write_region(folder, record.grid, record.region)
        values = None if record.label_values is None else list(record.label_values)
        for name, keys in record.keys.items():
            _write_registration(disk, keys, record, name, folder / name, values)
        if not keep:
            for key in entries:
                disk.remove("resampled", key)
    return folder


#: The evaluated region, written beside the registrations' folders by export_resampled.
_REGION_FILE = "region.nii.gz"


def _write_registration(
    disk: DiskCache,
    keys: Sequence[str],
    record: ResampledImages,
    name: str,
    folder: Path,
    values: list[int] | None,
) -> None:
    """Write ``image_###.nii.gz`` and (with labels) ``memberships_###.nii.gz``, each with a
    JSON sidecar (``image_###.json``, ``memberships_###.json``) that says what it is.

    The images are float64, in the input's intensity units, 0 outside the subject's field of
    view (NIfTI keeps no NaN). The memberships have one component per nonzero label value
    (``values[1:]``, in that order) and no background component
    (:func:`itk_nrreval.io._memberships.write_membership_image` gives the format).
    """
    grid = record.grid
    folder.mkdir(parents=True, exist_ok=True)
    for i, key in enumerate(keys):
        entry = disk.open("resampled", key)
        # float64 as documented, whatever the cache holds
        img = sitk.GetImageFromArray(entry.array("image").astype(np.float64).reshape(grid.shape))
        grid.apply_to(img)
        # ITK's NIfTI writer puts this key in the header's description (`descrip`)
        img.SetMetaData("ITK_FileNotes", "nrreval resampled image; 0 outside the field of view")
        with atomic_path(folder / f"image_{i:03d}.nii.gz") as tmp:
            sitk.WriteImage(img, str(tmp), True)
        about = {
            "subject": i,
            "registration": folder.name,
            "evaluated_region": f"../{_REGION_FILE}",
        }
        write_json(
            folder / f"image_{i:03d}.json",
            {
                "kind": "resampled image",
                "image": f"image_{i:03d}.nii.gz",
                "outside_field_of_view": 0.0,
                "coverage": record.coverage[name][i],
                **about,
            },
        )
        if values is None:
            continue
        memb = stored_memberships(entry, grid.shape, record.labels[name][i])
        dense = np.zeros((len(values) - 1, *grid.shape), np.float32)
        own = memb.dense()
        for j, v in enumerate(record.labels[name][i]):
            dense[values.index(v) - 1] = own[j]
        write_membership_image(
            folder / f"memberships_{i:03d}.nii.gz",
            dense,
            labels=values[1:],
            geometry=grid,
            about=about,
        )


def _write_region(folder: Path, grid: Geometry, region: np.ndarray | None) -> None:
    """Write ``region.nii.gz`` (uint8, 1 where the scores were taken) beside the
    registrations' folders of saved images: ``nrreval overlap --mask`` with it reproduces
    evaluate's overlap from the saved memberships. `region` None is the whole grid."""
    where = np.ones(grid.shape, np.uint8) if region is None else region.astype(np.uint8)
    img = sitk.GetImageFromArray(where)
    grid.apply_to(img)
    # ITK's NIfTI writer puts this key in the header's description (`descrip`)
    img.SetMetaData("ITK_FileNotes", "nrreval evaluated region; 1 where the scores were taken")
    folder.mkdir(parents=True, exist_ok=True)
    with atomic_path(folder / _REGION_FILE) as tmp:
        sitk.WriteImage(img, str(tmp), True)


def stored_memberships(entry, shape: tuple[int, ...], labels) -> SparseMemberships:
    """The label memberships a ``resampled`` cache entry holds (its ``lab_*`` arrays), on a
    grid of numpy `shape`, for the label values `labels` (the entry's meta records them)."""
    return SparseMemberships(
        values=np.asarray(labels, np.int64),
        shape=shape,
        ptr=entry.array("lab_ptr"),
        index=entry.array("lab_idx"),
        weight=entry.array("lab_val"),
    )


def image_slice(disk: DiskCache, grid: Geometry, key: str) -> np.ndarray:
    """The middle slice (numpy index ``shape[0] // 2``; the whole grid in 2D) of a resampled
    image's cache entry, float32, NaN outside its field of view; read from the memory-mapped
    entry without loading the volume."""
    per = int(np.prod(grid.shape[1:])) if grid.dimension == 3 else int(np.prod(grid.shape))
    start = per * (grid.shape[0] // 2) if grid.dimension == 3 else 0
    shape = grid.shape[1:] if grid.dimension == 3 else grid.shape
    entry = disk.open("resampled", key)
    img = np.array(entry.array("image", mmap=True)[start : start + per], np.float32)
    bits = entry.array("covered", mmap=True)[start // 8 : (start + per + 7) // 8]
    covered = np.unpackbits(np.asarray(bits))[start % 8 : start % 8 + per].astype(bool)
    img[~covered] = np.nan
    return img.reshape(shape)


def thumbnails(
    disk: DiskCache,
    grid: Geometry,
    reg_grid: Geometry,
    keys: Sequence[str],
    measures_key: str,
    metas: Sequence[dict],
) -> dict[str, np.ndarray]:
    """The report's small arrays for one registration, read back from its cache entries:
    the resampled images' `keys` and the first subject's measures (`measures_key`).

    A constant number of 2D slices whatever N (the middle slice, numpy index
    ``shape[0] // 2``, of a 3D grid; the whole grid in 2D), each read from the memory-mapped
    entry without loading a volume:

    * ``image_0``, ``image_1`` (float32): subjects 0 and 1 resampled into the common frame,
      NaN outside their fields of view (``image_1`` only when N >= 2; :func:`image_slice`;
      :func:`~itk_nrreval._pipeline.run_pipeline` adds ``image_<i>`` of the subjects it is
      asked to picture);
    * ``labels_0`` (int32, with labels): subject 0's label value of largest resampled
      membership, 0 where the background's (one minus the labels') is at least as large;
    * ``detj_0`` (float32): det J of subject 0's transform on the middle slice of the
      registration's reference grid, NaN outside its mask;
    * ``log_jacobian_counts`` (int64, ``LOG_JACOBIAN_BINS``), ``log_jacobian_edges`` and
      ``log_jacobian_outside`` (int64: below, above the bins, folded): the histogram of
      log det J summed over all N subjects;
    * ``common_spacing``, ``reference_spacing`` (mm, numpy order (row, column)): the pixel
      size of the common-grid and reference-grid slices.
    """
    per = int(np.prod(grid.shape[1:])) if grid.dimension == 3 else int(np.prod(grid.shape))
    start = per * (grid.shape[0] // 2) if grid.dimension == 3 else 0
    shape = grid.shape[1:] if grid.dimension == 3 else grid.shape
    out: dict[str, np.ndarray] = {}
    for i in range(min(2, len(keys))):
        out[f"image_{i}"] = image_slice(disk, grid, keys[i])
    entry = disk.open("resampled", keys[0])
    if "labels" in metas[0]:
        ptr = entry.array("lab_ptr")
        idx, val = entry.array("lab_idx", mmap=True), entry.array("lab_val", mmap=True)
        best = np.zeros(per, np.float32)
        total = np.zeros(per, np.float32)
        lab = np.zeros(per, np.int32)
        for j, v in enumerate(metas[0]["labels"]):
            own = idx[ptr[j] : ptr[j + 1]]
            lo, hi = np.searchsorted(own, [start, start + per])
            at = np.asarray(own[lo:hi]) - start
            w = np.asarray(val[ptr[j] + lo : ptr[j] + hi])
            total[at] += w
            better = w > best[at]
            best[at[better]] = w[better]
            lab[at[better]] = v
        lab[best <= 1.0 - total] = 0
        out["labels_0"] = lab.reshape(shape)
    out["detj_0"] = np.array(disk.open("measures", measures_key).array("detj_middle"), np.float32)
    counts = np.zeros(LOG_JACOBIAN_BINS, np.int64)
    outside = np.zeros(3, np.int64)
    for meta in metas:
        h = meta["log_jacobian_histogram"]
        counts += np.asarray(h["counts"], np.int64)
        outside += np.array([h["below"], h["above"], h["folded"]], np.int64)
    out["log_jacobian_counts"] = counts
    out["log_jacobian_edges"] = np.linspace(*LOG_JACOBIAN_RANGE, LOG_JACOBIAN_BINS + 1)
    out["log_jacobian_outside"] = outside
    out["common_spacing"] = np.array([grid.spacing[1], grid.spacing[0]])
    out["reference_spacing"] = np.array([reg_grid.spacing[1], reg_grid.spacing[0]])
    return out


# ------------------------------------------------------------- Dice and HD95 per label
