"""The checks a batch passes before the model sees it: each camera, the state and the action chunk by key.

A wrong input gets a ValueError that names the key, what was found and what was expected (a uint8 frame, a
state of another batch size, a NaN), instead of a shape or dtype error from inside the backbone. Below them,
the batch helpers the policy's entry points share.
"""

import torch
from lerobot.utils.constants import ACTION, OBS_STATE
from torch import Tensor

from .configuration_ebvla import EBVLAConfig


def validate_observation(batch: dict[str, Tensor], config: EBVLAConfig) -> None:
    """Raises a ValueError naming the key when a camera or the state is missing, misshapen, non-finite, of the
    wrong dtype, or of another batch size than the rest of the observation."""
    resizes = config.backbone == "vlm" or config.resnet.resize_shape is not None
    for key, feature in config.image_features.items():
        if key not in batch:
            raise ValueError(
                f"Missing camera `{key}`: the policy was configured with cameras {list(config.image_features)}, "
                f"the batch has keys {sorted(batch)}. Rename cameras with the pre-processor's rename map."
            )
        image = batch[key]
        if not image.is_floating_point():
            raise ValueError(
                f"Camera `{key}` has dtype {image.dtype}; the policy expects float images in [0, 1], as LeRobot's "
                "datasets and envs give them (lerobot-train divides uint8 frames by 255). Convert with "
                "`image.float() / 255`."
            )
        expected = (
            f"(B, {feature.shape[0]}, H, W)" if resizes else f"(B, {', '.join(map(str, feature.shape))})"
        )
        ok = image.ndim == 4 and image.shape[1] == feature.shape[0]
        ok &= resizes or tuple(image.shape[1:]) == tuple(feature.shape)
        if not ok:
            raise ValueError(f"Camera `{key}` must be {expected}. Got {tuple(image.shape)}.")
        _check_finite(image, key)
    if config.state_dim is not None:
        if OBS_STATE not in batch:
            raise ValueError(
                f"Missing `{OBS_STATE}` of size {config.state_dim}. Batch keys: {sorted(batch)}."
            )
        state = batch[OBS_STATE]
        if state.ndim != 2 or state.shape[1] != config.state_dim:
            raise ValueError(f"`{OBS_STATE}` must be (B, {config.state_dim}). Got {tuple(state.shape)}.")
        _check_finite(state, OBS_STATE)
    inputs = [*config.image_features, *([OBS_STATE] if config.state_dim is not None else [])]
    sizes = {key: batch[key].shape[0] for key in inputs}
    if len(set(sizes.values())) > 1:
        found = ", ".join(f"`{key}` {size}" for key, size in sizes.items())
        raise ValueError(f"Every input of an observation batch needs the same batch size B. Got {found}.")


def validate_actions(batch: dict[str, Tensor], config: EBVLAConfig) -> None:
    """Raises a ValueError when the training target is missing, misshapen or non-finite."""
    expected = (config.chunk_size, config.action_dim)
    if ACTION not in batch:
        raise ValueError(f"Training needs `{ACTION}` of shape (B, {expected[0]}, {expected[1]}).")
    action = batch[ACTION]
    if action.ndim != 3 or tuple(action.shape[1:]) != expected:
        raise ValueError(f"`{ACTION}` must be (B, {expected[0]}, {expected[1]}). Got {tuple(action.shape)}.")
    _check_finite(action, ACTION)


def _check_finite(tensor: Tensor, key: str) -> None:
    if tensor.is_floating_point() and not torch.isfinite(tensor).all():
        raise ValueError(f"`{key}` contains NaN or infinite values.")


def batch_size_of(batch: dict[str, Tensor]) -> int:
    """B, read from the first tensor of the batch that has a batch dimension."""
    return next(v.shape[0] for v in batch.values() if isinstance(v, Tensor) and v.ndim > 0)


def repeat_observations(batch: dict[str, Tensor], n: int) -> dict[str, Tensor]:
    """Each observation repeated n times in a row, (B, ...) -> (B * n, ...); per-observation lists likewise.

    Tensors made under `torch.inference_mode` (lerobot-eval) come back as normal tensors autograd can use.
    """
    batch_size = batch_size_of(batch)

    def repeat(value):
        if isinstance(value, Tensor) and value.ndim > 0 and value.shape[0] == batch_size:
            return value.clone().repeat_interleave(n, dim=0)
        if isinstance(value, list | tuple) and len(value) == batch_size:
            return [item for item in value for _ in range(n)]
        return value.clone() if isinstance(value, Tensor) else value

    return {key: repeat(value) for key, value in batch.items()}


def without_inference_tensors(batch: dict[str, Tensor]) -> dict[str, Tensor]:
    """Clones tensors made under `torch.inference_mode` (lerobot-eval), which autograd cannot record."""
    return {k: v.clone() if isinstance(v, Tensor) and v.is_inference() else v for k, v in batch.items()}
