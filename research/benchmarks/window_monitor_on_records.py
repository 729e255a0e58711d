"""Replay recorded rollouts through the window test: several rollouts together flag what none does alone.

A joint-energy policy's per-rollout monitor (`context_energy_two_sided` here) scores each rollout on its own; under a mild
shift it can pass every rollout while each one sits a little off vanilla's, all the same way. The window test
(`window_monitor.WindowTypicalityMonitor`) looks at the last n rollouts together. This script builds the
calibration that `ebvla-ood-report --calibrate_to` would save (the score fitted on the calibration rollouts) and
the window's reference (the held-out vanilla rollouts scored against it), then feeds the test rollouts to the
monitor one by one, as a deployment would, and prints each window's decision.

The defaults are records committed with the repository (MetaWorld, light preset, training seed 12000): 24 fresh
rollouts under sensor noise of severity 3, which the per-rollout default scores as *more* typical than vanilla
(AUROC 0.33). Point the three folders at your own `ebvla-eval` records (with `context_energy`, from a policy
trained with `joint_energy.target`) to do the same.

    python research/benchmarks/window_monitor_on_records.py --window=8
"""

from dataclasses import dataclass
from pathlib import Path

import draccus
import research_scores  # noqa: F401  (registers the research scores, `context_energy_two_sided` among them)
from window_monitor import WindowTypicalityMonitor
from window_report import score_sets

from lerobot_policy_ebvla.monitoring.records import load_episodes
from lerobot_policy_ebvla.runtime import EnergyReadout

RECORDS = Path(__file__).resolve().parents[1] / "results/metaworld_sweep_margin_full/seed12000/observation"


@dataclass
class WindowExampleConfig:
    # Vanilla rollouts the score is fitted on, and held-out vanilla rollouts: the window's reference.
    calibration: Path = RECORDS / "context_energy_full" / "calibration"
    vanilla: Path = RECORDS / "context_energy_full" / "vanilla"
    # The rollouts to monitor, in the order they ran.
    rollouts: Path = RECORDS / "context_energy_fresh" / "noise_s3"
    score: str = "context_energy_two_sided"
    # n rollouts per window, and alpha, its false-alarm rate on vanilla windows.
    window: int = 8
    false_alarm_rate: float = 0.05
    # The monitor sees each rollout's first k chunks (what it has early on).
    first_chunks: int = 3


def main(cfg: WindowExampleConfig) -> None:
    calibration_episodes, vanilla = load_episodes([cfg.calibration]), load_episodes([cfg.vanilla])
    calibration, scored = score_sets(calibration_episodes, {"vanilla": vanilla}, cfg.score, cfg.first_chunks)
    # calibration.save(checkpoint) would write it beside the weights; from_pretrained(checkpoint, reference) reads
    # it back.
    monitor = WindowTypicalityMonitor(calibration, scored["vanilla"].values, cfg.window, cfg.false_alarm_rate)

    rollouts = load_episodes([cfg.rollouts])
    ordered = sorted(rollouts.values(), key=lambda chunks: chunks[0].episode_index)
    alarms, decisions = 0, 0
    for chunks in ordered:
        chunks = chunks[: cfg.first_chunks]
        decision = monitor.add_rollout(
            EnergyReadout.of_arrays(
                [c.final_energy for c in chunks], context_energy=[c.context_energy for c in chunks]
            )
        )
        episode = chunks[0].episode_index
        if decision is None:
            print(f"rollout {episode:3d}: {monitor.n_rollouts} of {cfg.window} rollouts, no decision yet")
            continue
        decisions += 1
        alarms += decision.is_atypical
        print(
            f"rollout {episode:3d}: window p = {decision.p_value:.4f} -> "
            f"{decision.side or 'typical'} (AUROC against the reference: "
            + ", ".join(f"{a:.2f}" for a in decision.aurocs)
            + ")"
        )
    print(f"\n{alarms} of {decisions} windows atypical at alpha = {cfg.false_alarm_rate} ({cfg.rollouts}).")


if __name__ == "__main__":
    main(draccus.parse(WindowExampleConfig))
