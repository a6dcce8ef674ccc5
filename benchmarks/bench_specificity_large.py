"""Specificity at large N: N = 1,000, 5,000, 10,000 training images, N - 1 modes, M = 100,000.

Times ``nr.texture_measures`` (specificity and generalization from one pass) on the blocked
paths: L2 by one GEMM per block of samples, L1 by the tiled numba kernel. Models are random
training parameters with a decaying spectrum (variance of mode k ~ 1 / (k + 1)); building them
is not timed. L1 at N = 10,000 is ~1e13 distance terms at M = 100,000 (30+ min on 2 cores), so
it is measured at ``--l1-large-samples`` (default 10,000) samples and reported as measured
there; the cost is exactly linear in M, ``time ~ c M N (N - 1)``.

In the same run, at N = 1,000 and on the same samples, the old per-sample search is timed
against the blocked one (both distances) and their answers compared (they are bit-identical).
Each case runs in its own process, so its peak resident memory (``getrusage``) is its own.

Writes ``benchmarks/out/specificity_large.json`` and ``docs/specificity_large.png``. With the
defaults it takes about 40 min on 2 cores: ``python benchmarks/bench_specificity_large.py``
(``--samples``, ``--sizes``, ``--l1-large-samples`` to shorten it).
"""

from __future__ import annotations

import argparse
import importlib
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
SIZES = (1_000, 5_000, 10_000)
M = 100_000
L1_LARGE = 10_000  # N from which L1 is measured at --l1-large-samples samples
SEED = 1


def build_model(n_images: int, seed: int = 0):
    """A TextureModel of N random training points, N - 1 modes, decaying spectrum."""
    import itk_nrreval as nr

    rng = np.random.default_rng(seed)
    n_modes = n_images - 1
    variances = 1.0 / (1.0 + np.arange(n_modes))
    params = rng.standard_normal((n_images, n_modes))
    params *= np.sqrt(variances)
    params -= params.mean(axis=0)
    return nr.TextureModel(
        training_params=params, mode_variances=variances, mean=np.zeros(1), mask=None, geometry=None
    )


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _summary(spec, gen) -> dict:
    return {
        "specificity": spec.value,
        "specificity_stderr": spec.stderr,
        "generalization": gen.value,
        "nearest_counts_max": int(spec.nearest_counts.max()),
    }


def case(n_images: int, distance: str, n_samples: int, path: str) -> dict:
    """One timed texture_measures call in this process; path "blocked", "old" or "both"."""
    import itk_nrreval as nr

    spec_mod = importlib.import_module(
        "itk_nrreval.measures.specificity"
    )  # the module, not the function
    model = build_model(n_images)
    rss_model = _peak_mb()
    forced = {"blocked": 0, "old": 1 << 60}
    out = {"n_images": n_images, "distance": distance, "n_samples": n_samples}
    results = {}
    for p in ("old", "blocked") if path == "both" else (path,):
        spec_mod._BLOCKED_MIN_IMAGES[distance] = forced[p]
        nr.texture_measures(model, n_samples=64, distance=distance, seed=SEED, backend="cpu")
        t = time.perf_counter()
        s, g = nr.texture_measures(
            model, n_samples=n_samples, distance=distance, seed=SEED, backend="cpu"
        )
        seconds = time.perf_counter() - t
        results[p] = (s, g)
        out[f"seconds_{p}"] = seconds
        out[f"ns_per_term_{p}"] = 1e9 * seconds / (n_samples * n_images * (n_images - 1))
        out.update({f"{k}_{p}": v for k, v in _summary(s, g).items()})
    if path == "both":
        (sa, ga), (sb, gb) = results["old"], results["blocked"]
        out["identical"] = bool(
            sa.value == sb.value
            and sa.stderr == sb.stderr
            and np.array_equal(sa.nearest_counts, sb.nearest_counts)
            and np.array_equal(ga.nearest_distances, gb.nearest_distances)
        )
        out["speedup"] = out["seconds_old"] / out["seconds_blocked"]
    out["peak_rss_mb"] = _peak_mb()
    out["model_rss_mb"] = rss_model
    out["training_matrix_mb"] = n_images * (n_images - 1) * 8 / 2**20
    return out


def eigh_case(n_images: int) -> dict:
    """Time of the N x N eigendecomposition that builds a model from its Gram matrix."""
    model = build_model(n_images)
    gram = model.training_params @ model.training_params.T
    t = time.perf_counter()
    np.linalg.eigh(gram)
    return {"n_images": n_images, "eigh_seconds": time.perf_counter() - t}


def _in_subprocess(*args) -> dict:
    cmd = [sys.executable, __file__, "--case", *map(str, args)]
    done = subprocess.run(cmd, check=True, capture_output=True, text=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def plot(numbers: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.6))
    m = numbers["n_samples"]
    grid = np.geomspace(min(numbers["sizes"]) * 0.8, max(numbers["sizes"]) * 1.25, 50)
    for distance, colour in (("l2", "C0"), ("l1", "C1")):
        rows = [r for r in numbers["cases"] if r["distance"] == distance and "seconds_blocked" in r]
        full = [r for r in rows if r["n_samples"] == m]
        part = [r for r in rows if r["n_samples"] != m]
        label = {"l2": "L2 (GEMM)", "l1": "L1 (blocked)"}[distance]
        ax.loglog(
            [r["n_images"] for r in full],
            [r["seconds_blocked"] for r in full],
            "o",
            color=colour,
            label=f"{label}, measured at M = {m:,}",
        )
        if part:
            ax.loglog(
                [r["n_images"] for r in part],
                [r["seconds_blocked"] * m / r["n_samples"] for r in part],
                "s",
                mfc="none",
                color=colour,
                label=f"{label}, measured at M = {part[0]['n_samples']:,}, times M ratio",
            )
        c = numbers["cost_per_term_ns"][distance] * 1e-9
        ax.loglog(grid, c * m * grid * (grid - 1), "-", color=colour, lw=0.8, alpha=0.7)
        ax.text(
            grid[-1], c * m * grid[-1] ** 2, f" c = {c * 1e12:.0f} ps", color=colour, va="center"
        )
    old = [r for r in numbers["cases"] if "seconds_old" in r]
    if old:
        ax.loglog(
            [r["n_images"] for r in old],
            [r["seconds_old"] * m / r["n_samples"] for r in old],
            "x",
            color="k",
            label="old per-sample path (L1, L2)",
        )
    ax.set_xlabel("N training images (N - 1 modes)")
    ax.set_ylabel(f"texture_measures time, s (M = {m:,})")
    ax.set_title("Specificity at large N: time = c M N (N - 1)  (2 cores)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    ax.set_xlim(grid[0], grid[-1] * 2.2)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=M, help="M for the timed runs")
    parser.add_argument("--sizes", type=int, nargs="+", default=list(SIZES))
    parser.add_argument(
        "--l1-large-samples",
        type=int,
        default=L1_LARGE,
        help=f"M for L1 at N >= {L1_LARGE:,} (cost is linear in M)",
    )
    parser.add_argument("--no-eigh", action="store_true", help="skip timing the Gram eigh")
    parser.add_argument("--case", nargs="+", help=argparse.SUPPRESS)
    args = parser.parse_args([] if argv is None else argv)
    if args.case:
        if args.case[0] == "eigh":
            print(json.dumps(eigh_case(int(args.case[1]))))
        else:
            n, distance, n_samples, path = args.case
            print(json.dumps(case(int(n), distance, int(n_samples), path)))
        return {}

    m = args.samples
    cases = []
    smallest = min(args.sizes)
    for n in sorted(args.sizes):
        for distance in ("l2", "l1"):
            n_samples = args.l1_large_samples if distance == "l1" and n >= L1_LARGE else m
            path = "both" if n == smallest else "blocked"
            r = _in_subprocess(n, distance, n_samples, path)
            cases.append(r)
            extra = f", old {r['seconds_old']:.1f} s" if path == "both" else ""
            print(
                f"N = {n:,} {distance} M = {n_samples:,}: {r['seconds_blocked']:.1f} s "
                f"({r['ns_per_term_blocked'] * 1e3:.0f} ps/term){extra}, "
                f"peak {r['peak_rss_mb']:.0f} MB",
                flush=True,
            )
    eigh = [] if args.no_eigh else [_in_subprocess("eigh", n) for n in sorted(args.sizes)]
    cost = {}
    for distance in ("l1", "l2"):
        rows = [r for r in cases if r["distance"] == distance]
        largest = max(rows, key=lambda r: r["n_images"])  # least overhead per term
        cost[distance] = largest["ns_per_term_blocked"]
    numbers = {
        "n_samples": m,
        "sizes": sorted(args.sizes),
        "seed": SEED,
        "cost_model": "seconds = c * M * N * (N - 1); c from the largest N, per distance",
        "cost_per_term_ns": cost,
        "cases": cases,
        "eigh": eigh,
    }
    print(f"\nM = {m:,}, N - 1 modes, 2 cores; c = seconds / (M N (N - 1))")
    print("| N | distance | M measured | seconds | c (ps/term) | peak RSS MB | old s | speed-up |")
    print("|---|---|---|---|---|---|---|---|")
    for r in cases:
        old = (
            f"{r['seconds_old']:.1f} | {r['speedup']:.1f}x (identical: {r['identical']})"
            if "seconds_old" in r
            else " | "
        )
        print(
            f"| {r['n_images']:,} | {r['distance']} | {r['n_samples']:,} | "
            f"{r['seconds_blocked']:.1f} | {r['ns_per_term_blocked'] * 1e3:.0f} | "
            f"{r['peak_rss_mb']:.0f} | {old} |"
        )
    for e in eigh:
        print(f"eigh of the {e['n_images']:,}^2 Gram: {e['eigh_seconds']:.1f} s")
    out = ROOT / "benchmarks" / "out"
    out.mkdir(exist_ok=True)
    (out / "specificity_large.json").write_text(json.dumps(numbers, indent=2) + "\n")
    docs = ROOT / "docs"
    docs.mkdir(exist_ok=True)
    plot(numbers, docs / "specificity_large.png")
    return numbers


if __name__ == "__main__":
    main(sys.argv[1:])
