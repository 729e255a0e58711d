"""The run-time OOD monitor: a checkpoint's calibration applied to chunks and rollouts as they come."""

from pathlib import Path

import numpy as np
from torch import Tensor

from .calibration import OODCalibration
from .history import EnvironmentHistories
from .threshold import ArrayLike, OODDecision, as_array


class EnergyOODMonitor:
    """Compares chunk scores, as the calibration defines them, to its threshold T.

    Per chunk, `check` compares each chunk score to T. Per rollout, `update` accumulates each environment's
    chunk components and compares their running rollout score (`OODCalibration.score_rollout`, the
    calibration's aggregation) to T, and `check_rollout` does the same for a finished rollout's chunks. The
    chunk score is the calibration's (`OODCalibration.chunk_score`): `update` and `check_rollout` count the
    chunks themselves, `check` needs the index for a score that reads it (the phase energy); a score that
    reads the pooled context (the context scores) needs `context_features` everywhere, and one that reads the
    joint energy's context term (the context-energy scores) `context_energy` (`EnergyReadout.context_energy`).

    Example:
        monitor = EnergyOODMonitor.from_pretrained("outputs/train/ebvla/checkpoints/last/pretrained_model")
        actions, energy = policy.predict_action_chunk(batch, return_energy=True)
        if any(d.is_ood for d in monitor.update(energy.final_energy)):
            ...  # stop, ask for help, fall back to a safe policy
    """

    def __init__(self, calibration: OODCalibration):
        self.calibration = calibration
        # Per environment, the `OODCalibration.chunk_components` row of each chunk so far.
        self._histories = EnvironmentHistories()

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

    def check(
        self,
        final_energy: float | Tensor,
        chunk_index: int | None = None,
        context_features: ArrayLike | None = None,
        context_energy: ArrayLike | float | None = None,
    ) -> OODDecision | list[OODDecision]:
        """Checks chunk final energies: a scalar gives one decision, a (B,) tensor or array a list of B.

        `chunk_index` (the chunks' index in their episodes) is needed by a phase-energy calibration only,
        `context_features` ((D,) or (B, D) pooled contexts) by a context calibration only, `context_energy`
        (E_c(C) of each chunk) by a context-energy calibration only.
        """
        scores = as_array(
            self.calibration.chunk_score(
                as_array(final_energy), chunk_index, context_features, context_energy
            )
        )
        if (final_energy.ndim if isinstance(final_energy, Tensor) else np.ndim(final_energy)) == 0:
            return self._decide(scores[0])
        return [self._decide(e) for e in scores]

    def check_rollout(
        self,
        chunk_energies: ArrayLike,
        context_features: ArrayLike | None = None,
        context_energies: ArrayLike | None = None,
    ) -> OODDecision:
        """Checks a rollout from its chunks' final energies (chunks 0, 1, ...), aggregated as calibrated.

        `context_features`, (N, D) one pooled context per chunk, is needed by a context calibration;
        `context_energies`, (N,) E_c(C) of each chunk, by a context-energy calibration.
        """
        components = self.calibration.rollout_components(chunk_energies, context_features, context_energies)
        return self._decide(self.calibration.score_rollout(components))

    def update(
        self,
        final_energy: float | Tensor,
        context_features: ArrayLike | None = None,
        context_energy: float | Tensor | None = None,
    ) -> list[OODDecision]:
        """Adds one chunk's score per environment and checks each environment's rollout so far.

        Args:
            final_energy: A float (one environment) or a (B,) tensor, one entry per environment.
            context_features: The chunk's pooled context per environment, (B, D), for a context calibration.
            context_energy: The chunk's E_c(C) per environment (`EnergyReadout.context_energy`), for a
                context-energy calibration.

        Returns:
            One decision per environment on its running rollout score.
        """
        energies = as_array(final_energy)
        self._histories.check(len(energies))
        # The environments step together: this is chunk `n_chunks` of every one of them.
        chunk_index = self._histories.n_chunks
        self._histories.append(
            self.calibration.chunk_components(energies, chunk_index, context_features, context_energy)
        )
        return [
            self._decide(self.calibration.score_rollout(np.stack(history))) for history in self._histories
        ]

    def reset(self) -> None:
        """Forgets the accumulated scores; call it when the environments reset."""
        self._histories.reset()
