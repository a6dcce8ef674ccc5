"""Can the verdict be gamed? Rohlfing's class-matching cheat against the demo's registrations.

The demo population (2D phantom, N = 36) is registered by the five genuine algorithms
(:func:`itk_nrreval.experiments.demo.run_demo`). A sixth "registration" then maps every voxel of the
fluid reference to the nearest voxel of the same intensity class in each affinely aligned
image (:func:`data_synth.cheat.class_matching_cheat`; classes: the reference's intensity
quartiles inside the brain, background apart). The images it produces look like the
reference, class by class, while correspondence inside each class is nonsense.

Reported: the cheat's specificity rank by the score alone and in the verdict (flags
applied), its plausibility, and whether any genuine registration is flagged.
``python benchmarks/run_all.py cheat`` (about 5 minutes).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import SimpleITK as sitk
import yaml

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "benchmarks" / "out" / "cheat"
SAMPLES = 100_000


def classes_of(image: sitk.Image, edges: np.ndarray) -> sitk.Image:
    arr = sitk.GetArrayFromImage(image)
    out = sitk.GetImageFromArray(np.digitize(arr, edges).astype(np.int16))
    out.CopyInformation(image)
    return out


def add_cheat(demo_out: Path) -> Path:
    """Write the cheat of the demo in `demo_out` beside its registrations.

    Returns ``demo_out / "manifest_cheat.yaml"``: the demo's manifest plus ``cheat``.
    """
    from data_synth.cheat import class_matching_cheat
    from itk_nrreval.io.frame import read_chains
    from itk_nrreval.io.manifest import load_manifest

    manifest_path = demo_out / "manifest.yaml"
    m = load_manifest(manifest_path)
    ref = sitk.ReadImage(str(m.registrations["affine"].reference))
    arr = sitk.GetArrayFromImage(ref)
    brain = arr > 0.05 * arr.max()
    edges = np.quantile(arr[brain], [0.0, 0.25, 0.5, 0.75])  # background, then 4 classes
    ref_classes = classes_of(ref, edges)
    folder = demo_out / "registrations" / "cheat"
    folder.mkdir(parents=True, exist_ok=True)
    items = []
    for i, (path, affine) in enumerate(zip(m.images, read_chains(m, "affine"), strict=True)):
        image = sitk.ReadImage(str(path), sitk.sitkFloat64)
        aligned = sitk.Resample(image, ref, affine, sitk.sitkLinear, 0.0)
        cheat = class_matching_cheat(ref_classes, classes_of(aligned, edges), affine)
        sitk.WriteTransform(cheat, str(folder / f"s{i:02d}.h5"))
        items.append(str(folder / f"s{i:02d}.h5"))
    data = yaml.safe_load(manifest_path.read_text())
    data["registrations"]["cheat"] = {
        "reference": data["registrations"]["affine"]["reference"],
        "reference_index": data["registrations"]["affine"].get("reference_index"),
        "transforms": items,
    }
    if data["registrations"]["cheat"]["reference_index"] is None:
        del data["registrations"]["cheat"]["reference_index"]
    cheat_manifest = demo_out / "manifest_cheat.yaml"
    cheat_manifest.write_text(yaml.safe_dump(data, sort_keys=False))
    return cheat_manifest


def main() -> dict:
    import itk_nrreval as nr
    from itk_nrreval.experiments.demo import run_demo

    t0 = time.perf_counter()
    demo = run_demo(out=OUT, n=36, n_samples=SAMPLES, progress=False, log=lambda _: None)
    cheat_manifest = add_cheat(OUT)
    res = nr.evaluate(
        cheat_manifest,
        n_samples=SAMPLES,
        execution=nr.Execution(cache=OUT / "cache"),
        progress=False,
        seed=0,
    )
    names = list(res.scores)
    by_score = sorted(names, key=lambda n: res.scores[n].specificity.value)
    cheat = res.scores["cheat"]
    print("| registration | specificity | 95% CI | rank by score | folded | SDlogJ | flags |")
    print("|---|--:|---|--:|--:|--:|---|")
    for n in by_score:
        s = res.scores[n]
        iv = s.intervals["specificity"]
        print(
            f"| {n} | {s.specificity.value:.2f} | [{iv.lo:.2f}, {iv.hi:.2f}] | "
            f"{by_score.index(n) + 1} | {s.folded_fraction:.2%} | {s.plausibility.sdlogj:.2f} | "
            f"{'; '.join(s.flags) or '-'} |"
        )
    print()
    for t in res.verdict.text:
        print(t)
    out = {
        "rank_by_score": by_score.index("cheat") + 1,
        "rank_in_verdict": res.verdict.ranking.index("cheat") + 1,
        "n_registrations": len(names),
        "cheat_flags": list(cheat.flags),
        "cheat_plausibility": cheat.plausibility.to_dict(),
        "genuine_flagged": {n: list(res.scores[n].flags) for n in names if n != "cheat"},
        "specificity": {n: res.scores[n].specificity.value for n in names},
        "overlap_inverse_volume": {n: res.scores[n].overlap["inverse_volume"] for n in names},
        "correspondence_error_demo": demo.correspondence_error_mm,
        "verdict": res.verdict.to_dict(),
        "seconds": time.perf_counter() - t0,
    }
    print(
        f"\ncheat: rank {out['rank_by_score']} of {len(names)} by specificity alone, "
        f"{out['rank_in_verdict']} in the verdict ({out['seconds']:.0f} s)"
    )
    return out
