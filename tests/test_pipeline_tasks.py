"""The evaluate pipeline's per-image tasks are frozen objects keyed by their inputs, and the
content-keyed cache is a wrapper around running them (issue 43): a task runs once, a
changed input runs it again, a field that is not an input of its result does not, and no
task reads or writes its own entry."""

from __future__ import annotations

import ast
import dataclasses
import inspect
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk

from itk_nrreval._cache import DiskCache
from itk_nrreval._images import Geometry
from itk_nrreval._pipeline import _common_frame, _image_tasks, _label_metrics, _tasks

TASKS = [
    _image_tasks.MeasureTransform,
    _image_tasks.ResampleImage,
    _image_tasks.LabelSums,
    _image_tasks.BiasCorrect,
    _image_tasks.ResampleBrainMask,
    _label_metrics.CrispLabels,
    _label_metrics.LabelDistances,
    _common_frame.RegistrationMask,
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


def test_no_task_outside_the_task_objects_keys_itself():
    """Every ``task_key`` call of the per-image tasks is in the wrapper (the frame's tasks,
    which estimate F from every image, are the driver's)."""
    for module in (_image_tasks, _label_metrics):
        text = Path(module.__file__).read_text()
        assert "task_key(" not in text, module.__name__
