"""The paper's vision-language backbone (Sec. II-A): fused DINOv2 + SigLIP, a Prismatic projector, Qwen2.5.

Following Prismatic and OpenVLA-OFT, every camera is encoded by two frozen ViTs whose patch features are
concatenated per patch and projected to the language model's width D. The language model (LoRA-tuned, base
weights frozen) reads the prompt

    [ vision tokens (K_t = 256 per camera) | instruction tokens (padded) | K_a learned latents ]

and returns the hidden states of all its layers, the embedding output included. The context of energy-head
block i is built from one of them, l_i (Eq. 1):

    C_i = [h_a^(l_i); p; h_t^(l_i)] in R^{(K_a + 1 + K_t) x D},

with h_t the first K_t positions (the vision tokens only: the paper's "first K_t positions", K_t = 512 for two
cameras), h_a the last K_a positions (the latents, which attend to the vision and instruction tokens) and p
the linearly projected proprioceptive state (a learned token when the dataset has no state). The instruction
reaches the head through h_a only: under the causal mask the vision positions never see it.
"""

from collections.abc import Iterator
from contextlib import contextmanager

import timm
import torch
import torch.nn.functional as F  # noqa: N812
from einops import rearrange
from lerobot.utils.constants import OBS_LANGUAGE_ATTENTION_MASK, OBS_LANGUAGE_TOKENS, OBS_STATE
from peft import LoraConfig, inject_adapter_in_model
from torch import Tensor, nn
from transformers import AutoConfig, AutoModel, PretrainedConfig

from .configuration_ebvla import EBVLAConfig


class PretrainedWeightsUnavailableError(OSError):
    """Pretrained backbone weights (or the language model's config) could not be fetched from the Hub or cache."""


ENCODER_LABELS = {"dinov2": "DINOv2", "siglip": "SigLIP"}

# How to point each field at local weights, for the error message.
_LOCAL_FOLDER_HINTS = {
    "vlm.dinov2_model_name": "'local-dir:/path' holding timm's config.json and model.safetensors",
    "vlm.siglip_model_name": "'local-dir:/path' holding timm's config.json and model.safetensors",
    "vlm.model_name": "a folder written by transformers' save_pretrained, tokenizer included",
}


@contextmanager
def fetching(field: str, name: str, what: str) -> Iterator[None]:
    """Turns a failed Hub or cache look-up of `name` (the config field `field`) into one actionable error.

    With no network and an empty cache, huggingface_hub and transformers raise an `OSError` deep inside
    timm or `from_pretrained`; the user needs to know which weights are missing and how to proceed.
    """
    try:
        yield
    except OSError as error:
        # The cause's first line; the rest of it is chained.
        reason = next(iter(str(error).strip().splitlines()), "").rstrip(".")
        raise PretrainedWeightsUnavailableError(
            f"Could not fetch the {what} `{field}={name!r}` ({type(error).__name__}: {reason}). To proceed: "
            "download it once with network access into the Hugging Face cache (HF_HOME), set "
            f"`--policy.{field}` to {_LOCAL_FOLDER_HINTS[field]}, or train the light backbone with "
            "`--policy.backbone=resnet`."
        ) from error


class EBVLAFusedVisionEncoder(nn.Module):
    """DINOv2 and SigLIP patch features of the same image, concatenated per patch (Prismatic's fused encoder).

    Each encoder sees the image resized to `vlm.vision_image_size` and normalized with its own mean and std, and
    contributes the patch tokens of its second-to-last block (Prismatic's choice; prefix tokens dropped).
    The last block, final norm and head are pruned away: they would never be used.

    Args:
        config: Reads `vlm.dinov2_model_name`, `vlm.siglip_model_name`, `vlm.vision_image_size`, `vlm.vision_model_overrides`,
            `vlm.load_pretrained_backbone` and `vlm.freeze_vision_encoder`.
    """

    def __init__(self, config: EBVLAConfig):
        super().__init__()
        self.image_size = config.vlm.vision_image_size
        self.frozen = config.vlm.freeze_vision_encoder
        self.encoders = nn.ModuleDict()
        self.layer_index: dict[str, int] = {}
        self.image_stats: dict[str, tuple[tuple[float, ...], tuple[float, ...]]] = {}
        grids = set()
        for name, model_name in (
            ("dinov2", config.vlm.dinov2_model_name),
            ("siglip", config.vlm.siglip_model_name),
        ):
            with fetching(f"vlm.{name}_model_name", model_name, f"{ENCODER_LABELS[name]} encoder weights"):
                encoder = timm.create_model(
                    model_name,
                    pretrained=config.vlm.load_pretrained_backbone,
                    img_size=self.image_size,
                    num_classes=0,
                    **config.vlm.vision_model_overrides,
                )
            if len(encoder.blocks) < 2:
                raise ValueError(
                    f"The `{model_name}` encoder needs >= 2 blocks (features are read at the second-to-last)."
                )
            data_config = timm.data.resolve_model_data_config(encoder)
            (self.layer_index[name],) = encoder.prune_intermediate_layers(
                indices=[len(encoder.blocks) - 2], prune_norm=True, prune_head=True
            )
            self.encoders[name] = encoder
            # Plain floats rather than buffers: derived from the timm name, and never cast to bf16 with the model.
            self.image_stats[name] = (tuple(data_config["mean"]), tuple(data_config["std"]))
            grids.add(tuple(encoder.patch_embed.grid_size))
        if len(grids) != 1:
            raise ValueError(
                f"DINOv2 and SigLIP must cut `vlm.vision_image_size={self.image_size}` into the same patch grid to be "
                f"fused per patch. Got grids {sorted(grids)}."
            )
        (grid,) = grids
        self.num_patches = grid[0] * grid[1]
        self.embed_dim = sum(encoder.embed_dim for encoder in self.encoders.values())
        if self.frozen:
            self.encoders.requires_grad_(False)

    def train(self, mode: bool = True) -> "EBVLAFusedVisionEncoder":
        # Frozen encoders stay in eval mode (no dropout or drop-path), whatever the policy's mode.
        return super().train(mode and not self.frozen)

    def resize(self, images: Tensor) -> Tensor:
        """(N, 3, H, W) in [0, 1] -> (N, 3, S, S), S = `vlm.vision_image_size`, bicubic as in the timm transforms."""
        images = images.float()  # antialiased bicubic has no bf16 kernel; normalization is cast down after
        if images.shape[-2:] == (self.image_size, self.image_size):
            return images
        resized = F.interpolate(
            images, size=(self.image_size,) * 2, mode="bicubic", antialias=True, align_corners=False
        )
        return resized.clamp(0.0, 1.0)  # bicubic overshoots

    def forward(self, images: Tensor) -> Tensor:
        """(N, 3, S, S) images in [0, 1] -> fused patch features (N, num_patches, embed_dim)."""
        features = []
        with torch.set_grad_enabled(torch.is_grad_enabled() and not self.frozen):
            for name, encoder in self.encoders.items():
                mean, std = (
                    torch.tensor(stat, device=images.device).view(1, 3, 1, 1)
                    for stat in self.image_stats[name]
                )
                x = ((images.float() - mean) / std).to(encoder.patch_embed.proj.weight.dtype)
                (patches,) = encoder.forward_intermediates(
                    x, indices=[self.layer_index[name]], intermediates_only=True, output_fmt="NLC"
                )
                features.append(patches)  # (N, num_patches, embed_dim of this encoder)
        return torch.cat(features, dim=-1)


class EBVLAVisionProjector(nn.Module):
    """Prismatic's fused GELU MLP projector: vision_dim -> 4 vision_dim -> D -> D."""

    def __init__(self, vision_dim: int, lm_dim: int):
        super().__init__()
        self.mlp = nn.Sequential(
            nn.Linear(vision_dim, 4 * vision_dim),
            nn.GELU(),
            nn.Linear(4 * vision_dim, lm_dim),
            nn.GELU(),
            nn.Linear(lm_dim, lm_dim),
        )

    def forward(self, features: Tensor) -> Tensor:
        return self.mlp(features)


def resolve_language_model_config(config: EBVLAConfig) -> PretrainedConfig:
    """The language model's config; resolved once from `vlm.model_name`, then read from `config.vlm.model_config`.

    The first resolution (Hub, cache or local folder) is recorded in `config.vlm.model_config`, so a saved
    `config.json` is enough to rebuild the model offline.
    """
    if config.vlm.model_config is None:
        with fetching("vlm.model_name", config.vlm.model_name, "language model's config"):
            resolved = AutoConfig.from_pretrained(config.vlm.model_name).to_dict()
        if "num_hidden_layers" in config.vlm.model_config_overrides:
            # The per-layer attention types are derived from the depth; a stale list would fail validation.
            resolved.pop("layer_types", None)
        lm_config = AutoConfig.for_model(**{**resolved, **config.vlm.model_config_overrides})
        config.vlm.model_config = lm_config.to_diff_dict()
    return AutoConfig.for_model(**config.vlm.model_config)


def default_context_layers(num_context_layers: int, n_blocks: int) -> tuple[int, ...]:
    """Hidden-state indices l_1..l_L spread evenly over the N_l extracted states 0..N_l - 1, ends included.

    Table V extracts N_l = 23 states "with the embedding": states 0 (the embedding output) to 22 of Qwen2.5-0.5B's
    25. With L = 4 blocks this gives (0, 7, 15, 22); one block takes the deepest extracted state.
    """
    last = num_context_layers - 1
    if n_blocks == 1:
        return (last,)
    return tuple(round(i * last / (n_blocks - 1)) for i in range(n_blocks))


def round_frozen_weights(module: nn.Module, dtype: torch.dtype) -> None:
    """Rounds every frozen parameter of `module` to `dtype` precision, keeping its storage dtype.

    The frozen encoders and base language model then hold exactly the values a `dtype` copy holds: the policy
    computes with the weights its checkpoint stores in `dtype` (half the bytes for bf16, see
    `EBVLAPolicy._save_pretrained`), so a saved and reloaded policy acts exactly as the one that was trained.
    """
    with torch.no_grad():
        for param in module.parameters():
            if not param.requires_grad and param.is_floating_point() and param.dtype != dtype:
                param.copy_(param.to(dtype))


def resolve_context_layers(config: EBVLAConfig, num_layers: int) -> tuple[int, ...]:
    """l_1..l_L: `vlm.context_layers` if set, else `default_context_layers`, checked against the N + 1 states."""
    num_hidden_states = num_layers + 1
    if config.vlm.context_layers is not None:
        if max(config.vlm.context_layers) >= num_hidden_states:
            raise ValueError(
                f"`vlm.context_layers` must index the {num_hidden_states} hidden states of the language model "
                f"(0..{num_hidden_states - 1}). Got {tuple(config.vlm.context_layers)}."
            )
        return tuple(config.vlm.context_layers)
    if config.vlm.num_context_layers > num_hidden_states:
        raise ValueError(
            f"`vlm.num_context_layers` must be <= {num_hidden_states} (the language model's layers + the "
            f"embedding). Got {config.vlm.num_context_layers}."
        )
    return default_context_layers(config.vlm.num_context_layers, config.n_blocks)


class EBVLAVisionLanguageBackbone(nn.Module):
    """Encodes cameras, instruction and state into the per-block contexts C_i of the energy head (Eq. 1).

        cameras ──► fused DINOv2+SigLIP (frozen) ──► projector ──► vision tokens (K_t) ─┐
        instruction tokens ──► embedding (frozen) ──────────────────────────────────────┤
        K_a learned latents ────────────────────────────────────────────────────────────┤
                                                                                         ▼
                        Qwen2.5 + LoRA ──► hidden states h^(0..N) ──► [h_a^(l_i); p; h_t^(l_i)] = C_i
        state ──► linear ──► p ─────────────────────────────────────────────────────┘

    Trainable: LoRA adapters, projector, latents and the state projection (or token). Frozen: the vision
    encoders (unless `vlm.freeze_vision_encoder=False`) and every base weight of the language model.

    Attributes:
        context_dim: Width D of the context tokens (the language model's hidden size).
        context_layers: Hidden-state index l_i feeding head block i.
        num_vision_tokens: K_t, vision tokens over all cameras.

    Args:
        config: The EB-VLA config; `config.vlm.model_config` is filled in if it was None.
    """

    def __init__(self, config: EBVLAConfig):
        super().__init__()
        self.config = config
        self.camera_keys = list(config.image_features)
        self.vision = EBVLAFusedVisionEncoder(config)
        self.num_vision_tokens = self.vision.num_patches * len(self.camera_keys)

        lm_config = resolve_language_model_config(config)
        self.context_dim = lm_config.hidden_size
        self.context_layers = resolve_context_layers(config, lm_config.num_hidden_layers)
        if config.vlm.load_pretrained_backbone:
            # fp32 like the rest of the policy; cast the whole policy for bf16.
            with fetching("vlm.model_name", config.vlm.model_name, "language model weights"):
                self.lm = AutoModel.from_pretrained(
                    config.vlm.model_name, config=lm_config, dtype=torch.float32
                )
        else:
            self.lm = AutoModel.from_config(lm_config, dtype=torch.float32)
        self.lm.requires_grad_(False)
        # Hidden state l is the output of `layers[l - 1]`: layers past the deepest l_i never reach the head, so
        # adapters there would get no gradient.
        deepest = max(self.context_layers)
        read_layers = {"layers_to_transform": list(range(deepest)), "layers_pattern": "layers"}
        lora = LoraConfig(
            r=config.vlm.lora_rank,
            lora_alpha=config.vlm.lora_alpha,
            lora_dropout=config.vlm.lora_dropout,
            target_modules=list(config.vlm.lora_target_modules),
            **(read_layers if 0 < deepest < lm_config.num_hidden_layers else {}),
        )
        self.lm = inject_adapter_in_model(lora, self.lm)
        for name, param in self.lm.named_parameters():
            param.requires_grad_("lora_" in name)

        self.projector = EBVLAVisionProjector(self.vision.embed_dim, self.context_dim)
        # Initialised like the language model's own embeddings.
        self.latents = nn.Parameter(
            torch.randn(config.vlm.num_latent_tokens, self.context_dim) * lm_config.initializer_range
        )
        if config.state_dim is not None:
            self.state_proj = nn.Linear(config.state_dim, self.context_dim)
            self.state_token = None
        else:
            self.state_proj = None
            self.state_token = nn.Parameter(torch.randn(1, self.context_dim) * lm_config.initializer_range)
        if config.vlm.frozen_weights_dtype != "float32":
            round_frozen_weights(self, getattr(torch, config.vlm.frozen_weights_dtype))

    def encode_images(self, batch: dict[str, Tensor]) -> Tensor:
        """Projected vision tokens of all cameras, camera after camera: (B, K_t, D)."""
        # Resizing first lets cameras of different native resolutions share one encoder pass.
        images = torch.cat([self.vision.resize(batch[key]) for key in self.camera_keys])  # (n B, 3, S, S)
        features = self.vision(images)  # (n B, P, vision_dim)
        features = features.to(self.projector.mlp[0].weight.dtype)
        features = rearrange(features, "(n b) p d -> b (n p) d", n=len(self.camera_keys))
        return self.projector(features)

    def encode_state(self, batch: dict[str, Tensor], batch_size: int) -> Tensor:
        """p: the projected state, or the learned token without one, (B, 1, D)."""
        if self.state_proj is None:
            return self.state_token.expand(batch_size, -1, -1)
        state = batch[OBS_STATE].to(self.state_proj.weight.dtype)
        return self.state_proj(state).unsqueeze(1)

    def forward(self, batch: dict[str, Tensor]) -> list[Tensor]:
        """Returns C_i = [h_a^(l_i); p; h_t^(l_i)], each (B, K_a + 1 + K_t, D), one per head block."""
        if OBS_LANGUAGE_TOKENS not in batch or OBS_LANGUAGE_ATTENTION_MASK not in batch:
            raise ValueError(
                f"The VLM backbone needs the tokenized task under `{OBS_LANGUAGE_TOKENS}` and "
                f"`{OBS_LANGUAGE_ATTENTION_MASK}` (the EB-VLA pre-processor's tokenizer step). Got {sorted(batch)}."
            )
        vision_tokens = self.encode_images(batch)  # (B, K_t, D)
        batch_size, k_t, k_a = (
            vision_tokens.shape[0],
            self.num_vision_tokens,
            self.config.vlm.num_latent_tokens,
        )
        text_tokens = self.lm.get_input_embeddings()(batch[OBS_LANGUAGE_TOKENS])  # (B, T, D)
        latents = self.latents.to(text_tokens.dtype).expand(batch_size, -1, -1)  # (B, K_a, D)
        inputs_embeds = torch.cat([vision_tokens.to(text_tokens.dtype), text_tokens, latents], dim=1)

        text_mask = batch[OBS_LANGUAGE_ATTENTION_MASK].to(torch.long)
        mask = torch.cat(
            [text_mask.new_ones(batch_size, k_t), text_mask, text_mask.new_ones(batch_size, k_a)], dim=1
        )
        # Padding sits between the instruction and the latents; counting only real tokens keeps the latents'
        # rotary positions right after the instruction, whatever its length.
        position_ids = (mask.cumsum(dim=1) - 1).clamp(min=0)
        hidden_states = self.lm(
            inputs_embeds=inputs_embeds,
            attention_mask=mask,
            position_ids=position_ids,
            output_hidden_states=True,
            use_cache=False,
        ).hidden_states  # N + 1 tensors (B, K_t + T + K_a, D); the last one after the final norm

        p = self.encode_state(batch, batch_size).to(text_tokens.dtype)
        return [
            torch.cat([hidden_states[layer][:, -k_a:], p, hidden_states[layer][:, :k_t]], dim=1)
            for layer in self.context_layers
        ]
