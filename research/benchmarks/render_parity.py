"""Do two machines render the same LIBERO scene the same, as the policy's energy sees it? (issue 52, item 4)

An evaluation split between machines (the vanilla rollouts on the CPU, the shifted ones on a lent GPU) compares
rollouts rendered by two OpenGL implementations: Mesa's software EGL here, NVIDIA's EGL there. If the policy's
energy told the renderers apart, a shift's AUROC would partly measure the machine. The control: the same vanilla
jobs (same initial states, same seeds) on both machines, paired episode by episode.

- At chunk 0 both start from the same simulator state (LIBERO's fixed initial state), so any difference in E_c
  (`context_energy`) is the renderer's (and the policy's float arithmetic); `goal_distance` at chunk 0 checks
  that the states are the same.
- Over the first 3 chunks (the monitor's window) the trajectories may already part; the AUROC of one machine's
  rollouts against the other's, on the mean E_c of those chunks, is what Table III would see from the renderer
  alone (0.5: the energy cannot tell them apart).

    python research/benchmarks/render_parity.py --here=<work>/eval/<run>/vanilla_calib \\
        --there=<gpu work>/eval/<run>/vanilla_calib
"""

import argparse
import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from lerobot_policy_ebvla.monitoring.metrics import auroc
from lerobot_policy_ebvla.monitoring.records import (
    EnergyRecord,
    group_by_episode,
    read_energy_records,
    records_file_in,
)


@dataclass
class Parity:
    """The renderer's footprint on the energy, over `pairs` episodes run on both machines."""

    pairs: int
    max_goal_distance_difference_at_reset: float
    context_energy_at_reset_mean_abs_difference: float
    context_energy_at_reset_spread: float
    mean_context_energy_first_chunks_auroc: float

    def summary(self) -> str:
        return (
            f"{self.pairs} paired episodes: E_c at reset differs by {self.context_energy_at_reset_mean_abs_difference:.4f}"
            f" on average (its spread over episodes: {self.context_energy_at_reset_spread:.4f}); the mean E_c of the"
            f" first 3 chunks tells the machines apart at AUROC {self.mean_context_energy_first_chunks_auroc:.3f};"
            f" goal distances at reset differ by at most {self.max_goal_distance_difference_at_reset:.2e}"
        )


def episodes_of(folder: Path) -> dict[tuple, list[EnergyRecord]]:
    """Each episode's records by chunk (keyed as `group_by_episode` keys them: condition, task and index), over
    the task folders (or the one folder) of `folder`."""
    folders = sorted(p for p in folder.glob("task*") if p.is_dir()) or [folder]
    episodes = {}
    for task_folder in folders:
        if records_file_in(task_folder) is not None:  # a job cut short leaves none
            episodes.update(group_by_episode(read_energy_records(task_folder)))
    return episodes


def render_parity(here: Path, there: Path, chunks: int = 3) -> Parity:
    """Pairs the episodes of two runs of the same jobs and measures how far their energies part.

    Raises:
        ValueError: No episode (task, index) is in both, or an episode lacks `context_energy` (a policy
            without the joint energy: compare `final_energy` by hand).
    """
    a, b = episodes_of(here), episodes_of(there)
    keys = sorted(set(a) & set(b))
    if not keys:
        raise ValueError(f"no episode of {here} is also in {there}: run the same jobs on both machines.")

    def reset_value(records: list[EnergyRecord], field: str) -> float:
        value = getattr(records[0], field)
        if value is None:
            raise ValueError(
                f"episode {records[0].task} {records[0].episode_index} has no `{field}` at chunk 0."
            )
        return float(value)

    def window_mean(records: list[EnergyRecord]) -> float:
        return float(np.mean([r.context_energy for r in records[:chunks]]))

    reset_a = np.array([reset_value(a[k], "context_energy") for k in keys])
    reset_b = np.array([reset_value(b[k], "context_energy") for k in keys])
    goal = [
        abs(a[k][0].goal_distance - b[k][0].goal_distance)
        for k in keys
        if a[k][0].goal_distance is not None and b[k][0].goal_distance is not None
    ]
    return Parity(
        pairs=len(keys),
        max_goal_distance_difference_at_reset=float(max(goal)) if goal else float("nan"),
        context_energy_at_reset_mean_abs_difference=float(np.mean(np.abs(reset_a - reset_b))),
        context_energy_at_reset_spread=float(np.std(reset_a)),
        mean_context_energy_first_chunks_auroc=auroc(
            [window_mean(a[k]) for k in keys], [window_mean(b[k]) for k in keys]
        ),
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--here", type=Path, required=True, help="one machine's eval folder of the jobs")
    parser.add_argument(
        "--there", type=Path, required=True, help="the other machine's folder of the same jobs"
    )
    parser.add_argument("--out", type=Path, default=None, help="a JSON file for the figures")
    args = parser.parse_args(argv)
    parity = render_parity(args.here, args.there)
    print(parity.summary())
    if args.out is not None:
        args.out.write_text(json.dumps(asdict(parity), indent=1))


if __name__ == "__main__":
    main()
