"""The head's energy of the MCMC's starting sample as an OOD signal beside E_c (issue 52, Table III's blind spots).

On LIBERO the monitor that ships with the light preset (`context_phase_energy`, E_c against vanilla at each chunk
index) knows the camera but not a dimmed light or mild sensor noise (0.65-0.68 on D). A look at D's records
(2026-12-02, research/docs/libero_runs.md, "The starting sample's energy beside E_c") found a second energy that
moves there: E_head(a^(0)) = E(a^(0), C) - E_c(C), the head's energy of the refinement's Gaussian start, falls
under every shift. The package's `context_start_energy` (`runtime.scores.ContextStartEnergy`) reads both, each
against its vanilla value at the same chunk index, the start term with its sign turned:

    s_t = (z_c,t - z_s,t) / 2,   z_c,t = (E_c,t - mu_c[t]) / sigma_c[t],   z_s,t = (E_head,t(a^(0)) - mu_s[t]) / sigma_s[t]

It was chosen on D's records and tested on C's by a rule fixed before C's were read by it (that section); the
score lived here until it passed. `report` writes the ten-task Table III (`libero_ten_task_report.py`) with it first
and the default monitor, the feature k-NN and the paper's energy beside it:

    python research/benchmarks/start_energy.py --results=research/results/libero_object10_more \\
        --run=ebvla_joint_fast_cpu_more \\
        --output_dir=research/results/libero_object10_more/reports/ebvla_joint_fast_cpu_more/start_energy
"""

import sys
from pathlib import Path

import libero_ten_task_report

SCORE = "context_start_energy"
# Beside it in the report: the light preset's monitor, the feature k-NN baseline, the paper's energy.
BESIDE = ("context_phase_energy", "context_knn", "final_energy")


def report_args(argv: list[str]) -> list[str]:
    """`libero_ten_task_report.py`'s arguments (`--results`, `--run`, `--output_dir`) for this report: the conformal
    T, `context_start_energy` first and `BESIDE` after it."""
    return [*argv, "--threshold_rule=conformal", "--scores", SCORE, *BESIDE]


def report(results: Path, run: str, output_dir: Path) -> None:
    """The ten-task Table III of `run` (`report_args`)."""
    libero_ten_task_report.main(
        report_args([f"--results={results}", f"--run={run}", f"--output_dir={output_dir}"])
    )


if __name__ == "__main__":
    libero_ten_task_report.main(report_args(sys.argv[1:]))
