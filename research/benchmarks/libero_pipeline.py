"""LIBERO-Object at scale (issue 21) in resumable stages, each of which fits one short GPU slice.

The paper's LIBERO experiment with a light `ebvla`: scripted demonstrations of all ten LIBERO-Object tasks,
`ebvla-train` (lerobot-train reading each action chunk from its column alone: the demonstrations' frames are
stored as images) of the paper's recipe (Table V's K_train 8-15, K_inf 15), of the contrastive variant and of
LeRobot's Diffusion Policy on the same data, evaluation in LeRobot's LIBERO env with energy records (vanilla
calibration and held-out rollouts, LIBERO-Plus camera perturbations), then Table III and Table IV from the
records. Every stage skips what its folder already holds, so a stage cut short by the end of a GPU slice is
run again in the next one and resumes; `pack` gathers what must come back (records, logs, the light
checkpoints) into one archive.

    W=outputs/libero_pipeline
    python research/benchmarks/libero_pipeline.py record --work=$W --jobs=10          # ~20 attempts per task
    python research/benchmarks/libero_pipeline.py train --work=$W --device=cuda --detach
    python research/benchmarks/libero_pipeline.py eval --work=$W --device=cuda --jobs=14 --deadline_s=480
    python research/benchmarks/libero_pipeline.py pack --work=$W --archive=$OUT/libero_results.tar.gz
    python research/benchmarks/libero_pipeline.py report --work=$W                    # Table III and IV, on any CPU

Frames are recorded and evaluated at 128 px (`--image_size`): the light policies resize to 128 anyway, and a
128 px PNG decodes about four times faster than HuggingFaceVLA/libero's 256, which is what bounds the
loader. LeRobot's LIBERO env starts episode i of a task at initial state i (`--env.first_init_state` shifts
it), so calibration and held-out rollouts are initial states [0, V/2) and [V/2, V), and the perturbed
rollouts start from the calibration's states: only the camera differs.
"""

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tarfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

REPO_ID = "local/libero_object_expert"
SUITE = "libero_object"

# The light `ebvla` for LIBERO-Object: both cameras resized to 128 px, keypoints of a 3-stage ResNet-18 from
# scratch, one learned token per task instruction (the ten tasks share one scene and differ only by the object
# the instruction names, which the light backbone cannot read), a D=256, 8-head, L=2 energy head. Everything
# else is `EBVLAConfig`'s default: Table V's MCMC (K_train 8-15, alpha in [0.05, 0.4], K_inf 15, alpha 0.22).
EBVLA_LIGHT = [
    "--policy.type=ebvla",
    "--policy.backbone=resnet",
    "--policy.resnet.resize_shape=[128,128]",
    "--policy.resnet.vision_backbone_stages=3",
    "--policy.resnet.task_instructions=[]",
    "--policy.dim_model=256",
    "--policy.n_heads=8",
    "--policy.n_blocks=2",
    "--policy.optimizer_lr=3e-4",
    "--policy.push_to_hub=false",
]
RUNS = {
    # The paper's training signal (Eq. 4 alone) at Table V's K_train 8-15.
    "ebvla_paper": EBVLA_LIGHT,
    # The variant the MetaWorld study favours for detection: the contrastive term and state dropout.
    "ebvla_variant": [*EBVLA_LIGHT, "--policy.contrastive.weight=0.1", "--policy.resnet.state_dropout=0.5"],
    # LeRobot's Diffusion Policy at its defaults, both cameras, random crops of 90% of the frame (`run_args`),
    # its ResNet-18 from scratch as ebvla's (ImageNet weights cannot be downloaded offline). It has no language
    # input: on LIBERO-Object it cannot know which object the instruction names.
    "diffusion": [
        "--policy.type=diffusion",
        "--policy.pretrained_backbone_weights=null",
        "--policy.push_to_hub=false",
    ],
}

# The two-core protocol (research/docs/libero_runs.md, "On two cores"). `ebvla_cpu` is the quickstart's light policy
# (presets.LIGHT_POLICY: D=128, 4 heads, L=2, a 2D FFN, a 2-stage ResNet-18 from scratch, the contrastive term
# and state dropout, which made it read its camera on MetaWorld) with both cameras at 96 px, one token per task
# instruction and Table V's K_train 8-15, without the preset's joint energy on its own encoder (added to the preset
# after these runs, 2026-11-26); `diffusion_cpu` is LeRobot's Diffusion Policy with the CPU-sized
# U-Net of the MetaWorld comparison (down_dims 128/256/512), the same 96 px cameras and 8-step chunks.
EBVLA_CPU = [
    "--policy.type=ebvla",
    "--policy.backbone=resnet",
    "--policy.resnet.resize_shape=[96,96]",
    "--policy.resnet.vision_backbone_stages=2",
    "--policy.resnet.task_instructions=[]",
    "--policy.dim_model=128",
    "--policy.n_heads=4",
    "--policy.n_blocks=2",
    "--policy.ffn_multiplier=2",
    "--policy.resnet.state_dropout=0.5",
    "--policy.contrastive.weight=0.2",
    "--policy.contrastive.dtype=auto",
    "--policy.optimizer_lr=5e-4",
    "--policy.push_to_hub=false",
]
RUNS["ebvla_cpu"] = EBVLA_CPU
# The LIBERO recipe candidates of issue 52 (research/docs/libero_recipe_rule.md: the rule that picks one, written
# before any was trained). A: the MetaWorld fix as the light preset ships it, E_c on its own encoder, the margin on
# generic corruptions, E_c flat at the data. B: A with the two corruptions the preset leaves out (random
# convolutions, shading), LIBERO's failures under lighting being what the preset's list does not cover.
JOINT_ENERGY_CPU = [
    "--policy.joint_energy.target=observation",
    "--policy.joint_energy.weight=0.01",
    "--policy.joint_energy.gradient_penalty=0.1",
    "--policy.monitor.score=context_phase_energy",
]
RUNS["ebvla_joint_cpu"] = [
    *EBVLA_CPU,
    *JOINT_ENERGY_CPU,
    "--policy.joint_energy.corruptions=[channel_gain,patch_swap,shift,state_noise]",
]
RUNS["ebvla_joint_all_cpu"] = [
    *EBVLA_CPU,
    *JOINT_ENERGY_CPU,
    "--policy.joint_energy.corruptions=[channel_gain,patch_swap,shift,state_noise,random_conv,shading]",
]
# C (added 2026-11-27 evening, before any candidate had a result: A had run 59 of its 10,000 steps): A with E_c's
# own encoder at 48 px instead of the policy's 96 and its gradient penalty on one step in 4 at 4 times the weight
# (`joint_energy.encoder_resize_shape`, `joint_energy.gradient_penalty_every`). A's step takes 2.9 s on a 2-core CPU
# without AVX512 (10,000 steps: 8 hours), about 60 % of it E_c's encoder; C is the candidate two cores can afford.
RUNS["ebvla_joint_fast_cpu"] = [
    *RUNS["ebvla_joint_cpu"],
    "--policy.joint_energy.encoder_resize_shape=[48,48]",
    "--policy.joint_energy.gradient_penalty_every=4",
]
# K (2026-12-01, research/docs/libero_runs.md, "K: C's recipe from scratch with the raised starting energy"): C's
# flags with the head's energy readout started at 18 (`energy_bias_init`, the light preset's since 2026-12-01: on
# MetaWorld's main job its chunk's L1 at step 400 was what the readout at 0 reached at step 1000 or never), trained
# from scratch on F's 668 demonstrations.
RUNS["ebvla_joint_fast_cpu_b18"] = [*RUNS["ebvla_joint_fast_cpu"], "--policy.energy_bias_init=18"]


# Runs that start from another run's saved weights, on their own work folder's dataset: a new AdamW (the finished
# run's optimizer state is not kept) and a new cosine schedule, which LeRobot scales to the run's steps.
@dataclass(frozen=True)
class FineTune:
    start: str  # the weights' `pretrained_model` folder, relative to the repository root
    flags: tuple[str, ...] = ()


REPOSITORY = Path(__file__).resolve().parents[2]
# Peak rate 1e-4, a fifth of C's, so that the tasks a fine-tune does not add to keep what they learned.
FINE_TUNE_RATE = ("--policy.optimizer_lr=1e-4",)
FINE_TUNES = {
    # D (2026-11-29, after the ten-task check): C's ten-task checkpoint (step 20,000) trained on with 44 more
    # demonstrations each of tasks 1 and 5, the two whose grasps miss (cream cheese 8/20 and tomato sauce 9/20 on the
    # fixed initial states, 6/10 and 3/10 on fresh placements; the object is never carried).
    "ebvla_joint_fast_cpu_more": FineTune(
        "research/results/libero_object10/train/ebvla_joint_fast_cpu/last/pretrained_model", FINE_TUNE_RATE
    ),
    # E (2026-11-29, night): D trained on with 10 demonstrations per task whose arm starts as the fixed states' arms
    # do (`record --arm_episodes`), beside D's 528: D succeeds on 98 % of fresh placements but 85 % of the fixed
    # states 30-49, whose only measured difference is the arm's start (research/docs/libero_placement_gap.md).
    "ebvla_joint_fast_cpu_arm": FineTune(
        "research/results/libero_object10_more/train/ebvla_joint_fast_cpu_more/last/pretrained_model",
        FINE_TUNE_RATE,
    ),
    # F (2026-11-30): E trained on with 20 more arm-start demonstrations each of tasks 1 and 5 (`record
    # --more_arm_episodes`), the small-object grasps that E still misses on the fixed states (15/20 and 10/20 on
    # states 30-49; the other eight tasks 149/160).
    "ebvla_joint_fast_cpu_arm_more": FineTune(
        "research/results/libero_object10_arm/train/ebvla_joint_fast_cpu_arm/last/pretrained_model",
        FINE_TUNE_RATE,
    ),
    # G (2026-11-30, late morning): F trained on 2000 more steps on F's own 668 demonstrations, nothing added: D's, E's
    # and F's demonstrations each moved the fixed states by at most 7 of 200, and C's L1 was still falling slowly.
    "ebvla_joint_fast_cpu_arm_more_longer": FineTune(
        "research/results/libero_object10_arm_more/train/ebvla_joint_fast_cpu_arm_more/last/pretrained_model",
        FINE_TUNE_RATE,
    ),
    # H (2026-11-30, afternoon): G's weights at the demonstrations' own 128 px frames instead of 96, 2000 steps on F's
    # 668 demonstrations: G's L1 is flat, and the misses are small-object grasps. The keypoints' grid is rebuilt for
    # the larger map (`backbone_resnet.keep_own_keypoint_grid`); every learned weight starts as G's.
    "ebvla_joint_fast_cpu_arm_more_128px": FineTune(
        "research/results/libero_object10_arm_more/train/ebvla_joint_fast_cpu_arm_more_longer/last/pretrained_model",
        (*FINE_TUNE_RATE, "--policy.resnet.resize_shape=[128,128]"),
    ),
    # I (2026-11-30, evening): G trained on 1500 steps with F's 668 demonstrations and recovery demonstrations of tasks
    # 1 and 5 (`record --recovery_episodes`): G's failed rollouts never move their object (a missed grasp, then the
    # empty hand carried on), and no demonstration shows a grasp tried again.
    "ebvla_joint_fast_cpu_recover": FineTune(
        "research/results/libero_object10_arm_more/train/ebvla_joint_fast_cpu_arm_more_longer/last/pretrained_model",
        FINE_TUNE_RATE,
    ),
    # J (2026-11-30, night): I with its recovery demonstrations stored from the rise after the miss on (`record
    # --recovery_from_rise`): I learned the stored misses. Only the data differs from I's fine-tune.
    "ebvla_joint_fast_cpu_recover_rise": FineTune(
        "research/results/libero_object10_arm_more/train/ebvla_joint_fast_cpu_arm_more_longer/last/pretrained_model",
        FINE_TUNE_RATE,
    ),
}
for _name in FINE_TUNES:  # each start descends from C: the flags it was trained with
    RUNS[_name] = RUNS["ebvla_joint_fast_cpu"]


# A trained run's checkpoint evaluated with other inference settings, under a name of its own (its records apart;
# it is never trained). Added 2026-11-30 (research/docs/libero_runs.md, "Best of 8 by energy on the fixed states").
@dataclass(frozen=True)
class InferenceVariant:
    base: str  # the run whose last checkpoint it evaluates, on the same work folder
    flags: tuple[str, ...] = ()  # `ebvla-eval` options added to the base's
    # Actions executed per chunk, when not the checkpoint's: the env then renders the frames this count reads.
    n_action_steps: int | None = None


INFERENCE_VARIANTS = {
    # D with best of 8 by energy: 8 chains refined per chunk from independent a^(0), the lowest final energy kept
    # (on MetaWorld, +14 / -1 episodes against one chain: BENCHMARKS.md, "Best-of-N by energy in closed loop").
    "ebvla_joint_fast_cpu_more_best8": InferenceVariant(
        "ebvla_joint_fast_cpu_more", ("--policy.num_restarts=8",)
    ),
    # F executing 4 of each 8-step chunk before refining the next from a new frame: twice the decisions, each from
    # a frame 4 steps old at most (research/docs/libero_runs.md, "F re-planning every 4 steps").
    "ebvla_joint_fast_cpu_arm_more_act4": InferenceVariant("ebvla_joint_fast_cpu_arm_more", n_action_steps=4),
}
for _name, _variant in INFERENCE_VARIANTS.items():
    RUNS[_name] = RUNS[_variant.base]
RUNS["diffusion_cpu"] = [
    "--policy.type=diffusion",
    "--policy.pretrained_backbone_weights=null",
    "--policy.resize_shape=[96,96]",
    "--policy.crop_ratio=0.9",
    "--policy.down_dims=[128,256,512]",
    "--policy.n_obs_steps=1",
    "--policy.horizon=8",
    "--policy.n_action_steps=8",
    "--policy.drop_n_last_frames=0",
    "--policy.push_to_hub=false",
]

# The baseline of issue 52 item 5, with the settings LeRobot's Diffusion Policy uses for such manipulation tasks:
# two observation steps, a 16-step horizon executing 8 (so the last 16 - 8 - 2 + 1 = 7 frames of an episode start
# no sample), the full U-Net, 10 DDIM steps at evaluation, both cameras at 96 px cropped to 90 %. It is trained until
# its held-out action error stops falling (a GPU job: hours on two cores), never judged on a fixed step budget.
RUNS["diffusion_fair"] = [
    "--policy.type=diffusion",
    "--policy.pretrained_backbone_weights=null",
    "--policy.resize_shape=[96,96]",
    "--policy.crop_ratio=0.9",
    "--policy.n_obs_steps=2",
    "--policy.horizon=16",
    "--policy.n_action_steps=8",
    "--policy.drop_n_last_frames=7",
    "--policy.noise_scheduler_type=DDIM",
    "--policy.num_inference_steps=10",
    "--policy.push_to_hub=false",
]

# Camera perturbations of LIBERO-Plus (Table III's), most informative first: severities 5 and 3 of both.
CAMERA_CONDITIONS = (("pose", 5), ("fov", 5), ("pose", 3), ("fov", 3), ("pose", 1), ("fov", 1))


def bin_path(name: str) -> str:
    """A console script of this Python's environment (the venv's `lerobot-train`, not another one on PATH),
    else the one on PATH (packages installed with `pip install --target` put theirs in `<target>/bin`)."""
    sibling = Path(sys.executable).with_name(name)
    return str(sibling) if sibling.exists() else (shutil.which(name) or name)


def child_env() -> dict[str, str]:
    # One thread per child: the stages run many children side by side on the machine's cores.
    return {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"), "OMP_NUM_THREADS": "1"}


def run_logged(cmd: list[str], log: Path, timeout_s: float | None = None) -> int:
    """Runs `cmd` in its own process group with its output in `log`; kills the whole group at the timeout.

    Returns the exit status, or -1 when the timeout killed it.
    """
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "w") as out:
        process = subprocess.Popen(
            cmd, stdout=out, stderr=subprocess.STDOUT, env=child_env(), start_new_session=True
        )
        try:
            return process.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
            return -1


# Record ------------------------------------------------------------------------------------------------------


# Demonstrations whose arm starts as the fixed states' arms do (`record --arm_episodes`): placements of their own
# seeds (ARM_PLACEMENT_SEED + attempt), no other piece's and no evaluation's (FRESH_PLACEMENT_SEED = 200000).
ARM_PLACEMENT_SEED = 300000


# Recovery demonstrations (`record --recovery_episodes`, added 2026-11-30 evening): the arm starts the fixed states'
# way, on placements of their own seeds, and the expert's first grasp aims `RECOVERY_MISS` beside the object, so that
# it closes on nothing, rises, reopens and grasps again (`RecordLiberoConfig.miss_first_grasp`).
RECOVERY_PLACEMENT_SEED = 310000
RECOVERY_MISS = 0.05
# A piece's kind: plain, the arm's start (`arm`), or recovery: I's, its miss stored (`recover`), or J's, stored from
# the rise after the miss on (`recoverrise`, `record --recovery_from_rise`; added 2026-11-30, night).
PLAIN, ARM, RECOVER, RECOVER_RISE = "", "arm", "recover", "recoverrise"


def piece_name(task: int, first: int, kind: str = PLAIN) -> str:
    """The folder of a recorder process's piece under `<work>/data`."""
    return f"task{task}_{kind}_from{first}" if kind else f"task{task}_from{first}"


def piece_report(work: Path, task: int, first: int, kind: str = PLAIN) -> Path:
    """The recorder's report of a piece (task, first initial state): it exists once the piece is recorded."""
    return work / "data" / piece_name(task, first, kind) / "meta" / "recording_report.json"


def record(
    work: Path,
    tasks: list[int],
    episodes_per_task: int,
    image_size: int,
    jobs: int,
    parts: int = 1,
    max_steps: int | None = None,
    keep_failed: bool = False,
    placement_seed: int | None = None,
    use_videos: bool = False,
    more_episodes: dict[int, int] | None = None,
    pieces_from: list[Path] | None = None,
    arm_episodes: int = 0,
    more_arm_episodes: dict[int, int] | None = None,
    recovery_episodes: dict[int, int] | None = None,
    recovery_from_rise: bool = False,
) -> Path:
    """Records each task in `parts` processes (each from its own initial states), then aggregates every part
    into `<work>/data/all`.

    `more_episodes` adds demonstrations to some tasks (task -> count), in more pieces of the same size after the
    `episodes_per_task` ones: with `placement_seed`, from placements no other piece used. `arm_episodes` adds that
    many to every task, in one piece of its own (`task<t>_arm_from0`), the arm's start drawn as the
    fixed states' (`--env.robot_init_noise`, FIXED_STATES_ARM_NOISE) on placements of ARM_PLACEMENT_SEED + attempt;
    `more_arm_episodes` adds such attempts to some tasks (task -> count), in more pieces of `arm_episodes` each.
    `recovery_episodes` (task -> count) adds one piece per task of recovery demonstrations (`RECOVERY_MISS`), the arm
    started as the fixed states', on placements of RECOVERY_PLACEMENT_SEED + attempt: with `recovery_from_rise`, their
    frames stored from the rise after the miss on (`RecordLiberoConfig.store_missed_grasp` off), else every frame.
    Pieces saved results folders already hold (`pieces_from`, their `data/`: pieces recorded as video) are linked,
    not recorded again.

    `max_steps`, `keep_failed`, `placement_seed` and `use_videos` are the recorder's (tiny test runs keep the
    expert's unfinished episodes; with `placement_seed`, demonstrations start from freshly sampled placements, never
    from the fixed initial states that evaluation uses; `use_videos` stores the frames as video, about a twelfth of
    the images' size, for a dataset that must travel in a GPU bundle: research/docs/libero_runs.md)."""
    merged = work / "data" / "all"
    if (merged / "meta" / "info.json").exists():
        print(f"record: {merged} exists")
        return merged
    pieces = [
        (*piece, PLAIN) for piece in record_pieces(tasks, episodes_per_task, parts, more_episodes or {})
    ]
    if arm_episodes:  # one piece a task: a recorder's start-up is not repeated for a few attempts
        pieces += [(*piece, ARM) for piece in record_pieces(tasks, arm_episodes, 1, more_arm_episodes or {})]
    elif more_arm_episodes:
        raise ValueError(
            "`more_arm_episodes` adds pieces of `arm_episodes` attempts each: give `arm_episodes` too."
        )
    recovery = RECOVER_RISE if recovery_from_rise else RECOVER
    pieces += [(task, 0, n, recovery) for task, n in sorted((recovery_episodes or {}).items()) if n]
    for task, first, _, kind in pieces:
        piece = work / "data" / piece_name(task, first, kind)
        recorded = (folder / "data" / piece.name for folder in pieces_from or [])
        saved = next((s for s in recorded if (s / "meta" / "recording_report.json").exists()), None)
        if saved is not None and not piece.exists():
            piece.parent.mkdir(parents=True, exist_ok=True)
            piece.symlink_to(saved.resolve(), target_is_directory=True)

    def record_piece(piece: tuple[int, int, int, str]) -> int:
        task, first, n, kind = piece
        root = work / "data" / piece_name(task, first, kind)
        if piece_report(work, task, first, kind).exists():
            return 0
        cmd = [
            bin_path("ebvla-record-libero"),
            f"--env.task={SUITE}",
            f"--env.task_ids=[{task}]",
            f"--env.first_init_state={first}",
            f"--episodes_per_task={n}",
            f"--image_size={image_size}",
            f"--repo_id=local/libero_object_{root.name}",
            f"--root={root}",
            "--overwrite=true",  # a folder without a report is an interrupted recording
            f"--keep_failed={str(keep_failed).lower()}",
            f"--use_videos={str(use_videos).lower()}",
        ]
        if max_steps is not None:
            cmd.append(f"--max_steps={max_steps}")
        if kind == ARM:
            cmd += [
                f"--placement_seed={ARM_PLACEMENT_SEED}",
                f"--env.robot_init_noise={FIXED_STATES_ARM_NOISE}",
            ]
        elif kind in (RECOVER, RECOVER_RISE):
            cmd += [
                f"--placement_seed={RECOVERY_PLACEMENT_SEED}",
                f"--env.robot_init_noise={FIXED_STATES_ARM_NOISE}",
                "--regrasp=true",
                f"--miss_first_grasp={RECOVERY_MISS}",
                f"--store_missed_grasp={str(kind == RECOVER).lower()}",
            ]
        elif placement_seed is not None:
            cmd.append(f"--placement_seed={placement_seed}")
        return run_logged(cmd, work / "logs" / f"record_{root.name}.log")

    recorded_before = all(piece_report(work, task, first, kind).exists() for task, first, _, kind in pieces)
    start = time.time()
    with ThreadPoolExecutor(jobs) as pool:
        statuses = list(pool.map(record_piece, pieces))
    print(f"record: {len(pieces)} pieces in {time.time() - start:.0f} s, exit statuses {statuses}")
    reports = {}
    for task, first, _, kind in pieces:
        path = piece_report(work, task, first, kind)
        if path.exists():
            reports[(task, first, kind)] = json.loads(path.read_text())
    kept = [piece_name(*key) for key, report in reports.items() if report["n_kept"] > 0]
    if not kept:
        raise RuntimeError(f"No task recorded a successful episode; logs in {work / 'logs'}.")
    from lerobot.datasets.aggregate import aggregate_datasets

    aggregate_datasets(
        repo_ids=[f"local/libero_object_{name}" for name in kept],
        aggr_repo_id=REPO_ID,
        roots=[work / "data" / name for name in kept],
        aggr_root=merged,
    )
    summary = {
        "image_size": image_size,
        "episodes_per_task": episodes_per_task,
        "more_episodes": {str(task): n for task, n in sorted((more_episodes or {}).items())},
        "pieces_from": [str(folder) for folder in pieces_from or []],
        "placement_seed": placement_seed,
        "arm_episodes": arm_episodes,
        "more_arm_episodes": {str(task): n for task, n in sorted((more_arm_episodes or {}).items())},
        "arm_placement_seed": ARM_PLACEMENT_SEED if arm_episodes else None,
        "robot_init_noise": FIXED_STATES_ARM_NOISE if arm_episodes or recovery_episodes else 0.0,
        "recovery_episodes": {str(task): n for task, n in sorted((recovery_episodes or {}).items())},
        "recovery_placement_seed": RECOVERY_PLACEMENT_SEED if recovery_episodes else None,
        "recovery_miss": RECOVERY_MISS if recovery_episodes else None,
        "recovery_from_rise": recovery_from_rise,
        "use_videos": use_videos,
        "tasks": {},
    }
    for (task, _, kind), report in sorted(reports.items()):
        name = next(iter(report["success_rate_per_task"]))
        entry = summary["tasks"].setdefault(
            task, {"task": name, "attempts": 0, "kept": 0, "steps_of_kept": []}
        )
        entry["attempts"] += report["n_attempted"]
        entry["kept"] += report["n_kept"]
        entry["steps_of_kept"] += [ep["n_steps"] for ep in report["episodes"] if ep["kept"]]
        if kind:
            entry[f"{kind}_attempts"] = entry.get(f"{kind}_attempts", 0) + report["n_attempted"]
            entry[f"{kind}_kept"] = entry.get(f"{kind}_kept", 0) + report["n_kept"]
    # Pieces restored from saved results were recorded by an earlier session: its recording time stands, and
    # aggregating them again adds nothing to it.
    path = work / "recording_summary.json"
    earlier = json.loads(path.read_text()).get("seconds", 0.0) if path.exists() else 0.0
    summary["seconds"] = round(earlier + (0.0 if recorded_before else time.time() - start), 1)
    path.write_text(json.dumps(summary, indent=1))
    return merged


def task_counts(items: list[str]) -> dict[int, int]:
    """`TASK=N` command-line items as {task: N}."""
    counts = {}
    for item in items:
        task, sep, n = item.partition("=")
        if not sep or not task.isdigit() or not n.isdigit():
            raise ValueError(f"Expected TASK=N (two whole numbers), got {item!r}.")
        counts[int(task)] = int(n)
    return counts


def record_pieces(
    tasks: list[int], episodes_per_task: int, parts: int, more_episodes: dict[int, int]
) -> list[tuple[int, int, int]]:
    """(task, first attempt, attempts) of each recorder process: `parts` per task, and for a task of
    `more_episodes` as many more pieces of the same size as its extra attempts need."""
    per_part = -(-episodes_per_task // parts)
    pieces = []
    for task in tasks:
        total = episodes_per_task + more_episodes.get(task, 0)
        pieces += [(task, first, min(per_part, total - first)) for first in range(0, total, per_part)]
    return pieces


# Train -------------------------------------------------------------------------------------------------------


def run_args(run: str, image_size: int) -> list[str]:
    """`RUNS[run]` for frames of `image_size` (Diffusion Policy crops 90% of them, 115 px of 128)."""
    if run == "diffusion":  # `diffusion_cpu` resizes, then crops by `crop_ratio`
        crop = int(0.9 * image_size)
        return [*RUNS[run], f"--policy.crop_shape=[{crop},{crop}]"]
    return RUNS[run]


def train_command(
    work: Path, run: str, steps: int, batch_size: int, device: str, workers: int, save_freq: int | None = None
) -> list[str]:
    """`ebvla-train` (lerobot-train reading action chunks from their column) of `run`, or its resumption.

    `save_freq` (default: a tenth of `steps`) bounds what a training cut short loses."""
    out = work / "train" / run
    last = out / "checkpoints" / "last" / "pretrained_model" / "train_config.json"
    if last.exists():
        return [bin_path("ebvla-train"), f"--config_path={last}", "--resume=true", f"--steps={steps}"]
    if run in FINE_TUNES:
        fine_tune = FINE_TUNES[run]
        policy = [f"--policy.path={REPOSITORY / fine_tune.start}", *fine_tune.flags]
    else:
        policy = run_args(run, json.loads((work / "recording_summary.json").read_text())["image_size"])
    return [
        bin_path("ebvla-train"),
        *policy,
        f"--policy.device={device}",
        f"--dataset.repo_id={REPO_ID}",
        f"--dataset.root={work / 'data' / 'all'}",
        f"--batch_size={batch_size}",
        f"--steps={steps}",
        f"--save_freq={save_freq or max(steps // 10, 1)}",
        "--log_freq=100",
        f"--num_workers={workers}",
        "--seed=1000",
        "--wandb.enable=false",
        f"--output_dir={out}",
    ]


def train(
    work: Path,
    runs: list[str],
    steps: int,
    batch_size: int,
    device: str,
    workers: int,
    detach: bool,
    until_s: float | None = None,
    save_freq: int | None = None,
    threads: int = 2,
) -> list[subprocess.Popen]:
    """Trains `runs` side by side (each with `workers` loader processes); `detach` returns at once, with the
    trainings' processes.

    A detached training starts a session of its own, so it outlives the command that started it. `until_s`
    stops the trainings after that many seconds, detached or not (their last checkpoint stays; the next call
    resumes from it), so that a long training runs in parts.
    """
    variants = [run for run in runs if run in INFERENCE_VARIANTS]
    if variants:
        raise ValueError(
            f"{variants} evaluate another run's checkpoint and are not trained: train their base run."
        )
    processes = []
    for run in runs:
        if (work / "train" / run / "DONE").exists():
            print(f"train: {run} done")
            continue
        cmd = train_command(work, run, steps, batch_size, device, workers, save_freq)
        # `timeout` rather than a wait here: a detached training has no parent left to stop it.
        if until_s is not None:
            cmd = ["timeout", "--signal=TERM", f"{until_s:.0f}", *cmd]
        # Marks the run done only when the training exits 0 (a timed-out one exits 124).
        script = f'{subprocess.list2cmdline(cmd)} && touch "{work / "train" / run / "DONE"}"'
        log = work / "logs" / f"train_{run}.log"
        log.parent.mkdir(parents=True, exist_ok=True)
        processes.append(
            subprocess.Popen(
                ["bash", "-c", script],
                stdout=open(log, "a"),  # noqa: SIM115 (the child keeps it open)
                stderr=subprocess.STDOUT,
                env=child_env() | {"OMP_NUM_THREADS": str(threads)},
                start_new_session=True,
            )
        )
        print(f"train: {run} started (pid {processes[-1].pid}), log {log}")
    if detach:
        return processes
    for process in processes:
        if process.wait() == 124:
            print(f"train: stopped after {until_s:.0f} s (pid {process.pid}); the next call resumes")
    return processes


def stop_training(work: Path) -> None:
    """Stops every training of `work` (their last checkpoint stays): the GPU slice is needed for evaluation."""
    subprocess.run(["pkill", "-f", f"ebvla-train.*{work / 'train'}"], check=False)


def last_checkpoint(work: Path, run: str) -> Path | None:
    """The run's last saved `pretrained_model` (an inference variant's: its base run's), None before the first."""
    run = INFERENCE_VARIANTS[run].base if run in INFERENCE_VARIANTS else run
    path = work / "train" / run / "checkpoints" / "last" / "pretrained_model"
    return path if (path / "model.safetensors").exists() else None


# Evaluate ----------------------------------------------------------------------------------------------------


# Fresh placements for evaluation: sampled with seeds 200000 + i (the recordings use 100000 + i).
FRESH_CONDITION = "vanilla_fresh"
FRESH_PLACEMENT_SEED = 200000
# The vanilla jobs of each ebvla run: the monitor's calibration, then the held-out rollouts.
VANILLA_CONDITIONS = ("vanilla_calib", "vanilla_heldout")
# Held-out vanilla rollouts from the fixed initial states after the held-out ones, run last: a second held-out set
# for a threshold rule chosen after the first was looked at (research/docs/libero_runs.md, "D's threshold rule").
CONFIRM_CONDITION = "vanilla_confirm"
# The fresh placements again with the arm's starting angles drawn as LIBERO's fixed states draw theirs (robosuite's
# Gaussian, 0.02 rad a joint) and set as LIBERO sets a fixed state's, after the controller is loaded: does the arm's
# start explain the fixed states' lower success (research/docs/libero_placement_gap.md)? The records of
# `vanilla_fresh_arm` drew the arm with robosuite's `initialization_noise` instead, the controller loaded at the
# noisy pose (commit 8043c8d; research/docs/libero_runs.md, "The arm's start").
FRESH_ARM_CONDITION = "vanilla_fresh_arm_set"
FIXED_STATES_ARM_NOISE = 0.02


@dataclass(frozen=True)
class EvalJob:
    """`n` episodes of one task, one condition and one policy, from initial states [first, first + n)."""

    run: str
    condition: str  # vanilla_calib, vanilla_heldout, vanilla_fresh, or <perturbation><severity>
    task: int
    first: int
    n: int
    seed: int
    perturbation: str = "none"
    severity: int = 0

    @property
    def name(self) -> str:
        return f"{self.run}/{self.condition}/task{self.task}"


def eval_jobs(
    runs: list[str],
    tasks: list[int],
    vanilla: int,
    perturbed: int,
    conditions=CAMERA_CONDITIONS,
    calibration: int | None = None,
    fresh: int = 0,
    vanilla_conditions: tuple[str, ...] = VANILLA_CONDITIONS,
    confirm: int = 0,
    fresh_arm: int = 0,
    first: tuple[str, ...] = (),
    only_first: bool = False,
) -> list[EvalJob]:
    """The evaluation queue, most needed first: vanilla calibration and held-out rollouts of the `ebvla` runs,
    then the camera perturbations of the `ebvla` runs in the order of `conditions`; the other policies (no
    energy to calibrate a monitor on) get the held-out rollouts alone, their success beside ebvla's.

    Without `calibration`, initial states [0, vanilla / 2) calibrate, [vanilla / 2, vanilla) are held out and
    the perturbed rollouts start from the calibration's states. With it, states [0, calibration) calibrate,
    `vanilla` held-out rollouts follow them, and the perturbed rollouts start from the held-out states, so that
    a perturbed rollout and a held-out vanilla one differ only by the perturbation.

    `fresh` vanilla rollouts per task of each `ebvla` run come last (`vanilla_fresh`): from placements LIBERO
    samples with seeds `FRESH_PLACEMENT_SEED` + i, which neither the fixed initial states nor the recordings
    (seeds 100000 + i) use: success off the states every other job starts from. `confirm` vanilla rollouts per
    task (`vanilla_confirm`, needs `calibration`) follow them, from the fixed states after the held-out ones.
    `fresh_arm` rollouts per task (`vanilla_fresh_arm_set`) come last: the first `fresh_arm` fresh placements again,
    the arm's start drawn as the fixed states' (`FIXED_STATES_ARM_NOISE`).

    `first` moves the jobs it names to the front, in its order (the others keep theirs): an entry names a condition
    (`vanilla_confirm`) or one run's (`<run>/vanilla_calib`). A short slice then spends its time on the rollouts a
    rule fixed beforehand reads; with `only_first` the queue is those jobs alone.

    `vanilla_conditions` keeps some of the vanilla calibration and held-out jobs (none: `()`), for a machine that
    runs the rest while another runs those (the queue with no `conditions`): the two queues together are the
    whole one.
    """
    half = vanilla // 2 if calibration is None else calibration
    heldout = vanilla - half if calibration is None else vanilla
    perturbed_first = 0 if calibration is None else calibration
    ebvla_runs = [run for run in runs if run.startswith("ebvla")]
    other_runs = [run for run in runs if run not in ebvla_runs]

    def vanilla_jobs(run: str) -> list[EvalJob]:
        return [
            job
            for task in tasks
            for job in (
                EvalJob(run, "vanilla_calib", task, 0, half, 1000),
                EvalJob(run, "vanilla_heldout", task, half, heldout, 2000),
            )
        ]

    def camera_jobs(perturbation: str, severity: int) -> list[EvalJob]:
        condition = f"{perturbation}{severity}"
        return [
            EvalJob(run, condition, task, perturbed_first, perturbed, 3000, perturbation, severity)
            for run in ebvla_runs
            for task in tasks
        ]

    # The other policies' vanilla success comes after the first two camera conditions: Table III needs those
    # more, and it is the first thing a short slice drops.
    queue = [job for run in ebvla_runs for job in vanilla_jobs(run) if job.condition in vanilla_conditions]
    for perturbation, severity in conditions[:2]:
        queue += camera_jobs(perturbation, severity)
    if "vanilla_heldout" in vanilla_conditions:
        queue += [
            job for run in other_runs for job in vanilla_jobs(run) if job.condition == "vanilla_heldout"
        ]
    for perturbation, severity in conditions[2:]:
        queue += camera_jobs(perturbation, severity)
    queue += [
        EvalJob(run, FRESH_CONDITION, task, 0, fresh, FRESH_PLACEMENT_SEED)
        for run in ebvla_runs
        for task in tasks
        if fresh
    ]
    if confirm and calibration is None:
        raise ValueError("`confirm` rollouts start after the held-out states: give `calibration` too.")
    queue += [
        EvalJob(run, CONFIRM_CONDITION, task, calibration + vanilla, confirm, 4000)
        for run in ebvla_runs
        for task in tasks
        if confirm
    ]
    queue += [
        EvalJob(run, FRESH_ARM_CONDITION, task, 0, fresh_arm, FRESH_PLACEMENT_SEED)
        for run in ebvla_runs
        for task in tasks
        if fresh_arm
    ]

    def rank(job: EvalJob) -> int:
        named = [i for i, entry in enumerate(first) if entry in (job.condition, f"{job.run}/{job.condition}")]
        return min(named, default=len(first))

    queue = sorted(queue, key=rank)
    return [job for job in queue if rank(job) < len(first)] if only_first else queue


def eval_command(work: Path, job: EvalJob, device: str, episode_length: int | None = None) -> list[str]:
    """`ebvla-eval` (energy records with context features) for `ebvla`, `lerobot-eval` for other policies."""
    program = "ebvla-eval" if job.run.startswith("ebvla") else "lerobot-eval"
    # Rendered at the recorded size, so that the policy sees frames as in its data.
    image_size = json.loads((work / "recording_summary.json").read_text())["image_size"]
    cmd = [
        bin_path(program),
        f"--policy.path={last_checkpoint(work, job.run)}",
        f"--policy.device={device}",
        "--env.type=libero_ebvla",
        f"--env.task={SUITE}",
        f"--env.task_ids=[{job.task}]",
        f"--env.first_init_state={job.first}",
        f"--env.perturbation={job.perturbation}",
        f"--env.perturbation_severity={job.severity}",
        f"--env.observation_height={image_size}",
        f"--env.observation_width={image_size}",
        f"--eval.n_episodes={job.n}",
        "--eval.batch_size=1",
        f"--seed={job.seed}",
        f"--output_dir={work / 'eval' / job.name}",
    ]
    if episode_length is not None:
        cmd.append(f"--env.episode_length={episode_length}")
    variant = INFERENCE_VARIANTS.get(job.run)
    executed = None if variant is None else variant.n_action_steps
    if variant is not None:
        cmd += variant.flags
    if executed is not None:
        cmd.append(f"--policy.n_action_steps={executed}")
    if job.condition in (FRESH_CONDITION, FRESH_ARM_CONDITION):
        # LeRobot's env then keeps the placements LIBERO's reset samples from the episode's seed.
        cmd.append("--env.init_states=false")
    if job.condition == FRESH_ARM_CONDITION:
        cmd.append(f"--env.robot_init_noise={FIXED_STATES_ARM_NOISE}")
    if program == "ebvla-eval":
        cmd.append("--record_context_features=true")
        # The policy reads a frame every n_action_steps steps; the others are not rendered (the same rollouts,
        # about half the time on two cores). ebvla-eval raises should a chunk be refined from another step.
        if executed is None:
            config = last_checkpoint(work, job.run) / "config.json"
            executed = json.loads(config.read_text())["n_action_steps"] if config.exists() else 1
        if executed > 1:
            cmd.append(f"--env.render_every={executed}")
    return cmd


def evaluate(
    work: Path,
    jobs: list[EvalJob],
    device: str,
    parallel: int,
    deadline_s: float,
    episode_length: int | None = None,
) -> dict:
    """Runs the queue `parallel` at a time until it is empty or `deadline_s` has passed; a job cut short is
    removed, so that the next call runs it again. Returns {job name: status}."""
    stop_at = time.time() + deadline_s
    statuses = {}

    def run_job(job: EvalJob) -> None:
        folder = work / "eval" / job.name
        if (folder / "eval_info.json").exists():
            statuses[job.name] = "done before"
            return
        if last_checkpoint(work, job.run) is None or time.time() > stop_at - 30:
            statuses[job.name] = "not run"
            return
        shutil.rmtree(folder, ignore_errors=True)
        log = work / "logs" / "eval" / f"{job.name.replace('/', '_')}.log"
        command = eval_command(work, job, device, episode_length)
        status = run_logged(command, log, timeout_s=stop_at - time.time())
        if status != 0 or not (folder / "eval_info.json").exists():
            shutil.rmtree(folder, ignore_errors=True)
        statuses[job.name] = (
            "done" if status == 0 else ("cut at the deadline" if status == -1 else f"exit {status}")
        )

    with ThreadPoolExecutor(parallel) as pool:
        list(pool.map(run_job, jobs))
    counts = {s: sum(v == s for v in statuses.values()) for s in set(statuses.values())}
    print(f"eval: {counts}")
    return statuses


def camera_check(work: Path, run: str, frames: int = 32) -> None:
    """The camera check on dataset frames (both cameras blanked) of `run`'s checkpoint, into
    `<work>/eval/<run>/camera_check.json`: read it before any claim about images."""
    out = work / "eval" / run / "camera_check.json"
    checkpoint = last_checkpoint(work, run)
    if out.exists() or checkpoint is None:
        return
    if not (work / "data" / "all").exists():  # an evaluation-only machine: the check runs where the data is
        print(f"camera check {run}: not run here, no dataset in {work / 'data' / 'all'}")
        return
    from lerobot_policy_ebvla.monitoring.vision import checkpoint_camera_dependence

    result = checkpoint_camera_dependence(str(checkpoint), str(work / "data" / "all"), REPO_ID, frames, 1000)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"summary": result.summary(), **vars(result)}, indent=1, default=str))
    print(f"camera check {run}: {result.summary()}")


# Pack and report ---------------------------------------------------------------------------------------------


def light_checkpoint(run: str) -> bool:
    """Whether a run's checkpoint is light enough to bring back and commit: the `ebvla` runs' (a few MB). Diffusion
    Policy's (its U-Net and ResNet-18 with their optimizer state, hundreds of MB) is not, so it trains and is
    evaluated within one slice."""
    return run.startswith("ebvla")


def pack(work: Path, archive: Path) -> None:
    """Records (with their context features), eval infos, logs, summaries and the light `ebvla` runs' last
    checkpoints (a few MB each) in one archive."""
    archive.parent.mkdir(parents=True, exist_ok=True)
    kept_names = ("eval_info.json", "camera_check.json", "recording_summary.json", "recording_report.json")
    with tarfile.open(archive, "w:gz") as tar:
        for path in sorted(work.rglob("*")):
            relative = path.relative_to(work)
            if relative.parts[0] == "train" or not path.is_file():
                continue
            if relative.parts[0] == "data" and path.name not in kept_names:
                continue  # the frames, and the PNGs an interrupted recording leaves
            if path.suffix in (".jsonl", ".npy", ".log", ".md", ".png") or path.name in kept_names:
                tar.add(path, arcname=str(relative))
        for run in RUNS:
            checkpoint = last_checkpoint(work, run)
            if light_checkpoint(run) and checkpoint is not None:
                tar.add(checkpoint.resolve(), arcname=f"train/{run}/pretrained_model")
    print(f"pack: {archive} ({archive.stat().st_size / 2**20:.1f} MiB)")


def save_results(work: Path, results: Path) -> None:
    """Copies what the next session needs to go on, and what a table is recomputed from, into `results` (a
    folder to commit): the recording summaries, each light run's last checkpoint with its optimizer state
    (resume; `light_checkpoint`; without it once the run is done), `DONE` markers, eval infos, gzip records with their context features, camera
    checks, reports, timings.

    Frames stored as images are not saved: `record` with the same `--placement_seed` makes the same dataset
    again. Pieces recorded as video (`--use_videos`, about 0.6 MB an episode at 128 px) are saved whole, so that
    the next session trains on them instead of recording them again (about two hours for ten tasks on two cores).
    """
    from lerobot_policy_ebvla.monitoring.records import (
        GZIP_SUFFIX,
        read_energy_records,
        records_file_in,
        write_energy_records,
    )

    results.mkdir(parents=True, exist_ok=True)
    small = ["recording_summary.json", "success.json", "timings.jsonl", "eval_status.json"]
    small += [str(p.relative_to(work)) for p in work.glob("eval/*/camera_check.json")]
    small += [str(p.relative_to(work)) for p in work.glob("eval/*/*/task*/eval_info.json")]
    small += [str(p.relative_to(work)) for p in work.glob("train/*/DONE")]
    small += [str(p.relative_to(work)) for p in work.glob("reports/**/*") if p.is_file()]
    for name in small:
        if (work / name).is_file():
            (results / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(work / name, results / name)
    # Pieces linked from another results folder (`record`'s `pieces_from`) are saved there already.
    recorded_here = [
        report
        for report in work.glob("data/*/meta/recording_report.json")
        if not report.parents[1].is_symlink()
    ]
    # Under a name of their own: restored into data/, a piece's report would mark it recorded without its frames.
    for report in recorded_here:
        target = results / "recording_reports" / f"{report.parents[1].name}.json"
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(report, target)
    for report in recorded_here:
        piece, target = report.parents[1], results / "data" / report.parents[1].name
        if (piece / "videos").is_dir() and not target.exists():
            shutil.copytree(piece, target)
    for info in work.glob("eval/*/*/task*/eval_info.json"):
        source = records_file_in(info.parent)
        target = results / info.parent.relative_to(work) / "energy_records.jsonl.gz"
        if source is not None and not target.exists():
            records = read_energy_records(source)
            if source.name.endswith(GZIP_SUFFIX):
                shutil.copyfile(source, target)
                features = source.with_name(source.name.replace(".jsonl.gz", ".features.npy.gz"))
                if features.exists():
                    shutil.copyfile(features, target.with_name(features.name))
            else:
                write_energy_records(target, records)
    for run_dir in sorted((work / "train").glob("*")):
        last = run_dir / "checkpoints" / "last"
        if (
            not light_checkpoint(run_dir.name)
            or not (last / "pretrained_model" / "model.safetensors").exists()
        ):
            continue
        target = results / "train" / run_dir.name / "last"
        shutil.rmtree(target, ignore_errors=True)
        # A finished run is never resumed: its optimizer state (twice the weights) stays behind.
        done = (run_dir / "DONE").exists()
        shutil.copytree(
            last.resolve(), target, ignore=shutil.ignore_patterns("training_state") if done else None
        )
    print(f"save: {results}")


def restore_results(results: Path, work: Path) -> None:
    """The reverse of `save_results`: puts what `results` holds into `work` where `work` lacks it, so that every
    stage resumes (training from the saved checkpoint, evaluation after the jobs already done)."""
    for path in sorted(results.rglob("*")):
        relative = path.relative_to(results)
        if not path.is_file() or relative.parts[0] == "train" and "last" in relative.parts:
            continue
        target = work / relative
        # The compressed copy of records `work` still holds uncompressed (the session that saved them) would
        # leave two record files in one folder.
        uncompressed = target.with_name(target.name.removesuffix(".gz"))
        if not target.exists() and not (target.name.endswith(".gz") and uncompressed.exists()):
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(path, target)
    for last in sorted(results.glob("train/*/last")):
        checkpoints = work / "train" / last.parent.name / "checkpoints"
        if (checkpoints / "last").exists():
            continue
        state = last / "training_state" / "training_step.json"
        # A finished run is saved without its training state: it stopped at the config's last step.
        source = state if state.exists() else last / "pretrained_model" / "train_config.json"
        step = json.loads(source.read_text())["step" if state.exists() else "steps"]
        shutil.copytree(last, checkpoints / f"{step:06d}")
        (checkpoints / "last").symlink_to(f"{step:06d}")
        # LeRobot resumes from the config the checkpoint names; it must point at this work folder.
        config = checkpoints / f"{step:06d}" / "pretrained_model" / "train_config.json"
        train_config = json.loads(config.read_text())
        train_config["output_dir"] = str(work / "train" / last.parent.name)
        train_config["dataset"]["root"] = str(work / "data" / "all")
        config.write_text(json.dumps(train_config, indent=4))
    print(f"restore: {results} -> {work}")


def log_timing(work: Path, stage: str, seconds: float, args: list[str]) -> None:
    """Appends a stage's wall time to `<work>/timings.jsonl` (the protocol's costs, stage by stage)."""
    row = {
        "stage": stage,
        "seconds": round(seconds, 1),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
    }
    with open(work / "timings.jsonl", "a") as out:
        out.write(json.dumps({**row, "args": args, "cpus": os.cpu_count()}) + "\n")


def success_table(work: Path) -> dict:
    """Success per run, condition and task from lerobot-eval's `eval_info.json` files."""
    table: dict = {}
    for info in sorted((work / "eval").glob("*/*/task*/eval_info.json")):
        run, condition, task = info.parent.relative_to(work / "eval").parts
        # lerobot-eval's multi-task layout: one entry per (suite, task id), each with its episodes' successes.
        successes = [
            bool(s) for t in json.loads(info.read_text())["per_task"] for s in t["metrics"]["successes"]
        ]
        table.setdefault(run, {}).setdefault(condition, {})[task] = [sum(successes), len(successes)]
    return table


# The LIBERO checkpoints' OOD score where the light preset's would be `context_phase_energy`: E_c with the head's
# energy of the MCMC's start, chosen on D's rollouts and confirmed on C's (research/docs/libero_runs.md, "The
# starting sample's energy beside E_c"). The runs' training flags keep the score they were trained with.
LIBERO_MONITOR_SCORE = "context_start_energy"


def libero_monitor_score(checkpoint: Path) -> list[str]:
    """`--score=LIBERO_MONITOR_SCORE` for a checkpoint its config would monitor with `context_phase_energy`."""
    from lerobot_policy_ebvla.monitoring.ood_report import checkpoint_monitor_score

    return (
        [f"--score={LIBERO_MONITOR_SCORE}"]
        if checkpoint_monitor_score(checkpoint) == "context_phase_energy"
        else []
    )


def report(
    work: Path,
    runs: list[str],
    failure_calibration_shifts: tuple[str, ...] = (),
    failure_choice: Path | None = None,
    threshold_rule: str = "mean_std",
) -> None:
    """Success per task, Table III (ebvla-ood-report) and Table IV (ebvla-failure-report) of each run.

    Table IV needs failures on both sides: a policy that rarely fails in vanilla gives its calibration none to
    choose an alarm on. The rollouts under `failure_calibration_shifts` (perturbation names) then join the
    calibration, and those under every other shift join the held-out episodes: the alarm is chosen on some
    shifts and reported on others, never on the rollouts it was chosen on. Without them, Table IV is vanilla
    calibration against held-out vanilla.

    `failure_choice` (the JSON of `failure_check_choice.py`, chosen on the calibration rollouts alone) sets the
    monitor's failure check in the OOD report and in what `--calibrate_to` saves. Rollouts from fresh placements
    (`vanilla_fresh`) are held-out vanilla rollouts there too: no threshold is fitted on them, nor on the
    confirmation rollouts (`vanilla_confirm`).

    `threshold_rule` is the rule of the OOD threshold the checkpoint's monitor ships (Eq. 5 or the conformal
    quantile); the failure check keeps Eq. 5, the rule `failure_check_choice.py` chooses at.
    """
    failure_options = (
        [] if failure_choice is None else json.loads(failure_choice.read_text())["report_options"]
    )
    table = success_table(work)
    (work / "success.json").write_text(json.dumps(table, indent=1))
    for run, conditions in table.items():
        for condition, tasks in sorted(conditions.items()):
            wins, total = (sum(v[i] for v in tasks.values()) for i in (0, 1))
            print(
                f"{run:14} {condition:16} {wins:3}/{total:<3} "
                + " ".join(f"{a}/{b}" for a, b in tasks.values())
            )
    for run in runs:
        folder = work / "eval" / run
        if not run.startswith("ebvla") or not (folder / "vanilla_calib").exists():
            continue
        # Each condition's records sit in one folder per task.
        perturbed = sorted(
            p.name for p in folder.glob("*") if p.is_dir() and not p.name.startswith("vanilla")
        )
        calibration, heldout = (str(folder / name / "task*") for name in ("vanilla_calib", "vanilla_heldout"))
        fresh = [
            str(folder / name / "task*")
            for name in (FRESH_CONDITION, CONFIRM_CONDITION)
            if (folder / name).is_dir()
        ]
        # The checkpoint's own monitor (its config's scores), calibrated on the calibration rollouts as a user
        # would: the report's "monitor" rows are then what ships with it.
        checkpoint = work / "train" / run / "checkpoints" / "last" / "pretrained_model"
        monitor = (
            [
                f"--calibrate_to={checkpoint}",
                "--overwrite_calibration=true",
                *libero_monitor_score(checkpoint),
            ]
            if checkpoint.is_dir()
            else []
        )
        if perturbed:
            subprocess.run(
                [
                    bin_path("ebvla-ood-report"),
                    f"--calibration=[{calibration}]",
                    f"--vanilla=[{','.join([heldout, *fresh])}]",
                    f"--ood=[{','.join(str(folder / name / 'task*') for name in perturbed)}]",
                    f"--output_dir={work / 'reports' / run / 'ood'}",
                    *monitor,
                    *failure_options,
                    f"--threshold_rule={threshold_rule}",
                    "--failure_threshold_rule=mean_std",
                ],
                check=True,
            )
        failure_calibration, failure_heldout = [calibration], [heldout, *fresh]
        for name in perturbed if failure_calibration_shifts else []:
            side = (
                failure_calibration
                if name.rstrip("0123456789") in failure_calibration_shifts
                else failure_heldout
            )
            side.append(str(folder / name / "task*"))
        subprocess.run(
            [
                bin_path("ebvla-failure-report"),
                f"--calibration=[{','.join(failure_calibration)}]",
                f"--records=[{','.join(failure_heldout)}]",
                f"--output_dir={work / 'reports' / run / 'failure'}",
            ],
            check=True,
        )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "stage", choices=["record", "train", "stop", "eval", "pack", "report", "save", "restore"]
    )
    parser.add_argument("--work", type=Path, default=Path("outputs/libero_pipeline"))
    parser.add_argument("--tasks", type=int, nargs="+", default=list(range(10)))
    parser.add_argument("--episodes_per_task", type=int, default=22, help="expert attempts per task")
    parser.add_argument("--image_size", type=int, default=128)
    parser.add_argument("--parts", type=int, default=1, help="record: processes per task")
    parser.add_argument(
        "--max_steps", type=int, default=None, help="record: the expert's step cap (LeRobot's 280)"
    )
    parser.add_argument(
        "--keep_failed", action="store_true", help="record: keep the expert's failed episodes"
    )
    parser.add_argument(
        "--placement_seed",
        type=int,
        default=None,
        help="record: start demonstrations from placements sampled with this seed (+ attempt), not from the "
        "fixed initial states evaluation uses",
    )
    parser.add_argument(
        "--use_videos", action="store_true", help="record: frames as video (a dataset small enough to travel)"
    )
    parser.add_argument(
        "--more_episodes",
        nargs="*",
        default=[],
        metavar="TASK=N",
        help="record: N more expert attempts of TASK, after its --episodes_per_task",
    )
    parser.add_argument(
        "--pieces_from",
        type=Path,
        nargs="*",
        default=[],
        help="record: saved results folders whose video pieces are linked instead of recorded again",
    )
    parser.add_argument(
        "--arm_episodes",
        type=int,
        default=0,
        help="record: expert attempts per task with the arm's start drawn as the fixed states' (pieces of their own)",
    )
    parser.add_argument(
        "--more_arm_episodes",
        nargs="*",
        default=[],
        metavar="TASK=N",
        help="record: N more attempts of TASK with the fixed states' arm start, after its --arm_episodes",
    )
    parser.add_argument(
        "--recovery_episodes",
        nargs="*",
        default=[],
        metavar="TASK=N",
        help="record: N recovery demonstrations of TASK (a first grasp beside the object, then the grasp again)",
    )
    parser.add_argument(
        "--recovery_from_rise",
        action="store_true",
        help="record: store the recovery demonstrations' frames from the rise after the miss on (J), not all (I)",
    )
    parser.add_argument("--jobs", type=int, default=10, help="processes side by side (record, eval)")
    parser.add_argument("--runs", nargs="+", choices=list(RUNS), default=["ebvla_paper", "diffusion"])
    parser.add_argument(
        "--failure_calibration_shifts",
        nargs="*",
        default=[],
        help="report: the perturbations whose rollouts join Table IV's calibration (the others' join its held-out "
        "episodes); none: vanilla calibration only",
    )
    parser.add_argument(
        "--failure_choice",
        type=Path,
        default=None,
        help="report: failure_check_choice.py's JSON; its options set the monitor's failure check",
    )
    parser.add_argument(
        "--threshold_rule",
        choices=("mean_std", "conformal"),
        default="mean_std",
        help="report: the rule of the OOD threshold the checkpoint ships (the failure check keeps mean_std)",
    )
    parser.add_argument("--steps", type=int, default=8000)
    parser.add_argument("--batch_size", type=int, default=32)
    parser.add_argument("--workers", type=int, default=5, help="loader processes per training")
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--detach", action="store_true", help="train: return while the trainings run on")
    parser.add_argument(
        "--train_until_s", type=float, default=None, help="train: stop after this long (resume next call)"
    )
    parser.add_argument("--save_freq", type=int, default=None, help="train: steps between checkpoints")
    parser.add_argument("--threads", type=int, default=2, help="train: torch threads per training")
    parser.add_argument(
        "--calibration",
        type=int,
        default=None,
        help="eval: calibration episodes per task (states [0, N)); then --vanilla held-out ones and the "
        "perturbed ones start from the held-out states. Default: --vanilla is split in half",
    )
    parser.add_argument(
        "--vanilla", type=int, default=20, help="vanilla episodes per task and run (half calibrate)"
    )
    parser.add_argument(
        "--fresh",
        type=int,
        default=0,
        help="eval: vanilla episodes per task of each ebvla run from fresh placements (seeds 200000 + i), last",
    )
    parser.add_argument(
        "--confirm",
        type=int,
        default=0,
        help="eval: vanilla episodes per task of each ebvla run from the fixed states after the held-out ones, last",
    )
    parser.add_argument(
        "--fresh_arm",
        type=int,
        default=0,
        help="eval: the first fresh placements again, the arm's start drawn as the fixed states' (0.02 rad), last",
    )
    parser.add_argument("--perturbed", type=int, default=5, help="episodes per task and camera condition")
    parser.add_argument(
        "--first",
        nargs="*",
        default=[],
        help="eval: the jobs to run first, in this order: a condition (vanilla_confirm) or a run's (RUN/vanilla_calib)",
    )
    parser.add_argument("--only_first", action="store_true", help="eval: run only the jobs --first names")
    parser.add_argument(
        "--vanilla_conditions",
        nargs="*",
        choices=VANILLA_CONDITIONS,
        default=list(VANILLA_CONDITIONS),
        help="eval: the vanilla jobs to run (none: another machine runs them; the perturbed rollouts still start "
        "from the held-out states)",
    )
    parser.add_argument(
        "--deadline_s", type=float, default=480.0, help="eval: stop starting and cut jobs after this"
    )
    parser.add_argument(
        "--conditions",
        nargs="*",
        default=[f"{p}:{s}" for p, s in CAMERA_CONDITIONS],
        help="eval: camera conditions as perturbation:severity, in the order they are run",
    )
    parser.add_argument(
        "--episode_length", type=int, default=None, help="eval: steps per episode (LeRobot's 280)"
    )
    parser.add_argument("--archive", type=Path, default=None, help="pack: the archive to write")
    parser.add_argument(
        "--results", type=Path, default=None, help="save / restore: the folder of committed products"
    )
    args = parser.parse_args(argv)
    work = args.work.resolve()
    work.mkdir(parents=True, exist_ok=True)
    start = time.time()
    if args.stage == "save":
        save_results(work, args.results.resolve())
    elif args.stage == "restore":
        restore_results(args.results.resolve(), work)
    elif args.stage == "record":
        record(
            work,
            args.tasks,
            args.episodes_per_task,
            args.image_size,
            args.jobs,
            args.parts,
            args.max_steps,
            args.keep_failed,
            args.placement_seed,
            args.use_videos,
            task_counts(args.more_episodes),
            [folder.resolve() for folder in args.pieces_from],
            args.arm_episodes,
            task_counts(args.more_arm_episodes),
            task_counts(args.recovery_episodes),
            args.recovery_from_rise,
        )
    elif args.stage == "train":
        train(
            work,
            args.runs,
            args.steps,
            args.batch_size,
            args.device,
            args.workers,
            args.detach,
            args.train_until_s,
            args.save_freq,
            args.threads,
        )
    elif args.stage == "stop":
        stop_training(work)
    elif args.stage == "eval":
        start = time.time()
        for run in args.runs:
            if run.startswith("ebvla"):
                camera_check(work, run)
        conditions = [(c.split(":")[0], int(c.split(":")[1])) for c in args.conditions]
        jobs = eval_jobs(
            args.runs,
            args.tasks,
            args.vanilla,
            args.perturbed,
            conditions,
            args.calibration,
            args.fresh,
            tuple(args.vanilla_conditions),
            args.confirm,
            args.fresh_arm,
            tuple(args.first),
            args.only_first,
        )
        remaining = args.deadline_s - (time.time() - start)
        statuses = evaluate(work, jobs, args.device, args.jobs, remaining, args.episode_length)
        (work / "eval_status.json").write_text(json.dumps(statuses, indent=1))
    elif args.stage == "pack":
        pack(work, args.archive or work / "libero_results.tar.gz")
    else:
        report(
            work, args.runs, tuple(args.failure_calibration_shifts), args.failure_choice, args.threshold_rule
        )
    if args.stage in ("record", "train", "eval", "report"):
        log_timing(work, args.stage, time.time() - start, argv if argv is not None else sys.argv[1:])


if __name__ == "__main__":
    main()
