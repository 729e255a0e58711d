"""The post-hoc confidence scores the paper says the final energy replaces, scored from the same records.

Every score is per chunk, higher meaning less confident, and a rollout's score aggregates its chunks as the
final energy's does (`scores.episode_scores`), so all of them go through the same threshold and metrics. The
scores a run-time calibration can apply have the name of their class in `runtime.scores.SCORES`:

- "final_energy": E(a^(K_inf), C), the paper's score.
- "phase_energy": the final energy against the vanilla final energy at the same chunk index,
  (E_t - mu_v[t]) / sigma_v[t] with mu_v[t], sigma_v[t] from the calibration rollouts
  (`runtime.statistics.PhaseStatistics`): the energy's level follows the task's phase, so a chunk is compared
  with what is normal at its point of the task. Needs only the final energy and the chunk index.
- "initial_energy": E(a^(0), C), the energy of the unrefined sample (always recorded).
- "normalized_energy": the final energy plus the log of the mean Boltzmann weight exp(-E) of N chunks drawn
  from the MCMC prior under the same context (recorder option `normalized_energy_samples`): the energy is
  only defined up to a per-context offset, which this Monte-Carlo log-partition removes.
- "restart_spread": the spread of N chunks refined from independent a^(0) for the same observation
  (recorder option `restart_spread_chains`): an ensemble-disagreement score.
- "context_distance", "context_knn": how far the observation's pooled backbone context is from the contexts of
  the calibration rollouts (recorder option `record_context_features`). The context distance is the
  Mahalanobis distance under the calibration features' mean and Ledoit-Wolf shrunk covariance (D can exceed
  the number of chunks; `runtime.statistics.ContextStatistics`); the context k-NN distance is the Euclidean
  distance to the k-th nearest calibration feature, features standardized per dimension by the calibration
  mean and std (`runtime.statistics.ContextNeighbours`). Both are the run-time scores of the same names,
  computed by the same code.

Two more scores combine the final energy and the context distance per rollout, so they have no chunk score
(`scores.combined_rollout_scores`): the rollout's final energy and its context distance, each aggregated over
its chunks as every score is, are each standardized by the calibration rollouts' mean and std of that score,
z = (s - mu_v) / sigma_v (`runtime.statistics.CombinedStatistics`), and

- "energy_and_context": max(z_E, z_d), the run-time score of that name: high when either is;
- "energy_and_context_sum": z_E + z_d, for comparison: a score that sees nothing adds its noise to the other's.

A run-time score registered in `SCORES` that none of these is (a new one) is scored through its class
(`RegisteredScoreModel`), so that the report has it without a line here.

The reference scores ("phase_energy", "context_distance", "context_knn", and the registered ones) are fitted
on the calibration rollouts (`fit_score_reference`). A calibration rollout is scored leave-one-episode-out,
against a reference fitted without it: in-sample, its own chunks would pull its score down and with it the
threshold fitted on these scores.
"""

from collections.abc import Hashable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from ..runtime.readout import EnergyReadout
from ..runtime.scores import (
    SCORES,
    ChunkInputs,
    ChunkScore,
    ContextKNN,
    FinalEnergy,
    VanillaRollouts,
)
from ..runtime.statistics import (
    DEFAULT_KNN_K,
    ContextNeighbours,
    ContextStatistics,
    PhaseStatistics,
    energies_by_index,
)
from .records import Episode

SCORE_NAMES = (
    FinalEnergy.name,
    "phase_energy",
    "initial_energy",
    "normalized_energy",
    "restart_spread",
    "context_distance",
    ContextKNN.name,
)
FEATURE_SCORES = ("context_distance", ContextKNN.name)
# Rollout scores combining the final energy's and the context distance's, standardized on the calibration
# rollouts: their max (the run-time "energy_and_context") and their sum.
COMBINED_SCORES = ("energy_and_context", "energy_and_context_sum")
# The scores they combine, in `CombinedStatistics` order.
COMBINED_FROM = (FinalEnergy.name, "context_distance")
# Scores fitted on the calibration rollouts (`ScoreReference`), besides the registered ones.
REFERENCE_SCORES = ("phase_energy", *FEATURE_SCORES)


@dataclass
class ContextFeatureModel:
    """The context distance and k-NN distance of context features to the calibration rollouts' contexts.

    Build it with `fit`; `reference_ids` names the episode of each calibration feature. Both distances of an
    episode named by `episode_id` leave that episode's features out (leave-one-episode-out). `statistics` is
    what `--score=context_distance` saves with the calibration, `neighbours` what `--score=context_knn` saves:
    a held-out feature's distances are the run-time ones.
    """

    features: np.ndarray
    reference_ids: list
    statistics: ContextStatistics
    neighbours: ContextNeighbours
    # The context statistics without one episode, by episode id, fitted when first needed.
    _left_out: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    @classmethod
    def fit(
        cls, features: np.ndarray, episode_ids: Sequence[Hashable], k: int = DEFAULT_KNN_K
    ) -> "ContextFeatureModel":
        """Fits on (N, D) calibration features, `episode_ids[i]` the episode of feature i."""
        features = np.asarray(features, dtype=np.float64)
        if features.ndim != 2 or features.shape[0] != len(episode_ids) or features.shape[0] < 2:
            raise ValueError(
                f"`features` must be (N >= 2, D) with one episode id per row; got {features.shape} and "
                f"{len(episode_ids)} ids."
            )
        if k < 1:
            raise ValueError(f"`k` (nearest neighbours) must be >= 1, got {k}.")
        statistics = ContextStatistics.fit(features)
        return cls(features, list(episode_ids), statistics, ContextNeighbours.fit(features, k))

    def _same_episode(self, episode_id: Hashable) -> np.ndarray:
        return np.array([i == episode_id for i in self.reference_ids])

    def context_distance(self, features: np.ndarray, episode_id: Hashable = None) -> np.ndarray:
        """Mahalanobis distance of each feature to the calibration features outside episode `episode_id`.

        A calibration episode's distances come from a mean and covariance refitted without its features
        (cached per episode); with fewer than two features left, the full fit is used.
        """
        same_episode = self._same_episode(episode_id)
        if not same_episode.any():
            return self.statistics.distance(features)
        if episode_id not in self._left_out:
            self._left_out[episode_id] = ContextStatistics.fit_without(self.features, same_episode)
        return self._left_out[episode_id].distance(features)

    def context_knn(self, features: np.ndarray, episode_id: Hashable = None) -> np.ndarray:
        """Distance of each feature to its k-th nearest calibration feature outside episode `episode_id`."""
        return self.neighbours.distance(features, excluded=self._same_episode(episode_id))


class PhaseEnergyModel:
    """The phase energy of chunks, against `PhaseStatistics` of the calibration episodes' final energies.

    A calibration episode (named by `episode_id`) is scored against statistics refitted without it (cached
    per episode); with no other calibration episode the full fit is used.
    """

    def __init__(self, energies: Mapping[Hashable, np.ndarray]):
        self.energies = dict(energies)
        self.statistics = PhaseStatistics.fit(list(self.energies.values()))
        self._left_out: dict[Hashable, PhaseStatistics] = {}

    def score(self, final_energies: np.ndarray, chunk_indices: np.ndarray, episode_id: Hashable = None):
        statistics = self.statistics
        if episode_id in self.energies and len(self.energies) > 1:
            if episode_id not in self._left_out:
                others = [e for key, e in self.energies.items() if key != episode_id]
                self._left_out[episode_id] = PhaseStatistics.fit(others)
            statistics = self._left_out[episode_id]
        return statistics.z(final_energies, chunk_indices)


def chunk_context_nn(
    calibration: Mapping[Hashable, Episode], episodes: Mapping[Hashable, Episode], chunk: int
) -> np.ndarray:
    """The chunk-context nearest-neighbour failure baseline: how far each episode's pooled context at chunk
    `chunk` (0-based; an episode's last chunk when it is shorter) lies from the nearest **successful**
    calibration rollout's context at the same chunk, per dimension standardized by those contexts' mean and std.

    No energy at all: a rollout whose scene at that point of the task looks unlike any that went well. A
    calibration episode is scored against the others (leave-one-episode-out).

    Raises:
        ValueError: Fewer than two successful calibration rollouts, or a chunk without its context feature.
    """

    def context_at(episode: Episode) -> np.ndarray:
        record = episode[min(chunk, len(episode) - 1)]
        if record.context_feature is None:
            raise ValueError(
                "The chunk-context nearest-neighbour baseline needs each chunk's pooled context "
                "(`ebvla-eval --record_context_features=true`)."
            )
        return np.asarray(record.context_feature, dtype=np.float64)

    reference_ids = [key for key, episode in calibration.items() if episode[0].success]
    if len(reference_ids) < 2:
        raise ValueError(
            f"The chunk-context nearest-neighbour baseline needs at least 2 successful calibration rollouts, "
            f"got {len(reference_ids)}."
        )
    neighbours = ContextNeighbours.fit(np.stack([context_at(calibration[key]) for key in reference_ids]), k=1)
    return np.array(
        [
            neighbours.distance(
                context_at(episode)[None], excluded=np.array([i == key for i in reference_ids])
            )[0]
            for key, episode in episodes.items()
        ]
    )


def every_chunk_has(episodes: Sequence[Episode], field: str) -> bool:
    """Whether every chunk record of `episodes` (at least one) has the optional `field`."""
    records = [r for episode in episodes for r in episode]
    return bool(records) and all(getattr(r, field) is not None for r in records)


def episode_readout(episode: Episode) -> EnergyReadout:
    """An episode's chunks as the policy's readout of them: each optional input when every chunk recorded it."""
    features, context_energy, phase_energy = (
        [getattr(r, field) for r in episode] if every_chunk_has([episode], field) else None
        for field in ("context_feature", "context_energy", "phase_energy")
    )
    return EnergyReadout.of_arrays(
        np.array([r.final_energy for r in episode], dtype=np.float64),
        np.array([r.chunk_index for r in episode]),
        None if features is None else np.stack(features),
        context_energy,
        np.array([r.initial_energy for r in episode], dtype=np.float64),
        phase_energy,
    )


def recorded_inputs(episodes: Sequence[Episode]) -> set[str]:
    """The `ChunkInputs` fields every chunk of `episodes` has: what the run-time scores can read from them."""
    optional = {
        "context_features": "context_feature",
        "context_energy": "context_energy",
        "phase_energy": "phase_energy",
    }
    return {"final_energy", "chunk_index", "initial_energy"} | {
        name for name, field in optional.items() if every_chunk_has(episodes, field)
    }


def vanilla_rollouts(
    episodes: Mapping[Hashable, Episode], aggregation: str = "mean", knn_k: int = DEFAULT_KNN_K
) -> VanillaRollouts:
    """The calibration episodes as a run-time score is fitted on them (`episode_readout`), with whether each
    succeeded."""
    return VanillaRollouts(
        [episode_readout(episode) for episode in episodes.values()],
        aggregation,
        knn_k,
        [episode[0].success for episode in episodes.values()],
    )


class RegisteredScoreModel:
    """A run-time score of `SCORES` that this module has no baseline of, fitted on the calibration episodes.

    A calibration episode (named by `episode_id`) is scored against a score that never saw it: the score's own
    cross-fitting where it has one (`ChunkScore.held_out_fits`), else the score refitted without it (cached per
    episode); with no other calibration episode, against the full fit.
    """

    def __init__(
        self, score: type[ChunkScore], episodes: Mapping[Hashable, Episode], aggregation: str, knn_k: int
    ):
        self.keys = list(episodes)
        self.rollouts = vanilla_rollouts(episodes, aggregation, knn_k)
        self.score = score
        self.fitted = score.fit(self.rollouts)
        self._left_out: dict[Hashable, ChunkScore] = {}
        readers = score.held_out_fits(self.rollouts) if len(self.keys) > 1 else None
        if readers is not None:
            self._left_out = {
                key: reader or self.fitted for key, reader in zip(self.keys, readers, strict=True)
            }

    def fitted_for(self, episode_id: Hashable = None) -> ChunkScore:
        """The fitted score an episode is scored with."""
        if episode_id not in self.keys or len(self.keys) < 2:
            return self.fitted
        if episode_id not in self._left_out:
            self._left_out[episode_id] = self.score.fit(self.rollouts.without(self.keys.index(episode_id)))
        return self._left_out[episode_id]

    def components(self, episode: Episode, episode_id: Hashable = None) -> tuple[ChunkScore, np.ndarray]:
        """The fitted score of the episode and its chunks' components, (N, n_components), in chunk order."""
        fitted = self.fitted_for(episode_id)
        return fitted, fitted.components(ChunkInputs.of(episode_readout(episode)))


@dataclass
class ScoreReference:
    """What the reference scores learn from the calibration episodes (`fit_score_reference`)."""

    phase: PhaseEnergyModel
    features: ContextFeatureModel | None = None
    # The registered run-time scores none of the above is, by name.
    registered: dict[str, RegisteredScoreModel] = field(default_factory=dict)


def registered_scores() -> list[str]:
    """The run-time scores of `SCORES` that none of `SCORE_NAMES` and `COMBINED_SCORES` is."""
    return [name for name in SCORES if name not in (*SCORE_NAMES, *COMBINED_SCORES)]


def available_scores(episodes: Sequence[Episode]) -> list[str]:
    """The chunk scores of `SCORE_NAMES` every chunk of `episodes` has the data for, in that order."""
    names = ["final_energy", "phase_energy", "initial_energy"]
    names += [name for name in ("normalized_energy", "restart_spread") if every_chunk_has(episodes, name)]
    if every_chunk_has(episodes, "context_feature"):
        names += list(FEATURE_SCORES)
    return names


def fit_feature_model(episodes: Mapping[Hashable, Episode], k: int = DEFAULT_KNN_K) -> ContextFeatureModel:
    """Fits the feature baselines on the context features of every chunk of the (calibration) episodes."""
    features = [r.context_feature for episode in episodes.values() for r in episode]
    ids = [key for key, episode in episodes.items() for _ in episode]
    return ContextFeatureModel.fit(np.stack(features), ids, k=k)


def fit_phase_model(episodes: Mapping[Hashable, Episode]) -> PhaseEnergyModel:
    """Fits the phase energy on the final energies of the (calibration) episodes, by chunk index."""
    return PhaseEnergyModel(
        {
            key: energies_by_index([r.final_energy for r in episode], [r.chunk_index for r in episode])
            for key, episode in episodes.items()
        }
    )


def fit_score_reference(
    episodes: Mapping[Hashable, Episode],
    knn_k: int = DEFAULT_KNN_K,
    features: bool = True,
    registered: Sequence[str] = (),
    aggregation: str = "mean",
) -> ScoreReference:
    """Fits the reference scores on calibration episodes: the feature baselines only with `features`, and the
    `registered` scores (of `registered_scores`) with the calibration's `aggregation`."""
    return ScoreReference(
        fit_phase_model(episodes),
        fit_feature_model(episodes, knn_k) if features else None,
        {name: RegisteredScoreModel(SCORES[name], episodes, aggregation, knn_k) for name in registered},
    )
