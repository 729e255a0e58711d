"""`ebvla-failure-report`: energy-slope failure prediction (paper Table IV), chosen on calibration episodes.

For each step, the (window, k) with the best balanced accuracy is chosen on calibration episodes, with the
slope threshold set by successful reference episodes, then reported unchanged on held-out episodes: across
tasks (all episodes pooled) and within each task. Slope Final and Slope Start both.

    ebvla-failure-report --calibration='[outputs/eval/vanilla_seed0]' --records='[outputs/eval/vanilla_seed1]' \\
        --output_dir=outputs/failure_report

Prints and writes `failure_report.md` and `energy_over_time.png` (held-out episodes). `--help` lists every
option.
"""

import logging
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import draccus
from lerobot.utils.utils import init_logging

from lerobot_policy_ebvla.monitoring.failure import (
    DEFAULT_MULTIPLIERS,
    Episode,
    evaluate_configurations,
    format_failure_table,
    select_configurations,
    successful,
)
from lerobot_policy_ebvla.monitoring.plots import plot_energy_over_time
from lerobot_policy_ebvla.monitoring.records import load_episodes, resolve_record_files

METRIC_TITLES = {"final": "Slope Final", "start": "Slope Start"}


@dataclass
class FailureReportConfig:
    """Energy-slope failure prediction (Table IV): (window, k) chosen on calibration episodes, reported held out.

    Each path is a records file, an eval folder or a glob pattern; lists are written
    `--records='[outputs/eval/a,outputs/eval/b*]'`. An episode's `success` is its label (positives: failed).
    """

    # Episodes on which each step's (window, k) is chosen.
    calibration: list[str] = field(default_factory=list)
    # Held-out episodes the chosen configurations are reported on.
    records: list[str] = field(default_factory=list)
    # Episodes whose slopes set mean_ref and std_ref: only their successful episodes are used (failed ones
    # are filtered out and counted in the report). Default: the successful episodes of `calibration`.
    reference: list[str] = field(default_factory=list)
    # Allow `records` that share files with `calibration`, or no `calibration` (then `records` is both):
    # the report is labelled IN-SAMPLE. Without it such a report is refused.
    in_sample: bool = False
    # Judge every episode at every step, an episode that ended carrying its last energy forward (the
    # paper's fixed episode set, same failure rate at every step); false leaves ended episodes out.
    carry_forward: bool = True
    # Keep only rows with these perturbation names (e.g. '[none]' for vanilla rollouts); default: all.
    perturbation: list[str] | None = None
    # Report steps 1..max_step (step s is the s-th chunk).
    max_step: int = 20
    # Try windows 2..max_window.
    max_window: int = 20
    # Std multipliers k to try.
    multipliers: list[float] = field(default_factory=lambda: list(DEFAULT_MULTIPLIERS))
    # Folder for failure_report.md and energy_over_time.png.
    output_dir: Path = Path("outputs/failure_report")


def protocol(cfg: FailureReportConfig) -> bool:
    """Whether the report is in-sample; refuses an in-sample report without `in_sample`."""
    if not cfg.records:
        raise ValueError("Give the held-out episodes to report on with `--records`.")
    calibration = set(resolve_record_files(cfg.calibration))
    shared = sorted(str(f) for f in calibration & set(resolve_record_files(cfg.records)))
    in_sample = not calibration or bool(shared)
    if in_sample and not cfg.in_sample:
        why = f"they share {shared}" if shared else "no `--calibration` episodes were given"
        raise ValueError(
            f"Refusing an in-sample report: {why}. Choose (window, k) on other episodes with `--calibration`, "
            "or pass `--in_sample=true` to report in-sample (labelled as such)."
        )
    return in_sample


def _scope(
    title: str,
    calibration: Sequence[Episode],
    held_out: Sequence[Episode],
    reference: Sequence[Episode],
    cfg: FailureReportConfig,
) -> str:
    n_failed = sum(not e[0].success for e in held_out)
    lines = [
        f"## {title}\n\n{len(calibration)} calibration episodes choose (window, k); {len(held_out)} held-out "
        f"episodes ({n_failed} failed) are reported; {len(successful(reference))} successful reference "
        "episodes set the threshold."
    ]
    if not calibration or not held_out or not successful(reference):
        return lines[0] + "\n\nNot enough episodes to report.\n"
    steps, windows = range(1, cfg.max_step + 1), range(2, cfg.max_window + 1)
    for metric, metric_title in METRIC_TITLES.items():
        chosen = select_configurations(
            calibration, steps, windows, cfg.multipliers, metric, reference, cfg.carry_forward
        )
        results = evaluate_configurations(held_out, chosen, metric, reference, cfg.carry_forward)
        lines.append(f"### {metric_title}\n\n{format_failure_table(results, chosen_on=chosen)}")
    return "\n\n".join(lines) + "\n"


def run(cfg: FailureReportConfig) -> str:
    """Builds the report, writes it and the energy-over-time figure to `cfg.output_dir`, returns its markdown."""
    in_sample = protocol(cfg)
    held_out = list(load_episodes(cfg.records, cfg.perturbation).values())
    calibration = (
        list(load_episodes(cfg.calibration, cfg.perturbation).values()) if cfg.calibration else held_out
    )
    if not held_out:
        raise ValueError(
            f"No episodes in `--records` {cfg.records} (perturbation filter {cfg.perturbation})."
        )
    given_reference = list(load_episodes(cfg.reference, cfg.perturbation).values()) if cfg.reference else None
    reference = given_reference if given_reference is not None else calibration
    n_dropped = len(reference) - len(successful(reference))
    reference = successful(reference)

    label = "IN-SAMPLE (calibration and report episodes overlap: optimistic)" if in_sample else "held-out"
    source = "`--reference`" if given_reference is not None else "the calibration episodes"
    header = (
        f"# Energy-based failure prediction ({label})\n\n"
        f"Reference: the {len(reference)} successful episodes of {source} set mean_ref and std_ref"
        f"{f'; {n_dropped} failed episodes were filtered out of it' if n_dropped else ''}. "
        + (
            "Episodes that ended before a step carry their last energy forward (every episode is judged at "
            "every step)."
            if cfg.carry_forward
            else "Episodes that ended before a step are left out at that step."
        )
        + " Positives are failed episodes."
    )
    sections = [header, _scope("Across tasks (all episodes pooled)", calibration, held_out, reference, cfg)]
    tasks = sorted({e[0].task for e in held_out} & {e[0].task for e in calibration})
    if len(tasks) > 1:
        for task in tasks:

            def of_task(episodes: Sequence[Episode], task: str = task) -> list[Episode]:
                return [e for e in episodes if e[0].task == task]

            sections.append(
                _scope(
                    f"Within task {task!r}", of_task(calibration), of_task(held_out), of_task(reference), cfg
                )
            )
    report = "\n\n".join(sections)

    cfg.output_dir.mkdir(parents=True, exist_ok=True)
    (cfg.output_dir / "failure_report.md").write_text(report, encoding="utf-8")
    plot_energy_over_time(held_out, cfg.output_dir / "energy_over_time.png")
    return report


def main(args: list[str] | None = None) -> None:
    init_logging()
    cfg = draccus.parse(FailureReportConfig, args=sys.argv[1:] if args is None else args)
    report = run(cfg)
    sys.stdout.write(report)
    logging.info(f"Saved failure_report.md and energy_over_time.png to {cfg.output_dir}")


if __name__ == "__main__":
    main()
