"""Summaries of evaluation conditions: success, mean energies, and whether the final energy separates them.

A condition is one evaluation (a scene: vanilla, a blanked camera, a perturbation). Its summary holds the
success rate and mean energies of its episodes and one row per episode, each episode's energies being the mean
over its chunks (`scores.episode_scores`). The final energy then ranks each condition against a reference one,
and failed against successful episodes, by AUROC. `monitor_summary` says what the checkpoint's monitor (both its
thresholds, from an OOD report's calibration) makes of the same rollouts. The quickstart prints and writes these
(`pipelines/quickstart.py`).
"""

import math
from collections.abc import Iterable, Mapping, Sequence

from ..runtime.threshold import exceeds
from .metrics import BinaryRates, auroc
from .ood_sections import ALL_CONDITIONS
from .records import Episode, EpisodeKey
from .scores import episode_scores


def mean_or_nan(values: Sequence[float]) -> float:
    """The mean of `values`; NaN when there are none (a condition without failed episodes, say)."""
    return float(sum(values) / len(values)) if len(values) else math.nan


def condition_summary(episodes: Mapping[EpisodeKey, Episode]) -> dict:
    """Success and mean energies of one condition's episodes, with one row per episode in key order.

    Args:
        episodes: The condition's episodes, e.g. `records.group_by_episode` of its `energy_records.jsonl`.

    Returns:
        `n_episodes`, `n_success`, `success_rate`, the mean final energy of successful and of failed episodes
        (`mean_final_energy_success`, `mean_final_energy_failure`), the mean over episodes of their mean
        initial and final energies (`mean_initial_energy`, `mean_final_energy`), and `episodes`: rows of
        task, episode, seed, success, chunks, mean_initial_energy, mean_final_energy. NaN where no episode
        counts.
    """
    episodes = dict(sorted(episodes.items()))
    initial = episode_scores(episodes, "initial_energy")
    final = episode_scores(episodes, "final_energy")
    rows = [
        {
            "task": key.task,
            "episode": key.episode_index,
            "seed": chunks[0].seed,
            "success": chunks[0].success,
            "chunks": len(chunks),
            "mean_initial_energy": float(initial_energy),
            "mean_final_energy": float(final_energy),
        }
        for (key, chunks), initial_energy, final_energy in zip(episodes.items(), initial, final, strict=True)
    ]
    succeeded, failed = final_energy_by_outcome(rows)
    return {
        "n_episodes": len(rows),
        "n_success": len(succeeded),
        "success_rate": len(succeeded) / len(rows) if rows else math.nan,
        "mean_final_energy_success": mean_or_nan(succeeded),
        "mean_final_energy_failure": mean_or_nan(failed),
        "mean_initial_energy": mean_or_nan(initial),
        "mean_final_energy": mean_or_nan(final),
        "episodes": rows,
    }


def final_energy_by_outcome(rows: Iterable[dict]) -> tuple[list[float], list[float]]:
    """The mean final energies of the successful and of the failed episode rows (`condition_summary`'s)."""
    rows = list(rows)
    return (
        [row["mean_final_energy"] for row in rows if row["success"]],
        [row["mean_final_energy"] for row in rows if not row["success"]],
    )


def pooled_episodes(conditions: Mapping[str, dict]) -> list[dict]:
    """The episode rows of every condition summary, in condition order."""
    return [row for condition in conditions.values() for row in condition["episodes"]]


def energy_aurocs(conditions: Mapping[str, dict], reference: str) -> dict[str, float]:
    """AUROC of the episodes' mean final energy: each condition against `reference`, failed against succeeded.

    Threshold-free, so nothing is fitted on the episodes it is reported on; with 10 episodes a side its 95%
    interval is wide (about +-0.2), so it says whether the energy reacts, not how well it detects.

    Args:
        conditions: {condition name: `condition_summary`}.
        reference: The condition the others are ranked against (its episodes are the negatives), e.g. vanilla.

    Returns:
        {condition name: AUROC} for every condition but `reference`, and `failed_vs_successful` over the
        episodes of all conditions (failed episodes are the positives). NaN where a side has no episode.
    """

    def final_energies(condition: dict) -> list[float]:
        return [row["mean_final_energy"] for row in condition["episodes"]]

    aurocs = {
        name: auroc(final_energies(conditions[reference]), final_energies(condition))
        for name, condition in conditions.items()
        if name != reference
    }
    aurocs["failed_vs_successful"] = auroc(*final_energy_by_outcome(pooled_episodes(conditions)))
    return aurocs


def monitor_summary(scored) -> dict:
    """The monitor's two checks on an OOD report's held-out rollouts (`ood_report.OODScores`), at the thresholds
    saved with the checkpoint.

    `unfamiliar`: per shift, the OOD score's AUROC against the held-out vanilla rollouts over the first N chunks
    and over whole episodes, and the rollouts alarmed at the saved T as the run-time monitor decides
    (`OODScores.saved_scores`, within the first chunks: vanilla's too). `failing` (a checkpoint with a failure check): failed against
    successful rollouts over all of them, first N chunks: AUROC, and the alarms at its T.
    """
    n = scored.failure_chunks
    ood, first, whole = scored.saved_score, scored.at(n), scored.at(None)
    ood_chunks = scored.cfg.table_iii_first_chunks or None
    threshold = scored.saved_fit.threshold

    def alarmed(scores) -> list[int]:
        return [int(exceeds(scores, threshold).sum()), len(scores)]

    unfamiliar = {"vanilla": {"alarmed": alarmed(scored.saved_scores(scored.vanilla_chunks))}}
    for condition, scores in whole.positives.items():
        if condition != ALL_CONDITIONS:
            unfamiliar[condition] = {
                "auroc_first_chunks": auroc(first.negatives[ood], first.positives[condition][ood]),
                "auroc": auroc(whole.negatives[ood], scores[ood]),
                "alarmed": alarmed(scored.saved_scores(scored.condition_chunks[condition])),
            }
    summary = {
        "score": ood,
        "n_calibration": len(scored.calibration_set),
        "chunks": n,
        "ood_chunks": ood_chunks,
        "unfamiliar": unfamiliar,
    }
    if scored.failure_score != "none":
        name = scored.failure_score
        scores, failed = scored.held_out(name, n), scored.held_out_failed()
        rates = BinaryRates.from_scores(scores[~failed], scores[failed], scored.fit(name, n).threshold)
        summary["failing"] = {
            "score": name,
            "auroc": auroc(scores[~failed], scores[failed]),
            "n_failed": int(failed.sum()),
            "n_successful": int((~failed).sum()),
            "failed_alarmed": rates.tp,
            "successful_alarmed": rates.fp,
        }
    return summary
