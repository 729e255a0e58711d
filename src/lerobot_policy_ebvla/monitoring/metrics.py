"""Detection metrics shared by OOD detection (Table III), failure prediction (Table IV) and the baselines.

Positives are the samples a detector should flag: OOD rollouts in Table III, failed episodes in Table IV.
A rate whose denominator is zero (no positives, no negatives, ...) is NaN, never an exception.
"""

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..runtime.threshold import ArrayLike, as_array, exceeds


def ratio(numerator: float, denominator: float) -> float:
    return numerator / denominator if denominator > 0 else math.nan


def percent(value: float, digits: int = 1) -> str:
    return "nan" if math.isnan(value) else f"{100 * value:.{digits}f}%"


def wilson_interval(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """The Wilson score interval (95% at z = 1.96) of a success rate: honest at the small n of rollouts,
    where the normal approximation gives bounds outside [0, 1]. (NaN, NaN) for n = 0."""
    if n == 0:
        return math.nan, math.nan
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(0.0, centre - half), min(1.0, centre + half)


def markdown_table(headers: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(str(cell) for cell in row) + " |" for row in rows]
    return "\n".join(lines)


@dataclass(frozen=True)
class BinaryRates:
    """Confusion counts of a detector and the rates Tables III and IV report (fractions in [0, 1])."""

    tp: int
    fp: int
    tn: int
    fn: int

    @classmethod
    def from_flags(cls, negative_flags: np.ndarray, positive_flags: np.ndarray) -> "BinaryRates":
        """Counts from the detector's decisions on the negatives and on the positives."""
        tp, fp = int(np.sum(positive_flags)), int(np.sum(negative_flags))
        return cls(tp=tp, fp=fp, tn=int(np.size(negative_flags)) - fp, fn=int(np.size(positive_flags)) - tp)

    @classmethod
    def from_scores(
        cls, negative_scores: ArrayLike, positive_scores: ArrayLike, threshold: float
    ) -> "BinaryRates":
        """Counts of the rule "flag when score > threshold" (`runtime.threshold.exceeds`) on both classes.

        Either side may be empty: its rate is then NaN (the FPR of held-out negatives alone, say).
        """
        return cls.from_flags(exceeds(negative_scores, threshold), exceeds(positive_scores, threshold))

    @property
    def n(self) -> int:
        return self.tp + self.fp + self.tn + self.fn

    @property
    def n_positive(self) -> int:
        return self.tp + self.fn

    @property
    def accuracy(self) -> float:
        return ratio(self.tp + self.tn, self.n)

    @property
    def tpr(self) -> float:
        """Catch rate (recall, sensitivity)."""
        return ratio(self.tp, self.tp + self.fn)

    @property
    def fpr(self) -> float:
        """False-alarm rate."""
        return ratio(self.fp, self.fp + self.tn)

    @property
    def specificity(self) -> float:
        return ratio(self.tn, self.fp + self.tn)

    @property
    def balanced_accuracy(self) -> float:
        return (self.tpr + self.specificity) / 2.0  # NaN if either class is empty

    @property
    def f1(self) -> float:
        return ratio(2 * self.tp, 2 * self.tp + self.fp + self.fn)


def _check_no_nan(scores: np.ndarray, name: str) -> None:
    if np.isnan(scores).any():
        raise ValueError(f"`{name}` contains NaN scores; they cannot be ranked.")


def _pairwise_wins(negatives: np.ndarray, positives: np.ndarray) -> np.ndarray:
    """(n_pos, n_neg): 1 where the positive scores higher, 1/2 on a tie (inf ties with inf), 0 otherwise."""
    return (positives[:, None] > negatives[None, :]) + 0.5 * (positives[:, None] == negatives[None, :])


def _stratified_bootstrap_interval(
    wins: np.ndarray, n_resamples: int, level: float, seed: int
) -> tuple[float, float]:
    """Percentile interval of the mean of (n_pos, n_neg) pairwise `wins` over rollouts resampled within each class."""
    n_positive, n_negative = wins.shape
    rng = np.random.default_rng(seed)
    # A resample is a count per rollout; its mean is the count-weighted mean of the pairwise wins.
    pos_counts = rng.multinomial(n_positive, np.full(n_positive, 1 / n_positive), n_resamples)
    neg_counts = rng.multinomial(n_negative, np.full(n_negative, 1 / n_negative), n_resamples)
    means = np.sum((pos_counts @ wins) * neg_counts, axis=1) / (n_positive * n_negative)
    tail = 100 * (1 - level) / 2
    low, high = np.percentile(means, [tail, 100 - tail])
    return float(low), float(high)


def auroc(negative_scores: ArrayLike, positive_scores: ArrayLike) -> float:
    """Area under the ROC curve: the probability that a positive scores higher than a negative.

    The Mann-Whitney U statistic; a tie counts one half. NaN when either set is empty.

    Raises:
        ValueError: A score is NaN.
    """
    negatives, positives = as_array(negative_scores), as_array(positive_scores)
    _check_no_nan(negatives, "negative_scores")
    _check_no_nan(positives, "positive_scores")
    if negatives.size == 0 or positives.size == 0:
        return math.nan
    return float(_pairwise_wins(negatives, positives).mean())


def bootstrap_auroc_interval(
    negative_scores: ArrayLike,
    positive_scores: ArrayLike,
    n_resamples: int = 1000,
    level: float = 0.95,
    seed: int = 0,
) -> tuple[float, float]:
    """Percentile bootstrap interval of the AUROC, resampling each class with replacement (stratified).

    Rollouts (episodes) are the resampled unit, so the interval reflects how many were run. The generator is
    seeded: the same inputs give the same interval.

    Returns:
        (low, high); NaN when either set is empty.
    """
    negatives, positives = as_array(negative_scores), as_array(positive_scores)
    _check_no_nan(negatives, "negative_scores")
    _check_no_nan(positives, "positive_scores")
    if negatives.size == 0 or positives.size == 0:
        return math.nan, math.nan
    return _stratified_bootstrap_interval(_pairwise_wins(negatives, positives), n_resamples, level, seed)


def bootstrap_auroc_difference_interval(
    negative_scores: ArrayLike,
    positive_scores: ArrayLike,
    other_negative_scores: ArrayLike,
    other_positive_scores: ArrayLike,
    n_resamples: int = 1000,
    level: float = 0.95,
    seed: int = 0,
) -> tuple[float, float]:
    """Paired percentile bootstrap interval of AUROC(first score) - AUROC(other score) on the same rollouts.

    Both scores are read on the same rollouts, in the same order, so each resample draws one count per rollout
    (stratified by class, as `bootstrap_auroc_interval`) and applies it to both: the interval is of the difference,
    which is narrower than the two intervals side by side because the rollouts that are hard for one are mostly
    hard for the other. An interval wholly below 0: the first score is below the other beyond resampling noise.

    Returns:
        (low, high); NaN when either class is empty.

    Raises:
        ValueError: The two scores were not read on as many negatives and positives, or a score is NaN.
    """
    scores = [
        as_array(s) for s in (negative_scores, positive_scores, other_negative_scores, other_positive_scores)
    ]
    names = ("negative_scores", "positive_scores", "other_negative_scores", "other_positive_scores")
    for values, name in zip(scores, names, strict=True):
        _check_no_nan(values, name)
    negatives, positives, other_negatives, other_positives = scores
    if negatives.shape != other_negatives.shape or positives.shape != other_positives.shape:
        raise ValueError(
            f"A paired interval needs both scores on the same rollouts: got {negatives.size} and "
            f"{other_negatives.size} negatives, {positives.size} and {other_positives.size} positives."
        )
    if negatives.size == 0 or positives.size == 0:
        return math.nan, math.nan
    wins = _pairwise_wins(negatives, positives) - _pairwise_wins(other_negatives, other_positives)
    return _stratified_bootstrap_interval(wins, n_resamples, level, seed)


def format_auroc(
    negative_scores: ArrayLike, positive_scores: ArrayLike, n_resamples: int = 1000, seed: int = 0
) -> str:
    """The AUROC with its bootstrap 95% interval, as the reports print it: "0.875 [0.700, 1.000]"."""
    low, high = bootstrap_auroc_interval(negative_scores, positive_scores, n_resamples, seed=seed)
    return f"{auroc(negative_scores, positive_scores):.3f} [{low:.3f}, {high:.3f}]"


def marked_auroc(
    negative_scores: ArrayLike, positive_scores: ArrayLike, n_resamples: int = 1000
) -> tuple[str, float]:
    """The AUROC with its bootstrap 95% interval at two decimals, "!" where the interval lies wholly below 0.5
    (confidently wrong): "0.16 [0.05, 0.29]!"; and the AUROC."""
    value = auroc(negative_scores, positive_scores)
    low, high = bootstrap_auroc_interval(negative_scores, positive_scores, n_resamples)
    return f"{value:.2f} [{low:.2f}, {high:.2f}]{'!' if high < 0.5 else ''}", value


def roc_curve(
    negative_scores: ArrayLike, positive_scores: ArrayLike
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ROC curve of the rule "flag when score > T" over every distinct threshold.

    Returns:
        (fpr, tpr, thresholds), each of length n_distinct + 1. The first threshold is the highest score
        (nothing flagged, the point (0, 0)); each next one is the next lower distinct score; the last is
        -inf (everything flagged, the point (1, 1)). Rates are NaN when their class is empty.

    Raises:
        ValueError: A score is NaN.
    """
    negatives, positives = as_array(negative_scores), as_array(positive_scores)
    _check_no_nan(negatives, "negative_scores")
    _check_no_nan(positives, "positive_scores")
    thresholds = np.r_[np.unique(np.concatenate([negatives, positives]))[::-1], -np.inf]
    # searchsorted on sorted scores counts, for every threshold at once, the scores above it.
    n_pos_above = positives.size - np.searchsorted(np.sort(positives), thresholds, side="right")
    n_neg_above = negatives.size - np.searchsorted(np.sort(negatives), thresholds, side="right")
    nan = np.full(thresholds.size, np.nan)
    tpr = n_pos_above / positives.size if positives.size else nan
    fpr = n_neg_above / negatives.size if negatives.size else nan
    return fpr.astype(np.float64), tpr.astype(np.float64), thresholds
