"""Does specificity pick the right setting? Parameter sweeps on generated populations.

For each generated population (phantom and MNI-based 2D, one 3D phantom) and each sweep
(demons smoothing of the field and of the update, B-spline grid spacing and bending weight),
:func:`itk_nrreval.experiments.sweep.sweep` registers the population once per setting and evaluates
every setting; the population's true transforms give each setting's true mean
correspondence error. Reported per sweep: the setting chosen
by specificity (the verdict's best: lowest specificity among unflagged settings), the
settings it cannot separate from that one, the setting chosen by the truth and by the
inverse-volume overlap, Spearman correlations over the settings, and which settings the
plausibility checks flagged. Figures are copied to ``docs/sweep_<case>.png``.

Run: ``python benchmarks/run_all.py sweeps`` (about an hour on 2 cores; ``SWEEP_QUICK=1``
runs the 2D phantom fluid sweep only, ``SWEEP_CASES=a,b`` the cases named).
"""

from __future__ import annotations

import os
import shutil
import time
from pathlib import Path

from itk_nrreval.cli import main as cli
from itk_nrreval.experiments.sweep import sweep
from itk_nrreval.io.manifest import load_manifest
from itk_nrreval.io.transforms import chain_transform

HERE = Path(__file__).resolve().parent
OUT = HERE / "out" / "sweeps"
DOCS = HERE.parent / "docs"

SMOOTHING = (0.5, 1.0, 2.0, 4.0, 8.0, 16.0)  # demons field smoothing, mm at full resolution
GRID = (4.0, 8.0, 16.0, 32.0, 64.0)  # B-spline control-point spacing, mm
UPDATE = (0.0, 1.0, 2.0, 4.0, 8.0)  # demons update-field smoothing, mm at full resolution
BENDING = (0.0, 1.0, 10.0, 100.0, 1000.0)  # elastix bending-energy weight (similarity: 1)

CASES = [
    # (case, kind, dim, n, spacing, method, engine, parameter, values)
    ("phantom2d_fluid", "phantom", 2, 24, None, "fluid", None, "smoothing_mm", SMOOTHING),
    ("mni2d_fluid", "mni", 2, 24, None, "fluid", None, "smoothing_mm", SMOOTHING),
    ("phantom2d_pairwise", "phantom", 2, 24, None, "pairwise", None, "grid_spacing", GRID),
    ("mni2d_pairwise", "mni", 2, 24, None, "pairwise", None, "grid_spacing", GRID),
    (
        "phantom2d_fluid_update",
        "phantom",
        2,
        24,
        None,
        "fluid",
        None,
        "update_smoothing_mm",
        UPDATE,
    ),
    ("phantom2d_bending", "phantom", 2, 24, None, "pairwise", None, "bending_weight", BENDING),
    ("phantom3d_fluid", "phantom", 3, 10, 2.0, "fluid", None, "smoothing_mm", (1.0, 4.0, 16.0)),
]


def _population(kind: str, dim: int, n: int, spacing) -> Path:
    folder = OUT / f"data_{kind}{dim}d_n{n}"
    manifest = folder / "manifest.yaml"
    if not manifest.exists():
        args = ["synth", "--kind", kind, "--dim", str(dim), "--n", str(n), "--out", str(folder)]
        if spacing is not None:
            args += ["--spacing", str(spacing)]
        assert cli(args) == 0
    return manifest


def main() -> dict:
    quick = os.environ.get("SWEEP_QUICK") == "1"
    chosen = os.environ.get("SWEEP_CASES")  # e.g. "phantom2d_bending,mni2d_fluid"
    cases = CASES[: 1 if quick else None]
    if chosen:
        cases = [c for c in CASES if c[0] in chosen.split(",")]
    results = {}
    for case, kind, dim, n, spacing, method, engine, name, values in cases:
        t0 = time.perf_counter()
        manifest = _population(kind, dim, n, spacing)
        m = load_manifest(manifest)
        truth = m.registrations["truth"]
        res = sweep(
            list(m.images),
            method=method,
            parameters={name: values},
            out=OUT / case,
            labels=list(m.labels),
            engine=engine,
            truth=[chain_transform(t) for t in truth.transforms],
            truth_reference=truth.reference,
            n_samples=50_000,
            seed=0,
            progress=False,
        )
        shutil.copyfile(OUT / case / "sweep.png", DOCS / f"sweep_{case}.png")
        by = res.best_by
        flagged = [s.values[name] for s in res.settings if res.evaluation.scores[s.name].flags]
        value_of = {s.name: s.values[name] for s in res.settings}
        truth_best = by.get("true_correspondence_error_mm")
        results[case] = {
            "parameter": name,
            "values": list(values),
            "specificity_choice": value_of[res.lowest_specificity],
            "not_separable": [value_of[s] for s in res.not_separable],
            "lowest_specificity": value_of[by["specificity"]],
            "truth_choice": value_of[truth_best],
            "overlap_choice": value_of[by["overlap.inverse_volume"]],
            "truth_in_not_separable": truth_best in res.not_separable,
            "spearman_truth": res.spearman["true_correspondence_error_mm"],
            "spearman_overlap": res.spearman["overlap.inverse_volume"],
            "flagged": flagged,
            "truth_error_mm": {str(value_of[k]): v for k, v in res.truth_error_mm.items()},
            "seconds": round(time.perf_counter() - t0, 1),
        }
    print(
        "| case | parameter | specificity's choice (not separable) | lowest specificity | "
        "truth's choice | overlap's choice | Spearman vs truth | Spearman vs overlap | flagged |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for case, r in results.items():
        print(
            f"| {case} | {r['parameter']} | {r['specificity_choice']:g} "
            f"({', '.join(f'{v:g}' for v in r['not_separable'])}) | {r['lowest_specificity']:g} | "
            f"{r['truth_choice']:g} | {r['overlap_choice']:g} | {r['spearman_truth']:.2f} | "
            f"{r['spearman_overlap']:.2f} | {', '.join(f'{v:g}' for v in r['flagged']) or '-'} |"
        )
    return results


if __name__ == "__main__":
    main()
