"""Each registration's own perturbation curve as a ruler: a label-free idea tried for the
verdict, NOT KEPT.

Issue 41, idea (b): apply the paper's clamped-plate-spline warps of known mean displacement
``d`` to *each* registration's result (not only the common frame's), and read from its
specificity curve ``S(d)`` how much a millimetre of misregistration costs that registration.
If errors added in quadrature, ``S(d) ~ a + k sqrt(e^2 + d^2)`` would give each
registration's own error ``e`` from the curve's bend near ``d = 0``; short of that, the
curve's rise under a small perturbation (``S(0.5) / S(0)``) says how much of a low
specificity is fine-scale fit that half a pixel undoes.

Measured on the verdict benchmark's two TUNING cases of registration families
(``families_mni2d``, ``families_phantom2d``: affine, demons at 0.5-4 mm, B-splines on 10 and
25 mm grids, each to subject 0): ``d`` = 0, 0.5, 1, 2, 3 pixels, 3 repeats, M = 5,000, seed 0
(:func:`itk_nrreval.experiments.perturbation.validate_manifest` with each registration as the common
frame; all seven share subject 0's grid). Spearman of each candidate against the true
error, over the seven registrations and over the six deformable ones, is in
``docs/verdict.md`` ("A registration's own perturbations as a ruler"). No candidate orders
the registrations the same way on both cases, so none was carried to the held-out split.

``python benchmarks/bench_perturbation_ruler.py [--compute]``: ``--compute`` first measures
the curves of the cases that lack them (``ruler.json`` in the case's folder, about 3-4
minutes a case on 2 cores); then the table is printed and written to
``benchmarks/out/verdict/ruler.md``. Without the verdict benchmark's saved cases
(``python benchmarks/bench_verdict.py --new``) it says so and does nothing.
"""

from __future__ import annotations

import json
import sys
import warnings
from pathlib import Path

import numpy as np
import yaml
from scipy.stats import spearmanr

from itk_nrreval.experiments.perturbation import validate_manifest

HERE = Path(__file__).resolve().parent
OUT = HERE / "out" / "verdict"
CASES = ("families_mni2d", "families_phantom2d")  # TUNING cases only (bench_verdict.TUNING)
DISPLACEMENTS = (0.0, 0.5, 1.0, 2.0, 3.0)  # mean CPS displacement, pixels
REPEATS = 3
N_SAMPLES = 5000
RULER_JSON = "ruler.json"


def _absolute(case: Path, manifest: dict) -> dict:
    """The case's manifest with every path absolute (it is passed as a dict)."""

    def at(p):
        return str((case / p).resolve())

    out = dict(manifest, images=[at(p) for p in manifest["images"]])
    out["labels"] = [at(p) for p in manifest["labels"]]
    out["mask"] = at(manifest["mask"])
    out["registrations"] = {
        name: dict(
            reg, reference=at(reg["reference"]), transforms=[at(p) for p in reg["transforms"]]
        )
        for name, reg in manifest["registrations"].items()
    }
    return out


def measure(case: Path) -> dict:
    """Every registration's specificity under each perturbation (``ruler.json``)."""
    manifest = _absolute(case, yaml.safe_load((case / "manifest.yaml").read_text()))
    truth = json.loads((case / "truth.json").read_text())["true_error_mm"]
    curves = {}
    for name in manifest["registrations"]:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = validate_manifest(
                dict(manifest, common_frame=name),
                displacements=DISPLACEMENTS,
                repeats=REPEATS,
                n_samples=N_SAMPLES,
                seed=0,
                progress=False,
            )
        curves[name] = {
            "d": [r.displacement for r in result.rows],
            "specificity": [r.specificity for r in result.rows],
            "true_error_mm": truth[name],
        }
        print(f"{case.name}: {name} measured", file=sys.stderr)
    tmp = case / (RULER_JSON + ".tmp")
    tmp.write_text(json.dumps(curves) + "\n")
    tmp.replace(case / RULER_JSON)
    return curves


def candidates(curves: dict) -> dict[str, dict[str, float]]:
    """Each candidate's value per registration: specificity at d = 0, 0.5, 1 and 2 pixels,
    the rise ``S(0.5) / S(0)`` and the slope between 1 and 3 pixels."""

    def at(name, d):
        c = curves[name]
        return float(np.mean([s for x, s in zip(c["d"], c["specificity"], strict=True) if x == d]))

    return {
        "S(0)": {n: at(n, 0.0) for n in curves},
        "S(0.5)": {n: at(n, 0.5) for n in curves},
        "S(1)": {n: at(n, 1.0) for n in curves},
        "S(2)": {n: at(n, 2.0) for n in curves},
        "S(0.5) / S(0)": {n: at(n, 0.5) / at(n, 0.0) for n in curves},
        "(S(3) - S(1)) / 2": {n: (at(n, 3.0) - at(n, 1.0)) / 2 for n in curves},
    }


def main(argv: list[str] | None = None) -> dict:
    """The table (``rows``: its lines); `argv` ``["--compute"]`` measures the cases that lack
    it first (``run_all.py`` passes nothing)."""
    argv = [] if argv is None else argv
    if not all((OUT / c / "truth.json").exists() for c in CASES):
        print("no saved cases: run `python benchmarks/bench_verdict.py --new` first")
        return {"rows": []}
    lines = ["| case | candidate | Spearman, 7 registrations | 6 deformable |", "|---|---|--:|--:|"]
    for c in CASES:
        path = OUT / c / RULER_JSON
        if not path.exists() and "--compute" not in argv:
            continue
        curves = json.loads(path.read_text()) if path.exists() else measure(OUT / c)
        truth = {n: v["true_error_mm"] for n, v in curves.items()}
        deformable = [n for n in curves if n != "affine"]
        for label, values in candidates(curves).items():
            every = spearmanr([values[n] for n in curves], [truth[n] for n in curves])[0]
            some = spearmanr([values[n] for n in deformable], [truth[n] for n in deformable])[0]
            lines.append(f"| {c} | {label} | {every:+.2f} | {some:+.2f} |")
    text = "\n".join(lines) + "\n"
    print(text)
    (OUT / "ruler.md").write_text(text)
    return {"rows": lines[2:]}


if __name__ == "__main__":
    main(sys.argv[1:])
