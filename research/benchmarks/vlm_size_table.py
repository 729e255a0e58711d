"""Parameter and memory table of the full-size EB-VLA (paper defaults, Table V), built on the meta device.

Nothing is downloaded and no memory is allocated: the policy is built with random-weight configs on
`torch.device("meta")`, and sizes are read off its parameters. Run:

    python research/benchmarks/vlm_size_table.py --offline

`--offline` skips the Hub and uses the built-in Qwen2.5-0.5B config values below; without it the tool first
asks the Hub (or the local cache) for `Qwen/Qwen2.5-0.5B`'s config.
"""

import argparse
import logging

import torch
from lerobot.configs.types import FeatureType, PolicyFeature

from lerobot_policy_ebvla import EBVLAConfig, EBVLAPolicy
from lerobot_policy_ebvla.configuration_groups import VLMBackboneConfig

# FALLBACK ONLY, used when the Hub is unreachable: Qwen/Qwen2.5-0.5B's config.json values (24 layers, width 896,
# MLP 4864, 14 query / 2 key-value heads, 151936 tokens, tied embeddings, RoPE theta 1e6).
QWEN25_05B_FALLBACK_CONFIG = {
    "model_type": "qwen2",
    "vocab_size": 151936,
    "hidden_size": 896,
    "intermediate_size": 4864,
    "num_hidden_layers": 24,
    "num_attention_heads": 14,
    "num_key_value_heads": 2,
    "hidden_act": "silu",
    "max_position_embeddings": 32768,
    "initializer_range": 0.02,
    "rms_norm_eps": 1e-6,
    "rope_parameters": {"rope_type": "default", "rope_theta": 1_000_000.0},
    "tie_word_embeddings": True,
    "use_sliding_window": False,
    "max_window_layers": 24,
    "bos_token_id": 151643,
    "eos_token_id": 151643,
}

GIB = 1024**3


def full_size_config(state_dim: int = 8, action_dim: int = 7, offline: bool = False) -> EBVLAConfig:
    """The paper's configuration: two 224 px cameras (primary, wrist), LIBERO-like state and action sizes."""
    config = EBVLAConfig(
        device="cpu",
        vlm=VLMBackboneConfig(load_pretrained_backbone=False),
        input_features={
            "observation.images.primary": PolicyFeature(FeatureType.VISUAL, (3, 224, 224)),
            "observation.images.wrist": PolicyFeature(FeatureType.VISUAL, (3, 224, 224)),
            "observation.state": PolicyFeature(FeatureType.STATE, (state_dim,)),
        },
        output_features={"action": PolicyFeature(FeatureType.ACTION, (action_dim,))},
    )
    if offline:
        config.vlm.model_config = dict(QWEN25_05B_FALLBACK_CONFIG)
    else:
        try:
            from transformers import AutoConfig

            config.vlm.model_config = AutoConfig.from_pretrained(config.vlm.model_name).to_diff_dict()
        except OSError as error:
            logging.warning("Hub unreachable (%s): using the built-in Qwen2.5-0.5B config.", error)
            config.vlm.model_config = dict(QWEN25_05B_FALLBACK_CONFIG)
    return config


def components(policy: EBVLAPolicy) -> dict[str, list[torch.nn.Parameter]]:
    """The policy's parameters grouped by component, each parameter in exactly one group."""
    backbone = policy.model.backbone
    lm_named = list(backbone.lm.named_parameters())
    groups = {
        "DINOv2 ViT-L/14 (reg4)": list(backbone.vision.encoders["dinov2"].parameters()),
        "SigLIP So400m/14": list(backbone.vision.encoders["siglip"].parameters()),
        "Projector (fused GELU MLP)": list(backbone.projector.parameters()),
        "Qwen2.5-0.5B base": [p for n, p in lm_named if "lora_" not in n],
        "LoRA adapters": [p for n, p in lm_named if "lora_" in n],
        "Latents K_a + proprio p": [
            backbone.latents,
            *(p for m in (backbone.state_proj,) if m for p in m.parameters()),
        ],
        "Energy head (EBT)": list(policy.model.head.parameters()),
    }
    if backbone.state_token is not None:
        groups["Latents K_a + proprio p"].append(backbone.state_token)
    grouped = {id(p) for ps in groups.values() for p in ps}
    if grouped != {id(p) for p in policy.parameters()}:
        raise RuntimeError("Some parameters belong to no component: update `components`.")
    return groups


def size_table(policy: EBVLAPolicy) -> str:
    rows = []
    total = trainable_total = 0
    for name, params in components(policy).items():
        n = sum(p.numel() for p in params)
        n_train = sum(p.numel() for p in params if p.requires_grad)
        total, trainable_total = total + n, trainable_total + n_train
        rows.append((name, n, n_train))
    rows.append(("Total", total, trainable_total))
    lines = [
        "| Component | Params (M) | Trainable (M) | Frozen (M) | fp32 (GiB) | bf16 (GiB) |",
        "| --- | ---: | ---: | ---: | ---: | ---: |",
    ]
    for name, n, n_train in rows:
        lines.append(
            f"| {name} | {n / 1e6:.2f} | {n_train / 1e6:.2f} | {(n - n_train) / 1e6:.2f} | "
            f"{4 * n / GIB:.3f} | {2 * n / GIB:.3f} |"
        )
    frozen = total - trainable_total
    # AdamW: weights + gradient + two moments for each trainable parameter, weights alone for frozen ones.
    fp32_static = 4 * total + 3 * 4 * trainable_total
    mixed_static = (
        2 * frozen + 4 * 4 * trainable_total
    )  # bf16 frozen weights, fp32 trainable + grads + moments
    bf16_static = 2 * total + 3 * 2 * trainable_total  # everything bf16 (the GPU benchmark's setting)
    # `EBVLAPolicy._save_pretrained` stores a tensor in bf16 when bf16 holds it exactly: every frozen weight with
    # `frozen_weights_dtype="bfloat16"`, which rounds them when the backbone is built. Trainable ones stay fp32.
    narrow_frozen = 2 if policy.config.vlm.frozen_weights_dtype == "bfloat16" else 4
    lines += [
        "",
        "Checkpoint (model.safetensors, weights only):",
        f"- frozen_weights_dtype=float32 (all fp32): {4 * total / GIB:.3f} GiB",
        f"- frozen_weights_dtype={policy.config.vlm.frozen_weights_dtype} (frozen in that dtype, trainable fp32): "
        f"{(narrow_frozen * frozen + 4 * trainable_total) / GIB:.3f} GiB",
        "",
        "Static training memory (weights, gradients and AdamW moments; activations excluded):",
        f"- all fp32: {fp32_static / GIB:.2f} GiB",
        f"- frozen weights bf16, trainable fp32 (weights + grads + moments): {mixed_static / GIB:.2f} GiB",
        f"- all bf16: {bf16_static / GIB:.2f} GiB",
    ]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--offline", action="store_true", help="Use the built-in Qwen2.5-0.5B config.")
    parser.add_argument("--state-dim", type=int, default=8, help="Proprioceptive state size (LIBERO: 8).")
    parser.add_argument("--action-dim", type=int, default=7, help="Action size d_a (Table V: 7).")
    args = parser.parse_args()

    config = full_size_config(args.state_dim, args.action_dim, offline=args.offline)
    with torch.device("meta"):
        policy = EBVLAPolicy(config)
    backbone = policy.model.backbone
    print(
        f"EB-VLA full size: K_t = {backbone.num_vision_tokens} vision tokens, K_a = {config.vlm.num_latent_tokens} "
        f"latents, {config.vlm.tokenizer_max_length} instruction tokens, context layers {backbone.context_layers}, "
        f"LoRA rank {config.vlm.lora_rank}, head L = {config.n_blocks}, D = {config.dim_model}.\n"
    )
    print(size_table(policy))


if __name__ == "__main__":
    main()
