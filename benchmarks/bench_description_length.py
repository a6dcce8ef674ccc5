"""A description length that prices shape and texture in one currency: issue 41's idea (a).

Declared on 2026-11-28 (seventh session of issue 41), in full, BEFORE it was measured on any
case; nothing below was fitted. If it is changed after a measurement, the change is set on
``TUNING`` only and said here, with what it was checked on.

**The measure.** A registration describes each subject's image as the group's template
warped by the subject's deformation, plus a texture residual. Its description length is
the bits that message takes, per subject, with both parts coded at precisions that cost
the same in the image (Twining, Cootes et al.'s MDL for groupwise registration, in the
simplest form that needs no model of any engine). On the registration's reference grid,
inside the case's mask (``n`` voxels of the grid's ``n_grid``):

- **texture**: each registered image's residual from the group's mean image, ``r_i = m (J_i
  - mean J)``; its power spectrum averaged over the subjects, ``P_k = mean_i |FFT(r_i)_k|^2 /
  n``, is a stationary Gaussian model. Coding ``N`` subjects to the noise level ``D_I =
  sigma^2`` costs ``N (n / n_grid) sum_k max(0, log2(P_k / D_I) / 2)`` bits (the
  rate-distortion function of a Gaussian source: reverse water-filling). Texture below the
  noise level costs nothing, so a registration that fits noise gains nothing by it. The
  template (the mean image minus its mean in the mask) is coded once, the same way.
- **shape**: each subject's displacement field (mm), minus its least-squares affine part
  inside the mask (an affine's 12 numbers are no cost worth pricing), residual from the
  subjects' mean non-linear field, masked; per component, the same Gaussian code at the
  distortion ``D_x = sigma^2 / g^2`` (mm^2), with ``g^2`` the images' mean squared
  directional derivative (intensity per mm, noise's share removed): a displacement error
  of ``sqrt(D_x)`` costs as much in the image as the noise. The mean field is coded once.
- ``sigma`` (noise) and ``g`` come from the scored images in their own space, not from any
  registration: per image, over its voxels above its Otsu threshold, ``sigma`` by the median
  absolute value of the ``[1, -2, 1]`` second difference taken along every axis (Immerkaer's
  estimator, made robust to edges), and ``g^2`` as the mean squared central difference per
  axis, minus noise's ``sigma^2 / (2 h^2)``; the medians over the images.

**Since it entered the package** (``itk_nrreval.measures.description_length``), every case
is measured by ``evaluate(description_length=True)`` itself (:func:`measure`): in the
common frame, over the evaluated region (the mask where every image covers it) rather than
over the whole mask on each registration's own grid, with Otsu's threshold on ITK's 128
bins in numpy rather than SimpleITK's. The tables are of that measurement; the first
(mask, own grids) is in ``docs/verdict.md``.

Lower is better. Its confidence is the jackknife over subjects (each subject left out in
turn, the whole measure recomputed on the rest, bits per subject): a pair's difference is
**separable** when it exceeds ``MIN_Z`` jackknife standard errors (below).

**The rule declared with it.** The description length prefers ``a`` over ``b`` when ``a``'s
is separably lower. Judged like the verdict (``bench_verdict``: pairs whose true errors differ
by more than 10%): right, wrong or open, per split, on the images the registrations were
made on and on the second scan. Beside it, the verdict without labels with the description
length's preference added as evidence: it decides a pair the verdict leaves open, and a
pair the two decide opposite ways becomes open.

**After every split up to FRESH9 was measured** (``docs/verdict.md``): every pair it decided
wrong outside TUNING was between registrations of different families, in both directions.
So it counts only between two registrations of one family (the same ``method`` and
``engine`` in the manifest's ``parameters``; the saved sweeps, whose manifests predate
that record, are each one family), a restriction chosen after seeing those splits and
checked on FRESH10, declared before its cases ran. The verdict columns are now today's
``itk_nrreval.measures.verdict``, which reads the description length so
(``decided_with``), and the same verdict as if every registration were of one family.

Cases: every saved case of ``bench_verdict`` whose images form no groups (the multi-modal
case is left out; so are cases whose manifest is gone). The first measurement took only
cases whose registrations shared the mask's grid with no frame transform, and the sweeps
(no mask) over each registration's whole reference grid, the latter added after its first
run on ``TUNING`` (53 of 65 pairs right, none wrong), before any other split was measured;
``evaluate`` now measures every case in its common frame.

A preference needs :data:`~itk_nrreval.measures.description_length.MIN_Z` jackknife
standard errors: declared as 1.96 (a 95% interval), set to 3.2 on ``TUNING`` alone, before
any other split was measured (at 1.96 it decided 199 of TUNING's 243 judged pairs right and
4 wrong, at z = 2.22-2.89: a 64 mm B-spline grid against an 8 mm one on the MNI 2D sweep,
twice; 16 against 4 mm demons smoothing on the 3D MNI sweep; 1 mm demons against a 10 mm
B-spline grid on families_mni2d's second scan); 3.2 is the steepest wrong plus 10%.

``python benchmarks/bench_description_length.py [--compute] [--split tuning,...]``:
``--compute`` measures the cases that lack it first (``description_length.json`` in the
case's folder; seconds a 2D case, minutes a 3D one), ``--split`` only those splits' cases;
the tables, over every case measured so far, go to
``benchmarks/out/verdict/description_length.md``.
"""

from __future__ import annotations

import collections
import importlib.util
import itertools
import json
import sys
from pathlib import Path

import numpy as np
from scipy.stats import spearmanr

from itk_nrreval.measures.description_length import MIN_Z, DescriptionLength, z_of_difference

HERE = Path(__file__).resolve().parent
RESULT_JSON = "description_length.json"


def _bench(name: str):
    spec = importlib.util.spec_from_file_location(name, HERE / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


# ------------------------------------------------------------------------ the saved cases


def measure(manifest) -> dict:
    """Every registration's description length, with its jackknife, for one manifest: as
    ``evaluate(description_length=True)`` computes it (over the evaluated region: the mask
    where every image covers it; M = 1,000, no confidence: neither touches it)."""
    import warnings

    import itk_nrreval as nr

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = nr.evaluate(
            manifest,
            n_samples=1000,
            confidence=False,
            inverse_consistency=False,
            description_length=True,
            progress=False,
        )
    first = next(iter(result.scores.values())).description_length
    out = {
        "sigma": first.noise_sd,
        "g2": first.noise_sd**2 / first.displacement_precision_mm**2,
        "registrations": {},
    }
    for name, scores in result.scores.items():
        dl = scores.description_length
        out["registrations"][name] = {
            "bits": dl.bits,
            "texture": dl.texture,
            "shape": dl.shape,
            "jackknife": list(dl.jackknife),
        }
    return out


def usable(manifest) -> str | None:
    """Why a saved case's manifest cannot be measured, or None."""
    if manifest.groups is not None:
        return "its images form groups (a mixture)"
    return None


# ------------------------------------------------------------------------ judged


def description_lengths(record: dict) -> dict[str, DescriptionLength]:
    """A saved case's description lengths (``description_length.json``), by registration."""
    sigma, precision = record["sigma"], (record["sigma"] ** 2 / record["g2"]) ** 0.5
    return {
        name: DescriptionLength(
            r["bits"], r["texture"], r["shape"], tuple(r["jackknife"]), sigma, precision
        )
        for name, r in record["registrations"].items()
    }


def preference(lengths: dict[str, DescriptionLength], a: str, b: str) -> str | None:
    """The registration the description length prefers of `a`, `b` by at least
    :data:`~itk_nrreval.measures.description_length.MIN_Z` jackknife standard errors, or
    None."""
    z = z_of_difference(lengths[a], lengths[b])  # > 0: a's is the shorter
    if not abs(z) >= MIN_Z:
        return None
    return a if z > 0 else b


def decided_with(bv, case: str, record: dict, family: dict) -> set[tuple[str, str]]:
    """The pairs ``(better, worse)`` today's verdict without labels decides for a saved case
    when its scores carry the description lengths of `record` and the families `family`
    (``itk_nrreval.measures.verdict``, which reads them)."""
    import dataclasses

    from itk_nrreval.evaluation import _judged

    evaluation = bv._load(case)
    lengths = description_lengths(record)
    scores = {
        name: dataclasses.replace(score, description_length=lengths[name], family=family.get(name))
        for name, score in evaluation.scores.items()
    }
    v = _judged(scores, evaluation.comparisons, has_labels=False)  # in the images' dimension
    return {(d.better, d.worse) for d in v.decisions}


def judge(bv, case: str, record: dict, verdict_rows: list[dict]) -> list[dict]:
    """Each judged pair (true errors 10% apart) of `case`: the description length's outcome
    alone (``mdl``; ``family``: only between two registrations of one known family), the
    verdict's without labels (``verdict``), and today's verdict reading it (``with_family``;
    ``with``: as if every registration were of one family)."""
    lengths = description_lengths(record)
    errors = json.loads((bv.OUT / case / "truth.json").read_text())["true_error_mm"]
    verdict = {(r["a"], r["b"]): r["outcome"] for r in verdict_rows if r["case"] == case}
    family = bv.families_of(case)
    with_family = decided_with(bv, case, record, family)
    with_all = decided_with(bv, case, record, dict.fromkeys(family, ("one",)))

    def outcome(decided, a, b):
        return "right" if (a, b) in decided else "wrong" if (b, a) in decided else "open"

    rows = []
    for a, b in itertools.combinations(errors, 2):
        if errors[b] < errors[a]:
            a, b = b, a
        if errors[b] - errors[a] <= bv.MARGIN * errors[a]:
            continue
        said = preference(lengths, a, b)
        mdl = "open" if said is None else ("right" if said == a else "wrong")
        same = family.get(a) is not None and family.get(a) == family.get(b)
        rows.append(
            {
                "case": case,
                "a": a,
                "b": b,
                "mdl": mdl,
                "family": mdl if same else "open",
                "verdict": verdict.get((a, b), "open"),
                "with": outcome(with_all, a, b),
                "with_family": outcome(with_family, a, b),
            }
        )
    return rows


def _cell(rows: list[dict], key: str) -> str:
    c = collections.Counter(r[key] for r in rows)
    return f"{c['right']} / {c['wrong']} / {c['open']}"


def main(argv: list[str] | None = None) -> dict:
    """The tables (``rows``) over every saved case; `argv` ``["--compute"]`` measures the
    cases lacking it first (``--split a,b``: only those splits' cases)."""
    argv = [] if argv is None else argv
    bv = _bench("bench_verdict")
    from itk_nrreval.io.manifest import load_manifest

    splits = argv[argv.index("--split") + 1].split(",") if "--split" in argv else bv.SPLITS
    second_of = {v: k for k, v in bv.SECOND_SCAN.items()}
    results, skipped = {}, {}
    for case in [*bv.DECLARED, *bv.SECOND_SCAN.values()]:
        path = bv.OUT / case / RESULT_JSON
        if not (bv.OUT / case / "truth.json").exists():
            continue
        if path.exists():  # every saved case is in the tables, whichever splits are computed
            results[case] = json.loads(path.read_text())
            continue
        if "--compute" not in argv or bv.split_of(second_of.get(case, case)) not in splits:
            continue
        try:
            manifest = bv._quiet(load_manifest, bv.manifest_of(case))
        except FileNotFoundError as exc:
            skipped[case] = str(exc)
            continue
        why = usable(manifest)
        if why:
            skipped[case] = why
            continue
        print(f"[description length] {case}", flush=True)
        record = measure(manifest)
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps(record) + "\n")
        tmp.replace(path)
        results[case] = record
    for case, why in skipped.items():
        print(f"[description length] {case} left out: {why}")
    verdict_rows = []
    for case in results:
        verdict_rows += [dict(r, case=case) for r in bv.judge(case, labels=False)]
    by_split = collections.defaultdict(lambda: {"seen": [], "second": [], "rho": []})
    for case, record in results.items():
        result = record["registrations"]
        base = second_of.get(case, case)
        split = bv.split_of(base)
        rows = judge(bv, case, record, verdict_rows)
        by_split[split]["second" if case in second_of else "seen"] += rows
        truth = json.loads((bv.OUT / case / "truth.json").read_text())["true_error_mm"]
        names = [n for n in truth if n in result]
        deformable = [n for n in names if n != "affine"]
        if case not in second_of and len(deformable) > 2:
            by_split[split]["rho"].append(
                spearmanr([result[n]["bits"] for n in deformable], [truth[n] for n in deformable])[
                    0
                ]
            )
    header = (
        "| split | pairs | description length | verdict without labels | the verdict with it "
        "| within a family | the verdict with that | Spearman, deformable |"
    )
    lines = {"seen": [header], "second": [header]}
    for split in bv.SPLITS:
        if split not in by_split:
            continue
        s = by_split[split]
        rho = np.asarray(s["rho"], float)
        spearman = f"{np.nanmean(rho):+.2f} ({np.nanmin(rho):+.2f})" if rho.size else "-"
        for mode in ("seen", "second"):
            rows = s[mode]
            cells = [_cell(rows, k) for k in ("mdl", "verdict", "with", "family", "with_family")]
            rho_cell = spearman if mode == "seen" else "-"
            lines[mode].append(
                f"| {split} | {len(rows)} | " + " | ".join(cells) + f" | {rho_cell} |"
            )
    rule = "|---|--:|--:|--:|--:|--:|--:|--:|"
    text = (
        "Each cell: right / wrong / open.\n\nOn the images the registrations were made on:\n\n"
        + "\n".join([lines["seen"][0], rule, *lines["seen"][1:]])
        + "\n\nOn the second scan:\n\n"
        + "\n".join([lines["second"][0], rule, *lines["second"][1:]])
        + "\n"
    )
    print(text)
    (bv.OUT / "description_length.md").write_text(text)
    return {"rows": lines["seen"][1:] + lines["second"][1:]}


if __name__ == "__main__":
    main(sys.argv[1:])
