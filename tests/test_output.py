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
    from itk_nrreval.report import write_evaluation

    before = matplotlib.get_backend()
    matplotlib.use("svg")  # a backend a user might have chosen
    try:
        make_case(tmp_path)
        result = nr.evaluate(tmp_path / "manifest.yaml", n_samples=500, progress=False)
        written = write_evaluation(result, tmp_path / "out")
        assert any(p.suffix == ".png" for p in written)
        assert matplotlib.get_backend() == "svg"
    finally:
        matplotlib.use(before)


def _tree(folder):
    """Every path below `folder` with its bytes (None for a folder)."""
    return {
        str(p.relative_to(folder)): (p.read_bytes() if p.is_file() else None)
        for p in sorted(folder.rglob("*"))
    }


def test_staged_folder_replaces_only_its_own_entries_and_keeps_the_cache(tmp_path):
    from itk_nrreval._output import MARKER, staged_folder

    out = tmp_path / "out"
    with staged_folder(out, command="evaluate") as stage:  # a first run: `out` made and marked
        assert stage.parent == out and stage.name.startswith(".")
        (out / "cache").mkdir()
        (out / "cache" / "entry").write_text("cached")
        (stage / "results.json").write_text("old")
        (stage / "stale.png").write_text("old figure")
    (out / "notes.txt").write_text("the user's")  # not the toolkit's: never touched
    with staged_folder(out, command="evaluate") as stage:
        (stage / "results.json").write_text("new")
    assert sorted(p.name for p in out.iterdir()) == [MARKER, "cache", "notes.txt", "results.json"]
    assert (out / "results.json").read_text() == "new"
    assert (out / "cache" / "entry").read_text() == "cached"
    assert (out / "notes.txt").read_text() == "the user's"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # nothing left beside it


def test_staged_folder_refuses_a_folder_it_did_not_make(tmp_path):
    from itk_nrreval._errors import InputError
    from itk_nrreval._output import staged_folder

    out = tmp_path / "data"
    out.mkdir()
    (out / "image.nii.gz").write_text("the user's")
    before = _tree(tmp_path)
    with pytest.raises(InputError, match="did not make"):
        with staged_folder(out, command="evaluate") as stage:
            (stage / "results.json").write_text("new")
    assert _tree(tmp_path) == before


def test_staged_folder_never_replaces_a_file_it_did_not_write(tmp_path):
    """A user's file that appears, during a run, under a name the run writes is kept."""
    from itk_nrreval._errors import InputError
    from itk_nrreval._output import staged_folder

    out = tmp_path / "out"
    with pytest.raises(InputError, match="not written by nrreval"):
        with staged_folder(out, command="evaluate") as stage:
            (stage / "report.html").write_text("new")
            (out / "report.html").write_text("the user's")
    assert (out / "report.html").read_text() == "the user's"


def test_staged_folder_interrupted_keeps_the_previous_result_and_the_cache(tmp_path):
    from itk_nrreval._output import staged_folder

    out = tmp_path / "out"
    with staged_folder(out, command="evaluate") as stage:
        (stage / "results.json").write_text("old")
    with pytest.raises(KeyboardInterrupt):
        with staged_folder(out, command="evaluate") as stage:
            (out / "cache").mkdir()
            (out / "cache" / "entry").write_text("computed before the interruption")
            (stage / "results.json").write_text("half")
            raise KeyboardInterrupt
    assert (out / "results.json").read_text() == "old"
    assert (out / "cache" / "entry").exists()  # a rerun resumes from it
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    # a stage left by a killed process is removed by the next run
    dead = out / ".nrreval-stage-tmp-999999999-abc"
    dead.mkdir()
    with staged_folder(out, command="evaluate"):
        pass
    assert not dead.exists()


def test_staged_folder_bad_input_leaves_out_as_it_was(tmp_path):
    """Exit 2 leaves nothing behind: not the cache entries of the run, not a new folder."""
    from itk_nrreval._errors import InputError
    from itk_nrreval._output import staged_folder

    new = tmp_path / "new"
    with pytest.raises(InputError):
        with staged_folder(new, command="evaluate"):
            (new / "cache" / "ab").mkdir(parents=True)
            (new / "cache" / "ab" / "entry").write_text("x")
            raise InputError("bad image")
    assert not new.exists()

    out = tmp_path / "out"
    with staged_folder(out, command="evaluate") as stage:
        (out / "cache" / "aa").mkdir(parents=True)
        (out / "cache" / "aa" / "entry").write_text("kept")
        (stage / "results.json").write_text("old")
    (out / "notes.txt").write_text("the user's")
    before = _tree(out)
    with pytest.raises(InputError):
        with staged_folder(out, command="evaluate"):
            (out / "cache" / "bb").mkdir()
            (out / "cache" / "bb" / "entry").write_text("x")
            (out / "cache" / "aa" / "other").write_text("x")
            raise InputError("bad image")
    assert _tree(out) == before


def _blob_images(folder, stem: str) -> list[str]:
    """Three small 2D images, a bright block moved by one pixel each time."""
    import numpy as np
    import SimpleITK as sitk

    paths = []
    for i in range(3):
        arr = np.zeros((24, 24), np.float32)
        arr[6 + i : 16 + i, 5:17] = 100.0
        paths.append(str(folder / f"{stem}{i}.nii.gz"))
        sitk.WriteImage(sitk.GetImageFromArray(arr), paths[-1])
    return paths


def test_register_cli_replaces_its_own_files_only(tmp_path, capsys):
    """A second `nrreval register` into its folder replaces the first run's files, keeps
    a user's file there, and refuses a non-empty folder it did not make."""
    from itk_nrreval.cli import main

    out = tmp_path / "affine"
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "keep.txt").write_text("the user's")
    first, second = _blob_images(tmp_path, "s"), _blob_images(tmp_path, "t")
    args = ["register", "--method", "affine", "--no-progress"]
    assert main([*args, "--images", *first, "--reference", first[0], "--out", str(foreign)]) == 2
    assert "did not make" in capsys.readouterr().err
    assert sorted(p.name for p in foreign.iterdir()) == ["keep.txt"]
    assert main([*args, "--images", *first, "--reference", first[0], "--out", str(out)]) == 0
    (out / "notes.txt").write_text("the user's")
    again = ["--images", *second, "--reference", second[0], "--manifest", str(tmp_path / "m2.yaml")]
    assert main([*args, *again, "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == sorted(
        [
            "notes.txt",
            "reference.nii.gz",
            "registration.json",
            *(f"{i:03d}_t{i}.h5" for i in range(3)),
        ]
    )
    assert [p for p in out.iterdir() if p.name.startswith(".nrreval-stage")] == []
    # the manifest points at the final folder, not the temporary one it was written in
    from itk_nrreval.io.manifest import load_manifest

    m = load_manifest(tmp_path / "m2.yaml")
    assert all(str(t[0]).startswith(str(out)) for t in m.registrations["affine"].transforms)


def test_register_refuses_to_rewrite_a_manifest_it_did_not_write(tmp_path, capsys):
    """Adding a registration rewrites the manifest: a hand-written one (comments, layout) is
    refused before any work, byte for byte untouched."""
    from itk_nrreval.cli import main

    paths = _blob_images(tmp_path, "s")
    mine = tmp_path / "mine.yaml"
    mine.write_text(
        "# my study, do not lose this comment\nimages: [s0.nii.gz, s1.nii.gz, s2.nii.gz]\n"
    )
    before = mine.read_bytes()
    args = ["register", "--method", "affine", "--no-progress", "--images", *paths]
    code = main([*args, "--manifest", str(mine), "--out", str(tmp_path / "affine")])
    err = capsys.readouterr().err
    assert code == 2 and "a manifest nrreval did not write" in err and str(mine) in err
    assert mine.read_bytes() == before and not (tmp_path / "affine").exists()
    # a manifest nrreval wrote is extended as before
    ours = tmp_path / "ours.yaml"
    assert main([*args, "--manifest", str(ours), "--out", str(tmp_path / "a1")]) == 0
    assert main([*args, "--manifest", str(ours), "--out", str(tmp_path / "a2"), "--name", "b"]) == 0
    from itk_nrreval.io.manifest import load_manifest

    assert set(load_manifest(ours).registrations) == {"affine", "b"}


def _write_registration(out, **kwargs):
    """register(out=) of three small blobs (affine: seconds)."""
    import SimpleITK as sitk

    from itk_nrreval.experiments.registration import register

    images = [sitk.ReadImage(p) for p in _blob_images(out.parent, out.name + "_img")]
    return register(images, method="affine", progress=False, out=out, **kwargs)


def test_python_writers_never_replace_a_users_file(tmp_path):
    """The Python API's writers (register(out=), every result's .write) into a folder that
    holds a user's file of a name they write: refused before anything is written, the
    user's file byte for byte kept; a second write into the toolkit's own folder replaces
    only its own files, and a user's file of another name stays."""
    from test_evaluate import make_case

    import itk_nrreval as nr
    from itk_nrreval import InputError

    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "reference.nii.gz").write_bytes(b"the user's reference")
    (mine / "notes.txt").write_text("the user's notes")
    before = _tree(mine)
    with pytest.raises(InputError, match="reference.nii.gz.*not written by nrreval"):
        _write_registration(mine)
    assert _tree(mine) == before

    ours = tmp_path / "ours"
    result = _write_registration(ours)
    (ours / "notes.txt").write_text("the user's notes")
    result.write(ours)  # its own files: replaced
    assert (ours / "notes.txt").read_text() == "the user's notes"
    assert (ours / "registration.json").is_file()

    case = tmp_path / "case"
    case.mkdir()
    make_case(case)
    evaluation = nr.evaluate(case / "manifest.yaml", n_samples=200, progress=False)
    report = tmp_path / "report"
    report.mkdir()
    (report / "report.html").write_text("<p>the user's page</p>")
    before = _tree(report)
    with pytest.raises(InputError, match="report.html.*not written by nrreval"):
        evaluation.write(report)
    assert _tree(report) == before
    evaluation.write(tmp_path / "new", figures=False)
    evaluation.write(tmp_path / "new", figures=False)  # a rerun replaces its own files


def test_add_to_manifest_refuses_a_hand_written_manifest(tmp_path):
    """RegistrationResult.add_to_manifest rewrites the whole manifest: a hand-written one
    (comments, layout) is refused as the CLI refuses it, before the transforms are
    written; a manifest the toolkit wrote is extended."""
    from itk_nrreval import InputError

    result = _write_registration(tmp_path / "first")
    images = [str(p) for p in sorted(tmp_path.glob("first_img*.nii.gz"))]
    mine = tmp_path / "mine.yaml"
    first = tmp_path / "first"
    mine.write_text(
        "# my study, do not lose this comment\n"
        f"images: [{', '.join(images)}]\n"
        f"registrations:\n  mine:\n    reference: {first / 'reference.nii.gz'}\n"
        f"    transforms: [{', '.join(str(p) for p in sorted(first.glob('*.h5')))}]\n"
    )
    before = mine.read_bytes()
    with pytest.raises(InputError, match="a manifest nrreval did not write"):
        result.add_to_manifest(mine, "affine", out=tmp_path / "affine")
    assert mine.read_bytes() == before and not (tmp_path / "affine").exists()
    ours = tmp_path / "ours.yaml"
    result.add_to_manifest(ours, "a", out=tmp_path / "a", images=images)
    result.add_to_manifest(ours, "b", out=tmp_path / "b")
    from itk_nrreval.io.manifest import load_manifest

    assert set(load_manifest(ours).registrations) == {"a", "b"}


def test_staged_folder_refuses_another_commands_folder(tmp_path):
    """Issue 44, 1: the record names the command that made the folder; another command's
    staged write is refused before anything is written or moved."""
    from itk_nrreval._errors import InputError
    from itk_nrreval._output import staged_folder

    out = tmp_path / "out"
    with staged_folder(out, command="synth", keep=()) as stage:
        (stage / "manifest.yaml").write_text("images: []\n")
    before = _tree(out)
    with pytest.raises(InputError, match="holds the output of `nrreval synth`"):
        with staged_folder(out, command="evaluate") as stage:
            (stage / "manifest.yaml").write_text("replaced\n")
    assert _tree(out) == before
    with staged_folder(out, command="synth", keep=()) as stage:  # the same command reruns
        (stage / "manifest.yaml").write_text("images: [a]\n")
    assert (out / "manifest.yaml").read_text() == "images: [a]\n"


def test_a_folder_another_process_writes_into_is_refused(tmp_path):
    """Issue 44, 3: two runs into one folder at once. The second is refused with one line
    while the first holds the folder; once it has ended, the folder is free."""
    import subprocess
    import sys

    from itk_nrreval._errors import InputError
    from itk_nrreval._output import staged_folder

    out = tmp_path / "out"
    holder = subprocess.Popen(
        [sys.executable, "-c", (
            "import sys; from itk_nrreval._output import staged_folder\n"
            f"with staged_folder({str(out)!r}, command='evaluate') as stage:\n"
            "    print('in', flush=True); sys.stdin.readline()\n"
        )],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert holder.stdout.readline() == "in\n"
        before = _tree(out)
        with pytest.raises(InputError, match="another nrreval run is writing into"):
            with staged_folder(out, command="evaluate"):
                pass
        assert _tree(out) == before
    finally:
        holder.communicate("\n", timeout=60)
    with staged_folder(out, command="evaluate") as stage:
        (stage / "results.json").write_text("{}\n")
    assert (out / "results.json").is_file()
