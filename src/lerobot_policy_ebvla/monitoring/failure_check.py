"""The monitor's failure check in the OOD report: Table IV at equal elapsed time, beside the feature baselines.

`EnergyMonitor`'s second threshold (`runtime.FailureCalibration`) decides on a rollout's first N chunks against the
vanilla calibration rollouts' first N chunks. The OOD report already holds every score of those chunks
(`ood_report.OODScores`); here each score becomes the same decision at its own calibration threshold, the monitor's
two checks are combined as it combines them at run time, and the chunk-context nearest-neighbour baseline is added.
"""

import numpy as np

from ..runtime.calibration import OODCalibration
from ..runtime.threshold import exceeds
from .baselines import FEATURE_SCORES, chunk_context_nn
from .lead_time import failure_onset
from .metrics import BinaryRates, markdown_table, percent
from .ood_sections import auroc_interval


def failure_check_section(scored) -> str:
    """The section of an OOD report's scores (`ood_report.OODScores`): the failure check and each baseline at its
    calibration threshold over the first N chunks, and the monitor's two checks together."""
    failed = scored.held_out_failed()
    # Every set starts with the held-out vanilla rollouts: each takes as many rollouts as it has labels.
    labels = {
        "held-out vanilla rollouts": failed[: len(scored.vanilla)],
        "held-out vanilla and perturbed rollouts together": failed,
    }
    rows = {
        label: {
            title: (None if scores is None else scores[: len(set_labels)], flags[: len(set_labels)])
            for title, set_labels in labels.items()
        }
        for label, (scores, flags) in failure_check_decisions(scored).items()
    }
    return format_failure_check(
        rows, labels, scored.failure_chunks, scored.failure_score, scored.cfg, failure_onsets(scored)
    )


def failure_check_decisions(scored) -> dict[str, tuple[np.ndarray | None, np.ndarray]]:
    """By row label, each held-out rollout's score over its first N chunks (None for the monitor's combined
    decision) and whether it is alarmed at the row's calibration threshold, in `held_out_failed`'s order."""
    n, vanilla, ood = scored.failure_chunks, scored.vanilla, scored.ood

    def alarms(name: str) -> np.ndarray:
        return exceeds(scored.held_out(name, n), scored.fit_failure(name, n).threshold)

    failure, ood_score = scored.failure_score, scored.saved_score
    failure_alarms = alarms(failure)
    rows = {
        "monitor (either check)": (
            None,
            exceeds(scored.saved_held_out(), scored.saved_fit.threshold) | failure_alarms,
        )
    }
    for name in dict.fromkeys([failure, ood_score, "final_energy", *FEATURE_SCORES]):
        if name in scored.names:
            rows[name] = (scored.held_out(name, n), failure_alarms if name == failure else alarms(name))
    if scored.reference.features:
        calibration = chunk_context_nn(scored.calibration_set, scored.calibration_set, n - 1)
        cfg = scored.cfg
        threshold = OODCalibration.fit(
            calibration[scored.failure_reference_mask()],
            k=cfg.k,
            false_alarm_rate=cfg.false_alarm_rate,
            rule=cfg.failure_rule,
        ).threshold
        scores = chunk_context_nn(scored.calibration_set, {**vanilla, **ood}, n - 1)
        rows["chunk_context_nn"] = (scores, exceeds(scores, threshold))
    return rows


def failure_onsets(scored) -> np.ndarray:
    """Each held-out rollout's failure onset (`lead_time.failure_onset`, 1-based step; NaN where the records carry
    no goal distances), in `held_out_failed`'s order."""
    episodes = [*scored.vanilla.values(), *scored.ood.values()]
    return np.array([np.nan if (o := failure_onset(e)) is None else o for e in episodes], dtype=float)


# What sets T of each row, by `OODReportConfig.failure_reference`.
_REFERENCE_TEXT = {
    "vanilla": "the calibration rollouts' first {n} chunks alone (vanilla; no failed rollout chooses anything)",
    "successful": "the first {n} chunks of the calibration rollouts that succeeded (vanilla; the failed ones are "
    "left out of mu_v and sigma_v)",
}


def format_failure_check(
    rows: dict, failed: dict, chunks: int, failure_score: str, cfg, onsets: np.ndarray | None = None
) -> str:
    """Table IV at equal elapsed time for the monitor's failure check, and the same decision by each baseline.

    Args:
        rows: By row label, (scores or None, flags) per set of `failed`: each rollout's score over its first
            `chunks` chunks and whether it was alarmed at the row's calibration threshold (None: no AUROC, a
            decision combined from two thresholds).
        failed: By set title, each rollout's label (True: failed), in the rows' order.
        onsets: Each rollout's failure onset (`lead_time.failure_onset`, 1-based step; NaN where unknown), in the
            largest set's order. A set whose failures all have one gets the caught failures' lead to it.
    """
    lines = [
        f"## The monitor's failure check (Table IV at equal elapsed time), held out\n\n"
        f"The checkpoint's failure check, `{failure_score}` over each rollout's first {chunks} chunks, alarms when "
        f"it exceeds T set on {_REFERENCE_TEXT[cfg.failure_reference].format(n=chunks)}. Positives are the "
        "failed rollouts, negatives the successful ones. Each baseline "
        "below decides the same way, its T from the same calibration rollouts and rule: `chunk_context_nn` is "
        f"the pooled context at chunk {chunks} against the successful calibration rollouts' at that chunk (no "
        f"energy). `monitor (either check)` is what `EnergyMonitor` raises by chunk {chunks}: its OOD check "
        f"(the saved score over the first {chunks} chunks against its saved T) or its failure check."
    ]
    for title, labels in failed.items():
        if labels.all() or not labels.any():
            lines.append(f"### {title}: {int(labels.sum())} of {labels.size} failed, no rates")
            continue
        onset = None if onsets is None else onsets[: labels.size]
        with_onset = onset is not None and bool(np.isfinite(onset[labels]).all())
        headers = ["Score", "Failed alarmed (TPR)", "Successful alarmed (FPR)", "Bal. acc.", "AUROC [95% CI]"]
        if with_onset:
            headers.append("Caught at or before the onset, median lead (chunks)")
        table = []
        for label, per_set in rows.items():
            scores, flags = per_set[title]
            rates = BinaryRates.from_flags(flags[~labels], flags[labels])
            table.append(
                [
                    label,
                    f"{rates.tp}/{rates.n_positive} ({percent(rates.tpr)})",
                    f"{rates.fp}/{rates.fp + rates.tn} ({percent(rates.fpr)})",
                    percent(rates.balanced_accuracy),
                    "-" if scores is None else auroc_interval(scores[~labels], scores[labels], cfg),
                    *([_lead_to_onset(onset[labels & flags] - chunks)] if with_onset else []),
                ]
            )
        note = (
            f"\n\nThe onset is a failure's last chunk that brought its object closer to the goal; an alarm at "
            f"chunk {chunks} leads it by (onset - {chunks}) chunks, negative once the failure had begun."
            if with_onset
            else ""
        )
        lines.append(
            f"### {title}: {int(labels.sum())} of {labels.size} failed\n\n"
            + markdown_table(headers, table)
            + note
        )
    return "\n\n".join(lines)


def _lead_to_onset(leads: np.ndarray) -> str:
    """'k/n, median +m' over the caught failures' leads to their onsets (chunks)."""
    if not leads.size:
        return "-"
    return f"{int((leads >= 0).sum())}/{leads.size}, median {np.median(leads):+.0f}"
