"""The failure prediction report (paper Table IV): (window, k) chosen on calibration episodes, reported held out.

`FailureReportConfig` is the configuration `ebvla-failure-report` parses; `write_failure_report` builds the
report from record files and writes `failure_report.md` and `energy_over_time.png` (held-out episodes). For each
step, the (window, k) with the best balanced accuracy is chosen on calibration episodes, with the slope
threshold set by successful reference episodes, then reported unchanged on held-out episodes: across tasks
(all episodes pooled) and within each task that has at least two failed and two successful held-out episodes.
Slope Final, Slope Start and, where the records carry the joint energy's context term, Slope Context, each with the slope's AUROC per step and the lead time of its alarms.

Run at every step, those checks add up their false alarms. The report also gives the deployable alarm: one
check, at the step chosen on calibration (`failure.select_check_step`), with its held-out catches, false alarms
and lead; `--calibrate_to=<checkpoint>` saves it as `failure_alarm.json` for `runtime.EnergyFailureMonitor`.

Episodes are compared at equal elapsed time by default: at step s only the episodes still running at step s
are judged. `--carry_forward=true` judges every episode at every step instead, an ended one carrying its last
energy forward (the paper's fixed episode set, and an artefact: a flat slope then marks a finished episode).
"""

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from ..runtime.failure_alarm import FAILURE_ALARM_FILENAME
from .baselines import every_chunk_has
from .failure import (
    DEFAULT_MULTIPLIERS,
    Episode,
    FailurePredictionResult,
    evaluate_configurations,
    failure_alarm,
    first_alarms,
    format_failure_table,
    select_check_step,
    select_configurations,
    slope_scores,
    successful,
)
from .lead_time import LeadTimeSummary, format_alarms, format_lead_time_table
from .metrics import format_auroc, markdown_table, percent
from .plots import plot_energy_over_time
from .protocol import check_held_out
from .records import load_episodes

logger = logging.getLogger(__name__)

METRIC_TITLES = {"final": "Slope Final", "start": "Slope Start", "context": "Slope Context"}


def slope_metrics(episodes: Sequence[Episode]) -> list[str]:
    """The slopes every chunk of `episodes` has the energy for: Slope Final and Slope Start, and Slope Context
    where the records carry the joint energy's context term."""
    return [m for m in METRIC_TITLES if m != "context" or every_chunk_has(episodes, "context_energy")]


# A task gets its own section (and lead-time row) with at least this many failed and successful episodes.
MIN_PER_CLASS = 2


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
    # Allow `records` that share files or episode seeds with `calibration` or `reference`, or no
    # `calibration` (then `records` is both): the report is labelled IN-SAMPLE. Without it such a report is
    # refused.
    in_sample: bool = False
    # false (default): equal elapsed time, at step s only the episodes still running at step s are judged.
    # true: every episode at every step, an ended one carrying its last energy forward (the paper's fixed
    # episode set; late steps then separate "still running" from "done").
    carry_forward: bool = False
    # Keep only rows with these perturbation names (e.g. '[none]' for vanilla rollouts); default: all.
    perturbation: list[str] | None = None
    # Report steps 1..max_step (step s is the s-th chunk).
    max_step: int = 20
    # Try windows 2..max_window.
    max_window: int = 20
    # Std multipliers k to try.
    multipliers: list[float] = field(default_factory=lambda: list(DEFAULT_MULTIPLIERS))
    # Bootstrap resamples of the AUROC intervals.
    n_bootstrap: int = 1000
    # Seed of the bootstrap generator.
    seed: int = 0
    # The one-check alarm competes only at steps where at least this fraction of the successful calibration
    # episodes is still running (later, "still running" alone predicts failure: a timeout, not a prediction).
    check_min_running: float = 0.5
    # Write failure_alarm.json (the pooled one-check alarm of the metric with the better calibration
    # balanced accuracy) into this pretrained_model folder, for `EnergyFailureMonitor.from_pretrained`.
    calibrate_to: Path | None = None
    # Replace a failure_alarm.json that `calibrate_to` already holds.
    overwrite_alarm: bool = False
    # Folder for failure_report.md and energy_over_time.png.
    output_dir: Path = Path("outputs/failure_report")


@dataclass(frozen=True)
class _Check:
    """The one-check alarm of one metric in one scope: chosen on calibration, run on the held-out episodes."""

    metric: str
    chosen: FailurePredictionResult  # its calibration rates
    held_out: FailurePredictionResult  # its rates on the held-out episodes judged at its step
    auroc: str
    alarms: LeadTimeSummary  # as a monitor over every held-out episode


def _episode_balanced_accuracy(s: LeadTimeSummary) -> float:
    if not s.n_failed or not s.n_successful:
        return math.nan
    return (s.failed_alarmed / s.n_failed + 1 - s.successful_alarmed / s.n_successful) / 2


def _format_checks(checks: dict[str, list[_Check]]) -> str:
    headers = [
        "Scope",
        "Metric",
        "Step",
        "Win.",
        "Std",
        "Bal. Acc. (calibration, judged)",
        "Bal. Acc. held out at the step (judged, failed)",
        "AUROC [95% CI]",
        "Failures alarmed",
        "Successes alarmed",
        "Bal. Acc. as a monitor",
        "Median lead (chunks, env steps)",
    ]
    rows = []
    for scope, scope_checks in checks.items():
        for c in scope_checks:
            s = c.alarms
            rows.append(
                [
                    scope,
                    METRIC_TITLES[c.metric],
                    c.chosen.step,
                    c.chosen.window,
                    f"{c.chosen.multiplier:.2f}",
                    f"{percent(c.chosen.balanced_accuracy, 2)} ({c.chosen.n_episodes})",
                    f"{percent(c.held_out.balanced_accuracy, 2)} ({c.held_out.n_episodes}, {c.held_out.n_failed})",
                    c.auroc,
                    f"{s.failed_alarmed}/{s.n_failed}",
                    f"{s.successful_alarmed}/{s.n_successful}",
                    percent(_episode_balanced_accuracy(s), 2),
                    f"{s.median_lead_chunks:g}, {s.median_lead_env_steps:g}",
                ]
            )
    summaries = [c.alarms for scope_checks in checks.values() for c in scope_checks]
    if any(s.failed_with_onset for s in summaries):  # records with goal distances: the lead to the onset
        headers.append("Alarmed by the onset; median lead to it (chunks)")
        for row, s in zip(rows, summaries, strict=True):
            row.append(
                f"{s.failed_alarmed_before_onset}/{s.failed_with_onset}; {s.median_lead_to_onset_chunks:g}"
            )
    return markdown_table(headers, rows)


def _counts(episodes: Sequence[Episode]) -> tuple[int, int]:
    n_failed = sum(not e[0].success for e in episodes)
    return n_failed, len(episodes) - n_failed


def _scope(
    title: str,
    calibration: Sequence[Episode],
    held_out: Sequence[Episode],
    reference: Sequence[Episode],
    cfg: FailureReportConfig,
    metrics: Sequence[str],
    list_alarms: bool = False,
) -> tuple[str, dict[str, LeadTimeSummary], list[_Check]]:
    """One section: Table IV for each slope of `metrics`, chosen on `calibration`, reported on `held_out`.

    Returns the section, per metric title the lead time of its alarms on `held_out`, and the one-check alarm
    of each metric that has one.
    """
    n_failed, _ = _counts(held_out)
    lines = [
        f"## {title}\n\n{len(calibration)} calibration episodes choose (window, k); {len(held_out)} held-out "
        f"episodes ({n_failed} failed) are reported; {len(successful(reference))} successful reference "
        "episodes set the threshold."
    ]
    if not calibration or not held_out or not successful(reference):
        return lines[0] + "\n\nNot enough episodes to report.\n", {}, []
    steps, windows = range(1, cfg.max_step + 1), range(2, cfg.max_window + 1)
    summaries, checks = {}, []
    for metric in metrics:
        metric_title = METRIC_TITLES[metric]
        chosen = select_configurations(
            calibration, steps, windows, cfg.multipliers, metric, reference, cfg.carry_forward
        )
        results = evaluate_configurations(held_out, chosen, metric, reference, cfg.carry_forward)
        aurocs = [
            format_auroc(
                *slope_scores(held_out, r.step, r.window, metric, cfg.carry_forward),
                cfg.n_bootstrap,
                cfg.seed,
            )
            for r in results
        ]
        alarms = first_alarms(held_out, chosen, reference, metric=metric, carry_forward=cfg.carry_forward)
        summaries[metric_title] = LeadTimeSummary.of(alarms)
        check = select_check_step(chosen, len(successful(calibration)), cfg.check_min_running)
        held_out_at = {r.step: (r, auroc) for r, auroc in zip(results, aurocs, strict=True)}
        if check is not None and check.step in held_out_at:
            check_alarms = first_alarms(
                held_out, [check], reference, metric=metric, carry_forward=cfg.carry_forward
            )
            checks.append(_Check(metric, check, *held_out_at[check.step], LeadTimeSummary.of(check_alarms)))
        lines.append(
            f"### {metric_title}\n\n{format_failure_table(results, chosen_on=chosen, aurocs=aurocs)}"
        )
        if list_alarms:
            lines.append(
                f"First alarm of each failed held-out episode ({metric_title}, each step's chosen "
                f"configuration applied at that step):\n\n{format_alarms(alarms)}"
            )
    return "\n\n".join(lines) + "\n", summaries, checks


def write_failure_report(cfg: FailureReportConfig) -> str:
    """Builds the report, writes it and the energy-over-time figure to `cfg.output_dir`, returns its markdown.

    Raises:
        ValueError: No held-out episodes, or a refused in-sample report (`monitoring.protocol`).
        FileExistsError: `calibrate_to` holds a failure alarm and `overwrite_alarm` is False.
    """
    if cfg.calibrate_to is not None and cfg.carry_forward:
        raise ValueError(
            "`--calibrate_to` saves a run-time alarm, which judges running episodes: it needs "
            "`--carry_forward=false` (equal elapsed time)."
        )
    alarm_file = cfg.calibrate_to / FAILURE_ALARM_FILENAME if cfg.calibrate_to else None
    if alarm_file is not None and alarm_file.exists() and not cfg.overwrite_alarm:
        raise FileExistsError(f"{alarm_file} exists; pass `--overwrite_alarm=true` to replace it.")
    if not cfg.records:
        raise ValueError("Give the held-out episodes to report on with `--records`.")
    records = load_episodes(cfg.records, cfg.perturbation)
    calibration = load_episodes(cfg.calibration, cfg.perturbation) if cfg.calibration else None
    given_reference = load_episodes(cfg.reference, cfg.perturbation) if cfg.reference else None
    # The reference sets the threshold: it is calibration data as much as the episodes that choose (window, k).
    calibration_side = None if calibration is None else {**calibration, **(given_reference or {})}
    in_sample = check_held_out(calibration_side, records, cfg.in_sample)
    held_out = list(records.values())
    if not held_out:
        raise ValueError(
            f"No episodes in `--records` {cfg.records} (perturbation filter {cfg.perturbation})."
        )
    calibration = held_out if calibration is None else list(calibration.values())
    reference = calibration if given_reference is None else list(given_reference.values())
    n_dropped = len(reference) - len(successful(reference))
    reference = successful(reference)

    label = "IN-SAMPLE (calibration and report episodes overlap: optimistic)" if in_sample else "held-out"
    source = "`--reference`" if given_reference is not None else "the calibration episodes"
    header = (
        f"# Energy-based failure prediction ({label})\n\n"
        f"Reference: the {len(reference)} successful episodes of {source} set mean_ref and std_ref"
        f"{f'; {n_dropped} failed episodes were filtered out of it' if n_dropped else ''}. "
        + (
            "Carry forward: episodes that ended before a step carry their last energy forward (every episode "
            "is judged at every step; late steps then separate finished episodes from running ones)."
            if cfg.carry_forward
            else "Equal elapsed time: at step s only the episodes still running at step s are judged (each "
            "labelled by whether it eventually fails), and only those of the reference set the threshold."
        )
        + " Positives are failed episodes. Per step: the paper's Table IV columns, the episodes judged, and "
        "the AUROC [bootstrap 95% interval] of the slope at the chosen window. Lead time: the first step at "
        "which the chosen configuration of that step flags an episode, and how many chunks (and env steps, "
        "between the two chunks' predictions) before its last chunk, the failure or the step cap."
    )
    metrics = slope_metrics([*calibration, *held_out, *reference])
    pooled, pooled_summaries, pooled_checks = _scope(
        "Across tasks (all episodes pooled)", calibration, held_out, reference, cfg, metrics, list_alarms=True
    )
    sections = [header, pooled]
    summaries = {"all tasks": pooled_summaries}
    checks = {"all tasks": pooled_checks}
    tasks = sorted({e[0].task for e in held_out} & {e[0].task for e in calibration})
    if len(tasks) > 1:
        for task in tasks:

            def of_task(episodes: Sequence[Episode], task: str = task) -> list[Episode]:
                return [e for e in episodes if e[0].task == task]

            n_failed, n_successful = _counts(of_task(held_out))
            if min(n_failed, n_successful) < MIN_PER_CLASS:
                sections.append(
                    f"## Within task {task!r}\n\nLeft out: {n_failed} failed and {n_successful} successful "
                    f"held-out episodes (a task needs at least {MIN_PER_CLASS} of each).\n"
                )
                continue
            section, summaries[task], checks[task] = _scope(
                f"Within task {task!r}",
                of_task(calibration),
                of_task(held_out),
                of_task(reference),
                cfg,
                metrics,
            )
            sections.append(section)
    for metric_title in (METRIC_TITLES[m] for m in metrics):
        rows = {scope: s[metric_title] for scope, s in summaries.items() if metric_title in s}
        sections.append(
            f"## Lead time, {metric_title}: pooled and per task\n\nEach task with its own configurations "
            f"(chosen on its calibration episodes); tasks with fewer than {MIN_PER_CLASS} failed or "
            "successful held-out episodes are left out.\n\n" + format_lead_time_table(rows)
        )
    sections.append(
        "## The deployable alarm: one check, at the step chosen on calibration\n\n"
        "Per scope and metric, the step with the best balanced accuracy on the calibration episodes among the "
        f"steps where at least {percent(cfg.check_min_running, 0)} of their successful episodes are still "
        "running (later, still running alone predicts failure) (ties: the earliest), "
        "with that step's (window, k) and reference threshold, checked once per episode. Held out: its rates "
        "on the episodes judged at that step, then as a monitor over every held-out episode (one that ended "
        "before the step is never alarmed): failures and successes alarmed, the balanced accuracy of that, "
        "and the lead before each caught failure's last chunk.\n\n" + _format_checks(checks)
    )
    report = "\n\n".join(sections)

    cfg.output_dir.mkdir(parents=True, exist_ok=True)
    (cfg.output_dir / "failure_report.md").write_text(report, encoding="utf-8")
    plot_energy_over_time(held_out, cfg.output_dir / "energy_over_time.png")
    if cfg.calibrate_to is not None:
        _save_alarm(pooled_checks, reference, cfg)
    return report


def _save_alarm(checks: Sequence[_Check], reference: Sequence[Episode], cfg: FailureReportConfig) -> None:
    """Saves the pooled check of the metric with the better calibration balanced accuracy (ties: Slope Final)."""
    if not checks:
        raise ValueError(
            "No step qualifies for the one-check alarm (too few calibration episodes still running, or one "
            "class missing), so there is nothing to save with `--calibrate_to`."
        )
    best = max(checks, key=lambda c: c.chosen.balanced_accuracy)  # `checks` lists Slope Final first
    alarm = failure_alarm(best.chosen, reference, best.metric)
    path = alarm.save(cfg.calibrate_to, overwrite=cfg.overwrite_alarm)
    logger.info(
        f"Saved the failure alarm ({METRIC_TITLES[best.metric]} at step {alarm.step}, window {alarm.window}, "
        f"T = {alarm.threshold:.4f}) to {path}"
    )
