"""Energy-based out-of-distribution detection (paper Sec. III-C, Eq. 5, Table III).

The anomaly score of a chunk is its final energy E(a^(K_inf), C). A rollout's score aggregates its chunks'
final energies (`rollout_score`, mean by default). From the scores of vanilla (in-distribution) rollouts we
take their mean mu_v and standard deviation sigma_v and flag a rollout as OOD when

    E > T = mu_v + k * sigma_v                                                             (Eq. 5)

or, with `rule="conformal"`, when E exceeds the conformal threshold of a stated false-alarm rate alpha
(`threshold.py` holds both rules and the decision itself).

`OODCalibration` holds the statistics and lives next to a checkpoint as `ood_calibration.json`;
`EnergyOODMonitor` applies it at run time; `ood_detection_table` evaluates it (Table III).

Positives are OOD rollouts, as in Table III: TPR is the share of OOD rollouts caught, FPR the share of
vanilla rollouts falsely flagged.
"""

import dataclasses
import json
import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from torch import Tensor

from .metrics import BinaryRates, markdown_table, percent
from .records import EnergyRecord, EpisodeKey, group_by_episode
from .threshold import ArrayLike, MeanStd, as_array, conformal_threshold, exceeds, mean_std_threshold

OOD_CALIBRATION_FILENAME = "ood_calibration.json"
SCORE_AGGREGATIONS = ("mean", "max", "last", "median")
THRESHOLD_RULES = ("mean_std", "conformal")
TABLE_III_MULTIPLIERS = (0.2, 0.5, 0.7, 0.8, 0.9, 1.0, 1.5, 2.0, 3.0)


def rollout_score(chunk_energies: ArrayLike, aggregation: str = "mean") -> float:
    """Forms a rollout's anomaly score from the final energies (or other scores) of its chunks, in order.

    Args:
        chunk_energies: E(a^(K_inf), C) of each predicted chunk of the rollout.
        aggregation: "mean" (default, every chunk counts equally), "max" (the least confident chunk),
            "last" (the most recent chunk, what a streaming monitor sees) or "median" (robust to a few
            outlying chunks). With "mean" and "max" one +inf chunk makes the score +inf.

    Raises:
        ValueError: No energies, or an unknown aggregation.
    """
    if aggregation not in SCORE_AGGREGATIONS:
        raise ValueError(f"`aggregation` must be one of {SCORE_AGGREGATIONS}, got {aggregation!r}.")
    energies = as_array(chunk_energies)
    if energies.size == 0:
        raise ValueError("A rollout score needs at least one chunk energy.")
    reduce = {"mean": np.mean, "max": np.max, "last": lambda e: e[-1], "median": np.median}[aggregation]
    return float(reduce(energies))


def rollout_scores(
    records: Iterable[EnergyRecord],
    aggregation: str = "mean",
    chunk_score: Callable[[EnergyRecord], float] = lambda r: r.final_energy,
) -> dict[EpisodeKey, float]:
    """Rollout score of every episode in a list of energy records, keyed by episode.

    `chunk_score` picks each chunk's score: the final energy by default (a baseline otherwise).
    """
    return {
        key: rollout_score([chunk_score(r) for r in chunks], aggregation)
        for key, chunks in group_by_episode(records).items()
    }


def _to_json_number(value: float | None) -> float | str | None:
    return "inf" if value == math.inf else value


@dataclass(frozen=True)
class OODCalibration:
    """Vanilla-rollout statistics that define the OOD threshold T (Eq. 5, or the conformal quantile).

    Args:
        mu_v: Mean rollout score of the vanilla (in-distribution) rollouts.
        sigma_v: Population standard deviation of the vanilla rollout scores.
        k: Sensitivity multiplier of Eq. 5; lower catches more OOD rollouts at the cost of more false alarms.
        aggregation: How a rollout's chunk energies were reduced to its score (see `rollout_score`). The
            monitor must aggregate the same way for T to mean anything.
        n_rollouts: Number of vanilla rollouts the statistics come from.
        false_alarm_rate: alpha of `conformal_threshold`, None when not computed.
        conformal_threshold: The (1 - alpha) conformal quantile of the vanilla scores (+inf when there were
            too few rollouts for alpha), None when not computed.
        rule: Which threshold the monitor applies: "mean_std" (Eq. 5, the paper's, default) or "conformal".
    """

    mu_v: float
    sigma_v: float
    k: float = 1.0
    aggregation: str = "mean"
    n_rollouts: int = 0
    false_alarm_rate: float | None = None
    conformal_threshold: float | None = None
    rule: str = "mean_std"

    def __post_init__(self):
        if self.aggregation not in SCORE_AGGREGATIONS:
            raise ValueError(f"`aggregation` must be one of {SCORE_AGGREGATIONS}, got {self.aggregation!r}.")
        if not (math.isfinite(self.mu_v) and math.isfinite(self.sigma_v) and self.sigma_v >= 0):
            raise ValueError(
                f"`mu_v` and `sigma_v` must be finite, sigma_v >= 0; got {self.mu_v}, {self.sigma_v}."
            )
        if self.rule not in THRESHOLD_RULES:
            raise ValueError(f"`rule` must be one of {THRESHOLD_RULES}, got {self.rule!r}.")
        if self.rule == "conformal" and self.conformal_threshold is None:
            raise ValueError(
                "`rule='conformal'` needs a `conformal_threshold` (fit with `false_alarm_rate`)."
            )

    @classmethod
    def fit(
        cls,
        vanilla_scores: ArrayLike,
        k: float = 1.0,
        aggregation: str = "mean",
        false_alarm_rate: float | None = None,
        rule: str = "mean_std",
    ) -> "OODCalibration":
        """Estimates mu_v and sigma_v, and with `false_alarm_rate` the conformal threshold, from vanilla scores.

        Non-finite scores (a vanilla rollout whose refinement diverged) are left out with a warning: one
        +inf would make mu_v infinite and the detector useless.

        Raises:
            ValueError: No finite score to fit on.
        """
        stats = MeanStd.fit(vanilla_scores, "vanilla")
        conformal = None
        if false_alarm_rate is not None:
            conformal = conformal_threshold(vanilla_scores, false_alarm_rate, "vanilla")
        return cls(stats.mean, stats.std, float(k), aggregation, stats.n, false_alarm_rate, conformal, rule)

    @property
    def threshold(self) -> float:
        """The threshold of `rule`: mu_v + k * sigma_v, or the conformal quantile."""
        if self.rule == "conformal":
            return self.conformal_threshold
        return mean_std_threshold(self.mu_v, self.sigma_v, self.k)

    def with_k(self, k: float) -> "OODCalibration":
        """The same statistics with Eq. 5's threshold at another k (an explicit k selects Eq. 5)."""
        return dataclasses.replace(self, k=float(k), rule="mean_std")

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
        # `threshold` is written for people reading the file; loading recomputes it. JSON has no infinity.
        payload = {**dataclasses.asdict(self), "threshold": self.threshold}
        payload = {key: _to_json_number(value) for key, value in payload.items()}
        path.write_text(json.dumps(payload, indent=2, allow_nan=False) + "\n", encoding="utf-8")
        return path

    @classmethod
    def load(cls, path: str | Path) -> "OODCalibration":
        """Reads a calibration from `ood_calibration.json` or from the checkpoint folder that holds it.

        Files written before the conformal fields existed read with `rule="mean_std"`.
        """
        path = Path(path)
        if path.is_dir():
            path = path / OOD_CALIBRATION_FILENAME
        payload = json.loads(path.read_text(encoding="utf-8"))
        payload.pop("threshold", None)
        if payload.get("conformal_threshold") == "inf":
            payload["conformal_threshold"] = math.inf
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
                "create it with `ebvla-ood-report --calibrate_to=...`."
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
        """Builds a monitor from a checkpoint's `ood_calibration.json`, optionally with Eq. 5 at another k."""
        calibration = OODCalibration.from_pretrained(pretrained_name_or_path)
        return cls(calibration if k is None else calibration.with_k(k))

    @property
    def threshold(self) -> float:
        return self.calibration.threshold

    def _decide(self, energy: float) -> OODDecision:
        return OODDecision(not bool(exceeds(energy, self.threshold)[0]), float(energy), self.threshold)

    def check(self, final_energy: float | Tensor) -> OODDecision | list[OODDecision]:
        """Checks chunk final energies: a scalar gives one decision, a (B,) tensor or array a list of B."""
        ndim = final_energy.ndim if isinstance(final_energy, Tensor) else np.ndim(final_energy)
        if ndim == 0:
            return self._decide(float(final_energy))
        return [self._decide(e) for e in as_array(final_energy)]

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
        energies = as_array(final_energy)
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
    rates = BinaryRates.from_flags(exceeds(vanilla_scores, threshold), exceeds(ood_scores, threshold))
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
