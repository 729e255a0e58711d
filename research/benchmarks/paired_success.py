"""Success of two runs on the same fixed initial states, episode by episode (issue 52, "Best of 8 by energy").

Both runs' records of one condition (`eval/<run>/<condition>/task<i>`) start from the same LIBERO fixed states with the
same env seeds (checked on each episode's first goal distance); the MCMC's noise differs. Per task: each run's
successes, the episodes the second run won and lost against the first, and over all tasks the two-sided sign test.

    python research/benchmarks/paired_success.py \\
        --first=research/results/libero_object10_more/eval/ebvla_joint_fast_cpu_more/vanilla_confirm \\
        --second=research/results/libero_object10_more/eval/ebvla_joint_fast_cpu_more_best8/vanilla_confirm
"""

import argparse
import json
from math import comb, isclose
from pathlib import Path

from lerobot_policy_ebvla.monitoring.records import load_episodes


def outcomes(folder: Path) -> list[tuple[bool, float]]:
    """(success, first goal distance) of each episode of one task folder, in episode order."""
    episodes = sorted(load_episodes([str(folder)]).items(), key=lambda item: item[0][1])
    return [(episode[0].success, episode[0].goal_distance) for _, episode in episodes]


def same_state(first: float, second: float) -> bool:
    """Whether two episodes' first goal distances (m) come from one initial state. MuJoCo on another CPU kind
    rounds the same state's distance differently in its last bits (1e-16 m); two fixed states of one task differ by
    3.6e-6 m at the closest in G's records."""
    return isclose(first, second, rel_tol=0.0, abs_tol=1e-9)


def sign_test(won: int, lost: int) -> float:
    """Two-sided sign test of `won` against `lost` (ties left out)."""
    n = won + lost
    return 1.0 if n == 0 else min(1.0, 2 * sum(comb(n, k) for k in range(min(won, lost) + 1)) / 2**n)


def paired(first: Path, second: Path) -> dict:
    tasks = {}
    for folder in sorted(second.glob("task*")):
        a, b = outcomes(first / folder.name), outcomes(folder)
        if len(a) != len(b) or not all(same_state(x[1], y[1]) for x, y in zip(a, b, strict=True)):
            raise ValueError(
                f"{folder.name}: the two runs did not start from the same states (first goal distances)."
            )
        tasks[folder.name] = {
            "first": sum(x[0] for x in a),
            "second": sum(y[0] for y in b),
            "episodes": len(a),
            "won": sum(y[0] and not x[0] for x, y in zip(a, b, strict=True)),
            "lost": sum(x[0] and not y[0] for x, y in zip(a, b, strict=True)),
        }
    total = {
        key: sum(t[key] for t in tasks.values()) for key in ("first", "second", "episodes", "won", "lost")
    }
    return {"tasks": tasks, "total": total, "sign_test_p": sign_test(total["won"], total["lost"])}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--first", type=Path, required=True, help="the first run's condition folder")
    parser.add_argument("--second", type=Path, required=True, help="the second run's condition folder")
    parser.add_argument("--output", type=Path, default=None)
    args = parser.parse_args(argv)
    result = paired(args.first, args.second)
    print(json.dumps(result, indent=1))
    if args.output is not None:
        args.output.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
