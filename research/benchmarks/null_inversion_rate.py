"""How often a shift that does not move a score at all is reported "confidently under 0.5".

The reports mark a condition's AUROC confidently wrong when its bootstrap 95% interval
(`monitoring.metrics.bootstrap_auroc_interval`, the one every table uses) lies wholly below 0.5. For a condition whose
shifted rollouts score exactly like vanilla ones, that happens by chance alone; this measures how often, for the
sweep's sizes (8 shifted rollouts against 40 vanilla) and the fresh re-runs' (24 against 100), by drawing both sides
from one distribution. The AUROC and its interval depend on ranks only, so the distribution does not matter.

    python research/benchmarks/null_inversion_rate.py --sizes 8,40 24,100 --trials=2000
"""

import argparse

import numpy as np

from lerobot_policy_ebvla.monitoring.metrics import bootstrap_auroc_interval


def null_inversion_rate(n_shifted: int, n_vanilla: int, trials: int, seed: int = 0) -> float:
    """The share of `trials` null conditions whose AUROC interval lies wholly below 0.5."""
    rng = np.random.default_rng(seed)
    inverted = 0
    for trial in range(trials):
        vanilla, shifted = rng.standard_normal(n_vanilla), rng.standard_normal(n_shifted)
        inverted += bootstrap_auroc_interval(vanilla, shifted, seed=trial)[1] < 0.5
    return inverted / trials


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--sizes", nargs="+", default=["8,40", "24,100"], help="SHIFTED,VANILLA rollout counts."
    )
    parser.add_argument("--trials", type=int, default=2000)
    args = parser.parse_args()
    print("| shifted | vanilla | null conditions confidently under 0.5 | binomial 95% half-width |")
    print("|---|---|---|---|")
    for size in args.sizes:
        n_shifted, n_vanilla = (int(n) for n in size.split(","))
        rate = null_inversion_rate(n_shifted, n_vanilla, args.trials)
        half_width = 1.96 * np.sqrt(rate * (1 - rate) / args.trials)
        print(f"| {n_shifted} | {n_vanilla} | {rate:.1%} | {half_width:.1%} |")


if __name__ == "__main__":
    main()
