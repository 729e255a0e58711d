"""The contrastive term's head pass with each context's keys and values shared by its N candidates, against
copies of them per candidate (issue 23).

The contrastive term scores B x N candidate chunks (N = 1 + mismatched + noisy per context) through the energy
head, forward and backward, every training step. Since the head's cross-attention takes a context batch of B
for B x N chunks (`EBVLACrossAttention.forward`), the N candidates of a context are N * H queries of one
attention call; before, the keys and values were repeated N times (`repeat_interleave`) and the gradient summed
back. This times both on the light policy's head (D=128, 4 heads, L=2) at the quickstart's batch, the two
variants taking turns, and checks that they give the same energies. The gain grows with the context's length:
the light policy's context is 2 tokens (its camera's keypoints, the state), the VLA's 64 latent tokens and more.

    python research/benchmarks/shared_context_attention.py --json research/results/shared_context_attention_cpu.json
    python research/benchmarks/shared_context_attention.py --context_tokens=65
"""

import argparse
import json
import platform
import statistics
import time
from pathlib import Path

import torch
from lerobot.configs.types import FeatureType, PolicyFeature

from lerobot_policy_ebvla.energy_head import EBVLAEnergyHead
from lerobot_policy_ebvla.presets import light_policy_config


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--batch_size", type=int, default=16, help="Contexts B.")
    parser.add_argument(
        "--candidates", type=int, default=24, help="N per context: 1 + (B - 1) + 8 by default."
    )
    parser.add_argument(
        "--context_tokens",
        type=int,
        default=2,
        help="The light policy's: its camera's keypoint token, the state.",
    )
    parser.add_argument("--repeats", type=int, default=5, help="Rounds; each times both variants.")
    parser.add_argument(
        "--passes", type=int, default=10, help="Forward + backward passes per variant and round."
    )
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()

    torch.manual_seed(0)
    config = light_policy_config()
    config.output_features = {"action": PolicyFeature(type=FeatureType.ACTION, shape=(4,))}
    head = EBVLAEnergyHead(config, config.dim_model)
    b, n = args.batch_size, args.candidates
    contexts = [
        torch.randn(b, args.context_tokens, config.dim_model, requires_grad=True) for _ in head.blocks
    ]
    actions = torch.randn(b * n, config.chunk_size, 4)

    def energy(shared: bool) -> torch.Tensor:
        kv = head.context_kv(contexts)
        if not shared:
            kv = [(k.repeat_interleave(n, dim=0), v.repeat_interleave(n, dim=0)) for k, v in kv]
        return head(actions, kv).mean()

    difference = abs(energy(True).item() - energy(False).item())
    times = {"copied": [], "shared": []}
    for _ in range(args.repeats):
        for name in times:
            start = time.perf_counter()
            for _ in range(args.passes):
                energy(name == "shared").backward()
            times[name].append((time.perf_counter() - start) / args.passes * 1000)
    medians = {name: round(statistics.median(t), 1) for name, t in times.items()}
    print(
        f"head forward + backward of {b} x {n} candidates: copied keys/values {medians['copied']} ms, shared "
        f"{medians['shared']} ms (median of {args.repeats} rounds); |mean energy difference| {difference:.2e}"
    )
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(
            json.dumps(
                {
                    **{k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()},
                    "median_ms": medians,
                    "all_ms": times,
                    "mean_energy_difference": difference,
                    "machine": platform.processor() or platform.machine(),
                    "torch_threads": torch.get_num_threads(),
                    "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                },
                indent=2,
            )
        )


if __name__ == "__main__":
    main()
