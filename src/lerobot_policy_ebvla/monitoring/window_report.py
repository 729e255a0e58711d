"""The window typicality test (`runtime.window`) on recorded rollouts: how often windows of n rollouts alarm.

One run is a calibration set, a reference set (vanilla rollouts scored against the calibration's fit, the
test's reference), held-out vanilla rollouts (the false alarms) and conditions. Every window of n rollouts of a
set (all C(N, n) of them, or `max_windows` drawn without repeats when there are more) is tested, and the share
that is atypical is the set's window alarm rate. Beside it, per rollout: the score's AUROC against the held-out
vanilla and its alarm rate at the shipped T = mu_v + k sigma_v, so a condition the per-rollout score misses or
inverts can be read against what the window makes of it. `benchmarks/window_typicality.py` is the command.
"""

import itertools
import math
from collections.abc import Hashable, Mapping
from dataclasses import dataclass

import numpy as np

from ..runtime.calibration import OODCalibration
from ..runtime.window import TOO_TYPICAL, WindowTypicalityTest
from .baselines import fit_score_reference, registered_scores
from .metrics import BinaryRates, auroc, bootstrap_auroc_interval, markdown_table, percent
from .records import Episode
from .score_summary import successes
from .scores import episode_scores

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
    """How many windows of a set were tested, the share alarmed, and the share alarmed as too typical."""

    n_windows: int
    alarmed: float
    too_typical: float

    @classmethod
    def of(
        cls, test: WindowTypicalityTest, rollout_scores: np.ndarray, max_windows: int, seed: int = 0
    ) -> "WindowRates":
        decisions = [
            test.check(rollout_scores[list(w)])
            for w in window_indices(len(rollout_scores), test.window, max_windows, seed)
        ]
        if not decisions:
            return cls(0, math.nan, math.nan)
        return cls(
            len(decisions),
            float(np.mean([d.is_atypical for d in decisions])),
            float(np.mean([d.side == TOO_TYPICAL for d in decisions])),
        )


def rollout_scores_of(
    calibration: Mapping[Hashable, Episode],
    sets: Mapping[str, Mapping[Hashable, Episode]],
    score: str,
    first_chunks: int | None,
    aggregation: str = "mean",
) -> tuple[OODCalibration, dict[str, np.ndarray]]:
    """The calibration of `score` (T from its rollouts' leave-one-out scores, as `ebvla-ood-report` fits it) and
    each set's rollout scores against it, over each episode's first k chunks (None: whole episodes)."""
    registered = [score] if score in registered_scores() else []
    features = any(r.context_feature is not None for e in calibration.values() for r in e)
    reference = fit_score_reference(
        calibration, features=features, registered=registered, aggregation=aggregation
    )
    calibration_scores = episode_scores(calibration, score, aggregation, reference, first_chunks)
    fitted = OODCalibration.fit(calibration_scores, aggregation=aggregation)
    return fitted, {
        name: episode_scores(episodes, score, aggregation, reference, first_chunks)
        for name, episodes in sets.items()
    }


def window_table(
    test: WindowTypicalityTest,
    threshold: float,
    vanilla: Mapping[Hashable, Episode],
    vanilla_scores: np.ndarray,
    conditions: Mapping[str, tuple[Mapping[Hashable, Episode], np.ndarray]],
    max_windows: int = DEFAULT_MAX_WINDOWS,
    n_bootstrap: int = 1000,
) -> str:
    """The held-out vanilla rollouts, then each condition: success, the per-rollout AUROC [95% interval] and
    alarm rate at T, and the share of its windows alarmed (of them, too typical). A "!" marks a per-rollout
    AUROC whose interval lies wholly under 0.5 (confidently wrong)."""

    def row(name, episodes, scores, area):
        rates = WindowRates.of(test, scores, max_windows)
        return [
            name,
            str(len(scores)),
            successes(episodes),
            area,
            percent(BinaryRates.from_scores([], scores, threshold).tpr, 0),
            f"{percent(rates.alarmed, 0)} ({percent(rates.too_typical, 0)}) of {rates.n_windows}",
        ]

    rows = [row("held-out vanilla", vanilla, vanilla_scores, "")]
    for name, (episodes, scores) in conditions.items():
        low, high = bootstrap_auroc_interval(vanilla_scores, scores, n_bootstrap)
        area = f"{auroc(vanilla_scores, scores):.2f} [{low:.2f}, {high:.2f}]{'!' if high < 0.5 else ''}"
        rows.append(row(name, episodes, scores, area))
    headers = [
        "Set",
        "n",
        "success",
        "rollout AUROC",
        "rollout alarms at T",
        f"windows of {test.window} alarmed (too typical)",
    ]
    return markdown_table(headers, rows)
