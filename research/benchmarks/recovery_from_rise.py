"""Recovery demonstrations without their deliberate miss, cut from I's recorded pieces (research/docs/libero_runs.md,
"J").

I's recovery demonstrations (`record --recovery_episodes`, recorded with the miss stored) taught the policy to close
beside the object. The recorder now stores a recovery's frames from the rise after its miss on
(`RecordLiberoConfig.store_missed_grasp`, off by default). The simulator is deterministic, so the frames it would store
are I's frames from that step on: `cut` writes them as the pieces `libero_pipeline.py record --recovery_from_rise`
expects (3 minutes for I's 40, where recording them again takes about 40), and `check` records one attempt with
the package's recorder and compares it with the cut piece's episode: states and actions equal, frames within the video
codec's error (I's frames were decoded and encoded again).

    python research/benchmarks/recovery_from_rise.py cut --source=research/results/libero_object10_recover \
        --work=outputs/libero10_rise --tasks 1 5
    MUJOCO_GL=egl python research/benchmarks/recovery_from_rise.py check --work=outputs/libero10_rise --task=5
"""

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from lerobot_policy_ebvla.recording.libero import GRIPPER_CLOSED  # noqa: E402
from research.benchmarks.libero_pipeline import (  # noqa: E402
    FIXED_STATES_ARM_NOISE,
    RECOVER,
    RECOVER_RISE,
    RECOVERY_MISS,
    RECOVERY_PLACEMENT_SEED,
    SUITE,
    bin_path,
    piece_name,
)

# The largest mean absolute difference (of 255) between a frame the recorder stores and the same frame decoded and
# encoded once more: AV1 at crf 30 on 128 px frames.
CODEC_TOLERANCE = 6.0


def rise_start(actions: np.ndarray) -> int:
    """Index of the first frame of the rise after the first grasp: the hand closed and moving (the grasp holds it still
    while it closes)."""
    closed = actions[:, 6] == GRIPPER_CLOSED
    moving = np.abs(actions[:, :3]).max(axis=1) > 0
    first_close = int(np.argmax(closed))
    if not closed.any() or not (closed & moving)[first_close:].any():
        raise ValueError("The episode never closes the hand and moves it: no missed grasp to cut.")
    return first_close + int(np.argmax((closed & moving)[first_close:]))


def episode_frames(dataset, episode: int) -> list[dict]:
    meta = dataset.meta.episodes[episode]
    return [dataset[i] for i in range(meta["dataset_from_index"], meta["dataset_to_index"])]


def as_stored(frame: dict, camera_keys: list[str]) -> dict:
    """A dataset item as `add_frame` takes it: images (H, W, 3) uint8, the rest float32 arrays."""
    out = {key: torch.round(frame[key] * 255).to(torch.uint8).permute(1, 2, 0).numpy() for key in camera_keys}
    out["observation.state"] = frame["observation.state"].numpy().astype(np.float32)
    out["action"] = frame["action"].numpy().astype(np.float32)
    out["task"] = frame["task"]
    return out


def cut(source: Path, work: Path, tasks: list[int]) -> None:
    from lerobot.datasets import LeRobotDataset

    for task in tasks:
        src = source / "data" / piece_name(task, 0, RECOVER)
        dst = work / "data" / piece_name(task, 0, RECOVER_RISE)
        if (dst / "meta" / "recording_report.json").exists():
            print(f"cut: {dst} exists")
            continue
        if dst.exists():
            shutil.rmtree(dst)  # an interrupted cut
        source_report = json.loads((src / "meta" / "recording_report.json").read_text())
        dataset = LeRobotDataset(source_report["repo_id"], root=src)
        camera_keys = [key for key, ft in dataset.meta.features.items() if ft["dtype"] == "video"]
        # The recorder's features (`dataset_features`), without the ones LeRobot adds (index, timestamp, ...).
        features = {
            key: {name: ft[name] for name in ("dtype", "shape", "names")}
            for key, ft in dataset.meta.features.items()
            if key in [*camera_keys, "observation.state", "action"]
        }
        out = LeRobotDataset.create(
            repo_id=f"local/libero_object_{dst.name}",
            fps=dataset.meta.fps,
            features=features,
            root=dst,
            robot_type=dataset.meta.robot_type,
            use_videos=True,
        )
        cuts = []
        for episode in range(dataset.meta.total_episodes):
            frames = episode_frames(dataset, episode)
            first = rise_start(np.stack([f["action"].numpy() for f in frames]))
            for frame in frames[first:]:
                out.add_frame(as_stored(frame, camera_keys))
            out.save_episode()
            cuts.append({"episode": episode, "frames": len(frames), "first_kept": first})
            print(
                f"cut: task {task} episode {episode}: frames {first}-{len(frames) - 1} kept of {len(frames)}"
            )
        out.finalize()
        report = {
            **source_report,
            "repo_id": f"local/libero_object_{dst.name}",
            "store_missed_grasp": False,
            "cut_from": str(src),
            "cuts": cuts,
        }
        (dst / "meta" / "recording_report.json").write_text(json.dumps(report, indent=2))


def check(work: Path, task: int) -> dict:
    """Records attempt 0 of the task's recovery piece with the package's recorder; compares with the cut episode 0."""
    from lerobot.datasets import LeRobotDataset

    cut_root = work / "data" / piece_name(task, 0, RECOVER_RISE)
    cut_report = json.loads((cut_root / "meta" / "recording_report.json").read_text())
    recorded_root = work / "check" / piece_name(task, 0, RECOVER_RISE)
    if not (recorded_root / "meta" / "recording_report.json").exists():
        cmd = [
            bin_path("ebvla-record-libero"),
            f"--env.task={SUITE}",
            f"--env.task_ids=[{task}]",
            "--episodes_per_task=1",
            f"--image_size={cut_report['image_size']}",
            f"--repo_id=local/check_{recorded_root.name}",
            f"--root={recorded_root}",
            "--overwrite=true",
            "--use_videos=true",
            f"--placement_seed={RECOVERY_PLACEMENT_SEED}",
            f"--env.robot_init_noise={FIXED_STATES_ARM_NOISE}",
            "--regrasp=true",
            f"--miss_first_grasp={RECOVERY_MISS}",
            "--store_missed_grasp=false",
        ]
        subprocess.run(cmd, check=True)
    recorded = LeRobotDataset(f"local/check_{recorded_root.name}", root=recorded_root)
    trimmed = LeRobotDataset(cut_report["repo_id"], root=cut_root)
    a, b = episode_frames(recorded, 0), episode_frames(trimmed, 0)
    camera_keys = [key for key, ft in recorded.meta.features.items() if ft["dtype"] == "video"]
    result = {
        "task": task,
        "frames_recorded": len(a),
        "frames_cut": len(b),
        "max_abs_state_difference": float(
            max(
                (x["observation.state"] - y["observation.state"]).abs().max()
                for x, y in zip(a, b, strict=False)
            )
        ),
        "max_abs_action_difference": float(
            max((x["action"] - y["action"]).abs().max() for x, y in zip(a, b, strict=False))
        ),
        "max_mean_abs_pixel_difference": float(
            max((x[k] - y[k]).abs().mean() * 255 for x, y in zip(a, b, strict=False) for k in camera_keys)
        ),
    }
    result["equal"] = (
        result["frames_recorded"] == result["frames_cut"]
        and result["max_abs_state_difference"] < 1e-6
        and result["max_abs_action_difference"] == 0
        and result["max_mean_abs_pixel_difference"] < CODEC_TOLERANCE
    )
    (work / "check" / f"check_task{task}.json").write_text(json.dumps(result, indent=2))
    print(json.dumps(result, indent=2))
    return result


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("stage", choices=["cut", "check"])
    parser.add_argument("--source", type=Path, default=Path("research/results/libero_object10_recover"))
    parser.add_argument("--work", type=Path, required=True)
    parser.add_argument("--tasks", type=int, nargs="+", default=[1, 5])
    parser.add_argument("--task", type=int, default=5)
    args = parser.parse_args()
    if args.stage == "cut":
        cut(args.source, args.work, args.tasks)
    else:
        check(args.work, args.task)


if __name__ == "__main__":
    main()
