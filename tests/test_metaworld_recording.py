"""Recording MetaWorld expert demonstrations, training on them and evaluating with energy records."""

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("metaworld")
os.environ.setdefault("MUJOCO_GL", "egl")

from lerobot.envs.configs import MetaworldEnv as LeRobotMetaworldEnvConfig  # noqa: E402
from lerobot.envs.utils import env_to_policy_features  # noqa: E402

from lerobot_policy_ebvla.envs import MetaworldEBVLAEnv  # noqa: E402
from lerobot_policy_ebvla.monitoring.records import read_energy_records  # noqa: E402
from lerobot_policy_ebvla.recording.loop import REPORT_FILENAME  # noqa: E402
from lerobot_policy_ebvla.recording.metaworld import RecordMetaworldConfig, record_metaworld  # noqa: E402

TASK = "reach-v3"  # the expert finishes in about 50 steps
IMAGE_SIZE = 64  # the light backbone needs more than 32 px
N_ACTION_STEPS = 4
EVAL_STEPS = 10


def record(root: Path, **overrides) -> dict:
    env_overrides = overrides.pop("env", {})
    env = MetaworldEBVLAEnv(task=TASK, fast_render=True, **env_overrides)
    cfg = RecordMetaworldConfig(
        env=env, repo_id="local/reach", root=root, episodes_per_task=1, image_size=IMAGE_SIZE, **overrides
    )
    return record_metaworld(cfg)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> tuple[Path, dict]:
    root = tmp_path_factory.mktemp("data") / "reach"
    return root, record(root, seed=3)


def test_recorded_dataset_has_the_features_of_lerobots_metaworld_env(recorded):
    from lerobot.datasets import LeRobotDataset

    root, _ = recorded
    dataset = LeRobotDataset("local/reach", root=root)
    env_features = env_to_policy_features(LeRobotMetaworldEnvConfig(task=TASK))
    assert set(env_features) <= set(dataset.features)
    assert set(dataset.features) - set(env_features) == {
        "timestamp",
        "frame_index",
        "episode_index",
        "index",
        "task_index",
    }
    frame = dataset[0]
    assert frame["observation.image"].shape == (3, IMAGE_SIZE, IMAGE_SIZE)
    assert frame["observation.state"].shape == env_features["observation.state"].shape
    assert frame["action"].shape == env_features["action"].shape
    assert frame["task"] == "Reach a goal position"


def test_report_lists_every_episode_with_its_seed_success_and_length(recorded):
    from lerobot.datasets import LeRobotDataset

    root, report = recorded
    on_disk = json.loads((root / "meta" / REPORT_FILENAME).read_text())
    assert on_disk == json.loads(json.dumps(report))
    (episode,) = report["episodes"]
    assert episode["task"] == TASK and episode["seed"] == 3 and episode["success"] and episode["kept"]
    dataset = LeRobotDataset("local/reach", root=root)
    assert dataset.num_episodes == 1
    assert dataset.num_frames == episode["n_steps"]


def test_expert_actions_are_in_the_action_space(recorded):
    from lerobot.datasets import LeRobotDataset

    dataset = LeRobotDataset("local/reach", root=recorded[0])
    actions = np.stack([dataset[i]["action"].numpy() for i in range(dataset.num_frames)])
    assert np.all(np.abs(actions) <= 1.0)


def test_refuses_to_overwrite_an_existing_dataset(recorded):
    with pytest.raises(FileExistsError, match="--overwrite"):
        record(recorded[0])


def test_failed_episodes_are_reported_and_left_out_unless_kept(tmp_path):
    # Five steps are too few for the expert: the episode fails.
    report = record(tmp_path / "short", env={"max_episode_steps": 5})
    (episode,) = report["episodes"]
    assert not episode["success"] and not episode["kept"] and episode["n_steps"] == 5
    assert report["n_kept"] == 0

    report = record(tmp_path / "short", env={"max_episode_steps": 5}, keep_failed=True, overwrite=True)
    assert report["episodes"][0]["kept"] and report["n_kept"] == 1


def run_cli(args: list[str], cwd: Path) -> None:
    result = subprocess.run(
        [sys.executable, "-m", *args], cwd=cwd, capture_output=True, text=True, timeout=600, check=False
    )
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-5000:]


@pytest.mark.slow
def test_train_then_eval_writes_one_energy_record_per_chunk(recorded, tmp_path):
    root, _ = recorded
    train_dir = tmp_path / "train"
    run_cli(
        [
            "lerobot.scripts.lerobot_train",
            "--dataset.repo_id=local/reach",
            f"--dataset.root={root}",
            "--policy.type=ebvla",
            "--policy.backbone=resnet",
            "--policy.dim_model=64",
            "--policy.n_heads=2",
            "--policy.n_blocks=1",
            f"--policy.n_action_steps={N_ACTION_STEPS}",
            f"--policy.resnet.resize_shape=[{IMAGE_SIZE},{IMAGE_SIZE}]",
            "--policy.device=cpu",
            "--policy.push_to_hub=false",
            "--steps=2",
            "--batch_size=4",
            "--num_workers=0",
            "--save_freq=2",
            "--wandb.enable=false",
            f"--output_dir={train_dir}",
        ],
        cwd=tmp_path,
    )
    eval_dir = tmp_path / "eval"
    run_cli(
        [
            "lerobot_policy_ebvla.scripts.eval_energy",
            f"--policy.path={train_dir / 'checkpoints' / 'last' / 'pretrained_model'}",
            "--policy.device=cpu",
            "--env.type=metaworld_ebvla",
            f"--env.task={TASK}",
            "--env.fast_render=true",
            "--env.camera_perturbation=fov",
            "--env.perturbation_severity=2",
            f"--env.max_episode_steps={EVAL_STEPS}",
            "--eval.n_episodes=1",
            "--eval.batch_size=1",
            f"--output_dir={eval_dir}",
        ],
        cwd=tmp_path,
    )
    assert (eval_dir / "eval_info.json").is_file()
    records = read_energy_records(eval_dir)
    assert {r.episode_index for r in records} == {0}
    assert all(
        r.task == TASK and r.seed == 1000 and r.perturbation == "fov" and r.severity == 2.0 for r in records
    )
    assert [r.chunk_index for r in records] == list(range(len(records)))
    assert [r.env_step for r in records] == [N_ACTION_STEPS * k for k in range(len(records))]
    assert all(math.isfinite(r.initial_energy) and math.isfinite(r.final_energy) for r in records)
    success = json.loads((eval_dir / "eval_info.json").read_text())["per_task"][0]["metrics"]["successes"][0]
    assert {r.success for r in records} == {success}
    # A failed episode runs all EVAL_STEPS steps; a successful one ends earlier, with fewer chunks.
    max_chunks = math.ceil(EVAL_STEPS / N_ACTION_STEPS)
    assert len(records) == max_chunks if not success else len(records) <= max_chunks
