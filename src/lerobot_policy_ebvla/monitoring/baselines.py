"""The post-hoc confidence scores the paper says the final energy replaces, scored from the same records.

Every score is per chunk, higher meaning less confident, and a rollout's score aggregates its chunks as the
final energy's does (`ood.rollout_score`), so all of them go through the same threshold and metrics:

- "final_energy": E(a^(K_inf), C), the paper's score.
- "initial_energy": E(a^(0), C), the energy of the unrefined sample (always recorded).
- "normalized_energy": the final energy plus the log of the mean Boltzmann weight exp(-E) of N chunks drawn
  from the MCMC prior under the same context (recorder option `normalized_energy_samples`): the energy is
  only defined up to a per-context offset, which this Monte-Carlo log-partition removes.
- "restart_spread": the spread of N chunks refined from independent a^(0) for the same observation
  (recorder option `restart_spread_chains`): an ensemble-disagreement score.
- "mahalanobis", "knn": how far the observation's pooled backbone context is from the contexts of the
  calibration rollouts (recorder option `record_context_features`). Mahalanobis uses the calibration
  features' mean and their Ledoit-Wolf shrunk covariance (D can exceed the number of chunks); k-NN is the
  Euclidean distance to the k-th nearest calibration feature, features standardized per dimension by the
  calibration mean and std, skipping features of the same episode so that in-sample scores are not
  trivially zero.
"""

from collections.abc import Hashable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from .ood import rollout_score
from .records import EnergyRecord

SCORE_NAMES = ("final_energy", "initial_energy", "normalized_energy", "restart_spread", "mahalanobis", "knn")
FEATURE_SCORES = ("mahalanobis", "knn")

Episode = Sequence[EnergyRecord]


def _ledoit_wolf(centered: np.ndarray) -> np.ndarray:
    """Ledoit-Wolf (2004) shrinkage of the covariance of (N, D) centered samples toward mu * I."""
    n, d = centered.shape
    sample_cov = centered.T @ centered / n
    mu = np.trace(sample_cov) / d
    squared = centered**2
    beta = (np.sum(squared.T @ squared) / n - np.sum(sample_cov**2)) / n  # sum of the entries' variances
    delta = np.sum((sample_cov - mu * np.eye(d)) ** 2)  # distance of S to the target
    shrinkage = 0.0 if delta == 0 else min(beta, delta) / delta
    return (1 - shrinkage) * sample_cov + shrinkage * mu * np.eye(d)


@dataclass
class ContextFeatureModel:
    """Mahalanobis and k-NN distances of context features to the calibration rollouts' contexts.

    Build it with `fit`; `reference_ids` names the episode of each reference feature.
    """

    mean: np.ndarray
    scale: np.ndarray
    precision: np.ndarray
    reference: np.ndarray
    reference_ids: list
    k: int = 5

    @classmethod
    def fit(cls, features: np.ndarray, episode_ids: Sequence[Hashable], k: int = 5) -> "ContextFeatureModel":
        """Fits on (N, D) calibration features, `episode_ids[i]` the episode of feature i."""
        features = np.asarray(features, dtype=np.float64)
        if features.ndim != 2 or features.shape[0] != len(episode_ids) or features.shape[0] < 2:
            raise ValueError(
                f"`features` must be (N >= 2, D) with one episode id per row; got {features.shape} and "
                f"{len(episode_ids)} ids."
            )
        if k < 1:
            raise ValueError(f"`k` (nearest neighbours) must be >= 1, got {k}.")
        mean = features.mean(axis=0)
        scale = np.maximum(features.std(axis=0), 1e-12)  # constant dimensions carry no distance
        precision = np.linalg.pinv(_ledoit_wolf(features - mean), hermitian=True)
        return cls(mean, scale, precision, (features - mean) / scale, list(episode_ids), k)

    def mahalanobis(self, features: np.ndarray) -> np.ndarray:
        centered = np.asarray(features, dtype=np.float64) - self.mean
        return np.sqrt(np.maximum(np.einsum("nd,de,ne->n", centered, self.precision, centered), 0.0))

    def knn(self, features: np.ndarray, episode_id: Hashable = None) -> np.ndarray:
        """Distance of each feature to its k-th nearest reference feature outside episode `episode_id`."""
        queries = (np.asarray(features, dtype=np.float64) - self.mean) / self.scale
        squared = (queries**2).sum(axis=1)[:, None] - 2 * queries @ self.reference.T
        distances = np.sqrt(np.maximum(squared + (self.reference**2).sum(axis=1)[None, :], 0.0))
        same_episode = np.array([i == episode_id for i in self.reference_ids])
        distances[:, same_episode] = np.inf
        k = min(self.k, int(np.sum(~same_episode)))
        if k == 0:
            return np.full(len(queries), np.inf)
        return np.partition(distances, k - 1, axis=1)[:, k - 1]


def available_scores(episodes: Sequence[Episode]) -> list[str]:
    """The scores every chunk of `episodes` has the data for, in `SCORE_NAMES` order."""
    records = [r for episode in episodes for r in episode]
    names = ["final_energy", "initial_energy"]
    if records and all(r.normalized_energy is not None for r in records):
        names.append("normalized_energy")
    if records and all(r.restart_spread is not None for r in records):
        names.append("restart_spread")
    if records and all(r.context_feature is not None for r in records):
        names += list(FEATURE_SCORES)
    return names


def fit_feature_model(episodes: Mapping[Hashable, Episode], k: int = 5) -> ContextFeatureModel:
    """Fits the feature baselines on the context features of every chunk of the (calibration) episodes."""
    features = [r.context_feature for episode in episodes.values() for r in episode]
    ids = [key for key, episode in episodes.items() for _ in episode]
    return ContextFeatureModel.fit(np.stack(features), ids, k=k)


def chunk_scores(
    episode: Episode,
    score: str,
    feature_model: ContextFeatureModel | None = None,
    episode_id: Hashable = None,
) -> np.ndarray:
    """The per-chunk scores of one episode, in chunk order."""
    if score in FEATURE_SCORES:
        if feature_model is None:
            raise ValueError(f"Score {score!r} needs a `feature_model` fitted on calibration contexts.")
        features = np.stack([r.context_feature for r in episode])
        if score == "mahalanobis":
            return feature_model.mahalanobis(features)
        return feature_model.knn(features, episode_id)
    if score not in SCORE_NAMES:
        raise ValueError(f"`score` must be one of {SCORE_NAMES}, got {score!r}.")
    return np.array([getattr(r, score) for r in episode], dtype=np.float64)


def episode_scores(
    episodes: Mapping[Hashable, Episode],
    score: str,
    aggregation: str = "mean",
    feature_model: ContextFeatureModel | None = None,
) -> np.ndarray:
    """One rollout score per episode (in `episodes` order) for the named score."""
    return np.array(
        [
            rollout_score(chunk_scores(episode, score, feature_model, key), aggregation)
            for key, episode in episodes.items()
        ]
    )
