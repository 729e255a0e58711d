"""The energy landscape of a saved policy around one observation's refined chunk (paper Fig. 2), as a PNG.

The body of `ebvla-landscape`: load the policy and its pre-processor, take one observation (a dataset frame or
a `torch.save`d dict), sweep two action dimensions of one chunk timestep (`monitoring.landscape`) and plot it
(`monitoring.plots`).
"""

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from ..monitoring.landscape import policy_energy_landscape
from ..monitoring.plots import plot_energy_landscape


@dataclass
class LandscapeConfig:
    """Energy landscape (Fig. 2): the energy over a 2-D grid of one timestep's actions around a refined chunk.

    Give the policy and one observation: `dataset_repo_id` (+ `dataset_root`, `frame_index`) or
    `observation`.
    """

    # Local `pretrained_model` folder or Hub repo id of the policy.
    policy_path: str | None = None
    # LeRobotDataset to take the observation from.
    dataset_repo_id: str | None = None
    # Local root of the dataset.
    dataset_root: Path | None = None
    # Global frame index in the dataset.
    frame_index: int = 0
    # A `torch.save`d observation dict (instead of a dataset frame).
    observation: Path | None = None
    # The two action dimensions swept.
    dims: list[int] = field(default_factory=lambda: [0, 1])
    # The chunk timestep swept.
    timestep: int = 0
    # Grid points per axis.
    grid_size: int = 50
    # One value s: sweep [value - s, value + s] around the refined action; two values: an absolute range.
    span: list[float] = field(default_factory=lambda: [1.0])
    # Candidate chunks scored per call.
    batch_size: int = 1024
    # surface, contour or both.
    kind: str = "both"
    # Torch device; default: the policy config's.
    device: str | None = None
    # Seed of the initial sample a^(0).
    seed: int = 0
    # The PNG written.
    output: Path = Path("outputs/energy_landscape.png")

    def validate(self) -> None:
        # Not __post_init__: draccus would wrap the ValueError in a less readable ParsingError.
        if self.policy_path is None:
            raise ValueError("`policy_path` is required: a `pretrained_model` folder or a Hub repo id.")
        if (self.dataset_repo_id is None) == (self.observation is None):
            raise ValueError("Give exactly one of `dataset_repo_id` and `observation`.")
        if len(self.span) not in (1, 2):
            raise ValueError(f"`span` takes one value (half-width) or two (low, high), got {self.span}.")
        if len(self.dims) != 2:
            raise ValueError(f"`dims` must be two action dimensions, got {self.dims}.")


def load_observation(cfg: LandscapeConfig) -> dict[str, Any]:
    """The raw observation (observation.* keys and task) of a dataset frame or a saved dict."""
    if cfg.observation is not None:
        return torch.load(cfg.observation, map_location="cpu")
    from lerobot.datasets import LeRobotDataset

    frame = LeRobotDataset(cfg.dataset_repo_id, root=cfg.dataset_root)[cfg.frame_index]
    return {k: v for k, v in frame.items() if k.startswith("observation.") or k == "task"}


def run(cfg: LandscapeConfig) -> Path:
    cfg.validate()
    # Imported here so that `--help` stays fast.
    from lerobot.policies.factory import make_pre_post_processors

    from ..modeling_ebvla import EBVLAPolicy

    policy = EBVLAPolicy.from_pretrained(cfg.policy_path)
    device = torch.device(cfg.device or policy.config.device)
    policy.to(device).eval()
    preprocessor, _ = make_pre_post_processors(
        policy.config,
        pretrained_path=cfg.policy_path,
        preprocessor_overrides={"device_processor": {"device": str(device)}},
    )
    batch = preprocessor(load_observation(cfg))
    span = cfg.span[0] if len(cfg.span) == 1 else tuple(cfg.span)
    landscape = policy_energy_landscape(
        policy,
        batch,
        generator=torch.Generator(device).manual_seed(cfg.seed),
        dims=tuple(cfg.dims),
        timestep=cfg.timestep,
        grid_size=cfg.grid_size,
        span=span,
        batch_size=cfg.batch_size,
    )
    title = f"Energy landscape, action dims {tuple(cfg.dims)} at timestep {cfg.timestep}"
    path = plot_energy_landscape(landscape, cfg.output, kind=cfg.kind, title=title)
    logging.info(f"Refined chunk energy {landscape.center_energy:.4f}; saved the landscape to {path}")
    return path
