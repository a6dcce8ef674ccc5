"""Per-subject quality control (issue 27): are failed subjects found, and clean ones left alone?

Generated phantom cohorts (data_synth), one per seed, in two settings: 2D, N = 36, 64 x 64
pixels; 3D, N = 12, 32^3 voxels of 2 mm. Each is evaluated with ``nrreval evaluate``: with
its true registration (clean: every flag is a false positive), and with some subjects'
registrations broken (:mod:`data_synth.damage`: mirrored, affine only, displacements
scaled 3x, duplicated image, shifted off the common grid, inverted transform, two subjects'
transforms swapped), a few damages per damaged cohort (``GROUPS``) at positions that move
with the seed. Reported per damage: the recall (damaged subjects flagged; both subjects of
a swap are damaged), the right diagnoses (flagged with the right cause named), and the
diagnosis accuracy where one is named; the false positives among the undamaged subjects of
the damaged cohorts (the subject a duplicate copies is flagged with it, and is counted
apart: either of the two may be the copy) and of the clean cohorts; how many times better
the alternatives of :func:`itk_nrreval.measures.subject_qc.transform_mixups` fit (``better_fit``),
which ``SubjectThresholds.better_fit_ratio`` was set from; and on the clean 2D cohorts the
spread of each robust z-score (quantiles and the share beyond the default thresholds),
which the other thresholds of :class:`itk_nrreval.io.plausibility.SubjectThresholds` were set
from.

Run with ``nice -n 5`` on a shared machine; ``SETTINGS`` sets the cost (about 4 minutes).
"""

from __future__ import annotations

import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

import itk_nrreval as nr
from data_synth import make_population
from data_synth.damage import DAMAGES, DIAGNOSES, write_damaged

SCALE = 3.0
Z_NAMES = ("z", "overlap_z", "sdlogj_z", "nonlinear_rms_z", "inverse_consistency_z")
#: The mix-ups that transform_mixups names; every other damage's better_fit should be low.
MIXUPS = ("inverted", "swapped")

#: Per setting: dimension, N, voxels per side, seeds, and the damages of each damaged
#: cohort of a seed (one subject per damage; a swap and a duplicate also take the subject
#: before it). Fewer damages per cohort at N = 12, where each damaged subject is 8%.
SETTINGS = {
    "2D": {
        "dim": 2,
        "n": 36,
        "size": 64,
        "seeds": tuple(range(1, 13)),
        "groups": (
            ("mirrored", "affine_only", "scaled", "duplicated", "off_grid"),
            ("inverted", "swapped"),
        ),
    },
    "3D": {
        "dim": 3,
        "n": 12,
        "size": 32,
        "seeds": tuple(range(1, 9)),
        "groups": (
            ("mirrored", "inverted"),
            ("affine_only", "scaled"),
            ("swapped",),
            ("duplicated", "off_grid"),
        ),
    },
}


def _damages(seed: int, damages: tuple[str, ...], n: int) -> dict[int, str]:
    """One subject per damage, evenly spaced from a start that moves with the seed (never
    subject 0; the subject before each is undamaged)."""
    spacing = n // len(damages)
    start = 1 + (seed * 7) % (spacing - 1)
    return {start + spacing * k: damage for k, damage in enumerate(damages)}


def _z_values(q) -> dict[str, float]:
    d = q.deformation
    return {
        "z": q.z,
        "overlap_z": q.overlap_z,
        "sdlogj_z": d["sdlogj_z"],
        "nonlinear_rms_z": d["nonlinear_rms_z"],
        "inverse_consistency_z": d["inverse_consistency_z"],
    }


def _evaluate(manifest: Path):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # coverage and flagged-registration warnings
        result = nr.evaluate(manifest, n_samples=500, confidence=False, progress=False)
    return next(iter(result.scores.values())).subjects


def _setting(dim: int, n: int, size: int, seeds, groups, tmp: Path) -> dict:
    """Evaluate every seed's clean and damaged cohorts of one setting; count."""
    total = {d: 0 for d in DAMAGES}
    found = {d: 0 for d in DAMAGES}
    named = {d: 0 for d in DAMAGES}
    right = {d: 0 for d in DAMAGES}
    better_fit: dict[str, list[float]] = {}  # damage (or "undamaged") -> checked subjects'
    false_pos, partners, n_partners, others = 0, 0, 0, 0
    clean_flagged, clean_total = 0, 0
    clean_reasons: dict[str, int] = {}
    false_pos_reasons: dict[str, int] = {}  # the damaged cohorts' false positives, by words
    zs: dict[str, list[float]] = {k: [] for k in Z_NAMES}
    for seed in seeds:
        pop = make_population("phantom", dim=dim, n=n, seed=seed, size=size)
        for g, group in enumerate(groups):
            damages = _damages(seed, group, n)
            folder = tmp / f"{dim}d-s{seed}-g{g}"
            clean, damaged = write_damaged(pop, folder, damages, scale=SCALE)
            if g == 0:  # the clean cohort is the same for every group
                for q in _evaluate(clean):
                    clean_total += 1
                    clean_flagged += bool(q.flags)
                    for flag in q.flags:
                        key = flag.split(" ")[0]
                        clean_reasons[key] = clean_reasons.get(key, 0) + 1
                    for k, v in _z_values(q).items():
                        if v is not None:
                            zs[k].append(v)
            damage_of = dict(damages)
            damage_of.update({i - 1: "swapped" for i, d in damages.items() if d == "swapped"})
            copied = {i - 1 for i, d in damages.items() if d == "duplicated"}
            for q in _evaluate(damaged):
                kind = damage_of.get(q.index)
                if q.better_fit is not None:
                    key = kind if kind is not None else "undamaged"
                    better_fit.setdefault(key, []).append(q.better_fit)
                if kind is not None:
                    total[kind] += 1
                    found[kind] += bool(q.flags)
                    named[kind] += q.diagnosis is not None
                    right[kind] += bool(q.diagnosis and DIAGNOSES[kind] in q.diagnosis)
                elif q.index in copied:
                    n_partners += 1
                    partners += bool(q.flags)
                else:
                    others += 1
                    false_pos += bool(q.flags)
                    for flag in q.flags:
                        key = " ".join(flag.split(":")[0].split()[:6])
                        false_pos_reasons[key] = false_pos_reasons.get(key, 0) + 1
    return {
        "dim": dim,
        "n": n,
        "size": size,
        "seeds": list(seeds),
        "groups": [list(g) for g in groups],
        "total": total,
        "flagged": found,
        "named": named,
        "right": right,
        "damaged_cohort_false_positives": [false_pos, others],
        "damaged_cohort_false_positive_flags": false_pos_reasons,
        "duplicate_partners_flagged": [partners, n_partners],
        "clean_flagged": [clean_flagged, clean_total],
        "clean_flag_reasons": clean_reasons,
        "better_fit": {k: sorted(v) for k, v in better_fit.items()},
        "clean_z": zs,
    }


def _spread(zs: dict[str, list[float]]) -> dict[str, dict]:
    th = nr.SubjectThresholds()
    limits = {
        "z": th.outlier_z,
        "overlap_z": -th.overlap_z,
        "sdlogj_z": th.deformation_z,
        "nonlinear_rms_z": th.deformation_z,
        "inverse_consistency_z": th.deformation_z,
    }
    spread = {}
    for k, values in zs.items():
        v = np.asarray(values)
        v = v[np.isfinite(v)]
        beyond = np.mean(v < limits[k]) if limits[k] < 0 else np.mean(v > limits[k])
        spread[k] = {
            "n": int(v.size),
            "q01": float(np.quantile(v, 0.01)),
            "median": float(np.median(v)),
            "q99": float(np.quantile(v, 0.99)),
            "min": float(v.min()),
            "max": float(v.max()),
            "sd": float(v.std()),
            "beyond_threshold": float(beyond),
            "threshold": limits[k],
        }
    return spread


def _print(name: str, r: dict, seconds: float) -> None:
    side = " x ".join([str(r["size"])] * r["dim"])
    print(
        f"\n{name} phantom cohorts, N = {r['n']} ({side} voxels), {len(r['seeds'])} seeds, "
        f"damaged cohorts per seed: {r['groups']} (displacements scaled {SCALE:g}x); "
        f"{seconds:.0f} s\n"
    )
    print("| damage | flagged (recall) | right diagnosis | right where one is named |")
    print("|---|--:|--:|--:|")
    for d in DAMAGES:
        t, f, nm, ok = r["total"][d], r["flagged"][d], r["named"][d], r["right"][d]
        where = f"{ok}/{nm}" if nm else "-"
        print(f"| {d} | {f}/{t} ({f / t:.0%}) | {ok}/{t} | {where} |")
    fp, others = r["damaged_cohort_false_positives"]
    cf, ct = r["clean_flagged"]
    p, np_ = r["duplicate_partners_flagged"]
    print(
        f"\nFalse positives: damaged cohorts {fp} of {others} undamaged subjects flagged "
        f"({fp / others:.1%}; their flags: {r.get('damaged_cohort_false_positive_flags')}); "
        f"clean cohorts {cf} of {ct} ({cf / ct:.1%}), flags by first "
        f"word: {r['clean_flag_reasons']}. The subject a duplicate copies: {p}/{np_} flagged "
        "with it (expected: the pair is the finding)."
    )
    fits = r["better_fit"]
    words = [
        f"{k}: {len(v)} checked, {min(v):.2f}-{max(v):.2f}" for k, v in sorted(fits.items()) if v
    ]
    print(f"better_fit of the flagged subjects checked (min-max): {'; '.join(words)}")


def main() -> dict:
    out = {}
    with tempfile.TemporaryDirectory(prefix="bench-subject-qc-") as tmp:
        for name, s in SETTINGS.items():
            t0 = time.perf_counter()
            r = _setting(s["dim"], s["n"], s["size"], s["seeds"], s["groups"], Path(tmp))
            seconds = time.perf_counter() - t0
            r["seconds"] = seconds
            r["clean_z"] = _spread(r["clean_z"])
            _print(name, r, seconds)
            out[name] = r
    print("\n| robust z on clean 2D cohorts | 1% | median | 99% | min | max | SD | beyond |")
    print("|---|--:|--:|--:|--:|--:|--:|--:|")
    for k, z in out["2D"]["clean_z"].items():
        print(
            f"| {k} | {z['q01']:.2f} | {z['median']:.2f} | {z['q99']:.2f} | {z['min']:.2f} | "
            f"{z['max']:.2f} | {z['sd']:.2f} | {z['beyond_threshold']:.2%} "
            f"({z['threshold']:+g}) |"
        )
    return out


if __name__ == "__main__":
    main()
