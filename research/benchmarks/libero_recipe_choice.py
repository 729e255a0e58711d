"""The LIBERO recipe choice rule of research/docs/libero_recipe_rule.md, applied to evaluated runs.

For each run of `libero_pipeline.RUNS` evaluated on tasks 2, 3 and 9 (`research/benchmarks/libero_cpu.sh`), from its
records alone: held-out vanilla success, and over each rollout's first 3 chunks the AUROC of its saved monitor
score under each of the 13 shift conditions (held-out vanilla against the condition), the balanced accuracy at the
shipped threshold (T = mu_v + 1 sigma_v on the calibration rollouts) and that threshold's alarm rate on held-out
vanilla. Then the rule: eligible runs (success >= 90 %), the highest minimum AUROC, ties within 0.03 broken by the
balanced accuracy, then by the lower alarm rate; clause 4 names the chosen run's miss (a minimum AUROC below 0.5 or a
balanced accuracy below 80 %), and `--not_run` the candidates without records.

    python research/benchmarks/libero_recipe_choice.py --results=research/results/libero_cpu \\
        --runs ebvla_cpu ebvla_joint_cpu ebvla_joint_all_cpu
"""

import argparse
import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from lerobot_policy_ebvla.monitoring.metrics import auroc
from lerobot_policy_ebvla.monitoring.ood_report import (
    ALL_CONDITIONS,
    OODReportConfig,
    OODScores,
    score_ood_report,
)
from lerobot_policy_ebvla.monitoring.records import group_by_episode, read_energy_records, records_file_in

SHIFTS = [f"{p}{s}" for p in ("pose", "distance", "rotation", "fov") for s in (5, 3, 1)] + ["light_dim5"]
FIRST_CHUNKS = 3
MIN_SUCCESS = 0.9
TIE = 0.03
# Clause 4: below either, the chosen run still goes to the ten-task check, its miss named.
GOOD_MIN_AUROC = 0.5
GOOD_BALANCED_ACCURACY = 0.8


@dataclass
class RunCriteria:
    run: str
    score: str
    heldout_success: tuple[int, int]
    auroc_per_condition: dict[str, float]
    min_auroc: float
    balanced_accuracy: float
    heldout_alarm_rate: float

    @property
    def eligible(self) -> bool:
        wins, total = self.heldout_success
        return total > 0 and wins / total >= MIN_SUCCESS


def rollout_successes(folders: list[Path]) -> tuple[int, int]:
    """(successful rollouts, rollouts) over the record folders."""
    outcomes = []
    for folder in folders:
        episodes = group_by_episode(read_energy_records(records_file_in(folder)))
        outcomes += [episode[0].success for episode in episodes.values()]
    return sum(outcomes), len(outcomes)


def heldout_success(run_dir: Path) -> tuple[int, int]:
    return rollout_successes(sorted((run_dir / "vanilla_heldout").glob("task*")))


@dataclass
class AtThreshold:
    """One score over the first chunks: its AUROC per condition, and its threshold T from the calibration rollouts
    alone with the balanced accuracy and the held-out vanilla alarm rate it gives."""

    auroc_per_condition: dict[str, float]
    threshold: float
    balanced_accuracy: float
    heldout_alarm_rate: float


def at_threshold(scored: OODScores, score: str, first_chunks: int = FIRST_CHUNKS) -> AtThreshold:
    sets = scored.at(first_chunks)
    threshold = scored.fit(score, first_chunks).threshold
    negatives, shifted = sets.negatives[score], sets.positives[ALL_CONDITIONS][score]
    alarm_rate = float(np.mean(negatives > threshold))
    return AtThreshold(
        {
            condition: float(auroc(negatives, positives[score]))
            for condition, positives in sets.positives.items()
            if condition != ALL_CONDITIONS
        },
        threshold,
        0.5 * (float(np.mean(shifted > threshold)) + 1.0 - alarm_rate),
        alarm_rate,
    )


def run_criteria(results: Path, run: str, score: str, output_dir: Path) -> RunCriteria:
    """The rule's three criteria for one evaluated run, its monitor scoring `score`."""
    run_dir = results / "eval" / run
    cfg = OODReportConfig(
        calibration=[str(run_dir / "vanilla_calib" / "task*")],
        vanilla=[str(run_dir / "vanilla_heldout" / "task*")],
        ood=[str(run_dir / shift / "task*") for shift in SHIFTS],
        score=score,
        output_dir=output_dir,
        first_chunks=[FIRST_CHUNKS],
    )
    row = at_threshold(score_ood_report(cfg), score)
    return RunCriteria(
        run,
        score,
        heldout_success(run_dir),
        row.auroc_per_condition,
        min(row.auroc_per_condition.values()),
        row.balanced_accuracy,
        row.heldout_alarm_rate,
    )


def choose(criteria: list[RunCriteria]) -> RunCriteria | None:
    """The rule: among eligible runs, the highest minimum AUROC; within `TIE` of it, the higher balanced accuracy,
    then the lower held-out alarm rate. None when no run is eligible."""
    eligible = [c for c in criteria if c.eligible]
    if not eligible:
        return None
    best = max(c.min_auroc for c in eligible)
    tied = [c for c in eligible if c.min_auroc >= best - TIE]
    return max(tied, key=lambda c: (c.balanced_accuracy, -c.heldout_alarm_rate))


def clause_4_misses(chosen: RunCriteria) -> list[str]:
    """What keeps the chosen run from being good enough (clause 4), each with its number; empty when nothing."""
    misses = []
    if chosen.min_auroc < GOOD_MIN_AUROC:
        worst = min(chosen.auroc_per_condition, key=chosen.auroc_per_condition.get)
        misses.append(f"minimum AUROC {chosen.min_auroc:.3f} ({worst}) < {GOOD_MIN_AUROC}")
    if chosen.balanced_accuracy < GOOD_BALANCED_ACCURACY:
        misses.append(
            f"balanced accuracy {100 * chosen.balanced_accuracy:.1f}% < {100 * GOOD_BALANCED_ACCURACY:.0f}%"
        )
    return misses


def monitor_score(results: Path, run: str) -> str:
    """The score the run's checkpoint saved (`monitor.score`), "final_energy" for one saved before it existed.
    `results` is saved results (`train/<run>/last`) or a work folder (`train/<run>/checkpoints/last`)."""
    run_dir = results / "train" / run
    configs = [run_dir / "last" / "pretrained_model" / "config.json"]
    configs.append(run_dir / "checkpoints" / "last" / "pretrained_model" / "config.json")
    saved = next((json.loads(c.read_text()) for c in configs if c.exists()), {})
    return saved.get("monitor", {}).get("score", "final_energy")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--results", type=Path, required=True)
    parser.add_argument("--runs", nargs="+", required=True)
    parser.add_argument(
        "--not_run", nargs="*", default=[], help="candidates of the rule without records, named in the output"
    )
    parser.add_argument("--output_dir", type=Path, default=Path("outputs/libero_recipe_choice"))
    args = parser.parse_args(argv)
    criteria = [
        run_criteria(args.results, run, monitor_score(args.results, run), args.output_dir / run)
        for run in args.runs
    ]
    chosen = choose(criteria)
    print("| run | score | held-out success | min AUROC (condition) | bal. acc. at T | held-out alarms |")
    print("|---|---|---:|---|---:|---:|")
    for c in criteria:
        worst = min(c.auroc_per_condition, key=c.auroc_per_condition.get)
        print(
            f"| {c.run} | {c.score} | {c.heldout_success[0]}/{c.heldout_success[1]} | {c.min_auroc:.3f} ({worst}) "
            f"| {100 * c.balanced_accuracy:.1f}% | {100 * c.heldout_alarm_rate:.1f}% |"
        )
    misses = clause_4_misses(chosen) if chosen else []
    print(f"\nchosen: {chosen.run if chosen else 'none eligible'}")
    if misses:
        print("not good enough (clause 4): " + "; ".join(misses))
    if args.not_run:
        print("not run: " + ", ".join(args.not_run))
    args.output_dir.mkdir(parents=True, exist_ok=True)
    payload = {
        "criteria": [asdict(c) for c in criteria],
        "chosen": chosen.run if chosen else None,
        "clause_4_misses": misses,
        "not_run": args.not_run,
    }
    (args.output_dir / "choice.json").write_text(json.dumps(payload, indent=1))


if __name__ == "__main__":
    main()
