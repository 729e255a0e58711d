"""The failure alarm that ships with a checkpoint: one energy-slope check, at a step chosen on calibration.

The paper's failure predictor (Sec. III-D, Table IV) flags an episode at step s when the slope of its energy over
the last w steps exceeds T = mu_ref + k * sigma_ref, the slopes of successful reference episodes at the same step
and window. Table IV reports every step with its own (w, k); run at every step as a monitor, those checks add up
their false alarms, so most successful episodes end up flagged. `FailureAlarm` is the deployable form: a single
check, at the step s* whose (w, k) had the best balanced accuracy on calibration episodes
(`ebvla-failure-report --calibrate_to=<checkpoint>` chooses and saves it), so the alarm rate of successful
episodes is that of one check and the alarm comes s* chunks into the episode, before a failure at the step cap.

It needs failed calibration rollouts to choose s*, w and k. The checkpoint's own monitor (`monitor.EnergyMonitor`)
carries a failure check that does not: an energy score of the first N chunks against vanilla rollouts alone
(`calibration.FailureCalibration`). This alarm is the paper's, kept for Table IV and for users who record failures.

Steps are 1-based (step s is the s-th chunk). The slope is the least-squares slope of the energies of steps
max(1, s - w + 1) .. s against their step numbers; a non-finite slope (a diverged refinement's +inf) raises the
alarm, as the threshold rule says (`threshold.exceeds`).

    monitor = EnergyFailureMonitor.from_pretrained("outputs/train/ebvla/checkpoints/last/pretrained_model")
    action = policy.select_action(batch)
    if any(d.alarm for d in monitor.update(policy.last_energy)):
        ...  # ask for help, slow down, hand over

Nothing here imports the analysis (`monitoring/`).
"""

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .checkpoint_files import CheckpointJSON
from .history import ReadoutMonitor
from .readout import EnergyReadout
from .threshold import ArrayLike, as_array, exceeds, mean_std_threshold

FAILURE_ALARM_FILENAME = "failure_alarm.json"
# The energy each slope is of: the refined chunk's (Slope Final), the initial sample's (Slope Start), or the
# joint energy's context term E_c(C) (Slope Context; only a policy trained with a joint energy, `joint_energy.target`, has it).
SLOPE_ENERGIES = {"final": "final_energy", "start": "initial_energy", "context": "context_energy"}


def window_slopes(windows: np.ndarray) -> np.ndarray:
    """Least-squares slopes of the rows of an (N, w) array against 0 .. w-1, all rows at once; 0 when w < 2."""
    w = windows.shape[1]
    if w < 2:
        return np.zeros(windows.shape[0])
    x_centered = np.arange(w, dtype=np.float64) - (w - 1) / 2
    # Centering x alone is enough: sum(x_c * (y - y_mean)) = sum(x_c * y) because sum(x_c) = 0.
    with np.errstate(invalid="ignore"):
        return windows @ x_centered / np.sum(x_centered**2)


@dataclass(frozen=True)
class FailureAlarm(CheckpointJSON):
    """One slope check: at step `step`, alarm when the slope over `window` steps exceeds T.

    Args:
        metric: "final" (Slope Final, the refined energy), "start" (Slope Start, the initial sample's) or
            "context" (Slope Context, the joint energy's context term E_c(C)).
        step: s*, the 1-based step (chunk) at which the check is made.
        window: w, the steps the slope is fitted over, ending at s*.
        k: The multiplier of T = mu_ref + k * sigma_ref.
        mu_ref: The mean slope of the successful reference episodes at (s*, w).
        sigma_ref: Their population std.
        n_reference: How many reference slopes set mu_ref and sigma_ref.
        calibration_balanced_accuracy: The check's balanced accuracy on the episodes that chose it (for the
            reader; the report gives its held-out figure).
        n_calibration: How many calibration episodes were judged at s*.
    """

    metric: str
    step: int
    window: int
    k: float
    mu_ref: float
    sigma_ref: float
    n_reference: int
    calibration_balanced_accuracy: float = math.nan
    n_calibration: int = 0

    filename = FAILURE_ALARM_FILENAME
    what = "failure alarm"
    command = "ebvla-failure-report"

    def __post_init__(self):
        if self.metric not in SLOPE_ENERGIES:
            raise ValueError(f"`metric` must be one of {tuple(SLOPE_ENERGIES)}, got {self.metric!r}.")
        if self.step < 1 or self.window < 1:
            raise ValueError(f"`step` and `window` must be >= 1, got step={self.step}, window={self.window}.")
        if not (math.isfinite(self.mu_ref) and math.isfinite(self.sigma_ref) and self.sigma_ref >= 0):
            raise ValueError(
                f"`mu_ref` and `sigma_ref` must be finite with sigma_ref >= 0, got {self.mu_ref}, {self.sigma_ref}."
            )

    @property
    def threshold(self) -> float:
        return mean_std_threshold(self.mu_ref, self.sigma_ref, self.k)

    def slope(self, energies: ArrayLike) -> float:
        """The slope at s* of one episode's energies (steps 1, 2, ...; at least `step` of them)."""
        energies = as_array(energies)
        if energies.size < self.step:
            raise ValueError(f"The check is at step {self.step}; got the energies of {energies.size} steps.")
        window = energies[max(0, self.step - self.window) : self.step]
        return float(window_slopes(window[None, :])[0])

    def check(self, energies: ArrayLike) -> bool:
        """Whether one episode's energies (steps 1 .. >= s*) raise the alarm at s*."""
        return bool(exceeds(self.slope(energies), self.threshold)[0])

    # failure_alarm.json: the fields, and `threshold` for people reading the file (loading recomputes it).

    def to_json(self, checkpoint_dir: Path) -> dict[str, Any]:
        payload = {**dataclasses.asdict(self), "threshold": self.threshold}
        # JSON has no NaN: an unknown calibration accuracy is written as null.
        return {key: None if isinstance(v, float) and math.isnan(v) else v for key, v in payload.items()}

    @classmethod
    def from_json(cls, payload: dict[str, Any], path: Path) -> "FailureAlarm":
        payload = dict(payload)
        payload.pop("threshold", None)
        if payload.get("calibration_balanced_accuracy") is None:
            payload["calibration_balanced_accuracy"] = math.nan
        return cls(**payload)

    @classmethod
    def expected_fields(cls) -> str:
        return ", ".join(f.name for f in dataclasses.fields(cls))


@dataclass(frozen=True)
class FailureDecision:
    """The alarm's answer for one environment after a chunk.

    `alarm` is None before step s* (nothing decided yet), then the decision made at s*, kept for the rest of
    the episode; `slope` is the slope it was made on (None before s*).
    """

    alarm: bool | None
    step: int
    slope: float | None
    threshold: float


class EnergyFailureMonitor(ReadoutMonitor):
    """Feeds each chunk's readout to a `FailureAlarm`, one history per environment; decides at s*.

    The same shape as `EnergyOODMonitor`: `from_pretrained(checkpoint)`, `update(policy.last_energy)` after each
    step (each readout counted once), `reset()` with the policy.
    """

    def __init__(self, alarm: FailureAlarm):
        super().__init__()  # each environment's energies so far
        self.alarm = alarm
        self._decisions: list[FailureDecision | None] = []

    @classmethod
    def from_pretrained(cls, pretrained_name_or_path: str | Path) -> "EnergyFailureMonitor":
        return cls(FailureAlarm.from_pretrained(pretrained_name_or_path))

    def _add(self, readout: EnergyReadout) -> list[FailureDecision]:
        """Adds the readout's energy (final, initial or context, as the alarm's metric says) per environment."""
        field = SLOPE_ENERGIES[self.alarm.metric]
        energies = getattr(readout, field)
        if energies is None:
            raise ValueError(
                f"The failure alarm checks the slope of `{field}`, which this readout does not have (only a "
                "policy trained with a joint energy, `joint_energy.target`, reports `context_energy`)."
            )
        values = as_array(energies)
        self._histories.append([float(value) for value in values])
        if not self._decisions:
            self._decisions = [None] * len(values)
        answers = []
        for env, history in enumerate(self._histories):
            if len(history) == self.alarm.step:
                slope = self.alarm.slope(history)
                self._decisions[env] = FailureDecision(
                    bool(exceeds(slope, self.alarm.threshold)[0]), len(history), slope, self.alarm.threshold
                )
            decision = self._decisions[env]
            if decision is None:
                decision = FailureDecision(None, len(history), None, self.alarm.threshold)
            else:
                decision = dataclasses.replace(decision, step=len(history))
            answers.append(decision)
        return answers

    def reset(self) -> None:
        """Forgets the histories and decisions; call it when the environments reset (with `policy.reset()`)."""
        super().reset()
        self._decisions = []
