"""The run-time OOD monitor: a checkpoint's calibration applied to chunks and rollouts as they come."""

from pathlib import Path

import numpy as np

from .calibration import OODCalibration
from .history import ReadoutMonitor
from .readout import EnergyReadout
from .threshold import OODDecision


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
