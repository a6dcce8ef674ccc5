"""The evaluate dataflow, written once: per-image tasks, per-voxel-block sums, the driver.

:func:`itk_nrreval.evaluate` runs here, in this process by default or on a Dask cluster
(:mod:`itk_nrreval._scaleout`); both run the same tasks, the executor only maps them. The
work is cut so that no process holds the N x n data (N images, n voxels):

1. **per image** (N tasks per registration): the frame estimate ``F_i`` (registrations
   other than the common one); the transform's measures (which voxels of the common grid
   it brings the image's field of view to, and the deformation's plausibility,
   :mod:`itk_nrreval.io.plausibility`, on the registration's own reference grid); then, once
   every transform is measured and the region every image covers under every
   registration is known, registration by registration: the image resampled into the
   common frame, its fuzzy label memberships (sparse: the voxels where each label is
   nonzero), the per-image sums the overlap needs (label gradients, presence) and the
   image divided by its local mean (the subjects' bias-corrected distances). Each is a
   small frozen task object whose fields are its inputs (:mod:`._tasks`); one wrapper,
   :func:`~._tasks.cached`, writes its result to a disk cache under a digest of everything
   it depends on (input
   file contents, transforms, the frame, grid, mask, settings, and the code version: the
   package's and the task's, ``_task_keys._TASK_VERSIONS``; :mod:`itk_nrreval.io._cache`), so a
   rerun -- after an interruption, or with more images or registrations -- finds it there
   instead of recomputing it. A registration's resampled images leave the cache once its
   scores are taken (unless kept: ``keep_resampled``), so that the cache holds one
   registration's images at a time;
2. **per voxel block** (a few tasks per registration): every image's block is read back
   (memory-mapped) to add that block's share of the N x N Gram matrix of the centred
   images, the mean image, and the overlap pair sums per label;
3. **on the driver**: the blocks' sums are added up in block order (so the numbers do not
   depend on the order tasks finish in); the texture model comes from the Gram matrix
   (:meth:`TextureModel.from_gram`), specificity and generalization from the model, the
   overlap from its per-label sums (:meth:`OverlapTable.from_sums`).

Peak memory is therefore independent of N apart from the N x N Gram matrix: one image
and its memberships per task, one voxel block of all N images (``_reduction._BLOCK_BYTES``) per
reduction, one mean image per registration on the driver. The cache folder must be visible
to the driver and every worker (a shared filesystem on a cluster).

Its modules, in the order of the dataflow:

- :mod:`._task_keys`: the cache keys and code versions of the tasks, and what every task
  of a run shares (:class:`~._task_keys.TaskContext`);
- :mod:`._tasks`: the task objects' base and the content-keyed cache around running one
  (:func:`~._tasks.cached`; :func:`~._tasks.key_of`, the only caller of ``task_key``);
- :mod:`._common_frame`: each registration's common frame F: its estimate tasks, the keys
  of the mean and spread added up from them;
- :mod:`._image_tasks`: the per-image tasks (the transform's measures, the resampled image
  and memberships, the label sums, the bias-corrected image, the brain mask) and their
  plans over a registration;
- :mod:`._coverage`: the images' coverage of the common grid and the evaluated region;
- :mod:`._reduction`: the per-voxel-block reductions to a registration's scores;
- :mod:`._label_metrics`: Dice and HD95 per label: their tasks, plans and assembly;
- :mod:`._driver`: :func:`run_pipeline`, which runs the plans through the cache, then the
  reductions, in that order.
"""

from ._coverage import COVERAGE_WARNING, Coverage
from ._driver import PipelineRun, run_pipeline
from ._reduction import ReducedRegistration

__all__ = [
    "COVERAGE_WARNING",
    "Coverage",
    "ReducedRegistration",
    "PipelineRun",
    "run_pipeline",
]
