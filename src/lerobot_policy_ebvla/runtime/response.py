"""What the policy does with a chunk its energy flags as out of distribution (beyond the paper).

After each refinement, the score of every chunk is compared to the threshold T = mu_v + k * sigma_v (Eq. 5)
of the checkpoint's `ood_calibration.json`, with the one rule of `threshold.py`: only a score <= T is in
distribution, so +inf (diverged refinement) and NaN are flagged. The score is the calibration's
(`OODCalibration.chunk_score`, the checkpoint's `monitor.score`, which `ebvla-ood-report --calibrate_to` saves:
the final energy E(a^(K_inf), C), the paper's, unless the training preset says otherwise); a score that reads the
chunk's pooled context has the policy compute it from the backbone pass that encoded the chunk's context.
`EBVLAConfig.monitor.response` picks what happens to a flagged chunk:

- "continue": it is executed and a warning is logged (the default).
- "hold": each of its H actions is replaced by the hold action; the next refinement checks again.
- "raise": `EnergyOODError` is raised, carrying the energies and T.

The policy returns normalized actions and the post-processor unnormalizes them, so the hold action is built
in normalized space with the normalization statistics of the checkpoint's pre-processor (LeRobot's
`NormalizerProcessorStep`, which holds both the state and the action statistics):

    zero_delta:     a_hold = normalize_action(0)                      = -mean_a / std_a  (mean/std)
    current_state:  a_hold = normalize_action(unnormalize_state(s))  = (s * std_s + mean_s - mean_a) / std_a

so that after the post-processor the robot receives exactly a zero delta, or its observed state.
"""

import logging
import math
from pathlib import Path
from typing import TYPE_CHECKING

import torch
from lerobot.lerobot_types import TransitionKey
from lerobot.processor import (
    NormalizerProcessorStep,
    PolicyProcessorPipeline,
    UnnormalizerProcessorStep,
)
from lerobot.processor.converters import create_transition
from lerobot.utils.constants import OBS_STATE, POLICY_PREPROCESSOR_DEFAULT_NAME
from torch import Tensor

from .calibration import OOD_CALIBRATION_FILENAME, OODCalibration
from .readout import EnergyReadout
from .threshold import OODDecision

if TYPE_CHECKING:  # annotations only: run-time code reads the config's fields and imports nothing above it
    from ..configuration_ebvla import EBVLAConfig

logger = logging.getLogger(__name__)


class EnergyOODError(RuntimeError):
    """Raised with `monitor.response="raise"` when a refined chunk's score exceeds the OOD threshold.

    Attributes:
        energy: The highest score (the calibration's `score`) among the flagged chunks, NaN counted as +inf.
        threshold: The threshold T it exceeded.
        decision: The full per-batch-element decision.
    """

    def __init__(self, energy: float, threshold: float, decision: OODDecision, score: str = "final_energy"):
        super().__init__(
            f"EB-VLA refined a chunk with {score} {energy:.4g} above the OOD threshold {threshold:.4g} "
            "(`monitor.response='raise'`): the observation looks out of distribution."
        )
        self.energy = energy
        self.threshold = threshold
        self.decision = decision


class HoldAction:
    """The hold action of each observation, in normalized action space (see the module docstring).

    Args:
        kind: "zero_delta" or "current_state".
        normalizer: The pre-processor's normalizer: the statistics and modes of state and action.
    """

    def __init__(self, kind: str, normalizer: NormalizerProcessorStep):
        self.kind = kind
        self.normalizer = normalizer
        self.unnormalizer = UnnormalizerProcessorStep(
            features=normalizer.features, norm_map=normalizer.norm_map, stats=normalizer.stats
        )

    @classmethod
    def from_pretrained(cls, kind: str, pretrained_name_or_path: str | Path) -> "HoldAction":
        """Takes the normalizer of the pre-processor saved beside the policy's weights."""
        preprocessor = PolicyProcessorPipeline.from_pretrained(
            pretrained_name_or_path, config_filename=f"{POLICY_PREPROCESSOR_DEFAULT_NAME}.json"
        )
        normalizers = [s for s in preprocessor.steps if isinstance(s, NormalizerProcessorStep)]
        if not normalizers:
            raise ValueError(
                f"The pre-processor of {pretrained_name_or_path} has no normalizer step, so the hold action "
                "cannot be mapped to the normalized action space the policy outputs."
            )
        return cls(kind, normalizers[0])

    def __call__(self, batch: dict[str, Tensor], batch_size: int, action_dim: int) -> Tensor:
        """The normalized hold action, (B, action_dim), for a pre-processed observation batch."""
        if self.kind == "zero_delta":
            raw = torch.zeros(batch_size, action_dim)
        else:
            normalized_state = {OBS_STATE: batch[OBS_STATE].float()}
            raw = self.unnormalizer(create_transition(observation=normalized_state))
            raw = raw[TransitionKey.OBSERVATION][OBS_STATE]
        return self.normalizer(create_transition(action=raw.float()))[TransitionKey.ACTION]


class EnergyOODResponse:
    """Applies the config's OOD response to refined chunks, with a checkpoint's calibrated threshold.

    The config is the one source of truth: its `monitor.response`, `hold_action` and `threshold_k` are read from
    it at every chunk, so a response never disagrees with the config it was built for. What comes from the
    checkpoint is what the config cannot hold: the calibration and the normalizer of the hold action.

    Args:
        config: The policy's config (read at every call).
        calibration: The vanilla statistics of the checkpoint's `ood_calibration.json`.
        hold_action: The hold action of `config.monitor.hold_action`, with the checkpoint's normalizer; required
            while `config.monitor.response == "hold"`.
    """

    def __init__(
        self, config: "EBVLAConfig", calibration: OODCalibration, hold_action: HoldAction | None = None
    ):
        self.config = config
        self.calibration = calibration
        self.hold_action = hold_action
        self._check_hold_action()

    @classmethod
    def from_pretrained(
        cls, config: "EBVLAConfig", pretrained_name_or_path: str | Path
    ) -> "EnergyOODResponse | None":
        """The response of a checkpoint: its `ood_calibration.json`, and the pre-processor's normalizer to hold.

        Returns None for `monitor.response="continue"` when the checkpoint has no calibration.

        Raises:
            FileNotFoundError: "hold" or "raise" and the checkpoint has no calibration.
        """
        try:
            calibration = OODCalibration.from_pretrained(pretrained_name_or_path)
        except FileNotFoundError as e:
            if config.monitor.response == "continue":
                return None
            raise FileNotFoundError(
                f"`monitor.response={config.monitor.response!r}` compares energies to the threshold saved in "
                f"{OOD_CALIBRATION_FILENAME} beside the weights, and {pretrained_name_or_path} has none: "
                "calibrate it with `ebvla-ood-report --calibrate_to=<pretrained_model>` on vanilla rollouts."
            ) from e
        hold_action = None
        if config.monitor.response == "hold":
            hold_action = HoldAction.from_pretrained(config.monitor.hold_action, pretrained_name_or_path)
        return cls(config, calibration, hold_action)

    @property
    def needs_context_features(self) -> bool:
        """Whether each chunk's pooled context must come with it (the calibration's score reads it)."""
        return self.calibration.needs_context_features

    @property
    def threshold(self) -> float:
        """T of the calibration, at the config's `monitor.threshold_k` when it sets one."""
        k = self.config.monitor.threshold_k
        return (self.calibration if k is None else self.calibration.with_k(k)).threshold

    def _check_hold_action(self) -> None:
        kind = self.config.monitor.hold_action
        if self.config.monitor.response == "hold" and (
            self.hold_action is None or self.hold_action.kind != kind
        ):
            raise ValueError(
                f"`monitor.response='hold'` with `monitor.hold_action={kind!r}` needs that hold action built from the "
                "checkpoint's normalizer: change the response with "
                "`policy.configure_ood_response(<checkpoint>, response=..., hold_action=...)`."
            )

    def __call__(
        self, actions: Tensor, readout: EnergyReadout, batch: dict[str, Tensor]
    ) -> tuple[Tensor, OODDecision]:
        """Checks each chunk (B, H, action_dim) of `readout` against T and continues, holds or raises.

        Returns the chunks to execute (held ones replaced) and the decision.
        """
        response, threshold = self.config.monitor.response, self.threshold
        scores = self.calibration.chunk_score(readout)
        decision = OODDecision.of(torch.as_tensor(scores, dtype=torch.float32), threshold, response)
        flagged, held = decision.flagged, decision.held
        if not flagged.any():
            return actions, decision
        # NaN sorts as the highest: report it rather than a finite energy beside it.
        energy = float(decision.scores[flagged].nan_to_num(nan=math.inf).max())
        score = self.calibration.score.name
        if response == "raise":
            raise EnergyOODError(energy, threshold, decision, score)
        logger.warning(
            "EB-VLA: %d of %d chunks have a %s above the OOD threshold %.4g (highest %.4g): %s.",
            int(flagged.sum()),
            flagged.numel(),
            score,
            threshold,
            energy,
            "holding them" if response == "hold" else "executing them anyway (`monitor.response='continue'`)",
        )
        if response == "hold":
            self._check_hold_action()
            batch_size, _, action_dim = actions.shape
            hold = self.hold_action(batch, batch_size, action_dim).to(actions.device, actions.dtype)
            mask = held.to(actions.device)[:, None, None]  # (B, 1, 1)
            actions = torch.where(mask, hold[:, None, :].expand_as(actions), actions)
        return actions, decision


def respond_to_energy(
    response: EnergyOODResponse | None,
    config: "EBVLAConfig",
    actions: Tensor,
    readout: EnergyReadout,
    batch: dict[str, Tensor],
) -> tuple[Tensor, OODDecision | None]:
    """The policy's entry point: applies `response` to the chunks of `readout`, or checks that none is needed
    without a calibration. The readout holds the pooled context when `response.needs_context_features`.

    Raises:
        ValueError: `config.monitor.response` is "hold" or "raise" and the policy has no calibrated response.
    """
    if response is None:
        if config.monitor.response != "continue":
            raise ValueError(
                f"`monitor.response={config.monitor.response!r}` needs the threshold of an OOD calibration: load the "
                f"policy with `EBVLAPolicy.from_pretrained` from a checkpoint holding {OOD_CALIBRATION_FILENAME} "
                "(or call `policy.configure_ood_response(<checkpoint>)`)."
            )
        return actions, None
    return response(actions, readout, batch)
