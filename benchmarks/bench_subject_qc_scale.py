"""Per-subject quality control at scale (issue 27): N = 250, 500 and 1,000 on Dask.

A generated 2D phantom cohort (64 x 64 pixels of 1.6 mm, 14 labels) of N_MAX subjects with
two registrations: ``nonrigid`` (the true template-to-subject transforms) and ``affine``
(their affine parts), three subjects' registrations broken in both as a mix-up of files
would break them (:mod:`data_synth.damage`): subject 60 mirrored, subject 130 inverted,
subjects 200 and 201 swapped (each with the other's transform). The first N subjects are
evaluated with ``Execution(scheduler="local", workers=2)`` in a fresh driver process with a cold
cache (M = 10,000 model samples, no confidence intervals); reported: the evaluate time,
the driver's peak resident memory (the scheduler runs in it; the workers are separate
processes), the time of the per-subject step on the driver
(``assess_subjects`` twice per registration and ``transform_mixups``, the resampling of the
flagged subjects through changed transforms with their inner products apart), how many
subjects are flagged, and whether the damaged ones are flagged with the right diagnosis.

``python benchmarks/bench_subject_qc_scale.py`` runs it alone (about 6 minutes on 2 busy
cores); the cohort is generated once into ``benchmarks/out/subject_qc_scale`` (about
100 MB) and reused; the per-subject inputs of each run are saved there as
``qc_inputs_cache_<N>_<registration>.npz``, and timed again alone with one BLAS thread.
"""

from __future__ import annotations

import json
import math
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
COHORT = ROOT / "benchmarks" / "out" / "subject_qc_scale"
N_MAX = 1000
SIZES = (250, 500, 1000)
SIZE = 64
SEED = 27
#: Subject -> damage, in both registrations (a swap also damages the subject before it).
DAMAGES = {60: "mirrored", 130: "inverted", 201: "swapped"}
SAMPLES = 10_000


def _affine(transform) -> object:
    """The affine map `transform` is (a composite of affine maps), as one AffineTransform:
    read off the images of the origin and the unit vectors (exact for an affine map)."""
    import numpy as np
    import SimpleITK as sitk

    dim = transform.GetDimension()
    origin = np.asarray(transform.TransformPoint([0.0] * dim))
    columns = [np.asarray(transform.TransformPoint(list(e))) - origin for e in np.eye(dim)]
    return sitk.AffineTransform(np.stack(columns, axis=1).ravel().tolist(), origin.tolist())


def make_cohort() -> None:
    """N_MAX subjects, the damaged ``nonrigid`` manifest (data_synth.damage) and the affine
    parts of its transforms."""
    import SimpleITK as sitk
    import yaml

    from data_synth.damage import damaged_transform, write_damaged
    from data_synth.population import make_population

    if (COHORT / "subjects.json").exists():
        return
    pop = make_population("phantom", dim=2, n=N_MAX, seed=SEED, size=SIZE)
    _, damaged = write_damaged(pop, COHORT, DAMAGES)
    manifest = yaml.safe_load(damaged.read_text())
    poses = [s.template_to_subject.GetNthTransform(0) for s in pop.subjects]
    affine = list(poses)
    for i, damage in DAMAGES.items():
        if damage == "mirrored":
            flip = damaged_transform(pop, i, damage).GetNthTransform(0)
            affine[i] = sitk.CompositeTransform([flip, poses[i]])
        elif damage == "inverted":
            affine[i] = poses[i].GetInverse()
        elif damage == "swapped":
            affine[i], affine[i - 1] = poses[i - 1], poses[i]
    (COHORT / "affine").mkdir(exist_ok=True)
    affine_files = []
    for i, t in enumerate(affine):
        path = COHORT / "affine" / f"s{i:03d}.mat"
        sitk.WriteTransform(_affine(t), str(path))
        affine_files.append(str(path))
    (COHORT / "subjects.json").write_text(
        json.dumps(
            {
                "images": manifest["images"],
                "labels": manifest["labels"],
                "reference": manifest["registrations"]["damaged"]["reference"],
                "nonrigid": manifest["registrations"]["damaged"]["transforms"],
                "affine": affine_files,
            }
        )
    )


def manifest_for(n: int) -> Path:
    import yaml

    info = json.loads((COHORT / "subjects.json").read_text())
    data = {
        "images": info["images"][:n],
        "labels": info["labels"][:n],
        "registrations": {
            name: {"reference": info["reference"], "transforms": info[name][:n]}
            for name in ("nonrigid", "affine")
        },
    }
    path = COHORT / f"manifest_{n}.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def run_driver(n: int) -> dict:
    """One cold-cache evaluation on 2 workers in a fresh driver process."""
    cache = COHORT / f"cache_{n}"
    shutil.rmtree(cache, ignore_errors=True)
    cmd = [sys.executable, __file__, "--driver", str(manifest_for(n)), str(cache)]
    t0 = time.perf_counter()
    out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
    wall = time.perf_counter() - t0
    shutil.rmtree(cache, ignore_errors=True)
    res = json.loads(out.strip().splitlines()[-1])
    res.update(n=n, wall_s=wall)
    for k, r in enumerate(res["registrations"].values()):
        r.update(time_alone(n, k))
    for name, r in res["registrations"].items():
        damaged = " ".join(
            f"{d[:3]}{'+' if r['damaged'][d]['flagged'] else '-'}"
            f"{'+' if r['damaged'][d]['diagnosed'] else '-'}"
            for d in r["damaged"]
        )
        print(
            f"| {n} | {name} | {res['evaluate_s']:.0f} | {res['driver_peak_mb']:.0f} "
            f"({res['driver_peak_before_subject_qc_mb']:.0f}) | "
            f"{r['assess_s']:.2f} | {r['mixups_s']:.2f} | {r['products_s']:.2f} | "
            f"{r.get('leave_one_out_1thread_s', math.nan):.2f} | "
            f"{r.get('transform_mixups_1thread_s', math.nan):.2f} | "
            f"{r['flagged']} | {r['checked']} | {damaged} |",
            flush=True,
        )
    return res


def _peak_mb() -> float:
    """This process's peak resident memory so far (MB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # kB on Linux


def driver(manifest: str, cache: str) -> None:
    """Evaluate on 2 workers, timing the per-subject step (module docstring) as it runs."""
    import warnings

    import numpy as np

    import itk_nrreval as nr
    import itk_nrreval._evaluation_subjects as evaluation  # the caller: patched here
    from data_synth.damage import DIAGNOSES

    seconds = {}  # registration -> {"assess_s", "mixups_s", "products_s"}
    peaks = {}
    saved = []  # the registrations whose per-subject inputs were saved
    assess, mixups = evaluation.assess_subjects, evaluation.transform_mixups

    def timed_assess(**kwargs):
        if not seconds:  # the driver's peak before the first per-subject step
            peaks["before_subject_qc_mb"] = _peak_mb()
        t0 = time.perf_counter()
        out = assess(**kwargs)
        # the Gram matrix says which registration: every call of one shares it
        key = id(kwargs["gram"])
        seconds.setdefault(key, dict(assess_s=0.0, mixups_s=0.0, products_s=0.0))
        seconds[key]["assess_s"] += time.perf_counter() - t0
        return out

    def timed_mixups(subjects, *, products, gram, **kwargs):
        entry = seconds.setdefault(id(gram), dict(assess_s=0.0, mixups_s=0.0, products_s=0.0))

        def timed_products(alternatives):
            t0 = time.perf_counter()
            cross, squared = products(alternatives)
            entry["products_s"] += time.perf_counter() - t0
            # what the per-subject algebra needs, for main() to time it again alone
            np.savez(
                Path(cache).parent / f"qc_inputs_{Path(cache).name}_{len(saved)}.npz",
                gram=gram,
                scored=np.asarray(kwargs["scored"]),
                z=np.array([math.nan if q.z is None else q.z for q in subjects]),
                flagged=np.array([bool(q.flags) for q in subjects]),
                cross=cross,
                squared=squared,
            )
            saved.append(True)
            return cross, squared

        t0 = time.perf_counter()
        out = mixups(subjects, products=timed_products, gram=gram, **kwargs)
        entry["mixups_s"] += time.perf_counter() - t0 - entry["products_s"]
        entry["checked"] = len(out)
        return out

    evaluation.assess_subjects, evaluation.transform_mixups = timed_assess, timed_mixups
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the flagged-registration warnings
        res = nr.evaluate(
            manifest,
            n_samples=SAMPLES,
            execution=nr.Execution(scheduler="local", workers=2, cache=cache),
            confidence=False,
            progress=False,
        )
    evaluate_s = time.perf_counter() - t0
    peak = _peak_mb()
    damage_of = dict(DAMAGES)
    damage_of.update({i - 1: "swapped" for i, d in DAMAGES.items() if d == "swapped"})
    registrations = {}
    for (name, scores), timing in zip(res.scores.items(), seconds.values(), strict=True):
        subjects = scores.subjects
        registrations[name] = {
            **timing,
            "checked": timing.get("checked", 0),
            "flagged": sum(bool(q.flags) for q in subjects),
            "flagged_undamaged": sum(bool(q.flags) for q in subjects if q.index not in damage_of),
            # what the undamaged flagged subjects are diagnosed with (None: no cause named)
            "undamaged_diagnoses": [
                [q.index, q.diagnosis and q.diagnosis.split(":")[0], q.better_fit]
                for q in subjects
                if q.flags and q.index not in damage_of
            ],
            "damaged": {
                f"{d} ({i})": {
                    "flagged": bool(subjects[i].flags),
                    "diagnosed": bool(
                        subjects[i].diagnosis and DIAGNOSES[d] in subjects[i].diagnosis
                    ),
                    "diagnosis": subjects[i].diagnosis,
                    "better_fit": subjects[i].better_fit,
                }
                for i, d in sorted(damage_of.items())
            },
        }
    print(
        json.dumps(
            {
                "evaluate_s": evaluate_s,
                "driver_peak_mb": peak,
                "driver_peak_before_subject_qc_mb": peaks["before_subject_qc_mb"],
                "registrations": registrations,
            }
        )
    )


def time_alone(n: int, registration: int) -> dict:
    """The per-subject algebra on one registration's saved Gram matrix, in a fresh process
    with one BLAS thread (the driver's shares 2 cores with the workers and the machine):
    the leave-one-out distances and :func:`transform_mixups` (its products as saved)."""
    path = COHORT / f"qc_inputs_cache_{n}_{registration}.npz"
    if not path.exists():  # no subject flagged: nothing checked
        return {}
    one_thread = {k: "1" for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
    cmd = [sys.executable, __file__, "--alone", str(path)]
    env = {**os.environ, **one_thread}
    out = subprocess.run(cmd, check=True, capture_output=True, text=True, env=env).stdout
    return json.loads(out.strip().splitlines()[-1])


def alone(path: str) -> None:
    """:func:`time_alone`'s process: time the algebra on the saved inputs `path`."""
    import numpy as np

    from itk_nrreval.measures.subject_qc import SubjectQC, leave_one_out_distances, transform_mixups

    saved = np.load(path)
    subjects = [
        SubjectQC(index=i, image=str(i), score=None, z=float(z), flags=("flagged",) * bool(f))
        for i, (z, f) in enumerate(zip(saved["z"], saved["flagged"], strict=True))
    ]
    t0 = time.perf_counter()
    leave_one_out_distances(saved["gram"])
    loo = time.perf_counter() - t0
    t0 = time.perf_counter()
    transform_mixups(
        subjects,
        images=[str(i) for i in range(len(subjects))],
        scored=saved["scored"],
        gram=saved["gram"],
        products=lambda alternatives: (saved["cross"], saved["squared"]),
    )
    mixups = time.perf_counter() - t0
    print(json.dumps({"leave_one_out_1thread_s": loo, "transform_mixups_1thread_s": mixups}))


def main() -> dict:
    t0 = time.perf_counter()
    make_cohort()
    print(f"cohort of {N_MAX} 2D subjects ready ({time.perf_counter() - t0:.0f} s)\n")
    print(
        "| N | registration | evaluate (s) | driver peak (MB; before subject QC) | "
        "assess_subjects (s) | "
        "transform_mixups (s) | its resampling and products (s) | leave-one-out alone, "
        "1 thread (s) | transform_mixups alone, 1 thread (s) | flagged | checked | "
        "damaged: flagged, diagnosed |"
    )
    print("|---|---|--:|--:|--:|--:|--:|--:|--:|--:|--:|---|")
    runs = [run_driver(n) for n in SIZES]
    return {"runs": runs, "samples": SAMPLES, "size": SIZE, "damages": DAMAGES}


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "--driver":
        driver(sys.argv[2], sys.argv[3])
    elif len(sys.argv) == 3 and sys.argv[1] == "--alone":
        alone(sys.argv[2])
    else:
        results = main()
        out = ROOT / "benchmarks" / "out" / "subject_qc_scale.json"
        out.write_text(json.dumps(results, indent=2) + "\n")
