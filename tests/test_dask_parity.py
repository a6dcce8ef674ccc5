"""The Dask path writes the same results.json as the in-process path, and the cache keys.

Issue 25: ``--scheduler local`` reported ``inverse_consistency_mm = 0.0`` for every
registration, and a rerun that reused its cache kept the 0.0.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import pytest
import SimpleITK as sitk
import yaml

import itk_nrreval as nr
from data_synth import make_population, write_population
from itk_nrreval.transforms import invert

pytest.importorskip("dask.distributed")

KW = dict(n_samples=2000, seed=5, progress=False, figures=False)
REL = 1e-9  # every float of results.json, relative (absolute near zero: ABS)
ABS = 1e-12
# What legitimately differs between the two runs: how the run was executed. Nothing else
# (no timings, no paths of the cache or output folder are in results.json).
EXECUTION_FIELDS = {
    ("run", "scheduler"),  # None in process, "local" on the cluster
    ("run", "workers"),  # 1 in process, the cluster's worker count
}


def assert_same_json(a, b, path=()) -> None:
    """`a` and `b` equal key by key, recursively; floats to REL (or ABS near zero)."""
    if path in EXECUTION_FIELDS:
        return
    where = "/".join(map(str, path)) or "<root>"
    if isinstance(a, dict):
        assert isinstance(b, dict) and sorted(a) == sorted(b), where
        for k in a:
            assert_same_json(a[k], b[k], (*path, k))
    elif isinstance(a, list):
        assert isinstance(b, list) and len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same_json(x, y, (*path, i))
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
    return write_population(pop, tmp_path / "data", montage=False, show_progress=False)


def test_dask_results_json_equals_in_process(tmp_path):
    manifest = population(tmp_path)
    nr.evaluate(manifest, out=tmp_path / "single", **KW)
    nr.evaluate(manifest, out=tmp_path / "dask", scheduler="local", workers=1, **KW)
    single, scaled = results_json(tmp_path / "single"), results_json(tmp_path / "dask")
    # inverse consistency is computable here, and not the 0.0 of issue 25
    assert single["registrations"]["truth"]["plausibility"]["inverse_consistency_mm"] > 1e-4
    assert (single["run"]["scheduler"], scaled["run"]["scheduler"]) == (None, "local")
    assert_same_json(single, scaled)


_MEASURE_IN_SUBPROCESS = """
import sys
import SimpleITK as sitk
from itk_nrreval.plausibility import deformation_measures
t = sitk.ReadTransform(sys.argv[1])
reference = sitk.ReadImage(sys.argv[2])
print(repr(deformation_measures(t, reference)[0].inverse_consistency_mm))
"""


def test_inverse_consistency_under_the_dask_workers_allocator(tmp_path):
    """deformation_measures in a process with Dask's worker setting MALLOC_TRIM_THRESHOLD_.

    That setting fixes glibc's mmap threshold at 128 kB, so a freed field's memory goes back
    to the system at once: reading an image's voxels after the image is gone (the cause of
    issue 25) gives zeros there. The reference is the definition, point by point:
    ``mean_p |T^-1(T(p)) - p|`` with TransformPoint, over every voxel centre p.
    """
    manifest = population(tmp_path)
    data = yaml.safe_load(manifest.read_text())["registrations"]["truth"]
    path, ref_path = (manifest.parent / p for p in (data["transforms"][0], data["reference"]))
    t, reference = sitk.ReadTransform(str(path)), sitk.ReadImage(str(ref_path))
    inverse = invert(t, grid=reference)
    nx, ny = reference.GetSize()
    errors = []
    for j in range(ny):
        for i in range(nx):
            p = reference.TransformIndexToPhysicalPoint((i, j))
            errors.append(math.dist(inverse.TransformPoint(t.TransformPoint(p)), p))
    expected = math.fsum(errors) / len(errors)
    assert expected > 1e-4  # a field's numerical inverse: not exact
    env = {**os.environ, "MALLOC_TRIM_THRESHOLD_": "65536"}
    done = subprocess.run(
        [sys.executable, "-c", _MEASURE_IN_SUBPROCESS, str(path), str(ref_path)],
        env=env,
        capture_output=True,
        text=True,
        check=True,
    )
    assert float(done.stdout) == pytest.approx(expected, rel=1e-9)
