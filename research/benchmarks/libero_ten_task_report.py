"""The ten-task check of issue 52: success and Table III of one evaluated run over all ten LIBERO-Object tasks, the
seven the recipe never saw and the three it was chosen on, each against the issue's targets.

Written on 2026-11-28, while the chosen run (`ebvla_joint_fast_cpu`) trained on the ten tasks and before any of
its rollouts existed (research/docs/libero_recipe_rule.md, "What the ten-task check reports"). It reads the
records `libero_pipeline.py eval` writes, one folder per condition and task (`eval/<run>/<condition>/task<i>`):
`vanilla_calib` (initial states 0-9), `vanilla_heldout` (states 10-29), `vanilla_fresh` (placements from seeds no
recording used) and one folder per shift.

For each group of tasks, over each rollout's first 3 chunks, with the threshold T = mu_v + 1 sigma_v of the
calibration rollouts of all ten tasks (the one monitor a user ships, whatever task it then runs):
- success on the fixed initial states and on fresh placements, with Wilson 95 % intervals;
- per score, the AUROC of held-out vanilla against all shifts (bootstrap 95 % interval) and against each shift,
  the balanced accuracy at T, and the alarm rate at T on held-out vanilla and on fresh placements;
- the issue's targets for the run's saved monitor score, each met or missed with its number.

With `--failure_choice` (the JSON of `failure_check_choice.py`, chosen on the calibration rollouts alone; added on
2026-11-29 for D, before its report), each group also gets Table IV at equal elapsed time: the monitor's failure
check and the baselines (`failure_check.failure_check_decisions`) on the group's held-out vanilla rollouts (fixed
states 10-29 and fresh placements, as pre-registered in research/docs/libero_runs.md, "D's failure check"), with
each caught failure's lead to its onset and to the episode's end, and the issue's two Table IV targets.

With `--threshold_rule=conformal` (added on 2026-11-29 for D, research/docs/libero_runs.md "D's threshold rule") T is
the conformal quantile of the calibration rollouts' scores at alpha = 5 %, the failure check keeping Eq. 5; the
confirmation rollouts (`vanilla_confirm`, fixed states 30-49), where evaluated, get their own alarm rate and balanced
accuracy at T against all shifts, with the two targets that rule was fixed for.

    python research/benchmarks/libero_ten_task_report.py --results=research/results/libero_object10 \\
        --run=ebvla_joint_fast_cpu --output_dir=research/results/libero_object10/reports/ebvla_joint_fast_cpu/ten_task
"""

import argparse
import json
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import research_scores  # noqa: F401  (registers context_energy_two_sided and the other research scores)
from libero_recipe_choice import at_threshold, monitor_score, rollout_successes

from lerobot_policy_ebvla.monitoring.failure_check import failure_check_decisions, failure_onsets
from lerobot_policy_ebvla.monitoring.metrics import (
    BinaryRates,
    auroc,
    bootstrap_auroc_interval,
    wilson_interval,
)
from lerobot_policy_ebvla.monitoring.ood_report import (
    ALL_CONDITIONS,
    OODReportConfig,
    OODScores,
    score_ood_report,
)

TASK_GROUPS = {
    "all ten": (0, 1, 2, 3, 4, 5, 6, 7, 8, 9),
    "seven untouched": (0, 1, 4, 5, 6, 7, 8),
    "three of the choice": (2, 3, 9),
}
CALIBRATION, HELDOUT, FRESH = "vanilla_calib", "vanilla_heldout", "vanilla_fresh"
CONFIRM = "vanilla_confirm"
FIRST_CHUNKS = 3
# Beside the run's saved monitor score: the two-sided E_c named by the choice as the light miss's next candidate
# (pre-registered here, looked at on tasks 2, 3 and 9 only), the feature baselines, and the paper's energy.
BESIDE = ("context_energy_two_sided", "context_knn", "context_distance", "final_energy")
# The Table III targets for the monitor.
MIN_BALANCED_ACCURACY = 0.90
MIN_AUROC = 0.5
MIN_AUROC_WHERE_SUCCESS_FALLS = 0.85
SUCCESS_DROP = 0.20
MAX_ALARM_RATE = 0.10
# Its Table IV targets, on held-out vanilla rollouts.
MIN_FAILURE_BALANCED_ACCURACY = 0.80
FAILURE_BASELINE = "chunk_context_nn"
# Its success targets, over all ten tasks.
MIN_SUCCESS_FIXED_STATES = 0.90
MIN_SUCCESS_FRESH = 0.80


@dataclass
class Rate:
    wins: int
    n: int

    @property
    def value(self) -> float:
        return self.wins / self.n if self.n else float("nan")

    def text(self) -> str:
        low, high = wilson_interval(self.wins, self.n)
        return f"{self.wins}/{self.n} = {100 * self.value:.1f}% [{100 * low:.1f}, {100 * high:.1f}]"


@dataclass
class ScoreRow:
    score: str
    pooled_auroc: float
    pooled_interval: tuple[float, float]
    auroc_per_condition: dict[str, float]
    balanced_accuracy: float
    heldout_alarm_rate: float
    fresh_alarm_rate: float | None
    # Added on 2026-11-28 after the rollouts, as context beside the pre-registered columns (no target reads them):
    # what a user gets at T under each shift, and the pooled AUROC over whole episodes beside the first chunks'.
    alarm_rate_per_condition: dict[str, float] = field(default_factory=dict)
    whole_episode_auroc: float = float("nan")
    whole_episode_interval: tuple[float, float] = (float("nan"), float("nan"))
    # The confirmation rollouts (fixed states 30-49), where evaluated: alarms at T, and the balanced accuracy of
    # their alarm rate against all shifts' catch rate.
    confirm_alarm_rate: float | None = None
    confirm_balanced_accuracy: float | None = None


@dataclass
class FailureRow:
    """One row of Table IV at equal elapsed time: a score's decision over the first N chunks at its calibration T,
    failed (positives) against successful (negatives) held-out vanilla rollouts."""

    score: str
    failed_alarmed: int
    failed: int
    successful_alarmed: int
    successful: int
    balanced_accuracy: float
    auroc: float | None  # None: the monitor's decision combined from two thresholds
    auroc_interval: tuple[float, float] | None
    # Over the caught failures: how many were caught at or before their onset, and the median chunks from the
    # alarm (chunk N) to the onset and to the episode's last chunk.
    caught_before_onset: int
    median_lead_to_onset: float
    median_lead_to_end: float


@dataclass
class GroupReport:
    group: str
    tasks: tuple[int, ...]
    success: dict[str, Rate]
    success_per_condition: dict[str, Rate]
    rows: list[ScoreRow] = field(default_factory=list)
    targets: list[tuple[str, str, bool]] = field(default_factory=list)
    failure_rows: list[FailureRow] = field(default_factory=list)
    # Table IV on the confirmation rollouts (fixed states 30-49), where evaluated.
    confirm_failure_rows: list[FailureRow] = field(default_factory=list)


def task_folders(run_dir: Path, condition: str, tasks: tuple[int, ...]) -> list[Path]:
    return [run_dir / condition / f"task{t}" for t in tasks if (run_dir / condition / f"task{t}").is_dir()]


def success(folders: list[Path]) -> Rate:
    return Rate(*rollout_successes(folders))


def shift_conditions(run_dir: Path) -> list[str]:
    """The shift folders of a run, in the pipeline's names ("pose5", "noise3", ...)."""
    return sorted(p.name for p in run_dir.iterdir() if p.is_dir() and not p.name.startswith("vanilla"))


def condition_name(folder: str) -> str:
    """The ood report's name of a shift folder: "pose5" -> "pose 5", "light_dim5" -> "light_dim 5"."""
    stem = folder.rstrip("0123456789")
    return f"{stem} {folder[len(stem) :]}"


def failure_options(choice: Path | None) -> dict:
    """The `OODReportConfig` fields of the failure check `failure_check_choice.py` chose (none: no Table IV)."""
    if choice is None:
        return {}
    options = dict(
        o.removeprefix("--").split("=", 1) for o in json.loads(choice.read_text())["report_options"]
    )
    return {
        "failure_score": options["failure_score"],
        "failure_chunks": int(options["failure_chunks"]),
        "failure_reference": options["failure_reference"],
    }


def score_all_tasks(
    run_dir: Path,
    scores: list[str],
    output_dir: Path,
    failure_check: dict | None = None,
    threshold_rule: str = "mean_std",
) -> OODScores:
    """Every score of the held-out and fresh vanilla rollouts and of every shift, over all the evaluated tasks, with
    T fitted on the calibration rollouts of all ten tasks. Scored once: each group's rows come from its own rollouts
    in it (`held_out_of`), so the calibration's leave-one-out fits, most of the report's time, are made once."""
    tasks = TASK_GROUPS["all ten"]
    cfg = OODReportConfig(
        calibration=[str(p) for p in task_folders(run_dir, CALIBRATION, tasks)],
        vanilla=[str(p) for c in (HELDOUT, FRESH, CONFIRM) for p in task_folders(run_dir, c, tasks)],
        ood=[str(p) for c in shift_conditions(run_dir) for p in task_folders(run_dir, c, tasks)],
        score=scores[0],
        output_dir=output_dir,
        first_chunks=[FIRST_CHUNKS],
        threshold_rule=threshold_rule,
        failure_threshold_rule="mean_std",
        **(failure_check or {}),
    )
    return score_ood_report(cfg)


def held_out_of(scored: OODScores, tasks: tuple[int, ...], vanilla: tuple[str, ...]) -> OODScores:
    """`scored` with only the rollouts of `tasks` (their records' `task<i>` folders), its vanilla ones those of the
    `vanilla` condition folders, in the same order: the scores a report of those folders alone gives, with the
    same calibration."""
    folders = {f"task{t}" for t in tasks}

    def keep(episodes: dict, vanilla_only: bool = False) -> dict:
        def kept(record_file: str) -> bool:
            task = Path(record_file).parent
            return task.name in folders and (not vanilla_only or task.parent.name in vanilla)

        return {key: value for key, value in episodes.items() if kept(key[0])}

    conditions = {c: kept for c, episodes in scored.conditions.items() if (kept := keep(episodes))}
    return replace(
        scored,
        vanilla=keep(scored.vanilla, vanilla_only=True),
        ood=keep(scored.ood),
        conditions=conditions,
        vanilla_chunks={
            name: keep(chunks, vanilla_only=True) for name, chunks in scored.vanilla_chunks.items()
        },
        condition_chunks={
            c: {name: keep(chunks) for name, chunks in scored.condition_chunks[c].items()} for c in conditions
        },
    )


def score_rows(
    heldout: OODScores, fresh: OODScores, confirm: OODScores, scores: list[str]
) -> tuple[list[ScoreRow], list[str]]:
    """Each score's Table III row for one group of tasks (`held_out_of` the held-out, the fresh and the confirmation
    rollouts), and the scores the records could not give. Only the vanilla rollouts' scores are read from `fresh`
    and `confirm`: the threshold stays the calibration's."""
    fresh_sets = fresh.at(FIRST_CHUNKS) if fresh.vanilla else None
    confirm_sets = confirm.at(FIRST_CHUNKS) if confirm.vanilla else None
    sets = heldout.at(FIRST_CHUNKS)
    whole = heldout.at(None)
    rows, missing = [], []
    for score in scores:
        if score not in sets.negatives:
            missing.append(score)
            continue
        row = at_threshold(heldout, score, FIRST_CHUNKS)
        negatives, positives = sets.negatives[score], sets.positives[ALL_CONDITIONS][score]
        confirm = (
            None
            if confirm_sets is None
            else BinaryRates.from_scores(confirm_sets.negatives[score], positives, row.threshold)
        )
        whole_negatives, whole_positives = whole.negatives[score], whole.positives[ALL_CONDITIONS][score]
        rows.append(
            ScoreRow(
                score=score,
                pooled_auroc=float(auroc(negatives, positives)),
                pooled_interval=bootstrap_auroc_interval(negatives, positives),
                auroc_per_condition=row.auroc_per_condition,
                balanced_accuracy=row.balanced_accuracy,
                heldout_alarm_rate=row.heldout_alarm_rate,
                fresh_alarm_rate=None
                if fresh_sets is None
                else float(np.mean(fresh_sets.negatives[score] > row.threshold)),
                alarm_rate_per_condition={
                    condition: float(np.mean(shifted_scores[score] > row.threshold))
                    for condition, shifted_scores in sets.positives.items()
                    if condition != ALL_CONDITIONS
                },
                whole_episode_auroc=float(auroc(whole_negatives, whole_positives)),
                whole_episode_interval=bootstrap_auroc_interval(whole_negatives, whole_positives),
                confirm_alarm_rate=None if confirm is None else confirm.fpr,
                confirm_balanced_accuracy=None if confirm is None else confirm.balanced_accuracy,
            )
        )
    return rows, missing


def failure_rows(scored: OODScores) -> list[FailureRow]:
    """Table IV at equal elapsed time on `scored`'s held-out vanilla rollouts: the monitor's failure check and each
    baseline at its calibration T over the first N chunks (`failure_check_decisions`)."""
    n_vanilla, n = len(scored.vanilla), scored.failure_chunks
    failed = scored.held_out_failed()[:n_vanilla]
    onsets = failure_onsets(scored)[:n_vanilla]
    lengths = np.array([len(episode) for episode in scored.vanilla.values()], dtype=float)
    rows = []
    for label, (scores, flags) in failure_check_decisions(scored).items():
        flags = flags[:n_vanilla]
        rates = BinaryRates.from_flags(flags[~failed], flags[failed])
        caught = failed & flags
        to_onset, to_end = onsets[caught] - n, lengths[caught] - n
        if scores is not None:
            scores = scores[:n_vanilla]
        rows.append(
            FailureRow(
                score=label,
                failed_alarmed=rates.tp,
                failed=rates.n_positive,
                successful_alarmed=rates.fp,
                successful=rates.fp + rates.tn,
                balanced_accuracy=rates.balanced_accuracy,
                auroc=None if scores is None else float(auroc(scores[~failed], scores[failed])),
                auroc_interval=None
                if scores is None
                else bootstrap_auroc_interval(scores[~failed], scores[failed]),
                caught_before_onset=int(np.sum(to_onset >= 0)),
                median_lead_to_onset=float(np.median(to_onset)) if to_onset.size else float("nan"),
                median_lead_to_end=float(np.median(to_end)) if to_end.size else float("nan"),
            )
        )
    return rows


def failure_targets(
    rows: list[FailureRow], failure_score: str, where: str = "held out"
) -> list[tuple[str, str, bool]]:
    """The issue's Table IV targets for the monitor's failure check, on the rollouts `where` names."""
    by_score = {row.score: row for row in rows}
    check = by_score[failure_score]
    targets = [
        (
            f"Table IV: balanced accuracy >= {100 * MIN_FAILURE_BALANCED_ACCURACY:.0f}% {where}",
            f"{100 * check.balanced_accuracy:.1f}%",
            check.balanced_accuracy >= MIN_FAILURE_BALANCED_ACCURACY,
        )
    ]
    if FAILURE_BASELINE in by_score:
        baseline, (low, high) = by_score[FAILURE_BASELINE], check.auroc_interval
        targets.append(
            (
                f"Table IV: not below {FAILURE_BASELINE} outside its interval"
                + ("" if where == "held out" else f" ({where})"),
                f"{check.auroc:.3f} [{low:.3f}, {high:.3f}] against {baseline.auroc:.3f}",
                baseline.auroc <= high,
            )
        )
    return targets


def check_targets(report: GroupReport, monitor: str) -> list[tuple[str, str, bool]]:
    """The issue's targets for the monitor's row, each as (target, what was measured, met)."""
    rows = {row.score: row for row in report.rows}
    row = rows[monitor]
    vanilla = report.success["fixed initial states"].value
    worst = min(row.auroc_per_condition, key=row.auroc_per_condition.get)
    falling = [c for c, rate in report.success_per_condition.items() if vanilla - rate.value >= SUCCESS_DROP]
    worst_falling = min(falling, key=row.auroc_per_condition.get) if falling else None
    targets = [
        (
            f"balanced accuracy at T >= {100 * MIN_BALANCED_ACCURACY:.0f}%",
            f"{100 * row.balanced_accuracy:.1f}%",
            row.balanced_accuracy >= MIN_BALANCED_ACCURACY,
        ),
        (
            f"AUROC >= {MIN_AUROC} under every condition",
            f"lowest {row.auroc_per_condition[worst]:.3f} ({worst})",
            row.auroc_per_condition[worst] >= MIN_AUROC,
        ),
        (
            f"AUROC >= {MIN_AUROC_WHERE_SUCCESS_FALLS} where success falls {100 * SUCCESS_DROP:.0f}+ points",
            "no such condition"
            if worst_falling is None
            else f"lowest {row.auroc_per_condition[worst_falling]:.3f} ({worst_falling}) of {len(falling)}",
            worst_falling is None or row.auroc_per_condition[worst_falling] >= MIN_AUROC_WHERE_SUCCESS_FALLS,
        ),
        (
            f"alarms on held-out vanilla <= {100 * MAX_ALARM_RATE:.0f}%",
            f"{100 * row.heldout_alarm_rate:.1f}%",
            row.heldout_alarm_rate <= MAX_ALARM_RATE,
        ),
    ]
    if row.confirm_alarm_rate is not None:
        targets += [
            (
                f"confirmation (states 30-49): balanced accuracy at T >= {100 * MIN_BALANCED_ACCURACY:.0f}%",
                f"{100 * row.confirm_balanced_accuracy:.1f}%",
                row.confirm_balanced_accuracy >= MIN_BALANCED_ACCURACY,
            ),
            (
                f"confirmation (states 30-49): alarms <= {100 * MAX_ALARM_RATE:.0f}%",
                f"{100 * row.confirm_alarm_rate:.1f}%",
                row.confirm_alarm_rate <= MAX_ALARM_RATE,
            ),
        ]
    if "context_knn" in rows:
        knn = rows["context_knn"]
        targets.append(
            (
                "not below context_knn outside its interval",
                f"{row.pooled_auroc:.3f} [{row.pooled_interval[0]:.3f}, {row.pooled_interval[1]:.3f}] "
                f"against {knn.pooled_auroc:.3f}",
                knn.pooled_auroc <= row.pooled_interval[1],
            )
        )
    if report.group == "all ten":
        fixed, fresh = report.success["fixed initial states"], report.success.get("fresh placements")
        targets.append(
            (
                f"success on the fixed initial states >= {100 * MIN_SUCCESS_FIXED_STATES:.0f}%",
                fixed.text(),
                fixed.value >= MIN_SUCCESS_FIXED_STATES,
            )
        )
        if fresh is not None:
            targets.append(
                (
                    f"success on fresh placements >= {100 * MIN_SUCCESS_FRESH:.0f}%",
                    fresh.text(),
                    fresh.value >= MIN_SUCCESS_FRESH,
                )
            )
    return targets


def group_report(
    run_dir: Path, group: str, scores: list[str], scored: OODScores, with_failure: bool = False
) -> GroupReport:
    # The group's tasks that were evaluated: all of them once the queue is done.
    tasks = tuple(t for t in TASK_GROUPS[group] if (run_dir / HELDOUT / f"task{t}").is_dir())
    rates = {"fixed initial states": success(task_folders(run_dir, HELDOUT, tasks))}
    if task_folders(run_dir, FRESH, tasks):
        rates["fresh placements"] = success(task_folders(run_dir, FRESH, tasks))
    if task_folders(run_dir, CONFIRM, tasks):
        rates["confirmation (states 30-49)"] = success(task_folders(run_dir, CONFIRM, tasks))
    rates["calibration (states 0-9)"] = success(task_folders(run_dir, CALIBRATION, tasks))
    per_condition = {
        condition_name(c): success(task_folders(run_dir, c, tasks)) for c in shift_conditions(run_dir)
    }
    report = GroupReport(group, tasks, rates, per_condition)
    report.rows, missing = score_rows(
        *(held_out_of(scored, tasks, (vanilla,)) for vanilla in (HELDOUT, FRESH, CONFIRM)), scores
    )
    if missing:
        print(f"{group}: the records give no {missing}")
    report.targets = check_targets(report, scores[0])
    if with_failure:
        report.failure_rows = failure_rows(held_out_of(scored, tasks, (HELDOUT, FRESH)))
        report.targets += failure_targets(report.failure_rows, scored.failure_score)
        if task_folders(run_dir, CONFIRM, tasks):
            report.confirm_failure_rows = failure_rows(held_out_of(scored, tasks, (CONFIRM,)))
            report.targets += failure_targets(
                report.confirm_failure_rows, scored.failure_score, "on the confirmation (states 30-49)"
            )
    return report


def failure_markdown(
    rows: list[FailureRow],
    failure_score: str,
    chunks: int,
    rollouts: str = "states 10-29 and fresh placements",
) -> list[str]:
    lines = [
        "",
        f"Table IV at equal elapsed time: each score over the first {chunks} chunks at its calibration T (the "
        f"monitor's failure check: `{failure_score}`), failed against successful held-out vanilla rollouts "
        f"({rollouts}). Leads: chunks from the alarm at chunk "
        f"{chunks} to the caught failure's onset (its object's last progress toward the goal; negative once it had "
        "begun) and to the episode's last chunk.",
        "",
        "| Score | Failed alarmed | Successful alarmed | Bal. acc. | AUROC [95% CI] | Caught at or before onset "
        "| Median lead to onset / to end |",
        "|---|---:|---:|---:|---|---:|---|",
    ]
    for row in rows:
        interval = (
            "-"
            if row.auroc is None
            else f"{row.auroc:.3f} [{row.auroc_interval[0]:.3f}, {row.auroc_interval[1]:.3f}]"
        )
        lines.append(
            f"| `{row.score}` | {row.failed_alarmed}/{row.failed} | {row.successful_alarmed}/{row.successful} "
            f"| {100 * row.balanced_accuracy:.1f}% | {interval} | {row.caught_before_onset}/{row.failed_alarmed} "
            f"| {row.median_lead_to_onset:+.0f} / {row.median_lead_to_end:+.0f} |"
        )
    return lines


def confirmation_markdown(report: GroupReport) -> list[str]:
    """The confirmation rollouts' rows, where they were evaluated."""
    if not report.rows or report.rows[0].confirm_alarm_rate is None:
        return []
    lines = [
        "",
        "| Score, at the same T | Alarms: confirmation vanilla (states 30-49) | Bal. acc.: states 30-49 against all shifts |",
        "|---|---:|---:|",
    ]
    return lines + [
        f"| `{r.score}` | {100 * r.confirm_alarm_rate:.1f}% | {100 * r.confirm_balanced_accuracy:.1f}% |"
        for r in report.rows
    ]


def markdown(
    run: str, reports: list[GroupReport], failure_check: dict | None = None, threshold_rule: str = "mean_std"
) -> str:
    lines = [f"# The ten-task check of `{run}`", ""]
    rule = (
        "the conformal quantile at alpha = 5 % of the calibration rollouts of all ten tasks (the failure check: "
        "mu_v + 1 sigma_v)"
        if threshold_rule == "conformal"
        else "mu_v + 1 sigma_v on the calibration rollouts of all ten tasks"
    )
    lines.append(
        f"First {FIRST_CHUNKS} chunks; T = {rule}; AUROCs of "
        "held-out vanilla (states 10-29) against the shifts, intervals bootstrap 95 %; success intervals Wilson 95 %."
    )
    for report in reports:
        lines += ["", f"## {report.group}: tasks {', '.join(map(str, report.tasks))}", ""]
        lines += ["| Rollouts | Success |", "|---|---|"]
        lines += [f"| {name} | {rate.text()} |" for name, rate in report.success.items()]
        lines += [f"| {name} | {rate.text()} |" for name, rate in report.success_per_condition.items()]
        lines += [
            "",
            "| Score | AUROC, all shifts | Bal. acc. at T | Alarms: held-out vanilla | Alarms: fresh | Worst condition |",
            "|---|---|---:|---:|---:|---|",
        ]
        for row in report.rows:
            worst = min(row.auroc_per_condition, key=row.auroc_per_condition.get)
            fresh = "-" if row.fresh_alarm_rate is None else f"{100 * row.fresh_alarm_rate:.1f}%"
            lines.append(
                f"| `{row.score}` | {row.pooled_auroc:.3f} [{row.pooled_interval[0]:.3f}, {row.pooled_interval[1]:.3f}] "
                f"| {100 * row.balanced_accuracy:.1f}% | {100 * row.heldout_alarm_rate:.1f}% | {fresh} "
                f"| {worst} {row.auroc_per_condition[worst]:.3f} |"
            )
        lines += confirmation_markdown(report)
        conditions = list(report.rows[0].auroc_per_condition) if report.rows else []
        lines += ["", "| Condition | " + " | ".join(f"`{r.score}`" for r in report.rows) + " |"]
        lines += ["|---|" + "---:|" * len(report.rows)]
        lines += [
            f"| {c} | " + " | ".join(f"{r.auroc_per_condition[c]:.3f}" for r in report.rows) + " |"
            for c in conditions
        ]
        lines += [
            "",
            "Added after the rollouts (no target reads them): each score's pooled AUROC over whole episodes beside "
            "its first chunks', and the rate of rollouts alarmed at T (first 3 chunks) under each shift.",
            "",
            "| Score | AUROC, all shifts, first 3 chunks | whole episodes |",
            "|---|---|---|",
        ]
        lines += [
            f"| `{r.score}` | {r.pooled_auroc:.3f} | {r.whole_episode_auroc:.3f} "
            f"[{r.whole_episode_interval[0]:.3f}, {r.whole_episode_interval[1]:.3f}] |"
            for r in report.rows
        ]
        lines += ["", "| Alarmed at T | " + " | ".join(f"`{r.score}`" for r in report.rows) + " |"]
        lines += ["|---|" + "---:|" * len(report.rows)]
        lines += [
            f"| {c} | "
            + " | ".join(f"{100 * r.alarm_rate_per_condition[c]:.0f}%" for r in report.rows)
            + " |"
            for c in conditions
        ]
        if report.failure_rows:
            check = (failure_check["failure_score"], failure_check["failure_chunks"])
            lines += failure_markdown(report.failure_rows, *check)
            if report.confirm_failure_rows:
                lines += failure_markdown(
                    report.confirm_failure_rows, *check, "the confirmation: states 30-49"
                )
        lines += ["", "| Target (the monitor's score) | Measured | Met |", "|---|---|---|"]
        lines += [f"| {t} | {m} | {'yes' if ok else '**no**'} |" for t, m, ok in report.targets]
    return "\n".join(lines) + "\n"


def saved_json(reports: list[GroupReport], failure_check: dict | None) -> list[dict]:
    """The reports as JSON. Without a failure check or confirmation rollouts it keeps the shape of the reports
    written before Table IV and the confirmation were added."""
    saved = [
        {
            k: v
            for k, v in asdict(r).items()
            if (k != "failure_rows" or failure_check) and (k != "confirm_failure_rows" or v)
        }
        for r in reports
    ]
    for report in saved:
        for row in report["rows"]:
            if row["confirm_alarm_rate"] is None:
                del row["confirm_alarm_rate"], row["confirm_balanced_accuracy"]
    return saved


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--results", type=Path, required=True, help="a work folder or saved results of the run"
    )
    parser.add_argument("--run", required=True)
    parser.add_argument("--output_dir", type=Path, default=Path("outputs/libero_ten_task_report"))
    parser.add_argument(
        "--failure_choice",
        type=Path,
        default=None,
        help="failure_check_choice.py's JSON: adds Table IV with the failure check it chose",
    )
    parser.add_argument(
        "--threshold_rule",
        choices=("mean_std", "conformal"),
        default="mean_std",
        help="the OOD threshold T: mu_v + 1 sigma_v, or the conformal quantile at alpha = 5 %%",
    )
    parser.add_argument(
        "--scores",
        nargs="+",
        default=None,
        help="the scores to report, the one the targets judge first (default: the run's saved monitor score, then "
        "the baselines beside it)",
    )
    args = parser.parse_args(argv)
    run_dir = args.results / "eval" / args.run
    if not (run_dir / HELDOUT).is_dir():
        raise SystemExit(
            f"No held-out rollouts of {args.run} in {run_dir}: run `libero_pipeline.py eval` first."
        )
    monitor = monitor_score(args.results, args.run)
    scores = args.scores or [monitor, *(s for s in BESIDE if s != monitor)]
    # A group none of whose tasks was evaluated (a partial queue, or the three-task runs) is left out, named.
    evaluated = [g for g, tasks in TASK_GROUPS.items() if task_folders(run_dir, HELDOUT, tasks)]
    for group in TASK_GROUPS.keys() - set(evaluated):
        print(f"{group}: no held-out rollouts of its tasks yet, left out")
    failure_check = failure_options(args.failure_choice)
    scored = score_all_tasks(run_dir, scores, args.output_dir, failure_check, args.threshold_rule)
    reports = [group_report(run_dir, group, scores, scored, bool(failure_check)) for group in evaluated]
    args.output_dir.mkdir(parents=True, exist_ok=True)
    text = markdown(args.run, reports, failure_check, args.threshold_rule)
    (args.output_dir / "ten_task_report.md").write_text(text)
    (args.output_dir / "ten_task_report.json").write_text(
        json.dumps(saved_json(reports, failure_check), indent=1, default=str)
    )
    print(text)


if __name__ == "__main__":
    main()
