"""The whole cohort at 1 mm: ``evaluate`` with its defaults, five registrations (issue 30).

The 1 mm 3D phantom cohort of ``bench_memory.py`` (200 x 236 x 190 voxels, 9.0 M; 26
labels), N = 12 subjects (N = 36 too with ``NRREVAL_BENCH_COHORT_N=12,36``), and five
registrations of it, each subject's transform per registration:

- ``field_a``, ``field_b``, ``field_c``: the true template-to-subject transform (an affine
  map and a 1 mm displacement field) composed with a small affine error of its own per
  registration and subject (rotation up to 1 degree, scaling up to 1 %, translation up to
  1 mm), acting first: ANTs order ``[error.mat, truth.h5]``;
- ``affine``: the affine part of the true transform;
- ``affine_err``: that affine part composed with its own small error.

All five share the template as reference, and the manifest says nothing of their frames,
so the four registrations after ``field_a`` (the common frame) are brought into it by the
mean of per-image frame estimates: N field inversions each for ``field_b`` and ``field_c``.

Each evaluation is the default in-process path with confidence and plausibility on
(``nr.evaluate(manifest, execution=nr.Execution(cache=...))``, nothing else set), in a
fresh process with a cold cache; it reports its wall time, its CPU time (user + system: the
machine may be shared, which inflates the wall time but not the CPU time), its peak resident memory
(``ru_maxrss``) and the size of its cache on disk at its largest during the run (sampled
every second; GB of 2^30 bytes) and when it ends. Targets (issue 30, two cores): N = 12
under 5 minutes; N = 36 under 15 minutes, peak RSS under 3 GB, cache under 4 GB.

The floor, in the same process once the evaluation is done: SimpleITK's own ``Resample``
(linear, float32) of each registration's first three images onto the common grid through
their composed transforms ``T_i^R o F`` (F the frame the evaluation found), in CPU seconds;
the cohort's floor is each registration's mean times N, and the evaluation's CPU time is
reported as a ratio to it.

``python benchmarks/run_all.py cohort`` runs it (N = 12: about 7 minutes of CPU and 4.5 of
wall time on two cores, two tasks at once; N = 36: 21 and 12; the cohort, 2.8 GB for N = 12
and 8.4 GB for N = 36, is generated once into ``benchmarks/out/cohort3d_1mm``, shared with
``bench_memory.py``, and reused).
"""

from __future__ import annotations

import json
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
SPACING_MM = 1.0
SIZES = tuple(int(n) for n in os.environ.get("NRREVAL_BENCH_COHORT_N", "12").split(","))
FIELD_REGISTRATIONS = ("field_a", "field_b", "field_c")
FLOOR_IMAGES = 3  # images per registration whose SimpleITK Resample is timed (the floor)


def _cohort(n: int) -> tuple[Path, dict]:
    """bench_memory's 1 mm cohort (generated on first use) and its subjects."""
    sys.path.insert(0, str(HERE))
    from bench_memory import cohort

    folder = cohort(SPACING_MM, n)
    return folder, json.loads((folder / "subjects.json").read_text())


def _affine_error(seed: int):
    """A small random affine map about the template's centre: rotation <= 1 degree, scaling
    <= 1 %, translation <= 1 mm along each axis."""
    import numpy as np
    import SimpleITK as sitk

    rng = np.random.default_rng(seed)
    rotation = sitk.VersorRigid3DTransform()
    axis = rng.standard_normal(3)
    rotation.SetRotation((axis / np.linalg.norm(axis)).tolist(), np.radians(rng.uniform(-1, 1)))
    error = sitk.AffineTransform(3)
    matrix = np.asarray(rotation.GetMatrix()).reshape(3, 3) @ np.diag(rng.uniform(0.99, 1.01, 3))
    error.SetMatrix(matrix.ravel().tolist())
    error.SetTranslation(rng.uniform(-1.0, 1.0, 3).tolist())
    return error


def manifest_for(n: int) -> Path:
    """The five registrations of the first `n` subjects (error files written on first use)."""
    import SimpleITK as sitk
    import yaml

    folder, info = _cohort(n)
    template = sitk.ReadImage(info["template"])
    centre = template.TransformContinuousIndexToPhysicalPoint(
        [(s - 1) / 2 for s in template.GetSize()]
    )
    errors = folder / "errors"
    errors.mkdir(exist_ok=True)
    subjects = info["subjects"][:n]
    chains = {name: [] for name in (*FIELD_REGISTRATIONS, "affine", "affine_err")}
    for i, s in enumerate(subjects):
        for k, name in enumerate((*FIELD_REGISTRATIONS, "affine_err")):
            path = errors / f"{name}_{i:03d}.mat"
            if not path.exists():
                error = _affine_error(1000 * k + i)
                error.SetCenter(centre)
                sitk.WriteTransform(error, str(path))
            true = s["affine"] if name == "affine_err" else s["truth"]
            chains[name].append([str(path), true])  # ANTs order: the error acts first
        chains["affine"].append(s["affine"])
    data = {
        "images": [s["image"] for s in subjects],
        "labels": [s["labels"] for s in subjects],
        "registrations": {
            name: {"reference": info["template"], "transforms": items}
            for name, items in chains.items()
        },
    }
    path = folder / f"manifest_five_{n}.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def _size_mb(folder: Path) -> float:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file()) / 2**20


def run(n: int) -> dict:
    """One cold-cache evaluation in a fresh process."""
    manifest = manifest_for(n)
    cache = manifest.parent / f"cache_five_{n}"
    shutil.rmtree(cache, ignore_errors=True)
    cmd = [sys.executable, __file__, "--run", str(manifest), str(cache)]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    errors = cache.parent / f"cache_five_{n}.stderr"
    t0 = time.perf_counter()
    with (
        open(errors, "w") as err,
        subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=err, text=True, env=env) as proc,
    ):
        largest = 0.0  # the cache's size at its largest, sampled every second
        while proc.poll() is None:
            try:
                largest = max(largest, _size_mb(cache))
            except OSError:  # an entry renamed or removed while it was listed
                pass
            time.sleep(1.0)
        out = proc.stdout.read()
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        tail = errors.read_text().strip().splitlines()[-5:]
        raise RuntimeError(f"the evaluation exited with {proc.returncode}: {' / '.join(tail)}")
    errors.unlink()
    res = json.loads(out.strip().splitlines()[-1])
    res.update(n=n, wall_s=wall, cache_mb=_size_mb(cache), cache_peak_mb=largest)
    shutil.rmtree(cache, ignore_errors=True)
    print(
        f"| {n} | {res['evaluate_s'] / 60:.1f} | {res['cpu_s'] / 60:.1f} | "
        f"{res['peak_mb'] / 1024:.2f} | {res['cache_peak_mb'] / 1024:.2f} | "
        f"{res['cache_mb'] / 1024:.2f} | {res['floor_cpu_s'] / 60:.2f} | "
        f"{res['ratio_to_floor']:.1f}x |",
        flush=True,
    )
    return res


def _floor_cpu_s(manifest: str, res, per_registration: int = FLOOR_IMAGES) -> dict:
    """The floor: SimpleITK's own ``Resample`` (linear, float32) of the first images of each
    registration onto the common grid through their composed transforms ``T_i^R o F`` (F the
    frame the evaluation found), in CPU seconds of this process per image, and for the whole
    cohort (each registration's mean times N)."""
    import SimpleITK as sitk
    import yaml

    from itk_nrreval.io.frame import resampling_transform
    from itk_nrreval.io.transforms import chain_transform

    data = yaml.safe_load(Path(manifest).read_text())
    reference = sitk.ReadImage(data["registrations"]["field_a"]["reference"])
    per_image, total = {}, 0.0
    for name, reg in data["registrations"].items():
        frame = res.scores[name].frame.transform
        spent = []
        pairs = list(zip(data["images"], reg["transforms"], strict=True))[:per_registration]
        for image, item in pairs:
            moving = sitk.ReadImage(image, sitk.sitkFloat32)
            full = resampling_transform(chain_transform(item), frame)
            t0 = time.process_time()
            sitk.Resample(moving, reference, full, sitk.sitkLinear, 0.0, sitk.sitkFloat32)
            spent.append(time.process_time() - t0)
            del moving, full
        per_image[name] = sum(spent) / len(spent)
        total += per_image[name] * len(data["images"])
    return {"floor_per_image_cpu_s": per_image, "floor_cpu_s": total}


def _run_one(manifest: str, cache: str) -> None:
    import itk_nrreval as nr

    t0 = time.perf_counter()
    res = nr.evaluate(manifest, execution=nr.Execution(cache=cache), progress=False)
    seconds = time.perf_counter() - t0
    usage = resource.getrusage(resource.RUSAGE_SELF)
    cpu_s = usage.ru_utime + usage.ru_stime
    floor = _floor_cpu_s(manifest, res)  # after the evaluation's own numbers are taken
    print(
        json.dumps(
            {
                "evaluate_s": seconds,
                "cpu_s": cpu_s,
                "peak_mb": usage.ru_maxrss / 1024,  # kB -> MB on Linux
                **floor,
                "ratio_to_floor": cpu_s / floor["floor_cpu_s"],
                "scores": {k: s.measures() for k, s in res.scores.items()},
                "plausibility": {k: s.plausibility.to_dict() for k, s in res.scores.items()},
            }
        )
    )


def main() -> dict:
    print(f"1 mm phantom, five registrations, evaluate's defaults, {os.cpu_count()} cores\n")
    print(
        "| N | evaluate (min) | CPU (min) | peak RSS (GB) | cache at its largest (GB) "
        "| cache at the end (GB) | SimpleITK floor (CPU min) | CPU / floor |"
    )
    print("|---|---|---|---|---|---|---|---|")
    return {"spacing_mm": SPACING_MM, "runs": [run(n) for n in SIZES]}


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "--run":
        _run_one(sys.argv[2], sys.argv[3])
    else:
        results = main()
        out = ROOT / "benchmarks" / "out" / "cohort.json"
        out.write_text(json.dumps(results, indent=2) + "\n")
