"""Per-image work as small frozen task objects, and the content-keyed cache around them.

A task is a frozen dataclass: its fields are its inputs, and :meth:`Task.compute` does the
work from them (and from the entries of other tasks it reads, by key), returning the arrays
and metadata of its result. It does not key, read or write its own entry: :func:`cached`
does, around it. The key (:func:`key_of`) digests the task's kind, its code version
(:func:`~._task_keys.task_key`) and every field the result depends on; a field that only
says *how* to compute what another field already determines (the frame's description
beside its digest, the grid beside a key that holds it) is marked :data:`NOT_KEYED`.
:func:`key_of` is the only caller of ``task_key``: an entry a reduction adds up on the
driver (the mean frame F, its spread) is keyed the same way, by a frozen description of
its inputs (a :class:`Keyed`).

The driver makes a plan of tasks per registration and runs them through
:func:`run_plan` on its executor (in this process, on threads, or on a Dask cluster:
tasks are small and pickle), then reduces their entries.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Iterator, Sequence
from typing import Any, ClassVar

import numpy as np

from ..io._cache import DiskCache
from ._task_keys import task_key

#: ``field(metadata=NOT_KEYED)``: a field the task's result does not depend on beyond the
#: keyed ones (left out of its key).
NOT_KEYED = {"keyed": False}

#: One cache entry's content: its arrays by name, and its JSON metadata.
Entry = tuple[dict[str, np.ndarray], dict[str, Any]]


class Keyed:
    """A frozen dataclass that keys a cache entry: its :attr:`kind` (the kind of entry, and
    of the code version in :func:`key_of`) and its fields (the inputs)."""

    kind: ClassVar[str]


class Task(Keyed):
    """What every task has: its :attr:`kind` and :meth:`compute`. Subclasses are frozen
    dataclasses.

    A task's result is one entry of its kind, unless :meth:`entry_kinds` says otherwise.
    """

    def compute(self, cache: DiskCache) -> Entry:
        """The result's arrays and metadata; `cache` holds the entries it reads."""
        raise NotImplementedError

    def entry_kinds(self) -> tuple[str, ...]:
        """The kinds of entry the result is stored as, all under the task's one key: its
        own kind; a task whose result is read two ways overrides this and
        :meth:`compute_entries`."""
        return (self.kind,)

    def compute_entries(self, cache: DiskCache) -> dict[str, Entry]:
        """The result as one :data:`Entry` per kind of :meth:`entry_kinds`."""
        return {self.kind: self.compute(cache)}


def key_of(task: Keyed) -> str:
    """The cache key of `task`: its kind, code version and keyed fields, in field order."""
    parts = [
        getattr(task, f.name) for f in dataclasses.fields(task) if f.metadata.get("keyed", True)
    ]
    return task_key(task.kind, *parts)


def cached(task: Task, cache: DiskCache) -> tuple[str, dict[str, Any], bool]:
    """Run `task` once: ``(its key, its first entry's metadata, whether it was cached
    already)``.

    A second call with equal keyed fields finds the entries and computes nothing. The
    metadata is what the entry holds (JSON: lists, not tuples; Python floats), whether it
    was just computed or found.
    """
    key = key_of(task)
    kinds = task.entry_kinds()
    found = [cache.get(kind, key) for kind in kinds]
    if all(entry is not None for entry in found):
        return key, dict(found[0].meta), True
    entries = task.compute_entries(cache)
    if set(entries) != set(kinds):
        raise RuntimeError(f"{type(task).__name__}: entries {sorted(entries)}, not {kinds}")
    # the metadata as a later run reads it back, so that found and computed look alike
    metas = {kind: json.loads(json.dumps(entries[kind][1])) for kind in kinds}
    for kind in kinds:
        cache.put(kind, key, entries[kind][0], metas[kind])
    return key, metas[kinds[0]], False


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


def plan_keys(executor, plan: Sequence[Keyed], *, desc: str) -> list[str]:
    """Every task's :func:`key_of`, in plan order, computed on `executor`'s workers (a key
    digests the content of its input files, which each process keeps once read)."""
    keys = [""] * len(plan)
    for i, key in executor.map(key_of, [(task,) for task in plan], desc=desc, progress=False):
        keys[i] = key
    return keys
