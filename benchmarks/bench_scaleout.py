"""Scale-out: ``nrreval evaluate --scheduler local`` on a generated 3D cohort (2 mm voxels).

N = 200 subjects of the 3D phantom (100 x 118 x 95 voxels, 26 labels) with two
registrations: ``truth`` (the true template-to-subject transforms, the common frame) and
``affine`` (only their affine part). Each evaluation runs in its own driver process with a
cold cache, and reports the driver's own peak resident memory (the scheduler runs in it; the
workers are separate processes): for N = 50, 100 and 200 on 2 workers, and 1 against 2
workers at one N. Writes ``docs/scaleout.png``.

``python benchmarks/bench_scaleout.py`` runs it alone; the cohort is generated once into
``benchmarks/out/cohort3d`` (about 6 GB) and reused.
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

ROOT = Path(__file__).resolve().parent.parent
COHORT = ROOT / "benchmarks" / "out" / "cohort3d"
N_MAX = 200
BATCH = 25
SIZES = (50, 100, 200)
SPEEDUP_N = int(os.environ.get("NRREVAL_BENCH_SPEEDUP_N", "50"))
SAMPLES = 100_000


def make_cohort() -> None:
    """N_MAX subjects, written in batches (a batch of 3D subjects holds ~1.5 GB)."""
    import SimpleITK as sitk
    import yaml

    from data_synth.population import make_population
    from data_synth.writing import write_population

    if (COHORT / "subjects.json").exists():
        return
    subjects = []
    for b in range(N_MAX // BATCH):
        folder = COHORT / f"batch{b}"
        pop = make_population("phantom", dim=3, n=BATCH, seed=100 + b)
        manifest = yaml.safe_load(write_population(pop, folder, montage=False).read_text())
        for i, s in enumerate(pop.subjects):
            affine = sitk.AffineTransform(s.template_to_subject.GetNthTransform(0))
            mat = folder / "affine" / f"s{i:02d}.mat"
            mat.parent.mkdir(exist_ok=True)
            sitk.WriteTransform(affine, str(mat))
            subjects.append(
                {
                    "image": str(folder / manifest["images"][i]),
                    "labels": str(folder / manifest["labels"][i]),
                    "truth": str(folder / manifest["registrations"]["truth"]["transforms"][i]),
                    "affine": str(mat),
                }
            )
        if b == 0:
            template = folder / manifest["registrations"]["truth"]["reference"]
        del pop
    (COHORT / "subjects.json").write_text(
        json.dumps({"template": str(template), "subjects": subjects})
    )


def manifest_for(n: int) -> Path:
    import yaml

    info = json.loads((COHORT / "subjects.json").read_text())
    subs = info["subjects"][:n]
    data = {
        "images": [s["image"] for s in subs],
        "labels": [s["labels"] for s in subs],
        "registrations": {
            "truth": {"reference": info["template"], "transforms": [s["truth"] for s in subs]},
            "affine": {"reference": info["template"], "transforms": [s["affine"] for s in subs]},
        },
    }
    path = COHORT / f"manifest_{n}.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def run_driver(n: int, workers: int) -> dict:
    """One cold-cache evaluation in a fresh driver process."""
    cache = COHORT / f"cache_{n}_{workers}"
    shutil.rmtree(cache, ignore_errors=True)
    cmd = [sys.executable, __file__, "--driver", str(manifest_for(n)), str(workers), str(cache)]
    t0 = time.perf_counter()
    out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
    wall = time.perf_counter() - t0
    shutil.rmtree(cache, ignore_errors=True)
    res = json.loads(out.strip().splitlines()[-1])
    res.update(n=n, workers=workers, wall_s=wall)
    print(
        f"| {n} | {workers} | {res['evaluate_s']:.0f} | {wall:.0f} | {res['driver_peak_mb']:.0f} |",
        flush=True,
    )
    return res


def driver(manifest: str, workers: int, cache: str) -> None:
    import itk_nrreval as nr

    t0 = time.perf_counter()
    res = nr.evaluate(
        manifest,
        n_samples=SAMPLES,
        execution=nr.Execution(scheduler="local", workers=workers, cache=cache),
        progress=False,
    )
    seconds = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # kB -> MB on Linux
    scores = {n: s.measures() for n, s in res.scores.items()}
    print(json.dumps({"evaluate_s": seconds, "driver_peak_mb": peak, "scores": scores}))


def plot(runs: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(9, 3.6))
    two = sorted((r for r in runs if r["workers"] == 2), key=lambda r: r["n"])
    ns = [r["n"] for r in two]
    a.plot(ns, [r["driver_peak_mb"] for r in two], "o-", label="driver peak RSS")
    a.axhline(1500, color="r", ls="--", label="1.5 GB target")
    a.set(xlabel="N images", ylabel="MB", title="Driver memory (2 workers)", ylim=(0, 1700))
    a.legend(loc="center right")
    pair = [r for r in runs if r["n"] == SPEEDUP_N]
    pair.sort(key=lambda r: r["workers"])
    b.bar(
        [f"{r['workers']} worker{'s' * (r['workers'] > 1)}" for r in pair],
        [r["evaluate_s"] for r in pair],
    )
    if len(pair) == 2:
        b.set_title(f"N = {SPEEDUP_N}: {pair[0]['evaluate_s'] / pair[1]['evaluate_s']:.2f}x")
    b.set(ylabel="evaluate time (s)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> dict:
    t0 = time.perf_counter()
    make_cohort()
    t_cohort = time.perf_counter() - t0
    print(f"cohort of {N_MAX} 3D subjects ready ({t_cohort:.0f} s)\n")
    print("| N | workers | evaluate (s) | with start-up (s) | driver peak (MB) |")
    print("|---|---|---|---|---|")
    runs = [run_driver(n, 2) for n in SIZES]
    runs.append(run_driver(SPEEDUP_N, 1))
    two = next(r for r in runs if r["n"] == SPEEDUP_N and r["workers"] == 2)
    one = runs[-1]
    speedup = one["evaluate_s"] / two["evaluate_s"]
    print(f"\n2 workers vs 1 at N = {SPEEDUP_N}: {speedup:.2f}x")
    plot(runs, ROOT / "docs" / "scaleout.png")
    return {"runs": runs, "speedup_2_vs_1": speedup, "speedup_n": SPEEDUP_N, "samples": SAMPLES}


if __name__ == "__main__":
    if len(sys.argv) == 5 and sys.argv[1] == "--driver":
        driver(sys.argv[2], int(sys.argv[3]), sys.argv[4])
    else:
        results = main()
        out = ROOT / "benchmarks" / "out" / "scaleout.json"
        out.write_text(json.dumps(results, indent=2) + "\n")
