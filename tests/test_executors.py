"""The executors every parallel command maps its tasks through (itk_nrreval._executors)."""

from __future__ import annotations

import time

import pytest

from itk_nrreval._executors import InProcessExecutor, ThreadExecutor, local_executor


def _slow_square(x: int, delay: float) -> int:
    time.sleep(delay)
    return x * x


def test_threads_yield_every_result_with_its_index():
    # the first task is the slowest, so results may come out of order: each has its index
    calls = [(i, 0.05 if i == 0 else 0.0) for i in range(6)]
    got = list(ThreadExecutor(3).map(_slow_square, calls, desc="t", progress=False))
    assert sorted(got) == [(i, i * i) for i in range(6)]
    ordered = list(InProcessExecutor().map(_slow_square, calls, desc="t", progress=False))
    assert ordered == [(i, i * i) for i in range(6)]


def _fails_on(x: int, bad: int) -> int:
    if x == bad:
        raise ValueError(f"task {x} failed")
    return x


def test_a_failing_task_raises_from_the_map():
    calls = [(i, 2) for i in range(5)]
    with pytest.raises(ValueError, match="task 2 failed"):
        list(ThreadExecutor(2).map(_fails_on, calls, desc="t", progress=False))


def test_local_executor_is_threads_only_for_more_than_one():
    assert isinstance(local_executor(1), InProcessExecutor)
    assert isinstance(local_executor(3), ThreadExecutor) and local_executor(3).n_workers == 3
