"""EB-VLA's energy head vs LeRobot's Diffusion Policy on MetaWorld (the analogue of the paper's Table I).

Both policies get the SAME image encoder (LeRobot's Diffusion Policy ResNet-18 encoder: group norm, no
pretrained weights, the same resize, random crop and spatial-softmax keypoints), the same recorded expert
data, the same number of training steps and batch size, and are evaluated on the same seeded episodes with
LeRobot's rollout (`eval_policy_all`, through `pipelines.eval_energy`, what `ebvla-eval` runs, for both: it
records EB-VLA's energies and renders no videos). Only the action head differs: EB-VLA's energy transformer
refined by MCMC, or Diffusion Policy's 1-D conditional U-Net denoised by DDPM.

One multi-task policy per method is trained on all tasks (the light backbone has no language input; the
images tell the tasks apart). Steps:

1. record MetaWorld's scripted experts (`ebvla-record-metaworld`'s code) unless `<output_dir>/data` exists;
2. `lerobot-train` each method (concurrently with `--jobs >= 2`);
3. evaluate each method on each task (`eval_metaworld_checkpoint`, each evaluation in a process of its own;
   `--eval_episodes` episodes from seed `--seed`), and EB-VLA under the camera perturbations of
   `--perturbations` (for the OOD and failure reports);
4. write `results.json` and `results.md` (success rate per task and method, with episode counts and seeds);
5. with `--calibration_seed`, evaluate EB-VLA's vanilla rollouts a second time on other seeds and write the
   held-out `ebvla-ood-report` (calibrated on those, reported on the `--seed` rollouts and the perturbations)
   and `ebvla-failure-report` into `ood_report/` and `failure_report/`.

Example (the run reported in research/docs/benchmarks_metaworld.md):

    MUJOCO_GL=egl OMP_NUM_THREADS=2 python research/benchmarks/compare_diffusion_metaworld.py --device=cuda --jobs=18 \\
        --steps=800 --batch_size=32 --num_workers=7 --eval_episodes=10 --max_episode_steps=120 \\
        --perturbations pose:2 pose:4 fov:2 fov:4

The energy study's five-task run (research/docs/energy_study.md, section 6) on the 2-core CPU:

    MUJOCO_GL=egl OMP_NUM_THREADS=1 python research/benchmarks/compare_diffusion_metaworld.py --output_dir=/tmp/mt/run \
        --tasks=button-press-v3,drawer-open-v3,drawer-close-v3,window-open-v3,door-open-v3 --record_episodes=30 \
        --image_size=64 --steps=4000 --batch_size=16 --num_workers=1 --ebvla_dim=128 \
        --ebvla_args="--policy.n_heads=4 --policy.n_blocks=2 --policy.train_mcmc_steps_range=[2,4] \
            --policy.optimizer_lr=5e-4 --policy.resnet.vision_backbone_stages=2 --policy.resnet.state_dropout=0.5 \
            --policy.contrastive.weight=0.1" \
        --ebvla_eval_args="--normalized_energy_samples=16 --restart_spread_chains=4 --record_context_features=true" \
        --diffusion_down_dims 128 256 512 --eval_episodes=10 --max_episode_steps=150 --seed=1000 \
        --calibration_seed=2000 --perturbations blank:1 pose:5 noise:5 --jobs=2

On a 2-core CPU (`--device=cpu --jobs=2`) the 800-step, 128 px run takes hours: an EB-VLA training step there takes
seconds, and each of the 18 evaluations several minutes.
"""

import argparse
import json
import multiprocessing
import os
import shlex
import shutil
import subprocess
import sys
import time
import traceback
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from pathlib import Path
from typing import Any

from lerobot_policy_ebvla.pipelines.eval_energy import eval_metaworld_checkpoint

# The image encoder both methods share (field names are the same in DiffusionConfig and EBVLAConfig's `resnet`).
ENCODER = {
    "vision_backbone": "resnet18",
    "pretrained_backbone_weights": "null",
    "use_group_norm": "true",
    "spatial_softmax_num_keypoints": "32",
    "crop_is_random": "true",
    "use_separate_rgb_encoder_per_camera": "false",
}
# Diffusion derives its crop from resize_shape * crop_ratio; EB-VLA takes the crop shape itself.
CROP_RATIO = 0.9


def method_args(method: str, args: argparse.Namespace) -> list[str]:
    group = "resnet." if method == "ebvla" else ""
    encoder = [f"--policy.{group}{name}={value}" for name, value in ENCODER.items()]
    encoder.append(f"--policy.{group}resize_shape=[{args.image_size},{args.image_size}]")
    if method == "ebvla":
        crop = int(args.image_size * CROP_RATIO)
        return [
            "--policy.type=ebvla",
            "--policy.backbone=resnet",
            *encoder,
            f"--policy.resnet.crop_shape=[{crop},{crop}]",
            f"--policy.dim_model={args.ebvla_dim}",
            "--policy.n_heads=8",
            "--policy.n_blocks=4",
            "--policy.chunk_size=8",
            "--policy.n_action_steps=8",
            f"--policy.scheduler_warmup_steps={min(500, args.steps // 10)}",
            f"--policy.scheduler_decay_steps={args.steps}",
            *args.ebvla_args,
        ]
    if method == "diffusion":
        return [
            "--policy.type=diffusion",
            *encoder,
            f"--policy.crop_ratio={CROP_RATIO}",
            f"--policy.down_dims=[{','.join(str(d) for d in args.diffusion_down_dims)}]",
            # The same observation and chunk as EB-VLA: one observation step, an 8-step chunk, all executed.
            # Diffusion keeps its own min-max normalization: its sample clipping assumes actions in [-1, 1].
            "--policy.n_obs_steps=1",
            "--policy.horizon=8",
            "--policy.n_action_steps=8",
            "--policy.drop_n_last_frames=0",
            f"--policy.scheduler_warmup_steps={min(500, args.steps // 10)}",
        ]
    raise ValueError(f"Unknown method {method!r}.")


def run(command: list[str], log: Path) -> float:
    """Runs a command with its output in `log`; returns its wall time; raises on failure."""
    start = time.perf_counter()
    with open(log, "w") as f:
        f.write("$ " + " ".join(command) + "\n")
        f.flush()
        result = subprocess.run(command, stdout=f, stderr=subprocess.STDOUT, check=False)
    seconds = time.perf_counter() - start
    if result.returncode != 0:
        raise RuntimeError(f"{command[:4]} failed ({result.returncode}) after {seconds:.0f} s; see {log}.")
    print(f"[{seconds:6.0f} s] done: {log}", flush=True)
    return seconds


def record(args: argparse.Namespace, root: Path) -> None:
    if (root / "meta" / "info.json").is_file():
        print(f"Reusing the dataset at {root}.")
        return
    command = [
        sys.executable,
        "-m",
        "lerobot_policy_ebvla.scripts.record_metaworld",
        f"--env.task={args.tasks}",
        "--env.fast_render=true",
        f"--episodes_per_task={args.record_episodes}",
        "--seed=0",
        f"--image_size={args.image_size}",
        "--repo_id=local/metaworld_bench",
        f"--root={root}",
        f"--overwrite={str(root.exists()).lower()}",
    ]
    run(command, args.output_dir / "record.log")


def train(method: str, args: argparse.Namespace, root: Path) -> float:
    command = [
        sys.executable,
        "-m",
        "lerobot.scripts.lerobot_train",
        "--dataset.repo_id=local/metaworld_bench",
        f"--dataset.root={root}",
        *method_args(method, args),
        f"--policy.device={args.device}",
        "--policy.push_to_hub=false",
        f"--steps={args.steps}",
        f"--batch_size={args.batch_size}",
        f"--save_freq={args.save_freq or args.steps}",
        f"--log_freq={max(1, args.steps // 20)}",
        f"--num_workers={args.num_workers}",
        "--seed=0",
        "--wandb.enable=false",
        f"--output_dir={args.output_dir / 'train' / method}",
    ]
    return run(command, args.output_dir / f"train_{method}.log")


def run_in_process(function: Callable[..., Any], log: Path, *args: Any, **kwargs: Any) -> float:
    """Runs `function(*args, **kwargs)` in a fresh process, as a command would run, with its output in `log`.

    Returns its wall time; raises on failure. A process of its own keeps each evaluation's global state
    (seeds, torch threads, MuJoCo) apart from the others that `--jobs` runs at the same time.
    """
    start = time.perf_counter()
    with ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn")) as process:
        try:
            process.submit(_logged, function, log, *args, **kwargs).result()
        except Exception as error:
            seconds = time.perf_counter() - start
            raise RuntimeError(f"{function.__name__} failed after {seconds:.0f} s; see {log}.") from error
    seconds = time.perf_counter() - start
    print(f"[{seconds:6.0f} s] done: {log}", flush=True)
    return seconds


def _logged(function: Callable[..., Any], log: Path, *args: Any, **kwargs: Any) -> None:
    """In the child process: stdout and stderr (LeRobot's logging included) go to `log`."""
    with open(log, "w") as f:
        os.dup2(f.fileno(), sys.stdout.fileno())
        os.dup2(f.fileno(), sys.stderr.fileno())
    from lerobot.utils.utils import init_logging

    init_logging()
    try:
        function(*args, **kwargs)
    except Exception:
        traceback.print_exc()
        raise


def eval_options(flags: list[str]) -> dict[str, Any]:
    """`--ebvla_eval_args` (`--name=value` flags) as `EnergyEvalPipelineConfig` fields; values are read as
    JSON where they are (`16`, `true`), as strings otherwise."""
    options = {}
    for flag in flags:
        name, _, value = flag.removeprefix("--").partition("=")
        try:
            options[name] = json.loads(value)
        except json.JSONDecodeError:
            options[name] = value
    return options


def evaluate(
    method: str,
    task: str,
    args: argparse.Namespace,
    perturbation: str = "none",
    severity: int = 0,
    calibration: bool = False,
) -> float:
    """One evaluation, in a process of its own.

    `calibration` runs vanilla from `--calibration_seed` (the OOD reports' mu_v, sigma_v).
    """
    if calibration:
        name = "calibration"
    elif perturbation == "none":
        name = "vanilla"
    else:
        name = f"{perturbation}{severity}"
    checkpoint = args.output_dir / "train" / method / "checkpoints" / "last" / "pretrained_model"
    return run_in_process(
        eval_metaworld_checkpoint,
        args.output_dir / "logs" / f"eval_{method}_{name}_{task}.log",
        checkpoint,
        args.output_dir / "eval" / method / name / task,
        task=task,
        device=args.device,
        max_episode_steps=args.max_episode_steps,
        n_episodes=args.eval_episodes,
        seed=args.calibration_seed if calibration else args.seed,
        perturbation=perturbation,
        severity=severity,
        **(eval_options(args.ebvla_eval_args) if method == "ebvla" else {}),
    )


def successes(eval_dir: Path) -> list[bool]:
    with open(eval_dir / "eval_info.json") as f:
        info = json.load(f)
    flags = []
    for task in info["per_task"]:
        flags += [bool(s) for s in task["metrics"]["successes"]]
    return flags


def write_results(args: argparse.Namespace, tasks: list[str], methods: list[str], timings: dict) -> dict:
    results = {"tasks": {}, "settings": {k: str(v) for k, v in vars(args).items()}, "timings_s": timings}
    for task in tasks:
        results["tasks"][task] = {}
        for method in methods:
            flags = successes(args.output_dir / "eval" / method / "vanilla" / task)
            results["tasks"][task][method] = {"n_success": sum(flags), "n_episodes": len(flags)}
    lines = [
        f"| Task | {' | '.join(methods)} |",
        "|---|" + "---|" * len(methods),
    ]
    totals = {m: [0, 0] for m in methods}
    for task in tasks:
        cells = []
        for method in methods:
            r = results["tasks"][task][method]
            totals[method][0] += r["n_success"]
            totals[method][1] += r["n_episodes"]
            cells.append(
                f"{100 * r['n_success'] / r['n_episodes']:.0f}% ({r['n_success']}/{r['n_episodes']})"
            )
        lines.append(f"| {task} | {' | '.join(cells)} |")
    cells = [f"{100 * s / n:.0f}% ({s}/{n})" for s, n in totals.values()]
    lines.append(f"| **all** | {' | '.join(cells)} |")
    table = "\n".join(lines)
    results["table_md"] = table
    with open(args.output_dir / "results.json", "w") as f:
        json.dump(results, f, indent=2)
    (args.output_dir / "results.md").write_text(
        f"Success rate, episodes {args.seed}..{args.seed + args.eval_episodes - 1} (seeds) per task, at most "
        f"{args.max_episode_steps} steps each; {args.steps} training steps, batch {args.batch_size}.\n\n"
        + table
        + "\n"
    )
    print(table)
    return results


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description="Train LeRobot's diffusion policy and ebvla with the same image encoder, data and "
        "budget on MetaWorld tasks, evaluate both on the same seeds (Table I analogue).",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("--output_dir", type=Path, default=Path("outputs/bench_metaworld"))
    parser.add_argument("--tasks", default="reach-v3,button-press-v3,push-v3")
    parser.add_argument("--methods", default="ebvla,diffusion")
    parser.add_argument(
        "--record_episodes", type=int, default=15, help="Expert episodes per task (seeds 0..)."
    )
    parser.add_argument("--steps", type=int, default=800, help="Training steps, the same for every method.")
    parser.add_argument("--batch_size", type=int, default=32)
    parser.add_argument("--num_workers", type=int, default=4, help="Data-loader workers per training.")
    parser.add_argument("--ebvla_dim", type=int, default=256, help="EB-VLA head width D (8 heads, L=4).")
    parser.add_argument("--diffusion_down_dims", type=int, nargs="+", default=[256, 512, 1024])
    parser.add_argument("--eval_episodes", type=int, default=10, help="Evaluation episodes per task.")
    parser.add_argument("--max_episode_steps", type=int, default=120)
    parser.add_argument("--seed", type=int, default=1000, help="Seed of the first evaluation episode.")
    parser.add_argument(
        "--perturbations",
        nargs="*",
        default=[],
        metavar="NAME:SEVERITY",
        help="Extra ebvla evaluations under camera perturbations, e.g. pose:2 fov:4.",
    )
    parser.add_argument("--image_size", type=int, default=128, help="Recorded and resized image side (px).")
    parser.add_argument(
        "--ebvla_args",
        type=shlex.split,
        default=[],
        help="Extra ebvla training options, one string: '--policy.resnet.vision_backbone_stages=2 --policy.resnet.state_dropout=0.5'.",
    )
    parser.add_argument(
        "--ebvla_eval_args",
        type=shlex.split,
        default=[],
        help="Extra evaluation options for every ebvla evaluation (`EnergyEvalPipelineConfig` fields, as "
        "ebvla-eval takes them), e.g. '--normalized_energy_samples=16'.",
    )
    parser.add_argument(
        "--calibration_seed",
        type=int,
        default=None,
        help="Also evaluate ebvla vanilla from this seed (other episodes than --seed's) and write the held-out "
        "ebvla-ood-report (with --perturbations) and ebvla-failure-report.",
    )
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--jobs", type=int, default=1, help="Processes run at once (trainings, then evals).")
    parser.add_argument(
        "--save_freq",
        type=int,
        default=None,
        help="Checkpoint every this many steps (default: only at the end); `--skip_train` evaluates the last one.",
    )
    parser.add_argument("--skip_train", action="store_true", help="Evaluate the existing checkpoints.")
    parser.add_argument("--overwrite", action="store_true", help="Replace previous training runs.")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    os.environ.setdefault("MUJOCO_GL", "egl")
    tasks, methods = args.tasks.split(","), args.methods.split(",")
    perturbations = [(p.split(":")[0], int(p.split(":")[1])) for p in args.perturbations]
    args.output_dir.mkdir(parents=True, exist_ok=True)
    (args.output_dir / "logs").mkdir(exist_ok=True)
    root = args.output_dir / "data" / "metaworld_bench"
    timings = {}

    start = time.perf_counter()
    record(args, root)
    timings["record"] = time.perf_counter() - start

    if not args.skip_train:
        for method in methods:
            train_dir = args.output_dir / "train" / method
            if train_dir.exists():
                if not args.overwrite:
                    sys.exit(f"{train_dir} exists: pass --overwrite to retrain, or --skip_train.")
                shutil.rmtree(train_dir)
        with ThreadPoolExecutor(max_workers=max(1, min(args.jobs, len(methods)))) as pool:
            walls = list(pool.map(lambda m: train(m, args, root), methods))
        timings.update({f"train_{m}": w for m, w in zip(methods, walls, strict=True)})

    jobs = [{"method": m, "task": t} for m in methods for t in tasks]
    if "ebvla" in methods:
        if args.calibration_seed is not None:
            jobs += [{"method": "ebvla", "task": t, "calibration": True} for t in tasks]
        jobs += [
            {"method": "ebvla", "task": t, "perturbation": p, "severity": s}
            for p, s in perturbations
            for t in tasks
        ]
    start = time.perf_counter()
    with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        walls = list(pool.map(lambda job: evaluate(args=args, **job), jobs))
    timings["eval_all"] = time.perf_counter() - start
    timings["eval_process_sum"] = sum(walls)
    write_results(args, tasks, methods, {k: round(v, 1) for k, v in timings.items()})
    if "ebvla" in methods and args.calibration_seed is not None:
        held_out_reports(args, perturbations)


def held_out_reports(args: argparse.Namespace, perturbations: list[tuple[str, int]]) -> None:
    """Table III (with --perturbations) and Table IV of ebvla, calibrated on other episodes than reported."""
    evals = args.output_dir / "eval" / "ebvla"
    calibration, vanilla = f"{evals}/calibration/*", f"{evals}/vanilla/*"
    scripts = "lerobot_policy_ebvla.scripts"
    if perturbations:
        ood = ",".join(f"{evals}/{p}{s}/*" for p, s in perturbations)
        run(
            [
                sys.executable,
                "-m",
                f"{scripts}.ood_report",
                f"--calibration=[{calibration}]",
                f"--vanilla=[{vanilla}]",
                f"--ood=[{ood}]",
                f"--output_dir={args.output_dir / 'ood_report'}",
            ],
            args.output_dir / "logs" / "ood_report.log",
        )
    run(
        [
            sys.executable,
            "-m",
            f"{scripts}.failure_report",
            f"--calibration=[{calibration}]",
            f"--records=[{vanilla}]",
            f"--output_dir={args.output_dir / 'failure_report'}",
        ],
        args.output_dir / "logs" / "failure_report.log",
    )


if __name__ == "__main__":
    main()
