"""Does the policy see? The refined chunk and its final energy with the real cameras against blanked ones.

A policy can succeed from its proprioceptive state alone; then no visual perturbation can move its energy,
and a camera study on it measures nothing. Before any claim about images, compare the policy's output on
the same observations with every camera replaced by a blank (black) image, under the same a^(0) and
Langevin noise (same generator seed), so that only the cameras differ.
"""

from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor


@dataclass
class CameraDependence:
    """How much the policy's output depends on its cameras, over `num_frames` observations.

    Attributes:
        chunk_change: Mean over observations of ||a_real - a_blank|| / ||a_real||, the relative change of
            the refined (normalized) chunk when the cameras are blanked. 0 means the policy is blind.
        energy_real: Mean final energy E(a^(K), C) with the real cameras.
        energy_blank: Mean final energy with blanked cameras.
        num_frames: Number of observations compared.
    """

    chunk_change: float
    energy_real: float
    energy_blank: float
    num_frames: int

    @property
    def energy_shift(self) -> float:
        """energy_blank - energy_real: how far blanking the cameras moves the confidence score."""
        return self.energy_blank - self.energy_real

    def summary(self) -> str:
        return (
            f"chunk change {100 * self.chunk_change:.2f}% with blanked cameras; final energy "
            f"{self.energy_real:.3f} (real) vs {self.energy_blank:.3f} (blanked), over {self.num_frames} frames"
        )


def blank_cameras(batch: dict[str, Tensor], camera_keys: list[str]) -> dict[str, Tensor]:
    """A copy of `batch` whose cameras are all-zero images (black, as images are not normalized)."""
    missing = [key for key in camera_keys if key not in batch]
    if missing:
        raise ValueError(f"Cameras {missing} are not in the batch (keys: {sorted(batch)}).")
    return {key: torch.zeros_like(value) if key in camera_keys else value for key, value in batch.items()}


def camera_dependence(policy, batch: dict[str, Tensor], *, seed: int = 0) -> CameraDependence:
    """Refines chunks for the (pre-processed) observations in `batch` with real and with blanked cameras.

    Args:
        policy: An `EBVLAPolicy`.
        batch: A pre-processed observation batch of B frames (cameras, state, task for the VLM backbone).
        seed: Seeds a^(0) and the Langevin noise, identically for both passes.
    """
    camera_keys = list(policy.config.image_features)
    device = next(policy.parameters()).device

    def refine(observation: dict[str, Tensor]) -> tuple[Tensor, Tensor]:
        generator = torch.Generator(device=device).manual_seed(seed)
        chunk, readout = policy.predict_action_chunk(observation, generator=generator, return_energy=True)
        return chunk.float(), readout.final_energy.float()

    was_training = policy.training
    policy.eval()
    try:
        real_chunk, real_energy = refine(batch)
        blank_chunk, blank_energy = refine(blank_cameras(batch, camera_keys))
    finally:
        policy.train(was_training)
    change = (real_chunk - blank_chunk).flatten(1).norm(dim=1) / real_chunk.flatten(1).norm(dim=1).clamp(
        min=1e-8
    )
    return CameraDependence(
        chunk_change=change.mean().item(),
        energy_real=real_energy.mean().item(),
        energy_blank=blank_energy.mean().item(),
        num_frames=real_chunk.shape[0],
    )


def checkpoint_camera_dependence(
    checkpoint: str | Path, dataset_root: str | Path, repo_id: str, num_frames: int = 16, seed: int = 0
) -> CameraDependence:
    """`camera_dependence` of a saved policy on `num_frames` frames spread over a LeRobotDataset.

    Args:
        checkpoint: A `pretrained_model` folder (weights, config and processors).
        dataset_root: Folder of the dataset; `repo_id` its id.
        num_frames: Frames compared, evenly spaced over the dataset.
        seed: Seeds a^(0) and the Langevin noise of both passes.
    """
    import numpy as np
    from lerobot.datasets import LeRobotDataset
    from lerobot.policies.factory import make_pre_post_processors
    from torch.utils.data import default_collate

    from ..modeling_ebvla import EBVLAPolicy

    policy = EBVLAPolicy.from_pretrained(checkpoint)
    preprocessor, _ = make_pre_post_processors(policy.config, pretrained_path=str(checkpoint))
    dataset = LeRobotDataset(repo_id, root=dataset_root)
    keys = [*policy.config.input_features, "task"]
    indices = np.linspace(0, len(dataset) - 1, num=min(num_frames, len(dataset))).round().astype(int)
    frames = [{key: dataset[int(i)][key] for key in keys} for i in indices]
    return camera_dependence(policy, preprocessor(default_collate(frames)), seed=seed)
