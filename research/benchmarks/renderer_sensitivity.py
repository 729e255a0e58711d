"""How far E_c moves under what a second machine could change in a frame, against how far it moved there.

E's rollouts on a lent H200 (NVIDIA's EGL, the policy on CUDA) put E_c at the first chunk 5.9-7.1 above the same
fixed states rendered here (Mesa's software EGL, the policy on the CPU), with a spread of 0.005-0.14 over episodes
(research/docs/libero_runs.md, "E's evaluation on a lent GPU"). Two things differ there: the frames (another OpenGL
implementation) and the arithmetic (lerobot-eval turns on TF32 for matrix products, and cuDNN's convolutions use
TF32 by default). This script measures, on the CPU, E_c's change under each candidate on dataset frames:

- the arithmetic: every Conv2d and Linear input and weight rounded to TF32's 10-bit mantissa (an upper bound on
  what TF32 changes: it rounds the products' inputs, not the accumulation);
- the frames: pixel noise of 1-4 levels, a blur of 0.5 px (another anti-aliasing), a gamma of 0.95 or 1.05
  (another colour transfer), a one-pixel shift (another rasterization rule).

    python research/benchmarks/renderer_sensitivity.py \\
        --checkpoint=outputs/libero10_arm/train/ebvla_joint_fast_cpu_arm/checkpoints/last/pretrained_model \\
        --dataset=outputs/libero10_arm/data/all --output=research/results/libero_object10_arm_gpu/renderer_sensitivity.json

It reads E_c only; which of the two moved it on the machine takes a run there with the policy on the CPU.
"""

import argparse
import json
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch
from libero_pipeline import REPO_ID  # the recorded dataset's id, one name for it
from torch.nn import functional


def round_to_tf32(x: torch.Tensor) -> torch.Tensor:
    """x with its float32 mantissa rounded to TF32's 10 bits (round half to even on the dropped 13 bits)."""
    bits = x.float().contiguous().view(torch.int32)
    dropped = 13
    half = 1 << (dropped - 1)
    lsb = (bits >> dropped) & 1
    rounded = ((bits + half - 1 + lsb) >> dropped) << dropped
    return rounded.view(torch.float32)


@contextmanager
def tf32_arithmetic(module: torch.nn.Module):
    """Rounds the inputs and weights of every Conv2d and Linear of `module` to TF32 while the context is open."""
    layers = [m for m in module.modules() if isinstance(m, (torch.nn.Conv2d, torch.nn.Linear))]
    saved = [layer.weight.data.clone() for layer in layers]
    # Straight through: the MCMC still differentiates E with respect to the actions through the rounded inputs.
    hooks = [
        layer.register_forward_pre_hook(
            lambda _, args: tuple(a + (round_to_tf32(a) - a).detach() for a in args)
        )
        for layer in layers
    ]
    for layer in layers:
        layer.weight.data = round_to_tf32(layer.weight.data)
    try:
        yield
    finally:
        for hook in hooks:
            hook.remove()
        for layer, weight in zip(layers, saved, strict=True):
            layer.weight.data = weight


def blur(images: torch.Tensor, sigma: float, radius: int = 2) -> torch.Tensor:
    """A separable Gaussian blur of (B, C, H, W) images, edges replicated."""
    x = torch.arange(-radius, radius + 1, dtype=images.dtype)
    kernel = torch.exp(-(x**2) / (2 * sigma**2))
    kernel = (kernel / kernel.sum()).repeat(images.shape[1], 1, 1, 1)  # (C, 1, 1, 2r + 1)
    pad = functional.pad(images, (radius, radius, 0, 0), mode="replicate")
    rows = functional.conv2d(pad, kernel, groups=images.shape[1])
    pad = functional.pad(rows, (0, 0, radius, radius), mode="replicate")
    return functional.conv2d(pad, kernel.transpose(-1, -2), groups=images.shape[1])


def frame_changes(generator: torch.Generator) -> dict:
    """Each candidate change to a camera frame (B, C, H, W) in [0, 1]."""

    def noise(levels: int):
        return lambda x: (
            x + (torch.randint(-levels, levels + 1, x.shape, generator=generator) / 255.0)
        ).clamp(0, 1)

    return {
        "pixel_noise_1": noise(1),
        "pixel_noise_4": noise(4),
        "blur_0.5px": lambda x: blur(x, 0.5),
        "gamma_0.95": lambda x: x.clamp(0, 1) ** 0.95,
        "gamma_1.05": lambda x: x.clamp(0, 1) ** 1.05,
        "shift_1px": lambda x: torch.roll(x, shifts=1, dims=-1),
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--checkpoint", type=Path, required=True)
    parser.add_argument("--dataset", type=Path, required=True)
    parser.add_argument("--frames", type=int, default=32)
    parser.add_argument("--output", type=Path, default=None)
    args = parser.parse_args(argv)

    from lerobot.datasets import LeRobotDataset
    from lerobot.policies.factory import make_pre_post_processors
    from torch.utils.data import default_collate

    from lerobot_policy_ebvla.modeling_ebvla import EBVLAPolicy

    torch.manual_seed(0)
    policy = EBVLAPolicy.from_pretrained(str(args.checkpoint)).eval()
    preprocessor, _ = make_pre_post_processors(policy.config, pretrained_path=str(args.checkpoint))
    dataset = LeRobotDataset(REPO_ID, root=args.dataset)
    keys = [*policy.config.input_features, "task"]
    indices = np.linspace(0, len(dataset) - 1, num=args.frames).round().astype(int)
    frames = [{key: dataset[int(i)][key] for key in keys} for i in indices]
    cameras = list(policy.config.image_features)

    def context_energy(observation: dict) -> np.ndarray:
        batch = preprocessor(default_collate(observation))
        generator = torch.Generator().manual_seed(0)
        _, readout = policy.predict_action_chunk(batch, generator=generator, return_energy=True)
        return readout.context_energy.float().numpy()

    base = context_energy(frames)
    result = {
        "checkpoint": str(args.checkpoint),
        "frames": len(frames),
        "context_energy_mean": float(base.mean()),
        "context_energy_spread": float(base.std()),
        "mean_abs_change": {},
    }
    with tf32_arithmetic(policy):
        result["mean_abs_change"]["tf32_conv_and_linear"] = float(
            np.abs(context_energy(frames) - base).mean()
        )
    generator = torch.Generator().manual_seed(1)
    for name, change in frame_changes(generator).items():
        changed = [{k: change(v[None])[0] if k in cameras else v for k, v in f.items()} for f in frames]
        result["mean_abs_change"][name] = float(np.abs(context_energy(changed) - base).mean())
    print(json.dumps(result, indent=1))
    if args.output is not None:
        args.output.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
