"""The cache keys of the evaluate pipeline's tasks, and what every task of a run shares.

A task's result is cached under a digest of everything it depends on (:func:`task_key`):
its inputs and options, the format of an entry (``_FORMAT``), the package's version and the
task's own computation version (``_TASK_VERSIONS``), so that an entry computed by older code
is never reused. :class:`TaskContext` is what every task of one run needs: the cache
folder, the common grid, the mask.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import _version
from ..io._cache import DiskCache, digest_of
from ..io._images import Geometry

_FORMAT = 7  # bump when what a cache entry holds changes

#: The computation version of each cached task: bump a task's number whenever what it
#: computes changes (a fix, a new default), so that entries computed the old way are never
#: reused. Every key also holds the package version (:func:`task_key`).
_TASK_VERSIONS = {
    "estimate": 4,  # 2: a coarse, refined inverse; stored float32 (issue 30)
    # 3: the coarse inverse refined at the common grid's points (issue 30)
    # 4: float32 for the mean until added up, 16-bit steps for the spread (issue 30)
    "frame": 2,  # 2: stored float32, as its estimates (issue 30)
    "frame_disp": 1,
    "frame_spread": 3,  # the spread of the estimates of F (issue 30); 2: per image (issue 27)
    # 3: from estimates in 16-bit steps (issue 30)
    "reg_mask": 1,
    "resampled": 7,  # 2: inverse consistency no longer read from freed memory (issue 25)
    # 3: the transform's closest affine map (issue 27)
    # 4: inverse consistency from a coarse, refined inverse on every second voxel; float32
    # image, uint32 label indices (issue 30)
    # 5: inverse consistency refined at the round trip's points; the image from the
    # memberships' sampling of the transform (issue 30)
    # 6: the transform's measures in their own entry, "measures" (issue 30). The number
    # stayed 5 then; harmless, as the key lost the mask, the registration's mask and the
    # inverse-consistency option in that change, so no entry of before was found again
    # 7: the number caught up (issue 43): the key's parts are 6's (digest_of reads a tuple
    # as a list), so entries written under 5 since issue 30 are misses, never wrong hits
    "measures": 2,  # coverage and plausibility, before any image is resampled (issue 30)
    # 2: the non-diffeomorphic fraction and volume (issue 42)
    "label_sums": 1,
    "bias_corrected": 1,  # a resampled image divided by its local mean (issue 42)
    "brain_mask": 1,  # a subject's brain mask in the common frame (issue 42)
    "crisp_labels": 1,  # a subject's crisp label map and label boundaries (issue 45)
    "label_distances": 1,  # its Dice counts and directed HD95 against others (issue 45)
}


def task_key(kind: str, *parts) -> str:
    """The cache key of a `kind` entry: its code version and `parts`.

    `parts` must hold every input and every option the entry's result depends on.
    """
    return digest_of([kind, _FORMAT, _version.__version__, _TASK_VERSIONS[kind], *parts])


@dataclass(frozen=True)
class TaskContext:
    """What every task of one run needs (small; pickled into each task on a cluster)."""

    root: str
    grid: Geometry
    mask_key: str | None
    inverse_consistency: bool = True

    def cache(self) -> DiskCache:
        return DiskCache(self.root)

    def mask_flat(self) -> np.ndarray | None:
        """The mask over the flattened grid (numpy order), or None."""
        return mask_flat(self.cache(), self.mask_key)


def mask_flat(cache: DiskCache, mask_key: str | None) -> np.ndarray | None:
    """The mask stored under `mask_key` in `cache`, over the flattened grid (numpy order),
    or None without one."""
    if mask_key is None:
        return None
    return cache.open("mask", mask_key).array("mask")
