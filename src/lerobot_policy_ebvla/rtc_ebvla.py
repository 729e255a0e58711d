"""EB-VLA's side of LeRobot's real-time chunking (RTC): the previous chunk's leftover as the prefix MCMC inpaints.

`lerobot-rollout --inference.type=rtc` passes each new chunk the leftover of the previous one, the inference delay
d and (optionally) the execution horizon. `rtc_prefix` turns them, with `config.rtc_config`, into the
`mcmc.RTCPrefix` that `mcmc.refine_actions` holds and guides towards (the equations are in mcmc.py's docstring).
"""

import torch
from lerobot.policies.rtc.modeling_rtc import RTCProcessor
from torch import Tensor

from .configuration_ebvla import EBVLAConfig
from .mcmc import RTCPrefix

__all__ = ["rtc_prefix"]


def rtc_prefix(
    config: EBVLAConfig,
    batch_size: int,
    inference_delay: int | None,
    prev_chunk_left_over: Tensor | None,
    execution_horizon: int | None = None,
) -> RTCPrefix | None:
    """The leftover to inpaint, from the arguments `lerobot-rollout --inference.type=rtc` passes.

    None when there is nothing to inpaint: no leftover (the first chunk), an empty one, or RTC disabled in
    `config.rtc_config` (LeRobot then appends chunks instead of replacing them). The overlap is
    min(execution_horizon, leftover length, chunk_size) steps, the length without the rows of zeros LeRobot's
    engine pads a short leftover with; d is capped at it, as LeRobot's schedule does.
    Raises a ValueError naming the argument that does not fit the config.
    """
    if prev_chunk_left_over is None:
        return None
    rtc = config.rtc_config
    if rtc is None:
        raise ValueError(
            "`prev_chunk_left_over` was given but `rtc_config` is None: set `rtc_config` "
            "(lerobot-rollout --inference.type=rtc does) to refine chunks by real-time chunking."
        )
    if not rtc.enabled:
        return None
    if inference_delay is not None and not 0 <= inference_delay <= config.chunk_size:
        raise ValueError(
            f"`inference_delay` must be in [0, chunk_size={config.chunk_size}] control steps. Got "
            f"{inference_delay}: the chunk would arrive after all its actions were due."
        )
    if execution_horizon is not None and execution_horizon < 1:
        raise ValueError(f"`execution_horizon` must be >= 1. Got {execution_horizon}.")
    leftover = prev_chunk_left_over
    if leftover.ndim == 2:
        leftover = leftover.unsqueeze(0)
    if (
        leftover.ndim != 3
        or leftover.shape[0] not in (1, batch_size)
        or leftover.shape[2] != config.action_dim
    ):
        raise ValueError(
            f"`prev_chunk_left_over` must be (B={batch_size}, n, action_dim={config.action_dim}) or "
            f"(n, {config.action_dim}). Got {tuple(prev_chunk_left_over.shape)}."
        )
    if not torch.isfinite(leftover).all():
        raise ValueError("`prev_chunk_left_over` contains NaN or infinite values.")
    # LeRobot's RTC engine pads a leftover shorter than `execution_horizon` with rows of zeros: not actions.
    rows = leftover.ne(0).any(dim=2).any(dim=0).nonzero()
    length = int(rows[-1]) + 1 if len(rows) else 0
    horizon = min(execution_horizon or rtc.execution_horizon, length, config.chunk_size)
    if horizon == 0:
        return None
    actions = leftover.new_zeros(batch_size, config.chunk_size, config.action_dim, dtype=torch.float32)
    actions[:, :horizon] = leftover[:, :horizon]
    held_steps = min(inference_delay or 0, horizon)
    weights = RTCProcessor(rtc).get_prefix_weights(held_steps, horizon, config.chunk_size)
    return RTCPrefix(actions, held_steps, weights.to(actions.device), rtc.max_guidance_weight)
