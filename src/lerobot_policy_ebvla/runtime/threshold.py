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
mean over one chunk spreads more than over N. `ChunkWindow` turns those N running scores into one window score,
so that one T fitted as above bounds the alarms of all N decisions together.
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


@dataclass(frozen=True)
class ChunkWindow:
    """The window score of a rollout's first N chunks: one score for the N decisions a run-time monitor makes.

    After its n-th chunk a rollout has the running score s_n (its chunk scores so far, aggregated). A T fitted on
    the calibration rollouts' s_N alone holds its false-alarm rate at chunk N only: s_1 and s_2 spread more, and
    compared to the same T they flag many more vanilla rollouts early. The window score

        W = max_{n <= min(N, chunks so far)} (s_n - mu_n) / sigma_n

    standardizes each s_n by mu_n and sigma_n (population std) of the calibration rollouts' s_n, so a T fitted on
    the calibration rollouts' W bounds the share of in-distribution rollouts alarmed at any of their first N
    chunks (with the conformal rule, at most alpha). W stops changing after chunk N: the decision stands.

    Attributes:
        means: (mu_1, ..., mu_N).
        stds: (sigma_1, ..., sigma_N), each > 0.
    """

    means: tuple[float, ...]
    stds: tuple[float, ...]

    def __post_init__(self):
        object.__setattr__(self, "means", tuple(float(m) for m in self.means))
        object.__setattr__(self, "stds", tuple(float(s) for s in self.stds))
        if not self.means or len(self.means) != len(self.stds):
            raise ValueError(
                f"`means` and `stds` of a chunk window must be N >= 1 values each, got {len(self.means)} and "
                f"{len(self.stds)}."
            )
        if not all(math.isfinite(m) for m in self.means) or not all(
            math.isfinite(s) and s > 0 for s in self.stds
        ):
            raise ValueError(
                f"A chunk window's `means` must be finite and its `stds` finite and > 0, got {self.means} and "
                f"{self.stds}."
            )

    @property
    def chunks(self) -> int:
        """N, the chunks the window spans."""
        return len(self.means)

    @classmethod
    def fit(cls, running_scores: ArrayLike) -> "ChunkWindow":
        """mu_n and sigma_n of (R, N) calibration running scores (row r: s_1..s_N of rollout r).

        A rollout with a non-finite running score is left out with a warning, as `finite_scores` does. A
        sigma_n of 0 (one rollout, or identical scores) is raised to machine epsilon times max(1, |mu_n|), so
        that W stays defined.
        """
        running = _running_matrix(running_scores)
        finite = np.isfinite(running).all(axis=1)
        if not finite.all():
            warnings.warn(
                f"Leaving {int((~finite).sum())} rollout(s) with a non-finite running score out of the window.",
                stacklevel=2,
            )
        running = running[finite]
        if running.shape[0] == 0:
            raise ValueError("Cannot fit a chunk window without a rollout whose running scores are finite.")
        means = running.mean(axis=0)
        return cls(tuple(means), tuple(_positive(running.std(axis=0), means)))

    def score(self, running_scores: ArrayLike) -> float:
        """W of one rollout from its running scores s_1..s_n (n >= 1; the first N count). NaN if one is NaN."""
        running = as_array(running_scores)[: self.chunks]
        if running.size == 0:
            raise ValueError("The window score needs the running score of at least one chunk.")
        z = (running - np.asarray(self.means[: running.size])) / np.asarray(self.stds[: running.size])
        return float(np.nan if np.isnan(z).any() else z.max())

    def scores(self, running_scores: ArrayLike) -> np.ndarray:
        """(R,) W of each row of (R, N) running scores."""
        return np.array([self.score(row) for row in _running_matrix(running_scores, self.chunks)])

    @staticmethod
    def leave_one_out_scores(running_scores: ArrayLike) -> np.ndarray:
        """(R,) W of each calibration rollout standardized by the window of the other R - 1, as a new rollout
        would be (its own s_n would pull mu_n toward it). With R = 1, the window of the one rollout."""
        running = _running_matrix(running_scores)
        if running.shape[0] == 1:
            return ChunkWindow.fit(running).scores(running)
        return np.array(
            [
                ChunkWindow.fit(np.delete(running, r, axis=0)).score(running[r])
                for r in range(running.shape[0])
            ]
        )


def _running_matrix(running_scores: ArrayLike, chunks: int | None = None) -> np.ndarray:
    running = (
        running_scores.detach().to("cpu", torch.float64).numpy()
        if isinstance(running_scores, Tensor)
        else np.asarray(running_scores, dtype=np.float64)
    )
    if running.ndim != 2 or running.shape[1] < 1 or (chunks is not None and running.shape[1] != chunks):
        expected = "N >= 1" if chunks is None else f"N = {chunks}"
        raise ValueError(
            f"Running scores must be (R, {expected}): s_1..s_N of each rollout; got shape {running.shape}."
        )
    return running


def _positive(stds: np.ndarray, means: np.ndarray) -> np.ndarray:
    return np.maximum(stds, np.finfo(np.float64).eps * np.maximum(1.0, np.abs(means)))
