"""Renders the first frame of a MetaWorld task under every `--env.type=metaworld_ebvla` perturbation.

One row per perturbation, one column per severity (severity 0, the vanilla frame, first), saved as one PNG
grid. Each cell is titled with the mean absolute pixel difference to the vanilla frame (0-255 scale), and for
`robot_init` with the distance the hand moved.

    MUJOCO_GL=egl python research/benchmarks/metaworld_perturbation_gallery.py \\
        --task push-v3 --severities 1 3 5 --output docs/figures/metaworld_perturbations.png

`--training_corruptions` adds a row per image corruption the energy's outlier-exposure margin trains on
(`training_signal.CORRUPTIONS`), applied to the vanilla frame at strength s = severity / 5 (as
`energy_ood_corruption_strength` blends them): what the energy was shown, beside what it is evaluated on.
"""

import argparse
import os
import time
from pathlib import Path

import numpy as np


def first_frame(task: str, perturbation: str, severity: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(pixels, agent_pos) of the first observation of an episode, as a policy would see them."""
    from lerobot_policy_ebvla.envs import MetaworldEBVLAEnv
    from lerobot_policy_ebvla.envs.metaworld import MetaworldEBVLAGymEnv

    cfg = MetaworldEBVLAEnv(
        task=task, fast_render=True, perturbation=perturbation, perturbation_severity=severity
    )
    env = MetaworldEBVLAGymEnv(task=task, **cfg.gym_kwargs)
    try:
        observation, _ = env.reset(seed=seed)
    finally:
        env.close()
    return observation["pixels"], observation["agent_pos"]


def corrupted_frames(frame: np.ndarray, kind: str, strengths: list[float], seed: int) -> list[np.ndarray]:
    """`frame` under the training corruption `kind`, blended in at each strength (one draw for all)."""
    import torch

    from lerobot_policy_ebvla.training_signal import blend, corrupt_observation

    images = torch.from_numpy(frame).permute(2, 0, 1)[None].float() / 255.0
    generator = torch.Generator().manual_seed(seed)
    corrupted = corrupt_observation({"image": images}, ["image"], (kind,), generator)["image"]
    blends = [blend(images, corrupted, torch.tensor([s])) for s in strengths]
    return [(255.0 * b[0].permute(1, 2, 0)).round().to(torch.uint8).numpy() for b in blends]


def main() -> None:
    from lerobot_policy_ebvla.envs.perturbations import MAX_SEVERITY, PERTURBATIONS
    from lerobot_policy_ebvla.training_signal import CORRUPTIONS

    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--task", default="push-v3")
    parser.add_argument("--severities", type=int, nargs="+", default=[1, 3, 5])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--output", type=Path, default=Path("docs/figures/metaworld_perturbations.png"))
    parser.add_argument(
        "--training_corruptions",
        action="store_true",
        help="Also a row per image corruption of the energy's outlier-exposure margin, at strength severity / 5.",
    )
    args = parser.parse_args()
    os.environ.setdefault("MUJOCO_GL", "egl")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    start = time.perf_counter()
    vanilla, vanilla_pos = first_frame(args.task, "none", 0, args.seed)
    perturbations = [p for p in PERTURBATIONS if p != "none"]
    corruptions = [c for c in CORRUPTIONS if c != "state_noise"] if args.training_corruptions else []
    columns = [0, *args.severities]
    # (row name, [(frame, hand position, level)] per column): the sweep's perturbations, then the training
    # corruptions blended in at strength severity / 5.
    grid = []
    for perturbation in perturbations:
        frames = [
            (vanilla, vanilla_pos)
            if severity == 0
            else first_frame(args.task, perturbation, severity, args.seed)
            for severity in columns
        ]
        grid.append((perturbation, [(f, p, f"s={s}") for (f, p), s in zip(frames, columns, strict=True)]))
    for kind in corruptions:
        strengths = [severity / MAX_SEVERITY for severity in columns]
        frames = corrupted_frames(vanilla, kind, strengths, args.seed)
        cells = [(f, vanilla_pos, f"strength {s:.1f}") for f, s in zip(frames, strengths, strict=True)]
        grid.append((f"train:{kind}", cells))
    fig, axes = plt.subplots(len(grid), len(columns), figsize=(1.7 * len(columns), 1.9 * len(grid)))
    for row, (perturbation, cells) in enumerate(grid):
        for col, (frame, pos, level) in enumerate(cells):
            difference = np.abs(frame.astype(float) - vanilla.astype(float)).mean()
            title = f"{perturbation} {level}\n|dpix| {difference:.1f}"
            if perturbation == "robot_init":
                title += f", hand {100 * np.linalg.norm(pos[:3] - vanilla_pos[:3]):.1f} cm"
            print(title.replace("\n", "  "), flush=True)
            ax = axes[row, col]
            ax.imshow(frame)
            ax.set_title(title, fontsize=6.5)
            ax.axis("off")
    fig.suptitle(f"metaworld_ebvla perturbations, {args.task}, seed {args.seed}, fast_render", fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.985))
    args.output.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.output, dpi=90, pil_kwargs={"optimize": True})
    # A palette of 128 colours keeps the grid readable at about a third of the file size.
    from PIL import Image

    Image.open(args.output).convert("RGB").quantize(colors=128).save(args.output, optimize=True)
    print(f"Saved {args.output} ({time.perf_counter() - start:.0f} s)")


if __name__ == "__main__":
    main()
