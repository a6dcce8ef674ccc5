"""The Dask path writes the same results.json as the in-process path; what cache keys hold.

Issue 25: ``--scheduler local`` reported ``inverse_consistency_mm = 0.0`` for every
registration, and a rerun that reused its cache kept the 0.0.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest
import SimpleITK as sitk
import yaml
from test_evaluate import make_case

import itk_nrreval as nr
from data_synth import make_population, write_population
from itk_nrreval import _version
from itk_nrreval._pipeline import _task_keys
from itk_nrreval.io.plausibility import (
    INVERSE_CONSISTENCY_STEP,
    INVERSE_FIELD_STEP,
    INVERSE_REFINE_STEPS,
)
from itk_nrreval.io.transforms import PointwiseInverse

pytest.importorskip("dask.distributed")

KW = dict(n_samples=2000, seed=5, progress=False)
REL = 1e-9  # every float of results.json, relative (absolute near zero: ABS)
ABS = 1e-12
# What legitimately differs between the two runs: how the run was executed. Nothing else
# (no timings, no paths of the cache or output folder are in results.json).
EXECUTION_FIELDS = {
    ("run", "scheduler"),  # None in process, "local" on the cluster
    ("run", "workers"),  # 1 in process, the cluster's worker count
    ("run", "threads"),  # tasks at once in process (2 by default), 1 per Dask worker
}


def assert_same_json(a, b, path=(), *, ignore=EXECUTION_FIELDS) -> None:
    """`a` and `b` equal key by key, recursively; floats to REL (or ABS near zero).

    `ignore`: key paths (tuples) not compared.
    """
    if path in ignore:
        return
    where = "/".join(map(str, path)) or "<root>"
    if isinstance(a, dict):
        assert isinstance(b, dict) and sorted(a) == sorted(b), where
        for k in a:
            assert_same_json(a[k], b[k], (*path, k), ignore=ignore)
    elif isinstance(a, list):
        assert isinstance(b, list) and len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same_json(x, y, (*path, i), ignore=ignore)
    elif isinstance(a, float) and type(b) is float:
        assert math.isclose(a, b, rel_tol=REL, abs_tol=ABS), (where, a, b)
    else:
        assert type(a) is type(b) and a == b, (where, a, b)


def results_json(folder) -> dict:
    return json.loads((folder / "results.json").read_text())


def population(tmp_path, *, size: int = 96):
    """N = 4 generated subjects; "truth": affine + displacement field per subject.

    96 x 96 voxels: a displacement field of 147 kB, above glibc's 128 kB mmap threshold
    (issue 25 showed with fields above it; the demo's are 141 x 141).
    """
    pop = make_population("phantom", dim=2, n=4, seed=3, size=size)
    return write_population(pop, tmp_path / "data", montage=False, progress=False)


def test_dask_results_json_equals_in_process(tmp_path):
    manifest = population(tmp_path)
    nr.evaluate(manifest, **KW).write(tmp_path / "single", figures=False)
    nr.evaluate(
        manifest,
        execution=nr.Execution(scheduler="local", workers=1),
        **KW,
    ).write(tmp_path / "dask", figures=False)
    single, scaled = results_json(tmp_path / "single"), results_json(tmp_path / "dask")
    # inverse consistency is computable here, and not the 0.0 of issue 25
    assert single["registrations"]["truth"]["plausibility"]["inverse_consistency_mm"] > 1e-6
    assert (single["run"]["scheduler"], scaled["run"]["scheduler"]) == (None, "local")
    assert_same_json(single, scaled)


_MEASURE_IN_SUBPROCESS = """
import sys
import SimpleITK as sitk
from itk_nrreval.io.plausibility import deformation_measures
t = sitk.ReadTransform(sys.argv[1])
reference = sitk.ReadImage(sys.argv[2])
print(repr(deformation_measures(t, reference).plausibility.inverse_consistency_mm))
"""


def test_inverse_consistency_under_the_dask_workers_allocator(tmp_path):
    """deformation_measures in a process with Dask's worker setting MALLOC_TRIM_THRESHOLD_.

    That setting fixes glibc's mmap threshold at 128 kB, so a freed field's memory goes back
    to the system at once: reading an image's voxels after the image is gone (the cause of
    issue 25) gives zeros there. The reference is the definition, point by point:
    ``mean_p |T^-1(T(p)) - p|`` with T by TransformPoint, over the voxel centres p of even
    indices (issue 30), with the inverse evaluated as deformation_measures evaluates it (a
    coarse inverse on every INVERSE_FIELD_STEP-th node, refined at each point).
    """
    manifest = population(tmp_path)
    data = yaml.safe_load(manifest.read_text())["registrations"]["truth"]
    path, ref_path = (manifest.parent / p for p in (data["transforms"][0], data["reference"]))
    t, reference = sitk.ReadTransform(str(path)), sitk.ReadImage(str(ref_path))
    inverse = PointwiseInverse(
        t, grid=reference, field_step=INVERSE_FIELD_STEP, refine_steps=INVERSE_REFINE_STEPS
    )
    nx, ny = reference.GetSize()
    points = [
        reference.TransformIndexToPhysicalPoint((i, j))
        for j in range(0, ny, INVERSE_CONSISTENCY_STEP)
        for i in range(0, nx, INVERSE_CONSISTENCY_STEP)
    ]
    back = inverse.map_points(np.array([t.TransformPoint(p) for p in points]))
    errors = [math.dist(b, p) for b, p in zip(back, points, strict=True)]
    expected = math.fsum(errors) / len(errors)
    assert expected > 1e-6  # a field's numerical inverse: not exact
    env = {**os.environ, "MALLOC_TRIM_THRESHOLD_": "65536"}
    done = subprocess.run(
        [sys.executable, "-c", _MEASURE_IN_SUBPROCESS, str(path), str(ref_path)],
        env=env,
        capture_output=True,
        text=True,
        check=True,
    )
    assert float(done.stdout) == pytest.approx(expected, rel=1e-9)


# ----------------------------------------------------------------------------- cache keys

FAST = dict(n_samples=500, seed=5, progress=False, confidence=False)
N_IMAGES = 6  # make_case's


def one_registration(tmp_path):
    """make_case's registration "truth" alone (displacement fields; no frame estimates)."""
    data = make_case(tmp_path)
    data["registrations"] = {"truth": data["registrations"]["truth"]}
    path = tmp_path / "manifest.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path, tmp_path / "cache"


def measures_metas(cache) -> list:
    return sorted((cache / "measures").glob("*/*/entry.json"))


#: Entries of every kind kept, so that what a rerun reuses shows (issue 30: by default a
#: registration's resampled images leave the cache once its scores are taken).
KEPT = dict(keep_resampled=True)


def inverse_consistency(result) -> dict:
    return {n: s.plausibility.inverse_consistency_mm for n, s in result.scores.items()}


@pytest.mark.parametrize(
    "first, second",
    [
        ({"inverse_consistency": False}, {}),
        ({}, {"resampling": nr.Resampling(interpolation="bspline")}),
        ({}, {"resampling": nr.Resampling(label_interpolation="nearest")}),
        ({}, {"resampling": nr.Resampling(label_interpolation="gaussian", label_sigma_mm=1.0)}),
        (
            {"resampling": nr.Resampling(label_interpolation="gaussian", label_sigma_mm=1.0)},
            {"resampling": nr.Resampling(label_interpolation="gaussian", label_sigma_mm=2.0)},
        ),
    ],
)
def test_cache_not_reused_when_a_per_image_option_changes(tmp_path, first, second):
    """Every option that changes a per-image result changes its key: it is recomputed.

    The reference is a run of `second` on a fresh cache.
    """
    manifest, cache = one_registration(tmp_path)
    nr.evaluate(manifest, execution=nr.Execution(cache=cache, **KEPT), **first, **FAST)
    again = nr.evaluate(manifest, execution=nr.Execution(cache=cache, **KEPT), **second, **FAST)
    # the transforms' measures, or the resampled images: whichever the option changes
    assert again.run["cache_computed"] == N_IMAGES
    fresh = nr.evaluate(
        manifest, execution=nr.Execution(cache=tmp_path / "fresh"), **second, **FAST
    )
    # "run" holds the cache counts: computed afresh or not, they differ by construction
    assert_same_json(fresh.to_dict(), again.to_dict(), ignore={("run",)})


def test_cache_not_reused_across_computation_versions(tmp_path, monkeypatch):
    """Entries of an older computation of a task (here: the 0.0 of issue 25) are not reused.

    The run under the older version number writes its entries, which are then changed to
    what the buggy code wrote (inverse_consistency_mm 0.0); that version reuses them, the
    current one recomputes them (the transforms' measures: since issue 30 their own task).
    """
    manifest, cache = one_registration(tmp_path)
    current = _task_keys._TASK_VERSIONS["measures"]
    execution = nr.Execution(cache=cache, **KEPT)
    with monkeypatch.context() as patch:
        patch.setitem(_task_keys._TASK_VERSIONS, "measures", current - 1)
        right = inverse_consistency(nr.evaluate(manifest, execution=execution, **FAST))
        for path in measures_metas(cache):
            entry = json.loads(path.read_text())
            entry["meta"]["plausibility"]["inverse_consistency_mm"] = 0.0
            path.write_text(json.dumps(entry))
        old = nr.evaluate(manifest, execution=execution, **FAST)
        assert old.run["cache_computed"] == 0  # the tampered entries are the ones read
        assert set(inverse_consistency(old).values()) == {0.0}
    new = nr.evaluate(manifest, execution=execution, **FAST)
    assert new.run["cache_computed"] == N_IMAGES  # the measures; the resampled images kept
    assert inverse_consistency(new) == pytest.approx(right, rel=1e-12)
    assert min(right.values()) > 1e-6  # measured, not the 0.0 of issue 25


def test_cache_not_reused_across_package_versions(tmp_path, monkeypatch):
    manifest, cache = one_registration(tmp_path)
    execution = nr.Execution(cache=cache, **KEPT)
    with monkeypatch.context() as patch:
        patch.setattr(_version, "__version__", "0.0.1")
        nr.evaluate(manifest, execution=execution, **FAST)
    new = nr.evaluate(manifest, execution=execution, **FAST)
    # every transform measured and every image resampled again
    assert new.run["cache_computed"] == 2 * N_IMAGES and new.run["cache_reused"] == 0
    assert nr.evaluate(manifest, execution=execution, **FAST).run["cache_reused"] == 2 * N_IMAGES
