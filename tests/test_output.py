"""Outputs appear whole, with ordinary permissions, or not at all."""

from __future__ import annotations

import os

import pytest

from itk_nrreval._output import atomic_path, write_json


def test_written_file_has_the_permissions_of_an_ordinary_file(tmp_path):
    (tmp_path / "plain.txt").write_text("x")
    write_json(tmp_path / "out.json", {"a": 1})
    mode = os.stat(tmp_path / "out.json").st_mode & 0o777
    assert mode == os.stat(tmp_path / "plain.txt").st_mode & 0o777
    assert (tmp_path / "out.json").read_text() == '{\n  "a": 1\n}\n'


def test_failure_leaves_neither_the_file_nor_a_temporary(tmp_path):
    (tmp_path / "keep.json").write_text("old")
    with pytest.raises(RuntimeError, match="interrupted"):
        with atomic_path(tmp_path / "keep.json") as tmp:
            tmp.write_text("half")
            raise RuntimeError("interrupted")
    assert (tmp_path / "keep.json").read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.json"]


def test_temporary_keeps_the_suffix(tmp_path):
    with atomic_path(tmp_path / "image.nii.gz") as tmp:
        assert tmp.name.endswith(".nii.gz") and tmp.parent == tmp_path
        tmp.write_bytes(b"x")
    assert (tmp_path / "image.nii.gz").exists()


def test_reports_leave_the_matplotlib_backend_alone(tmp_path):
    import matplotlib
    from test_evaluate import make_case

    import itk_nrreval as nr
    from itk_nrreval.reports import write_reports

    before = matplotlib.get_backend()
    matplotlib.use("svg")  # a backend a user might have chosen
    try:
        make_case(tmp_path)
        result = nr.evaluate(tmp_path / "manifest.yaml", n_samples=500, progress=False)
        written = write_reports(result, tmp_path / "out")
        assert any(p.suffix == ".png" for p in written)
        assert matplotlib.get_backend() == "svg"
    finally:
        matplotlib.use(before)


def test_staged_folder_swaps_a_complete_result_in_and_keeps_the_cache(tmp_path):
    from itk_nrreval._output import staged_folder

    out = tmp_path / "out"
    (out / "cache").mkdir(parents=True)
    (out / "cache" / "entry").write_text("cached")
    (out / "results.json").write_text("old")
    (out / "stale.png").write_text("old figure")
    with staged_folder(out) as stage:
        assert stage.parent == tmp_path and stage != out
        (stage / "results.json").write_text("new")
    assert sorted(p.name for p in out.iterdir()) == ["cache", "results.json"]
    assert (out / "results.json").read_text() == "new"
    assert (out / "cache" / "entry").read_text() == "cached"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # nothing left beside it


def test_staged_folder_failure_leaves_the_previous_result(tmp_path):
    import pytest

    from itk_nrreval._output import staged_folder

    out = tmp_path / "out"
    out.mkdir()
    (out / "results.json").write_text("old")
    with pytest.raises(KeyboardInterrupt):
        with staged_folder(out) as stage:
            (stage / "results.json").write_text("half")
            raise KeyboardInterrupt
    assert (out / "results.json").read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    # a stage left by a killed process is removed by the next run
    dead = tmp_path / "out.tmp-999999999-abc"
    dead.mkdir()
    with staged_folder(out):
        pass
    assert not dead.exists()


def test_register_cli_replaces_its_output_folder_whole(tmp_path, capsys):
    """A second `nrreval register` into the same folder leaves only the new run's files."""
    import numpy as np
    import SimpleITK as sitk

    from itk_nrreval.cli import main

    paths = []
    for i in range(3):
        arr = np.zeros((24, 24), np.float32)
        arr[6 + i : 16 + i, 5:17] = 100.0
        paths.append(str(tmp_path / f"s{i}.nii.gz"))
        sitk.WriteImage(sitk.GetImageFromArray(arr), paths[-1])
    out = tmp_path / "affine"
    out.mkdir()
    (out / "stale_from_an_old_run.h5").write_text("old")
    args = ["register", "--images", *paths, "--method", "affine", "--out", str(out)]
    assert main([*args, "--no-progress", "--reference", paths[0]]) == 0
    assert not (out / "stale_from_an_old_run.h5").exists()
    assert sorted(p.name for p in out.iterdir()) == sorted(
        ["reference.nii.gz", "registration.json", *(f"{i:03d}_s{i}.h5" for i in range(3))]
    )
    assert [p for p in tmp_path.iterdir() if ".tmp-" in p.name or ".old-" in p.name] == []
    # the manifest points at the final folder, not the temporary one it was written in
    from itk_nrreval.manifest import load_manifest

    m = load_manifest(tmp_path / "manifest.yaml")
    assert all(str(t[0]).startswith(str(out)) for t in m.registrations["affine"].transforms)
