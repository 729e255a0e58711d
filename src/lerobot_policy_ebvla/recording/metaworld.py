"""Recording MetaWorld's scripted experts as a LeRobotDataset (`ebvla-record-metaworld`).

Each episode is rolled out in LeRobot's MetaWorld env (through `--env.type=metaworld_ebvla`, so fast rendering
and perturbations are the same options as in evaluation) with the task's scripted expert policy. The dataset has
exactly the features LeRobot's `metaworld` env gives a policy (`observation.image`, `observation.state`,
`action`) and the task instruction, so a policy trained on it evaluates with `lerobot-eval --env.type=metaworld`
(or `ebvla-eval`) unchanged.

Images are rendered at 480x480 (as in evaluation) and stored resized to `image_size` with antialiased bilinear
interpolation; the policy must resize evaluation frames the same way (EB-VLA's light backbone:
`--policy.resnet.resize_shape=[128,128]` for the default `image_size`).

Every attempted episode (task, seed, success, length) is logged and written to
`<root>/meta/recording_report.json`. Failed expert episodes are left out unless `keep_failed`.
"""

import logging
from collections.abc import Generator
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch
from lerobot.envs.utils import env_to_policy_features
from lerobot.utils.constants import ACTION, OBS_IMAGE, OBS_STATE
from torchvision.transforms.v2 import functional as tvf

from ..envs import MetaworldEBVLAEnv
from .loop import (
    Episode,
    RecordingConfig,
    check_env_records_images_and_state,
    episode_counts,
    format_report,
    prepare_root,
    record_episodes,
    write_report,
)

# Names of the 4-d state (`agent_pos`: end-effector position and gripper opening) and action.
STATE_NAMES = ["hand_x", "hand_y", "hand_z", "gripper_distance"]
ACTION_NAMES = ["delta_x", "delta_y", "delta_z", "gripper_effort"]


@dataclass
class RecordMetaworldConfig(RecordingConfig):
    # The env: tasks (`--env.task=reach-v3,push-v3` or a difficulty group such as `easy`), fast rendering
    # (`--env.fast_render=true`), camera perturbation and severity, episode step limit.
    env: MetaworldEBVLAEnv = field(default_factory=MetaworldEBVLAEnv)
    # Dataset repo id (stored locally; nothing is pushed).
    repo_id: str = "local/metaworld_expert"
    # Episode i of every task is seeded with `seed + i` (lerobot-eval's seeds start at 1000: keep clear).
    seed: int = 0
    # Side of the square images stored; frames are rendered at 480x480 and resized with antialiasing.
    image_size: int = 128

    def __post_init__(self):
        super().__post_init__()
        check_env_records_images_and_state(self.env)
        if self.image_size < 8:
            raise ValueError(f"`image_size` must be >= 8, got {self.image_size}.")


def dataset_features(env_cfg: MetaworldEBVLAEnv, image_size: int, use_videos: bool) -> dict[str, dict]:
    """LeRobotDataset features with the keys LeRobot's MetaWorld env gives a policy, images resized."""
    features = {}
    for key, feature in env_to_policy_features(env_cfg).items():
        if key == OBS_IMAGE:
            features[key] = {
                "dtype": "video" if use_videos else "image",
                "shape": (image_size, image_size, 3),
                "names": ["height", "width", "channels"],
            }
        elif key in (OBS_STATE, ACTION):
            names = STATE_NAMES if key == OBS_STATE else ACTION_NAMES
            features[key] = {"dtype": "float32", "shape": tuple(feature.shape), "names": names}
        else:
            raise ValueError(
                f"Unexpected MetaWorld feature {key!r}: this recorder knows {OBS_IMAGE}, "
                f"{OBS_STATE} and {ACTION}."
            )
    return features


def resize_image(image: np.ndarray, size: int) -> np.ndarray:
    """Resizes an (H, W, 3) uint8 frame to (size, size, 3) with antialiased bilinear interpolation.

    This is torchvision's resize, the one LeRobot's image encoders (and EB-VLA's `resnet.resize_shape`) apply to
    evaluation frames.
    """
    if image.shape[:2] == (size, size):
        return image
    chw = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)
    resized = tvf.resize(chw, [size, size], interpolation=tvf.InterpolationMode.BILINEAR, antialias=True)
    return resized.permute(1, 2, 0).numpy()


def record_expert_episode(env: Any, dataset: Any, seed: int, image_size: int) -> tuple[bool, int]:
    """Rolls out the env's scripted expert once, adding every frame to the dataset's episode buffer.

    Args:
        env: A `MetaworldEBVLAGymEnv`.
        dataset: A LeRobotDataset in write mode; the caller saves or discards the episode.
        seed: Seed of the episode (object and goal positions).
        image_size: Side of the stored images.

    Returns:
        (success, number of steps).
    """
    observation, _ = env.reset(seed=seed)
    success = False
    n_steps = 0
    while n_steps < env._max_episode_steps:
        # The experts' gains can exceed the action space, which MetaWorld clips anyway: store what is executed.
        expert_action = env.expert_policy.get_action(env.state_obs)
        action = np.clip(expert_action, env.action_space.low, env.action_space.high).astype(np.float32)
        dataset.add_frame(
            {
                OBS_IMAGE: resize_image(observation["pixels"], image_size),
                OBS_STATE: observation["agent_pos"].astype(np.float32),
                ACTION: action,
                "task": env.task_description,
            }
        )
        observation, _, terminated, truncated, info = env.step(action)
        n_steps += 1
        success = bool(info["is_success"])
        if terminated or truncated:
            break
    return success, n_steps


def expert_episodes(
    cfg: RecordMetaworldConfig, tasks: list[str], dataset: Any
) -> Generator[Episode, None, None]:
    """The episodes `cfg` asks for, task by task; each task's env is open while its episodes are recorded."""
    from ..envs.metaworld import MetaworldEBVLAGymEnv

    for task in tasks:
        env = MetaworldEBVLAGymEnv(task=task, **cfg.env.gym_kwargs)
        try:
            for attempt in range(cfg.episodes_per_task):
                seed = cfg.seed + attempt
                yield Episode(
                    task=task,
                    start={"attempt": attempt, "seed": seed},
                    label=f"{task} seed {seed}",
                    rollout=partial(record_expert_episode, env, dataset, seed, cfg.image_size),
                )
        finally:
            env.close()


def record_metaworld(cfg: RecordMetaworldConfig) -> dict:
    """Records the dataset described by `cfg` and returns the report written to `meta/recording_report.json`."""
    from lerobot.datasets import LeRobotDataset

    from ..envs.metaworld import task_groups

    root = Path(cfg.root)
    prepare_root(root, cfg.overwrite)
    tasks = [name for names in task_groups(cfg.env.task).values() for name in names]
    dataset = LeRobotDataset.create(
        repo_id=cfg.repo_id,
        fps=cfg.env.fps,
        features=dataset_features(cfg.env, cfg.image_size, cfg.use_videos),
        root=root,
        robot_type="sawyer",
        use_videos=cfg.use_videos,
    )
    episodes = record_episodes(dataset, expert_episodes(cfg, tasks, dataset), cfg.keep_failed)
    report = {
        "repo_id": cfg.repo_id,
        "env": {
            "type": cfg.env.type,
            "task": cfg.env.task,
            "fast_render": cfg.env.fast_render,
            "camera_perturbation": cfg.env.camera_perturbation,
            "perturbation_severity": cfg.env.perturbation_severity,
            "max_episode_steps": cfg.env.max_episode_steps,
        },
        "image_size": cfg.image_size,
        "use_videos": cfg.use_videos,
        "keep_failed": cfg.keep_failed,
        **episode_counts(episodes),
        "episodes": [ep.to_dict() for ep in episodes],
    }
    write_report(root, report)
    logging.info("Recorded %s at %s\n%s", cfg.repo_id, root, format_report(episodes))
    return report
