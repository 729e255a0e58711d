"""Energy-based out-of-distribution detection (paper Sec. III-C, Eq. 5, Table III).

The anomaly score of a chunk is its final energy E(a^(K_inf), C). A rollout's score aggregates its chunks'
final energies (`rollout_score`, mean by default). From the scores of vanilla (in-distribution) rollouts we
take their mean mu_v and standard deviation sigma_v and flag a rollout as OOD when

    E > T = mu_v + k * sigma_v                                                             (Eq. 5)

`OODCalibration` holds (mu_v, sigma_v, k) and lives next to a checkpoint as `ood_calibration.json`;
`EnergyOODMonitor` applies it at run time; `ood_detection_table`, `auroc` and `roc_curve` evaluate it.

Conventions:
- sigma_v is the population standard deviation (ddof=0), so a single vanilla rollout gives sigma_v = 0 and
  T = mu_v.
- A score is in distribution only when E <= T. Non-finite scores (+inf when refinement diverged, NaN) are
  therefore always flagged as OOD, which is the safe default for a monitor.
- Positives are OOD rollouts, as in Table III: TPR is the share of OOD rollouts caught, FPR the share of
  vanilla rollouts falsely flagged.
- A metric whose denominator is zero (no positives, no negatives, ...) is NaN, never an exception.
"""

import json
import math
import warnings
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from .records import EnergyRecord, EpisodeKey, group_by_episode

OOD_CALIBRATION_FILENAME = "ood_calibration.json"
SCORE_AGGREGATIONS = ("mean", "max", "last", "median")
TABLE_III_MULTIPLIERS = (0.2, 0.5, 0.7, 0.8, 0.9, 1.0, 1.5, 2.0, 3.0)

ArrayLike = Sequence[float] | np.ndarray | Tensor


def _as_array(values: ArrayLike | float) -> np.ndarray:
    if isinstance(values, Tensor):
        values = values.detach().to("cpu", torch.float64).numpy()
    return np.atleast_1d(np.asarray(values, dtype=np.float64))


def rollout_score(chunk_energies: ArrayLike, aggregation: str = "mean") -> float:
    """Forms a rollout's anomaly score from the final energies of its chunks, in execution order.

    Args:
        chunk_energies: E(a^(K_inf), C) of each predicted chunk of the rollout.
        aggregation: "mean" (default, every chunk counts equally), "max" (the least confident chunk),
            "last" (the most recent chunk, what a streaming monitor sees) or "median" (robust to a few
            outlying chunks). With "mean" and "max" one +inf chunk makes the score +inf.

    Raises:
        ValueError: No energies, or an unknown aggregation.
    """
    energies = _as_array(chunk_energies)
    if energies.size == 0:
        raise ValueError("A rollout score needs at least one chunk energy.")
    if aggregation == "mean":
        return float(np.mean(energies))
    if aggregation == "max":
        return float(np.max(energies))
    if aggregation == "last":
        return float(energies[-1])
    if aggregation == "median":
        return float(np.median(energies))
    raise ValueError(f"`aggregation` must be one of {SCORE_AGGREGATIONS}, got {aggregation!r}.")


def rollout_scores(records: Iterable[EnergyRecord], aggregation: str = "mean") -> dict[EpisodeKey, float]:
    """Rollout score of every episode in a list of energy records, keyed by episode."""
    return {
        key: rollout_score([r.final_energy for r in chunks], aggregation)
        for key, chunks in group_by_episode(records).items()
    }


@dataclass(frozen=True)
class OODCalibration:
    """Vanilla-rollout statistics that define the OOD threshold T = mu_v + k * sigma_v (Eq. 5).

    Args:
        mu_v: Mean rollout score of the vanilla (in-distribution) rollouts.
        sigma_v: Population standard deviation of the vanilla rollout scores.
        k: Sensitivity multiplier; lower catches more OOD rollouts at the cost of more false alarms.
        aggregation: How a rollout's chunk energies were reduced to its score (see `rollout_score`). The
            monitor must aggregate the same way for T to mean anything.
        n_rollouts: Number of vanilla rollouts the statistics come from.
    """

    mu_v: float
    sigma_v: float
    k: float = 1.0
    aggregation: str = "mean"
    n_rollouts: int = 0

    def __post_init__(self):
        if self.aggregation not in SCORE_AGGREGATIONS:
            raise ValueError(f"`aggregation` must be one of {SCORE_AGGREGATIONS}, got {self.aggregation!r}.")
        if not (math.isfinite(self.mu_v) and math.isfinite(self.sigma_v) and self.sigma_v >= 0):
            raise ValueError(
                f"`mu_v` and `sigma_v` must be finite, sigma_v >= 0; got {self.mu_v}, {self.sigma_v}."
            )

    @classmethod
    def fit(cls, vanilla_scores: ArrayLike, k: float = 1.0, aggregation: str = "mean") -> "OODCalibration":
        """Estimates mu_v and sigma_v from vanilla rollout scores.

        Non-finite scores (a vanilla rollout whose refinement diverged) are left out with a warning: one
        +inf would make mu_v infinite and the detector useless.

        Raises:
            ValueError: No finite score to fit on.
        """
        scores = _as_array(vanilla_scores)
        finite = scores[np.isfinite(scores)]
        if finite.size < scores.size:
            warnings.warn(
                f"Leaving {scores.size - finite.size} non-finite vanilla score(s) out of the calibration.",
                stacklevel=2,
            )
        if finite.size == 0:
            raise ValueError("Cannot calibrate the OOD threshold without a finite vanilla rollout score.")
        return cls(
            mu_v=float(finite.mean()),
            sigma_v=float(finite.std()),
            k=float(k),
            aggregation=aggregation,
            n_rollouts=int(finite.size),
        )

    @property
    def threshold(self) -> float:
        """T = mu_v + k * sigma_v."""
        return self.mu_v + self.k * self.sigma_v

    def with_k(self, k: float) -> "OODCalibration":
        return OODCalibration(self.mu_v, self.sigma_v, float(k), self.aggregation, self.n_rollouts)

    def save(self, checkpoint_dir: str | Path, overwrite: bool = False) -> Path:
        """Writes `ood_calibration.json` into a policy checkpoint folder (the `pretrained_model` folder).

        Raises:
            FileNotFoundError: The folder does not exist.
            ValueError: The folder is a training checkpoint that holds a `pretrained_model` folder.
            FileExistsError: A calibration exists and `overwrite` is False.
        """
        checkpoint_dir = Path(checkpoint_dir)
        if not checkpoint_dir.is_dir():
            raise FileNotFoundError(f"Checkpoint folder {checkpoint_dir} does not exist.")
        if (checkpoint_dir / "pretrained_model").is_dir():
            raise ValueError(
                f"{checkpoint_dir} holds a `pretrained_model` folder; save the calibration there, next to "
                "the policy's config.json, so `from_pretrained` finds it."
            )
        path = checkpoint_dir / OOD_CALIBRATION_FILENAME
        if path.exists() and not overwrite:
            raise FileExistsError(f"{path} already exists; pass overwrite=True to replace it.")
        # `threshold` is written for people reading the file; loading recomputes it from mu_v, sigma_v, k.
        payload = {**asdict(self), "threshold": self.threshold}
        path.write_text(json.dumps(payload, indent=2) + "\n", encoding="utf-8")
        return path

    @classmethod
    def load(cls, path: str | Path) -> "OODCalibration":
        """Reads a calibration from `ood_calibration.json` or from the checkpoint folder that holds it."""
        path = Path(path)
        if path.is_dir():
            path = path / OOD_CALIBRATION_FILENAME
        payload = json.loads(path.read_text(encoding="utf-8"))
        payload.pop("threshold", None)
        return cls(**payload)

    @classmethod
    def from_pretrained(cls, pretrained_name_or_path: str | Path) -> "OODCalibration":
        """Loads the calibration of a local checkpoint folder or of a Hugging Face Hub model repository."""
        if Path(pretrained_name_or_path).exists():
            return cls.load(pretrained_name_or_path)
        from huggingface_hub import hf_hub_download

        try:
            path = hf_hub_download(str(pretrained_name_or_path), OOD_CALIBRATION_FILENAME)
        except Exception as e:  # a mistyped local path reaches the Hub as an invalid repo id
            raise FileNotFoundError(
                f"No {OOD_CALIBRATION_FILENAME} in a local folder or Hub repo named {pretrained_name_or_path}; "
                "create it with `ebvla-ood-report --calibrate-to`."
            ) from e
        return cls.load(path)


@dataclass(frozen=True)
class OODDecision:
    """The monitor's verdict on one energy score.

    Args:
        in_distribution: True when energy <= threshold; False (OOD) otherwise, including non-finite energy.
        energy: The score that was checked (a chunk's final energy or a rollout score).
        threshold: The threshold T it was compared to.
    """

    in_distribution: bool
    energy: float
    threshold: float

    @property
    def is_ood(self) -> bool:
        return not self.in_distribution


class EnergyOODMonitor:
    """Run-time OOD monitor: compares final energies to the calibrated threshold T.

    Per chunk, `check` compares each final energy to T. Per rollout, `update` accumulates each environment's
    chunk energies and compares their running rollout score (the calibration's aggregation) to T, and
    `check_rollout` does the same for a finished rollout's energies.

    Example:
        monitor = EnergyOODMonitor.from_pretrained("outputs/train/ebvla/checkpoints/last/pretrained_model")
        actions, energy = policy.predict_action_chunk(batch, return_energy=True)
        if any(d.is_ood for d in monitor.update(energy.final_energy)):
            ...  # stop, ask for help, fall back to a safe policy
    """

    def __init__(self, calibration: OODCalibration):
        self.calibration = calibration
        self._histories: list[list[float]] = []

    @classmethod
    def from_pretrained(
        cls, pretrained_name_or_path: str | Path, k: float | None = None
    ) -> "EnergyOODMonitor":
        """Builds a monitor from a checkpoint's `ood_calibration.json`, optionally with another k."""
        calibration = OODCalibration.from_pretrained(pretrained_name_or_path)
        return cls(calibration if k is None else calibration.with_k(k))

    @property
    def threshold(self) -> float:
        return self.calibration.threshold

    def _decide(self, energy: float) -> OODDecision:
        # `energy <= T` rather than `not energy > T`: NaN compares False, so it is flagged as OOD.
        return OODDecision(bool(energy <= self.threshold), float(energy), self.threshold)

    def check(self, final_energy: float | Tensor) -> OODDecision | list[OODDecision]:
        """Checks chunk final energies: a scalar gives one decision, a (B,) tensor or array a list of B."""
        ndim = final_energy.ndim if isinstance(final_energy, Tensor) else np.ndim(final_energy)
        if ndim == 0:
            return self._decide(float(final_energy))
        return [self._decide(e) for e in _as_array(final_energy)]

    def check_rollout(self, chunk_energies: ArrayLike) -> OODDecision:
        """Checks a rollout from its chunks' final energies, aggregated as the calibration was."""
        return self._decide(rollout_score(chunk_energies, self.calibration.aggregation))

    def update(self, final_energy: float | Tensor) -> list[OODDecision]:
        """Adds one chunk's final energy per environment and checks each environment's rollout so far.

        Args:
            final_energy: A float (one environment) or a (B,) tensor, one entry per environment.

        Returns:
            One decision per environment on its running rollout score.
        """
        energies = _as_array(final_energy)
        if not self._histories:
            self._histories = [[] for _ in energies]
        if len(energies) != len(self._histories):
            raise ValueError(
                f"Expected {len(self._histories)} energies (one per environment), got {len(energies)}."
            )
        for history, energy in zip(self._histories, energies, strict=True):
            history.append(float(energy))
        return [self.check_rollout(history) for history in self._histories]

    def reset(self) -> None:
        """Forgets the accumulated energies; call it when the environments reset."""
        self._histories = []


# Evaluation metrics (Table III).


@dataclass(frozen=True)
class DetectionRow:
    """One row of Table III: the detector at T = mu_v + multiplier * sigma_v. Rates are fractions in [0, 1]."""

    multiplier: float
    threshold: float
    accuracy: float
    balanced_accuracy: float
    tpr: float
    fpr: float
    f1: float
    tp: int
    fp: int
    tn: int
    fn: int


def _ratio(numerator: float, denominator: float) -> float:
    return numerator / denominator if denominator > 0 else math.nan


def _check_no_nan(scores: np.ndarray, name: str) -> None:
    if np.isnan(scores).any():
        raise ValueError(f"`{name}` contains NaN scores; they cannot be ranked.")


def detection_row(
    vanilla_scores: ArrayLike, ood_scores: ArrayLike, threshold: float, multiplier: float = math.nan
) -> DetectionRow:
    """Confusion counts and rates of the rule "OOD when score > threshold" (positives are OOD rollouts)."""
    negatives, positives = _as_array(vanilla_scores), _as_array(ood_scores)
    # Same rule as the monitor: only scores <= T are in distribution, so NaN/inf count as flagged.
    tp = int(np.sum(~(positives <= threshold)))
    fp = int(np.sum(~(negatives <= threshold)))
    fn, tn = positives.size - tp, negatives.size - fp
    tpr, fpr = _ratio(tp, tp + fn), _ratio(fp, fp + tn)
    return DetectionRow(
        multiplier=multiplier,
        threshold=threshold,
        accuracy=_ratio(tp + tn, tp + tn + fp + fn),
        balanced_accuracy=(tpr + (1.0 - fpr)) / 2.0,  # NaN if either class is empty
        tpr=tpr,
        fpr=fpr,
        f1=_ratio(2 * tp, 2 * tp + fp + fn),
        tp=tp,
        fp=fp,
        tn=tn,
        fn=fn,
    )


def ood_detection_table(
    vanilla_scores: ArrayLike,
    ood_scores: ArrayLike,
    multipliers: Sequence[float] = TABLE_III_MULTIPLIERS,
    calibration: OODCalibration | None = None,
) -> list[DetectionRow]:
    """Table III: detection metrics for each sensitivity multiplier k.

    Args:
        vanilla_scores: Rollout scores of in-distribution rollouts (the negatives).
        ood_scores: Rollout scores of perturbed rollouts (the positives).
        multipliers: The k values, one row each.
        calibration: mu_v and sigma_v to use. None fits them on `vanilla_scores`, as the paper does; the
            false-positive rate is then measured on the rollouts that set the threshold, which is optimistic.
            Pass a calibration fitted on other vanilla rollouts for a held-out estimate.
    """
    if calibration is None:
        calibration = OODCalibration.fit(vanilla_scores)
    return [
        detection_row(vanilla_scores, ood_scores, calibration.with_k(k).threshold, multiplier=float(k))
        for k in multipliers
    ]


def _average_ranks(values: np.ndarray) -> np.ndarray:
    """1-based ranks; tied values share the average of their ranks (inf ties with inf)."""
    order = np.argsort(values, kind="mergesort")
    sorted_values = values[order]
    # Boundaries of runs of equal values in sorted order.
    new_run = np.r_[True, sorted_values[1:] != sorted_values[:-1]]
    run_id = np.cumsum(new_run) - 1
    run_starts = np.flatnonzero(new_run)
    run_ends = np.r_[run_starts[1:], values.size]  # exclusive
    run_rank = (run_starts + 1 + run_ends) / 2.0  # mean of ranks start+1 .. end
    ranks = np.empty(values.size)
    ranks[order] = run_rank[run_id]
    return ranks


def auroc(vanilla_scores: ArrayLike, ood_scores: ArrayLike) -> float:
    """Area under the ROC curve, the probability that an OOD rollout scores higher than a vanilla one.

    Computed from ranks (the Mann-Whitney U statistic); a tie counts one half. NaN when either set is empty.

    Raises:
        ValueError: A score is NaN.
    """
    negatives, positives = _as_array(vanilla_scores), _as_array(ood_scores)
    _check_no_nan(negatives, "vanilla_scores")
    _check_no_nan(positives, "ood_scores")
    n_neg, n_pos = negatives.size, positives.size
    if n_neg == 0 or n_pos == 0:
        return math.nan
    ranks = _average_ranks(np.concatenate([positives, negatives]))
    u_statistic = ranks[:n_pos].sum() - n_pos * (n_pos + 1) / 2.0
    return float(u_statistic / (n_pos * n_neg))


def roc_curve(vanilla_scores: ArrayLike, ood_scores: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ROC curve of the rule "OOD when score > T" over every distinct threshold.

    Returns:
        (fpr, tpr, thresholds), each of length n_distinct + 1. The first threshold is the highest score
        (nothing flagged, the point (0, 0)); each next one is the next lower distinct score; the last is
        -inf (everything flagged, the point (1, 1)). Rates are NaN when their class is empty.

    Raises:
        ValueError: A score is NaN.
    """
    negatives, positives = _as_array(vanilla_scores), _as_array(ood_scores)
    _check_no_nan(negatives, "vanilla_scores")
    _check_no_nan(positives, "ood_scores")
    distinct = np.unique(np.concatenate([negatives, positives]))[::-1]
    thresholds = np.r_[distinct, -np.inf]
    # searchsorted on sorted scores counts, for every threshold at once, the scores above it.
    sorted_pos, sorted_neg = np.sort(positives), np.sort(negatives)
    n_pos_above = positives.size - np.searchsorted(sorted_pos, thresholds, side="right")
    n_neg_above = negatives.size - np.searchsorted(sorted_neg, thresholds, side="right")
    with np.errstate(invalid="ignore", divide="ignore"):
        tpr = n_pos_above / positives.size if positives.size else np.full(thresholds.size, np.nan)
        fpr = n_neg_above / negatives.size if negatives.size else np.full(thresholds.size, np.nan)
    return fpr.astype(np.float64), tpr.astype(np.float64), thresholds


def _percent(value: float) -> str:
    return "nan" if math.isnan(value) else f"{100 * value:.1f}%"


def format_detection_table(rows: Sequence[DetectionRow]) -> str:
    """Renders Table III as a markdown table, rates in percent."""
    lines = [
        "| Multiplier | Threshold | Accuracy | Bal. Acc. | TPR (Catch) | FPR (False Alarm) | F1-Score | FP | FN |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        # "1.0σ" as in the paper, but without rounding away a finer multiplier such as 0.25.
        k = f"{r.multiplier:.1f}" if r.multiplier == round(r.multiplier, 1) else f"{r.multiplier:g}"
        rates = " | ".join(_percent(v) for v in (r.accuracy, r.balanced_accuracy, r.tpr, r.fpr, r.f1))
        lines.append(f"| {k}σ | {r.threshold:.3f} | {rates} | {r.fp} | {r.fn} |")
    return "\n".join(lines)
