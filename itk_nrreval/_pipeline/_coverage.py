"""How much of the common grid a registration's images cover, and where the scores are taken.

A common-grid voxel that a transform maps outside an image's field of view has no value in
that image, so the scores are taken on the voxels every image covers under every
registration (:func:`evaluated_region`), inside the mask; images (almost) off the grid are
left out of every score rather than emptying it (:func:`off_grid_subjects`).
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from .._errors import InputError, readable
from ..io._cache import DiskCache
from ..io._images import Geometry
from ..io.manifest import Manifest


@dataclass(frozen=True)
class Coverage:
    """How much of the common grid a registration's images cover (their fields of view).

    A common-grid voxel that a transform maps outside image i's field of view has no value
    in image i. The scores are therefore taken over the voxels every image covers under
    every registration (inside the mask), the same voxels for every registration so that
    their scores compare.

    Attributes
    ----------
    fraction : float
        The fraction of the mask's (or grid's) voxels covered by every image in the scores
        under this registration (images left off the grid do not count:
        :func:`off_grid_subjects`).
    per_image : tuple of float, length n_images
        Each image's covered fraction of the mask (or grid) under this registration.
    evaluated : float
        The fraction of the mask (or grid) where the scores are taken: covered by every
        image under every registration (the same for every registration of a run).
    """

    fraction: float
    per_image: tuple[float, ...]
    evaluated: float

    def to_dict(self) -> dict:
        return {
            "fraction": self.fraction,
            "evaluated": self.evaluated,
            "per_image_min": min(self.per_image) if self.per_image else None,
        }


COVERAGE_WARNING = 0.9  # warn when the scores are taken on less of the mask than this


def off_grid_subjects(resampled: Mapping, ratio: float) -> tuple[int, ...]:
    """The subjects that cover less of the common grid than `ratio` times the median
    subject, under any registration (ascending indices).

    Such a subject's transform maps it (almost) off the grid; kept, it would empty the region
    every score is taken on (:func:`evaluated_region`) for every registration.
    """
    out: set[int] = set()
    for _keys, metas, _frame in resampled.values():
        per_image = np.array([float(meta["coverage"]) for meta in metas])
        out |= set(np.flatnonzero(per_image < ratio * float(np.median(per_image))).tolist())
    return tuple(sorted(out))


def evaluated_region(
    disk: DiskCache,
    grid: Geometry,
    mask: np.ndarray | None,
    m: Manifest,
    resampled: Mapping,
    left_out: Sequence[int] = (),
) -> tuple[np.ndarray | None, dict[str, Coverage]]:
    """The voxels every image covers under every registration (inside the mask).

    Images `left_out` (:func:`off_grid_subjects`) do not restrict the region.

    Returns the region (bool, the grid's numpy shape; None when it is the whole grid and
    there is no mask) and each registration's :class:`Coverage`.
    """
    n_vox = int(np.prod(grid.shape))
    base = mask.reshape(-1).astype(bool) if mask is not None else None
    total = int(base.sum()) if base is not None else n_vox
    every = np.ones(n_vox, bool)
    fractions: dict[str, tuple[float, tuple[float, ...]]] = {}
    for name, (keys, metas, _frame) in resampled.items():
        covered = np.ones(n_vox, bool)
        for i, k in enumerate(keys):
            if i in left_out:
                continue
            bits = disk.open("measures", k).array("covered")
            covered &= np.unpackbits(bits, count=n_vox).astype(bool)
        inside = covered[base] if base is not None else covered
        per_image = tuple(float(meta["coverage"]) for meta in metas)
        fractions[name] = (float(inside.sum()) / total if total else 0.0, per_image)
        every &= covered
    region = every & base if base is not None else every
    evaluated = float(region.sum()) / total if total else 0.0
    where = "inside the mask" if mask is not None else "of the common grid"
    if not region.any():
        raise InputError(
            f"no voxel {where} is covered by every image under every registration: "
            "check the images' fields of view and the transforms"
        )
    if evaluated < COVERAGE_WARNING:
        name = min(fractions, key=lambda r: fractions[r][0])
        frac, per_image = fractions[name]
        i = min((j for j in range(len(per_image)) if j not in left_out), key=lambda j: per_image[j])
        warnings.warn(
            f"the scores are taken on the {evaluated:.0%} of the voxels {where} that every "
            f"image covers under every registration; least: registration {name!r} "
            f"({frac:.0%}), its image {m.scored_images[i]} ({per_image[i]:.0%})",
            UserWarning,
            stacklevel=4,
        )
    coverage = {
        name: Coverage(frac, per_image, evaluated) for name, (frac, per_image) in fractions.items()
    }
    if base is None and region.all():
        return None, coverage
    return region.reshape(grid.shape), coverage


def left_out_of_scores(m: Manifest, entries, off_grid_coverage: float) -> tuple[int, ...]:
    """The images left out of every score: those off the common grid under some
    registration (a warning names them), unless too few would be left (the region check
    reports it). `entries`: per registration (keys, metas, frame)."""
    left_out = off_grid_subjects(entries, off_grid_coverage)
    if not left_out or m.n_images - len(left_out) < 3:
        return ()
    warnings.warn(
        f"{len(left_out)} of {m.n_images} images cover (almost) none of the common "
        f"grid under some registration and are left out of every score: "
        f"{readable([str(m.images[i]) for i in left_out])}",
        UserWarning,
        stacklevel=4,
    )
    return tuple(left_out)


def check_region_covered(
    disk: DiskCache,
    name: str,
    keys: Sequence[str],
    scored: Sequence[int],
    region: np.ndarray | None,
    grid: Geometry,
) -> None:
    """Every scored image resampled has a value at every voxel of the region, which was
    found from the measured coverage before any image was resampled (RuntimeError if not:
    the two would disagree, and an image's 0 outside its field of view would be scored)."""
    n_vox = int(np.prod(grid.shape))
    where = None if region is None else region.reshape(-1)
    for i in scored:
        bits = disk.open("resampled", keys[i]).array("covered")
        missing = ~np.unpackbits(bits, count=n_vox).astype(bool)
        n_missing = int(missing.sum() if where is None else missing[where].sum())
        if n_missing:
            raise RuntimeError(
                f"registration {name!r}, image {i}: its resampled image has no value at "
                f"{n_missing} voxels of the evaluated region, which its measured coverage "
                "includes (a defect of this toolkit: please report it)"
            )
