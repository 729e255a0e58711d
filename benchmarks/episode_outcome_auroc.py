"""Does the energy tell failed from successful episodes? AUROC of episode scores, failed = positive.

Reads `ebvla-eval` folders (one per task) and scores each episode three ways: its mean final energy over all
chunks, over its first `--first_chunks` chunks (a failed episode runs longer, so its whole-episode mean also
sees more of the late, stalled motion), and its mean initial energy. Prints pooled and per-task AUROCs with
bootstrap 95% intervals.

    python benchmarks/episode_outcome_auroc.py /tmp/mt/run/eval/ebvla/vanilla/* --first_chunks 5
"""

import argparse

import numpy as np

from lerobot_policy_ebvla.monitoring import group_by_episode, read_energy_records
from lerobot_policy_ebvla.monitoring.metrics import auroc, bootstrap_auroc_interval


def episode_scores(eval_dirs: list[str], first_chunks: int) -> list[dict]:
    episodes = []
    for eval_dir in eval_dirs:
        for key, records in group_by_episode(read_energy_records(eval_dir)).items():
            finals = [r.final_energy for r in records]
            episodes.append(
                {
                    "task": key.task,
                    "success": records[0].success,
                    "chunks": len(records),
                    "final_all": float(np.mean(finals)),
                    "final_first": float(np.mean(finals[:first_chunks])),
                    "initial": float(np.mean([r.initial_energy for r in records])),
                }
            )
    return episodes


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "eval_dirs", nargs="+", help="ebvla-eval output folders (energy_records.jsonl inside)."
    )
    parser.add_argument("--first_chunks", type=int, default=5)
    args = parser.parse_args()
    episodes = episode_scores(args.eval_dirs, args.first_chunks)
    succeeded = [e for e in episodes if e["success"]]
    failed = [e for e in episodes if not e["success"]]
    print(
        f"{len(episodes)} episodes, {len(failed)} failed; mean chunks: successful "
        f"{np.mean([e['chunks'] for e in succeeded]):.1f}, failed {np.mean([e['chunks'] for e in failed]):.1f}"
    )
    names = {
        "final_all": "mean final energy, all chunks",
        "final_first": f"mean final energy, first {args.first_chunks} chunks",
        "initial": "mean initial energy",
    }
    for score, name in names.items():
        negatives, positives = [e[score] for e in succeeded], [e[score] for e in failed]
        low, high = bootstrap_auroc_interval(negatives, positives)
        print(f"  {name}: AUROC {auroc(negatives, positives):.3f} [{low:.3f}, {high:.3f}]")
    for task in sorted({e["task"] for e in episodes}):
        negatives = [e["final_first"] for e in succeeded if e["task"] == task]
        positives = [e["final_first"] for e in failed if e["task"] == task]
        print(
            f"    {task}: {len(negatives)} successful, {len(positives)} failed, AUROC (first chunks) "
            f"{auroc(negatives, positives):.3f}"
        )


if __name__ == "__main__":
    main()
