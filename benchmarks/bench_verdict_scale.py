"""Does specificity at a coarser image scale stop preferring rough fields? (issue 26, (c))

The known-truth benchmark (``bench_verdict.py``) leaves most pairs of the demons
field-smoothing sweeps open: the rougher setting has the lower specificity, not by enough
to rule out that roughness bought it. If what rough fields fit were fine-scale noise, the
texture model of smoothed images would lose that advantage. This benchmark takes the two
sweeps that ``bench_verdict.py`` ran (run it first), resamples their images into the common
frame once (``export_resampled`` after ``evaluate``), smooths each by a Gaussian of sigma mm
(0 = as registered) and counts, per scale, the pairs of settings that specificity orders as
the true correspondence error does.

``python benchmarks/bench_verdict_scale.py`` (about 2 minutes once ``bench_verdict`` has run).
"""

from __future__ import annotations

import itertools
import json
import tempfile
import warnings
from pathlib import Path

import numpy as np
import SimpleITK as sitk

import itk_nrreval as nr

VERDICT = Path(__file__).resolve().parent / "out" / "verdict"
CASES = ("sweep_phantom2d_fluid", "sweep_mni2d_fluid")
SIGMAS_MM = (0.0, 1.0, 2.0, 4.0)


def _specificity_by_scale(case: str) -> tuple[dict, dict]:
    errors = json.loads((VERDICT / case / "truth.json").read_text())["true_error_mm"]
    saved = VERDICT / case / "resampled"
    if not (saved / "region.nii.gz").exists():
        with warnings.catch_warnings(), tempfile.TemporaryDirectory() as cache:
            warnings.simplefilter("ignore")  # the flags are bench_verdict's business
            result = nr.evaluate(
                VERDICT / case / "sweep" / "manifest.yaml",
                n_samples=2000,
                seed=0,
                progress=False,
                confidence=False,
                execution=nr.Execution(cache=cache, keep_resampled=True),
            )
            nr.export_resampled(result, saved, cache=cache)
    region = sitk.GetArrayFromImage(sitk.ReadImage(str(saved / "region.nii.gz"))) > 0
    spec: dict[float, dict[str, float]] = {}
    for sigma in SIGMAS_MM:
        spec[sigma] = {}
        for name in errors:
            rows = []
            for path in sorted((saved / name).glob("image_*.nii.gz")):
                image = sitk.ReadImage(str(path))
                if sigma > 0:
                    image = sitk.SmoothingRecursiveGaussian(image, sigma)  # sigma in mm
                rows.append(sitk.GetArrayFromImage(image)[region])
            spec[sigma][name] = nr.specificity(np.stack(rows), n_samples=20_000, seed=0).value
    return errors, spec


def main() -> dict:
    missing = [c for c in CASES if not (VERDICT / c / "truth.json").exists()]
    if missing:
        raise SystemExit(f"run bench_verdict.py first (no saved case {', '.join(missing)})")
    out: dict = {}
    lines = ["| case | pairs | " + " | ".join(f"sigma {s:g} mm" for s in SIGMAS_MM) + " |"]
    lines.append("|---|--:|" + "--:|" * len(SIGMAS_MM))
    for case in CASES:
        errors, spec = _specificity_by_scale(case)
        pairs = list(itertools.combinations(errors, 2))
        agree = {
            s: sum((errors[a] < errors[b]) == (spec[s][a] < spec[s][b]) for a, b in pairs)
            for s in SIGMAS_MM
        }
        out[case] = {"pairs": len(pairs), "agree_with_truth": agree, "specificity": spec}
        lines.append(
            f"| {case} | {len(pairs)} | " + " | ".join(str(agree[s]) for s in SIGMAS_MM) + " |"
        )
    print("Pairs of settings ordered by specificity as by the true error, per image scale:\n")
    print("\n".join(lines))
    return out


if __name__ == "__main__":
    main()
