"""Per-episode scores: the one way every report, summary and benchmark turns chunk records into a score.

Each chunk of an episode has a score (its final energy, the paper's; or another score of `baselines.py`), and
an episode's score aggregates its chunks in order as the run-time monitor does
(`runtime.scores.rollout_score`), over all its chunks or over its first k only (what a monitor has seen k
chunks into the episode).

The combined scores (`baselines.COMBINED_SCORES`) are rollout scores only: `combined_rollout_scores` forms them
from the rollout scores of the final energy and the context distance. So are the registered run-time scores
`baselines.py` has no baseline of (`baselines.registered_scores`): their chunks' components are aggregated and
combined by their class (`registered_rollout_scores`), as the run-time monitor does.
"""

from collections.abc import Hashable, Mapping

import numpy as np

from ..runtime.scores import ChunkScore, reading_of, rollout_score, score_rollout
from ..runtime.statistics import CombinedStatistics
from .baselines import (
    COMBINED_FROM,
    COMBINED_SCORES,
    FEATURE_SCORES,
    REFERENCE_SCORES,
    SCORE_NAMES,
    ScoreReference,
)
from .records import Episode


def chunk_scores(
    episode: Episode,
    score: str,
    reference: ScoreReference | None = None,
    episode_id: Hashable = None,
) -> np.ndarray:
    """The per-chunk scores of one episode, in chunk order.

    Args:
        episode: The episode's chunk records, in chunk order.
        score: One of `baselines.SCORE_NAMES`.
        reference: The calibration episodes' fit, needed by the reference scores (`REFERENCE_SCORES`).
        episode_id: The episode's key; a calibration episode is then scored leave-one-episode-out.
    """
    if score in COMBINED_SCORES:
        raise ValueError(
            f"{score!r} combines rollout scores and has no chunk score: use `combined_rollout_scores`."
        )
    if score not in SCORE_NAMES:
        raise ValueError(f"`score` must be one of {SCORE_NAMES}, got {score!r}.")
    if score in REFERENCE_SCORES and (
        reference is None or (score in FEATURE_SCORES and not reference.features)
    ):
        raise ValueError(f"Score {score!r} needs a `reference` fitted on calibration episodes.")
    if score == "phase_energy":
        energies = np.array([r.final_energy for r in episode], dtype=np.float64)
        return reference.phase.score(energies, np.array([r.chunk_index for r in episode]), episode_id)
    if score in FEATURE_SCORES:
        features = np.stack([r.context_feature for r in episode])
        if score == "context_distance":
            return reference.features.context_distance(features, episode_id)
        return reference.features.context_knn(features, episode_id)
    return np.array([getattr(r, score) for r in episode], dtype=np.float64)


def episode_chunk_scores(
    episodes: Mapping[Hashable, Episode], score: str, reference: ScoreReference | None = None
) -> dict[Hashable, np.ndarray]:
    """The per-chunk scores of every episode, by key (`chunk_scores`, the key as `episode_id`).

    Compute them once and aggregate them in several ways with `aggregate_episodes`: a chunk's score does not
    depend on how many of the episode's chunks are aggregated.
    """
    return {key: chunk_scores(episode, score, reference, key) for key, episode in episodes.items()}


def _check_first_chunks(first_chunks: int | None) -> None:
    if first_chunks is not None and first_chunks < 1:
        raise ValueError(f"`first_chunks` must be >= 1 or None, got {first_chunks}.")


def aggregate_episodes(
    scores: Mapping[Hashable, np.ndarray], aggregation: str = "mean", first_chunks: int | None = None
) -> np.ndarray:
    """One rollout score per episode (in `scores` order) from its chunk scores, over its first k chunks or all.

    Args:
        scores: Each episode's chunk scores, in chunk order (`episode_chunk_scores`).
        aggregation: How the chunk scores form the episode's (`rollout_score`).
        first_chunks: Aggregate each episode's first k chunks only; an episode shorter than k uses all its
            chunks. None aggregates whole episodes.
    """
    _check_first_chunks(first_chunks)
    return np.array([rollout_score(s[:first_chunks], aggregation) for s in scores.values()])


def episode_scores(
    episodes: Mapping[Hashable, Episode],
    score: str,
    aggregation: str = "mean",
    reference: ScoreReference | None = None,
    first_chunks: int | None = None,
) -> np.ndarray:
    """One rollout score per episode (in `episodes` order) for the named score.

    Args:
        episodes: Episodes by key, each its chunk records in chunk order.
        score: One of `baselines.SCORE_NAMES`, or a registered score `reference` was fitted for.
        aggregation: How the chunk scores form the episode's (`rollout_score`).
        reference: See `chunk_scores`.
        first_chunks: Score each episode over its first k chunks only; an episode shorter than k uses all
            its chunks. None scores whole episodes.
    """
    if reference is not None and score in reference.registered:
        model = reference.registered[score]
        components = {key: model.components(episode, key) for key, episode in episodes.items()}
        return registered_rollout_scores(components, aggregation, first_chunks)
    return aggregate_episodes(episode_chunk_scores(episodes, score, reference), aggregation, first_chunks)


def registered_rollout_scores(
    components: Mapping[Hashable, tuple[ChunkScore, np.ndarray]],
    aggregation: str = "mean",
    first_chunks: int | None = None,
) -> np.ndarray:
    """One rollout score per episode of a registered score, from each episode's fitted score and chunk
    components (`baselines.RegisteredScoreModel.components`), over its first k chunks or all; a score with its
    own reading (`ChunkScore.rollout_aggregation`) is aggregated that way."""
    _check_first_chunks(first_chunks)
    return np.array(
        [score_rollout(s, c[:first_chunks], reading_of(s, aggregation)) for s, c in components.values()]
    )


def combined_rollout_scores(
    score: str, rollout_scores: Mapping[str, np.ndarray], calibration_scores: Mapping[str, np.ndarray]
) -> np.ndarray:
    """The rollout scores of a combined score (`baselines.COMBINED_SCORES`), one per rollout.

    Each of the final energy's and the context distance's rollout scores is standardized by the mean and std
    of the calibration rollouts' (`CombinedStatistics`, as the run-time "energy_and_context" is); the z's are
    then combined: their max ("energy_and_context") or their sum ("energy_and_context_sum").

    Args:
        score: One of `baselines.COMBINED_SCORES`.
        rollout_scores: The rollouts' "final_energy" and "context_distance" scores, aggregated alike (e.g.
            over the same first chunks), one entry per rollout.
        calibration_scores: The calibration rollouts' scores of the same two names, aggregated the same way.

    Raises:
        ValueError: An unknown score, or a score to combine missing.
    """
    if score not in COMBINED_SCORES:
        raise ValueError(f"`score` must be one of {COMBINED_SCORES}, got {score!r}.")
    for name, scores in (("rollout_scores", rollout_scores), ("calibration_scores", calibration_scores)):
        missing = [n for n in COMBINED_FROM if n not in scores]
        if missing:
            raise ValueError(
                f"`{name}` needs the scores {list(COMBINED_FROM)} to combine; missing {missing}."
            )
    statistics = CombinedStatistics.fit(*(calibration_scores[n] for n in COMBINED_FROM))
    z = statistics.z(*(rollout_scores[n] for n in COMBINED_FROM))
    return z.max(axis=1) if score == "energy_and_context" else z.sum(axis=1)
