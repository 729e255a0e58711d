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

`--scores` makes the score a candidate too (added on 2026-11-29 for D's second check, research/docs/libero_runs.md
"D's second failure check"): each energy score the failure check may read (`monitor.failure_score`), a calibration
rollout scored against the score fitted on the other calibration rollouts, as the OOD report scores it. The chosen
(score, N) has the highest calibration balanced accuracy; on a tie the earlier N, then the score named first.
`--development` adds rollouts already looked at (the held-out ones of an earlier report) to those the balanced
accuracy is measured on, T still from the calibration rollouts alone: more failures choose, and only rollouts outside
both sets can then test the choice.
"""

import argparse
import json
from pathlib import Path

import numpy as np

from lerobot_policy_ebvla.configuration_groups import FAILURE_SCORES
from lerobot_policy_ebvla.monitoring.baselines import RegisteredScoreModel
from lerobot_policy_ebvla.monitoring.records import load_episodes
from lerobot_policy_ebvla.runtime.scores import SCORES, score_rollout

SCORE = "final_energy"
CANDIDATES = (3, 4, 6, 8, 10, 12, 14, 16)
K = 1.0


def first_chunk_means(episodes: list, n: int) -> np.ndarray:
    """Each episode's mean final energy over its first n chunks (all of them if it is shorter)."""
    return np.array([np.mean([record.final_energy for record in episode[:n]]) for episode in episodes])


def calibration_scores(episodes: list, score: str, candidates, others: list = ()) -> dict[int, np.ndarray]:
    """Each calibration episode's `score` over its first n chunks, for each candidate n, fitted without it
    (leave-one-out), then each of `others` against the fit on all the calibration episodes."""
    if score == SCORE:
        return {n: first_chunk_means([*episodes, *others], n) for n in candidates}
    model = RegisteredScoreModel(SCORES[score], dict(enumerate(episodes)), "mean", knn_k=1)
    components = [model.components(episode, key) for key, episode in enumerate(episodes)]
    components += [model.components(episode) for episode in others]
    return {
        n: np.array([score_rollout(fitted, chunks[:n], "mean") for fitted, chunks in components])
        for n in candidates
    }


def balanced_accuracy(scores: np.ndarray, failed: np.ndarray, threshold: float) -> float:
    alarmed = scores > threshold
    return 0.5 * (alarmed[failed].mean() + (~alarmed[~failed]).mean())


def choose(
    episodes: list,
    candidates=CANDIDATES,
    k: float = K,
    scores: tuple[str, ...] = (SCORE,),
    development: list = (),
) -> dict:
    """The balanced accuracy at each candidate N (of each of `scores`) and the chosen N (and score), on the
    calibration `episodes` and the `development` ones, at T of the successful calibration episodes. With one score
    and no development episodes the rows and the JSON keep the shape of the choices written before they were added.

    Raises:
        ValueError: Without both failed and successful calibration rollouts (at least 2 successful).
    """
    failed = np.array([not episode[0].success for episode in episodes])
    judged = np.array([not episode[0].success for episode in [*episodes, *development]])
    if failed.all() or not failed.any() or (~failed).sum() < 2:
        raise ValueError(
            f"Choosing N needs failed and at least 2 successful calibration rollouts; got {failed.sum()} failed of "
            f"{failed.size}."
        )
    unknown = [s for s in scores if s not in FAILURE_SCORES or s == "none"]
    if unknown:
        raise ValueError(f"The failure check reads one of {FAILURE_SCORES[1:]}; got {unknown}.")
    rows = []
    for rank, score in enumerate(scores):
        for n, values in calibration_scores(episodes, score, candidates, development).items():
            reference = values[: failed.size][~failed]
            threshold = float(reference.mean() + k * reference.std())
            accuracy = balanced_accuracy(values, judged, threshold)
            row = {"score": score, "chunks": n, "threshold": threshold, "balanced_accuracy": accuracy}
            rows.append((round(accuracy, 9), -n, -rank, row))
    *_, best = max(rows, key=lambda ranked: ranked[:3])
    chosen = best["score"]
    # One candidate score: its name is the choice's, not each row's.
    rows = [{k: v for k, v in row.items() if len(scores) > 1 or k != "score"} for *_, row in rows]
    counts = {
        "calibration_rollouts": int(failed.size),
        "calibration_failed": int(failed.sum()),
    }
    if len(development):
        counts |= {
            "development_rollouts": len(development),
            "development_failed": int(judged[failed.size :].sum()),
        }
    return {
        "score": chosen,
        "k": k,
        **counts,
        "candidates": rows,
        "chunks": best["chunks"],
        "report_options": [
            f"--failure_score={chosen}",
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
    parser.add_argument(
        "--development",
        nargs="*",
        default=[],
        help="rollouts already looked at that also judge each candidate: files, folders or globs",
    )
    parser.add_argument(
        "--scores", nargs="+", default=[SCORE], help="the candidate energy scores (default: the final energy)"
    )
    args = parser.parse_args(argv)
    episodes = list(load_episodes([args.calibration]).values())
    development = list(load_episodes(args.development).values()) if args.development else []
    choice = choose(episodes, scores=tuple(args.scores), development=development)
    for row in choice["candidates"]:
        print(
            f"{row.get('score', SCORE)}, N = {row['chunks']:2}: T = {row['threshold']:7.3f}, balanced accuracy "
            f"{row['balanced_accuracy']:.1%} ({'calibration and development' if development else 'calibration'})"
        )
    print(
        f"chosen: {choice['score']}, N = {choice['chunks']} ({choice['calibration_failed']} of "
        f"{choice['calibration_rollouts']} failed)"
    )
    print(" ".join(choice["report_options"]))
    if args.output is not None:
        args.output.parent.mkdir(parents=True, exist_ok=True)
        args.output.write_text(json.dumps(choice, indent=1) + "\n")


if __name__ == "__main__":
    main()
