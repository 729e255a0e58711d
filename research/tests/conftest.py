"""Shared helpers of the research tests: the scripts of `research/benchmarks/`, loaded as modules, and the
committed records' folder. The package's tiny policies and batches come from `tests/conftest.py`."""

import importlib.util
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
BENCHMARKS = ROOT / "research" / "benchmarks"
RESULTS = ROOT / "research" / "results"


def load_benchmark(name: str):
    """The module of `research/benchmarks/<name>.py`, loaded with that folder on `sys.path` while it runs, so that
    its imports of sibling scripts resolve as when it runs from there."""
    sys.path.insert(0, str(BENCHMARKS))
    try:
        spec = importlib.util.spec_from_file_location(name, BENCHMARKS / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(BENCHMARKS))
    return module
