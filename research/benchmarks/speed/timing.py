"""Timing of `bench_speed.py`'s cells: a first call that probes memory, warm-ups, then interleaved rounds."""

import argparse
import math
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import torch

from .memory import peak_memory_mib, synchronize


@dataclass
class Cell:
    """One thing to time. `fn` runs one call; `setup` (untimed) runs before each call."""

    name: str
    fn: Callable[[], object]
    setup: Callable[[], object] | None = None
    group: str = ""
    meta: dict = field(default_factory=dict)
    times: list[float] = field(default_factory=list)
    peak_mib: float | None = None
    first_call_s: float | None = None
    reference: Callable[[], object] | None = None
    check: dict = field(default_factory=dict)

    def run(self, device: torch.device) -> float:
        if self.setup is not None:
            self.setup()
        synchronize(device)
        start = time.perf_counter()
        self.fn()
        synchronize(device)
        return time.perf_counter() - start

    @property
    def median_ms(self) -> float:
        return 1e3 * statistics.median(self.times) if self.times else math.nan


def measure(cells: list[Cell], device: torch.device, args: argparse.Namespace) -> None:
    """Probes each cell once (first-call time and peak memory), warms it up, then times interleaved rounds.

    Rounds visit every cell in turn so that a load change on a shared machine hits all cells alike. A cell
    stops after `--repeats` calls, or earlier once it has `--min-repeats` calls and `--cell-budget-s` seconds.
    """
    for cell in cells:
        start = time.perf_counter()
        if cell.setup is not None:
            cell.setup()
        cell.peak_mib = peak_memory_mib(cell.fn, device)
        cell.first_call_s = time.perf_counter() - start
        for _ in range(args.warmup - 1):
            cell.run(device)
        print(f"  probed {cell.name}: first call {cell.first_call_s:.2f} s", flush=True)
    for _ in range(args.repeats):
        for cell in cells:
            spent = sum(cell.times)
            if len(cell.times) >= args.min_repeats and spent >= args.cell_budget_s:
                continue
            cell.times.append(cell.run(device))
    for cell in cells:
        print(f"  {cell.name}: median {cell.median_ms:.1f} ms over {len(cell.times)}", flush=True)
        if cell.reference is not None:
            if cell.setup is not None:
                cell.setup()
            cell.check = compare_outputs(cell.reference, cell.fn, device)


def compare_outputs(reference: Callable, variant: Callable, device: torch.device, seed: int = 0) -> dict:
    """Max |difference| of actions and energies between two refinements seeded alike."""

    def seeded(fn):
        torch.manual_seed(seed)  # the refinement draws a^(0) and the Langevin noise from the global RNG
        if device.type == "cuda":
            torch.cuda.manual_seed(seed)
        actions, readout = fn()
        return actions, readout

    (a0, r0), (a1, r1) = seeded(reference), seeded(variant)
    return {
        "max_abs_action_diff": (a0 - a1).abs().max().item(),
        "max_abs_final_energy_diff": (r0.final_energy - r1.final_energy).abs().max().item(),
        "max_abs_initial_energy_diff": (r0.initial_energy - r1.initial_energy).abs().max().item(),
    }
