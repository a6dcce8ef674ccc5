"""The paper's Section IV experiment in its default configuration (``nrreval validate``).

N = 10 generated brain-like images (141 x 141, perfect registration), 12 values of d,
5 repeats, M = 50,000: 60 perturbed sets of 10 warps each. Target: under 3 minutes on 2 cores.
Also times the pieces (one warp draw, its inverse, one specificity) and writes the figures
to ``docs/validation_fig2.png`` and ``docs/validation_vs_d.png``.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent


def main() -> dict:
    from data_synth import perfectly_registered_arrays
    from itk_nrreval.cli.validate import plot_fig2, plot_vs_d
    from itk_nrreval.experiments.perturbation import DEFAULT_DISPLACEMENTS, validate
    from itk_nrreval.experiments.warps import random_cps
    from itk_nrreval.measures.specificity import specificity

    t0 = time.perf_counter()
    images, labels = perfectly_registered_arrays("phantom", n=10, seed=0)
    t_data = time.perf_counter() - t0

    t0 = time.perf_counter()
    warps = [random_cps((141, 141), 3.0, seed=s) for s in range(5)]
    t_draw = (time.perf_counter() - t0) / 5
    t0 = time.perf_counter()
    for w in warps:
        w.inverse_field()
    t_inv = (time.perf_counter() - t0) / 5
    specificity(images, n_samples=1000)  # compile
    t0 = time.perf_counter()
    specificity(images, n_samples=50_000)
    t_spec = time.perf_counter() - t0

    t0 = time.perf_counter()
    res = validate(
        images,
        labels,
        displacements=DEFAULT_DISPLACEMENTS,
        repeats=5,
        n_samples=50_000,
        weightings=("complexity", "inverse_volume"),
        seed=0,
        progress=False,
        source="synthetic:phantom",
    )
    t_run = time.perf_counter() - t0
    docs = ROOT / "docs"
    docs.mkdir(exist_ok=True)
    plot_fig2(res, docs / "validation_fig2.png")
    plot_vs_d(res, docs / "validation_vs_d.png")

    s = res.summary
    m = res.means()
    print("| step | seconds |\n|---|---|")
    print(f"| generate 10 images + labels | {t_data:.2f} |")
    print(f"| one CPS warp at d = 3 (with redraws) | {t_draw:.3f} |")
    print(f"| its inverse (Newton) | {t_inv:.3f} |")
    print(f"| one specificity, M = 50,000 | {t_spec:.3f} |")
    print(f"| **validate: 12 d x 5 repeats, N = 10** | **{t_run:.1f}** (target < 180) |")
    print()
    print("| d | specificity | SD | overlap (complexity) | overlap (inverse volume) |")
    print("|---|---|---|---|---|")
    for k, d in enumerate(m["displacement"]):
        print(
            f"| {d:g} | {m['specificity'][k]:.3f} | {m['specificity_sd'][k]:.3f} | "
            f"{m['overlap_complexity'][k]:.4f} | {m['overlap_inverse_volume'][k]:.4f} |"
        )
    print()
    print(
        f"Pearson r (d >= 0.375): complexity {s.pearson_r['complexity']:.4f}, "
        f"inverse volume {s.pearson_r['inverse_volume']:.4f}; Spearman {s.spearman:.4f}; "
        f"sensitivity {s.sensitivity:.1f} stderr per pixel; monotonic {s.monotonic}"
    )
    return {
        "seconds_validate": t_run,
        "seconds_data": t_data,
        "seconds_warp_draw_d3": t_draw,
        "seconds_warp_inverse": t_inv,
        "seconds_specificity": t_spec,
        "pearson_r": s.pearson_r,
        "spearman": s.spearman,
        "sensitivity": s.sensitivity,
        "monotonic": s.monotonic,
        "unperturbed": s.unperturbed,
        "mean_specificity": [float(v) for v in m["specificity"]],
        "displacements": [float(v) for v in m["displacement"]],
        "min_jacobian": float(np.min(res.column("min_jacobian"))),
    }


if __name__ == "__main__":
    main()
