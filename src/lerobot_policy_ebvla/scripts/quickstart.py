"""`ebvla-quickstart`: record, train, evaluate and monitor EB-VLA on MetaWorld in one command, on a CPU.

The whole pipeline of the project, offline and sized for a small CPU:

1. **Record** MetaWorld's scripted expert on one task (`button-press-v3`, 10 episodes, by default) as a
   LeRobotDataset (`ebvla-record-metaworld`'s code, fast rendering, 128 px images). An existing dataset is
   reused.
2. **Train** `ebvla` with `lerobot-train`: the light backbone (LeRobot's Diffusion Policy ResNet-18 image
   encoder, from scratch, at 64x64) and a CPU-sized energy head (D=128, 4 heads, L=2 blocks, instead of the
   paper's D=896, L=4), 2-4 MCMC steps per training step (the paper: 8-15), 300 steps of batch 16.
3. **Evaluate** with `ebvla-eval` (LeRobot's rollout) on 5 seeded episodes of at most 100 steps, recording
   the energy of every refined action chunk.
4. **Summarise**: success rate, and the mean initial and final energy per episode, for successful and failed
   episodes.

On a 2-core CPU shared with other jobs (load 4-8) the first full run took 33 minutes: recording 1.9 min,
training 28.4 min (0.3 s per step when the CPU was free, 3-16 s when it was shared), evaluation 2.1 min; it
succeeded in 3 of 5 button-press episodes. Five episodes say little: scale up with `--train_steps`,
`--batch_size`, `--eval_episodes`, `--dim_model`, `--n_blocks`, `--resize` and, with a GPU, `--device=cuda`
(docs/benchmarks_metaworld.md: 800 steps of batch 32 on a GPU, 3 tasks, 80% on button-press-v3).

Everything goes under `--output_dir` (default `outputs/ebvla_quickstart`):

    <output_dir>/data/<task>/          the recorded dataset (reused when present)
    <output_dir>/train/                lerobot-train's output (checkpoints/last/pretrained_model)
    <output_dir>/eval/                 eval_info.json and energy_records.jsonl
    <output_dir>/train.log, eval.log   the full output of lerobot-train and ebvla-eval
    <output_dir>/summary.json          the printed summary

A previous training run is never replaced unless `--overwrite` is given (which then removes `train/` and
`eval/` only; the dataset is always kept).

Example:

    pip install -e ".[metaworld]"
    ebvla-quickstart
    ebvla-quickstart --device=cuda --train_steps=3000 --batch_size=32 --output_dir=outputs/qs_gpu
"""

import argparse
import json
import logging
import math
import os
import shutil
import subprocess
import sys
import time
import warnings
from pathlib import Path

# Spatial-softmax keypoints of the light image encoder (LeRobot's Diffusion Policy default).
KEYPOINTS = 32
# MCMC steps per training step (the paper samples K in [8, 15]); fewer is faster on a CPU.
TRAIN_MCMC_STEPS = (2, 4)
# Written into output_dir when a run starts: a second run there is refused without --overwrite.
RUN_MARKER = "quickstart_run.json"


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="ebvla-quickstart",
        description=(
            "Record MetaWorld expert demonstrations, train EB-VLA (light backbone) with lerobot-train, "
            "evaluate it with ebvla-eval and print the success rate and energy statistics. Offline, on a CPU."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("--output_dir", type=Path, default=Path("outputs/ebvla_quickstart"))
    parser.add_argument(
        "--task",
        default="button-press-v3",
        help="MetaWorld v3 task (or comma-separated tasks). Not reach-v3: its goal is invisible in the images.",
    )
    parser.add_argument("--record_episodes", type=int, default=10, help="Expert episodes recorded per task.")
    parser.add_argument("--train_steps", type=int, default=300)
    parser.add_argument("--batch_size", type=int, default=16)
    parser.add_argument("--learning_rate", type=float, default=5e-4)
    parser.add_argument(
        "--resize", type=int, default=64, help="Side the image encoder resizes frames to (> 32)."
    )
    parser.add_argument("--dim_model", type=int, default=128, help="Energy-head width D (the paper: 896).")
    parser.add_argument("--n_heads", type=int, default=4, help="Attention heads of the energy head.")
    parser.add_argument("--n_blocks", type=int, default=2, help="Energy-head blocks L (the paper: 4).")
    parser.add_argument("--eval_episodes", type=int, default=5, help="Evaluation episodes per task.")
    parser.add_argument(
        "--max_episode_steps", type=int, default=100, help="Evaluation episodes end after this many steps."
    )
    parser.add_argument(
        "--seed", type=int, default=1000, help="Seed of training and of the first eval episode."
    )
    parser.add_argument("--device", default="cpu", help="Torch device for training and evaluation.")
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="Replace a previous training run (and its evaluation) in output_dir. The dataset is kept.",
    )
    args = parser.parse_args(argv)
    for name in ("record_episodes", "train_steps", "batch_size", "eval_episodes", "max_episode_steps"):
        if getattr(args, name) < 1:
            parser.error(f"--{name} must be >= 1, got {getattr(args, name)}.")
    if args.resize <= 32:
        parser.error(f"--resize must be > 32 (the ResNet downsamples 32x), got {args.resize}.")
    return args


def say(text: str) -> None:
    """Writes a line to the console at once (the subprocesses' lines interleave with ours)."""
    sys.stdout.write(text + "\n")
    sys.stdout.flush()


def banner(text: str) -> None:
    say(f"\n=== {text} ===")


def run_logged(command: list[str], log_path: Path) -> None:
    """Runs a command with its full output in `log_path`, echoing its log lines; raises if it fails."""
    say("$ " + " ".join(command))
    with open(log_path, "w") as log:
        process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        for line in process.stdout:
            log.write(line)
            # LeRobot's INFO lines carry the progress (tqdm bars before them are cut off); warnings stay
            # in the log file.
            if "INFO " in line:
                say("    " + line[line.index("INFO ") :].rstrip())
        process.wait()
    if process.returncode != 0:
        tail = log_path.read_text().splitlines()[-40:]
        say("\n".join(tail))
        raise RuntimeError(f"Command failed with exit code {process.returncode}; see {log_path}.")


def record_dataset(args: argparse.Namespace, root: Path, repo_id: str) -> None:
    if (root / "meta" / "info.json").is_file():
        say(f"Reusing the dataset at {root}.")
        return
    if root.exists() and any(root.iterdir()):
        raise FileExistsError(
            f"{root} exists but is not a LeRobotDataset; move it away or pick another --output_dir."
        )
    import datasets

    from lerobot_policy_ebvla.envs import MetaworldEBVLAEnv
    from lerobot_policy_ebvla.scripts.record_metaworld import RecordMetaworldConfig, record_metaworld

    datasets.disable_progress_bars()  # one "Map" bar per saved episode

    cfg = RecordMetaworldConfig(
        env=MetaworldEBVLAEnv(task=args.task, fast_render=True),
        repo_id=repo_id,
        root=root,
        episodes_per_task=args.record_episodes,
        seed=0,
        image_size=128,
        overwrite=root.exists(),  # an empty folder left by an interrupted run
    )
    report = record_metaworld(cfg)
    if report["n_kept"] == 0:
        raise RuntimeError("The expert failed every episode: nothing to train on.")


def train(args: argparse.Namespace, root: Path, repo_id: str, train_dir: Path) -> None:
    command = [
        sys.executable,
        "-m",
        "lerobot.scripts.lerobot_train",
        f"--dataset.repo_id={repo_id}",
        f"--dataset.root={root}",
        "--policy.type=ebvla",
        "--policy.backbone=resnet",
        "--policy.vision_backbone=resnet18",
        "--policy.pretrained_backbone_weights=null",
        "--policy.use_group_norm=true",
        f"--policy.resize_shape=[{args.resize},{args.resize}]",
        f"--policy.spatial_softmax_num_keypoints={KEYPOINTS}",
        f"--policy.dim_model={args.dim_model}",
        f"--policy.n_heads={args.n_heads}",
        f"--policy.n_blocks={args.n_blocks}",
        f"--policy.train_mcmc_steps_range=[{TRAIN_MCMC_STEPS[0]},{TRAIN_MCMC_STEPS[1]}]",
        f"--policy.optimizer_lr={args.learning_rate}",
        f"--policy.scheduler_warmup_steps={min(100, args.train_steps // 10)}",
        f"--policy.scheduler_decay_steps={args.train_steps}",
        f"--policy.device={args.device}",
        "--policy.push_to_hub=false",
        f"--steps={args.train_steps}",
        f"--batch_size={args.batch_size}",
        f"--save_freq={args.train_steps}",
        f"--log_freq={max(1, min(100, args.train_steps // 10))}",
        f"--seed={args.seed}",
        "--num_workers=0",
        "--wandb.enable=false",
        f"--output_dir={train_dir}",
    ]
    run_logged(command, args.output_dir / "train.log")


def evaluate(args: argparse.Namespace, checkpoint: Path, eval_dir: Path) -> None:
    from lerobot_policy_ebvla.scripts.eval_energy import metaworld_eval_command  # imports LeRobot's eval

    command = metaworld_eval_command(
        checkpoint,
        eval_dir,
        task=args.task,
        device=args.device,
        max_episode_steps=args.max_episode_steps,
        n_episodes=args.eval_episodes,
        seed=args.seed,
    )
    run_logged(command, args.output_dir / "eval.log")


def summarise(eval_dir: Path) -> dict:
    """Success rate and per-episode energies from `energy_records.jsonl` (one row per refined chunk)."""
    from lerobot_policy_ebvla.monitoring import group_by_episode, read_energy_records

    episodes = []
    for key, records in sorted(group_by_episode(read_energy_records(eval_dir)).items()):
        finals = [r.final_energy for r in records]
        initials = [r.initial_energy for r in records]
        episodes.append(
            {
                "task": key.task,
                "episode": key.episode_index,
                "seed": records[0].seed,
                "success": records[0].success,
                "chunks": len(records),
                "mean_initial_energy": sum(initials) / len(initials),
                "mean_final_energy": sum(finals) / len(finals),
            }
        )

    def mean(values: list[float]) -> float:
        return sum(values) / len(values) if values else math.nan

    succeeded = [e["mean_final_energy"] for e in episodes if e["success"]]
    failed = [e["mean_final_energy"] for e in episodes if not e["success"]]
    return {
        "n_episodes": len(episodes),
        "n_success": len(succeeded),
        "success_rate": len(succeeded) / len(episodes) if episodes else math.nan,
        "mean_final_energy_success": mean(succeeded),
        "mean_final_energy_failure": mean(failed),
        "mean_initial_energy": mean([e["mean_initial_energy"] for e in episodes]),
        "mean_final_energy": mean([e["mean_final_energy"] for e in episodes]),
        "episodes": episodes,
    }


def print_summary(summary: dict) -> None:
    say(f"{'task':<16} {'episode':>7} {'seed':>6} {'success':>7} {'chunks':>6} {'E_init':>8} {'E_final':>8}")
    for e in summary["episodes"]:
        say(
            f"{e['task']:<16} {e['episode']:>7} {str(e['seed']):>6} {str(e['success']):>7} {e['chunks']:>6} "
            f"{e['mean_initial_energy']:>8.3f} {e['mean_final_energy']:>8.3f}"
        )
    say(
        f"\nSuccess rate: {summary['n_success']}/{summary['n_episodes']} "
        f"({100 * summary['success_rate']:.0f}%)"
    )
    say(
        f"Mean energy per chunk: initial E(a^(0), C) = {summary['mean_initial_energy']:.3f}, "
        f"final E(a^(K), C) = {summary['mean_final_energy']:.3f} (MCMC refinement lowers it)"
    )
    say(
        f"Mean final energy of successful episodes: {summary['mean_final_energy_success']:.3f}, "
        f"of failed episodes: {summary['mean_final_energy_failure']:.3f} (nan: no such episode)"
    )


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    # MuJoCo renders off-screen; EGL needs no display (and is inherited by the subprocesses).
    os.environ.setdefault("MUJOCO_GL", "egl")
    from lerobot.utils.utils import init_logging

    init_logging()
    # Noise of the in-process recording: LeRobot falls back from torchcodec to PyAV (PNG frames need
    # neither), and MetaWorld warns that its experts' gains exceed the action space (actions are clipped).
    logging.getLogger("lerobot.utils.import_utils").setLevel(logging.ERROR)
    warnings.filterwarnings("ignore", message=r"Constant\(s\) may be too high")
    output_dir = args.output_dir
    train_dir, eval_dir = output_dir / "train", output_dir / "eval"
    # lerobot-train creates `train/` only when it first saves, so a run in progress is marked at once.
    marker = output_dir / RUN_MARKER
    if marker.exists() or train_dir.exists() or eval_dir.exists():
        if not args.overwrite:
            sys.exit(
                f"{output_dir} already holds a quickstart run ({RUN_MARKER}, train/ or eval/): pass --overwrite "
                "to replace it (the dataset is kept), or choose another --output_dir."
            )
        shutil.rmtree(train_dir, ignore_errors=True)
        shutil.rmtree(eval_dir, ignore_errors=True)
    output_dir.mkdir(parents=True, exist_ok=True)
    marker.write_text(
        json.dumps({"started": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "args": sys.argv[1:]}) + "\n"
    )
    dataset_name = args.task.replace(",", "_")
    root, repo_id = output_dir / "data" / dataset_name, f"local/metaworld_{dataset_name}"
    timings = {}

    start = time.perf_counter()
    banner(f"1/4 Recording MetaWorld expert demonstrations ({args.task}, {args.record_episodes} per task)")
    record_dataset(args, root, repo_id)
    timings["record_s"] = time.perf_counter() - start

    start = time.perf_counter()
    banner(
        f"2/4 Training ebvla for {args.train_steps} steps of batch {args.batch_size} (ResNet-18 at {args.resize} px, "
        f"energy head D={args.dim_model}, {args.n_heads} heads, L={args.n_blocks})"
    )
    train(args, root, repo_id, train_dir)
    timings["train_s"] = time.perf_counter() - start
    checkpoint = train_dir / "checkpoints" / "last" / "pretrained_model"

    start = time.perf_counter()
    banner(
        f"3/4 Evaluating with ebvla-eval: {args.eval_episodes} episodes per task, at most "
        f"{args.max_episode_steps} steps, seeds from {args.seed}"
    )
    evaluate(args, checkpoint, eval_dir)
    timings["eval_s"] = time.perf_counter() - start

    banner("4/4 Summary")
    summary = summarise(eval_dir)
    summary["timings_s"] = {name: round(seconds, 1) for name, seconds in timings.items()}
    summary["checkpoint"] = str(checkpoint)
    print_summary(summary)
    say("Time: " + ", ".join(f"{name[:-2]} {seconds / 60:.1f} min" for name, seconds in timings.items()))
    with open(output_dir / "summary.json", "w") as f:
        json.dump(summary, f, indent=2)
    say(f"\nCheckpoint: {checkpoint}")
    say(
        f"Energy records: {eval_dir / 'energy_records.jsonl'} (see docs/monitoring.md for the OOD and failure reports)"
    )


if __name__ == "__main__":
    main()
