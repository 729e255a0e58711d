"""Success rate and energy of one checkpoint under every MetaWorld perturbation at graded severities.

One evaluation folder per condition (`pipelines.eval_energy`, what `ebvla-eval` runs; MetaWorld's
perturbations: docs/metaworld.md), then one held-out `ebvla-ood-report` over all of them. The vanilla
rollouts of two seed ranges are evaluated too: the first (`--calibration_seed`) calibrates, the second
(`--seed`) is the report's negatives. A condition whose folder already holds its records is not evaluated
again, so an interrupted sweep resumes. `--record_context_features` also records each chunk's pooled backbone
context, so that the report adds the context scores (`context_distance`, `context_knn`) beside the energies.

    MUJOCO_GL=egl python research/benchmarks/metaworld_perturbation_sweep.py --checkpoint=<pretrained_model folder> \\
        --output_dir=outputs/metaworld_sweep --tasks=button-press-v3 --episodes=5
"""

import argparse
import sys
from pathlib import Path

from compare_diffusion_metaworld import run, run_in_process

from lerobot_policy_ebvla.envs.perturbations import PERTURBATIONS
from lerobot_policy_ebvla.pipelines.eval_energy import eval_metaworld_checkpoint

# pose_fov is pose and fov at once: each of the two is swept on its own.
SWEPT = [p for p in PERTURBATIONS if p not in ("none", "pose_fov")]


def evaluate(
    args: argparse.Namespace,
    folder: str,
    seed: int,
    perturbation: str = "none",
    severity: int = 0,
    episodes: int | None = None,
):
    out = args.output_dir / folder
    if (out / "energy_records.jsonl").is_file():
        return
    run_in_process(
        eval_metaworld_checkpoint,
        args.output_dir / f"{folder}.log",
        args.checkpoint,
        out,
        task=args.tasks,
        device=args.device,
        max_episode_steps=args.max_episode_steps,
        n_episodes=episodes or args.episodes,
        seed=seed,
        perturbation=perturbation,
        severity=severity,
        record_context_features=args.record_context_features,
        observation_size=args.observation_size,
    )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--checkpoint", type=Path, required=True, help="A pretrained_model folder.")
    parser.add_argument("--output_dir", type=Path, default=Path("outputs/metaworld_sweep"))
    parser.add_argument("--tasks", default="button-press-v3", help="One task or a comma-separated list.")
    parser.add_argument("--episodes", type=int, default=5, help="Episodes per condition.")
    parser.add_argument(
        "--calibration_episodes",
        type=int,
        default=None,
        help="Vanilla calibration episodes (default: --episodes). With few, one astray rollout sets the threshold.",
    )
    parser.add_argument(
        "--vanilla_episodes",
        type=int,
        default=None,
        help="Held-out vanilla episodes (default: --episodes): more of them firm up the vanilla success rate "
        "and the AUROCs' negatives.",
    )
    parser.add_argument("--max_episode_steps", type=int, default=150)
    parser.add_argument("--severities", type=int, nargs="+", default=[3, 5])
    parser.add_argument("--perturbations", nargs="+", default=SWEPT, choices=SWEPT)
    parser.add_argument("--seed", type=int, default=1000, help="First seed of the reported episodes.")
    parser.add_argument("--calibration_seed", type=int, default=2000, help="First seed of the calibration.")
    parser.add_argument("--device", default="cpu")
    parser.add_argument(
        "--observation_size",
        type=int,
        default=None,
        help="Side of the rendered frames: that of the checkpoint's data (the quickstart's: 128); default 480.",
    )
    parser.add_argument(
        "--record_context_features",
        action="store_true",
        help="Also record each chunk's pooled backbone context (`ebvla-eval --record_context_features=true`): "
        "the OOD report then adds the context scores (context_distance, context_knn). Off by default.",
    )
    args = parser.parse_args()

    args.output_dir.mkdir(parents=True, exist_ok=True)
    evaluate(args, "calibration", args.calibration_seed, episodes=args.calibration_episodes)
    evaluate(args, "vanilla", args.seed, episodes=args.vanilla_episodes)
    conditions = {f"{p}_s{s}": (p, s) for p in args.perturbations for s in args.severities}
    for folder, (perturbation, severity) in conditions.items():
        evaluate(args, folder, args.seed, perturbation, severity)
    ood = ",".join(str(args.output_dir / folder) for folder in sorted(conditions))
    run(
        [
            sys.executable,
            "-m",
            "lerobot_policy_ebvla.scripts.ood_report",
            f"--calibration=[{args.output_dir / 'calibration'}]",
            f"--vanilla=[{args.output_dir / 'vanilla'}]",
            f"--ood=[{ood}]",
            f"--output_dir={args.output_dir / 'ood_report'}",
        ],
        args.output_dir / "ood_report.log",
    )


if __name__ == "__main__":
    main()
