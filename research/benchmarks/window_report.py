"""The window typicality test (`window_monitor`) on recorded rollouts: how often windows of n rollouts alarm.

One run is a calibration set, a reference set (vanilla rollouts scored against the calibration's fit, the
test's reference), held-out vanilla rollouts (the false alarms) and conditions. Every window of n rollouts of a
set (all C(N, n) of them, or `max_windows` drawn without repeats when there are more) is tested, and the share
that is atypical is the set's window alarm rate. Beside it, per rollout: the score's AUROC against the held-out
vanilla and its alarm rate at the shipped T = mu_v + k sigma_v, so a condition the per-rollout score misses or
inverts can be read against what the window makes of it. `window_typicality.py` beside it is the command.
"""

import itertools
import math
from collections.abc import Hashable, Mapping
from dataclasses import dataclass

import numpy as np
from window_monitor import SHIFTED, TOO_TYPICAL, WindowTypicalityTest, window_values

from lerobot_policy_ebvla.monitoring.baselines import (
    episode_readout,
    every_chunk_has,
    fit_score_reference,
    registered_scores,
    vanilla_rollouts,
)
from lerobot_policy_ebvla.monitoring.metrics import BinaryRates, markdown_table, marked_auroc, percent
from lerobot_policy_ebvla.monitoring.ood_sections import successes
from lerobot_policy_ebvla.monitoring.records import Episode
from lerobot_policy_ebvla.monitoring.scores import episode_scores
from lerobot_policy_ebvla.runtime.calibration import OODCalibration
from lerobot_policy_ebvla.runtime.scores import SCORES

# At most this many windows of a set are tested; C(40, 8) is 77 million.
DEFAULT_MAX_WINDOWS = 5000


def window_indices(n_rollouts: int, window: int, max_windows: int, seed: int = 0) -> list[tuple[int, ...]]:
    """Every window of `window` of `n_rollouts` rollouts, or `max_windows` distinct ones drawn at random."""
    if n_rollouts < window:
        return []
    if math.comb(n_rollouts, window) <= max_windows:
        return list(itertools.combinations(range(n_rollouts), window))
    rng = np.random.default_rng(seed)
    drawn: set[tuple[int, ...]] = set()
    while len(drawn) < max_windows:
        drawn.add(tuple(sorted(rng.choice(n_rollouts, window, replace=False).tolist())))
    return sorted(drawn)


@dataclass(frozen=True)
class WindowRates:
    """How many windows of a set were tested, the share alarmed, and the shares alarmed as too typical and as
    shifted (`window_monitor`'s sides)."""

    n_windows: int
    alarmed: float
    too_typical: float
    shifted: float

    @classmethod
    def of(
        cls, test: WindowTypicalityTest, rollout_values: np.ndarray, max_windows: int, seed: int = 0
    ) -> "WindowRates":
        """Over the windows of a set's rollouts' window values, (N, m)."""
        decisions = [
            test.check(rollout_values[list(w)])
            for w in window_indices(len(rollout_values), test.window, max_windows, seed)
        ]
        if not decisions:
            return cls(0, math.nan, math.nan, math.nan)
        return cls(
            len(decisions),
            float(np.mean([d.is_atypical for d in decisions])),
            float(np.mean([d.side == TOO_TYPICAL for d in decisions])),
            float(np.mean([d.side == SHIFTED for d in decisions])),
        )


def window_values_of(
    calibration: OODCalibration, episodes: Mapping[Hashable, Episode], first_chunks: int | None = None
) -> np.ndarray:
    """(M, m): each episode's `window_monitor.window_values` against the calibration's fitted score, over its
    first k chunks (None: the whole episode), in `episodes` order: with held-out vanilla episodes, the window
    test's reference."""
    return np.stack(
        [
            window_values(calibration, calibration.chunk_components(episode_readout(episode))[:first_chunks])
            for episode in episodes.values()
        ]
    )


@dataclass
class ScoredSet:
    """A set's episodes, their rollout scores and their window values against one calibration."""

    episodes: Mapping[Hashable, Episode]
    scores: np.ndarray
    values: np.ndarray


def score_sets(
    calibration: Mapping[Hashable, Episode],
    sets: Mapping[str, Mapping[Hashable, Episode]],
    score: str,
    first_chunks: int | None,
    aggregation: str = "mean",
) -> tuple[OODCalibration, dict[str, ScoredSet]]:
    """The calibration `ebvla-ood-report --calibrate_to` would save for `score` (T from the calibration rollouts'
    leave-one-out scores, the score fitted on all of them) and each set scored against it, over each episode's
    first k chunks (None: whole episodes)."""
    registered = [score] if score in registered_scores() else []
    features = every_chunk_has(list(calibration.values()), "context_feature")
    reference = fit_score_reference(
        calibration, features=features, registered=registered, aggregation=aggregation
    )
    fitted = OODCalibration.fit(
        episode_scores(calibration, score, aggregation, reference, first_chunks),
        aggregation=aggregation,
        score=SCORES[score].fit(vanilla_rollouts(calibration, aggregation)),
    )
    return fitted, {
        name: ScoredSet(
            episodes,
            episode_scores(episodes, score, aggregation, reference, first_chunks),
            window_values_of(fitted, episodes, first_chunks),
        )
        for name, episodes in sets.items()
    }


def window_table(
    test: WindowTypicalityTest,
    threshold: float,
    vanilla: ScoredSet,
    conditions: Mapping[str, ScoredSet],
    max_windows: int = DEFAULT_MAX_WINDOWS,
    n_bootstrap: int = 1000,
) -> str:
    """The held-out vanilla rollouts, then each condition: success, the per-rollout AUROC [95% interval] and
    alarm rate at T, and the share of its windows alarmed (of them, too typical / shifted). A "!" marks a
    per-rollout AUROC whose interval lies wholly under 0.5 (confidently wrong)."""

    def row(name, scored, area):
        rates = WindowRates.of(test, scored.values, max_windows)
        return [
            name,
            str(len(scored.scores)),
            successes(scored.episodes),
            area,
            percent(BinaryRates.from_scores([], scored.scores, threshold).tpr, 0),
            f"{percent(rates.alarmed, 0)} ({percent(rates.too_typical, 0)} / {percent(rates.shifted, 0)}) "
            f"of {rates.n_windows}",
        ]

    rows = [row("held-out vanilla", vanilla, "")]
    for name, scored in conditions.items():
        rows.append(row(name, scored, marked_auroc(vanilla.scores, scored.scores, n_bootstrap)[0]))
    headers = [
        "Set",
        "n",
        "success",
        "rollout AUROC",
        "rollout alarms at T",
        f"windows of {test.window} alarmed (too typical / shifted)",
    ]
    return markdown_table(headers, rows)
