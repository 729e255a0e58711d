"""The OOD calibration that ships with a checkpoint, and the monitor that applies it (Sec. III-C, Eq. 5).

The anomaly score of a chunk is its final energy E(a^(K_inf), C). A rollout's score aggregates its chunks'
final energies (`rollout_score`, mean by default). From the scores of vanilla (in-distribution) rollouts we
take their mean mu_v and standard deviation sigma_v and flag a rollout as OOD when

    E > T = mu_v + k * sigma_v                                                             (Eq. 5)

or, with `rule="conformal"`, when E exceeds the conformal threshold of a stated false-alarm rate alpha
(`threshold.py` holds both rules and the decision itself).

`OODCalibration` holds the statistics and lives next to a checkpoint as `ood_calibration.json`;
`EnergyOODMonitor` applies it at run time. Evaluating a calibration (Table III) is analysis and lives in
`monitoring/ood.py`.

The final energy's level follows the task's phase (the energy of a normal chunk late in an episode is not the
energy of a normal first chunk), so a calibration may instead score each chunk against the vanilla energy at
the same chunk index: the *phase energy* z_t = (E_t - mu_v[t]) / sigma_v[t] (`PhaseStatistics`). Its per-index
statistics are saved in the calibration (`score="phase_energy"`), and `OODCalibration.chunk_score` turns a
chunk's (final energy, chunk index) into the score the threshold applies to.
"""

import dataclasses
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from torch import Tensor

from .threshold import ArrayLike, MeanStd, as_array, conformal_threshold, exceeds, mean_std_threshold

OOD_CALIBRATION_FILENAME = "ood_calibration.json"
SCORE_AGGREGATIONS = ("mean", "max", "last", "median")
THRESHOLD_RULES = ("mean_std", "conformal")
# The chunk scores a run-time calibration can compute from what the policy reports: the final energy, and the
# final energy against the vanilla energy at the same chunk index.
CALIBRATED_SCORES = ("final_energy", "phase_energy")
# sigma_v[t] is at least this fraction of the pooled sigma of all vanilla chunk energies.
PHASE_SIGMA_FLOOR = 0.1
# And at least this, so that a calibration of identical energies still divides by a positive number.
_MIN_SIGMA = 1e-12


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


def _ndim(values: ArrayLike | float) -> int:
    return values.ndim if isinstance(values, Tensor) else np.ndim(values)


def _to_json_number(value: float | None) -> float | str | None:
    return "inf" if value == math.inf else value


@dataclass(frozen=True)
class PhaseStatistics:
    """mu_v[t] and sigma_v[t]: the vanilla final energy at each chunk index t, the phase energy's reference.

    The phase energy of a chunk is z_t = (E_t - mu_v[t]) / sigma_v[t]: how far its final energy lies above
    what vanilla rollouts have at the same point of the task. Fit with `fit` on vanilla episodes.

    - mu_v[t] and sigma_v[t] (population std) are over the vanilla episodes that reached index t, finite
      energies only; an index where none has a finite energy takes the previous index's statistics (index 0
      the pooled ones).
    - sigma_v[t] is floored at `PHASE_SIGMA_FLOOR` (0.1) times the pooled sigma, the std of every vanilla
      chunk energy of every index together: a late index reached by one or two episodes would otherwise
      divide by almost nothing.
    - Indices past the longest vanilla episode use the last index's statistics.

    Args:
        mean: mu_v[t] for t = 0 .. T-1.
        std: sigma_v[t], already floored (every entry > 0).
    """

    mean: tuple[float, ...]
    std: tuple[float, ...]

    def __post_init__(self):
        object.__setattr__(self, "mean", tuple(float(m) for m in self.mean))
        object.__setattr__(self, "std", tuple(float(s) for s in self.std))
        if not self.mean or len(self.mean) != len(self.std):
            raise ValueError(
                f"`mean` and `std` need one entry per chunk index, got {len(self.mean)} and {len(self.std)}."
            )
        values = np.array([*self.mean, *self.std])
        if not np.all(np.isfinite(values)) or min(self.std) <= 0:
            raise ValueError("Phase statistics must be finite, with every std > 0.")

    @classmethod
    def fit(cls, episode_energies: Sequence[ArrayLike]) -> "PhaseStatistics":
        """Fits on the final energies of vanilla episodes, each in chunk order (index t is entry t).

        Raises:
            ValueError: No finite energy at all.
        """
        series = [as_array(e) for e in episode_energies]
        pooled = np.concatenate(series) if series else np.zeros(0)
        pooled = pooled[np.isfinite(pooled)]
        if pooled.size == 0:
            raise ValueError("Cannot fit phase statistics without a finite vanilla final energy.")
        floor = max(PHASE_SIGMA_FLOOR * float(pooled.std()), _MIN_SIGMA)
        previous = (float(pooled.mean()), max(float(pooled.std()), floor))
        means, stds = [], []
        for t in range(max(len(s) for s in series)):
            at_t = np.array([s[t] for s in series if len(s) > t])
            at_t = at_t[np.isfinite(at_t)]
            if at_t.size:
                previous = (float(at_t.mean()), max(float(at_t.std()), floor))
            means.append(previous[0])
            stds.append(previous[1])
        return cls(tuple(means), tuple(stds))

    def z(self, final_energy: ArrayLike | float, chunk_index: ArrayLike | int) -> np.ndarray:
        """The phase energy (E_t - mu_v[t]) / sigma_v[t] of each (final energy, chunk index) pair."""
        index = np.atleast_1d(np.asarray(chunk_index))
        if index.size and (not np.issubdtype(index.dtype, np.integer) or index.min() < 0):
            raise ValueError(f"`chunk_index` must be integers >= 0, got {chunk_index!r}.")
        index = np.minimum(index, len(self.mean) - 1)
        return (as_array(final_energy) - np.asarray(self.mean)[index]) / np.asarray(self.std)[index]


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
        score: The chunk score the statistics are of: "final_energy" (the paper's, default) or
            "phase_energy" (the final energy against the vanilla energy at the same chunk index).
        phase_mean: mu_v[t] of `PhaseStatistics`, for `score="phase_energy"`; None otherwise.
        phase_std: sigma_v[t] of `PhaseStatistics`, for `score="phase_energy"`; None otherwise.
    """

    mu_v: float
    sigma_v: float
    k: float = 1.0
    aggregation: str = "mean"
    n_rollouts: int = 0
    false_alarm_rate: float | None = None
    conformal_threshold: float | None = None
    rule: str = "mean_std"
    score: str = "final_energy"
    phase_mean: tuple[float, ...] | None = None
    phase_std: tuple[float, ...] | None = None

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
        if self.score not in CALIBRATED_SCORES:
            raise ValueError(f"`score` must be one of {CALIBRATED_SCORES}, got {self.score!r}.")
        if (self.phase_mean is None) != (self.phase_std is None):
            raise ValueError("`phase_mean` and `phase_std` come together: give both or neither.")
        if self.phase_mean is not None:
            # Validates them, and stores tuples whether they came from a fit or from a JSON list.
            phase = PhaseStatistics(self.phase_mean, self.phase_std)
            object.__setattr__(self, "phase_mean", phase.mean)
            object.__setattr__(self, "phase_std", phase.std)
        elif self.score == "phase_energy":
            raise ValueError("`score='phase_energy'` needs `phase_mean` and `phase_std` (`PhaseStatistics`).")

    @classmethod
    def fit(
        cls,
        vanilla_scores: ArrayLike,
        k: float = 1.0,
        aggregation: str = "mean",
        false_alarm_rate: float | None = None,
        rule: str = "mean_std",
        score: str = "final_energy",
        phase: PhaseStatistics | None = None,
    ) -> "OODCalibration":
        """Estimates mu_v and sigma_v, and with `false_alarm_rate` the conformal threshold, from vanilla scores.

        Non-finite scores (a vanilla rollout whose refinement diverged) are left out with a warning: one
        +inf would make mu_v infinite and the detector useless.

        Args:
            vanilla_scores: The vanilla rollouts' scores, each aggregated from its chunks' `score`.
            score: The chunk score `vanilla_scores` were aggregated from (`CALIBRATED_SCORES`).
            phase: The per-index statistics the phase energy was computed with, for `score="phase_energy"`.

        Raises:
            ValueError: No finite score to fit on.
        """
        stats = MeanStd.fit(vanilla_scores, "vanilla")
        conformal = None
        if false_alarm_rate is not None:
            conformal = conformal_threshold(vanilla_scores, false_alarm_rate, "vanilla")
        phase_mean, phase_std = (None, None) if phase is None else (phase.mean, phase.std)
        return cls(
            stats.mean,
            stats.std,
            float(k),
            aggregation,
            stats.n,
            false_alarm_rate,
            conformal,
            rule,
            score,
            phase_mean,
            phase_std,
        )

    @property
    def phase(self) -> PhaseStatistics | None:
        """The per-index statistics of the phase energy, None when the calibration has none."""
        return None if self.phase_mean is None else PhaseStatistics(self.phase_mean, self.phase_std)

    def chunk_score(
        self, final_energy: ArrayLike | float, chunk_index: ArrayLike | int | None = None
    ) -> float | np.ndarray:
        """The calibrated score of a chunk's final energy: what `threshold` and `rollout_score` apply to.

        For `score="final_energy"` it is the final energy itself (`chunk_index` is not needed); for
        `score="phase_energy"` it is (E - mu_v[t]) / sigma_v[t] at the chunk's 0-based index t in its episode.

        Args:
            final_energy: One final energy, or one per environment ((B,) array or tensor).
            chunk_index: The chunk's index in its episode: an int, or one per environment.

        Returns:
            A float for a scalar energy, else an array with one score per entry.

        Raises:
            ValueError: `score="phase_energy"` and no `chunk_index`.
        """
        scalar = _ndim(final_energy) == 0
        if self.score == "final_energy":
            scores = as_array(final_energy)
        elif chunk_index is None:
            raise ValueError("The phase energy needs the chunk's index in its episode (`chunk_index`).")
        else:
            scores = self.phase.z(final_energy, chunk_index)
        return float(scores[0]) if scalar and np.ndim(chunk_index) == 0 else scores

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

        Files written before the conformal fields existed read with `rule="mean_std"`, files written before
        the phase energy with `score="final_energy"`.
        """
        path = Path(path)
        if path.is_dir():
            path = path / OOD_CALIBRATION_FILENAME
        try:
            payload = json.loads(path.read_text(encoding="utf-8"))
            if not isinstance(payload, dict):
                raise TypeError(f"expected a JSON object, got {type(payload).__name__}")
            payload.pop("threshold", None)
            if payload.get("conformal_threshold") == "inf":
                payload["conformal_threshold"] = math.inf
            return cls(**payload)
        except (json.JSONDecodeError, TypeError, ValueError) as e:
            fields = ", ".join(f.name for f in dataclasses.fields(cls))
            raise ValueError(
                f"{path} is not a valid OOD calibration ({e}). Expected a JSON object with the fields "
                f"{fields} (mu_v, sigma_v required), as `OODCalibration.save` and `ebvla-ood-report "
                "--calibrate_to` write it: calibrate again, or remove the file."
            ) from e

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
    """Run-time OOD monitor: compares final energies, as the calibration's chunk score, to its threshold T.

    Per chunk, `check` compares each chunk score to T. Per rollout, `update` accumulates each environment's
    chunk scores and compares their running rollout score (the calibration's aggregation) to T, and
    `check_rollout` does the same for a finished rollout's energies. The chunk score is the final energy, or
    with a phase-energy calibration the final energy against the vanilla energy at the chunk's index
    (`OODCalibration.chunk_score`): `update` and `check_rollout` count the chunks themselves, `check` needs
    the index.

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

    def check(
        self, final_energy: float | Tensor, chunk_index: int | None = None
    ) -> OODDecision | list[OODDecision]:
        """Checks chunk final energies: a scalar gives one decision, a (B,) tensor or array a list of B.

        `chunk_index` (the chunks' index in their episodes) is needed by a phase-energy calibration only.
        """
        scores = as_array(self.calibration.chunk_score(as_array(final_energy), chunk_index))
        if _ndim(final_energy) == 0:
            return self._decide(float(scores[0]))
        return [self._decide(e) for e in scores]

    def check_rollout(self, chunk_energies: ArrayLike) -> OODDecision:
        """Checks a rollout from its chunks' final energies (chunks 0, 1, ...), aggregated as calibrated."""
        energies = as_array(chunk_energies)
        scores = self.calibration.chunk_score(energies, np.arange(energies.size))
        return self._decide(rollout_score(scores, self.calibration.aggregation))

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
