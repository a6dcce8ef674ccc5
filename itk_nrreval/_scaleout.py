"""Evaluation of large cohorts on a Dask cluster.

:func:`itk_nrreval.evaluate` with an ``Execution(scheduler=...)`` maps the tasks of
:mod:`itk_nrreval._pipeline` -- the same functions the in-process executor runs -- onto a
Dask cluster: per-image work and voxel-block sums become tasks, and no process holds all
the images. The per-image cache folder must be visible to the driver and every worker (a
shared filesystem on a cluster). The numbers equal the in-process run's (the driver adds
the blocks' sums in block order, whatever order they finish in).
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import SimpleITK as sitk

from ._errors import InputError, readable
from ._progress import progress_bar

__all__ = ["DaskExecutor", "cluster_client", "check_scheduler"]


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
        raise ValueError(f"workers: expected a positive integer, got {readable(workers)}")


class DaskExecutor:
    """Run each task on a Dask cluster (see :class:`itk_nrreval._executors.Executor`).

    Parameters
    ----------
    client : dask.distributed.Client
        From :func:`cluster_client`.
    """

    def __init__(self, client):
        self.client = client
        self.n_workers = len(client.scheduler_info()["workers"])

    def map(
        self, fn: Callable, calls: Sequence[tuple], *, desc: str, progress: bool
    ) -> Iterator[tuple[int, Any]]:
        from dask.distributed import as_completed

        futures = [self.client.submit(_one_core, fn, *args, pure=False) for args in calls]
        index = {f.key: i for i, f in enumerate(futures)}
        for fut in progress_bar(
            as_completed(futures), desc=desc, total=len(futures), enabled=progress
        ):
            yield index[fut.key], fut.result()
            fut.release()  # the driver keeps only what it has read


def _one_core(fn: Callable, *args):
    """Run `fn` on one core (a worker runs as many tasks at once as it has threads).

    SimpleITK's and numba's thread counts are restored afterwards: they are process-wide.
    """
    import numba

    sitk_threads = sitk.ProcessObject.GetGlobalDefaultNumberOfThreads()
    numba_threads = numba.get_num_threads()
    sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(1)
    numba.set_num_threads(1)
    try:
        return fn(*args)
    finally:
        sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(sitk_threads)
        numba.set_num_threads(numba_threads)
