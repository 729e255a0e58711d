"""Evaluating an energy OOD detector: Table III (paper Sec. III-C).

Positives are OOD rollouts, as in Table III: TPR is the share of OOD rollouts caught, FPR the share of
vanilla rollouts falsely flagged. Rollout scores come from `scores.episode_scores`; the calibration
itself (mu_v, sigma_v, T) and its run-time monitor live in `runtime/calibration.py`; the full report (every
condition, the baselines, intervals, figures) is `ood_report.py`.

`format_table_iii` prints the paper's table as it stands (its nine multipliers, its nine columns, mu_v and
sigma_v in the caption) with the AUROC and the episode counts beside it; `format_balanced_accuracy_table` sets
every score's balanced accuracy side by side at the same rules.
"""

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

from ..runtime.calibration import OODCalibration
from ..runtime.threshold import ArrayLike
from .metrics import BinaryRates, markdown_table, percent

TABLE_III_MULTIPLIERS = (0.2, 0.5, 0.7, 0.8, 0.9, 1.0, 1.5, 2.0, 3.0)


@dataclass(frozen=True)
class DetectionRow(BinaryRates):
    """One row of Table III: the rule "OOD when score > threshold" at one threshold.

    `multiplier` is k of T = mu_v + k * sigma_v; `label` names other thresholds (the conformal one).
    """

    multiplier: float = math.nan
    threshold: float = math.nan
    label: str = ""

    @property
    def name(self) -> str:
        if self.label:
            return self.label
        # "1.0σ" as in the paper, but without rounding away a finer multiplier such as 0.25.
        k = self.multiplier
        return f"{k:.1f}σ" if k == round(k, 1) else f"{k:g}σ"


def detection_row(
    vanilla_scores: ArrayLike,
    ood_scores: ArrayLike,
    threshold: float,
    multiplier: float = math.nan,
    label: str = "",
) -> DetectionRow:
    """Confusion counts and rates of "OOD when score > threshold" (positives are OOD rollouts)."""
    rates = BinaryRates.from_scores(vanilla_scores, ood_scores, threshold)
    return DetectionRow(**dataclasses.asdict(rates), multiplier=multiplier, threshold=threshold, label=label)


def ood_detection_table(
    vanilla_scores: ArrayLike,
    ood_scores: ArrayLike,
    multipliers: Sequence[float] = TABLE_III_MULTIPLIERS,
    calibration: OODCalibration | None = None,
) -> list[DetectionRow]:
    """Table III: detection metrics for each sensitivity multiplier k, and at the conformal threshold.

    Args:
        vanilla_scores: Rollout scores of in-distribution rollouts (the negatives).
        ood_scores: Rollout scores of perturbed rollouts (the positives).
        multipliers: The k values, one row each.
        calibration: mu_v and sigma_v to use; its conformal threshold, if any, adds a last row. None fits
            them on `vanilla_scores`, as the paper does: the false-positive rate is then measured on the
            rollouts that set the threshold, which is optimistic. Pass a calibration fitted on other
            vanilla rollouts for a held-out estimate.
    """
    if calibration is None:
        calibration = OODCalibration.fit(vanilla_scores)
    rows = [
        detection_row(vanilla_scores, ood_scores, calibration.with_k(k).threshold, multiplier=float(k))
        for k in multipliers
    ]
    if calibration.conformal_threshold is not None:
        label = f"conf. α={percent(calibration.false_alarm_rate)}"
        rows.append(detection_row(vanilla_scores, ood_scores, calibration.conformal_threshold, label=label))
    return rows


def format_detection_table(
    rows: Sequence[DetectionRow], baselines: dict[str, Sequence[DetectionRow]] | None = None
) -> str:
    """Renders Table III as a markdown table, rates in percent.

    Args:
        rows: The final energy's rows.
        baselines: Other scores' rows at the same thresholds rules (same k, same alpha), by score name: each
            adds a balanced-accuracy column, so the final energy and its baselines sit side by side.
    """
    baselines = baselines or {}
    headers = ["Multiplier", "Threshold", "Accuracy", "Bal. Acc.", "TPR (Catch)", "FPR (False Alarm)"]
    headers += ["F1-Score", "FP", "FN", *(f"Bal. Acc. {name}" for name in baselines)]
    table = []
    for i, r in enumerate(rows):
        rates = [percent(v) for v in (r.accuracy, r.balanced_accuracy, r.tpr, r.fpr, r.f1)]
        others = [percent(b[i].balanced_accuracy) for b in baselines.values()]
        table.append([r.name, f"{r.threshold:.3f}", *rates, r.fp, r.fn, *others])
    return markdown_table(headers, table)


def format_table_iii(
    rows: Sequence[DetectionRow], calibration: OODCalibration, auroc: str, n_vanilla: int, n_ood: int
) -> str:
    """Table III as the paper prints it, with what the paper leaves out stated beside it.

    Args:
        rows: The rows of `ood_detection_table`; a conformal row is left out (the paper has none).
        calibration: The mu_v and sigma_v the thresholds come from (the caption).
        auroc: The AUROC with its interval, e.g. from `metrics.format_auroc`.
        n_vanilla: Vanilla rollouts (negatives) the rows count.
        n_ood: OOD rollouts (positives) the rows count.
    """
    caption = (
        "Evaluating standard deviation multipliers for energy-based thresholding "
        f"(mu_v = {calibration.mu_v:.3f}, sigma_v = {calibration.sigma_v:.3f}, from "
        f"{calibration.n_rollouts} calibration rollouts only)."
    )
    beside = f"AUROC {auroc} (bootstrap 95% interval); n vanilla = {n_vanilla}, n OOD = {n_ood}."
    return f"{caption}\n\n{format_detection_table([r for r in rows if not r.label])}\n\n{beside}"


def format_balanced_accuracy_table(rows_by_score: dict[str, Sequence[DetectionRow]]) -> str:
    """Every score's balanced accuracy at the same rules (same k, same alpha), one column per score."""
    scores = list(rows_by_score.values())
    table = [
        [r.name, *(percent(rows[i].balanced_accuracy) for rows in scores)] for i, r in enumerate(scores[0])
    ]
    return markdown_table(["Rule", *(f"Bal. Acc. {name}" for name in rows_by_score)], table)
