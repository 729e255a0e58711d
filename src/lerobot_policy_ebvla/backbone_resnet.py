"""The light backbone: LeRobot's Diffusion Policy image encoder, for the head-only experiments.

The paper validates the EBT head against Diffusion Policy with "the same vision encoder" (Sec. III-A). This
backbone therefore reuses LeRobot's `DiffusionRgbEncoder` (ResNet, spatial-softmax keypoints, a linear layer)
as it is (`resnet.vision_backbone_stages` can cut its ResNet short), so an `ebvla` policy and LeRobot's `diffusion` policy built from the same encoder fields differ
only in their action head. Each camera becomes one context token, the proprioceptive state another:

    C = [camera_1; ...; camera_n; p] in R^{(n + 1) x D},  shared by all head blocks,

followed by a learned token of the task instruction when `resnet.task_instructions` is set.
"""

from types import SimpleNamespace

import torch
from einops import rearrange
from lerobot.policies.diffusion.modeling_diffusion import DiffusionRgbEncoder, SpatialSoftmax
from lerobot.policies.utils import get_output_shape
from lerobot.utils.constants import OBS_STATE
from torch import Tensor, nn

from .configuration_ebvla import EBVLAConfig


def keep_resnet_stages(encoder: DiffusionRgbEncoder, num_stages: int, config) -> DiffusionRgbEncoder:
    """Cuts `encoder`'s ResNet after stage `num_stages` (1-4) and fits its spatial softmax to the finer map.

    Works on any config with Diffusion Policy's encoder fields, so a `diffusion` baseline can get the same
    encoder as an `ebvla` policy (research/benchmarks/vision_dependence_offline.py does).
    """
    dropped_stages = 4 - num_stages
    if dropped_stages == 0:
        return encoder
    # `encoder.backbone` is the ResNet's children up to layer4: stem (4 modules), layer1, ..., layer4.
    encoder.backbone = encoder.backbone[: len(encoder.backbone) - dropped_stages]
    image_shape = next(iter(config.image_features.values())).shape
    height_width = config.crop_shape or config.resize_shape or image_shape[1:]
    feature_map_shape = get_output_shape(encoder.backbone, (1, image_shape[0], *height_width))[1:]
    encoder.pool = SpatialSoftmax(feature_map_shape, num_kp=config.spatial_softmax_num_keypoints)
    return encoder


def keep_own_keypoint_grid(module: SpatialSoftmax, state_dict: dict, prefix: str, *_) -> None:
    """Load pre-hook: a saved keypoint grid of another feature-map size gives way to `module`'s own.

    `pos_grid` is a function of the feature map's shape alone, so replacing it lets a checkpoint's weights load at
    another `resnet.resize_shape` (fine-tuning on larger frames); every learned weight still has to match.
    """
    key = prefix + "pos_grid"
    if key in state_dict and state_dict[key].shape != module.pos_grid.shape:
        state_dict[key] = module.pos_grid.detach().clone()


def diffusion_encoder_fields(config: EBVLAConfig) -> SimpleNamespace:
    """The light backbone's fields (`config.resnet`, under Diffusion Policy's names) with the cameras: what
    `DiffusionRgbEncoder` and `keep_resnet_stages` read from a `DiffusionConfig`."""
    return SimpleNamespace(**vars(config.resnet), image_features=config.image_features)


class ResNetFeatureMap(DiffusionRgbEncoder):
    """Diffusion Policy's encoder without its pooling: every cell of the ResNet's feature map is one token.

    Spatial-softmax keypoints start out nearly uniform, so the few numbers they pass on barely change with the
    image, and the energy's second-order gradient is too weak to sharpen them in a short CPU run: the light
    policies of research/docs/energy_study.md stayed blind. Feature-map cells differ with the image from the first step,
    and the head's cross-attention picks the cells it needs, as it does with the VLM's patch tokens.
    """

    def __init__(self, config: SimpleNamespace):
        """`config`: the encoder's fields, as `diffusion_encoder_fields` gives them."""
        super().__init__(config)
        keep_resnet_stages(self, config.vision_backbone_stages, config)
        del self.pool, self.out, self.relu
        image_shape = next(iter(config.image_features.values())).shape
        height_width = config.crop_shape or config.resize_shape or image_shape[1:]
        channels, height, width = get_output_shape(self.backbone, (1, image_shape[0], *height_width))[1:]
        self.feature_dim, self.num_cells = channels, height * width

    def forward(self, x: Tensor) -> Tensor:
        """(B, C, H, W) images in [0, 1] -> (B, cells, channels) features."""
        if self.resize is not None:
            x = self.resize(x)
        if self.do_crop:
            x = self.maybe_random_crop(x) if self.training else self.center_crop(x)
        return rearrange(self.backbone(x), "b c h w -> b (h w) c")


class EBVLAResNetBackbone(nn.Module):
    """Encodes cameras and state into the context tokens of the energy head.

    Args:
        config: Reads the Diffusion-Policy encoder fields (`resnet.vision_backbone`, `resnet.resize_shape`, `resnet.crop_shape`,
            `resnet.crop_is_random`, `resnet.use_group_norm`, `resnet.pretrained_backbone_weights`,
            `resnet.spatial_softmax_num_keypoints`, `resnet.use_separate_rgb_encoder_per_camera`), `resnet.vision_backbone_stages`,
            `resnet.camera_tokens`, the image and state features, `dim_model` (the token width), `n_blocks`,
            `resnet.state_dropout` and `resnet.task_instructions`.
    """

    def __init__(self, config: EBVLAConfig):
        super().__init__()
        self.config = config
        self.camera_keys = list(config.image_features)
        self.context_dim = config.dim_model
        n_encoders = len(self.camera_keys) if config.resnet.use_separate_rgb_encoder_per_camera else 1
        # `config.resnet` carries the encoder's fields under Diffusion Policy's names, so it builds it directly.
        encoder = diffusion_encoder_fields(config)
        if config.resnet.camera_tokens == "feature_map":
            self.rgb_encoders = nn.ModuleList(ResNetFeatureMap(encoder) for _ in range(n_encoders))
            tokens_per_camera = self.rgb_encoders[0].num_cells
        else:
            self.rgb_encoders = nn.ModuleList(
                keep_resnet_stages(DiffusionRgbEncoder(encoder), encoder.vision_backbone_stages, encoder)
                for _ in range(n_encoders)
            )
            tokens_per_camera = 1
            for module in self.rgb_encoders.modules():
                if isinstance(module, SpatialSoftmax):
                    module.register_load_state_dict_pre_hook(keep_own_keypoint_grid)
        self.camera_proj = nn.Linear(self.rgb_encoders[0].feature_dim, self.context_dim)
        # Cross-attention is permutation invariant: learned embeddings tell the head which camera (and which
        # feature-map cell) a token comes from.
        self.camera_embed = nn.Parameter(torch.zeros(len(self.camera_keys), self.context_dim))
        nn.init.normal_(self.camera_embed, std=0.02)
        self.cell_embed = None
        if tokens_per_camera > 1:
            self.cell_embed = nn.Parameter(torch.zeros(tokens_per_camera, self.context_dim))
            nn.init.normal_(self.cell_embed, std=0.02)
        self.state_proj = nn.Linear(config.state_dim, self.context_dim) if config.state_dim else None
        self.task_index = {task: i for i, task in enumerate(config.resnet.task_instructions or [])}
        self.task_embed = nn.Embedding(len(self.task_index), self.context_dim) if self.task_index else None

    def encode_cameras(self, batch: dict[str, Tensor]) -> Tensor:
        """Returns the camera tokens, (B, n_cameras * tokens_per_camera, D), camera by camera."""
        images = torch.stack([batch[key] for key in self.camera_keys], dim=1)  # (B, n, C, H, W)
        if len(self.rgb_encoders) == 1:
            features = self.rgb_encoders[0](rearrange(images, "b n c h w -> (b n) c h w"))
            features = features.unflatten(0, (images.shape[0], len(self.camera_keys)))
        else:
            features = torch.stack([enc(images[:, i]) for i, enc in enumerate(self.rgb_encoders)], dim=1)
        if features.dim() == 3:  # keypoints: one feature vector per camera
            features = features.unsqueeze(2)
        tokens = self.camera_proj(features) + self.camera_embed.unsqueeze(1)  # (B, n, tokens_per_camera, D)
        if self.cell_embed is not None:
            tokens = tokens + self.cell_embed
        return tokens.flatten(1, 2)

    def encode_task(self, batch: dict[str, Tensor]) -> Tensor:
        """Returns the learned token of each sample's task instruction, (B, 1, D)."""
        tasks = batch.get("task")
        if tasks is None:
            raise ValueError(
                f"The light backbone has task tokens for {len(self.task_index)} instructions "
                "(`resnet.task_instructions`), and the batch has no `task`."
            )
        tasks = [tasks] if isinstance(tasks, str) else list(tasks)
        unknown = sorted({task for task in tasks if task not in self.task_index})
        if unknown:
            raise ValueError(
                f"Unknown task instruction(s) {unknown}: the policy was trained on {list(self.task_index)}."
            )
        indices = torch.tensor(
            [self.task_index[task] for task in tasks], device=self.task_embed.weight.device
        )
        return self.task_embed(indices).unsqueeze(1)

    def forward(self, batch: dict[str, Tensor]) -> list[Tensor]:
        """Returns the context C of every head block, each (B, camera tokens [+ state] [+ task], D)."""
        tokens = [self.encode_cameras(batch)]
        if self.state_proj is not None:
            state = self.state_proj(batch[OBS_STATE]).unsqueeze(1)  # p, (B, 1, D)
            if self.training and self.config.resnet.state_dropout > 0:
                # Zeroing p (not dropping the token) keeps the context's length fixed for every sample.
                keep = (
                    torch.rand(state.shape[0], 1, 1, device=state.device) >= self.config.resnet.state_dropout
                )
                state = state * keep
            tokens.append(state)
        if self.task_embed is not None:
            tokens.append(self.encode_task(batch))
        context = torch.cat(tokens, dim=1)
        return [context] * self.config.n_blocks
