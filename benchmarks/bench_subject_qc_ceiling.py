"""How much recall can a per-subject score reach? Two checks of issue 42's recall goal.

Issue 42 asks subject QC, on genuine registrations, to flag at least 80% of the failed
subjects (true error above 1.5x the registration's median) at no more than 5% false alarms,
and its score to reach Spearman 0.8 against the true error. This benchmark asks whether a
better combination of today's terms, or any score of that Spearman, could meet the first:

1. **What a Spearman implies.** Where a score and the true error have rank correlation
   ``rho`` (a Gaussian copula: Pearson ``r = 2 sin(pi rho / 6)``) and a fraction ``f`` of
   the subjects failed (the top ``f`` of the true error), flagging the top of the score so
   that a fraction ``a`` of the others are flagged finds :func:`implied_recall` of the
   failed ones. Exact, by the bivariate normal CDF (tested against a simulation).
2. **The concern's weights fitted.** A logistic regression of *failed* on the concern's
   signed terms (:data:`itk_nrreval.measures.subject_qc.CONCERN_TERMS`: minus the overlap z,
   the bias-corrected distance z, SDlogJ z and inverse-consistency z above zero), fitted on
   the splits a rule may be set on (``TUNING`` and ``TUNING2`` of ``bench_verdict``, both
   scans), each case's subjects scored by the weights fitted on the other cases (leave one
   case out, its second scan with it). Its recall at a given share of the others flagged
   by it, pooled, against today's concern at the same share. Nothing here is used to set a
   threshold: this only says whether refitting the weights is worth a declared split.

Reads the cases ``bench_verdict.py`` saved (``benchmarks/out/verdict/``; run those first);
writes ``benchmarks/out/subject_qc_ceiling/summary.md``. Run:
``python benchmarks/bench_subject_qc_ceiling.py`` (seconds).
"""

from __future__ import annotations

import importlib.util
import math
import sys
import warnings
from pathlib import Path

import numpy as np
from scipy.optimize import brentq, minimize
from scipy.stats import multivariate_normal, norm

HERE = Path(__file__).resolve().parent
OUT = HERE / "out" / "subject_qc_ceiling"
#: The splits a rule may be set on (``bench_verdict``'s names).
SETS = ("TUNING", "TUNING2")
#: Every split declared after them (that ``bench_verdict`` has), for the worst-k counts.
LATER = ("FRESH", *(f"FRESH{k}" for k in range(2, 100)))
#: Shares of the others flagged by the score alone at which the recall is read.
FALSE_ALARMS = (0.03, 0.05)
#: The ridge on the logistic weights (not on the intercept), in units of the log likelihood.
RIDGE = 1.0


def implied_recall(spearman: float, *, failed_fraction: float, false_alarms: float) -> float:
    """The share of the failed subjects a score flags, at a share `false_alarms` of the
    others flagged, where score and true error have rank correlation `spearman` under a
    Gaussian copula and the top `failed_fraction` of the true error failed.

    Parameters
    ----------
    spearman : float
        Spearman's rho between score and true error, in (-1, 1).
    failed_fraction, false_alarms : float
        In (0, 1).

    Returns
    -------
    float
        ``P(S > t | E > e)`` with ``P(E > e) = failed_fraction`` and ``t`` such that
        ``P(S > t | E <= e) = false_alarms``; (S, E) standard bivariate normal with Pearson
        ``r = 2 sin(pi spearman / 6)``.
    """
    if not (-1.0 < spearman < 1.0 and 0.0 < failed_fraction < 1.0 and 0.0 < false_alarms < 1.0):
        raise ValueError(
            f"spearman must be in (-1, 1), the fractions in (0, 1); got {spearman}, "
            f"{failed_fraction}, {false_alarms}"
        )
    r = 2.0 * math.sin(math.pi * spearman / 6.0)
    e = norm.ppf(1.0 - failed_fraction)
    both = multivariate_normal(mean=[0.0, 0.0], cov=[[1.0, r], [r, 1.0]])

    def below_both(t: float) -> float:  # P(S <= t, E <= e)
        return float(both.cdf([t, e]))

    kept = 1.0 - failed_fraction  # P(E <= e)

    def others_flagged(t: float) -> float:
        return (kept - below_both(t)) / kept - false_alarms

    t = brentq(others_flagged, -12.0, 12.0, xtol=1e-10)
    flagged_failed = 1.0 - norm.cdf(t) - (kept - below_both(t))  # P(S > t, E > e)
    return flagged_failed / failed_fraction


def fit_logistic(x: np.ndarray, failed: np.ndarray, *, ridge: float = RIDGE) -> np.ndarray:
    """Weights (shape (k + 1,): k terms, then the intercept) of a logistic regression of
    `failed` (bool, shape (n,)) on `x` (shape (n, k)), with an L2 penalty `ridge` on the
    term weights."""
    xb = np.c_[x, np.ones(len(x))]
    y = failed.astype(float)

    def loss(w):
        s = xb @ w
        return np.sum(np.logaddexp(0.0, s) - y * s) + ridge * np.sum(w[:-1] ** 2)

    def gradient(w):
        p = 1.0 / (1.0 + np.exp(-(xb @ w)))
        g = xb.T @ (p - y)
        g[:-1] += 2.0 * ridge * w[:-1]
        return g

    return minimize(loss, np.zeros(xb.shape[1]), jac=gradient, method="L-BFGS-B").x


def out_of_fold(x: np.ndarray, failed: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """Each row's linear score under the weights fitted on the rows of the other groups."""
    score = np.empty(len(x))
    for g in np.unique(groups):
        inside = groups == g
        w = fit_logistic(x[~inside], failed[~inside])
        score[inside] = x[inside] @ w[:-1] + w[-1]
    return score


def recall_at(score: np.ndarray, failed: np.ndarray, false_alarms: float) -> float:
    """The share of the failed rows whose score is above the ``1 - false_alarms`` quantile
    of the others' scores."""
    t = np.quantile(score[~failed], 1.0 - false_alarms)
    return float(np.mean(score[failed] > t))


def found_among_worst(
    score: np.ndarray, failed: np.ndarray, registrations: np.ndarray, k: int
) -> tuple[int, int]:
    """How many of the failed rows are among the `k` of highest `score` of their
    registration (`registrations`: a name per row), and how many failed rows there are."""
    found = 0
    for name in np.unique(registrations):
        rows_of = np.flatnonzero(registrations == name)
        worst = rows_of[np.argsort(-score[rows_of], kind="stable")[:k]]
        found += int(failed[worst].sum())
    return found, int(failed.sum())


def _subject_qc_bench():
    path = HERE / "bench_subject_qc_genuine.py"
    spec = importlib.util.spec_from_file_location("bench_subject_qc_genuine", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _terms(q: dict, bq, *, labels: bool) -> list[float]:
    """A saved subject's concern terms, signed and clipped as the concern takes them; 0 (the
    cohort's median) where not measured."""
    from itk_nrreval.measures.subject_qc import CONCERN_TERMS

    out = []
    for term in CONCERN_TERMS:
        if term.key == "overlap_z" and not labels:
            continue
        v = term.sign * bq._get(q, bq._Z_WHERE[term.key])
        v = max(v, 0.0) if term.worse_only else v
        out.append(0.0 if math.isnan(v) else v)
    return out


def rows(bq, bv, *, labels: bool, splits: tuple[str, ...] = SETS) -> dict[str, np.ndarray]:
    """Every judged subject of the saved cases of `splits` (``bench_verdict``'s names), both
    scans: its terms, the concern, failed, its case and registration, and the concern's
    Spearman per deformable registration."""
    x, concern, failed, groups, spearman, registrations = [], [], [], [], [], []
    for split in splits:
        for base in (c for c in getattr(bv, split) if c.startswith("families_")):
            for name in (base, bv.SECOND_SCAN[base]):
                case = bq.load_case(bv.OUT / name)
                if case is None:
                    continue
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    measured = bq.measure_case(case, labels=labels)
                for reg, m in measured["registrations"].items():
                    saved = case["results"]["registrations"][reg]["subjects"]
                    for r in m["subjects"]:
                        x.append(_terms(saved[r["index"]], bq, labels=labels))
                        concern.append(r["terms"]["concern"])
                        failed.append(r["failed"])
                        groups.append(base)
                        registrations.append(f"{name}/{reg}")
                    if reg != bq.AFFINE:
                        spearman.append(m["spearman"]["concern"])
    return {
        "x": np.array(x),
        "concern": np.nan_to_num(np.array(concern, float), nan=-np.inf),
        "failed": np.array(failed, bool),
        "groups": np.array(groups),
        "spearman": np.array(spearman, float),
        "registrations": np.array(registrations),
    }


def main(argv: list[str] | None = None) -> dict:
    del argv
    bq = _subject_qc_bench()
    bv = bq._verdict_bench()
    lines = [
        "# How much recall can a per-subject score reach? (issue 42)",
        "",
        "Recall a Spearman implies (Gaussian copula), at a share of the others flagged:",
        "",
        "| Spearman | 10% failed, 3% flagged | 10% failed, 5% flagged |",
        "|--:|--:|--:|",
    ]
    implied = {}
    for rho in (0.7, 0.8, 0.85, 0.9, 0.95):
        at = [implied_recall(rho, failed_fraction=0.1, false_alarms=a) for a in FALSE_ALARMS]
        implied[rho] = at
        lines.append(f"| {rho:.2f} | {at[0]:.0%} | {at[1]:.0%} |")
    lines += [
        "",
        f"The concern's weights fitted (logistic, leave one case out) on {' + '.join(SETS)}:",
        "",
        "| mode | subjects (failed) | concern Spearman, mean | share flagged | implied | "
        "today's concern | weights fitted |",
        "|---|--:|--:|--:|--:|--:|--:|",
    ]
    measured = {}
    tuning = {}  # the tuning splits' rows per mode, counted again below for the worst k
    for labels in (True, False):
        d = tuning[labels] = rows(bq, bv, labels=labels)
        if not len(d["failed"]):
            print("[ceiling] no saved case of the tuning splits: run bench_verdict.py first")
            return {}
        fitted = out_of_fold(d["x"], d["failed"], d["groups"])
        rho = float(np.nanmean(d["spearman"]))
        f = float(d["failed"].mean())
        mode = "with labels" if labels else "without labels"
        measured[mode] = {}
        for a in FALSE_ALARMS:
            now, refit = recall_at(d["concern"], d["failed"], a), recall_at(fitted, d["failed"], a)
            implied_here = implied_recall(rho, failed_fraction=f, false_alarms=a)
            measured[mode][a] = {"concern": now, "fitted": refit, "implied": implied_here}
            lines.append(
                f"| {mode} | {len(d['failed'])} ({d['failed'].sum()}) | {rho:.2f} | {a:.0%} | "
                f"{implied_here:.0%} | {now:.0%} | {refit:.0%} |"
            )
        w = fit_logistic(d["x"], d["failed"])
        measured[mode]["weights, all cases"] = [round(float(v), 3) for v in w]
    lines += [
        "",
        "The failed subjects among the k of highest concern of their registration (both "
        "scans; nothing is set here, so every saved split is reported):",
        "",
        "| splits | mode | k = 1 | k = 3 | k = 5 |",
        "|---|---|--:|--:|--:|",
    ]
    worst_k: dict[str, dict] = {}
    for group in (SETS, ("HELD_OUT",), LATER):
        for labels in (True, False):
            if group == SETS:
                d = tuning[labels]
            else:
                d = rows(bq, bv, labels=labels, splits=tuple(s for s in group if hasattr(bv, s)))
            if not len(d["failed"]):
                continue
            found = [
                found_among_worst(d["concern"], d["failed"], d["registrations"], k)
                for k in (1, 3, 5)
            ]
            mode = "with labels" if labels else "without labels"
            name = " + ".join(group) if group != LATER else "the later splits saved"
            worst_k.setdefault(name, {})[mode] = found
            lines.append(f"| {name} | {mode} | " + " | ".join(f"{a}/{b}" for a, b in found) + " |")
    lines += ["", "Weights fitted on all of them (terms of CONCERN_TERMS, then intercept):", ""]
    lines += [f"- {mode}: {m['weights, all cases']}" for mode, m in measured.items()]
    text = "\n".join(lines) + "\n"
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "summary.md").write_text(text)
    print(text)
    return {"implied": implied, "measured": measured, "found among the worst k": worst_k}


if __name__ == "__main__":
    main(sys.argv[1:])
