"""The window typicality test: whether the last n rollouts, taken together, look like vanilla's (a study tool).

A per-rollout score cannot flag a shift that makes rollouts *more* typical than vanilla's own, or one that moves
every rollout a little the same way inside vanilla's spread. Issue 32's mild shifts (a light from another side,
sensor noise, a slight blur) do both to the joint energy's context term, and the two-sided context-energy score
then alarms on none of those rollouts (against 2% of vanilla's): one rollout near the centre, or a little above
it, is normal; n in a row are not. Over a window of rollouts run under the same conditions this is a batch
typicality test (Nalisnick et al. 2019), two-sided: each of the rollouts' window values (`window_values`: the
calibration's rollout score, and for a two-sided score |a| also its signed aggregate a) against the M
reference rows, vanilla rollouts scored against the calibration but not used to fit it, by the Mann-Whitney U
test (scipy's, exact for a window of at most 8), each of the m values at alpha / m (Bonferroni). A value's
statistic, as the share of (window, reference) pairs in which the window's is higher, is the window's AUROC
against the reference: for the score above 1/2 the rollouts score above vanilla's (what the per-rollout threshold
also sees, here from several rollouts at once), under it below them (too typical); for the signed aggregate,
away from 1/2 the rollouts have all shifted one way.

Ranks, not the values' mean: the calibration's scores have a heavy right tail (one rollout scoring 10-15 times
the median), and a mean moves with it. The rank-sum law, not n independent conformal ranks: the window's ranks
share one reference, which adds 1/(12 M) to the variance of their mean (with M = 40 the independent law alarmed
on 6.6% of vanilla windows at alpha = 5%). Held-out reference rollouts, not the calibration rollouts'
leave-one-out scores: those sit above fresh vanilla's (AUROC 0.49-0.66 on five training seeds). And enough of
them: the false-alarm rate is alpha over draws of the reference, not for each reference; on eight training seeds
20 reference rollouts gave 0-29% on held-out vanilla windows of 8, 40 gave 2-5% (research/docs/window_test.md).

The package's calibration (`OODCalibration`) knows nothing of the window: the reference is what this module's
callers pass, e.g. `window_report.window_values_of(calibration, held_out_vanilla)`.
"""

from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.stats import mannwhitneyu

from lerobot_policy_ebvla.runtime.calibration import OODCalibration
from lerobot_policy_ebvla.runtime.readout import EnergyReadout
from lerobot_policy_ebvla.runtime.scores import AbsoluteOfAggregate, ChunkScore, rollout_aggregates
from lerobot_policy_ebvla.runtime.statistics import float64
from lerobot_policy_ebvla.runtime.threshold import ArrayLike

# Rollouts per window unless told: chosen on issue 32's development seeds, where windows of 8 alarm on 2-4% of
# fresh vanilla windows and on 57-92% of those of the mild shifts that hide from the per-rollout score.
DEFAULT_WINDOW = 8
DEFAULT_WINDOW_FALSE_ALARM_RATE = 0.05
# Which way a window left the reference: its scores above vanilla's, below them, or its signed aggregate moved.
HIGH_SCORES, TOO_TYPICAL, SHIFTED = "high_scores", "too_typical", "shifted"


def score_window_values(score: ChunkScore, aggregates: np.ndarray) -> np.ndarray:
    """(R, m) what the window test compares per rollout, from (R, n_components) aggregates: the score itself,
    (R, 1); for a two-sided score |a| (`AbsoluteOfAggregate`) also its signed aggregate a, (R, 2): a small
    shift the same way on every rollout (issue 32's mild noise raises E_c a little on each) hides inside
    vanilla's spread of |a| but not of a."""
    if isinstance(score, AbsoluteOfAggregate):
        return np.stack([np.abs(aggregates[:, 0]), aggregates[:, 0]], axis=1)
    return score.combine(aggregates)[:, None]


def window_values(calibration: OODCalibration, components: ArrayLike) -> np.ndarray:
    """(m,) what the window test compares of a rollout, from its chunks' `calibration.chunk_components` in chunk
    order: each column aggregated with the calibration's aggregation, then `score_window_values` (the rollout
    score first)."""
    aggregates = rollout_aggregates(calibration.score, components, calibration.aggregation)
    return score_window_values(calibration.score, aggregates)[0]


@dataclass(frozen=True)
class WindowDecision:
    """The test's verdict on one window of rollouts.

    Attributes:
        rollout_values: The window's rollouts' window values, (n, m) as nested tuples, oldest first.
        aurocs: Per value, the share of (window, reference) pairs in which the window's is higher (ties half),
            U / (n M).
        p_values: Per value, the two-sided Mann-Whitney p-value of the window against the reference.
        false_alarm_rate: alpha; the window is atypical when a value's p-value is at most alpha / m.
    """

    rollout_values: tuple[tuple[float, ...], ...]
    aurocs: tuple[float, ...]
    p_values: tuple[float, ...]
    false_alarm_rate: float

    @property
    def p_value(self) -> float:
        """The window's p-value over its m tests (Bonferroni): m times the smallest, at most 1."""
        return min(1.0, len(self.p_values) * min(self.p_values))

    @property
    def is_atypical(self) -> bool:
        return self.p_value <= self.false_alarm_rate

    @property
    def side(self) -> str | None:
        """ "high_scores" or "too_typical" (the score's test decided: above or below vanilla's), "shifted" (a
        two-sided score's signed aggregate moved one way), None when typical."""
        if not self.is_atypical:
            return None
        which = int(np.argmin(self.p_values))
        if which > 0:
            return SHIFTED
        return HIGH_SCORES if self.aurocs[0] > 0.5 else TOO_TYPICAL


@dataclass(frozen=True)
class WindowTypicalityTest:
    """The two-sided test of a window of rollouts' values against M reference rows (see the module).

    Args:
        reference: (M, m) window values of vanilla rollouts, each scored against the calibration without being
            in its fit (`window_report.window_values_of`), as nested tuples or an array.
        window: n, the rollouts a decision is on.
        false_alarm_rate: alpha, the chance that a window of n vanilla rollouts is called atypical (over draws
            of the reference as well as of the window).
    """

    reference: tuple[tuple[float, ...], ...]
    window: int = DEFAULT_WINDOW
    false_alarm_rate: float = DEFAULT_WINDOW_FALSE_ALARM_RATE

    def __post_init__(self):
        reference = np.atleast_2d(float64(self.reference))
        if reference.shape[0] < 2 or not np.isfinite(reference).all():
            raise ValueError(
                f"`reference` needs at least 2 rows of finite vanilla window values, got shape {reference.shape} "
                f"({int((~np.isfinite(reference)).sum())} value(s) not finite)."
            )
        if self.window < 1:
            raise ValueError(f"`window` must be >= 1 rollout, got {self.window}.")
        if not 0.0 < self.false_alarm_rate < 1.0:
            raise ValueError(f"`false_alarm_rate` must be in (0, 1), got {self.false_alarm_rate}.")
        object.__setattr__(self, "reference", tuple(tuple(map(float, row)) for row in reference))

    def check(self, rollout_values: ArrayLike) -> WindowDecision:
        """Tests `window` rollouts' values, (n, m) oldest first (a 1-d array for m = 1). A non-finite value (a
        diverged refinement) counts as above every reference value.

        Raises:
            ValueError: Not `window` rows of the reference's m values.
        """
        values = float64(rollout_values)
        reference = np.asarray(self.reference)
        values = values[:, None] if values.ndim == 1 and reference.shape[1] == 1 else values
        if values.shape != (self.window, reference.shape[1]):
            raise ValueError(
                f"A window holds {self.window} rollouts of {reference.shape[1]} window value(s) each, "
                f"(n, m) = ({self.window}, {reference.shape[1]}); got shape {values.shape}."
            )
        ranked = np.where(np.isnan(values), np.inf, values)
        tests = [
            mannwhitneyu(ranked[:, j], reference[:, j], alternative="two-sided", method="auto")
            for j in range(reference.shape[1])
        ]
        return WindowDecision(
            tuple(tuple(map(float, row)) for row in values),
            tuple(float(t.statistic) / (self.window * reference.shape[0]) for t in tests),
            tuple(float(t.pvalue) for t in tests),
            self.false_alarm_rate,
        )


class WindowTypicalityMonitor:
    """Keeps the last n rollouts' window values and tests them together once there are n.

    Opt-in, beside the per-rollout monitor (`EnergyOODMonitor`): it needs n rollouts under the same conditions
    before it can say anything, and then says it of the conditions, not of one rollout.

    Example:
        reference = window_report.window_values_of(calibration, held_out_vanilla_episodes)
        monitor = WindowTypicalityMonitor.from_pretrained("outputs/.../pretrained_model", reference, window=8)
        for episode in episodes:
            ...  # run it, keeping each chunk's final energy (and E_c, for a context-energy calibration)
            decision = monitor.add_rollout(EnergyReadout.of_arrays(chunk_energies, context_energy=chunk_context_energies))
            if decision is not None and decision.is_atypical:
                ...  # these conditions are not the calibration's: recalibrate, or look at the scene
    """

    def __init__(
        self,
        calibration: OODCalibration,
        reference: ArrayLike,
        window: int = DEFAULT_WINDOW,
        false_alarm_rate: float = DEFAULT_WINDOW_FALSE_ALARM_RATE,
    ):
        """`reference`: (M, m) held-out vanilla rollouts' `window_values` against `calibration` (see
        `WindowTypicalityTest`)."""
        self.calibration = calibration
        self.test = WindowTypicalityTest(reference, window, false_alarm_rate)
        self._values: deque[np.ndarray] = deque(maxlen=window)

    @classmethod
    def from_pretrained(
        cls,
        pretrained_name_or_path: str | Path,
        reference: ArrayLike,
        window: int = DEFAULT_WINDOW,
        false_alarm_rate: float = DEFAULT_WINDOW_FALSE_ALARM_RATE,
    ) -> "WindowTypicalityMonitor":
        """Builds the monitor from a checkpoint's `ood_calibration.json` and the window's reference."""
        return cls(
            OODCalibration.from_pretrained(pretrained_name_or_path), reference, window, false_alarm_rate
        )

    @property
    def n_rollouts(self) -> int:
        """How many rollouts the window holds so far (at most n)."""
        return len(self._values)

    def add_values(self, window_values: ArrayLike) -> WindowDecision | None:
        """Adds one finished rollout's window values ((m,), `window_values`); the decision on the
        last n, or None while there are fewer."""
        self._values.append(np.atleast_1d(float64(window_values)))
        if len(self._values) < self.test.window:
            return None
        return self.test.check(np.stack(self._values))

    def add_rollout(self, readout: EnergyReadout) -> WindowDecision | None:
        """Adds one finished rollout from a readout of its chunks in order (`EnergyReadout.of_arrays`), as
        `EnergyOODMonitor.check_rollout` takes it."""
        components = self.calibration.chunk_components(readout)
        return self.add_values(window_values(self.calibration, components))

    def reset(self) -> None:
        """Forgets the window; call it when the conditions change on purpose (a new scene, a new task)."""
        self._values.clear()
