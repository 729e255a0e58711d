"""The policies `bench_speed.py` compares and the random, already pre-processed inputs they all see."""

from dataclasses import dataclass

import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.utils.constants import ACTION, OBS_STATE
from torch import Tensor, nn

from lerobot_policy_ebvla import EBVLAConfig, EBVLAPolicy
from lerobot_policy_ebvla.configuration_groups import ResNetBackboneConfig

# Context tokens per head block of the paper's VLM: K_a latents + the state token + K_t = 2 x 256 vision tokens.
VLM_CONTEXT_TOKENS = 64 + 1 + 512

EBVLA_HEADS = {
    "ebvla-light": {"dim_model": 256, "n_heads": 8, "n_blocks": 4},
    "ebvla-paper": {"dim_model": 896, "n_heads": 8, "n_blocks": 4},
    "ebvla-tiny": {"dim_model": 32, "n_heads": 2, "n_blocks": 2},  # --quick only
}
DIFFUSION_VARIANTS = {
    "diffusion": {},  # LeRobot's defaults: down_dims (512, 1024, 2048), DDPM, 100 inference steps.
    "diffusion-cpu": {
        "down_dims": (128, 256, 512),
        "noise_scheduler_type": "DDIM",
        "num_inference_steps": 10,
    },
}


@dataclass
class Scene:
    """The inputs both policies see (RoboMimic-like: two 84 px cameras cropped to 76, 9-d state, 7-d action)."""

    cameras: int = 2
    image_size: int = 84
    crop: int = 76
    state_dim: int = 9
    action_dim: int = 7
    chunk: int = 8
    keypoints: int = 32

    def input_features(self) -> dict[str, PolicyFeature]:
        features = {
            f"observation.images.cam{i}": PolicyFeature(
                FeatureType.VISUAL, (3, self.image_size, self.image_size)
            )
            for i in range(self.cameras)
        }
        features[OBS_STATE] = PolicyFeature(FeatureType.STATE, (self.state_dim,))
        return features

    def encoder_fields(self) -> dict:
        """The image-encoder fields, spelled the same in `EBVLAConfig.resnet` and `DiffusionConfig`."""
        return {
            "vision_backbone": "resnet18",
            "pretrained_backbone_weights": None,
            "use_group_norm": True,
            "crop_shape": (self.crop, self.crop),
            "crop_is_random": True,
            "spatial_softmax_num_keypoints": self.keypoints,
            "use_separate_rgb_encoder_per_camera": True,
        }

    def observation(self, batch_size: int, device: torch.device, seed: int = 0) -> dict[str, Tensor]:
        g = torch.Generator().manual_seed(seed)
        batch = {
            key: torch.rand(batch_size, *ft.shape, generator=g)
            for key, ft in self.input_features().items()
            if ft.type is FeatureType.VISUAL
        }
        batch[OBS_STATE] = torch.randn(batch_size, self.state_dim, generator=g)
        return {k: v.to(device) for k, v in batch.items()}

    def training_batch(self, batch_size: int, device: torch.device, seed: int = 1) -> dict[str, Tensor]:
        batch = self.observation(batch_size, device, seed)
        g = torch.Generator().manual_seed(seed + 1)
        batch[ACTION] = torch.randn(batch_size, self.chunk, self.action_dim, generator=g).to(device)
        batch["action_is_pad"] = torch.zeros(batch_size, self.chunk, dtype=torch.bool, device=device)
        return batch


def make_ebvla(scene: Scene, head: dict, device: str) -> EBVLAPolicy:
    config = EBVLAConfig(
        backbone="resnet",
        device=device,
        input_features=scene.input_features(),
        output_features={ACTION: PolicyFeature(FeatureType.ACTION, (scene.action_dim,))},
        chunk_size=scene.chunk,
        n_action_steps=scene.chunk,
        resnet=ResNetBackboneConfig(**scene.encoder_fields()),
        **head,
    )
    return EBVLAPolicy(config).to(device)


def make_diffusion(scene: Scene, overrides: dict, device: str) -> nn.Module:
    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy

    config = DiffusionConfig(
        device=device,
        input_features=scene.input_features(),
        output_features={ACTION: PolicyFeature(FeatureType.ACTION, (scene.action_dim,))},
        n_obs_steps=1,
        horizon=scene.chunk,
        n_action_steps=scene.chunk,
        drop_n_last_frames=0,
        **scene.encoder_fields(),
        **overrides,
    )
    return DiffusionPolicy(config).to(device)
