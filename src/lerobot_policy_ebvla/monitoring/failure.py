"""Energy-based failure prediction (paper Sec. III-D, Table IV).

A rollout predicts one action chunk per "step" (steps are 1-based: step s is the s-th chunk, chunk_index
s - 1). At step s, the slope of an energy series over a window of w steps is the least-squares slope of the
energies of steps max(1, s - w + 1) .. s against their step numbers. *Slope Start* uses the initial energy
E(a^(0), C), *Slope Final* the refined energy E(a^(K_inf), C). A rising final energy means refinement
struggles more and more to find expert-like actions, which the paper finds to precede failure.

The predictor flags an episode as failing at step s when

    slope > mean_ref + k * std_ref,

where mean_ref and std_ref (population std) are the slopes, at the same step and window, of the
*reference episodes*: by default the successful episodes of the evaluated set itself, the one-class analogue
of the vanilla calibration of Eq. 5. Positives are failed episodes.

Choices, stated because the paper leaves them open:
- Episodes with fewer than s chunks have ended before step s and are left out at that step, both from the
  reference statistics and from the metrics. Successful episodes tend to end early, so late steps are
  judged on fewer, mostly failing, episodes.
- When the window reaches before step 1 it is truncated to the steps available. A slope of fewer than two
  points is 0 ("no trend yet"); at step 1 every slope is 0 and nothing is flagged.
- A non-finite slope (a window holding +inf energy) is flagged and left out of the reference statistics.
- Calibrating on the evaluated episodes and then picking the best (window, k) per step on them, as Table IV
  does, is optimistic twice over. Pass `reference_episodes` from other rollouts for an honest threshold;
  the configuration is still selected in sample.
- No reference slope (no successful episode has reached step s) makes the predictor undefined: its
  metrics are NaN.
"""

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .records import EnergyRecord

ENERGY_METRICS = {"final": "final_energy", "start": "initial_energy"}
DEFAULT_STEPS = tuple(range(1, 21))
DEFAULT_WINDOWS = tuple(range(2, 21))
DEFAULT_MULTIPLIERS = tuple(round(0.1 * i, 1) for i in range(1, 21))

Episode = Sequence[EnergyRecord]


def linear_slope(values: Sequence[float] | np.ndarray) -> float:
    """Least-squares slope of `values` against 0, 1, 2, ... (energy change per step); 0 for < 2 points."""
    return float(_window_slopes(np.asarray(values, dtype=np.float64)[None, :])[0])


def _window_slopes(windows: np.ndarray) -> np.ndarray:
    """Least-squares slopes of the rows of a (N, w) array against 0 .. w-1, all rows at once."""
    w = windows.shape[1]
    if w < 2:
        return np.zeros(windows.shape[0])
    x = np.arange(w, dtype=np.float64)
    x_centered = x - x.mean()
    # Centering x alone is enough: sum(x_c * (y - y_mean)) = sum(x_c * y) because sum(x_c) = 0.
    with np.errstate(invalid="ignore"):
        return windows @ x_centered / np.sum(x_centered**2)


def energy_matrix(episodes: Sequence[Episode], metric: str = "final") -> np.ndarray:
    """Stacks the episodes' energy series into an (N, max_chunks) array, NaN after each episode's end.

    Raises:
        ValueError: An unknown metric, or an episode whose chunk indices are not 0, 1, 2, ...
    """
    if metric not in ENERGY_METRICS:
        raise ValueError(f"`metric` must be one of {tuple(ENERGY_METRICS)}, got {metric!r}.")
    field_name = ENERGY_METRICS[metric]
    max_len = max((len(e) for e in episodes), default=0)
    matrix = np.full((len(episodes), max_len), np.nan)
    for i, episode in enumerate(episodes):
        if [r.chunk_index for r in episode] != list(range(len(episode))):
            raise ValueError(f"Episode {i} does not hold chunks 0..{len(episode) - 1} in order.")
        matrix[i, : len(episode)] = [getattr(r, field_name) for r in episode]
    return matrix


def _lengths(episodes: Sequence[Episode]) -> np.ndarray:
    return np.array([len(e) for e in episodes], dtype=np.int64)


def _step_slopes(
    energies: np.ndarray, lengths: np.ndarray, step: int, window: int
) -> tuple[np.ndarray, np.ndarray]:
    """Slopes at `step` over `window` of the episodes still running at `step`, and their row indices."""
    if step < 1 or window < 1:
        raise ValueError(f"`step` and `window` must be >= 1, got step={step}, window={window}.")
    rows = np.flatnonzero(lengths >= step)
    start = max(0, step - window)
    return _window_slopes(energies[rows, start:step]), rows


def episode_slopes(episodes: Sequence[Episode], step: int, window: int, metric: str = "final") -> np.ndarray:
    """Slope of each episode's energy at `step` (1-based) over the past `window` steps; NaN if it ended."""
    slopes = np.full(len(episodes), np.nan)
    values, rows = _step_slopes(energy_matrix(episodes, metric), _lengths(episodes), step, window)
    slopes[rows] = values
    return slopes


@dataclass(frozen=True)
class FailurePredictionResult:
    """The predictor "slope > mean_ref + multiplier * std_ref" evaluated at one step. Rates are fractions.

    `n_episodes` counts the episodes still running at `step`, `n_failed` the failed ones among them.
    """

    step: int
    window: int
    multiplier: float
    threshold: float
    accuracy: float
    balanced_accuracy: float
    tpr: float
    specificity: float
    n_episodes: int
    n_failed: int


def _ratio(numerator: float, denominator: float) -> float:
    return numerator / denominator if denominator > 0 else math.nan


def _evaluate(
    step: int, window: int, k: float, slopes: np.ndarray, failed: np.ndarray, ref_slopes: np.ndarray
) -> FailurePredictionResult:
    finite_ref = ref_slopes[np.isfinite(ref_slopes)]
    n, n_failed = slopes.size, int(failed.sum())
    if finite_ref.size == 0:
        nan = math.nan
        return FailurePredictionResult(step, window, k, nan, nan, nan, nan, nan, n, n_failed)
    threshold = float(finite_ref.mean() + k * finite_ref.std())
    # `not slope <= T` so that a non-finite slope is flagged.
    flagged = ~(slopes <= threshold)
    tp = int(np.sum(flagged & failed))
    tn = int(np.sum(~flagged & ~failed))
    tpr, specificity = _ratio(tp, n_failed), _ratio(tn, n - n_failed)
    return FailurePredictionResult(
        step=step,
        window=window,
        multiplier=float(k),
        threshold=threshold,
        accuracy=_ratio(tp + tn, n),
        balanced_accuracy=(tpr + specificity) / 2.0,
        tpr=tpr,
        specificity=specificity,
        n_episodes=n,
        n_failed=n_failed,
    )


class _SlopeData:
    """Energy matrices of the evaluated and reference episodes, built once for a whole sweep."""

    def __init__(
        self, episodes: Sequence[Episode], reference_episodes: Sequence[Episode] | None, metric: str
    ):
        self.energies, self.lengths = energy_matrix(episodes, metric), _lengths(episodes)
        self.failed = np.array([not e[0].success if e else False for e in episodes], dtype=bool)
        if reference_episodes is None:
            # In-sample calibration: the successful episodes of the evaluated set.
            keep = ~self.failed
            self.ref_energies, self.ref_lengths = self.energies[keep], self.lengths[keep]
        else:
            self.ref_energies = energy_matrix(reference_episodes, metric)
            self.ref_lengths = _lengths(reference_episodes)

    def evaluate(self, step: int, window: int, multipliers: Sequence[float]) -> list[FailurePredictionResult]:
        slopes, rows = _step_slopes(self.energies, self.lengths, step, window)
        ref_slopes, _ = _step_slopes(self.ref_energies, self.ref_lengths, step, window)
        return [_evaluate(step, window, k, slopes, self.failed[rows], ref_slopes) for k in multipliers]


def evaluate_failure_predictor(
    episodes: Sequence[Episode],
    step: int,
    window: int,
    multiplier: float,
    metric: str = "final",
    reference_episodes: Sequence[Episode] | None = None,
) -> FailurePredictionResult:
    """Evaluates one (step, window, k) configuration of the slope predictor.

    Args:
        episodes: Episodes to classify, each its records sorted by chunk index (`group_by_episode`).
        step: 1-based step (chunk) at which the prediction is made.
        window: Number of past steps, ending at `step`, the slope is fitted over.
        multiplier: k in slope > mean_ref + k * std_ref.
        metric: "final" (Slope Final) or "start" (Slope Start).
        reference_episodes: Episodes whose slopes set mean_ref and std_ref, all of them regardless of
            success. None uses the successful episodes of `episodes` (optimistic, see the module docstring).
    """
    return _SlopeData(episodes, reference_episodes, metric).evaluate(step, window, [multiplier])[0]


def failure_prediction_sweep(
    episodes: Sequence[Episode],
    steps: Sequence[int] = DEFAULT_STEPS,
    windows: Sequence[int] = DEFAULT_WINDOWS,
    multipliers: Sequence[float] = DEFAULT_MULTIPLIERS,
    metric: str = "final",
    reference_episodes: Sequence[Episode] | None = None,
) -> list[FailurePredictionResult]:
    """Table IV: for each step, the (window, k) with the highest balanced accuracy.

    Ties keep the first configuration in (window, k) order. Steps no episode reaches are left out; a step
    where the balanced accuracy is undefined for every configuration (e.g. only failed episodes remain)
    reports its first configuration, with NaN metrics.

    Args:
        episodes: Episodes to classify, each its records sorted by chunk index (`group_by_episode`).
        steps: 1-based steps to report.
        windows: Window sizes to try.
        multipliers: Std multipliers k to try.
        metric: "final" (Slope Final) or "start" (Slope Start).
        reference_episodes: See `evaluate_failure_predictor`.

    Returns:
        One result per reported step, in the order of `steps`.
    """
    data = _SlopeData(episodes, reference_episodes, metric)
    best_per_step = []
    for step in steps:
        if not np.any(data.lengths >= step):
            continue
        best = None
        for window in windows:
            for result in data.evaluate(step, window, multipliers):
                if (
                    best is None
                    or result.balanced_accuracy > best.balanced_accuracy
                    or (math.isnan(best.balanced_accuracy) and not math.isnan(result.balanced_accuracy))
                ):
                    best = result
        best_per_step.append(best)
    return best_per_step


def _percent(value: float) -> str:
    return "nan" if math.isnan(value) else f"{100 * value:.2f}%"


def format_failure_table(results: Sequence[FailurePredictionResult]) -> str:
    """Renders Table IV as a markdown table, rates in percent, with the episodes counted at each step."""
    lines = [
        "| Step | Win. | Std | Acc. | Bal. Acc. | TPR | Spec. | Episodes | Failed |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        rates = " | ".join(_percent(v) for v in (r.accuracy, r.balanced_accuracy, r.tpr, r.specificity))
        lines.append(
            f"| {r.step} | {r.window} | {r.multiplier:.2f} | {rates} | {r.n_episodes} | {r.n_failed} |"
        )
    return "\n".join(lines)
