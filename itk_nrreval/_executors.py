"""Where tasks run: one protocol for every command that works in parallel.

A task is a function and its argument tuples; an executor maps it over them and yields
``(index, result)`` as each ends. :class:`InProcessExecutor` runs them here, in order;
:class:`ThreadExecutor` on threads of this process (for tasks on arrays already in memory
whose heavy parts release the GIL: SimpleITK, numpy); :class:`itk_nrreval._scaleout.DaskExecutor`
on a cluster (evaluate's ``Execution(scheduler=...)``). Results never depend on which one
ran them: each caller places a result by its index.
"""

from __future__ import annotations

import os
import threading
import warnings
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor, as_completed
from typing import Any, Protocol

import numba

from ._progress import progress_bar

__all__ = [
    "Executor",
    "InProcessExecutor",
    "ThreadExecutor",
    "local_executor",
    "kernels_thread_safe",
    "default_threads",
    "ITK_READ_LOCK",
    "NPY_HEADER_LOCK",
]


#: ITK's HDF5 library is not thread-safe (two threads reading ``.h5`` transforms at once end
#: the process: "HDF5: infinite loop closing library"). Every read by SimpleITK
#: (``ReadImage``, ``ReadTransform``, and header reads, ``_images.read_header``: ITK asks its
#: HDF5 reader about every file) takes this lock, so that tasks on threads of one process (or
#: callers' own threads) can read; a read is about 3 % of a task's time at 1 mm.
ITK_READ_LOCK = threading.Lock()

#: ``np.load`` parses a ``.npy`` header with ``ast.literal_eval``, and CPython 3.11's AST
#: conversion is not thread-safe (tasks loading cached arrays on threads once failed with
#: "SystemError: AST constructor recursion depth mismatch"): every header read of the cache
#: (:meth:`itk_nrreval.io._cache.CacheEntry.array`) takes this lock; the data is read outside it.
NPY_HEADER_LOCK = threading.Lock()


class Executor(Protocol):
    """Maps a task function over argument tuples; yields ``(index, result)`` as each ends."""

    n_workers: int

    def map(
        self, fn: Callable, calls: Sequence[tuple], *, desc: str, progress: bool
    ) -> Iterator[tuple[int, Any]]: ...


class InProcessExecutor:
    """Run every task in this process, one after the other, in order.

    Tasks use the threads SimpleITK and numba give them (all cores by default).
    """

    n_workers = 1

    def map(
        self, fn: Callable, calls: Sequence[tuple], *, desc: str, progress: bool
    ) -> Iterator[tuple[int, Any]]:
        for i, args in enumerate(
            progress_bar(calls, desc=desc, total=len(calls), enabled=progress)
        ):
            yield i, fn(*args)


class ThreadExecutor:
    """Run the tasks of each :meth:`map` on `n_workers` threads of this process.

    Results are yielded as tasks end (any order). A task that raises stops the map: the
    tasks not yet started are cancelled and the error is raised.
    """

    def __init__(self, n_workers: int):
        self.n_workers = int(n_workers)

    def map(
        self, fn: Callable, calls: Sequence[tuple], *, desc: str, progress: bool
    ) -> Iterator[tuple[int, Any]]:
        pool = ThreadPoolExecutor(self.n_workers)
        try:
            futures = {pool.submit(fn, *args): i for i, args in enumerate(calls)}
            done = as_completed(futures)
            for future in progress_bar(done, desc=desc, total=len(calls), enabled=progress):
                yield futures[future], future.result()
        finally:
            pool.shutdown(cancel_futures=True)


@numba.njit(cache=True, parallel=True)
def _one_parallel_loop(n):  # pragma: no cover - compiled
    total = 0
    for i in numba.prange(n):
        total += i
    return total


def kernels_thread_safe() -> bool:
    """Whether this process's compiled parallel kernels may run on several threads at once.

    numba chooses its threading layer when the first parallel kernel runs (a tiny one runs
    here to find out). OpenMP and TBB accept kernels launched from several threads at once;
    the fallback, ``workqueue`` (where neither library is installed), ends the process
    instead ("Concurrent access has been detected").
    """
    _one_parallel_loop(2)
    return numba.threading_layer() in ("omp", "tbb")


def default_threads() -> int:
    """How many tasks run at once in this process by default: 2 on two or more cores where
    :func:`kernels_thread_safe`, else 1.

    Each task's heavy parts (ITK filters, compiled kernels) use every core already; a
    second task at once keeps the cores busy while the first reads files, decompresses
    them or runs Python (``docs/speed.md``). More than two gains little, and each task at
    once holds its own images and fields.
    """
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return 2 if (cores or 1) >= 2 and kernels_thread_safe() else 1


def local_executor(n_workers: int) -> InProcessExecutor | ThreadExecutor:
    """`n_workers` threads of this process, or the caller's own thread for one.

    Where the compiled kernels cannot run on several threads at once
    (:func:`kernels_thread_safe`), the tasks run one at a time, with a warning.
    """
    if n_workers > 1 and not kernels_thread_safe():
        warnings.warn(
            f"numba's threading layer {numba.threading_layer()!r} cannot run kernels on "
            f"several threads at once: {n_workers} tasks at a time become 1 (with "
            "`pip install tbb`, they run at once)",
            RuntimeWarning,
            stacklevel=2,
        )
        n_workers = 1
    return ThreadExecutor(n_workers) if n_workers > 1 else InProcessExecutor()
