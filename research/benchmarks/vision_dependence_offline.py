"""Does a light policy trained on MetaWorld demonstrations read its camera? Offline, no rendering.

Trains `ebvla` (one or more training-signal variants) and, optionally, LeRobot's `diffusion` with the same
image encoder on the first episodes of a recorded LeRobotDataset (`ebvla-record-metaworld`), then compares on
frames of the held-out episodes:

- `l1`: mean L1 of the predicted (normalized) chunk against the expert's; `l1_blank`: the same with the camera
  blanked; `l1_mean_chunk`: the blind baseline of always predicting the training set's mean chunk;
- `chunk_change`: relative change of the predicted chunk when the camera is blanked, same noise;
- for ebvla, the final energy with the real and the blanked camera.

A policy whose `chunk_change` is ~0 is blind: it acts from the state alone, and no camera perturbation can
change its success or its energy.

Example (research/docs/energy_study.md):

    MUJOCO_GL=egl ebvla-record-metaworld --env.task=button-press-v3 --env.fast_render=true \\
        --episodes_per_task=24 --image_size=96 --repo_id=local/mw_bp --root=/tmp/mw_bp96
    python research/benchmarks/vision_dependence_offline.py --root /tmp/mw_bp96 --steps 400 --variants paper contrastive \\
        --diffusion
"""

import argparse
import json
import time
from pathlib import Path

import torch
from lerobot.configs.types import FeatureType
from lerobot.datasets import LeRobotDataset
from lerobot.datasets.factory import resolve_delta_timestamps
from lerobot.policies.factory import make_pre_post_processors
from lerobot.utils.feature_utils import dataset_to_policy_features

from lerobot_policy_ebvla import EBVLAPolicy
from lerobot_policy_ebvla.backbone_resnet import keep_resnet_stages
from lerobot_policy_ebvla.monitoring.vision import blank_cameras
from lerobot_policy_ebvla.presets import ebvla_config

VARIANTS = {
    "paper": {},
    "straight_through_clip": {"train_straight_through_clip": True},
    "contrastive": {"contrastive": {"weight": 1.0}},
    "straight_through+contrastive": {"train_straight_through_clip": True, "contrastive": {"weight": 1.0}},
    "state_dropout": {"resnet": {"state_dropout": 0.5}},
    "state_dropout+contrastive": {"resnet": {"state_dropout": 0.5}, "contrastive": {"weight": 1.0}},
    "state_dropout+straight_through": {"resnet": {"state_dropout": 0.5}, "train_straight_through_clip": True},
    # The control: no state input at all, so the camera is the only way to the expert chunk.
    "no_state": {},
    "no_state+straight_through": {"train_straight_through_clip": True},
    "no_state+contrastive": {"contrastive": {"weight": 1.0}},
    "no_state+contrastive_0.1": {"contrastive": {"weight": 0.1}},
    "contrastive_0.1": {"contrastive": {"weight": 0.1}},
    "state_dropout+contrastive_0.1": {"resnet": {"state_dropout": 0.5}, "contrastive": {"weight": 0.1}},
}
# The image encoder both methods share (DiffusionConfig and EBVLAConfig's `resnet` name these fields alike).
ENCODER = {
    "vision_backbone": "resnet18",
    "pretrained_backbone_weights": None,
    "use_group_norm": True,
    "spatial_softmax_num_keypoints": 32,
}


def split_features(meta):
    features = dataset_to_policy_features(meta.features)
    outputs = {k: f for k, f in features.items() if f.type is FeatureType.ACTION}
    inputs = {k: f for k, f in features.items() if k not in outputs}
    return inputs, outputs


def make_policy(method: str, variant: str, meta, args):
    overrides = VARIANTS.get(variant, {})
    inputs, outputs = split_features(meta)
    if variant.startswith("no_state") and method == "ebvla":
        inputs = {k: f for k, f in inputs.items() if f.type is not FeatureType.STATE}
    crop = (int(args.resize * 0.9),) * 2
    common = {
        "input_features": inputs,
        "output_features": outputs,
        "device": "cpu",
        "resize_shape": (args.resize, args.resize),
        "crop_shape": crop,
        **ENCODER,
        "crop_is_random": not args.fixed_crop,
    }
    if method == "diffusion":
        from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
        from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy

        config = DiffusionConfig(
            n_obs_steps=1,
            horizon=8,
            n_action_steps=8,
            down_dims=(128, 256, 512),
            num_inference_steps=10,
            noise_scheduler_type="DDIM",
            **common,
        )
        policy = DiffusionPolicy(config)
        encoders = policy.diffusion.rgb_encoder
        for encoder in encoders if isinstance(encoders, torch.nn.ModuleList) else [encoders]:
            keep_resnet_stages(encoder, args.stages, config)
        return policy, config
    io = {name: common.pop(name) for name in ("input_features", "output_features", "device")}
    encoder = {**common, "vision_backbone_stages": args.stages, "camera_tokens": args.camera_tokens}
    config = ebvla_config(
        {
            "backbone": "resnet",
            "dim_model": args.dim_model,
            "n_heads": 4,
            "n_blocks": 2,
            "train_mcmc_steps_range": tuple(args.train_mcmc_steps),
            "resnet": encoder,
            **io,
        },
        overrides,
    )
    return EBVLAPolicy(config), config


def hide_state(batch: dict, method: str, variant: str) -> dict:
    """The no-state control for diffusion, which needs a state input: the (normalized) state is zeroed."""
    if method == "diffusion" and variant.startswith("no_state"):
        return batch | {"observation.state": torch.zeros_like(batch["observation.state"])}
    return batch


def predict(policy, method: str, batch: dict, seed: int) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The normalized chunk (B, 8, d_a) and, for ebvla, the final energy; the same noise for every call."""
    if method == "diffusion":
        torch.manual_seed(seed)
        return policy.predict_action_chunk(batch)[:, :8], None
    chunk, readout = policy.predict_action_chunk(
        batch, generator=torch.Generator().manual_seed(seed), return_energy=True
    )
    return chunk, readout.final_energy


def run(method: str, variant: str, args) -> dict:
    meta = LeRobotDataset(args.repo_id, root=args.root).meta
    torch.manual_seed(args.seed)
    policy, config = make_policy(method, variant, meta, args)
    delta = resolve_delta_timestamps(config, meta)
    episodes = list(range(meta.total_episodes))
    train_eps, test_eps = episodes[: -args.held_out], episodes[-args.held_out :]
    train_set = LeRobotDataset(args.repo_id, root=args.root, episodes=train_eps, delta_timestamps=delta)
    test_set = LeRobotDataset(args.repo_id, root=args.root, episodes=test_eps, delta_timestamps=delta)
    pre, _ = make_pre_post_processors(config, dataset_stats=meta.stats)
    loader = torch.utils.data.DataLoader(
        train_set, batch_size=args.batch_size, shuffle=True, generator=torch.Generator().manual_seed(0)
    )
    optimizer = torch.optim.AdamW(policy.parameters(), lr=args.lr, weight_decay=1e-4)
    start, step = time.time(), 0
    policy.train()
    while step < args.steps:
        for raw in loader:
            loss, _ = policy.forward(hide_state(pre(raw), method, variant))
            optimizer.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(policy.parameters(), 10.0)
            optimizer.step()
            step += 1
            if step >= args.steps:
                break
    train_seconds = time.time() - start

    policy.eval()
    frames = torch.linspace(0, len(test_set) - 1, args.test_frames).long().tolist()
    batch = hide_state(pre(torch.utils.data.default_collate([test_set[i] for i in frames])), method, variant)
    target = batch["action"][:, :8]
    observation = {k: v for k, v in batch.items() if k.startswith("observation.")}
    camera_keys = [k for k in observation if k.startswith("observation.image")]
    with torch.no_grad():
        chunk, energy = predict(policy, method, observation, args.seed)
        blank_chunk, blank_energy = predict(
            policy, method, blank_cameras(observation, camera_keys), args.seed
        )
    mean_chunk = torch.stack(
        [
            pre(torch.utils.data.default_collate([train_set[i]]))["action"][0, :8]
            for i in range(0, len(train_set), max(1, len(train_set) // 200))
        ]
    ).mean(dim=0)
    change = (chunk - blank_chunk).flatten(1).norm(dim=1) / chunk.flatten(1).norm(dim=1).clamp(min=1e-8)
    result = {
        "method": method,
        "variant": variant,
        "stages": args.stages,
        "fixed_crop": args.fixed_crop,
        "camera_tokens": args.camera_tokens if method == "ebvla" else "keypoints",
        "steps": args.steps,
        "train_seconds": round(train_seconds, 1),
        "final_train_loss": loss.item(),
        "l1": (chunk - target).abs().mean().item(),
        "l1_blank": (blank_chunk - target).abs().mean().item(),
        "l1_mean_chunk": (mean_chunk - target).abs().mean().item(),
        "chunk_change": change.mean().item(),
    }
    if energy is not None:
        result |= {"energy_real": energy.mean().item(), "energy_blank": blank_energy.mean().item()}
    return result


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--root", type=Path, required=True)
    parser.add_argument("--repo-id", default="local/mw_bp")
    parser.add_argument("--steps", type=int, default=400)
    parser.add_argument("--batch-size", type=int, default=16)
    parser.add_argument("--lr", type=float, default=5e-4)
    parser.add_argument("--resize", type=int, default=96)
    parser.add_argument("--stages", type=int, default=4, help="ResNet stages the shared encoder keeps (1-4).")
    parser.add_argument(
        "--camera-tokens", default="keypoints", choices=["keypoints", "feature_map"], help="ebvla only."
    )
    parser.add_argument(
        "--fixed-crop",
        action="store_true",
        help="Center crop in training too (absolute pixel positions kept).",
    )
    parser.add_argument("--dim-model", type=int, default=128)
    parser.add_argument("--train-mcmc-steps", type=int, nargs=2, default=(2, 4))
    parser.add_argument("--held-out", type=int, default=4, help="Last episodes kept for testing.")
    parser.add_argument("--test-frames", type=int, default=64)
    parser.add_argument("--variants", nargs="*", default=["paper"], choices=list(VARIANTS))
    parser.add_argument("--diffusion", action="store_true", help="Also train LeRobot's diffusion policy.")
    parser.add_argument(
        "--diffusion-no-state", action="store_true", help="Train diffusion without the state (the control)."
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    diffusion_variant = "no_state" if args.diffusion_no_state else "-"
    runs = [("ebvla", v) for v in args.variants] + (
        [("diffusion", diffusion_variant)] if args.diffusion else []
    )
    results = []
    for method, variant in runs:
        results.append(run(method, variant, args))
        print(json.dumps(results[-1]), flush=True)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(
            json.dumps({"args": {k: str(v) for k, v in vars(args).items()}, "results": results}, indent=1)
        )


if __name__ == "__main__":
    main()
