"""`ebvla-quickstart`: record, train, evaluate and monitor EB-VLA on MetaWorld in one command, on a CPU.

The whole pipeline of the project, offline and sized for a small CPU, in one process:

1. **Record** MetaWorld's scripted expert (`ebvla-record-metaworld`'s `record_metaworld`, fast rendering) as
   a LeRobotDataset. An existing dataset is reused.
2. **Train** `ebvla` with LeRobot's own `train` (the function behind `lerobot-train`), given a
   `TrainPipelineConfig` composed here: the dataset, and the light `EBVLAConfig` of `LIGHT_POLICY` (LeRobot's
   Diffusion Policy ResNet-18 image encoder from scratch and a CPU-sized energy head).
3. **Evaluate** with `ebvla-eval`'s in-process evaluation (LeRobot's `eval_policy_all` under the
   `EnergyRecorder`), recording the energy of every refined chunk, in three conditions: the vanilla scene,
   a blanked camera (`--env.perturbation=blank`: does success depend on the camera?) and one perturbed scene
   (`--perturbation`, `--perturbation_severity`). Then the camera check on dataset frames
   (`monitoring.vision.camera_dependence`): how much the refined chunk and its final energy change when the
   camera is replaced by a black image, with the same MCMC noise.
4. **Summarise**: per condition, the success rate and the mean initial and final energy; the camera check;
   the final energy of successful and failed episodes. Written to `summary.json` as well.

Everything goes under `--output_dir` (default `outputs/ebvla_quickstart`):

    <output_dir>/data/<task>/          the recorded dataset (reused when present)
    <output_dir>/train/                LeRobot's training output (checkpoints/last/pretrained_model)
    <output_dir>/eval/<condition>/     eval_info.json and energy_records.jsonl of each condition
    <output_dir>/summary.json          the printed summary

A previous training run is never replaced unless `--overwrite=true` is given (which then removes `train/` and
`eval/` only; the dataset is always kept).

Example:

    pip install -e ".[metaworld]"
    ebvla-quickstart
    ebvla-quickstart --task=push-v3 --steps=3000 --batch_size=32 --policy.device=cuda --output_dir=outputs/qs_gpu
    ebvla-quickstart --policy.dim_model=256 --policy.n_blocks=4 --perturbation=light_dim --perturbation_severity=5

Every `--policy.*` field of `EBVLAConfig` can be set; the quickstart's own values (`LIGHT_POLICY`) are the
defaults of the ones it changes.
"""

import json
import logging
import math
import os
import shutil
import sys
import time
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path

import draccus

from lerobot_policy_ebvla.configuration_ebvla import EBVLAConfig
from lerobot_policy_ebvla.envs.configs import MetaworldEBVLAEnv
from lerobot_policy_ebvla.scripts.record_metaworld import RecordMetaworldConfig

# The quickstart's policy, where it differs from `EBVLAConfig`'s defaults (the paper's full VLA): LeRobot's
# Diffusion Policy ResNet-18 encoder, from scratch, at 64x64, and a CPU-sized energy head (D=128, 4 heads,
# L=2 blocks instead of D=896, L=4) trained with 2-4 MCMC steps (the paper: 8-15). This is the one place its
# sizes and training recipe live; every field can be overridden with `--policy.<field>=...`.
LIGHT_POLICY = {
    "backbone": "resnet",
    "resize_shape": (64, 64),
    # A 2-stage ResNet keeps an 8x8 keypoint map at 64 px (4 stages leave 2x2) and trains 4x faster.
    "vision_backbone_stages": 2,
    # With the paper's training signal alone the light policy learns from the 4-d state and ignores its camera
    # (docs/energy_study.md, section 1b). Hiding the state from half the samples and keeping each expert chunk
    # below the batch's other chunks (weight 0.1) is what made it read the camera and its energy react.
    "state_dropout": 0.5,
    "energy_contrastive_weight": 0.1,
    "dim_model": 128,
    "n_heads": 4,
    "n_blocks": 2,
    "train_mcmc_steps_range": (2, 4),
    "optimizer_lr": 5e-4,
    "push_to_hub": False,
}
# Written into output_dir when a run starts: a second run there is refused without --overwrite.
RUN_MARKER = "quickstart_run.json"
SUMMARY_FILENAME = "summary.json"
VANILLA, BLANK = "vanilla", "blank"


def light_policy() -> EBVLAConfig:
    return EBVLAConfig(**LIGHT_POLICY)


@dataclass
class QuickstartConfig:
    """Record MetaWorld demonstrations, train ebvla, evaluate it with energies and print a summary."""

    # MetaWorld v3 task, or comma-separated tasks. Pick one whose goal is visible in the images (not reach-v3).
    task: str = "button-press-v3"
    # Folder of the dataset, the training run, the evaluations and summary.json.
    output_dir: Path = Path("outputs/ebvla_quickstart")
    # Expert episodes recorded per task.
    record_episodes: int = 10
    # Side of the square images stored in the dataset (the policy resizes them to `policy.resize_shape`).
    image_size: int = RecordMetaworldConfig.image_size
    # Training steps. The policy's cosine schedule decays over them, with a warm-up of at most a tenth.
    steps: int = 1500
    # Training batch size.
    batch_size: int = 16
    # Evaluation episodes per task and condition (vanilla, blanked camera, perturbed).
    eval_episodes: int = 10
    # Evaluation episodes end after this many env steps (MetaWorld's own limit is 500).
    max_episode_steps: int = 100
    # The perturbed evaluation condition: one of `--env.type=metaworld_ebvla`'s perturbations (docs/metaworld.md),
    # or "none" to skip it.
    perturbation: str = "pose"
    # Its severity, 1 to 5.
    perturbation_severity: int = 3
    # Dataset frames of the camera check (real vs blanked camera, same MCMC noise).
    vision_frames: int = 16
    # Seed of training, of the first evaluation episode and of the camera check's MCMC noise.
    seed: int = 1000
    # Replace a previous training run (and its evaluations) in output_dir. The dataset is kept.
    overwrite: bool = False
    # The policy: `LIGHT_POLICY` over `EBVLAConfig`'s defaults; any `--policy.<field>=...` overrides it.
    policy: EBVLAConfig = field(default_factory=light_policy)

    def __post_init__(self):
        for name in (
            "record_episodes",
            "steps",
            "batch_size",
            "eval_episodes",
            "max_episode_steps",
            "vision_frames",
        ):
            if getattr(self, name) < 1:
                raise ValueError(f"`{name}` must be >= 1, got {getattr(self, name)}.")
        resize = self.policy.resize_shape or (self.image_size, self.image_size)
        stride = 2 ** (self.policy.vision_backbone_stages + 1)
        if min(resize) <= stride:
            raise ValueError(
                f"The images the ResNet sees must be larger than {stride} px (it downsamples {stride}x with "
                f"`policy.vision_backbone_stages={self.policy.vision_backbone_stages}`): got "
                f"`policy.resize_shape`={self.policy.resize_shape}, `image_size`={self.image_size}."
            )
        if self.policy.backbone != "resnet":
            raise ValueError(
                f"The quickstart trains the light backbone offline: `policy.backbone` must be 'resnet', "
                f"got {self.policy.backbone!r}."
            )
        # The env config checks the perturbation's name and severity, naming the field.
        self.perturbed_env(self.perturbation, self.perturbation_severity)

    def perturbed_env(self, perturbation: str, severity: int) -> MetaworldEBVLAEnv:
        """The evaluation env of one condition."""
        return MetaworldEBVLAEnv(
            task=self.task,
            fast_render=True,
            max_episode_steps=self.max_episode_steps,
            perturbation=perturbation,
            perturbation_severity=severity if perturbation != "none" else 0,
        )

    def conditions(self) -> dict[str, tuple[str, int]]:
        """{condition name: (perturbation, severity)} of the evaluations, vanilla first."""
        conditions = {VANILLA: ("none", 0), BLANK: ("blank", 1)}
        if self.perturbation not in ("none", "blank"):
            conditions[f"{self.perturbation}_s{self.perturbation_severity}"] = (
                self.perturbation,
                self.perturbation_severity,
            )
        return conditions


def parse_config(args: list[str]) -> QuickstartConfig:
    """Parses the command line into a `QuickstartConfig`; an invalid value raises a ValueError naming it.

    draccus builds a nested config from its class defaults plus the flags given, ignoring the field's
    `default_factory` once any `--policy.*` flag is given; `LIGHT_POLICY` therefore goes first on the
    command line, where the user's own flags override it.
    """
    defaults = [f"--policy.{name}={json.dumps(value)}" for name, value in LIGHT_POLICY.items()]
    if "--help" in args or "-h" in args:
        # argparse type-checks flags when printing help; `LIGHT_POLICY` is not needed for that.
        defaults = []
    try:
        return draccus.parse(QuickstartConfig, args=defaults + list(args), prog="ebvla-quickstart")
    except draccus.utils.ParsingError as error:
        # draccus wraps the config's own ValueError (which names the field) in a generic message.
        if isinstance(error.__cause__, ValueError):
            raise error.__cause__ from None
        raise


def say(text: str) -> None:
    """Writes a line to the console at once, between LeRobot's log lines."""
    sys.stdout.write(text + "\n")
    sys.stdout.flush()


def banner(text: str) -> None:
    say(f"\n=== {text} ===")


def record_dataset(cfg: QuickstartConfig, root: Path, repo_id: str) -> None:
    """Records the expert dataset unless `root` already holds one."""
    if (root / "meta" / "info.json").is_file():
        say(f"Reusing the dataset at {root}.")
        return
    if root.exists() and any(root.iterdir()):
        raise FileExistsError(
            f"{root} exists but is not a LeRobotDataset; move it away or pick another --output_dir."
        )
    import datasets

    from lerobot_policy_ebvla.scripts.record_metaworld import record_metaworld

    datasets.disable_progress_bars()  # one "Map" bar per saved episode
    report = record_metaworld(
        RecordMetaworldConfig(
            env=MetaworldEBVLAEnv(task=cfg.task, fast_render=True),
            repo_id=repo_id,
            root=root,
            episodes_per_task=cfg.record_episodes,
            image_size=cfg.image_size,
            overwrite=root.exists(),  # an empty folder left by an interrupted run
        )
    )
    if report["n_kept"] == 0:
        raise RuntimeError("The expert failed every episode: nothing to train on.")


def train_config(cfg: QuickstartConfig, root: Path, repo_id: str, train_dir: Path):
    """LeRobot's `TrainPipelineConfig` of the quickstart: the dataset and the policy, nothing else changed."""
    from lerobot.configs.default import DatasetConfig, WandBConfig
    from lerobot.configs.train import TrainPipelineConfig

    policy = cfg.policy
    policy.scheduler_decay_steps = cfg.steps
    policy.scheduler_warmup_steps = min(policy.scheduler_warmup_steps, cfg.steps // 10)
    return TrainPipelineConfig(
        dataset=DatasetConfig(repo_id=repo_id, root=str(root)),
        policy=policy,
        output_dir=train_dir,
        seed=cfg.seed,
        steps=cfg.steps,
        batch_size=cfg.batch_size,
        save_freq=cfg.steps,
        log_freq=max(1, min(100, cfg.steps // 10)),
        # Frames are decoded in the training process: worker processes cost more than they save on 2 cores.
        num_workers=0,
        wandb=WandBConfig(enable=False),
    )


def evaluate(
    cfg: QuickstartConfig, checkpoint: Path, eval_dir: Path, perturbation: str, severity: int
) -> None:
    """`ebvla-eval` in process: LeRobot's rollouts of the checkpoint, energies to `energy_records.jsonl`."""
    from lerobot.configs.default import EvalConfig
    from lerobot.configs.policies import PreTrainedConfig

    from lerobot_policy_ebvla.scripts.eval_energy import EnergyEvalPipelineConfig, eval_energy_main

    policy = PreTrainedConfig.from_pretrained(checkpoint)
    policy.pretrained_path = checkpoint
    # EvalPipelineConfig looks for `--policy.path` on the command line and warns when it finds none; the
    # policy is given here instead.
    eval_logger = logging.getLogger("lerobot.configs.eval")
    level = eval_logger.level
    eval_logger.setLevel(logging.ERROR)
    try:
        eval_cfg = EnergyEvalPipelineConfig(
            env=cfg.perturbed_env(perturbation, severity),
            eval=EvalConfig(n_episodes=cfg.eval_episodes, batch_size=1, use_async_envs=False),
            policy=policy,
            output_dir=eval_dir,
            seed=cfg.seed,
        )
    finally:
        eval_logger.setLevel(level)
    eval_energy_main(eval_cfg)


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
    succeeded = [e["mean_final_energy"] for e in episodes if e["success"]]
    failed = [e["mean_final_energy"] for e in episodes if not e["success"]]
    return {
        "n_episodes": len(episodes),
        "n_success": len(succeeded),
        "success_rate": len(succeeded) / len(episodes) if episodes else math.nan,
        "mean_final_energy_success": _mean(succeeded),
        "mean_final_energy_failure": _mean(failed),
        "mean_initial_energy": _mean([e["mean_initial_energy"] for e in episodes]),
        "mean_final_energy": _mean([e["mean_final_energy"] for e in episodes]),
        "episodes": episodes,
    }


def _mean(values: list[float]) -> float:
    return sum(values) / len(values) if values else math.nan


def energy_aurocs(conditions: dict[str, dict]) -> dict[str, float]:
    """AUROC of the episodes' mean final energy: each perturbed condition against vanilla, failed against successful.

    Threshold-free, so nothing is fitted on the episodes it is reported on; with 10 episodes a side its 95%
    interval is wide (about +-0.2), so it says whether the energy reacts, not how well it detects.
    """
    from lerobot_policy_ebvla.monitoring.metrics import auroc

    def finals(episodes: list[dict]) -> list[float]:
        return [e["mean_final_energy"] for e in episodes]

    vanilla = finals(conditions[VANILLA]["episodes"])
    aurocs = {
        name: auroc(vanilla, finals(c["episodes"])) for name, c in conditions.items() if name != VANILLA
    }
    episodes = [e for c in conditions.values() for e in c["episodes"]]
    aurocs["failed_vs_successful"] = auroc(
        finals([e for e in episodes if e["success"]]), finals([e for e in episodes if not e["success"]])
    )
    return aurocs


def print_summary(summary: dict) -> None:
    conditions = summary["conditions"]
    say(
        f"{'condition':<14} {'task':<16} {'episode':>7} {'seed':>6} {'success':>7} {'chunks':>6} "
        f"{'E_init':>8} {'E_final':>8}"
    )
    for name, condition in conditions.items():
        for e in condition["episodes"]:
            say(
                f"{name:<14} {e['task']:<16} {e['episode']:>7} {str(e['seed']):>6} {str(e['success']):>7} "
                f"{e['chunks']:>6} {e['mean_initial_energy']:>8.3f} {e['mean_final_energy']:>8.3f}"
            )
    vanilla = conditions[VANILLA]
    say(f"\n{'condition':<14} {'success':>12} {'E_init':>8} {'E_final':>8} {'E_final - vanilla':>18}")
    for name, c in conditions.items():
        rate = f"{c['n_success']}/{c['n_episodes']} ({100 * c['success_rate']:.0f}%)"
        shift = c["mean_final_energy"] - vanilla["mean_final_energy"]
        say(
            f"{name:<14} {rate:>12} {c['mean_initial_energy']:>8.3f} {c['mean_final_energy']:>8.3f} "
            f"{shift:>+18.3f}"
        )
    say(
        "(energies: mean per chunk of E(a^(0), C) and E(a^(K), C); MCMC refinement lowers it. A policy that "
        "reads its camera fails more with the camera blanked; an energy that knows rises there.)"
    )
    check = summary["camera_check"]
    say(
        f"Camera check on {check['num_frames']} dataset frames: the refined chunk changes by "
        f"{100 * check['chunk_change']:.1f}% with the camera blanked (0% = blind policy); final energy "
        f"{check['energy_real']:.3f} (real) vs {check['energy_blank']:.3f} (blanked)."
    )
    episodes = [e for c in conditions.values() for e in c["episodes"]]
    say(
        "Mean final energy of successful episodes (all conditions): "
        f"{_mean([e['mean_final_energy'] for e in episodes if e['success']]):.3f}, of failed episodes: "
        f"{_mean([e['mean_final_energy'] for e in episodes if not e['success']]):.3f} (nan: no such episode)"
    )
    say(
        "AUROC of the episodes' final energy (0.5 = no signal, 1 = always higher; nan: no such episode): "
        + ", ".join(f"{name} {value:.2f}" for name, value in summary["energy_auroc"].items())
    )


def _quiet_in_process_noise() -> None:
    # LeRobot falls back from torchcodec to PyAV (PNG frames need neither), and MetaWorld warns that its
    # experts' gains exceed the action space (actions are clipped).
    logging.getLogger("lerobot.utils.import_utils").setLevel(logging.ERROR)
    warnings.filterwarnings("ignore", message=r"Constant\(s\) may be too high")


def run(cfg: QuickstartConfig) -> dict:
    """Runs the four stages; returns the summary (also written to `<output_dir>/summary.json`)."""
    from lerobot.scripts.lerobot_train import train

    output_dir = cfg.output_dir
    train_dir, eval_root = output_dir / "train", output_dir / "eval"
    # LeRobot's training creates `train/` only when it first saves, so a run in progress is marked at once.
    marker = output_dir / RUN_MARKER
    if marker.exists() or train_dir.exists() or eval_root.exists():
        if not cfg.overwrite:
            sys.exit(
                f"{output_dir} already holds a quickstart run ({RUN_MARKER}, train/ or eval/): pass "
                "--overwrite=true to replace it (the dataset is kept), or choose another --output_dir."
            )
        shutil.rmtree(train_dir, ignore_errors=True)
        shutil.rmtree(eval_root, ignore_errors=True)
    output_dir.mkdir(parents=True, exist_ok=True)
    marker.write_text(
        json.dumps(
            {"started": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "config": draccus.encode(cfg)}, default=str
        )
        + "\n"
    )
    dataset_name = cfg.task.replace(",", "_")
    root, repo_id = output_dir / "data" / dataset_name, f"local/metaworld_{dataset_name}"
    timings = {}

    start = time.perf_counter()
    banner(f"1/4 Recording MetaWorld expert demonstrations ({cfg.task}, {cfg.record_episodes} per task)")
    record_dataset(cfg, root, repo_id)
    timings["record_s"] = time.perf_counter() - start

    start = time.perf_counter()
    p = cfg.policy
    banner(
        f"2/4 Training ebvla for {cfg.steps} steps of batch {cfg.batch_size} ({p.vision_backbone_stages}-stage "
        f"{p.vision_backbone} at {p.resize_shape} px, energy head D={p.dim_model}, {p.n_heads} heads, "
        f"L={p.n_blocks}; state dropout {p.state_dropout}, contrastive weight {p.energy_contrastive_weight})"
    )
    train(train_config(cfg, root, repo_id, train_dir))
    timings["train_s"] = time.perf_counter() - start
    checkpoint = train_dir / "checkpoints" / "last" / "pretrained_model"

    start = time.perf_counter()
    conditions = cfg.conditions()
    banner(
        f"3/4 Evaluating: {cfg.eval_episodes} episodes per task of at most {cfg.max_episode_steps} steps, seeds "
        f"from {cfg.seed}, in each of {', '.join(conditions)}; then the camera check on {cfg.vision_frames} frames"
    )
    for name, (perturbation, severity) in conditions.items():
        say(f"--- {name} ---")
        evaluate(cfg, checkpoint, eval_root / name, perturbation, severity)
    from lerobot_policy_ebvla.monitoring.vision import checkpoint_camera_dependence

    check = checkpoint_camera_dependence(checkpoint, root, repo_id, cfg.vision_frames, cfg.seed)
    timings["eval_s"] = time.perf_counter() - start

    banner("4/4 Summary")
    summaries = {name: summarise(eval_root / name) for name in conditions}
    summary = {
        "conditions": summaries,
        "energy_auroc": energy_aurocs(summaries),
        "camera_check": {**asdict(check), "energy_shift": check.energy_shift},
        "timings_s": {name: round(seconds, 1) for name, seconds in timings.items()},
        "checkpoint": str(checkpoint),
    }
    print_summary(summary)
    say("Time: " + ", ".join(f"{name[:-2]} {seconds / 60:.1f} min" for name, seconds in timings.items()))
    with open(output_dir / SUMMARY_FILENAME, "w") as f:
        json.dump(summary, f, indent=2)
    say(f"\nCheckpoint: {checkpoint}")
    say(
        f"Energy records: {eval_root}/<condition>/energy_records.jsonl (docs/monitoring.md: the OOD and "
        "failure reports read them)"
    )
    return summary


def main(args: list[str] | None = None) -> None:
    # MuJoCo renders off-screen; EGL needs no display.
    os.environ.setdefault("MUJOCO_GL", "egl")
    from lerobot.utils.utils import init_logging

    init_logging()
    _quiet_in_process_noise()
    run(parse_config(sys.argv[1:] if args is None else args))


if __name__ == "__main__":
    main()
