"""Does the energy tell failed from successful episodes? AUROC of episode scores, failed = positive.

Reads `ebvla-eval` folders (records files or glob patterns work too) and scores each episode three ways: its
mean final energy over all chunks, over its first `--first_chunks` chunks (a failed episode runs longer, so its
whole-episode mean also sees more of the late, stalled motion), and its mean initial energy. Prints pooled and
per-task AUROCs with bootstrap 95% intervals.

    python research/benchmarks/episode_outcome_auroc.py /tmp/mt/run/eval/ebvla/vanilla/* --first_chunks 5
"""

import argparse

import numpy as np

from lerobot_policy_ebvla.monitoring import auroc, bootstrap_auroc_interval, episode_scores, load_episodes


def print_auroc(name: str, scores: np.ndarray, failed: np.ndarray) -> None:
    negatives, positives = scores[~failed], scores[failed]
    low, high = bootstrap_auroc_interval(negatives, positives)
    print(f"  {name}: AUROC {auroc(negatives, positives):.3f} [{low:.3f}, {high:.3f}]")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "eval_dirs", nargs="+", help="ebvla-eval output folders (energy_records.jsonl inside)."
    )
    parser.add_argument("--first_chunks", type=int, default=5)
    args = parser.parse_args()

    episodes = load_episodes(args.eval_dirs)
    first_chunks = {key: chunks[: args.first_chunks] for key, chunks in episodes.items()}
    failed = np.array([not chunks[0].success for chunks in episodes.values()])
    tasks = np.array([key.task for _, key in episodes])
    lengths = np.array([len(chunks) for chunks in episodes.values()])
    print(
        f"{len(episodes)} episodes, {failed.sum()} failed; mean chunks: successful {lengths[~failed].mean():.1f}, "
        f"failed {lengths[failed].mean():.1f}"
    )
    first = episode_scores(first_chunks, "final_energy")
    print_auroc("mean final energy, all chunks", episode_scores(episodes, "final_energy"), failed)
    print_auroc(f"mean final energy, first {args.first_chunks} chunks", first, failed)
    print_auroc("mean initial energy", episode_scores(episodes, "initial_energy"), failed)
    for task in sorted(set(tasks)):
        in_task = tasks == task
        negatives, positives = first[in_task & ~failed], first[in_task & failed]
        print(
            f"    {task}: {len(negatives)} successful, {len(positives)} failed, AUROC (first chunks) "
            f"{auroc(negatives, positives):.3f}"
        )


if __name__ == "__main__":
    main()
