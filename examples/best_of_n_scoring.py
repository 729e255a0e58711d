"""Use the energy as a verifier: refine N candidate chunks per observation and keep the lowest-energy one.

`policy.score_action_chunks(batch, candidates)` returns E(a, C) of any chunks you give it, (B, N) for
(B, N, H, d_a) normalized candidates, encoding each observation once. Here the candidates are N refinements
from different seeds (`predict_action_chunk(batch, generator=...)`); they could as well come from another
policy or a planner. On dataset frames the expert's own chunk is known, so the script reports how far the
lowest-energy candidate is from it, against an arbitrary candidate, and where the expert chunk itself scores.
(`--policy.num_restarts=N` does the same selection inside the policy, at every refinement.)

    python examples/best_of_n_scoring.py --checkpoint=outputs/example_metaworld/train/checkpoints/last/pretrained_model \\
        --dataset_root=outputs/example_metaworld/data --n_candidates=8
"""

from dataclasses import dataclass
from pathlib import Path

import draccus
import torch
from lerobot.datasets import LeRobotDataset, LeRobotDatasetMetadata
from lerobot.policies import make_pre_post_processors
from lerobot.utils.constants import ACTION
from torch.utils.data import default_collate

from lerobot_policy_ebvla import EBVLAPolicy


@dataclass
class BestOfNConfig:
    # The `pretrained_model` folder of the checkpoint.
    checkpoint: Path = Path("outputs/example_metaworld/train/checkpoints/last/pretrained_model")
    # The LeRobotDataset to take observations (and the expert's chunks) from.
    dataset_root: Path = Path("outputs/example_metaworld/data")
    # Candidate chunks refined per observation.
    n_candidates: int = 8
    # Observations, spread over the dataset.
    n_frames: int = 16


def main(cfg: BestOfNConfig) -> None:
    policy = EBVLAPolicy.from_pretrained(cfg.checkpoint).eval()
    preprocessor, _ = make_pre_post_processors(policy.config, pretrained_path=cfg.checkpoint)
    horizon = policy.config.chunk_size

    # Frames with the expert's next H actions, so each observation comes with the expert chunk a*.
    fps = LeRobotDatasetMetadata("local/dataset", root=cfg.dataset_root).fps
    dataset = LeRobotDataset(
        "local/dataset", root=cfg.dataset_root, delta_timestamps={ACTION: [t / fps for t in range(horizon)]}
    )
    indices = torch.linspace(0, len(dataset) - 1, min(cfg.n_frames, len(dataset))).round().long()
    keys = [*policy.config.input_features, ACTION, "task"]
    frames = [dataset[int(i)] for i in indices]
    batch = preprocessor(default_collate([{key: frame[key] for key in keys} for frame in frames]))
    expert = batch.pop(ACTION)  # (B, H, d_a), normalized like the policy's actions

    # N candidates per observation: refinements from N seeds, (B, N, H, d_a).
    with torch.no_grad():
        seeds = [torch.Generator().manual_seed(seed) for seed in range(cfg.n_candidates)]
        candidates = torch.stack([policy.predict_action_chunk(batch, generator=g) for g in seeds], dim=1)
    energies = policy.score_action_chunks(batch, candidates)  # (B, N)
    expert_energy = policy.score_action_chunks(batch, expert.unsqueeze(1))[:, 0]  # (B,)

    best = candidates[torch.arange(len(candidates)), energies.argmin(dim=1)]  # (B, H, d_a)
    l1_best = (best - expert).abs().mean().item()
    l1_first = (candidates[:, 0] - expert).abs().mean().item()
    l1_all = (candidates - expert.unsqueeze(1)).abs().mean().item()
    print(f"\n{len(expert)} observations, {cfg.n_candidates} candidates each")
    print(
        f"L1 to the expert chunk (normalized): lowest-energy {l1_best:.3f}, first {l1_first:.3f}, mean {l1_all:.3f}"
    )
    print(
        f"Energy: candidates {energies.mean():.3f} (min {energies.min(dim=1).values.mean():.3f}), "
        f"expert chunk {expert_energy.mean():.3f}"
    )


if __name__ == "__main__":
    main(draccus.parse(BestOfNConfig))
