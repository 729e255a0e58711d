"""The decision chunk N of the monitor's failure check, chosen on calibration rollouts alone (issue 52, Table IV).

The failure check alarms when a rollout's score over its first N chunks exceeds T = mu + 1 sigma of the successful
calibration rollouts' (`ebvla-ood-report --failure_reference=successful`). Its score is the paper's final energy E
(`final_energy`, each chunk's E after the K_inf refinement steps, averaged over the first N chunks): on LIBERO the
failures that matter are grasps that miss, which only show once the arm has reached the object, so the first 3
chunks the OOD check reads know nothing of them (research/docs/libero_runs.md, "The ten-task check").

N is the one of `CANDIDATES` at which the calibration rollouts' own balanced accuracy (failed against successful,
at that T) is highest, the earlier on a tie. Only calibration rollouts are read: the held-out and fresh rollouts
the check is reported on choose nothing. Written on 2026-11-29, developed on C's ten-task records (whose held-out
rollouts it was looked at on) before D's rollouts existed; D's rollouts are its test.

    python research/benchmarks/failure_check_choice.py \\
        --calibration='research/results/libero_object10_more/eval/ebvla_joint_fast_cpu_more/vanilla_calib/task*' \\
        --output=research/results/libero_object10_more/reports/ebvla_joint_fast_cpu_more/failure_check_choice.json

It prints the `ebvla-ood-report` options of the chosen check.
"""

import argparse
import json
from pathlib import Path

import numpy as np

from lerobot_policy_ebvla.monitoring.records import load_episodes

SCORE = "final_energy"
CANDIDATES = (3, 4, 6, 8, 10, 12, 14, 16)
K = 1.0


def first_chunk_means(episodes: list, n: int) -> np.ndarray:
    """Each episode's mean final energy over its first n chunks (all of them if it is shorter)."""
    return np.array([np.mean([record.final_energy for record in episode[:n]]) for episode in episodes])


def balanced_accuracy(scores: np.ndarray, failed: np.ndarray, threshold: float) -> float:
    alarmed = scores > threshold
    return 0.5 * (alarmed[failed].mean() + (~alarmed[~failed]).mean())


def choose(episodes: list, candidates=CANDIDATES, k: float = K) -> dict:
    """The calibration balanced accuracy at each candidate N and the chosen N.

    Raises:
        ValueError: Without both failed and successful calibration rollouts (at least 2 successful).
    """
    failed = np.array([not episode[0].success for episode in episodes])
    if failed.all() or not failed.any() or (~failed).sum() < 2:
        raise ValueError(
            f"Choosing N needs failed and at least 2 successful calibration rollouts; got {failed.sum()} failed of "
            f"{failed.size}."
        )
    rows = []
    for n in candidates:
        scores = first_chunk_means(episodes, n)
        reference = scores[~failed]
        threshold = float(reference.mean() + k * reference.std())
        rows.append(
            {
                "chunks": n,
                "threshold": threshold,
                "balanced_accuracy": balanced_accuracy(scores, failed, threshold),
            }
        )
    best = max(rows, key=lambda row: (round(row["balanced_accuracy"], 9), -row["chunks"]))
    return {
        "score": SCORE,
        "k": k,
        "calibration_rollouts": int(failed.size),
        "calibration_failed": int(failed.sum()),
        "candidates": rows,
        "chunks": best["chunks"],
        "report_options": [
            f"--failure_score={SCORE}",
            f"--failure_chunks={best['chunks']}",
            "--failure_reference=successful",
        ],
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--calibration", required=True, help="calibration records: a file, folder or glob")
    parser.add_argument("--output", type=Path, default=None, help="write the choice here (JSON)")
    args = parser.parse_args(argv)
    episodes = list(load_episodes([args.calibration]).values())
    choice = choose(episodes)
    for row in choice["candidates"]:
        print(
            f"N = {row['chunks']:2}: T = {row['threshold']:7.3f}, calibration balanced accuracy {row['balanced_accuracy']:.1%}"
        )
    print(
        f"chosen: N = {choice['chunks']} ({choice['calibration_failed']} of {choice['calibration_rollouts']} failed)"
    )
    print(" ".join(choice["report_options"]))
    if args.output is not None:
        args.output.parent.mkdir(parents=True, exist_ok=True)
        args.output.write_text(json.dumps(choice, indent=1) + "\n")


if __name__ == "__main__":
    main()
