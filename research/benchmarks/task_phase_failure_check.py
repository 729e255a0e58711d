"""The test of `task_phase_energy`, a failure check on both terms of the joint energy against the rollout's own task's
successful calibration rollouts (issue 52, Table IV; research/docs/libero_runs.md, "The task's own successful rollouts
as the reference", where the reading was chosen on D and E and this test fixed before G's energies were read).

For each term x of the joint energy (E_c and the head's part E - E_c) and chunk index t: mu_task[t] is the mean of the
successful calibration rollouts of the rollout's task at chunk t, sigma[t] the standard deviation over all successful
calibration rollouts of x minus their own task's mu_task[t] (pooled within tasks), both as `PhaseStatistics` fits
them; z_t = (x_t - mu_task[t]) / sigma[t], averaged over the first N chunks and both terms (one-sided). A calibration
rollout is scored against the statistics fitted without it; T = mu + k sigma of the successful calibration rollouts'
scores. Beside it, at the same N and T rule: the shipped `joint_phase_energy` and `chunk_context_nn` (no energy), each
row with n per side, balanced accuracy and AUROC [95 %], the energy rows also with their AUROC minus the baseline's
and its paired bootstrap interval; the chosen check's caught failures' lead to the onset and to the episode's end.

    python research/benchmarks/task_phase_failure_check.py \\
        --calibration='outputs/libero10_arm_more/eval/ebvla_joint_fast_cpu_arm_more_longer/vanilla_calib/task*' \\
        --held_out 'outputs/libero10_arm_more/eval/ebvla_joint_fast_cpu_arm_more_longer/vanilla_heldout/task*' \\
        'outputs/libero10_arm_more/eval/ebvla_joint_fast_cpu_arm_more_longer/vanilla_confirm/task*' \\
        --output=research/results/libero_object10_arm_more/reports/task_phase_failure_check.json
"""

import argparse
from collections.abc import Hashable, Mapping, Sequence
from pathlib import Path

import numpy as np
from failure_check_test import (
    BASELINE,
    MIN_BALANCED_ACCURACY,
    leads,
    report_markdown,
    scores_at,
    write_report,
)
from failure_score_variants import difference_lines, rows_against_baseline

from lerobot_policy_ebvla.monitoring.records import Episode, load_episodes
from lerobot_policy_ebvla.runtime.statistics import PhaseStatistics, energies_by_index

CHOSEN = "task_phase_energy"
SHIPPED = "joint_phase_energy"
CHUNKS = 16
K = 1.0


def term_series(episode: Episode) -> tuple[np.ndarray, np.ndarray]:
    """The episode's E_c and E - E_c, each indexed by chunk index (NaN where a chunk is missing)."""
    index = [record.chunk_index for record in episode]
    context = np.array([record.context_energy for record in episode], dtype=float)
    final = np.array([record.final_energy for record in episode], dtype=float)
    return energies_by_index(context, index), energies_by_index(final - context, index)


def fit_task_phase(series: Sequence[np.ndarray], tasks: Sequence[str]) -> dict[str, PhaseStatistics]:
    """Each task's statistics of one term: its successful rollouts' mean at each chunk index, and the standard
    deviation of every rollout's deviation from its own task's mean, pooled over the tasks."""
    means = {
        task: PhaseStatistics.fit([s for s, t in zip(series, tasks, strict=True) if t == task]).mean
        for task in set(tasks)
    }
    residuals = [
        s - np.asarray(means[t])[np.minimum(np.arange(len(s)), len(means[t]) - 1)]
        for s, t in zip(series, tasks, strict=True)
    ]
    std = PhaseStatistics.fit(residuals).std
    length = len(std)
    return {
        task: PhaseStatistics(tuple(np.asarray(mean)[np.minimum(np.arange(length), len(mean) - 1)]), std)
        for task, mean in means.items()
    }


def task_phase_scores(
    calibration: Mapping[Hashable, Episode], episodes: Mapping[Hashable, Episode], n: int
) -> tuple[np.ndarray, np.ndarray]:
    """`task_phase_energy` over the first n chunks of the calibration rollouts (each against the statistics fitted
    without it) and of `episodes`.

    Raises:
        ValueError: A task of `episodes` has no successful calibration rollout.
    """
    references = [(key, episode) for key, episode in calibration.items() if episode[0].success]

    def fitted(leave_out=None) -> list[dict[str, PhaseStatistics]]:
        kept = [(term_series(e), e[0].task) for key, e in references if key != leave_out]
        tasks = [task for _, task in kept]
        return [fit_task_phase([terms[i] for terms, _ in kept], tasks) for i in range(2)]

    def score(episode: Episode, statistics: list[dict[str, PhaseStatistics]]) -> float:
        task = episode[0].task
        if task not in statistics[0]:
            raise ValueError(
                f"No successful calibration rollout of the task {task!r}: its statistics are unknown."
            )
        first = [record for record in episode if record.chunk_index < n] or episode[:1]
        index = np.array([record.chunk_index for record in first])
        context = np.array([record.context_energy for record in first], dtype=float)
        head = np.array([record.final_energy for record in first], dtype=float) - context
        z = [statistics[0][task].z(context, index), statistics[1][task].z(head, index)]
        return float(np.mean([values.mean() for values in z]))

    everyone = fitted()
    successful_keys = {key for key, _ in references}
    calibration_scores = np.array(
        [score(e, fitted(key) if key in successful_keys else everyone) for key, e in calibration.items()]
    )
    return calibration_scores, np.array([score(e, everyone) for e in episodes.values()])


def test_reading(
    calibration: dict, held_out_sets: dict[str, dict], chosen: str, reading, n: int, k: float
) -> dict:
    """Every row of every held-out set and of all of them together, at T of the successful calibration rollouts: the
    reading `chosen` (`reading(held_out)` gives the calibration rollouts' and the held-out ones' scores), the shipped
    check and the baseline, with the chosen check's caught failures' leads."""
    successful = np.array([episode[0].success for episode in calibration.values()])
    sets = {**held_out_sets, "all held out": {key: e for s in held_out_sets.values() for key, e in s.items()}}
    result = {"chosen": chosen, "chunks": n, "k": k, "calibration_rollouts": int(successful.size)}
    result["calibration_failed"] = int((~successful).sum())
    result["sets"] = {}
    for title, held_out in sets.items():
        failed = np.array([not episode[0].success for episode in held_out.values()])
        values = {
            chosen: reading(held_out),
            SHIPPED: scores_at(SHIPPED, calibration, held_out, n),
            BASELINE: scores_at(BASELINE, calibration, held_out, n),
        }
        rows = rows_against_baseline(values, successful, failed, k)
        row = next(r for r in rows if r["score"] == chosen)
        result["sets"][title] = {
            "rollouts": int(failed.size),
            "failed": int(failed.sum()),
            "rows": rows,
            "leads": leads(list(held_out.values()), values[chosen][1], row["threshold"], n),
        }
    return result


def test(calibration: dict, held_out_sets: dict[str, dict], n: int = CHUNKS, k: float = K) -> dict:
    """`task_phase_energy`'s rows (`test_reading`)."""
    return test_reading(
        calibration, held_out_sets, CHOSEN, lambda held_out: task_phase_scores(calibration, held_out, n), n, k
    )


def reading_targets(result: dict, at_least: bool = True) -> list[tuple[str, bool, str]]:
    """The fixed reading on all held-out rollouts together: (target, met, figures); its AUROC against the shipped
    check's at least (`at_least`) or above it."""
    rows = {r["score"]: r for r in result["sets"]["all held out"]["rows"]}
    chosen, shipped = rows[result["chosen"]], rows[SHIPPED]
    low, high = chosen["auroc_minus_baseline_interval"]
    return [
        (
            f"balanced accuracy >= {MIN_BALANCED_ACCURACY:.0%}",
            chosen["balanced_accuracy"] >= MIN_BALANCED_ACCURACY,
            f"{chosen['balanced_accuracy']:.1%}",
        ),
        (
            f"AUROC {'at least' if at_least else 'above'} {SHIPPED}'s",
            chosen["auroc"] >= shipped["auroc"] if at_least else chosen["auroc"] > shipped["auroc"],
            f"{chosen['auroc']:.3f} against {shipped['auroc']:.3f}",
        ),
        (
            f"not below {BASELINE} outside the paired interval",
            high >= 0,
            f"{chosen['auroc_minus_baseline']:+.3f} [{low:+.3f}, {high:+.3f}]",
        ),
    ]


def markdown(result: dict) -> str:
    return report_markdown(
        CHOSEN,
        result["chunks"],
        result["k"],
        result,
        reading_targets(result),
        lambda found: difference_lines(found["rows"], lambda name: f"`{name}`"),
    )


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--calibration", required=True, help="the checkpoint's calibration records (a glob)")
    parser.add_argument("--held_out", nargs="+", required=True, help="held-out records, one glob per set")
    parser.add_argument("--chunks", type=int, default=CHUNKS)
    parser.add_argument(
        "--output", type=Path, default=None, help="write the result here (JSON, and .md beside it)"
    )
    args = parser.parse_args(argv)
    calibration = load_episodes([args.calibration])
    held_out_sets = {Path(pattern).parent.name: load_episodes([pattern]) for pattern in args.held_out}
    result = test(calibration, held_out_sets, args.chunks)
    write_report(result, markdown(result), args.output)


if __name__ == "__main__":
    main()
