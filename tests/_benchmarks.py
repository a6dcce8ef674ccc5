"""Loading a benchmark script (benchmarks/*.py, not a package) as a module, for the tests
of the functions it defines."""

import importlib.util
from pathlib import Path
from types import ModuleType


def benchmark_module(name: str) -> ModuleType:
    """``benchmarks/<name>.py``, imported as a module named `name`."""
    path = Path(__file__).resolve().parents[1] / "benchmarks" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
