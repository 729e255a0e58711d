"""The window typicality test: whether the last n rollouts' scores, taken together, look like vanilla's.

A per-rollout score cannot flag a shift that makes rollouts *more* typical than vanilla's own. Issue 32's mild
shifts (a light from another side, sensor noise, a slight blur) pull the joint energy's context term toward its
vanilla mean at every chunk index, and the two-sided context-energy score then alarms on none of those rollouts
(against 2% of vanilla's): one rollout near the centre is normal, n in a row are not. Over a window of rollouts
run under the same conditions this is a batch typicality test (Nalisnick et al. 2019), two-sided: the window's
rollout scores (the calibration's, `OODCalibration.score_rollout`) against M reference scores, vanilla rollouts
scored against the calibration but not used to fit it, by the Mann-Whitney U test (scipy's, exact for a window
of at most 8). Its statistic, as the share of (window, reference) pairs in which the window's score is higher,
is the window's AUROC against the reference: above 1/2 the scores are above vanilla's (what the per-rollout
threshold also sees, here from several rollouts at once), under it they are below them (too typical).

Ranks, not the scores' mean: the calibration's scores have a heavy right tail (one rollout scoring 10-15 times
the median), and a mean moves with it. The rank-sum law, not n independent conformal ranks: the window's ranks
share one reference, which adds 1/(12 M) to the variance of their mean (with M = 40 the independent law alarmed
on 6.6% of vanilla windows at alpha = 5%). Held-out reference scores, not the calibration rollouts'
leave-one-out ones: those sit above fresh vanilla's (AUROC 0.49-0.66 on five training seeds). And enough of them:
the false-alarm rate is alpha over draws of the reference, not for each reference; on eight training seeds 20
reference rollouts gave 1-42% on held-out vanilla windows of 8, 40 gave 4-7% (docs/monitoring.md).
"""

from collections import deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.stats import mannwhitneyu

from .calibration import OODCalibration
from .threshold import ArrayLike, as_array

# Rollouts per window unless told: the too-typical shift it was chosen on (issue 32, seed 12000's light from
# another side) is alarmed on 83% of windows of 8 fresh rollouts.
DEFAULT_WINDOW = 8
DEFAULT_WINDOW_FALSE_ALARM_RATE = 0.05
# The sides a window can leave the reference on.
HIGH_SCORES, TOO_TYPICAL = "high_scores", "too_typical"


@dataclass(frozen=True)
class WindowDecision:
    """The test's verdict on one window of rollouts.

    Attributes:
        rollout_scores: The window's rollout scores, oldest first.
        auroc: The share of (window, reference) score pairs in which the window's is higher (ties half), U / (n M).
        p_value: The two-sided Mann-Whitney p-value of the window against the reference.
        false_alarm_rate: alpha, the p-value at or under which the window is atypical.
    """

    rollout_scores: tuple[float, ...]
    auroc: float
    p_value: float
    false_alarm_rate: float

    @property
    def is_atypical(self) -> bool:
        return self.p_value <= self.false_alarm_rate

    @property
    def side(self) -> str | None:
        """ "high_scores" (scores above the reference's), "too_typical" (below them), None when typical."""
        if not self.is_atypical:
            return None
        return HIGH_SCORES if self.auroc > 0.5 else TOO_TYPICAL


@dataclass(frozen=True)
class WindowTypicalityTest:
    """The two-sided test of a window of rollout scores against M reference scores (see the module).

    Args:
        reference_scores: Vanilla rollout scores, each scored against the calibration without being in its
            fit (`OODCalibration.reference_scores`).
        window: n, the rollouts a decision is on.
        false_alarm_rate: alpha, the chance that a window of n vanilla rollouts is called atypical (over draws
            of the reference as well as of the window).
    """

    reference_scores: tuple[float, ...]
    window: int = DEFAULT_WINDOW
    false_alarm_rate: float = DEFAULT_WINDOW_FALSE_ALARM_RATE

    def __post_init__(self):
        reference = as_array(self.reference_scores)
        if reference.size < 2 or not np.isfinite(reference).all():
            raise ValueError(
                f"`reference_scores` needs at least 2 finite vanilla rollout scores, got {reference.size} "
                f"({int((~np.isfinite(reference)).sum())} not finite)."
            )
        if self.window < 1:
            raise ValueError(f"`window` must be >= 1 rollout, got {self.window}.")
        if not 0.0 < self.false_alarm_rate < 1.0:
            raise ValueError(f"`false_alarm_rate` must be in (0, 1), got {self.false_alarm_rate}.")
        object.__setattr__(self, "reference_scores", tuple(float(r) for r in reference))

    def check(self, rollout_scores: ArrayLike) -> WindowDecision:
        """Tests `window` rollout scores, oldest first. A non-finite score (a diverged refinement) counts as
        above every reference score.

        Raises:
            ValueError: Not exactly `window` scores.
        """
        scores = as_array(rollout_scores)
        if scores.size != self.window:
            raise ValueError(f"A window holds {self.window} rollout scores, got {scores.size}.")
        ranked = np.where(np.isnan(scores), np.inf, scores)
        result = mannwhitneyu(ranked, self.reference_scores, alternative="two-sided", method="auto")
        return WindowDecision(
            tuple(float(s) for s in scores),
            float(result.statistic) / (scores.size * len(self.reference_scores)),
            float(result.pvalue),
            self.false_alarm_rate,
        )


class WindowTypicalityMonitor:
    """Keeps the last n rollouts' scores and tests them together once there are n.

    Opt-in, beside the per-rollout monitor (`EnergyOODMonitor`): it needs n rollouts under the same conditions
    before it can say anything, and then says it of the conditions, not of one rollout.

    Example:
        monitor = WindowTypicalityMonitor.from_pretrained("outputs/.../pretrained_model", window=8)
        for episode in episodes:
            ...  # run it, keeping each chunk's final energy (and E_c, for a context-energy calibration)
            decision = monitor.add_rollout(chunk_energies, context_energies=chunk_context_energies)
            if decision is not None and decision.is_atypical:
                ...  # these conditions are not the calibration's: recalibrate, or look at the scene
    """

    def __init__(
        self,
        calibration: OODCalibration,
        window: int = DEFAULT_WINDOW,
        false_alarm_rate: float = DEFAULT_WINDOW_FALSE_ALARM_RATE,
    ):
        if calibration.reference_scores is None:
            raise ValueError(
                "The calibration has no `reference_scores` (held-out vanilla rollout scores) for a window test; "
                "save it again with `ebvla-ood-report --calibrate_to=...`, which records the --vanilla rollouts' "
                "scores."
            )
        self.calibration = calibration
        self.test = WindowTypicalityTest(calibration.reference_scores, window, false_alarm_rate)
        self._scores: deque[float] = deque(maxlen=window)

    @classmethod
    def from_pretrained(
        cls,
        pretrained_name_or_path: str | Path,
        window: int = DEFAULT_WINDOW,
        false_alarm_rate: float = DEFAULT_WINDOW_FALSE_ALARM_RATE,
    ) -> "WindowTypicalityMonitor":
        """Builds the monitor from a checkpoint's `ood_calibration.json`."""
        return cls(OODCalibration.from_pretrained(pretrained_name_or_path), window, false_alarm_rate)

    def add_score(self, rollout_score: float) -> WindowDecision | None:
        """Adds one finished rollout's score; the decision on the last n, or None while there are fewer."""
        self._scores.append(float(rollout_score))
        if len(self._scores) < self.test.window:
            return None
        return self.test.check(list(self._scores))

    def add_rollout(
        self,
        chunk_energies: ArrayLike,
        context_features: ArrayLike | None = None,
        context_energies: ArrayLike | None = None,
    ) -> WindowDecision | None:
        """Adds one finished rollout from its chunks (chunks 0, 1, ...), scored as the calibration scores one
        (`OODCalibration.score_chunks`: the same inputs as `EnergyOODMonitor.check_rollout`)."""
        return self.add_score(
            self.calibration.score_chunks(chunk_energies, context_features, context_energies)
        )

    def reset(self) -> None:
        """Forgets the window; call it when the conditions change on purpose (a new scene, a new task)."""
        self._scores.clear()
