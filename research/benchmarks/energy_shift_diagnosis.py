"""Where the final energy falls under a shift: context, expert-chunk energy, refined energy, landscape (issue 32).

Offline, on MetaWorld expert episodes recorded under each perturbation (`ebvla-record-metaworld
--env.perturbation=...`), so that every perturbed observation comes with the expert's own chunk a*. For each
chunk-boundary frame (every `n_action_steps`-th, whole chunks only) and each condition it measures:

- the context: the norm of the camera and state tokens of the last block's context, their distance to the
  vanilla mean, and the spread of the light backbone's spatial-softmax keypoints (how far they sit from the
  image centre);
- the energies: E(a*, C) at the expert chunk, E(a^(0), C) at the initial sample and E(a^(K), C) at the refined
  chunk (same MCMC noise in every condition), and the refined chunk's L1 distance to a*;
- the landscape around the refined chunk: the mean rise E(a^(K) + s n, C) - E(a^(K), C) over random unit-std
  directions n, for radii s, and the mean energy of prior samples N(0, sigma_init^2) (the landscape's level).

Writes one JSON of per-frame values per condition and prints a table of condition means (bootstrap 95% CI).

    python research/benchmarks/energy_shift_diagnosis.py --checkpoint=CK --data_root=DIR --conditions none_s0 light_dim_s5 \
        --output=diag.json
"""

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from lerobot.datasets import LeRobotDataset
from lerobot.policies.factory import make_pre_post_processors
from torch.utils.data import default_collate

from lerobot_policy_ebvla import EBVLAPolicy

RADII = (0.1, 0.3, 1.0)


def load_frames(policy, preprocessor, root: Path, repo_id: str) -> dict:
    cfg = policy.config
    meta = LeRobotDataset(repo_id, root=root)
    fps = meta.fps
    dataset = LeRobotDataset(
        repo_id, root=root, delta_timestamps={"action": [i / fps for i in range(cfg.chunk_size)]}
    )
    keys = [*cfg.input_features, "task", "action", "action_is_pad", "episode_index", "frame_index"]
    frames = []
    for i in range(len(dataset)):
        item = dataset[i]
        if int(item["frame_index"]) % cfg.n_action_steps or bool(item["action_is_pad"].any()):
            continue
        frames.append({k: item[k] for k in keys})
    batch = default_collate(frames)
    episodes, frame_index = batch.pop("episode_index"), batch.pop("frame_index")
    batch.pop("action_is_pad")
    return preprocessor(batch), episodes.numpy(), frame_index.numpy()


@torch.no_grad()
def keypoint_spread(policy, batch) -> np.ndarray:
    """Mean distance of the spatial-softmax keypoints from the image centre (in [-1, 1] coordinates).

    A study of the light backbone's internals (not a quantity the policy exposes)."""
    backbone = policy.model.backbone
    key = backbone.camera_keys[0]
    encoder = backbone.rgb_encoders[0]
    images = batch[key]
    if encoder.resize is not None:
        images = encoder.resize(images)
    if encoder.do_crop:
        images = encoder.center_crop(images)
    keypoints = encoder.pool(encoder.backbone(images))  # (B, K, 2)
    return keypoints.norm(dim=-1).mean(dim=-1).numpy()


def measure(policy, batch, seed: int) -> dict[str, np.ndarray]:
    cfg = policy.config
    out = {}
    with torch.no_grad():
        contexts = policy.model.backbone(batch)
    last = contexts[-1]  # (B, tokens, D): camera token(s), then the state token p, then the task token
    backbone = policy.model.backbone
    n_cam = last.shape[1] - (backbone.state_proj is not None) - (backbone.task_embed is not None)
    out["camera_token"] = last[:, :n_cam].mean(dim=1).numpy()
    out["state_token"] = (
        last[:, n_cam].numpy() if backbone.state_proj is not None else np.zeros((len(last), 1))
    )
    out["pooled_context"] = policy.context_features(batch).numpy()
    if cfg.resnet.camera_tokens == "keypoints":
        out["keypoint_radius"] = keypoint_spread(policy, batch)
    expert = batch["action"]
    out["expert_energy"] = policy.score_action_chunks(batch, expert[:, None])[:, 0].numpy()
    generator = torch.Generator().manual_seed(seed)
    chunk, readout = policy.predict_action_chunk(batch, generator=generator, return_energy=True)
    out["initial_energy"] = readout.initial_energy.float().numpy()
    out["final_energy"] = readout.final_energy.float().numpy()
    out["refined_l1"] = (chunk.float() - expert.float()).abs().mean(dim=(1, 2)).numpy()
    g = torch.Generator().manual_seed(seed + 1)
    n_dir = 16
    for radius in RADII:
        noise = torch.randn((chunk.shape[0], n_dir, *chunk.shape[1:]), generator=g)
        energies = policy.score_action_chunks(batch, chunk[:, None] + radius * noise)
        out[f"rise_{radius}"] = (energies.mean(dim=1) - readout.final_energy).float().numpy()
    prior = cfg.init_action_std * torch.randn((chunk.shape[0], n_dir, *chunk.shape[1:]), generator=g)
    out["prior_energy"] = policy.score_action_chunks(batch, prior).mean(dim=1).float().numpy()
    return out


def bootstrap_ci(values: np.ndarray, n: int = 1000, seed: int = 0) -> tuple[float, float]:
    rng = np.random.default_rng(seed)
    means = [values[rng.integers(0, len(values), len(values))].mean() for _ in range(n)]
    return float(np.percentile(means, 2.5)), float(np.percentile(means, 97.5))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", required=True)
    parser.add_argument("--data_root", required=True, help="folder holding one dataset folder per condition")
    parser.add_argument(
        "--conditions", nargs="+", required=True, help="dataset folder names; the first is vanilla"
    )
    parser.add_argument("--repo_prefix", default="local/diag_")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--output", required=True)
    args = parser.parse_args()

    torch.manual_seed(args.seed)
    policy = EBVLAPolicy.from_pretrained(args.checkpoint).eval()
    preprocessor, _ = make_pre_post_processors(policy.config, pretrained_path=args.checkpoint)
    results, vanilla = {}, None
    for condition in args.conditions:
        batch, episodes, frames = load_frames(
            policy, preprocessor, Path(args.data_root) / condition, args.repo_prefix + condition
        )
        values = measure(policy, batch, args.seed)
        if vanilla is None:
            vanilla = {
                key: values[key].mean(axis=0) for key in ("camera_token", "state_token", "pooled_context")
            }
        for key in ("camera_token", "state_token", "pooled_context"):
            values[f"{key}_norm"] = np.linalg.norm(values[key], axis=-1)
            values[f"{key}_to_vanilla_mean"] = np.linalg.norm(values[key] - vanilla[key], axis=-1)
        row = {k: v.tolist() for k, v in values.items() if v.ndim == 1}
        row["episode_index"], row["frame_index"] = episodes.tolist(), frames.tolist()
        results[condition] = row
    Path(args.output).write_text(json.dumps({"checkpoint": args.checkpoint, "conditions": results}))

    columns = [
        "final_energy",
        "expert_energy",
        "initial_energy",
        "prior_energy",
        "rise_0.3",
        "refined_l1",
        "camera_token_to_vanilla_mean",
        "state_token_to_vanilla_mean",
        "camera_token_norm",
        "keypoint_radius",
    ]
    print("| condition | n | " + " | ".join(columns) + " |")
    print("|---" * (len(columns) + 2) + "|")
    base = results[args.conditions[0]]
    base_index = {
        key: i for i, key in enumerate(zip(base["episode_index"], base["frame_index"], strict=True))
    }
    for condition, row in results.items():
        cells = []
        for column in columns:
            if column not in row:
                cells.append("-")
                continue
            v = np.asarray(row[column])
            lo, hi = bootstrap_ci(v)
            cells.append(f"{v.mean():.2f} [{lo:.2f}, {hi:.2f}]")
        print(f"| {condition} | {len(row['final_energy'])} | " + " | ".join(cells) + " |")
        # Paired with vanilla: the same seed and frame (image perturbations leave the expert's states alone).
        pairs = [
            (i, base_index[key])
            for i, key in enumerate(zip(row["episode_index"], row["frame_index"], strict=True))
            if key in base_index
        ]
        if condition != args.conditions[0] and pairs:
            idx, vidx = map(np.asarray, zip(*pairs, strict=True))
            deltas = []
            for column in ("final_energy", "expert_energy", "initial_energy", "prior_energy", "rise_0.3"):
                d = np.asarray(row[column])[idx] - np.asarray(base[column])[vidx]
                lo, hi = bootstrap_ci(d)
                deltas.append(f"{column} {d.mean():+.2f} [{lo:+.2f}, {hi:+.2f}]")
            print(f"|   paired minus vanilla ({len(pairs)} frames): " + "; ".join(deltas) + " |")


if __name__ == "__main__":
    main()
