"""Shared helpers of the research tests: the scripts of `research/benchmarks/`, loaded as modules, and the
committed records' folder. The package's tiny policies and batches come from `tests/conftest.py`."""

import importlib.util
import json
import os
import sys
from pathlib import Path

import torch

# Two xdist workers on two cores: one torch thread each, and for the programs a test launches (tests/conftest.py).
if os.environ.get("PYTEST_XDIST_WORKER"):
    torch.set_num_threads(1)
    os.environ.setdefault("OMP_NUM_THREADS", "1")

ROOT = Path(__file__).resolve().parents[2]
BENCHMARKS = ROOT / "research" / "benchmarks"
RESULTS = ROOT / "research" / "results"


def load_benchmark(name: str):
    """The module of `research/benchmarks/<name>.py`, loaded with that folder on `sys.path` while it runs, so that
    its imports of sibling scripts resolve as when it runs from there.

    Loaded once, under its bare name in `sys.modules`, as a sibling script's `import <name>` finds it: a module
    that registers scores (`research_scores`) must not define its classes twice."""
    loaded = sys.modules.get(name)
    if loaded is not None and Path(getattr(loaded, "__file__", "")).parent == BENCHMARKS:
        return loaded
    sys.path.insert(0, str(BENCHMARKS))
    try:
        spec = importlib.util.spec_from_file_location(name, BENCHMARKS / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        try:
            spec.loader.exec_module(module)
        except BaseException:
            del sys.modules[name]
            raise
    finally:
        sys.path.remove(str(BENCHMARKS))
    return module


def task_successes(folder: Path) -> list[int | None]:
    """Successes of each LIBERO task's evaluation job under one condition folder (`eval/<run>/<condition>`), tasks
    0-9; None where the job did not finish."""
    counts = []
    for task in range(10):
        info = folder / f"task{task}" / "eval_info.json"
        if not info.exists():
            counts.append(None)
            continue
        overall = json.loads(info.read_text())["overall"]
        counts.append(round(overall["pc_success"] * overall["n_episodes"] / 100))
    return counts
