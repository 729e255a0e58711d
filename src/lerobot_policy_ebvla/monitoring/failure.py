"""Energy-based failure prediction (paper Sec. III-D, Table IV).

A rollout predicts one action chunk per "step" (steps are 1-based: step s is the s-th chunk, chunk_index
s - 1). At step s, the slope of an energy series over a window of w steps is the least-squares slope of the
energies of steps max(1, s - w + 1) .. s against their step numbers. *Slope Start* uses the initial energy
E(a^(0), C), *Slope Final* the refined energy E(a^(K_inf), C). A rising final energy means refinement
struggles more and more to find expert-like actions, which the paper finds to precede failure.

The predictor flags an episode as failing at step s when (the rule of `runtime/threshold.py`)

    slope > mean_ref + k * std_ref,

where mean_ref and std_ref (population std) are the slopes, at the same step and window, of *reference
episodes*: successful episodes only (the one-class analogue of the vanilla calibration of Eq. 5); failed
episodes given as reference are filtered out. Positives are failed episodes.

Choices, stated because the paper leaves them open:
- Equal elapsed time (default, `carry_forward=False`): at step s only the episodes still running at step s
  (at least s chunks) are judged, and only those of the reference set the threshold; an episode's label is
  whether it eventually fails. Successful episodes tend to end early, so late steps are judged on fewer,
  mostly failing, episodes: `FailurePredictionResult` counts them per step.
- Carry forward (`carry_forward=True`, the paper's fixed episode set: its failure rate is the same at every
  step): an episode that ended before step s keeps its last energy, so every episode is judged at every
  step and a finished episode's slope decays to 0. This is an artefact, not a prediction: a flat slope then
  separates "done" (mostly successes) from "still running" (mostly failures) at late steps.
- When the window reaches before step 1 it is truncated to the steps available. A slope of fewer than two
  points is 0 ("no trend yet"); at step 1 every slope is 0 and nothing is flagged.
- A non-finite slope (a window holding +inf energy) is flagged and left out of the reference statistics.
- Held-out protocol (`select_configurations` then `evaluate_configurations`): the (window, k) of each step
  is chosen on calibration episodes, and the threshold comes from calibration (reference) episodes, then
  both are applied unchanged to held-out episodes. Choosing on the evaluated episodes, as Table IV does, is
  optimistic.
- No reference slope (no successful episode has reached step s) makes the predictor undefined: its
  metrics are NaN, and it raises no alarm.
- Lead time (`first_alarms`): run as a monitor, the configuration chosen for each step (its window, k and
  reference threshold) is applied at that step; an episode's alarm is the first step it is flagged at, and
  its lead the number of chunks (and env steps) from that chunk to its last, the failure or the step cap.
- The alarms' lead, and the failure onset it is also measured to: `lead_time.py`.
"""

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..runtime.failure_alarm import SLOPE_ENERGIES, FailureAlarm, window_slopes
from ..runtime.threshold import MeanStd, exceeds
from .lead_time import Alarm, failure_onset
from .metrics import BinaryRates, markdown_table, percent
from .records import Episode

ENERGY_METRICS = SLOPE_ENERGIES
DEFAULT_STEPS = tuple(range(1, 21))
DEFAULT_WINDOWS = tuple(range(2, 21))
DEFAULT_MULTIPLIERS = tuple(round(0.1 * i, 1) for i in range(1, 21))


def linear_slope(values: Sequence[float] | np.ndarray) -> float:
    """Least-squares slope of `values` against 0, 1, 2, ... (energy change per step); 0 for < 2 points."""
    return float(window_slopes(np.asarray(values, dtype=np.float64)[None, :])[0])


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
        values = [getattr(r, field_name) for r in episode]
        if any(v is None for v in values):
            raise ValueError(
                f"Episode {i} has chunks without `{field_name}`, which the {metric!r} slope reads."
            )
        matrix[i, : len(episode)] = values
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
        return window_slopes(self.energies[rows, max(0, step - window) : step]), rows


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

    def _reference_stats(self, step: int, window: int) -> MeanStd | None:
        reference, _ = self.reference.at(step, window)
        # Non-finite reference slopes are left out silently (the module docstring says so), not with a warning.
        reference = reference[np.isfinite(reference)]
        return MeanStd.fit(reference, "reference slope") if reference.size else None

    def flags(self, step: int, window: int, multiplier: float) -> tuple[np.ndarray, np.ndarray]:
        """Flags of the episodes counted at `step` (none without a reference), and their rows."""
        slopes, rows = self.data.at(step, window)
        stats = self._reference_stats(step, window)
        if stats is None:
            return np.zeros(rows.size, dtype=bool), rows
        return exceeds(slopes, stats.threshold(multiplier)), rows

    def evaluate(self, step: int, window: int, multipliers: Sequence[float]) -> list[FailurePredictionResult]:
        slopes, rows = self.data.at(step, window)
        failed = self.data.failed[rows]
        stats = self._reference_stats(step, window)
        results = []
        for k in multipliers:
            rates, threshold = BinaryRates(0, 0, 0, 0), math.nan
            if stats is not None:
                threshold = stats.threshold(k)
                rates = BinaryRates.from_scores(slopes[~failed], slopes[failed], threshold)
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
    carry_forward: bool = False,
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
        carry_forward: Judge every episode at every step, an ended one with its last energy carried forward;
            False (default) judges at step s only the episodes still running at step s (equal elapsed time).
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
    carry_forward: bool = False,
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
    carry_forward: bool = False,
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


def select_check_step(
    chosen: Sequence[FailurePredictionResult], n_successful: int, min_running: float = 0.5
) -> FailurePredictionResult | None:
    """The step of the one-check alarm (`runtime.failure_alarm`): the best calibration balanced accuracy.

    Only steps where at least `min_running` of the `n_successful` successful calibration episodes are still
    running compete. Failed episodes run to the step cap, so at a step most successes have passed, "still
    running" alone predicts failure: such a check is a timeout, not a prediction. Ties keep the earliest step
    (the earlier alarm). None when no step qualifies with a defined accuracy.

    Args:
        chosen: One configuration per step, with its calibration rates (`select_configurations`).
        n_successful: How many successful episodes the calibration episodes that chose them hold.
        min_running: The fraction of those a step must still judge, in (0, 1].
    """
    if not 0.0 < min_running <= 1.0:
        raise ValueError(f"`min_running` must be in (0, 1], got {min_running}.")
    best = None
    for result in sorted(chosen, key=lambda c: c.step):
        if result.n_episodes - result.n_failed >= min_running * n_successful and _better(result, best):
            best = result
    return None if best is None or math.isnan(best.balanced_accuracy) else best


def failure_alarm(
    check: FailurePredictionResult, reference_episodes: Sequence[Episode], metric: str = "final"
) -> FailureAlarm:
    """The run-time alarm of a chosen check, its threshold from the successful reference episodes.

    Raises:
        ValueError: No successful reference episode reaches the check's step.
    """
    predictor = _Predictor(
        reference_episodes, reference_episodes, metric, carry_forward=False, width=check.step
    )
    stats = predictor._reference_stats(check.step, check.window)
    if stats is None:
        raise ValueError(f"No successful reference episode reaches step {check.step}: no threshold to save.")
    return FailureAlarm(
        metric=metric,
        step=check.step,
        window=check.window,
        k=check.multiplier,
        mu_ref=stats.mean,
        sigma_ref=stats.std,
        n_reference=stats.n,
        calibration_balanced_accuracy=check.balanced_accuracy,
        n_calibration=check.n_episodes,
    )


def format_failure_table(
    results: Sequence[FailurePredictionResult],
    chosen_on: Sequence[FailurePredictionResult] | None = None,
    aurocs: Sequence[str] | None = None,
) -> str:
    """Renders Table IV as markdown: the paper's columns (Step, Win., Std, Acc., Bal. Acc., TPR, Spec.), rates
    in percent, then the episodes judged at each step, the failed ones and the failure rate.

    Args:
        results: One result per step.
        chosen_on: The calibration results the configurations were chosen on (held-out protocol): adds
            their balanced accuracy beside the held-out one.
        aurocs: One AUROC cell per result (e.g. the slope's at the chosen window, `slope_scores` and
            `metrics.format_auroc`): adds an AUROC column.
    """
    headers = [
        "Step",
        "Win.",
        "Std",
        "Acc.",
        "Bal. Acc.",
        "TPR",
        "Spec.",
        "Episodes judged",
        "Failed",
        "Failure rate",
    ]
    by_step = {c.step: c for c in chosen_on or []}
    if aurocs is not None:
        headers.append("AUROC [95% CI]")
    if chosen_on is not None:
        headers.append("Bal. Acc. (calibration)")
    rows = []
    for i, r in enumerate(results):
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
        if aurocs is not None:
            row.append(aurocs[i])
        if chosen_on is not None:
            row.append(percent(by_step[r.step].balanced_accuracy, 2) if r.step in by_step else "")
        rows.append(row)
    return markdown_table(headers, rows)


def slope_scores(
    episodes: Sequence[Episode], step: int, window: int, metric: str = "final", carry_forward: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """The slopes at (`step`, `window`) of the successful and of the failed episodes judged at `step`.

    The AUROC of these (failed positive) is the slope's separation at that step, free of any threshold. A
    non-finite slope is +inf (flagged by any threshold, as the predictor does).
    """
    data = _Slopes(episodes, metric, carry_forward, width=step)
    slopes, rows = data.at(step, window)
    slopes = np.where(np.isnan(slopes), np.inf, slopes)
    failed = data.failed[rows]
    return slopes[~failed], slopes[failed]


def first_alarms(
    episodes: Sequence[Episode],
    chosen: Sequence[FailurePredictionResult],
    reference_episodes: Sequence[Episode] | None,
    *,
    metric: str = "final",
    carry_forward: bool = False,
) -> list[Alarm]:
    """Runs the chosen configurations as a monitor: each episode's first alarm, one `Alarm` per episode.

    At each step of `chosen` its (window, k), with the threshold of the reference episodes at that step, is
    applied to the episodes still running (an episode is never flagged after its last chunk).

    Args:
        episodes: The episodes to monitor, each its records sorted by chunk index.
        chosen: One configuration per step, e.g. from `select_configurations` on calibration episodes.
        reference_episodes: See `evaluate_configurations`.
        metric: "final" (Slope Final) or "start" (Slope Start).
        carry_forward: See `evaluate_failure_predictor`; the thresholds follow it.
    """
    width = max((c.step for c in chosen), default=0)
    predictor = _Predictor(episodes, reference_episodes, metric, carry_forward, width=width)
    first: list[int | None] = [None] * len(episodes)
    for config in sorted(chosen, key=lambda c: c.step):
        flags, rows = predictor.flags(config.step, config.window, config.multiplier)
        for row in rows[flags]:
            if first[row] is None and config.step <= len(episodes[row]):
                first[row] = config.step
    alarms = []
    for episode, step in zip(episodes, first, strict=True):
        failed = not episode[0].success
        onset = failure_onset(episode) if failed else None
        alarm = Alarm(
            episode[0].task, episode[0].episode_index, episode[0].seed, failed, len(episode), onset=onset
        )
        if step is not None:
            lead_env_steps = episode[-1].env_step - episode[step - 1].env_step
            alarm = dataclasses.replace(
                alarm,
                step=step,
                lead_chunks=len(episode) - step,
                lead_env_steps=lead_env_steps,
                lead_to_onset_chunks=None if onset is None else onset - step,
            )
        alarms.append(alarm)
    return alarms
