"""Where tasks run: one protocol for every command that works in parallel.

A task is a function and its argument tuples; an executor maps it over them and yields
``(index, result)`` as each ends. :class:`InProcessExecutor` runs them here, in order;
:class:`ThreadExecutor` on threads of this process (for tasks on arrays already in memory
whose heavy parts release the GIL: SimpleITK, numpy); :class:`itk_nrreval._scaleout.DaskExecutor`
on a cluster (evaluate's ``Execution(scheduler=...)``). Results never depend on which one
ran them: each caller places a result by its index.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor, as_completed
from typing import Any, Protocol

from ._progress import progress_bar

__all__ = ["Executor", "InProcessExecutor", "ThreadExecutor", "local_executor", "ITK_READ_LOCK"]


#: ITK's HDF5 library is not thread-safe (two threads reading ``.h5`` transforms at once end
#: the process: "HDF5: infinite loop closing library"). Every whole-file read by SimpleITK
#: (``ReadImage``, ``ReadTransform``) takes this lock, so that tasks on threads of one process
#: (or callers' own threads) can read; a read is about 3 % of a task's time at 1 mm. Header
#: reads (``ImageFileReader.ReadImageInformation``, in the manifest checks) do not.
ITK_READ_LOCK = threading.Lock()


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


def local_executor(n_workers: int) -> InProcessExecutor | ThreadExecutor:
    """`n_workers` threads of this process, or the caller's own thread for one."""
    return ThreadExecutor(n_workers) if n_workers > 1 else InProcessExecutor()
