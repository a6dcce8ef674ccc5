"""evaluate's tasks on threads of one process: the same numbers as one at a time, and a
numba without a thread-safe threading layer falls back to one at a time instead of dying."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import warnings

import pytest
from test_orientation import ROTATION_3D, SHIFT_3D, make_case_3d, moved_copy
from test_pipeline import KW, assert_same_scores, with_mask

import itk_nrreval as nr
from itk_nrreval._executors import kernels_thread_safe


def test_threads_give_the_numbers_of_one_at_a_time_3d_oblique(tmp_path):
    """3D, anisotropic voxels, oblique axes, a registration reached through the mean frame."""
    (tmp_path / "plain").mkdir()
    make_case_3d(tmp_path / "plain")
    moved_copy(tmp_path / "plain", tmp_path / "moved", ROTATION_3D, SHIFT_3D)
    manifest = tmp_path / "moved" / "manifest.yaml"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        one = nr.evaluate(manifest, execution=nr.Execution(threads=1), **KW)
        two = nr.evaluate(manifest, execution=nr.Execution(threads=2), **KW)
    assert one.run["threads"] == 1 and two.run["threads"] == 2
    assert two.scores["perturbed"].frame.method == "mean"
    assert_same_scores(one, two, rel=0)
    for name in one.scores:
        a, b = one.scores[name], two.scores[name]
        assert b.plausibility == a.plausibility
        assert b.frame.per_image_mm == a.frame.per_image_mm
        assert b.coverage == a.coverage


def test_default_is_two_threads_where_the_kernels_allow(tmp_path):
    result = nr.evaluate(with_mask(tmp_path), **KW)
    cores = len(os.sched_getaffinity(0))
    assert result.run["threads"] == (2 if cores >= 2 and kernels_thread_safe() else 1)


_RUN = """
import json, sys, warnings
import numba
import itk_nrreval as nr
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    r = nr.evaluate(sys.argv[1], execution=nr.Execution(threads=2), n_samples=2000, seed=5,
                    progress=False)
print(json.dumps({
    "layer": numba.threading_layer(),
    "threads": r.run["threads"],
    "warnings": [str(w.message) for w in caught if "threading layer" in str(w.message)],
    "specificity": {k: s.specificity.value for k, s in r.scores.items()},
}))
"""


def test_workqueue_layer_runs_one_task_at_a_time_with_a_warning(tmp_path):
    """numba's fallback layer ends the process when two threads launch kernels at once."""
    manifest = with_mask(tmp_path)
    env = dict(os.environ, NUMBA_THREADING_LAYER="workqueue")
    done = subprocess.run(
        [sys.executable, "-c", _RUN, str(manifest)],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    got = json.loads(done.stdout.strip().splitlines()[-1])
    assert got["layer"] == "workqueue"
    assert got["threads"] == 1
    assert len(got["warnings"]) == 1 and "2 tasks at a time become 1" in got["warnings"][0]
    here = nr.evaluate(manifest, execution=nr.Execution(threads=1), **KW)
    assert got["specificity"] == pytest.approx(
        {k: s.specificity.value for k, s in here.scores.items()}, rel=1e-12
    )
