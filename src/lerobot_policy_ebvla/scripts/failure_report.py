"""`ebvla-failure-report`: energy-slope failure prediction report (paper Table IV) from energy records.

Prints, for Slope Final and Slope Start, the best (window, std multiplier) per step by balanced accuracy,
and saves the energies over time (chunk index) of successful and failed episodes.

By default the threshold of each configuration is calibrated on the successful episodes of the evaluated
records themselves, as an upper bound; give `--reference` records of other rollouts for a held-out threshold.

Example:
    ebvla-failure-report --records outputs/eval/libero_spatial outputs/eval/libero_goal \
        --output-dir outputs/failure_report
"""

import argparse
import logging
import sys
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from lerobot.utils.utils import init_logging

from lerobot_policy_ebvla.monitoring.failure import (
    DEFAULT_MULTIPLIERS,
    energy_matrix,
    failure_prediction_sweep,
    format_failure_table,
)
from lerobot_policy_ebvla.monitoring.records import EnergyRecord, group_by_episode, read_energy_records

METRIC_TITLES = {"final": "Slope Final", "start": "Slope Start"}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="ebvla-failure-report",
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument(
        "--records",
        nargs="+",
        required=True,
        type=Path,
        metavar="PATH",
        help="Record files (or eval folders) of the episodes to classify; `success` is the label.",
    )
    parser.add_argument(
        "--reference",
        nargs="+",
        default=[],
        type=Path,
        metavar="PATH",
        help="Record files whose episodes (all of them) calibrate the slope threshold. Default: the "
        "successful episodes of --records (optimistic).",
    )
    parser.add_argument(
        "--perturbation",
        nargs="+",
        default=None,
        metavar="NAME",
        help='Keep only rows with these perturbation names (e.g. "none" for vanilla rollouts).',
    )
    parser.add_argument("--max-step", type=int, default=20, help="Report steps 1..max_step (1-based chunks).")
    parser.add_argument("--max-window", type=int, default=20, help="Try windows 2..max_window.")
    parser.add_argument(
        "--multipliers",
        nargs="+",
        type=float,
        default=list(DEFAULT_MULTIPLIERS),
        help="Std multipliers k to try.",
    )
    parser.add_argument(
        "--output-dir",
        type=Path,
        default=Path("outputs/failure_report"),
        help="Folder for `energy_over_time.png` and `failure_report.md`.",
    )
    return parser


def load_episodes(paths: Sequence[Path], perturbations: Sequence[str] | None) -> list[list[EnergyRecord]]:
    """Episodes of every file, grouped per file since episode indices restart in every evaluation run."""
    episodes = []
    for path in paths:
        records = read_energy_records(path)
        if perturbations is not None:
            records = [r for r in records if r.perturbation in perturbations]
        episodes += list(group_by_episode(records).values())
    return episodes


def plot_energy_over_time(episodes: Sequence[Sequence[EnergyRecord]], path: Path) -> None:
    """Saves initial and final energy against chunk index: each episode faintly, each group's mean boldly."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    failed = np.array([not e[0].success for e in episodes])
    fig, axes = plt.subplots(1, 2, figsize=(12, 4), sharex=True)
    for ax, metric in zip(axes, ("start", "final"), strict=True):
        energies = energy_matrix(episodes, metric)  # (N, max_chunks), NaN after an episode ends
        energies[~np.isfinite(energies)] = np.nan  # +inf would swamp the axis; leave a gap instead
        for label, rows, color in (("success", ~failed, "tab:blue"), ("failure", failed, "tab:red")):
            if not rows.any():
                continue
            for series in energies[rows]:
                ax.plot(series, color=color, alpha=0.15, linewidth=0.8)
            with warnings.catch_warnings():
                # Columns past the end of every episode of the group are all NaN; their mean is NaN.
                warnings.simplefilter("ignore", RuntimeWarning)
                mean = np.nanmean(energies[rows], axis=0)
            ax.plot(mean, color=color, linewidth=2.5, label=f"{label} mean (n={int(rows.sum())})")
        ax.set_title(f"{'Initial' if metric == 'start' else 'Final'} energy")
        ax.set_xlabel("chunk index")
        ax.set_ylabel("energy")
        ax.legend(fontsize="small")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> None:
    init_logging()
    args = build_parser().parse_args(argv)
    episodes = load_episodes(args.records, args.perturbation)
    if not episodes:
        raise SystemExit("No episodes found in the given records.")
    reference = load_episodes(args.reference, args.perturbation) if args.reference else None

    steps, windows = range(1, args.max_step + 1), range(2, args.max_window + 1)
    n_failed = sum(not e[0].success for e in episodes)
    sections = [f"{len(episodes)} episodes, {n_failed} failed. Positives are failed episodes.\n"]
    for metric, title in METRIC_TITLES.items():
        results = failure_prediction_sweep(episodes, steps, windows, args.multipliers, metric, reference)
        sections.append(f"## Best configurations, {title}\n\n{format_failure_table(results)}\n")
    report = "\n".join(sections)
    sys.stdout.write(report + "\n")

    args.output_dir.mkdir(parents=True, exist_ok=True)
    (args.output_dir / "failure_report.md").write_text(
        f"# Energy-based failure prediction\n\n{report}", encoding="utf-8"
    )
    plot_energy_over_time(episodes, args.output_dir / "energy_over_time.png")
    logging.info(f"Saved failure_report.md and energy_over_time.png to {args.output_dir}")


if __name__ == "__main__":
    main()
