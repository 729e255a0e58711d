"""The head's energy of the MCMC's starting sample as an OOD signal beside E_c (issue 52, Table III's blind spots).

On LIBERO the default monitor (`context_phase_energy`, E_c against vanilla at each chunk index) knows the camera but
not a dimmed light or mild sensor noise (0.65-0.68 on D). A look at D's records (2026-12-02, research/docs/
libero_runs.md, "The starting sample's energy") found a second energy that moves there: E_head(a^(0)) = E(a^(0), C) -
E_c(C), the head's energy of the refinement's Gaussian start, falls under every shift. `context_start_energy` reads
both, each against its vanilla value at the same chunk index, the start term with its sign turned:

    s_t = (z_c,t - z_s,t) / 2,   z_c,t = (E_c,t - mu_c[t]) / sigma_c[t],   z_s,t = (E_head,t(a^(0)) - mu_s[t]) / sigma_s[t]

each term aggregated over the rollout before the two are averaged (as `joint_phase_energy` does). No features.

The score is not registered on import: a registered score enters every report recomputed in the same process, and
the committed reports list the registry's scores line for line. `registered()` adds it for a block and takes it out
after. `report` writes the ten-task Table III (`libero_ten_task_report.py`) with this score first:

    python research/benchmarks/start_energy.py --results=research/results/libero_object10_more \\
        --run=ebvla_joint_fast_cpu_more \\
        --output_dir=research/results/libero_object10_more/reports/ebvla_joint_fast_cpu_more/start_energy
"""

import argparse
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import research_scores  # noqa: F401  (the research scores the ten-task report puts beside)

from lerobot_policy_ebvla.runtime.scores import (
    SCORES,
    ChunkInputs,
    ChunkScore,
    VanillaRollouts,
    check_statistics,
    fit_phase,
    register_score,
    statistics_pair,
)
from lerobot_policy_ebvla.runtime.statistics import PhaseStatistics

SCORE = "context_start_energy"
# Beside it in the report: the default monitor, the feature k-NN baseline, the paper's energy.
BESIDE = ("context_phase_energy", "context_knn", "final_energy")


@dataclass(frozen=True)
class ContextStartEnergy(ChunkScore):
    """E_c against its vanilla value at each chunk index, and the head's energy of the starting sample below its
    vanilla value there, averaged: s_t = (z_c,t - z_s,t) / 2 (module docstring)."""

    context: PhaseStatistics
    start: PhaseStatistics

    name = SCORE
    reads = ("chunk_index", "context_energy", "initial_energy")
    n_components = 2
    json_fields = (
        "context_energy_phase_mean",
        "context_energy_phase_std",
        "start_head_energy_phase_mean",
        "start_head_energy_phase_std",
    )

    def __post_init__(self):
        check_statistics(self.name, "context", self.context, PhaseStatistics)
        check_statistics(self.name, "start", self.start, PhaseStatistics)

    @classmethod
    def fit(cls, vanilla: VanillaRollouts) -> "ContextStartEnergy":
        return cls(
            fit_phase(vanilla, "context_energy", cls.name), fit_phase(vanilla, "start_head_energy", cls.name)
        )

    def components(self, chunks: ChunkInputs) -> np.ndarray:
        index = chunks.get("chunk_index", self.name)
        context = self.context.z(chunks.get("context_energy", self.name), index)
        # The start term's sign turned: a shift lowers the head's energy of the Gaussian start.
        start = -self.start.z(chunks.get("start_head_energy", self.name), index)
        return np.stack([context, start], axis=1)

    def combine(self, aggregates: np.ndarray) -> np.ndarray:
        return aggregates.mean(axis=1)

    def to_json(self) -> dict[str, Any]:
        values = (self.context.mean, self.context.std, self.start.mean, self.start.std)
        return dict(zip(self.json_fields, values, strict=True))

    @classmethod
    def from_json(cls, fields: dict[str, Any]) -> "ContextStartEnergy":
        names = cls.json_fields
        return cls(
            PhaseStatistics(*statistics_pair(fields, *names[:2], cls.name, PhaseStatistics)),
            PhaseStatistics(*statistics_pair(fields, *names[2:], cls.name, PhaseStatistics)),
        )


@contextmanager
def registered() -> Iterator[None]:
    """`ContextStartEnergy` in the package's `SCORES` for the block only (module docstring: why not on import)."""
    register_score(ContextStartEnergy)
    try:
        yield
    finally:
        del SCORES[SCORE]


def report(results: Path, run: str, output_dir: Path) -> None:
    """The ten-task Table III of `run` at the conformal T, `context_start_energy` first, `BESIDE` after it."""
    import libero_ten_task_report

    with registered():
        libero_ten_task_report.main(
            [
                f"--results={results}",
                f"--run={run}",
                f"--output_dir={output_dir}",
                "--threshold_rule=conformal",
                "--scores",
                SCORE,
                *BESIDE,
            ]
        )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--results", type=Path, required=True, help="a work folder or saved results of the run"
    )
    parser.add_argument("--run", required=True)
    parser.add_argument("--output_dir", type=Path, required=True)
    args = parser.parse_args(argv)
    report(args.results, args.run, args.output_dir)


if __name__ == "__main__":
    main()
