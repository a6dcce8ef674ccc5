"""Per-image work as small frozen task objects, and the content-keyed cache around them.

A task is a frozen dataclass: its fields are its inputs, and :meth:`compute` does the work
from them (and from the entries of other tasks it reads, by key), returning the arrays and
metadata of its result. It does not key, read or write its own entry: :func:`cached` does,
around it. The key (:func:`key_of`) digests the task's kind, its code version
(:func:`~._task_keys.task_key`) and every field the result depends on; a field that only
says *how* to compute what another field already determines (the frame's description
beside its digest, the grid beside a key that holds it) is marked :data:`NOT_KEYED`.

The driver makes a plan of tasks per registration and runs them through
:func:`run_plan` on its executor (in this process, on threads, or on a Dask cluster:
tasks are small and pickle), then reduces their entries.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Sequence
from typing import Any, ClassVar

import numpy as np

from .._cache import DiskCache
from ._task_keys import task_key

#: ``field(metadata=NOT_KEYED)``: a field the task's result does not depend on beyond the
#: keyed ones (left out of its key).
NOT_KEYED = {"keyed": False}


class Task:
    """What every task has: its :attr:`kind` (the cache's kind of entry) and
    :meth:`compute`. Subclasses are frozen dataclasses."""

    kind: ClassVar[str]

    def compute(self, cache: DiskCache) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """The result's arrays and metadata; `cache` holds the entries it reads."""
        raise NotImplementedError


def key_of(task: Task) -> str:
    """The cache key of `task`: its kind, code version and keyed fields, in field order."""
    parts = [
        getattr(task, f.name) for f in dataclasses.fields(task) if f.metadata.get("keyed", True)
    ]
    return task_key(task.kind, *parts)


def cached(task: Task, cache: DiskCache) -> tuple[str, dict[str, Any], bool]:
    """Run `task` once: ``(its key, its entry's metadata, whether it was cached already)``.

    A second call with equal fields finds the entry and computes nothing.
    """
    key = key_of(task)
    entry = cache.get(task.kind, key)
    if entry is not None:
        return key, dict(entry.meta), True
    arrays, meta = task.compute(cache)
    cache.put(task.kind, key, arrays, meta)
    return key, dict(meta), False


def run_cached(root: str, task: Task) -> tuple[str, dict[str, Any], bool]:
    """:func:`cached` on the cache folder `root`: what an executor runs (a worker opens the
    folder itself)."""
    return cached(task, DiskCache(root))


def run_plan(
    executor, root: str, plan: Sequence[Task], *, desc: str, progress: bool
) -> Iterator[tuple[int, str, dict[str, Any], bool]]:
    """Run every task of `plan` through the cache folder `root` on `executor` (its ``map``:
    in process, threads or Dask); yield ``(index into plan, key, metadata, reused)`` as
    each ends, in any order."""
    calls = [(root, task) for task in plan]
    for i, (key, meta, reused) in executor.map(run_cached, calls, desc=desc, progress=progress):
        yield i, key, meta, reused
