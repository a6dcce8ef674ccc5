"""Why does specificity prefer weakly smoothed demons? A direct test (docs/results.md).

The demo and the sweeps show specificity choosing less smoothing of the demons fields than
the true correspondence error does. The hypothesis was that weakly regularised fields
"follow noise and bias in homogeneous tissue". Two measurements test it on a 2D phantom
population of ``N`` subjects, registered with demons at each field smoothing of
``SMOOTHING`` (:func:`itk_nrreval.experiments.sweep.sweep`, with the true transforms):

1. The population as generated (global intensity scale, smooth bias field, Rician noise)
   and the same subjects (same anatomy, same true transforms, same seed) with *clean*
   intensities: no scale, no bias, no noise. If following noise and bias were the cause,
   the clean population would move specificity's choice towards the truth's.
2. The true registration evaluated beside the settings (same common frame, same region):
   a setting that scores *lower* specificity than the truth matches the images' intensities
   better than the true correspondence does -- it trades correspondence for similarity.

Run: ``python benchmarks/run_all.py fluid_hypothesis`` (about 15 minutes on 2 cores).
"""

from __future__ import annotations

import shutil
import time
import warnings
from pathlib import Path

import itk_nrreval as nr
from data_synth import make_population, write_population
from itk_nrreval.experiments.sweep import sweep
from itk_nrreval.io.manifest import add_registration, load_manifest
from itk_nrreval.io.transforms import chain_transform

HERE = Path(__file__).resolve().parent
OUT = HERE / "out" / "fluid_hypothesis"
N = 24
SMOOTHING = (0.5, 1.0, 2.0, 4.0, 8.0, 16.0)
POPULATIONS = {
    "as generated": {},
    "clean intensities": {"intensity_sd": 0.0, "bias_sd": 0.0, "noise": 0.0},
}


def _case(label: str, intensity: dict) -> dict:
    folder = OUT / label.replace(" ", "_")
    data = folder / "data" / "manifest.yaml"
    if not data.exists():
        pop = make_population("phantom", dim=2, n=N, seed=0, **intensity)
        write_population(pop, folder / "data", montage=False, progress=False)
    m = load_manifest(data)
    truth = m.registrations["truth"]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # flags and coverage are reported below
        res = sweep(
            list(m.images),
            method="fluid",
            parameters={"smoothing_mm": SMOOTHING},
            out=folder / "sweep",
            labels=list(m.labels),
            truth=[chain_transform(t) for t in truth.transforms],
            truth_reference=truth.reference,
            n_samples=50_000,
            seed=0,
            progress=False,
        )
    # The settings and the truth in one evaluation: the sweep's manifest plus `truth`.
    combined = folder / "sweep" / "with_truth.yaml"  # beside it: its paths are relative
    shutil.copyfile(folder / "sweep" / "manifest.yaml", combined)
    add_registration(  # the loaded manifest's paths are absolute
        combined,
        "truth",
        reference=truth.reference,
        transforms=[
            [str(p) for p in t] if isinstance(t, (list, tuple)) else str(t)
            for t in truth.transforms
        ],
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ev = nr.evaluate(
            combined,
            n_samples=50_000,
            seed=0,
            progress=False,
            execution=nr.Execution(cache=folder / "cache"),
        )
    value_of = {s.name: s.values["smoothing_mm"] for s in res.settings}
    rows = {}
    for name, scores in ev.scores.items():
        key = "truth" if name == "truth" else f"{value_of[name]:g}"
        rows[key] = {
            "specificity": scores.specificity.value,
            "ci95": [scores.intervals["specificity"].lo, scores.intervals["specificity"].hi],
            "overlap_inverse_volume": scores.overlap["inverse_volume"],
            "true_error_mm": 0.0 if name == "truth" else res.truth_error_mm[name],
            "flagged": bool(scores.flags),
        }
    return {
        "specificity_choice": value_of[res.lowest_specificity],
        "lowest_specificity": value_of[res.best_by["specificity"]],
        "truth_choice": value_of[res.best_by["true_correspondence_error_mm"]],
        "spearman_truth": res.spearman["true_correspondence_error_mm"],
        "below_truth": [
            k
            for k, r in rows.items()
            if k != "truth" and r["specificity"] < rows["truth"]["specificity"]
        ],
        "rows": rows,
    }


def main() -> dict:
    OUT.mkdir(parents=True, exist_ok=True)
    results = {}
    for label, intensity in POPULATIONS.items():
        t0 = time.perf_counter()
        results[label] = _case(label, intensity)
        results[label]["seconds"] = round(time.perf_counter() - t0, 1)
    for label, r in results.items():
        print(f"\n**{label}**: specificity's choice {r['specificity_choice']:g} mm (lowest "
              f"{r['lowest_specificity']:g}), truth's {r['truth_choice']:g} mm, Spearman "
              f"vs truth {r['spearman_truth']:+.2f}; below the truth's specificity: "
              f"{', '.join(r['below_truth']) or 'none'}\n")  # fmt: skip
        print(
            "| smoothing (mm) | specificity [95% CI] | overlap (inv. vol.) | true error (mm) "
            "| flagged |"
        )
        print("|---|--:|--:|--:|---|")
        for key, row in r["rows"].items():
            print(
                f"| {key} | {row['specificity']:.2f} "
                f"[{row['ci95'][0]:.2f}, {row['ci95'][1]:.2f}] | "
                f"{row['overlap_inverse_volume']:.3f} | "
                f"{row['true_error_mm']:.2f} | {'yes' if row['flagged'] else ''} |"
            )
    return results


if __name__ == "__main__":
    main()
