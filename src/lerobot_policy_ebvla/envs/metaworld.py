"""LeRobot's MetaWorld gym env with fast rendering and camera perturbations (`--env.type=metaworld_ebvla`).

`MetaworldEBVLAGymEnv` is LeRobot's `MetaworldEnv` with two scene edits applied to the MuJoCo model right after
the simulator is built (inside the worker process of an async vector env):

- `disable_shadows_and_reflections`: the fast-render setting.
- `perturb_camera`: LIBERO-Plus-style camera pose and field-of-view changes at graded severities.

Observations are LeRobot's (`pixels` 480x480 from `corner2`, `agent_pos`), so observation keys and shapes
do not change.
"""

from collections.abc import Callable, Sequence
from functools import partial
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np
from lerobot.envs.metaworld import DIFFICULTY_TO_TASKS, MetaworldEnv
from lerobot.envs.utils import _LazyAsyncVectorEnv

# Per severity level: degrees of azimuth and elevation of the "pose" orbit, relative widening of "fov".
AZIMUTH_DEG_PER_LEVEL = 5.0
ELEVATION_DEG_PER_LEVEL = 3.0
FOVY_GROWTH_PER_LEVEL = 0.10
# MetaWorld's table top is the z = 0 plane; the "pose" orbit pivots where the optical axis meets it.
TABLE_HEIGHT = 0.0


def disable_shadows_and_reflections(model: mujoco.MjModel) -> None:
    """Turns off shadow casting and mirror reflections, the two most expensive parts of MuJoCo's renderer.

    Rendering at 480x480 goes from about 5 to 18 frames per second on a CPU (EGL, software rasterizer).
    """
    model.light_castshadow[:] = 0
    model.mat_reflectance[:] = 0.0


def _rotation_quat(axis: np.ndarray, angle_deg: float) -> np.ndarray:
    quat = np.zeros(4)
    mujoco.mju_axisAngle2Quat(quat, axis / np.linalg.norm(axis), np.deg2rad(angle_deg))
    return quat


def orbit_camera(model: mujoco.MjModel, camera_id: int, azimuth_deg: float, elevation_deg: float) -> None:
    """Orbits a fixed world camera around the point of the table it looks at, keeping that point centred.

    Args:
        model: The MuJoCo model, edited in place.
        camera_id: Index of a camera attached to the world body.
        azimuth_deg: Rotation about the vertical axis through the pivot (counter-clockwise seen from above).
        elevation_deg: Rotation that raises the camera (positive) or lowers it towards the table.
    """
    if model.cam_bodyid[camera_id] != 0:
        raise ValueError("Only cameras attached to the world body can be orbited.")
    position = model.cam_pos[camera_id].copy()
    orientation = model.cam_quat[camera_id].copy()
    # A MuJoCo camera looks along its local -z axis.
    forward = np.zeros(3)
    mujoco.mju_rotVecQuat(forward, np.array([0.0, 0.0, -1.0]), orientation)
    if forward[2] >= 0:
        raise ValueError("The camera does not look down at the table, so it has no pivot to orbit around.")
    pivot = position + (TABLE_HEIGHT - position[2]) / forward[2] * forward
    offset = position - pivot
    # Raising the camera is a rotation about the horizontal axis orthogonal to the pivot->camera direction.
    elevation_axis = np.cross(offset, np.array([0.0, 0.0, 1.0]))
    rotation = np.zeros(4)
    mujoco.mju_mulQuat(
        rotation,
        _rotation_quat(np.array([0.0, 0.0, 1.0]), azimuth_deg),
        _rotation_quat(elevation_axis, elevation_deg),
    )
    rotated_offset = np.zeros(3)
    mujoco.mju_rotVecQuat(rotated_offset, offset, rotation)
    new_orientation = np.zeros(4)
    mujoco.mju_mulQuat(new_orientation, rotation, orientation)
    model.cam_pos[camera_id] = pivot + rotated_offset
    model.cam_quat[camera_id] = new_orientation


def perturb_camera(model: mujoco.MjModel, camera_name: str, kind: str, severity: int) -> None:
    """Applies a LIBERO-Plus-style camera perturbation of a given severity to a camera of `model`.

    Args:
        model: The MuJoCo model, edited in place.
        camera_name: The camera observations are rendered from (LeRobot's MetaWorld env uses "corner2").
        kind: "none", "pose" (orbit the camera), "fov" (widen its field of view) or "pose_fov" (both).
        severity: 0 (no change) to 5; the change grows linearly with it.
    """
    if kind not in ("none", "pose", "fov", "pose_fov"):
        raise ValueError(f"Unknown camera perturbation {kind!r}.")
    if kind == "none" or severity == 0:
        return
    camera_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera_name)
    if camera_id < 0:
        raise ValueError(f"The scene has no camera named {camera_name!r}.")
    if kind in ("pose", "pose_fov"):
        orbit_camera(model, camera_id, AZIMUTH_DEG_PER_LEVEL * severity, ELEVATION_DEG_PER_LEVEL * severity)
    if kind in ("fov", "pose_fov"):
        model.cam_fovy[camera_id] *= 1.0 + FOVY_GROWTH_PER_LEVEL * severity


class MetaworldEBVLAGymEnv(MetaworldEnv):
    """LeRobot's MetaWorld env with the scene edits of `MetaworldEBVLAEnv` (see its docstring for the args).

    It also keeps MetaWorld's 39-d state of the last observation (`state_obs`), which the scripted expert
    policies (`expert_policy.get_action(state_obs)`) act on.
    """

    def __init__(
        self,
        task: str,
        fast_render: bool = False,
        camera_perturbation: str = "none",
        perturbation_severity: int = 0,
        max_episode_steps: int | None = None,
        **kwargs: Any,
    ):
        super().__init__(task, **kwargs)
        self.fast_render = fast_render
        self.camera_perturbation = camera_perturbation
        self.perturbation_severity = perturbation_severity
        if max_episode_steps is not None:
            self._max_episode_steps = max_episode_steps
        self.state_obs: np.ndarray | None = None

    def _ensure_env(self) -> None:
        if self._env is not None:
            return
        super()._ensure_env()
        model = self._env.model
        if self.fast_render:
            disable_shadows_and_reflections(model)
        perturb_camera(model, self.camera_name, self.camera_perturbation, self.perturbation_severity)

    def _format_raw_obs(self, raw_obs: np.ndarray) -> dict[str, Any]:
        self.state_obs = raw_obs
        return super()._format_raw_obs(raw_obs)


def task_groups(task: str) -> dict[str, list[str]]:
    """Expands LeRobot's MetaWorld `task` string into {group: [task names]}, as `create_metaworld_envs` does.

    `task` is a comma-separated list of MetaWorld v3 tasks (e.g. "reach-v3,push-v3") or difficulty groups
    ("easy", "medium", "hard", "very_hard"); a task is its own group.
    """
    groups = [t.strip() for t in task.split(",") if t.strip()]
    if not groups:
        raise ValueError("`task` must contain at least one Meta-World task or difficulty group.")
    return {group: DIFFICULTY_TO_TASKS.get(group, [group]) for group in groups}


def create_metaworld_ebvla_envs(
    task: str,
    n_envs: int,
    gym_kwargs: dict[str, Any],
    env_cls: Callable[[Sequence[Callable[[], Any]]], Any],
) -> dict[str, dict[int, Any]]:
    """`lerobot.envs.metaworld.create_metaworld_envs` for `MetaworldEBVLAGymEnv`: {group: {task_id: vec_env}}."""
    if not isinstance(n_envs, int) or n_envs <= 0:
        raise ValueError(f"n_envs must be a positive int; got {n_envs}.")
    envs: dict[str, dict[int, Any]] = {}
    for group, tasks in task_groups(task).items():
        envs[group] = {}
        for task_id, task_name in enumerate(tasks):
            env_fns = [partial(MetaworldEBVLAGymEnv, task=task_name, **gym_kwargs) for _ in range(n_envs)]
            # LeRobot's lazy async env only starts its worker processes when the task is evaluated.
            is_async = env_cls is gym.vector.AsyncVectorEnv
            envs[group][task_id] = _LazyAsyncVectorEnv(env_fns) if is_async else env_cls(env_fns)
    return envs
