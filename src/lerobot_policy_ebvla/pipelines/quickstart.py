"""The quickstart: record, train, evaluate and monitor EB-VLA on MetaWorld in one process, on a CPU.

The whole pipeline of the project, offline and sized for a small CPU (`run`):

1. **Record** MetaWorld's scripted expert (`record_metaworld`, fast rendering) as a LeRobotDataset. An
   existing dataset is reused.
2. **Train** `ebvla` with LeRobot's own `train` (the function behind `lerobot-train`), given a
   `TrainPipelineConfig` composed here (`train_config`): the dataset, and the light policy of
   `presets.LIGHT_POLICY`. Its loader reads each action chunk from the action column alone
   (`column_queries`), not from whole decoded rows as LeRobot 0.6.1 does.
3. **Evaluate** with `pipelines.eval_energy` (LeRobot's `eval_policy_all` under the `EnergyRecorder`),
   recording the energy of every refined chunk: vanilla rollouts of other seeds that calibrate the monitor, then
   three conditions: the vanilla scene, a blanked camera (does success depend on the camera?) and one perturbed
   scene. Then the camera check on dataset frames (`monitoring.vision.checkpoint_camera_dependence`): how much the
   refined chunk and its final energy change when the camera is replaced by a black image, with the same MCMC
   noise.
4. **Monitor**: the checkpoint's `EnergyMonitor` calibrated on the calibration rollouts alone
   (`ebvla-ood-report --calibrate_to`'s work: `ood_calibration.json` and `failure_calibration.json` beside the
   weights, the full report in `monitor/ood_report.md`), and what it says of the three conditions: does its OOD
   check flag the shifted rollouts, and does its failure check name the rollouts that fail, from their first chunks.
5. **Summarise** (`monitoring.summary`): per condition, the success rate and the mean initial and final
   energy; the monitor; the paper's raw final energy beside it; the camera check. Printed, and written to
   `summary.json`.

Everything goes under `QuickstartConfig.output_dir`: the dataset in `data/<task>/`, LeRobot's training output
in `train/`, each condition's `eval_info.json` and `energy_records.jsonl` in `eval/<condition>/`, the monitor's
report in `monitor/`, and `summary.json`.
"""

import json
import logging
import shutil
import sys
import time
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path

import draccus

from ..configuration_ebvla import EBVLAConfig
from ..envs import MetaworldEBVLAEnv
from ..monitoring.ood_report import OODReportConfig, score_ood_report, write_scored_report
from ..monitoring.records import group_by_episode, read_energy_records
from ..monitoring.summary import (
    condition_summary,
    energy_aurocs,
    final_energy_by_outcome,
    mean_or_nan,
    monitor_summary,
    pooled_episodes,
)
from ..presets import light_policy_config
from ..recording.metaworld import RecordMetaworldConfig, record_metaworld
from .column_queries import single_column_delta_queries
from .eval_energy import eval_metaworld_checkpoint, metaworld_eval_env

# Written into output_dir when a run starts: a second run there is refused without `overwrite`.
RUN_MARKER = "quickstart_run.json"
SUMMARY_FILENAME = "summary.json"
VANILLA, BLANK, CALIBRATION = "vanilla", "blank", "calibration"
# The calibration rollouts' seeds start this far after the evaluation's: no seed is in both.
CALIBRATION_SEED_OFFSET = 100_000


@dataclass
class QuickstartConfig:
    """Record MetaWorld demonstrations, train ebvla, evaluate it with energies and print a summary."""

    # MetaWorld v3 task, or comma-separated tasks. Pick one whose goal is visible in the images (not reach-v3).
    task: str = "button-press-v3"
    # Folder of the dataset, the training run, the evaluations and summary.json.
    output_dir: Path = Path("outputs/ebvla_quickstart")
    # Expert episodes recorded per task.
    record_episodes: int = 10
    # Side of the square images stored in the dataset (the policy resizes them to `policy.resnet.resize_shape`). The
    # light policy's own 64 px: LeRobot's loader decodes every stored frame of a sample's action chunk, so
    # frames stored at the size the policy sees halve the loader's time (research/docs/benchmarks_history.md, section 7).
    image_size: int = 64
    # Side of the frames MetaWorld renders, in recording and in evaluation alike (`--env.observation_size`;
    # LeRobot's env renders 480 px). Frames are resized to `image_size` when recorded; a smaller frame renders
    # about twice as fast on a CPU.
    observation_size: int = 128
    # Training steps. The policy's cosine schedule decays over them, with a warm-up of at most a tenth.
    steps: int = 1000
    # Training batch size.
    batch_size: int = 16
    # Evaluation episodes per task and condition (vanilla, blanked camera, perturbed).
    eval_episodes: int = 10
    # Vanilla episodes per task that calibrate the checkpoint's monitor, from seeds `seed` + 100000 on (never an
    # evaluated episode's).
    calibration_episodes: int = 10
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
    policy: EBVLAConfig = field(default_factory=light_policy_config)

    def __post_init__(self):
        for name in (
            "record_episodes",
            "steps",
            "batch_size",
            "eval_episodes",
            "calibration_episodes",
            "max_episode_steps",
            "vision_frames",
        ):
            if getattr(self, name) < 1:
                raise ValueError(f"`{name}` must be >= 1, got {getattr(self, name)}.")
        if self.calibration_episodes < 2:
            raise ValueError(
                f"`calibration_episodes` must be >= 2 (a threshold needs a spread), got {self.calibration_episodes}."
            )
        # The config's own rule, checked now rather than after recording and before training.
        self.policy.validate_light_backbone_image(
            *(
                self.policy.resnet.crop_shape
                or self.policy.resnet.resize_shape
                or (self.image_size, self.image_size)
            )
        )
        if self.policy.backbone != "resnet":
            raise ValueError(
                f"The quickstart trains the light backbone offline: `policy.backbone` must be 'resnet', "
                f"got {self.policy.backbone!r}."
            )
        # The env config checks the perturbation's name and severity, naming the field.
        metaworld_eval_env(
            self.task,
            self.max_episode_steps,
            self.perturbation,
            self.perturbation_severity,
            self.observation_size,
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

    datasets.disable_progress_bars()  # one "Map" bar per saved episode
    report = record_metaworld(
        RecordMetaworldConfig(
            env=MetaworldEBVLAEnv(task=cfg.task, fast_render=True, observation_size=cfg.observation_size),
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
    cfg: QuickstartConfig,
    checkpoint: Path,
    eval_dir: Path,
    perturbation: str,
    severity: int,
    calibration: bool = False,
) -> None:
    """LeRobot's rollouts of the checkpoint in one condition, energies to `eval_dir/energy_records.jsonl`; the
    calibration's from seeds of their own."""
    eval_metaworld_checkpoint(
        checkpoint,
        eval_dir,
        task=cfg.task,
        max_episode_steps=cfg.max_episode_steps,
        n_episodes=cfg.calibration_episodes if calibration else cfg.eval_episodes,
        seed=cfg.seed + CALIBRATION_SEED_OFFSET if calibration else cfg.seed,
        perturbation=perturbation,
        severity=severity,
        observation_size=cfg.observation_size,
    )


def calibrate_monitor(cfg: QuickstartConfig, checkpoint: Path, eval_root: Path, shifts: list[str]) -> dict:
    """Calibrates the checkpoint's `EnergyMonitor` on the calibration rollouts (both files beside the weights, the
    report in `output_dir/monitor`) and returns what it says of the evaluated rollouts (`monitor_summary`)."""
    scored = score_ood_report(
        OODReportConfig(
            calibration=[str(eval_root / CALIBRATION)],
            vanilla=[str(eval_root / VANILLA)],
            ood=[str(eval_root / name) for name in shifts],
            output_dir=cfg.output_dir / "monitor",
            calibrate_to=checkpoint,
            overwrite_calibration=True,
            n_bootstrap=200,
        )
    )
    write_scored_report(scored)
    summary = monitor_summary(scored)
    # The report names a condition by its perturbation and severity; the summary by the quickstart's names.
    names = {f"{p} {float(s):g}": name for name, (p, s) in cfg.conditions().items()}
    summary["unfamiliar"] = {names.get(c, c): row for c, row in summary["unfamiliar"].items()}
    return summary


def format_monitor(monitor: dict) -> list[str]:
    """The monitor's lines of the printed summary."""
    n = monitor["chunks"]
    lines = [
        f"The checkpoint's monitor, calibrated on {monitor['n_calibration']} vanilla rollouts of other seeds "
        "(ood_calibration.json, failure_calibration.json beside the weights; monitor/ood_report.md):",
        f"  unfamiliar ({monitor['score']}): AUROC against vanilla, first {n} chunks / whole episode; rollouts "
        + (
            f"alarmed by chunk {monitor['ood_chunks']} (one T bounds all {monitor['ood_chunks']} decisions)"
            if monitor["ood_chunks"]
            else "alarmed at T over whole episodes"
        ),
    ]
    for condition, row in monitor["unfamiliar"].items():
        aurocs = f"{row['auroc_first_chunks']:.2f} / {row['auroc']:.2f}" if "auroc" in row else "-"
        alarmed, total = row["alarmed"]
        lines.append(f"    {condition:<12} {aurocs:>11}   {alarmed}/{total}")
    if "failing" in monitor:
        f = monitor["failing"]
        lines.append(
            f"  failing ({f['score']}, first {n} chunks): failed vs successful over the {f['n_failed'] + f['n_successful']} "
            f"rollouts above ({f['n_failed']} failed): AUROC {f['auroc']:.2f}; alarmed at T: failed "
            f"{f['failed_alarmed']}/{f['n_failed']}, successful {f['successful_alarmed']}/{f['n_successful']}"
        )
    return lines


def format_summary(summary: dict) -> str:
    """The printed summary: every episode, then per condition, the camera check and the AUROCs."""
    conditions = summary["conditions"]
    lines = [
        f"{'condition':<14} {'task':<16} {'episode':>7} {'seed':>6} {'success':>7} {'chunks':>6} "
        f"{'E_init':>8} {'E_final':>8}"
    ]
    for name, condition in conditions.items():
        for e in condition["episodes"]:
            lines.append(
                f"{name:<14} {e['task']:<16} {e['episode']:>7} {str(e['seed']):>6} {str(e['success']):>7} "
                f"{e['chunks']:>6} {e['mean_initial_energy']:>8.3f} {e['mean_final_energy']:>8.3f}"
            )
    vanilla = conditions[VANILLA]
    lines.append(
        f"\n{'condition':<14} {'success':>12} {'E_init':>8} {'E_final':>8} {'E_final - vanilla':>18}"
    )
    for name, c in conditions.items():
        rate = f"{c['n_success']}/{c['n_episodes']} ({100 * c['success_rate']:.0f}%)"
        shift = c["mean_final_energy"] - vanilla["mean_final_energy"]
        lines.append(
            f"{name:<14} {rate:>12} {c['mean_initial_energy']:>8.3f} {c['mean_final_energy']:>8.3f} "
            f"{shift:>+18.3f}"
        )
    check = summary["camera_check"]
    succeeded, failed = final_energy_by_outcome(pooled_episodes(conditions))
    lines += [
        "(energies: mean per chunk of E(a^(0), C) and E(a^(K), C); MCMC refinement lowers it. A policy that "
        "reads its camera fails more with the camera blanked; an energy that knows rises there.)",
        f"Camera check on {check['num_frames']} dataset frames: the refined chunk changes by "
        f"{100 * check['chunk_change']:.1f}% with the camera blanked (0% = blind policy); final energy "
        f"{check['energy_real']:.3f} (real) vs {check['energy_blank']:.3f} (blanked).",
    ]
    if "monitor" in summary:
        lines += format_monitor(summary["monitor"])
    lines += [
        "Mean final energy of successful episodes (all conditions): "
        f"{mean_or_nan(succeeded):.3f}, of failed episodes: {mean_or_nan(failed):.3f} (nan: no such episode)",
        "The paper's raw final energy, AUROC of the episodes' mean (0.5 = no signal, 1 = always higher; nan: no such "
        "episode): " + ", ".join(f"{name} {value:.2f}" for name, value in summary["energy_auroc"].items()),
    ]
    return "\n".join(lines)


def quiet_in_process_noise() -> None:
    """Silences warnings that the in-process stages raise and that say nothing about the run."""
    # LeRobot falls back from torchcodec to PyAV (PNG frames need neither), and MetaWorld warns that its
    # experts' gains exceed the action space (actions are clipped).
    logging.getLogger("lerobot.utils.import_utils").setLevel(logging.ERROR)
    warnings.filterwarnings("ignore", message=r"Constant\(s\) may be too high")


def start_run(cfg: QuickstartConfig) -> None:
    """Marks `output_dir` as holding a run, after removing a previous one if `overwrite` allows.

    Raises:
        FileExistsError: `output_dir` holds a previous run and `overwrite` is off.
    """
    output_dir = cfg.output_dir
    train_dir, eval_root = output_dir / "train", output_dir / "eval"
    # LeRobot's training creates `train/` only when it first saves, so a run in progress is marked at once.
    marker = output_dir / RUN_MARKER
    if marker.exists() or train_dir.exists() or eval_root.exists():
        if not cfg.overwrite:
            raise FileExistsError(
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


def run(cfg: QuickstartConfig) -> dict:
    """Runs the four stages; returns the summary (also written to `<output_dir>/summary.json`).

    Raises:
        FileExistsError: `output_dir` holds a previous run and `cfg.overwrite` is off.
    """
    from lerobot.scripts.lerobot_train import train

    from ..monitoring.vision import checkpoint_camera_dependence

    start_run(cfg)
    output_dir = cfg.output_dir
    train_dir, eval_root = output_dir / "train", output_dir / "eval"
    dataset_name = cfg.task.replace(",", "_")
    root, repo_id = output_dir / "data" / dataset_name, f"local/metaworld_{dataset_name}"
    timings = {}

    start = time.perf_counter()
    banner(f"1/5 Recording MetaWorld expert demonstrations ({cfg.task}, {cfg.record_episodes} per task)")
    record_dataset(cfg, root, repo_id)
    timings["record_s"] = time.perf_counter() - start

    start = time.perf_counter()
    p = cfg.policy
    banner(
        f"2/5 Training ebvla for {cfg.steps} steps of batch {cfg.batch_size} ({p.resnet.vision_backbone_stages}-stage "
        f"{p.resnet.vision_backbone} at {p.resnet.resize_shape} px, energy head D={p.dim_model}, {p.n_heads} heads, "
        f"L={p.n_blocks}; state dropout {p.resnet.state_dropout}, contrastive weight {p.contrastive.weight})"
    )
    with single_column_delta_queries():
        train(train_config(cfg, root, repo_id, train_dir))
    timings["train_s"] = time.perf_counter() - start
    checkpoint = train_dir / "checkpoints" / "last" / "pretrained_model"

    start = time.perf_counter()
    conditions = cfg.conditions()
    banner(
        f"3/5 Evaluating: {cfg.calibration_episodes} vanilla episodes per task to calibrate the monitor (seeds from "
        f"{cfg.seed + CALIBRATION_SEED_OFFSET}), then {cfg.eval_episodes} per task of at most {cfg.max_episode_steps} "
        f"steps, seeds from {cfg.seed}, in each of {', '.join(conditions)}; then the camera check on "
        f"{cfg.vision_frames} frames"
    )
    say(f"--- {CALIBRATION} ---")
    evaluate(cfg, checkpoint, eval_root / CALIBRATION, "none", 0, calibration=True)
    for name, (perturbation, severity) in conditions.items():
        say(f"--- {name} ---")
        evaluate(cfg, checkpoint, eval_root / name, perturbation, severity)
    check = checkpoint_camera_dependence(checkpoint, root, repo_id, cfg.vision_frames, cfg.seed)
    timings["eval_s"] = time.perf_counter() - start

    banner("4/5 Calibrating the checkpoint's monitor on the calibration rollouts")
    start = time.perf_counter()
    monitor = calibrate_monitor(cfg, checkpoint, eval_root, [name for name in conditions if name != VANILLA])
    timings["monitor_s"] = time.perf_counter() - start

    banner("5/5 Summary")
    summaries = {
        name: condition_summary(group_by_episode(read_energy_records(eval_root / name)))
        for name in conditions
    }
    summary = {
        "conditions": summaries,
        "monitor": monitor,
        "energy_auroc": energy_aurocs(summaries, reference=VANILLA),
        "camera_check": {**asdict(check), "energy_shift": check.energy_shift},
        "timings_s": {name: round(seconds, 1) for name, seconds in timings.items()},
        "checkpoint": str(checkpoint),
    }
    say(format_summary(summary))
    say("Time: " + ", ".join(f"{name[:-2]} {seconds / 60:.1f} min" for name, seconds in timings.items()))
    with open(output_dir / SUMMARY_FILENAME, "w") as f:
        json.dump(summary, f, indent=2)
    say(f"\nCheckpoint: {checkpoint}")
    say(
        f"Energy records: {eval_root}/<condition>/energy_records.jsonl (docs/monitoring.md: the OOD and "
        "failure reports read them)"
    )
    return summary
