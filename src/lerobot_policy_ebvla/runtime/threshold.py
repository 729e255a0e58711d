"""Where a confidence score becomes a decision: one rule, two ways to set its threshold.

The rule, for every score in this package (a chunk's final energy, a rollout score, an energy slope, a
baseline's score):

    flag when score > T                      (non-finite scores, +inf from a diverged refinement or NaN,
                                              are always flagged: only score <= T passes)

and T comes from scores of the reference (in-distribution, or successful) set in one of two ways:

- `mean_std_threshold`: T = mu + k * sigma, the paper's Eq. 5 (mu_v, sigma_v of the vanilla rollouts).
  sigma is the population standard deviation (ddof=0), so one reference score gives sigma = 0 and T = mu.
- `conformal_threshold`: the split-conformal quantile. With n exchangeable reference scores, T is their
  ceil((n + 1)(1 - alpha))-th smallest; a new in-distribution score then exceeds T with probability at
  most alpha (and at least alpha - 1/(n + 1) when scores have no ties). This states the false-alarm rate
  instead of leaving it to the distribution's shape. When n is too small for the requested alpha
  (ceil((n + 1)(1 - alpha)) > n), no finite threshold guarantees it and T = +inf (nothing is flagged).

A monitor that decides after every chunk on the rollout so far makes N decisions in its first N chunks, and a
mean over one chunk spreads more than over N: `statistics.ChunkWindow` turns those N running scores into one
window score, so that one T fitted as above bounds the alarms of all N decisions together.
"""

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

ArrayLike = Sequence[float] | np.ndarray | Tensor


def as_array(values: ArrayLike | float) -> np.ndarray:
    """Scores as a 1-D float64 array (tensors are detached and moved to the CPU)."""
    if isinstance(values, Tensor):
        values = values.detach().to("cpu", torch.float64).numpy()
    return np.atleast_1d(np.asarray(values, dtype=np.float64))


def exceeds(scores: ArrayLike | float, threshold: float) -> np.ndarray:
    """The decision rule: True where score > threshold, and where the score is not finite (NaN, +inf)."""
    # `~(s <= T)` rather than `s > T`: NaN compares False both ways, so it is flagged.
    return ~(as_array(scores) <= threshold)


def finite_scores(scores: ArrayLike, what: str) -> np.ndarray:
    """The finite scores, warning about the others: one +inf would make mu (and a quantile) infinite."""
    scores = as_array(scores)
    finite = scores[np.isfinite(scores)]
    if finite.size < scores.size:
        warnings.warn(
            f"Leaving {scores.size - finite.size} non-finite {what} score(s) out of the threshold.",
            stacklevel=3,
        )
    if finite.size == 0:
        raise ValueError(f"Cannot set a threshold without a finite {what} score.")
    return finite


@dataclass(frozen=True)
class MeanStd:
    """mu and sigma (population std) of the finite reference scores, and how many there were."""

    mean: float
    std: float
    n: int

    @classmethod
    def fit(cls, scores: ArrayLike, what: str = "reference") -> "MeanStd":
        finite = finite_scores(scores, what)
        return cls(float(finite.mean()), float(finite.std()), int(finite.size))

    def threshold(self, k: float) -> float:
        return mean_std_threshold(self.mean, self.std, k)


def mean_std_threshold(mu: float, sigma: float, k: float) -> float:
    """T = mu + k * sigma (Eq. 5)."""
    return mu + k * sigma


def conformal_threshold(reference_scores: ArrayLike, alpha: float, what: str = "reference") -> float:
    """The (1 - alpha) split-conformal quantile of the reference scores, with the finite-sample correction.

    Args:
        reference_scores: Scores of in-distribution samples not used for anything else (non-finite ones are
            left out with a warning).
        alpha: The target false-alarm rate, in (0, 1).

    Returns:
        T such that P(score > T) <= alpha for a new exchangeable in-distribution score; +inf when there are
        fewer than 1/alpha - 1 reference scores.
    """
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"`alpha` (the false-alarm rate) must be in (0, 1), got {alpha}.")
    finite = np.sort(finite_scores(reference_scores, what))
    n = finite.size
    # 1-based rank; the tolerance keeps e.g. (19 + 1) * 0.95 at 19 despite 0.95's binary rounding.
    rank = math.ceil((n + 1) * (1.0 - alpha) - 1e-9)
    return math.inf if rank > n else float(finite[rank - 1])


@dataclass(frozen=True)
class OODDecision:
    """The rule's verdict on B scores (B chunks, or B environments' rollouts so far) and the response to it.

    The policy leaves one per refined chunk batch in `policy.last_ood_decision`; `EnergyOODMonitor` answers
    one per chunk or rollout (B = 1).

    Attributes:
        scores: (B,) the scores checked: the calibration's chunk scores, or rollout scores.
        threshold: The threshold T they were compared to.
        flagged: (B,) bool, the score exceeds T or is not finite (`exceeds`).
        held: (B,) bool, the chunk was replaced by the hold action (flagged and `response == "hold"`).
        response: The policy's `monitor.response` to the flagged chunks ("continue", "hold" or "raise"); None for
            a decision that nothing acts on (the monitor's).
    """

    scores: Tensor
    threshold: float
    flagged: Tensor
    held: Tensor
    response: str | None = None

    @classmethod
    def of(cls, scores: ArrayLike | float, threshold: float, response: str | None = None) -> "OODDecision":
        """Applies the rule to scores (kept in their dtype: a float32 chunk score is compared as it is)."""
        scores = (scores if isinstance(scores, Tensor) else torch.from_numpy(as_array(scores))).reshape(-1)
        flagged = torch.from_numpy(exceeds(scores, threshold))
        held = flagged if response == "hold" else torch.zeros_like(flagged)
        return cls(scores, float(threshold), flagged, held, response)

    @property
    def is_ood(self) -> bool:
        """Whether any score was flagged."""
        return bool(self.flagged.any())

    @property
    def in_distribution(self) -> bool:
        """Whether every score is <= T (and finite)."""
        return not self.is_ood

    @property
    def energy(self) -> float:
        """The highest score checked (NaN if one is NaN); of one chunk or rollout, its score."""
        return float(self.scores.max())
