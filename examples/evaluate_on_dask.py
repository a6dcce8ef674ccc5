"""Evaluate registrations on a Dask cluster, with a per-image cache (large cohorts).

Usage::

    python examples/evaluate_on_dask.py [MANIFEST] [--scheduler local|tcp://host:8786]

Without a manifest, the small 2D case of ``evaluate_registrations.py`` is generated. The
evaluation runs twice on the cluster with the same cache folder -- the second run reuses
every per-image result -- and once in this process, to show that the numbers agree.
The ``if __name__ == "__main__"`` guard is needed: a local cluster starts worker processes
that import this file.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from _output import add_out_option, output_folder
from evaluate_registrations import make_demo

import itk_nrreval as nr


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("manifest", nargs="?", help="manifest to evaluate (default: a demo)")
    parser.add_argument("--scheduler", default="local", help="'local' or a scheduler address")
    parser.add_argument("--workers", type=int, default=2)
    add_out_option(parser)
    args = parser.parse_args()
    with output_folder(args.out, prefix="nrreval-dask-") as folder:
        run(args, folder)


def run(args: argparse.Namespace, folder: Path) -> None:
    manifest = args.manifest or make_demo(folder)
    kw = dict(n_samples=20_000, seed=0, progress=False)
    for attempt in ("first run", "rerun"):
        t0 = time.perf_counter()
        execution = nr.Execution(
            scheduler=args.scheduler, workers=args.workers, cache=folder / "cache"
        )
        result = nr.evaluate(manifest, execution=execution, **kw)
        run = result.run
        print(
            f"{attempt}: {time.perf_counter() - t0:.1f} s on {run['workers']} workers, "
            f"{run['cache_reused']} per-image results reused, {run['cache_computed']} computed"
        )
    single = nr.evaluate(manifest, **kw)
    for name, scores in result.scores.items():
        a, b = scores.specificity.value, single.scores[name].specificity.value
        print(f"{name:>10}: specificity {a:.6f} on Dask, {b:.6f} in one process")


if __name__ == "__main__":
    main()
