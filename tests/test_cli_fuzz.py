"""The command line under random damage: it never loses a file, never prints a traceback.

Each example starts from a valid small data folder (a manifest, its images, label maps and
transforms), damages it or the command's options at random, runs the command in process and
checks, whatever happened:

- the exit code is 0 or 2 (2 with one error line), and no traceback is printed;
- every file that was there before is byte-identical afterwards (hashes before and after);
- after exit 2, nothing at all was added anywhere: not in ``--out``, not beside it.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
import yaml
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from itk_nrreval._output import staged_folder
from itk_nrreval.cli import main

N = 4
SIZE = 20


def _image(arr: np.ndarray) -> sitk.Image:
    img = sitk.GetImageFromArray(arr)
    img.SetSpacing((1.5, 1.0))
    img.SetOrigin((3.0, -2.0))
    return img


def _write_base(folder: Path) -> None:
    """N blob images with label maps, two registrations (displacement fields; affines)."""
    folder.mkdir()
    y, x = np.mgrid[0:SIZE, 0:SIZE].astype(float)
    rng = np.random.default_rng(0)
    images, labels, fields, affines = [], [], [], []
    for i in range(N):
        cy, cx = 10 + rng.uniform(-1.5, 1.5), 10 + rng.uniform(-1.5, 1.5)
        blob = ((y - cy) / 6) ** 2 + ((x - cx) / 5) ** 2 < 1
        inner = ((y - cy) / 2.5) ** 2 + ((x - cx - 1) / 2) ** 2 < 1
        arr = (100.0 * blob + 40.0 * inner + rng.normal(0, 2, blob.shape)).astype(np.float32)
        lab = (blob.astype(np.uint8) + inner.astype(np.uint8)).astype(np.uint8)
        sitk.WriteImage(_image(arr), str(folder / f"s{i}.nii.gz"))
        sitk.WriteImage(_image(lab), str(folder / f"l{i}.nii.gz"))
        disp = np.zeros((SIZE, SIZE, 2))
        disp[..., 0] = 0.6 * np.sin(y / 4.0 + i)
        disp[..., 1] = 0.4 * np.cos(x / 5.0 - i)
        field = sitk.GetImageFromArray(disp, isVector=True)
        field.CopyInformation(_image(arr))
        sitk.WriteImage(field, str(folder / f"w{i}.nii.gz"))
        affine = sitk.AffineTransform(2)
        affine.SetTranslation((0.3 * i, -0.2 * i))
        sitk.WriteTransform(affine, str(folder / f"a{i}.tfm"))
        images.append(f"s{i}.nii.gz")
        labels.append(f"l{i}.nii.gz")
        fields.append(f"w{i}.nii.gz")
        affines.append(f"a{i}.tfm")
    manifest = {
        "images": images,
        "labels": labels,
        "registrations": {
            "field": {"reference": "s0.nii.gz", "transforms": fields},
            "affine": {"reference": "s0.nii.gz", "transforms": affines},
        },
    }
    (folder / "manifest.yaml").write_text(yaml.safe_dump(manifest))


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("fuzz") / "data"
    _write_base(folder)
    return folder


def _tree(root: Path) -> dict[str, str | None]:
    """Every path below `root` with the digest of its bytes (None for a folder)."""
    return {
        str(p.relative_to(root)): (
            hashlib.blake2b(p.read_bytes()).hexdigest() if p.is_file() else None
        )
        for p in sorted(root.rglob("*"))
    }


# ---- damage to the data --------------------------------------------------------------


def _edit(data: Path, edit) -> None:
    path = data / "manifest.yaml"
    m = yaml.safe_load(path.read_text())
    edit(m)
    path.write_text(yaml.safe_dump(m))


def _missing(data, i):
    (data / f"s{i}.nii.gz").unlink()


def _truncated(data, i):
    p = data / f"w{i}.nii.gz"
    p.write_bytes(p.read_bytes()[:60])


def _text_as_nifti(data, i):
    (data / f"l{i}.nii.gz").write_text("not an image\n")


def _wrong_dimension(data, i):
    sitk.WriteImage(sitk.Image([SIZE, SIZE, 3], sitk.sitkFloat32), str(data / f"s{i}.nii.gz"))


def _four_d(data, i):
    sitk.WriteImage(sitk.Image([SIZE, SIZE, 2, 2], sitk.sitkFloat32), str(data / f"s{i}.nii.gz"))


def _nan(data, i):
    arr = sitk.GetArrayFromImage(sitk.ReadImage(str(data / f"s{i}.nii.gz")))
    arr[: SIZE // 2] = np.nan
    sitk.WriteImage(_image(arr), str(data / f"s{i}.nii.gz"))


def _swapped(data, i):
    def edit(m):
        m["images"][i], m["labels"][i] = m["labels"][i], m["images"][i]

    _edit(data, edit)


def _duplicate(data, i):
    _edit(data, lambda m: m["images"].__setitem__(i, m["images"][(i + 1) % N]))


def _wrong_count(data, i):
    _edit(data, lambda m: m["labels"].pop(i))


def _field_count(data, i):
    _edit(data, lambda m: m["registrations"]["field"]["transforms"].pop(i))


DATA_DAMAGE = {
    "none": None,
    "missing file": _missing,
    "truncated file": _truncated,
    "text renamed .nii.gz": _text_as_nifti,
    "wrong dimension": _wrong_dimension,
    "4D": _four_d,
    "NaN": _nan,
    "label map and image swapped": _swapped,
    "duplicate entries": _duplicate,
    "wrong label count": _wrong_count,
    "wrong transform count": _field_count,
}

# ---- damage to the options -----------------------------------------------------------

BAD_OPTIONS = {
    "none": [],
    "samples 0": ["--samples", "0"],
    "samples text": ["--samples", "many"],
    "seed negative": ["--seed", "-3"],
    "distance unknown": ["--distance", "L7"],
}

# where the output goes, relative to the sandbox (which holds data/ and foreign/, own/)
OUT_PLACES = ["new", "at the inputs", "above the inputs", "inside the inputs", "an input file",
              "an existing file", "a foreign folder", "its own folder"]  # fmt: skip


def _out_path(root: Path, place: str) -> Path:
    return {
        "new": root / "results",
        "at the inputs": root / "data",
        "above the inputs": root,
        "inside the inputs": root / "data" / "results",
        "an input file": root / "data" / "s1.nii.gz",
        "an existing file": root / "notes.txt",
        "a foreign folder": root / "foreign",
        "its own folder": root / "own",
    }[place]


def _sandbox(base: Path, root: Path) -> None:
    shutil.copytree(base, root / "data")
    (root / "notes.txt").write_text("the user's notes\n")
    (root / "foreign").mkdir()
    (root / "foreign" / "thesis.tex").write_text("\\documentclass{article}\n")
    with staged_folder(root / "own", command="evaluate") as stage:  # what an earlier run left
        (stage / "results.json").write_text("{}\n")


def _command(name: str, root: Path, out: Path, options: list[str]) -> list[str]:
    data = root / "data"
    images = [str(data / f"s{i}.nii.gz") for i in range(N)]
    labels = [str(data / f"l{i}.nii.gz") for i in range(N)]
    quick = ["--quiet", "--seed", "0"]
    if name == "evaluate":
        return ["evaluate", str(data / "manifest.yaml"), "--out", str(out), "--samples", "100",
                "--no-figures", "--no-confidence", *quick, *options]  # fmt: skip
    if name == "specificity":
        return ["specificity", *images, "--samples", "100", "--json", str(out), *quick, *options]
    if name == "overlap":
        return ["overlap", *labels, "--json", str(out), "--quiet"]
    return ["synth", "--n", "3", "--out", str(out), "--seed", "0"]


@settings(
    max_examples=100,
    deadline=None,
    derandomize=True,  # the same examples in every run: a failure is reproducible
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(
    command=st.sampled_from(
        ["evaluate", "evaluate", "evaluate", "specificity", "overlap", "synth"]
    ),
    # about half the examples leave each part undamaged, so that valid runs (exit 0) are
    # common too: a damage is then tried both alone and with others
    damage=st.sampled_from(["none"] * 6 + sorted(DATA_DAMAGE)),
    which=st.integers(0, N - 1),
    option=st.sampled_from(["none"] * 4 + sorted(BAD_OPTIONS)),
    place=st.sampled_from(["new", "inside the inputs", "its own folder"] * 2 + OUT_PLACES),
)
def test_cli_under_random_damage_loses_nothing(
    base, tmp_path_factory, capsys, command, damage, which, option, place
):
    root = tmp_path_factory.mktemp("case")
    _sandbox(base, root)
    if DATA_DAMAGE[damage] is not None:
        DATA_DAMAGE[damage](root / "data", which)
    options = BAD_OPTIONS[option] if command in ("evaluate", "specificity") else []
    out = _out_path(root, place)
    before = _tree(root)
    capsys.readouterr()

    code = main(_command(command, root, out, options))

    err = capsys.readouterr().err
    event(f"{command}: exit {code}")
    assert "Traceback" not in err, err
    assert code in (0, 2), (code, err)
    after = _tree(root)
    # a rerun into the toolkit's own folder replaces what the toolkit wrote there, nothing else
    replaced = "own/" if place == "its own folder" and code == 0 else None
    lost = {
        p: d
        for p, d in before.items()
        if after.get(p) != d and not (replaced and p.startswith(replaced))
    }
    assert not lost, f"changed or removed: {sorted(lost)}"
    if code == 2:
        errors = [ln for ln in err.splitlines() if ": error: " in ln]
        assert len(errors) == 1 and err.strip().endswith(errors[0]), err
        assert after == before, f"left behind: {sorted(set(after) - set(before))}"
    shutil.rmtree(root)


@pytest.mark.parametrize(
    "place", ["at the inputs", "above the inputs", "an input file", "a foreign folder"]
)
@pytest.mark.parametrize("command", ["evaluate", "specificity", "overlap", "synth"])
def test_output_onto_the_inputs_is_refused_before_any_work(base, tmp_path, capsys, command, place):
    """The issue's repro, for each command: refused with exit 2, every file kept."""
    _sandbox(base, tmp_path)
    out = _out_path(tmp_path, place)
    before = _tree(tmp_path)
    code = main(_command(command, tmp_path, out, []))
    err = capsys.readouterr().err
    if command in ("specificity", "overlap") and place in ("above the inputs", "at the inputs"):
        assert code == 2 and "is a folder" in err
    elif command == "synth" and place in ("at the inputs", "above the inputs"):
        assert code == 2 and "did not make" in err
    else:
        assert code == 2, err
    assert _tree(tmp_path) == before


# ---- another command's output, concurrent runs, Ctrl-C -------------------------------

# Every command that writes an output folder, and a valid run of it into `out` (`data`: a
# folder `synth` made, whose manifest holds the true transforms of its images).
FOLDER_COMMANDS = ["synth", "register", "evaluate", "validate", "diagnose", "sweep", "demo"]


def _folder_command(name: str, data: Path, out: Path) -> list[str]:
    images = [str(p) for p in sorted((data / "img").glob("s*.nii.gz"))]
    manifest = str(data / "manifest.yaml")
    small = ["--samples", "100", "--quiet"]
    return {
        "synth": ["synth", "--n", "4", "--spacing", "4", "--out", str(out)],
        "register": ["register", "--images", *images, "--method", "affine", "--out", str(out),
                     "--manifest", str(out.parent / f"{out.name}-manifest.yaml"), "--quiet"],
        "evaluate": ["evaluate", manifest, "--out", str(out), "--no-figures", "--no-confidence",
                     *small],
        "validate": ["validate", manifest, "--out", str(out), "--displacements", "0.5",
                     "--repeats", "1", *small],
        "diagnose": ["diagnose", manifest, "--registration", "truth", "--out", str(out), *small],
        "sweep": ["sweep", "--from", manifest, "--truth", "truth", "--method", "affine",
                  "--param", "iterations=5", "--out", str(out), *small],
        "demo": ["demo", "--quick", "--n", "4", "--out", str(out)],
    }[name]  # fmt: skip


@pytest.fixture(scope="module")
def folders_of_each_command(tmp_path_factory) -> tuple[Path, dict[str, Path]]:
    """A folder made by a real run of each command but ``demo`` (a minute even when quick);
    the demo's folder is claimed as ``run_demo`` claims it before its first registration."""
    from itk_nrreval._output import claim_output_folder
    from itk_nrreval.experiments.demo import DEMO_OUTPUTS

    root = tmp_path_factory.mktemp("made")
    data = root / "data"
    assert main(_folder_command("synth", data, data)) == 0
    made = {"synth": data}
    for name in FOLDER_COMMANDS[1:-1]:
        made[name] = root / name
        assert main(_folder_command(name, data, made[name])) == 0, name
    made["demo"] = claim_output_folder(root / "demo", entries=DEMO_OUTPUTS, command="demo")
    (made["demo"] / "demo.json").write_text("{}\n")  # what a finished demo would leave
    return root, made


@pytest.mark.parametrize("command", FOLDER_COMMANDS)
def test_out_at_another_commands_folder_is_refused_and_loses_nothing(
    folders_of_each_command, capsys, command
):
    """Issue 44, 1: a rerun replaces only what the same command wrote there. `evaluate
    --out` at a register folder deleted its transforms; `synth --out` at an evaluate folder
    its results."""
    root, made = folders_of_each_command
    for producer, folder in made.items():
        if producer == command:
            continue
        before = _tree(root)
        capsys.readouterr()
        code = main(_folder_command(command, made["synth"], folder))
        err = capsys.readouterr().err
        assert code == 2, (command, producer, err)
        assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
        assert _tree(root) == before, (command, producer)


def test_out_record_without_its_command_is_refused(tmp_path, capsys):
    """A folder whose record does not say which command made it (an earlier version's) is
    not replaced: it could be any command's work."""
    from itk_nrreval._output import MARKER

    out = tmp_path / "old"
    out.mkdir()
    (out / "results.json").write_text("{}\n")
    (out / MARKER).write_text('{"tool": "itk-nrreval", "entries": ["results.json"]}\n')
    before = _tree(tmp_path)
    assert main(["synth", "--n", "4", "--spacing", "4", "--out", str(out)]) == 2
    assert "earlier nrreval version" in capsys.readouterr().err
    assert _tree(tmp_path) == before


def _nrreval_program() -> str:
    """The installed ``nrreval`` program (its entry point, not ``python -m``)."""
    import sys

    program = Path(sys.executable).parent / "nrreval"
    assert program.is_file(), f"{program}: not installed (pip install -e .)"
    return str(program)


def test_two_runs_into_one_out_the_second_is_refused(base, tmp_path, capsys):
    """Issue 44, 3: a second evaluate into an --out another is writing died with a 40-line
    traceback (cache entries removed under it). It is refused with one line, and the first
    run completes."""
    import subprocess
    import time

    _sandbox(base, tmp_path)
    out = tmp_path / "results"
    first = subprocess.Popen(
        [_nrreval_program(), *_command("evaluate", tmp_path, out, ["--samples", "200000"])],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    deadline = time.monotonic() + 120
    while not list(out.glob(".nrreval-stage-tmp-*")):  # the first run is under way
        assert first.poll() is None and time.monotonic() < deadline, first.communicate()
        time.sleep(0.02)
    code = main(_command("evaluate", tmp_path, out, []))
    err = capsys.readouterr().err
    assert first.poll() is None, "the first run ended before the second was tried"
    assert code == 2 and "another nrreval run is writing" in err, err
    assert len(err.strip().splitlines()) == 1
    _, first_err = first.communicate(timeout=300)
    assert first.returncode == 0, first_err
    assert (out / "results.json").is_file()


def test_ctrl_c_in_a_callback_whose_errors_python_ignores_is_asked_again(monkeypatch):
    """A Ctrl-C landing in the import system's weakref callback (importlib's
    ``_get_module_lock.<locals>.cb``) or in a ``__del__`` was raised where Python ignores
    exceptions: it printed "Exception ignored ... Traceback" and was lost (CI, the random
    point test below, seed 2). There the handler asks for it again shortly instead of
    raising; in any other frame it raises, as before."""
    import signal
    import sys

    import nrreval_console as console

    asked = []
    monkeypatch.setattr(console, "_ask_again", lambda: asked.append(True))
    # no command's result in place yet (this process may have written some: other tests)
    monkeypatch.delitem(sys.modules, "itk_nrreval._output", raising=False)
    namespace: dict = {}
    source = "import sys\ndef cb(ref):\n    return sys._getframe()\n"
    source += "class A:\n    def __del__(self):\n        return sys._getframe()\n"
    exec(compile(source, "<frozen importlib._bootstrap>", "exec"), namespace)
    for frame in (namespace["cb"](None), namespace["A"].__del__(object())):
        console._interrupt(signal.SIGINT, frame)  # does not raise
    assert asked == [True, True]
    ordinary = compile("def cb(ref):\n    return sys._getframe()\n", "mine.py", "exec")
    namespace_2: dict = {"sys": __import__("sys")}
    exec(ordinary, namespace_2)  # a function named cb that is not importlib's
    for frame in (namespace_2["cb"](None), None):
        with pytest.raises(KeyboardInterrupt):
            console._interrupt(signal.SIGINT, frame)
    assert asked == [True, True]


@pytest.mark.parametrize("seed", range(6))
def test_ctrl_c_at_a_random_point_ends_in_one_line_or_a_complete_result(base, tmp_path, seed):
    """Issue 44, 4: SIGINT anywhere in an evaluate run (imports, checks, tasks in threads,
    numba kernels, the final swap) ends with exit code 130 and one line, or exit 0 and the
    whole result; the previous result and every input stay byte-identical."""
    import contextlib
    import signal
    import subprocess

    _sandbox(base, tmp_path)
    out = tmp_path / "own"  # holds an earlier run's result
    command = [_nrreval_program(), *_command("evaluate", tmp_path, out, ["--samples", "20000"])]
    # the cache is the toolkit's and is kept (a rerun resumes); the record notes it
    kept = ("own/cache", "own/.nrreval-output.json")
    before = {p: d for p, d in _tree(tmp_path).items() if not p.startswith(kept)}
    delay = np.random.default_rng(seed).uniform(0.2, 6.0)
    run = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    with contextlib.suppress(subprocess.TimeoutExpired):
        # `delay` as a sleep would, unless the run ends first: a run quicker than the delay
        # (often, on an idle machine) is not waited for in vain. Either way, send_signal
        # skips a process that has ended, and the run's exit code and output are checked.
        run.wait(timeout=delay)
    run.send_signal(signal.SIGINT)
    _, err = run.communicate(timeout=300)
    lines = [line for line in err.splitlines() if ": warning: " not in line]
    assert "Traceback" not in err and "FATAL" not in err, (delay, err)
    assert run.returncode in (0, 130), (delay, run.returncode, err)
    after = {p: d for p, d in _tree(tmp_path).items() if not p.startswith(kept)}
    record = json.loads((out / ".nrreval-output.json").read_text())
    assert record["command"] == "evaluate" and "results.json" in record["entries"], record
    if run.returncode == 130:
        assert lines == [lines[-1]] and lines[-1].endswith("interrupted"), (delay, err)
        stale = [p for p in after if ".nrreval-stage-" in p]
        assert {p: d for p, d in after.items() if p not in stale} == before, delay
    else:
        results = json.loads((out / "results.json").read_text())
        assert results["verdict"]["text"] and (out / "summary.md").is_file()


@pytest.mark.parametrize("after_s", [0.0, 0.05])
def test_ctrl_c_once_the_result_is_complete_is_exit_0(base, tmp_path, after_s):
    """Ctrl-C the moment the new result is in place (during the final swap, or in the
    interpreter's shutdown, after its handler is gone): the result is complete, so the exit
    code is 0 and nothing is said -- not 130 over a replaced result, nor a silent death by
    the signal (exit -2), both seen before."""
    import signal
    import subprocess
    import time

    _sandbox(base, tmp_path)
    out = tmp_path / "results"
    command = [_nrreval_program(), *_command("evaluate", tmp_path, out, ["--samples", "2000"])]
    run = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    while not (out / "results.json").exists() and run.poll() is None:
        time.sleep(0.002)
    time.sleep(after_s)
    run.send_signal(signal.SIGINT)
    _, err = run.communicate(timeout=300)
    assert run.returncode == 0, (run.returncode, err)
    assert "interrupted" not in err and "Traceback" not in err, err
    assert json.loads((out / "results.json").read_text())["verdict"]["text"]


@pytest.mark.parametrize("command", ["evaluate", "synth"])
def test_ctrl_c_after_the_swap_is_exit_0_every_time(base, tmp_path, monkeypatch, command):
    """The race behind the flaky subprocess test above, made certain: SIGINT delivered the
    moment the staged result has been swapped in (before the summary is printed) ended the
    command with 130 -- which says the previous result was kept -- over a replaced result.
    Once the result is in place the command ends 0."""
    import os
    import signal

    from itk_nrreval import _output
    from itk_nrreval.cli import main

    swap = _output._interrupts_held_off

    @contextlib.contextmanager
    def swap_then_ctrl_c():
        with swap():
            yield
        os.kill(os.getpid(), signal.SIGINT)  # handled at the next bytecode, in this thread

    _sandbox(base, tmp_path)
    monkeypatch.setattr(_output, "_interrupts_held_off", swap_then_ctrl_c)
    out = tmp_path / "results"
    handler = signal.getsignal(signal.SIGINT)
    assert main(_command(command, tmp_path, out, [])) == 0
    assert (out / ".nrreval-output.json").is_file()
    # after the command, Ctrl-C is handled as it was before it (in a console: by Python)
    assert signal.getsignal(signal.SIGINT) is handler


class _InterruptedWhenCollected:
    """An object whose collection raises KeyboardInterrupt where nothing can catch it, as
    Ctrl-C does when it lands in a callback from compiled code (llvmlite's ctypes callbacks
    while numba loads its cache): Python reports it through ``sys.unraisablehook``."""

    def __del__(self):
        raise KeyboardInterrupt


def test_ctrl_c_where_it_cannot_propagate_still_ends_the_command(
    base, tmp_path, monkeypatch, capsys
):
    """Issue 44, 4, as seen once in the subprocess test above: a Ctrl-C raised inside a
    callback was printed as "Exception ignored ..." with a traceback, and the command carried
    on. It must end the command as any Ctrl-C does: exit 130, one line (besides progress
    bars), nothing else."""
    import data_synth.population as population

    make = population.make_population

    def interrupted_inside_a_callback(*args, **kwargs):
        _InterruptedWhenCollected()  # collected at once: its KeyboardInterrupt is unraisable
        return make(*args, **kwargs)

    _sandbox(base, tmp_path)
    monkeypatch.setattr(population, "make_population", interrupted_inside_a_callback)
    out = tmp_path / "synth"
    assert main(_command("synth", tmp_path, out, [])) == 130
    err = capsys.readouterr().err
    # synth draws progress bars on stderr (it has no --quiet), redrawn with carriage
    # returns: besides them, the one line and nothing else
    said = [part.strip() for line in err.splitlines() for part in line.split("\r")]
    said = [part for part in said if part and "%|" not in part]
    assert said == ["nrreval synth: interrupted"], err
    assert "Traceback" not in err and "Exception ignored" not in err, err
    assert not out.exists()
