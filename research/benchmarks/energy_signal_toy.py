"""Which training signal makes the energy see and know? A controlled toy, minutes on a 2-core CPU.

The observation is a 48x48 image with one white square at a random position plus a 4-d state of pure noise;
the expert chunk is a ramp towards the square's position (2-d actions). A policy that does not read its camera
cannot do better than the mean chunk. The same light `ebvla` policy is trained with each training-signal
variant (the paper's recipe, the straight-through clip, the contrastive energy term, per-MCMC-step alpha) and
then measured on held-out observations:

- `test_l1`: L1 of the refined chunk against the expert (`mean_chunk_l1` is the blind baseline);
- `blank_change`: relative change of the refined chunk when the camera is blanked (`monitoring.vision`);
- `rank_acc`: fraction of observations whose expert chunk has a lower energy than another observation's;
- `auroc_<shift>`: AUROC of the final energy E(a^(K), C), in-distribution test images against shifted ones
  (a blank image, a second "distractor" square, Gaussian pixel noise, a grey square), per-observation scores.

Example (the run in research/docs/energy_study.md):

    python research/benchmarks/energy_signal_toy.py --steps 300 --seeds 0 1 2 --json research/results/energy_signal_toy.json
"""

import argparse
import json
import statistics
import time
from pathlib import Path

import torch
from lerobot.configs.types import FeatureType, PolicyFeature

from lerobot_policy_ebvla import EBVLAConfig, EBVLAPolicy
from lerobot_policy_ebvla.configuration_groups import ContrastiveConfig, ResNetBackboneConfig
from lerobot_policy_ebvla.monitoring import auroc
from lerobot_policy_ebvla.monitoring.vision import camera_dependence

IMAGE = (3, 48, 48)
SQUARE = 12
CHUNK, ACTION_DIM = 8, 2
VARIANTS = {
    "paper": {},
    "straight_through_clip": {"train_straight_through_clip": True},
    "contrastive": {"contrastive": ContrastiveConfig(weight=1.0)},
    "straight_through+contrastive": {
        "train_straight_through_clip": True,
        "contrastive": ContrastiveConfig(weight=1.0),
    },
    "alpha_per_mcmc_step": {"train_step_size_sampling": "per_mcmc_step"},
}


def square_images(positions: torch.Tensor, value: float = 1.0) -> torch.Tensor:
    images = torch.zeros(len(positions), *IMAGE)
    span = IMAGE[1] - SQUARE
    for i, (row, col) in enumerate((positions * span).long().tolist()):
        images[i, :, row : row + SQUARE, col : col + SQUARE] = value
    return images


def make_split(n: int, seed: int) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    positions = torch.rand(n, 2, generator=g)
    ramp = torch.linspace(0.3, 1.0, CHUNK)[None, :, None]
    return {
        "observation.images.top": square_images(positions),
        "observation.state": torch.randn(n, 4, generator=g),
        "action": 1.5 * (2 * positions - 1)[:, None, :] * ramp,
        "action_is_pad": torch.zeros(n, CHUNK, dtype=torch.bool),
    }


def shifted_images(images: torch.Tensor, shift: str, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    if shift == "blank":
        return torch.zeros_like(images)
    if shift == "distractor":
        return (images + square_images(torch.rand(len(images), 2, generator=g))).clamp(max=1.0)
    if shift == "noise":
        return (images + 0.3 * torch.randn(images.shape, generator=g)).clamp(0.0, 1.0)
    if shift == "grey":
        return images * 0.5
    raise ValueError(f"Unknown shift {shift!r}.")


def make_config(overrides: dict) -> EBVLAConfig:
    return EBVLAConfig(
        backbone="resnet",
        device="cpu",
        resnet=ResNetBackboneConfig(spatial_softmax_num_keypoints=8),
        input_features={
            "observation.images.top": PolicyFeature(FeatureType.VISUAL, IMAGE),
            "observation.state": PolicyFeature(FeatureType.STATE, (4,)),
        },
        output_features={"action": PolicyFeature(FeatureType.ACTION, (ACTION_DIM,))},
        dim_model=64,
        n_heads=4,
        n_blocks=2,
        train_mcmc_steps_range=(3, 5),
        inference_mcmc_steps=10,
        **overrides,
    )


def train(policy: EBVLAPolicy, data: dict, steps: int, batch_size: int, seed: int) -> float:
    optimizer = torch.optim.AdamW(policy.parameters(), lr=1e-3)
    g = torch.Generator().manual_seed(seed)
    n = len(data["action"])
    for _ in range(steps):
        idx = torch.randint(0, n, (batch_size,), generator=g)
        loss, _ = policy.forward({k: v[idx] for k, v in data.items()})
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    return loss.item()


def final_energy(policy: EBVLAPolicy, observation: dict) -> torch.Tensor:
    _, readout = policy.predict_action_chunk(
        observation, generator=torch.Generator().manual_seed(0), return_energy=True
    )
    return readout.final_energy


def normalized_energy(policy: EBVLAPolicy, observation: dict, num_samples: int = 32) -> torch.Tensor:
    """The refined chunk's energy relative to the context's own energy scale (`policy.normalized_energy`, a
    Monte-Carlo log-partition over `num_samples` prior samples, the same draws for every call)."""
    generator = torch.Generator().manual_seed(1)
    return policy.normalized_energy(observation, final_energy(policy, observation), num_samples, generator)


def evaluate(policy: EBVLAPolicy, test: dict, seed: int) -> dict[str, float]:
    policy.eval()
    observation = {k: v for k, v in test.items() if k.startswith("observation.")}
    chunk = policy.predict_action_chunk(observation, generator=torch.Generator().manual_seed(0))
    expert = test["action"]
    energy_expert = policy.score_action_chunks(observation, expert[:, None])[:, 0]
    energy_other = policy.score_action_chunks(observation, expert.roll(1, dims=0)[:, None])[:, 0]
    energy_in = final_energy(policy, observation).tolist()
    normalized_in = normalized_energy(policy, observation).tolist()
    metrics = {
        "test_l1": (chunk - expert).abs().mean().item(),
        "mean_chunk_l1": (expert.mean(dim=0, keepdim=True) - expert).abs().mean().item(),
        "blank_change": camera_dependence(policy, observation).chunk_change,
        "rank_acc": (energy_expert < energy_other).float().mean().item(),
    }
    for shift in ("blank", "distractor", "noise", "grey"):
        shifted = dict(observation)
        shifted["observation.images.top"] = shifted_images(observation["observation.images.top"], shift, seed)
        metrics[f"auroc_{shift}"] = auroc(energy_in, final_energy(policy, shifted).tolist())
        metrics[f"auroc_norm_{shift}"] = auroc(normalized_in, normalized_energy(policy, shifted).tolist())
    return metrics


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--batch-size", type=int, default=32)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    data, test = make_split(512, seed=1000), make_split(128, seed=2000)
    results: dict[str, list[dict]] = {}
    for variant in args.variants:
        for seed in args.seeds:
            torch.manual_seed(seed)
            policy = EBVLAPolicy(make_config(VARIANTS[variant]))
            start = time.time()
            train_loss = train(policy, data, args.steps, args.batch_size, seed)
            metrics = {"seed": seed, "train_l1": train_loss, **evaluate(policy, test, seed)}
            metrics["seconds"] = time.time() - start
            results.setdefault(variant, []).append(metrics)
            print(variant, {k: round(v, 3) for k, v in metrics.items()}, flush=True)
    print("\nmean over seeds")
    keys = [k for k in results[args.variants[0]][0] if k not in ("seed", "seconds")]
    print("| variant | " + " | ".join(keys) + " |")
    print("|---" * (len(keys) + 1) + "|")
    for variant, runs in results.items():
        row = [f"{statistics.mean(r[k] for r in runs):.3f}" for k in keys]
        print(f"| {variant} | " + " | ".join(row) + " |")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(
            json.dumps({"args": vars(args) | {"json": str(args.json)}, "results": results}, indent=1)
        )


if __name__ == "__main__":
    main()
