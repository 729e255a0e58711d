"""The post-hoc confidence scores the paper says the final energy replaces, scored from the same records.

Every score is per chunk, higher meaning less confident, and a rollout's score aggregates its chunks as the
final energy's does (`scores.episode_scores`), so all of them go through the same threshold and metrics:

- "final_energy": E(a^(K_inf), C), the paper's score.
- "phase_energy": the final energy against the vanilla final energy at the same chunk index,
  (E_t - mu_v[t]) / sigma_v[t] with mu_v[t], sigma_v[t] from the calibration rollouts
  (`runtime.calibration.PhaseStatistics`): the energy's level follows the task's phase, so a chunk is compared
  with what is normal at its point of the task. Needs only the final energy and the chunk index.
- "initial_energy": E(a^(0), C), the energy of the unrefined sample (always recorded).
- "normalized_energy": the final energy plus the log of the mean Boltzmann weight exp(-E) of N chunks drawn
  from the MCMC prior under the same context (recorder option `normalized_energy_samples`): the energy is
  only defined up to a per-context offset, which this Monte-Carlo log-partition removes.
- "restart_spread": the spread of N chunks refined from independent a^(0) for the same observation
  (recorder option `restart_spread_chains`): an ensemble-disagreement score.
- "mahalanobis", "knn": how far the observation's pooled backbone context is from the contexts of the
  calibration rollouts (recorder option `record_context_features`). Mahalanobis uses the calibration
  features' mean and their Ledoit-Wolf shrunk covariance (D can exceed the number of chunks): it is the
  run-time context distance (`runtime.calibration.ContextStatistics`, `score="context_distance"`), fitted and
  computed by the same code. k-NN is the Euclidean distance to the k-th nearest calibration feature,
  features standardized per dimension by the calibration mean and std: for a held-out chunk it is the
  run-time context k-NN distance (`runtime.calibration.ContextNeighbours`, `score="context_knn"`), computed by
  the same function (`runtime.calibration.kth_nearest_distance`).

Two more scores combine the final energy and the context distance per rollout, so they have no chunk score
(`scores.combined_rollout_scores`): the rollout's final energy and its Mahalanobis distance, each aggregated
over its chunks as every score is, are each standardized by the calibration rollouts' mean and std of that
score, z = (s - mu_v) / sigma_v (`runtime.calibration.CombinedStatistics`), and

- "energy_and_context": max(z_E, z_d), the run-time `score="energy_and_context"`: high when either is;
- "energy_and_context_sum": z_E + z_d, for comparison: a score that sees nothing adds its noise to the other's.

The reference scores ("phase_energy", "mahalanobis", "knn") are fitted on the calibration rollouts
(`fit_score_reference`). A calibration rollout is scored leave-one-episode-out, against a reference fitted
without it: in-sample, its own chunks would pull its score down and with it the threshold fitted on these
scores.
"""

from collections.abc import Hashable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from ..runtime.calibration import (
    DEFAULT_KNN_K,
    ContextNeighbours,
    ContextStatistics,
    PhaseStatistics,
    kth_nearest_distance,
)
from .records import Episode

SCORE_NAMES = (
    "final_energy",
    "phase_energy",
    "initial_energy",
    "normalized_energy",
    "restart_spread",
    "mahalanobis",
    "knn",
)
FEATURE_SCORES = ("mahalanobis", "knn")
# Rollout scores combining the final energy's and the context distance's, standardized on the calibration
# rollouts: their max (the run-time "energy_and_context") and their sum.
COMBINED_SCORES = ("energy_and_context", "energy_and_context_sum")
# The scores they combine, in `CombinedStatistics` order.
COMBINED_FROM = ("final_energy", "mahalanobis")
# Scores fitted on the calibration rollouts (`ScoreReference`).
REFERENCE_SCORES = ("phase_energy", *FEATURE_SCORES)


@dataclass
class ContextFeatureModel:
    """Mahalanobis and k-NN distances of context features to the calibration rollouts' contexts.

    Build it with `fit`; `reference_ids` names the episode of each reference feature. Both distances of an
    episode named by `episode_id` leave that episode's features out of the reference (leave-one-episode-out).
    The Mahalanobis distance is the run-time context distance (`runtime.calibration.ContextStatistics`):
    `statistics` is what `--score=context_distance` saves with the calibration. The k-NN distance of a held-out
    feature is the run-time context k-NN distance (`runtime.calibration.ContextNeighbours`): `neighbours` is
    what `--score=context_knn` saves with the calibration.
    """

    statistics: ContextStatistics
    scale: np.ndarray
    reference: np.ndarray
    reference_ids: list
    neighbours: ContextNeighbours
    k: int = DEFAULT_KNN_K
    # Mahalanobis's statistics without one episode, by episode id, fitted when first needed.
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
        neighbours = ContextNeighbours.fit(
            features, k
        )  # the std is floored: constant dimensions carry no distance
        scale = neighbours.std
        reference = (features - statistics.mean) / scale
        return cls(statistics, scale, reference, list(episode_ids), neighbours, k)

    def _same_episode(self, episode_id: Hashable) -> np.ndarray:
        return np.array([i == episode_id for i in self.reference_ids])

    def mahalanobis(self, features: np.ndarray, episode_id: Hashable = None) -> np.ndarray:
        """Mahalanobis distance of each feature to the reference features outside episode `episode_id`.

        A calibration episode's distances come from a mean and covariance refitted without its features
        (cached per episode); with fewer than two features left, the full fit is used.
        """
        statistics = self.statistics
        same_episode = self._same_episode(episode_id)
        if same_episode.any() and np.sum(~same_episode) >= 2:
            if episode_id not in self._left_out:
                others = self.reference[~same_episode] * self.scale + self.statistics.mean
                self._left_out[episode_id] = ContextStatistics.fit(others)
            statistics = self._left_out[episode_id]
        return statistics.distance(features)

    def knn(self, features: np.ndarray, episode_id: Hashable = None) -> np.ndarray:
        """Distance of each feature to its k-th nearest reference feature outside episode `episode_id`."""
        queries = (np.asarray(features, dtype=np.float64) - self.statistics.mean) / self.scale
        return kth_nearest_distance(queries, self.reference, self.k, self._same_episode(episode_id))


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


@dataclass
class ScoreReference:
    """What the reference scores learn from the calibration episodes (`fit_score_reference`)."""

    phase: PhaseEnergyModel
    features: ContextFeatureModel | None = None


def available_scores(episodes: Sequence[Episode]) -> list[str]:
    """The scores every chunk of `episodes` has the data for, in `SCORE_NAMES` order."""
    records = [r for episode in episodes for r in episode]
    names = ["final_energy", "phase_energy", "initial_energy"]
    if records and all(r.normalized_energy is not None for r in records):
        names.append("normalized_energy")
    if records and all(r.restart_spread is not None for r in records):
        names.append("restart_spread")
    if records and all(r.context_feature is not None for r in records):
        names += list(FEATURE_SCORES)
    return names


def fit_feature_model(episodes: Mapping[Hashable, Episode], k: int = DEFAULT_KNN_K) -> ContextFeatureModel:
    """Fits the feature baselines on the context features of every chunk of the (calibration) episodes."""
    features = [r.context_feature for episode in episodes.values() for r in episode]
    ids = [key for key, episode in episodes.items() for _ in episode]
    return ContextFeatureModel.fit(np.stack(features), ids, k=k)


def fit_phase_model(episodes: Mapping[Hashable, Episode]) -> PhaseEnergyModel:
    """Fits the phase energy on the final energies of the (calibration) episodes, by chunk index."""
    energies = {}
    for key, episode in episodes.items():
        # A missing chunk index stays NaN, which the fit leaves out like any non-finite energy.
        series = np.full(max((r.chunk_index for r in episode), default=-1) + 1, np.nan)
        series[[r.chunk_index for r in episode]] = [r.final_energy for r in episode]
        energies[key] = series
    return PhaseEnergyModel(energies)


def fit_score_reference(
    episodes: Mapping[Hashable, Episode], knn_k: int = DEFAULT_KNN_K, features: bool = True
) -> ScoreReference:
    """Fits the reference scores on calibration episodes; the feature baselines only with `features`."""
    return ScoreReference(fit_phase_model(episodes), fit_feature_model(episodes, knn_k) if features else None)
