"""Run every ``benchmarks/bench_*.py`` (``make bench``).

Each benchmark module has ``main() -> dict``: it times the toolkit against a plain reference
in the same run, prints a short markdown report, and returns its numbers, which are saved
to ``benchmarks/out/<name>.json``. Pass names to run a subset: ``python run_all.py overlap``.
"""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent


def main(argv: list[str]) -> int:
    out = HERE / "out"
    out.mkdir(exist_ok=True)
    for path in sorted(HERE.glob("bench_*.py")):
        name = path.stem.removeprefix("bench_")
        if argv and name not in argv:
            continue
        spec = importlib.util.spec_from_file_location(path.stem, path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        print(f"\n## {name}\n", flush=True)
        results = module.main()
        (out / f"{name}.json").write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
