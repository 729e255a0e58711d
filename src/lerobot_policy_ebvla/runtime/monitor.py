"""The run-time monitors: a checkpoint's calibrations applied to chunks and rollouts as they come.

`EnergyMonitor` is the checkpoint's monitor: the OOD threshold and the failure check, both set on vanilla
rollouts, on one readout. `EnergyOODMonitor` is its OOD half alone (any one calibration, also a research score's).
"""

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .calibration import FailureCalibration, OODCalibration
from .history import ReadoutMonitor
from .readout import EnergyReadout
from .threshold import OODDecision, exceeds


class EnergyOODMonitor(ReadoutMonitor):
    """Compares each environment's running rollout score, as the calibration defines it, to its threshold T.

    `update` takes the policy's readout of each chunk (`policy.last_energy`, (B,) entries, one per environment),
    accumulates each environment's chunk components and compares their running rollout score
    (`OODCalibration.score_rollout`, the calibration's aggregation) to T; `reset` starts new episodes. `check`
    decides on each chunk of a readout alone, `check_rollout` on a finished rollout's chunks (a readout of its N
    chunks, `EnergyReadout.of_arrays`).

    Example:
        monitor = EnergyOODMonitor.from_pretrained("outputs/train/ebvla/checkpoints/last/pretrained_model")
        policy.reset(); monitor.reset()  # at every env.reset()
        action = policy.select_action(batch)
        if any(d.is_ood for d in monitor.update(policy.last_energy)):
            ...  # stop, ask for help, fall back to a safe policy

    `select_action` refines a chunk every `n_action_steps` calls; `update` counts each readout once, so it may be
    called after every step (a readout it has seen returns its decisions again). `update` raises a ValueError
    when not given one entry per environment, or a readout whose chunk index is not the monitor's next (the
    policy and the monitor were not reset together).
    """

    def __init__(self, calibration: OODCalibration):
        super().__init__()  # per environment, the `OODCalibration.chunk_components` row of each chunk so far
        self.calibration = calibration

    @classmethod
    def from_pretrained(
        cls, pretrained_name_or_path: str | Path, k: float | None = None
    ) -> "EnergyOODMonitor":
        """Builds a monitor from a checkpoint's `ood_calibration.json`, optionally with Eq. 5 at another k."""
        calibration = OODCalibration.from_pretrained(pretrained_name_or_path)
        return cls(calibration if k is None else calibration.with_k(k))

    @property
    def threshold(self) -> float:
        return self.calibration.threshold

    def _decide(self, score: float) -> OODDecision:
        return OODDecision.of(score, self.threshold)

    def _add(self, readout: EnergyReadout) -> list[OODDecision]:
        components = self.calibration.chunk_components(readout)
        self._histories.append(components)
        return [self._decide(self.calibration.score_rollout(np.stack(h))) for h in self._histories]

    def check(self, readout: EnergyReadout) -> list[OODDecision]:
        """One decision per chunk of `readout`, each chunk scored alone (a rollout of that one chunk)."""
        return [self._decide(score) for score in self.calibration.chunk_score(readout)]

    def check_rollout(self, readout: EnergyReadout) -> OODDecision:
        """The decision on a finished rollout, from a readout of its chunks in order (`EnergyReadout.of_arrays`),
        aggregated as calibrated."""
        return self._decide(self.calibration.score_rollout(self.calibration.chunk_components(readout)))


@dataclass(frozen=True)
class MonitorDecision:
    """The monitor's answer for one environment after a chunk: is the scene unfamiliar, is the rollout failing.

    Attributes:
        unfamiliar: The OOD check on the rollout so far (`EnergyOODMonitor`'s decision: its score, T, flagged).
        failing: None until the failure check decides (at the end of chunk N) or without one; then its decision,
            kept for the rest of the episode.
        failure_score: The score it decided on (its first N chunks), None before.
        failure_threshold: Its T, None without a failure check.
        chunks: How many chunks the environment has had.
    """

    unfamiliar: OODDecision
    failing: bool | None
    failure_score: float | None
    failure_threshold: float | None
    chunks: int

    @property
    def alarm(self) -> bool:
        """Either check flagged: the scene is unfamiliar, or its first chunks look like a failing rollout's."""
        return self.unfamiliar.is_ood or bool(self.failing)


class EnergyMonitor(ReadoutMonitor):
    """The checkpoint's energy monitor: two thresholds, both set on vanilla rollouts only, on one readout.

    - `unfamiliar`: the checkpoint's OOD calibration (`ood_calibration.json`, its `monitor.score`; for a policy
      with the joint energy on its own encoder, E_c against the vanilla E_c at each chunk index) on the rollout so
      far, as `EnergyOODMonitor` applies it (Table III).
    - `failing`: the failure check (`failure_calibration.json`, `monitor.failure_score`: the head's part of the
      joint energy, E - E_c, against vanilla at each chunk index, on either side) on the first N chunks, decided
      once at chunk N (Table IV at equal elapsed time). A checkpoint without one gets `failing=None`.

    `ebvla-ood-report --calibrate_to=<checkpoint>` writes both from the same vanilla calibration rollouts.

    Example:
        monitor = EnergyMonitor.from_pretrained("outputs/train/ebvla/checkpoints/last/pretrained_model")
        policy.reset(); monitor.reset()  # at every env.reset()
        action = policy.select_action(batch)
        for env, decision in enumerate(monitor.update(policy.last_energy)):
            if decision.alarm:
                ...  # decision.unfamiliar.is_ood: a scene unlike the calibration's; decision.failing: likely to fail

    `update` counts each readout once and raises a ValueError like `EnergyOODMonitor.update`.
    """

    def __init__(self, ood: OODCalibration, failure: FailureCalibration | None = None):
        super().__init__()  # per environment, (OOD components, failure components) of each chunk so far
        self.ood = ood
        self.failure = failure
        self._decided: list[tuple[bool, float] | None] = []

    @classmethod
    def from_pretrained(cls, pretrained_name_or_path: str | Path, k: float | None = None) -> "EnergyMonitor":
        """The monitor of a checkpoint: its `ood_calibration.json` (required; optionally at another k of Eq. 5)
        and its `failure_calibration.json` where it has one."""
        ood = OODCalibration.from_pretrained(pretrained_name_or_path)
        try:
            failure = FailureCalibration.from_pretrained(pretrained_name_or_path)
        except FileNotFoundError:  # calibrated before the failure check existed, or a policy without E_c
            failure = None
        return cls(ood if k is None else ood.with_k(k), failure)

    def _add(self, readout: EnergyReadout) -> list[MonitorDecision]:
        ood = self.ood.chunk_components(readout)
        failure = None if self.failure is None else self.failure.chunk_components(readout)
        self._histories.append([(o, None if failure is None else failure[i]) for i, o in enumerate(ood)])
        if not self._decided:
            self._decided = [None] * len(self._histories)
        decisions = []
        for env, history in enumerate(self._histories):
            if self.failure is not None and len(history) == self.failure.chunks:
                score = self.failure.score_rollout(np.stack([f for _, f in history]))
                self._decided[env] = (bool(exceeds(score, self.failure.threshold)[0]), score)
            decided = self._decided[env]
            decisions.append(
                MonitorDecision(
                    unfamiliar=OODDecision.of(
                        self.ood.score_rollout(np.stack([o for o, _ in history])), self.ood.threshold
                    ),
                    failing=None if decided is None else decided[0],
                    failure_score=None if decided is None else decided[1],
                    failure_threshold=None if self.failure is None else self.failure.threshold,
                    chunks=len(history),
                )
            )
        return decisions

    def reset(self) -> None:
        """Forgets the histories and the failure decisions; call it with `policy.reset()`."""
        super().reset()
        self._decided = []
