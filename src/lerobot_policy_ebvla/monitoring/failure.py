"""Energy-based failure prediction (paper Sec. III-D, Table IV).

A rollout predicts one action chunk per "step" (steps are 1-based: step s is the s-th chunk, chunk_index
s - 1). At step s, the slope of an energy series over a window of w steps is the least-squares slope of the
energies of steps max(1, s - w + 1) .. s against their step numbers. *Slope Start* uses the initial energy
E(a^(0), C), *Slope Final* the refined energy E(a^(K_inf), C). A rising final energy means refinement
struggles more and more to find expert-like actions, which the paper finds to precede failure.

The predictor flags an episode as failing at step s when (the rule of `threshold.py`)

    slope > mean_ref + k * std_ref,

where mean_ref and std_ref (population std) are the slopes, at the same step and window, of *reference
episodes*: successful episodes only (the one-class analogue of the vanilla calibration of Eq. 5); failed
episodes given as reference are filtered out. Positives are failed episodes.

Choices, stated because the paper leaves them open:
- Carry forward (default, the paper's fixed episode set: its failure rate is the same at every step): an
  episode that ended before step s keeps its last energy, so every episode is judged at every step and a
  finished episode's slope decays to 0. With `carry_forward=False`, episodes that ended are left out at
  that step, from the reference and from the metrics; successful episodes tend to end early, so late steps
  are then judged on fewer, mostly failing, episodes.
- When the window reaches before step 1 it is truncated to the steps available. A slope of fewer than two
  points is 0 ("no trend yet"); at step 1 every slope is 0 and nothing is flagged.
- A non-finite slope (a window holding +inf energy) is flagged and left out of the reference statistics.
- Held-out protocol (`select_configurations` then `evaluate_configurations`): the (window, k) of each step
  is chosen on calibration episodes, and the threshold comes from calibration (reference) episodes, then
  both are applied unchanged to held-out episodes. Choosing on the evaluated episodes, as Table IV does, is
  optimistic.
- No reference slope (no successful episode has reached step s) makes the predictor undefined: its
  metrics are NaN.
"""

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .metrics import BinaryRates, markdown_table, percent
from .records import EnergyRecord
from .threshold import exceeds, mean_std_threshold

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
    x_centered = np.arange(w, dtype=np.float64) - (w - 1) / 2
    # Centering x alone is enough: sum(x_c * (y - y_mean)) = sum(x_c * y) because sum(x_c) = 0.
    with np.errstate(invalid="ignore"):
        return windows @ x_centered / np.sum(x_centered**2)


def energy_matrix(
    episodes: Sequence[Episode], metric: str = "final", carry_forward: bool = False, width: int = 0
) -> np.ndarray:
    """Stacks the episodes' energy series into an (N, max(width, longest)) array.

    After an episode's end the row holds its last energy (`carry_forward`) or NaN.

    Raises:
        ValueError: An unknown metric, or an episode whose chunk indices are not 0, 1, 2, ...
    """
    if metric not in ENERGY_METRICS:
        raise ValueError(f"`metric` must be one of {tuple(ENERGY_METRICS)}, got {metric!r}.")
    field_name = ENERGY_METRICS[metric]
    max_len = max([width, *(len(e) for e in episodes)])
    matrix = np.full((len(episodes), max_len), np.nan)
    for i, episode in enumerate(episodes):
        if [r.chunk_index for r in episode] != list(range(len(episode))):
            raise ValueError(f"Episode {i} does not hold chunks 0..{len(episode) - 1} in order.")
        matrix[i, : len(episode)] = [getattr(r, field_name) for r in episode]
        if carry_forward and episode:
            matrix[i, len(episode) :] = matrix[i, len(episode) - 1]
    return matrix


def successful(episodes: Sequence[Episode]) -> list[Episode]:
    """The successful episodes: the only ones a reference (threshold) set may hold."""
    return [e for e in episodes if e and e[0].success]


class _Slopes:
    """The energy matrix of a set of episodes, built once, and its slopes at any (step, window)."""

    def __init__(self, episodes: Sequence[Episode], metric: str, carry_forward: bool, width: int):
        self.energies = energy_matrix(episodes, metric, carry_forward, width)
        lengths = np.array([len(e) for e in episodes], dtype=np.int64)
        self.lengths = np.full_like(lengths, self.energies.shape[1]) if carry_forward else lengths
        self.failed = np.array([bool(e) and not e[0].success for e in episodes], dtype=bool)

    def at(self, step: int, window: int) -> tuple[np.ndarray, np.ndarray]:
        """Slopes at `step` over `window` of the episodes still counted at `step`, and their row indices."""
        if step < 1 or window < 1:
            raise ValueError(f"`step` and `window` must be >= 1, got step={step}, window={window}.")
        rows = np.flatnonzero(self.lengths >= step)
        return _window_slopes(self.energies[rows, max(0, step - window) : step]), rows


def episode_slopes(
    episodes: Sequence[Episode], step: int, window: int, metric: str = "final", carry_forward: bool = False
) -> np.ndarray:
    """Slope of each episode's energy at `step` (1-based) over the past `window` steps; NaN if it ended."""
    data = _Slopes(episodes, metric, carry_forward, width=step)
    slopes = np.full(len(episodes), np.nan)
    values, rows = data.at(step, window)
    slopes[rows] = values
    return slopes


@dataclass(frozen=True)
class FailurePredictionResult(BinaryRates):
    """The predictor "slope > mean_ref + multiplier * std_ref" at one step, and its confusion counts.

    `n_episodes` counts the episodes judged at `step`, `n_failed` the failed ones among them. Without a
    reference slope the threshold is NaN, the counts are 0 and every rate is NaN.
    """

    step: int = 0
    window: int = 0
    multiplier: float = math.nan
    threshold: float = math.nan
    n_episodes: int = 0
    n_failed: int = 0

    @property
    def failure_rate(self) -> float:
        return self.n_failed / self.n_episodes if self.n_episodes else math.nan


class _Predictor:
    """Slopes of evaluated and reference episodes for a whole sweep; thresholds come from the reference."""

    def __init__(
        self,
        episodes: Sequence[Episode],
        reference_episodes: Sequence[Episode] | None,
        metric: str,
        carry_forward: bool,
        width: int,
    ):
        reference = successful(episodes if reference_episodes is None else reference_episodes)
        self.data = _Slopes(episodes, metric, carry_forward, width)
        self.reference = _Slopes(reference, metric, carry_forward, width)

    def evaluate(self, step: int, window: int, multipliers: Sequence[float]) -> list[FailurePredictionResult]:
        slopes, rows = self.data.at(step, window)
        failed = self.data.failed[rows]
        reference, _ = self.reference.at(step, window)
        reference = reference[np.isfinite(reference)]
        results = []
        for k in multipliers:
            rates, threshold = BinaryRates(0, 0, 0, 0), math.nan
            if reference.size:
                threshold = mean_std_threshold(float(reference.mean()), float(reference.std()), k)
                flags = exceeds(slopes, threshold)
                rates = BinaryRates.from_flags(flags[~failed], flags[failed])
            results.append(
                FailurePredictionResult(
                    **dataclasses.asdict(rates),
                    step=step,
                    window=window,
                    multiplier=float(k),
                    threshold=threshold,
                    n_episodes=int(failed.size),
                    n_failed=int(failed.sum()),
                )
            )
        return results


def evaluate_failure_predictor(
    episodes: Sequence[Episode],
    step: int,
    window: int,
    multiplier: float,
    metric: str = "final",
    reference_episodes: Sequence[Episode] | None = None,
    carry_forward: bool = True,
) -> FailurePredictionResult:
    """Evaluates one (step, window, k) configuration of the slope predictor.

    Args:
        episodes: Episodes to classify, each its records sorted by chunk index (`group_by_episode`).
        step: 1-based step (chunk) at which the prediction is made.
        window: Number of past steps, ending at `step`, the slope is fitted over.
        multiplier: k in slope > mean_ref + k * std_ref.
        metric: "final" (Slope Final) or "start" (Slope Start).
        reference_episodes: Episodes whose slopes set mean_ref and std_ref; only the successful ones are
            used. None uses the successful episodes of `episodes` (in-sample, optimistic).
        carry_forward: Judge every episode at every step, an ended one with its last energy carried forward.
    """
    predictor = _Predictor(episodes, reference_episodes, metric, carry_forward, width=step)
    return predictor.evaluate(step, window, [multiplier])[0]


def _better(result: FailurePredictionResult, best: FailurePredictionResult | None) -> bool:
    if best is None:
        return True
    if math.isnan(best.balanced_accuracy):
        return not math.isnan(result.balanced_accuracy)
    return result.balanced_accuracy > best.balanced_accuracy


def _max_step(episodes: Sequence[Episode]) -> int:
    return max((len(e) for e in episodes), default=0)


def failure_prediction_sweep(
    episodes: Sequence[Episode],
    steps: Sequence[int] = DEFAULT_STEPS,
    windows: Sequence[int] = DEFAULT_WINDOWS,
    multipliers: Sequence[float] = DEFAULT_MULTIPLIERS,
    metric: str = "final",
    reference_episodes: Sequence[Episode] | None = None,
    carry_forward: bool = True,
) -> list[FailurePredictionResult]:
    """Table IV: for each step, the (window, k) with the highest balanced accuracy on `episodes`.

    This chooses the configuration on the episodes it reports (as the paper does); for the held-out
    protocol, choose on calibration episodes with this function and report with `evaluate_configurations`.
    Ties keep the first configuration in (window, k) order. Steps no episode reaches are left out; a step
    where the balanced accuracy is undefined for every configuration reports its first one, with NaN rates.

    Args:
        episodes: Episodes to classify, each its records sorted by chunk index (`group_by_episode`).
        steps: 1-based steps to report.
        windows: Window sizes to try.
        multipliers: Std multipliers k to try.
        metric: "final" (Slope Final) or "start" (Slope Start).
        reference_episodes: See `evaluate_failure_predictor`.
        carry_forward: See `evaluate_failure_predictor`.

    Returns:
        One result per reported step, in the order of `steps`.
    """
    max_step = _max_step(episodes)
    predictor = _Predictor(episodes, reference_episodes, metric, carry_forward, width=max(steps, default=0))
    best_per_step = []
    for step in steps:
        if step > max_step:
            continue
        best = None
        for window in windows:
            for result in predictor.evaluate(step, window, multipliers):
                if _better(result, best):
                    best = result
        best_per_step.append(best)
    return best_per_step


select_configurations = failure_prediction_sweep


def evaluate_configurations(
    episodes: Sequence[Episode],
    chosen: Sequence[FailurePredictionResult],
    metric: str = "final",
    reference_episodes: Sequence[Episode] | None = None,
    carry_forward: bool = True,
) -> list[FailurePredictionResult]:
    """Applies configurations chosen elsewhere (one per step) to held-out episodes.

    Args:
        episodes: Held-out episodes to classify.
        chosen: The (step, window, multiplier) of each step, e.g. from `select_configurations` on
            calibration episodes.
        reference_episodes: The successful episodes that set the threshold; pass the calibration
            episodes so that nothing about the held-out episodes is used. None calibrates on the held-out
            set's own successful episodes (in-sample threshold).
    """
    max_step = _max_step(episodes)
    width = max((c.step for c in chosen), default=0)
    predictor = _Predictor(episodes, reference_episodes, metric, carry_forward, width=width)
    return [predictor.evaluate(c.step, c.window, [c.multiplier])[0] for c in chosen if c.step <= max_step]


def format_failure_table(
    results: Sequence[FailurePredictionResult], chosen_on: Sequence[FailurePredictionResult] | None = None
) -> str:
    """Renders Table IV as markdown, rates in percent, with the episodes and failure rate at each step.

    Args:
        results: One result per step.
        chosen_on: The calibration results the configurations were chosen on (held-out protocol): adds
            their balanced accuracy beside the held-out one.
    """
    headers = [
        "Step",
        "Win.",
        "Std",
        "Acc.",
        "Bal. Acc.",
        "TPR",
        "Spec.",
        "Episodes",
        "Failed",
        "Failure rate",
    ]
    by_step = {c.step: c for c in chosen_on or []}
    if chosen_on is not None:
        headers.append("Bal. Acc. (calibration)")
    rows = []
    for r in results:
        rates = [percent(v, 2) for v in (r.accuracy, r.balanced_accuracy, r.tpr, r.specificity)]
        row = [
            r.step,
            r.window,
            f"{r.multiplier:.2f}",
            *rates,
            r.n_episodes,
            r.n_failed,
            percent(r.failure_rate),
        ]
        if chosen_on is not None:
            row.append(percent(by_step[r.step].balanced_accuracy, 2) if r.step in by_step else "")
        rows.append(row)
    return markdown_table(headers, rows)
