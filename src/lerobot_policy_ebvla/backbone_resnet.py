"""The light backbone: LeRobot's Diffusion Policy image encoder, for the head-only experiments.

The paper validates the EBT head against Diffusion Policy with "the same vision encoder" (Sec. III-A). This
backbone therefore reuses LeRobot's `DiffusionRgbEncoder` (ResNet, spatial-softmax keypoints, a linear layer)
as it is, so an `ebvla` policy and LeRobot's `diffusion` policy built from the same encoder fields differ
only in their action head. Each camera becomes one context token, the proprioceptive state another:

    C = [camera_1; ...; camera_n; p] in R^{(n + 1) x D},  shared by all head blocks.
"""

import torch
from einops import rearrange
from lerobot.policies.diffusion.modeling_diffusion import DiffusionRgbEncoder
from lerobot.utils.constants import OBS_STATE
from torch import Tensor, nn

from .configuration_ebvla import EBVLAConfig


class EBVLAResNetBackbone(nn.Module):
    """Encodes cameras and state into the context tokens of the energy head.

    Args:
        config: Reads the Diffusion-Policy encoder fields (`vision_backbone`, `resize_shape`, `crop_shape`,
            `crop_is_random`, `use_group_norm`, `pretrained_backbone_weights`,
            `spatial_softmax_num_keypoints`, `use_separate_rgb_encoder_per_camera`), the image and state
            features, `dim_model` (the token width), `n_blocks` and `state_dropout`.
    """

    def __init__(self, config: EBVLAConfig):
        super().__init__()
        self.config = config
        self.camera_keys = list(config.image_features)
        self.context_dim = config.dim_model
        n_encoders = len(self.camera_keys) if config.use_separate_rgb_encoder_per_camera else 1
        # `EBVLAConfig` carries the encoder's fields under Diffusion Policy's names, so it builds it directly.
        self.rgb_encoders = nn.ModuleList(DiffusionRgbEncoder(config) for _ in range(n_encoders))
        feature_dim = self.rgb_encoders[0].feature_dim
        self.camera_proj = nn.Linear(feature_dim, self.context_dim)
        # Cross-attention is permutation invariant: a learned embedding tells the head which camera is which.
        self.camera_embed = nn.Parameter(torch.zeros(len(self.camera_keys), self.context_dim))
        nn.init.normal_(self.camera_embed, std=0.02)
        self.state_proj = nn.Linear(config.state_dim, self.context_dim) if config.state_dim else None

    def encode_cameras(self, batch: dict[str, Tensor]) -> Tensor:
        """Returns one token per camera, (B, n_cameras, D)."""
        images = torch.stack([batch[key] for key in self.camera_keys], dim=1)  # (B, n, C, H, W)
        if len(self.rgb_encoders) == 1:
            features = self.rgb_encoders[0](rearrange(images, "b n c h w -> (b n) c h w"))
            features = rearrange(features, "(b n) d -> b n d", n=len(self.camera_keys))
        else:
            features = torch.stack(
                [enc(images[:, i]) for i, enc in enumerate(self.rgb_encoders)], dim=1
            )  # (B, n, feature_dim)
        return self.camera_proj(features) + self.camera_embed

    def forward(self, batch: dict[str, Tensor]) -> list[Tensor]:
        """Returns the context C of every head block, each (B, n_cameras [+ 1], D)."""
        tokens = [self.encode_cameras(batch)]
        if self.state_proj is not None:
            state = self.state_proj(batch[OBS_STATE]).unsqueeze(1)  # p, (B, 1, D)
            if self.training and self.config.state_dropout > 0:
                # Zeroing p (not dropping the token) keeps the context's length fixed for every sample.
                keep = torch.rand(state.shape[0], 1, 1, device=state.device) >= self.config.state_dropout
                state = state * keep
            tokens.append(state)
        context = torch.cat(tokens, dim=1)
        return [context] * self.config.n_blocks
