"""The OOD calibration that ships with a checkpoint (Sec. III-C, Eq. 5): a threshold on one chunk score.

A rollout's score aggregates its chunks' scores (`scores.rollout_score`, mean by default); the chunk score is
the final energy E(a^(K_inf), C) (the paper's) or another score of `scores.SCORES`. From the scores of vanilla
(in-distribution) rollouts we take their mean mu_v and standard deviation sigma_v and flag a rollout as OOD
when

    E > T = mu_v + k * sigma_v                                                             (Eq. 5)

or, with `rule="conformal"`, when E exceeds the conformal threshold of a stated false-alarm rate alpha
(`threshold.py` holds both rules and the decision itself). A calibration fitted on the first N chunks
(`ebvla-ood-report --calibrate_to`) scores a rollout by its `ChunkWindow` score instead of its mean, so that T
holds its rate over every decision the run-time monitor makes in those N chunks, not only the N-th.

`OODCalibration` holds these statistics and the score object they are of, and lives next to a checkpoint as
`ood_calibration.json` (with the score's side files); `EnergyOODMonitor` (`monitor.py`) and the policy's
`monitor.response` (`response.py`) apply it at run time. Evaluating a calibration (Table III) is analysis and lives
in `monitoring/ood.py`.
"""

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .checkpoint_files import CheckpointJSON
from .readout import EnergyReadout
from .scores import (
    PACKAGE_SCORES,
    SCORE_AGGREGATIONS,
    SCORES,
    ChunkInputs,
    ChunkScore,
    FinalEnergy,
    VanillaRollouts,
    reading_of,
    score_rollout,
)
from .statistics import ChunkWindow, PhaseStatistics
from .threshold import ArrayLike, MeanStd, conformal_threshold, mean_std_threshold

OOD_CALIBRATION_FILENAME = "ood_calibration.json"
FAILURE_CALIBRATION_FILENAME = "failure_calibration.json"
# Table IV at equal elapsed time: the failure check decides on a rollout's first 3 chunks, the paper's early
# window and the one every LIBERO and MetaWorld table reports.
DEFAULT_FAILURE_CHUNKS = 3
THRESHOLD_RULES = ("mean_std", "conformal")


class UnregisteredScoreError(LookupError):
    """A saved calibration names a score that no imported module registered (not wrapped by `load`: the file is
    valid, the score's module is missing)."""


def _to_json_number(value: Any) -> Any:
    return "inf" if value == math.inf else value


@dataclass(frozen=True)
class OODCalibration(CheckpointJSON):
    """Vanilla-rollout statistics that define the OOD threshold T (Eq. 5, or the conformal quantile).

    Args:
        mu_v: Mean rollout score of the vanilla (in-distribution) rollouts.
        sigma_v: Population standard deviation of the vanilla rollout scores.
        k: Sensitivity multiplier of Eq. 5; lower catches more OOD rollouts at the cost of more false alarms.
        aggregation: How a rollout's chunk scores were reduced to its score (see `rollout_score`). The
            monitor must aggregate the same way for T to mean anything.
        n_rollouts: Number of vanilla rollouts the statistics come from.
        false_alarm_rate: alpha of `conformal_threshold`, None when not computed.
        conformal_threshold: The (1 - alpha) conformal quantile of the vanilla scores (+inf when there were
            too few rollouts for alpha), None when not computed.
        rule: Which threshold the monitor applies: "mean_std" (Eq. 5, the paper's, default) or "conformal".
        score: The chunk score the statistics are of, with what it was fitted on (a `ChunkScore` of
            `scores.SCORES`; the final energy, the paper's, by default).
        window: None: a rollout's score is its chunks' scores aggregated (the paper's). A `ChunkWindow` of N
            chunks: it is the window score W of its running scores over its first N chunks, and mu_v, sigma_v
            and the conformal threshold are those of the vanilla rollouts' W; the monitor's decision after
            chunk N stands for the rest of the episode.
    """

    mu_v: float
    sigma_v: float
    k: float = 1.0
    aggregation: str = "mean"
    n_rollouts: int = 0
    false_alarm_rate: float | None = None
    conformal_threshold: float | None = None
    rule: str = "mean_std"
    score: ChunkScore = field(default_factory=FinalEnergy)
    window: ChunkWindow | None = None

    filename = OOD_CALIBRATION_FILENAME
    what = "OOD calibration"
    command = "ebvla-ood-report"

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
        if SCORES.get(getattr(self.score, "name", None)) is not type(self.score):
            raise ValueError(
                f"`score` must be a `ChunkScore` registered in `SCORES` ({', '.join(SCORES)}), got {self.score!r}."
            )
        reading = self.score.rollout_aggregation
        if reading is not None and self.aggregation != reading:
            raise ValueError(
                f"`{self.score.name}` is read as the {reading!r} aggregation of its chunks, the reading it was chosen "
                f"with; got `aggregation={self.aggregation!r}`."
            )
        if self.window is not None and not isinstance(self.window, ChunkWindow):
            raise ValueError(f"`window` must be a `ChunkWindow` or None, got {type(self.window).__name__}.")

    @classmethod
    def fit(
        cls,
        vanilla_scores: ArrayLike,
        *,
        k: float = 1.0,
        aggregation: str = "mean",
        false_alarm_rate: float | None = None,
        rule: str = "mean_std",
        score: ChunkScore | None = None,
        window: ChunkWindow | None = None,
    ) -> "OODCalibration":
        """Estimates mu_v and sigma_v, and with `false_alarm_rate` the conformal threshold, from vanilla scores.

        Non-finite scores (a vanilla rollout whose refinement diverged) are left out with a warning: one
        +inf would make mu_v infinite and the detector useless.

        Args:
            vanilla_scores: The vanilla rollouts' scores, each aggregated from its chunks' `score` with
                `aggregation`.
            score: The fitted chunk score `vanilla_scores` were computed with; the final energy when None.
            window: The chunk window `vanilla_scores` are window scores of (`ChunkWindow.leave_one_out_scores`),
                None when they are aggregated chunk scores.

        Raises:
            ValueError: No finite score to fit on.
        """
        stats = MeanStd.fit(vanilla_scores, "vanilla")
        conformal = None
        if false_alarm_rate is not None:
            conformal = conformal_threshold(vanilla_scores, false_alarm_rate, "vanilla")
        return cls(
            stats.mean,
            stats.std,
            k=float(k),
            aggregation=aggregation,
            n_rollouts=stats.n,
            false_alarm_rate=false_alarm_rate,
            conformal_threshold=conformal,
            rule=rule,
            score=FinalEnergy() if score is None else score,
            window=window,
        )

    @classmethod
    def calibrate(
        cls,
        score: str,
        vanilla: VanillaRollouts,
        *,
        k: float = 1.0,
        false_alarm_rate: float | None = None,
        rule: str = "mean_std",
        window_chunks: int | None = None,
    ) -> "OODCalibration":
        """The calibration of the score named `score` (a checkpoint's `config.monitor.score`) on vanilla rollouts.

        The score is fitted on every vanilla rollout; mu_v and sigma_v are those of the vanilla rollouts' scores,
        each rollout scored against a score fitted without it (leave-one-out, or the score's own cross-fitting:
        `ChunkScore.held_out_fits`), as a new rollout would be. A score with its own reading
        (`rollout_aggregation`) is aggregated that way whatever `vanilla.aggregation` says.
        With `window_chunks=N` the rollout scores are window scores over the first N chunks (`ChunkWindow`), each
        standardized by the window of the other rollouts; a rollout shorter than N keeps its last running score.

        Raises:
            ValueError: The score is not registered, or a rollout lacks an input the score reads.
        """
        if score not in SCORES:
            raise ValueError(f"`score` must be one of {tuple(SCORES)}, got {score!r}.")
        score_class = SCORES[score]
        for rollout in vanilla.rollouts:
            rollout.require(score_class.reads, score)
        if window_chunks is not None and window_chunks < 1:
            raise ValueError(f"`window_chunks` must be >= 1 or None, got {window_chunks}.")
        aggregation = reading_of(score_class, vanilla.aggregation)
        full = score_class.fit(vanilla)
        readers = score_class.held_out_fits(vanilla)
        running = []
        for i, rollout in enumerate(vanilla.rollouts):
            if readers is not None:
                fitted = readers[i] or full
            else:
                fitted = score_class.fit(vanilla.without(i)) if len(vanilla) > 1 else full
            components = fitted.components(rollout)
            lengths = [len(components)] if window_chunks is None else range(1, window_chunks + 1)
            running.append([score_rollout(fitted, components[:n], aggregation) for n in lengths])
        fit = cls.fit_window if window_chunks is not None else cls.fit
        return fit(
            running if window_chunks is not None else np.asarray(running)[:, 0],
            k=k,
            aggregation=aggregation,
            false_alarm_rate=false_alarm_rate,
            rule=rule,
            score=full,
        )

    @classmethod
    def fit_window(cls, running_scores: ArrayLike, **fit_kwargs: Any) -> "OODCalibration":
        """`fit` on window scores: the `ChunkWindow` of (R, N) vanilla running scores (s_1..s_N of each rollout),
        and the statistics of each rollout's window score standardized without it (as a new rollout would be).
        `fit_kwargs`: `fit`'s keywords but `window`."""
        window = ChunkWindow.fit(running_scores)
        return cls.fit(ChunkWindow.leave_one_out_scores(running_scores), window=window, **fit_kwargs)

    @property
    def needs_context_features(self) -> bool:
        """Whether `chunk_score` needs each chunk's pooled context (`EBVLAPolicy.context_features`)."""
        return "context_features" in self.score.reads

    def chunk_components(self, readout: EnergyReadout) -> np.ndarray:
        """What a rollout's score is aggregated from, one row per chunk: (B, n), the score's n components
        (the chunk score itself for most scores), each aggregated over the rollout before they are combined
        (`score_rollout`).

        Args:
            readout: The policy's `EnergyReadout` of B chunks (`EBVLAPolicy.last_energy`), or recorded chunks
                as one (`EnergyReadout.of_arrays`): its chunk index, and its pooled context or E_c(C) where the
                score reads them.

        Raises:
            ValueError: An input the score reads is missing, or an input is not one row per final energy.
        """
        chunks = ChunkInputs.of(readout)
        chunks.require(self.score.reads, self.score.name)
        return self.score.components(chunks)

    def chunk_score(self, readout: EnergyReadout) -> np.ndarray:
        """(B,) the calibrated score of each chunk of `readout`, the score of a rollout of that one chunk: what
        `threshold` applies to. Arguments and errors as in `chunk_components`."""
        scores = self.score.combine(self.chunk_components(readout))
        if self.window is None:
            return scores
        return self.window.running.z(scores, 0)

    def score_rollout(self, components: ArrayLike) -> float:
        """The rollout score the threshold applies to, from its chunks' `chunk_components` in chunk order:
        each column aggregated over the chunks (`rollout_score`, the calibration's aggregation), then combined
        by the score.

        With a `window`, the window score of the running scores over the first N chunks (fewer so far: those).

        Raises:
            ValueError: `components` is not (N >= 1, n) with the score's n columns.
        """
        if self.window is None:
            return score_rollout(self.score, components, self.aggregation)
        components = np.asarray(components, dtype=np.float64)
        if components.ndim != 2 or components.shape[0] < 1:  # `score_rollout` names the expected shape
            return score_rollout(self.score, components, self.aggregation)
        lengths = range(1, min(len(components), self.window.chunks) + 1)
        return self.window.score(
            [score_rollout(self.score, components[:n], self.aggregation) for n in lengths]
        )

    @property
    def threshold(self) -> float:
        """The threshold of `rule`: mu_v + k * sigma_v, or the conformal quantile."""
        if self.rule == "conformal":
            return self.conformal_threshold
        return mean_std_threshold(self.mu_v, self.sigma_v, self.k)

    def with_k(self, k: float) -> "OODCalibration":
        """The same statistics with Eq. 5's threshold at another k (an explicit k selects Eq. 5)."""
        return dataclasses.replace(self, k=float(k), rule="mean_std")

    # ood_calibration.json: the statistics, `score` by name, and the score's fields; its statistics too many
    # for JSON go into the side files the JSON names (with their D, N, ... and SHA-256).

    def to_json(self, checkpoint_dir: Path) -> dict[str, Any]:
        # `threshold` is written for people reading the file; loading recomputes it. JSON has no infinity.
        payload = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        payload |= {"score": self.score.name, "threshold": self.threshold}
        window = payload.pop("window")
        if (
            window is not None
        ):  # absent, not null, without one: the files of the paper's calibration are unchanged
            payload["window"] = {"means": list(window.running.mean), "stds": list(window.running.std)}
        payload = {key: _to_json_number(value) for key, value in payload.items()}
        fields = self.score.to_json()
        for side_file in _all_side_files():
            if side_file in type(self.score).side_files:
                fields[side_file.field] = side_file.write(checkpoint_dir, fields[side_file.field])
            elif side_file.filename.startswith(Path(self.filename).stem):
                # A previous calibration of this file left it; another file's (the failure check's
                # neighbours beside the OOD calibration's) is not ours to remove.
                (checkpoint_dir / side_file.filename).unlink(missing_ok=True)
        return {**payload, **fields}

    @classmethod
    def from_json(cls, payload: dict[str, Any], path: Path) -> "OODCalibration":
        """Files written before the conformal fields existed read with `rule="mean_std"`, before the phase
        energy with `score="final_energy"`; v0.1.0 wrote every score's fields, null where unused. A
        `window_reference` (held-out vanilla rollouts' values for the window test, written by
        `ebvla-ood-report --calibrate_to` before that test moved to the research code) is ignored."""
        payload = dict(payload)
        payload.pop("threshold", None)
        payload.pop("window_reference", None)
        if payload.get("conformal_threshold") == "inf":
            payload["conformal_threshold"] = math.inf
        if isinstance(payload.get("window"), dict):
            window = payload["window"]
            payload["window"] = ChunkWindow(PhaseStatistics(window["means"], window["stds"]))
        name = payload.pop("score", FinalEnergy.name)
        if name not in SCORES:
            raise UnregisteredScoreError(
                f"{path} is a calibration of the score {name!r}, which is not registered: the package ships "
                f"{PACKAGE_SCORES}. A research score is registered by importing its module (the research "
                "benchmarks' `research_scores.py`) or with `lerobot_policy_ebvla.runtime.scores.register_score(cls)` "
                "before loading."
            )
        score_class = SCORES[name]
        own = {*score_class.json_fields, *(s.field for s in score_class.side_files)}
        statistics = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(k for k, v in payload.items() if k not in own | statistics and v is not None)
        if unknown:
            raise TypeError(f"unexpected field(s) {unknown} for `score={name!r}`")
        fields = {key: payload[key] for key in own if key in payload}
        for side_file in score_class.side_files:
            if side_file.field in fields:
                fields[side_file.field] = side_file.load(path, fields[side_file.field])
        common = {key: value for key, value in payload.items() if key in statistics}
        return cls(**common, score=score_class.from_json(fields))

    @classmethod
    def expected_fields(cls) -> str:
        statistics = [f.name for f in dataclasses.fields(cls)]
        own = [
            f"{name}: {', '.join([*s.json_fields, *(f.field for f in s.side_files)])}"
            for name, s in SCORES.items()
            if s.json_fields or s.side_files
        ]
        return f"{', '.join(statistics)} (mu_v, sigma_v required), and the score's own ({'; '.join(own)})"


@dataclass(frozen=True)
class FailureCalibration(OODCalibration):
    """The monitor's failure check: a threshold on an energy score of a rollout's first N chunks (Table IV at
    equal elapsed time), fitted like the OOD threshold on vanilla rollouts alone (`failure_calibration.json`).

    No failed rollout chooses it: mu_v and sigma_v (or the conformal quantile) are those of the vanilla
    calibration rollouts' scores over their first `chunks` chunks (or of those among them that succeeded:
    `ebvla-ood-report --failure_reference=successful`), so the alarm says "these first chunks are unlike a
    vanilla rollout's", and the report measures how often that means failure. It is decided once, at
    the end of chunk N, and kept for the episode (`EnergyMonitor`). The score is an energy score, the head's part
    of the joint energy by default (`monitor.failure_score`), or the success energy E_s (`success_energy`), whose
    weights are saved beside it: it stores no features.

    Args:
        chunks: N, the chunks the rollout score aggregates (the first N; an episode that ends before chunk N is
            never decided at run time and scored on all its chunks by the reports).
        (the rest as `OODCalibration`'s)
    """

    chunks: int = DEFAULT_FAILURE_CHUNKS

    filename = FAILURE_CALIBRATION_FILENAME
    what = "failure calibration"

    def __post_init__(self):
        super().__post_init__()
        if self.chunks < 1:
            raise ValueError(f"`chunks` must be >= 1, got {self.chunks}.")
        if type(self.score).feature_baseline:
            raise ValueError(
                f"The failure check stores no features; `{self.score.name}` is a feature baseline, which keeps the "
                "calibration's pooled contexts or their statistics. Use an energy score (head_energy_two_sided, the "
                "default, or success_energy)."
            )

    @classmethod
    def of(cls, calibration: OODCalibration, chunks: int) -> "FailureCalibration":
        """The failure check with `calibration`'s statistics, which must be those of the first `chunks` chunks."""
        return cls(
            **{f.name: getattr(calibration, f.name) for f in dataclasses.fields(OODCalibration)},
            chunks=chunks,
        )

    @classmethod
    def calibrate(
        cls,
        score: str,
        vanilla: VanillaRollouts,
        *,
        chunks: int = DEFAULT_FAILURE_CHUNKS,
        k: float = 1.0,
        false_alarm_rate: float | None = None,
        rule: str = "mean_std",
    ) -> "FailureCalibration":
        """`OODCalibration.calibrate` on the vanilla rollouts' first `chunks` chunks."""
        calibration = OODCalibration.calibrate(
            score, vanilla.first(chunks), k=k, false_alarm_rate=false_alarm_rate, rule=rule
        )
        return cls.of(calibration, chunks)


def _all_side_files() -> list:
    """Every side file a registered score saves, once."""
    return list(dict.fromkeys(s for score in SCORES.values() for s in score.side_files))
