"""The examples run, and write only into the folder given with --out (issue 17).

Each is run as a user would, in a subprocess, from an empty working folder and with an
empty TMPDIR: by default it must leave both empty (its temporary folder removed) and write
nothing into the repository; with ``--out DIR`` its outputs must be in DIR. The slow ones
(registrations of whole groups, a Dask cluster) are only asked for ``--help`` here.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
EXAMPLES = REPO / "examples"
FAST = {  # example -> (extra arguments, a file it writes into --out DIR)
    "cps_perturbation": ([], "cps_perturbation.png"),
    "make_population": ([], "synth_mni_2d.png"),
    "evaluate_registrations": (["--samples", "2000"], "results/results.json"),
    "slicer_console": (["--samples", "2000", "--quiet"], "results.json"),
}
WRITES_NOTHING = {"overlap_of_label_maps"}


def _slicer_console_says(stdout: str) -> None:
    """Outside Slicer, its generated population: the verdict first, then the ranking."""
    lines = stdout.splitlines()
    assert lines[0].startswith("truth is best: decided better than every other registration")
    ranked = [ln.split(":")[0] for ln in lines if ": specificity " in ln]
    assert ranked == ["truth", "pose_only"]


SAYS = {"slicer_console": _slicer_console_says}  # example -> a check of what it prints


def run_example(name: str, args: list[str], tmp_path: Path) -> subprocess.CompletedProcess:
    cwd, tmpdir = tmp_path / "cwd", tmp_path / "tmp"
    cwd.mkdir(exist_ok=True)
    tmpdir.mkdir(exist_ok=True)
    env = {**os.environ, "TMPDIR": str(tmpdir), "MPLBACKEND": "Agg"}
    return subprocess.run(
        [sys.executable, str(EXAMPLES / f"{name}.py"), *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )


def repo_files_written_since(t0: float) -> list[Path]:
    # (.hypothesis: the database of hypothesis, which no example imports, written by any
    # pytest run in the repository at the same time)
    skip = {".git", ".venv", "__pycache__", ".pytest_cache", ".ruff_cache", ".hypothesis", "out"}
    found = []
    for root, dirs, files in os.walk(REPO):
        dirs[:] = [d for d in dirs if d not in skip and not d.startswith("nrreval-")]
        found += [Path(root) / f for f in files if (Path(root) / f).stat().st_mtime > t0]
    return found


def test_every_example_is_covered_here():
    names = {p.stem for p in EXAMPLES.glob("*.py") if not p.stem.startswith("_")}
    slow = {"appearance_diagnostics", "evaluate_on_dask", "register_a_group", "multimodal"}
    assert names == set(FAST) | WRITES_NOTHING | slow


@pytest.mark.parametrize("name", sorted(FAST) + sorted(WRITES_NOTHING))
def test_example_leaves_nothing_behind(name, tmp_path):
    t0 = time.time()
    args = FAST[name][0] if name in FAST else []
    done = run_example(name, args, tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "Traceback" not in done.stderr
    if name in SAYS:
        SAYS[name](done.stdout)
    assert not list((tmp_path / "cwd").iterdir()), "wrote into the working folder"
    assert not list((tmp_path / "tmp").iterdir()), "left a temporary folder behind"
    assert not repo_files_written_since(t0), "wrote into the repository"


@pytest.mark.parametrize("name", ["cps_perturbation", "evaluate_registrations"])
def test_example_keeps_its_outputs_in_out(name, tmp_path):
    args, product = FAST[name]
    out = tmp_path / "kept"
    done = run_example(name, [*args, "--out", str(out)], tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    assert (out / product).is_file()
    assert not list((tmp_path / "cwd").iterdir())
    assert not list((tmp_path / "tmp").iterdir())


@pytest.mark.parametrize(
    "name", ["appearance_diagnostics", "evaluate_on_dask", "multimodal", "register_a_group"]
)
def test_slow_examples_take_an_output_folder(name, tmp_path):
    done = run_example(name, ["--help"], tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "--out DIR" in done.stdout
    assert not list((tmp_path / "cwd").iterdir())
