"""Peak memory of the default (in-process) ``evaluate`` against N, 3D with labels.

Generated 3D phantom cohorts (26 labels) with two registrations: ``truth`` (the true
template-to-subject transforms, the common frame) and ``affine`` (only their affine part).
Each evaluation runs in a fresh process with a cold cache and reports its own peak resident
memory (``ru_maxrss``) and time:

- 2 mm voxels (100 x 118 x 95): N = 12, 24, 36, 72 -- peak RSS against N;
- 1 mm voxels (200 x 236 x 190, 9.0 M voxels): N = 36, the size of a typical validation
  study (target: under 3 GB).

For comparison, the in-memory evaluation the toolkit had before the one-pipeline rewrite
(it held N float64 images, an N x n stack and dense N x L x n float32 memberships) needs
``N n (8 + 8 + 4 (L + 1))`` bytes for those arrays alone; the model line on the figure.

``python benchmarks/run_all.py memory`` runs it (about an hour; the cohorts are generated
once into ``benchmarks/out/cohort3d_{2,1}mm`` and reused). Writes ``docs/memory.png``.
"""

from __future__ import annotations

import json
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
N_LABELS = 26
SAMPLES = 100_000
RUNS = ((2.0, (12, 24, 36, 72)), (1.0, (36,)))


def cohort(spacing: float, n: int) -> Path:
    """A folder with ``subjects.json``: at least `n` subjects at `spacing` mm, made in batches."""
    import SimpleITK as sitk
    import yaml

    from data_synth.population import make_population
    from data_synth.writing import write_population

    folder = ROOT / "benchmarks" / "out" / f"cohort3d_{spacing:g}mm"
    info_path = folder / "subjects.json"
    info = json.loads(info_path.read_text()) if info_path.exists() else {"subjects": []}
    batch = 12 if spacing >= 2 else 4  # a batch of 1 mm subjects holds ~3 GB
    b = len(info["subjects"]) // batch
    while len(info["subjects"]) < n:
        sub = folder / f"batch{b}"
        pop = make_population("phantom", dim=3, n=batch, seed=300 + b, spacing=spacing)
        manifest = yaml.safe_load(write_population(pop, sub, montage=False).read_text())
        for i, s in enumerate(pop.subjects):
            affine = sitk.AffineTransform(s.template_to_subject.GetNthTransform(0))
            mat = sub / "affine" / f"s{i:02d}.mat"
            mat.parent.mkdir(exist_ok=True)
            sitk.WriteTransform(affine, str(mat))
            info["subjects"].append(
                {
                    "image": str(sub / manifest["images"][i]),
                    "labels": str(sub / manifest["labels"][i]),
                    "truth": str(sub / manifest["registrations"]["truth"]["transforms"][i]),
                    "affine": str(mat),
                }
            )
        info.setdefault("template", str(sub / manifest["registrations"]["truth"]["reference"]))
        info_path.write_text(json.dumps(info))
        del pop
        b += 1
    return folder


def manifest_for(folder: Path, n: int) -> Path:
    import yaml

    info = json.loads((folder / "subjects.json").read_text())
    subs = info["subjects"][:n]
    data = {
        "images": [s["image"] for s in subs],
        "labels": [s["labels"] for s in subs],
        "registrations": {
            "truth": {"reference": info["template"], "transforms": [s["truth"] for s in subs]},
            "affine": {"reference": info["template"], "transforms": [s["affine"] for s in subs]},
        },
    }
    path = folder / f"manifest_{n}.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def run(spacing: float, n: int) -> dict:
    """One cold-cache in-process evaluation in a fresh process."""
    folder = cohort(spacing, n)
    cache = folder / f"cache_{n}"
    shutil.rmtree(cache, ignore_errors=True)
    cmd = [sys.executable, __file__, "--run", str(manifest_for(folder, n)), str(cache)]
    out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
    shutil.rmtree(cache, ignore_errors=True)
    res = json.loads(out.strip().splitlines()[-1])
    res.update(spacing_mm=spacing, n=n)
    print(
        f"| {spacing:g} | {n} | {res['n_voxels'] / 1e6:.2f} M | {res['evaluate_s']:.0f} | "
        f"{res['peak_mb']:.0f} | {res['old_arrays_mb']:.0f} |",
        flush=True,
    )
    return res


def _run_one(manifest: str, cache: str) -> None:
    import numpy as np

    import itk_nrreval as nr

    t0 = time.perf_counter()
    res = nr.evaluate(
        manifest, n_samples=SAMPLES, execution=nr.Execution(cache=cache), progress=False
    )
    seconds = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # kB -> MB on Linux
    n_vox = int(np.prod(next(iter(res.mean_images.values())).shape))
    n = res.inputs["n_images"]
    n_values = len(res.options["label_values"])
    old = n * n_vox * (8 + 8 + 4 * n_values) / 2**20
    scores = {k: s.measures() for k, s in res.scores.items()}
    print(
        json.dumps(
            {
                "evaluate_s": seconds,
                "peak_mb": peak,
                "n_voxels": n_vox,
                "old_arrays_mb": old,
                "scores": scores,
            }
        )
    )


def plot(runs: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4))
    for spacing, marker in ((2.0, "o"), (1.0, "s")):
        rs = sorted((r for r in runs if r["spacing_mm"] == spacing), key=lambda r: r["n"])
        if not rs:
            continue
        ns = [r["n"] for r in rs]
        ax.plot(
            ns, [r["peak_mb"] / 1024 for r in rs], marker + "-", label=f"{spacing:g} mm: peak RSS"
        )
        ax.plot(
            ns,
            [r["old_arrays_mb"] / 1024 for r in rs],
            marker + ":",
            color="grey",
            label=f"{spacing:g} mm: arrays held before (model)",
        )
    ax.axhline(3, color="r", ls="--", label="3 GB target (N = 36, 1 mm)")
    ax.set(
        xlabel="N images",
        ylabel="GB",
        yscale="log",
        title="evaluate, in process, 3D, 26 labels, 2 registrations",
    )
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> dict:
    print("| voxel (mm) | N | voxels | evaluate (s) | peak RSS (MB) | arrays held before (MB) |")
    print("|---|---|---|---|---|---|")
    runs = [run(spacing, n) for spacing, ns in RUNS for n in ns]
    plot(runs, ROOT / "docs" / "memory.png")
    return {"runs": runs, "samples": SAMPLES}


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "--run":
        _run_one(sys.argv[2], sys.argv[3])
    else:
        results = main()
        out = ROOT / "benchmarks" / "out" / "memory.json"
        out.write_text(json.dumps(results, indent=2) + "\n")
