"""The evaluate pipeline's per-image tasks are frozen objects keyed by their inputs, and the
content-keyed cache is a wrapper around running them (issue 43): a task runs once, a
changed input runs it again, a field that is not an input of its result does not, and no
task reads or writes its own entry."""

from __future__ import annotations

import ast
import dataclasses
import inspect
from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest
import SimpleITK as sitk

from itk_nrreval._pipeline import _common_frame, _image_tasks, _label_metrics, _tasks
from itk_nrreval.io._cache import DiskCache
from itk_nrreval.io._images import Geometry

TASKS = [
    _image_tasks.MeasureTransform,
    _image_tasks.ResampleImage,
    _image_tasks.LabelSums,
    _image_tasks.BiasCorrect,
    _image_tasks.ResampleBrainMask,
    _label_metrics.CrispLabels,
    _label_metrics.LabelDistances,
    _common_frame.RegistrationMask,
    _common_frame.EstimateFrame,
    _common_frame.FrameDisplacement,
]


@pytest.fixture()
def case(tmp_path):
    """An oblique, anisotropic 3D image and a translation, on a grid not co-located with
    the image."""
    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    grid = Geometry((10, 9, 8), (1.2, 0.9, 1.5), (-5.0, -4.0, -3.0), tuple(q.ravel()))
    image = sitk.GetImageFromArray(rng.uniform(1.0, 2.0, size=(12, 11, 10)).astype(np.float32))
    image.SetSpacing((1.1, 1.0, 1.3))
    image.SetOrigin((-9.0, -8.0, -7.0))
    path = tmp_path / "image.nii.gz"
    sitk.WriteImage(image, str(path))
    transform = tmp_path / "t.tfm"
    sitk.WriteTransform(sitk.TranslationTransform(3, (0.7, -0.4, 0.2)), str(transform))
    return grid, path, transform


def _resample(grid, image, transform, **changes):
    fields = {
        "grid": grid,
        "image": image,
        "labels": None,
        "item": [str(transform)],
        "frame": ("identity",),
        "frame_digest": "identity",
        "reg_grid": grid,
        "interpolation": "linear",
        "label_resampling": ("linear", None),
    }
    return _image_tasks.ResampleImage(**{**fields, **changes})


def test_a_task_runs_once_and_again_only_when_an_input_changes(tmp_path, case):
    grid, image, transform = case
    root = str(tmp_path / "cache")
    task = _resample(grid, image, transform)
    key, meta, reused = _tasks.run_cached(root, task)
    assert not reused
    again, meta_again, reused_again = _tasks.run_cached(root, _resample(grid, image, transform))
    assert (again, reused_again, meta_again) == (key, True, meta)
    # an input changed: another key, computed anew
    cubic = _resample(grid, image, transform, interpolation="bspline")
    other, _, reused_other = _tasks.run_cached(root, cubic)
    assert other != key and not reused_other
    # F's description is not keyed (its digest is): the same entry
    described = _resample(grid, image, transform, frame=("chain", "anything"))
    assert _tasks.key_of(described) == key
    # the entry is what the task computes, stored by the wrapper
    stored = DiskCache(root).open("resampled", key).array("image")
    arrays, _ = task.compute(DiskCache(root))
    np.testing.assert_array_equal(stored, arrays["image"])


@pytest.mark.parametrize("task_class", TASKS, ids=lambda c: c.__name__)
def test_every_task_is_a_frozen_object_that_does_not_key_or_store_itself(task_class):
    assert dataclasses.is_dataclass(task_class)
    assert task_class.__dataclass_params__.frozen
    assert isinstance(task_class.kind, str) and task_class.kind
    source = inspect.getsource(task_class)
    called = {
        node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", "")
        for node in ast.walk(ast.parse(source.lstrip()))
        if isinstance(node, ast.Call)
    }
    assert not called & {"task_key", "put", "get", "cached", "run_cached"}, called


def test_only_the_wrapper_keys_an_entry():
    """``task_key`` is called in one place, :func:`_tasks.key_of`: every task, and every
    entry a reduction adds up on the driver (the mean frame, its spread), is keyed by a
    frozen description of its inputs."""
    package = Path(_tasks.__file__).resolve().parents[1]
    callers = {
        str(path.relative_to(package))
        for path in package.rglob("*.py")
        if "task_key(" in path.read_text()
    }
    assert callers == {"_pipeline/_tasks.py", "_pipeline/_task_keys.py"}
    tree = ast.parse(Path(_tasks.__file__).read_text())
    calling = {
        node.name
        for node in ast.walk(tree)
        if isinstance(node, ast.FunctionDef)
        and any(
            isinstance(c, ast.Call) and getattr(c.func, "id", "") == "task_key"
            for c in ast.walk(node)
        )
    }
    assert calling == {"key_of"}


def test_only_the_driver_runs_plans():
    """The task modules list tasks (plans) and compute nothing; the driver runs every plan
    through the cache wrapper (issue 43: a plan of tasks, then reductions, then a driver)."""
    folder = Path(_tasks.__file__).resolve().parent
    runners = {p.name for p in folder.glob("*.py") if "run_plan(" in p.read_text()}
    assert runners == {"_driver.py", "_tasks.py"}
    for module in (_image_tasks, _label_metrics):
        text = Path(module.__file__).read_text()
        assert "executor" not in text and "cached(" not in text, module.__name__


def test_a_task_stored_as_two_entries_runs_again_until_both_are_there(tmp_path, case):
    """The frame estimate is kept in 16-bit steps for the spread and, for the mean, as F is
    stored: two entries under one key. Found only when every entry it needs is there."""
    grid, _image, transform = case
    root = str(tmp_path / "cache")
    fields = {
        "grid": grid,
        "common_item": [transform],
        "item": [transform],
        "reg_grid": grid,
        "stored": np.dtype(np.uint16).str,
    }
    spread_only = _common_frame.EstimateFrame(**fields)
    for_mean = _common_frame.EstimateFrame(**fields, for_mean=True)
    assert _tasks.key_of(spread_only) == _tasks.key_of(for_mean)
    key, _, reused = _tasks.run_cached(root, spread_only)
    assert not reused
    disk = DiskCache(root)
    assert disk.get("estimate_steps", key) is not None and disk.get("estimate", key) is None
    assert _tasks.run_cached(root, spread_only)[2]
    assert not _tasks.run_cached(root, for_mean)[2]  # its second entry was missing
    assert _tasks.run_cached(root, for_mean)[2]
    disp = disk.get("estimate", key).array("disp")
    # T^-1 o T: the identity, within the coarse inverse's error
    assert disp.dtype == np.float32 and np.abs(disp).max() < 1e-2
    # another stored dtype: another key
    other = _common_frame.EstimateFrame(**{**fields, "stored": np.dtype(np.float32).str})
    assert _tasks.key_of(other) != key


@dataclasses.dataclass(frozen=True)
class _TupleMeta(_tasks.Task):
    """A task whose metadata holds a tuple and a numpy scalar."""

    kind: ClassVar[str] = "label_sums"
    x: int

    def compute(self, cache):
        return {}, {"pair": (self.x, 2.5), "half": np.float64(0.5)}


def test_a_found_result_looks_like_a_computed_one(tmp_path, case):
    """The wrapper returns the metadata as the entry holds it (JSON), computed or found."""
    disk = DiskCache(tmp_path / "cache")
    _, computed, reused = _tasks.cached(_TupleMeta(x=1), disk)
    _, found, reused_again = _tasks.cached(_TupleMeta(x=1), disk)
    assert (reused, reused_again) == (False, True)
    assert computed == found == {"pair": [1, 2.5], "half": 0.5}
    assert type(computed["half"]) is type(found["half"]) is float
