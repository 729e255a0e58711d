"""LeRobot's MetaWorld gym env with fast rendering and graded perturbations (`--env.type=metaworld_ebvla`).

`MetaworldEBVLAGymEnv` is LeRobot's `MetaworldEnv` with scene edits applied to the MuJoCo model right after
the simulator is built (inside the worker process of an async vector env):

- `disable_shadows_and_reflections`: the fast-render setting.
- `perturb_model`: LIBERO-Plus-style camera (pose, field of view), lighting and table/background edits.

and three perturbations applied while the env runs: `perturb_image` (sensor noise, blur, blackout) on every
observation, `distractor_markers` (extra objects drawn into every rendered frame) and `displaced_hand_position`
(the hand starts elsewhere after each reset). Every perturbation is graded by a severity 1..5 (0: none); the
per-level magnitudes are the constants below, tabulated in docs/metaworld.md.

Observations are LeRobot's (`pixels` 480x480 from `corner2`, `agent_pos`), so observation keys and shapes
do not change, unless `observation_size` renders smaller frames (a policy that sees 64 px needs no 480 px
frame, and the renderer's time falls with the pixels it fills).
"""

import os
import weakref
from collections.abc import Callable, Sequence
from functools import partial
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np
from lerobot.envs.metaworld import DIFFICULTY_TO_TASKS, MetaworldEnv

from ..lerobot_private import lazy_async_vector_env
from .frames import FrameGate
from .lighting import LIGHT_INTENSITY_PERTURBATIONS, perturb_light_intensity
from .perturbations import CAMERA_PERTURBATIONS, MAX_SEVERITY, check_perturbation
from .sensor import perturb_image

# Camera. Per severity level: degrees of azimuth and elevation of the "pose" orbit, relative widening of "fov".
AZIMUTH_DEG_PER_LEVEL = 5.0
ELEVATION_DEG_PER_LEVEL = 3.0
FOVY_GROWTH_PER_LEVEL = 0.10
# MetaWorld's table top is the z = 0 plane; the "pose" orbit pivots where the optical axis meets it.
TABLE_HEIGHT = 0.0

# Lighting: intensity and colour of every light (the three scene lights and the headlight) in envs/lighting.py.
# "light_direction": the direction of every scene light moves linearly (then renormalized) from its own to
# this low, grazing direction (from the robot's left, 14 degrees above the table), reached at severity 5.
LIGHT_GRAZING_DIR = (1.0, 0.0, -0.25)

# Table/background appearance. "table_color": the colour multiplying the table's wood texture and the
# floor/wall materials moves linearly towards these tints (reached at severity 5); the sky behind the scene
# (the skybox texture) is multiplied by the same kind of tint.
TABLE_MATERIAL = "table_wood"
MATERIAL_TINTS = {
    TABLE_MATERIAL: (0.25, 0.45, 1.0),  # blue table
    "basic_floor": (1.0, 0.45, 0.55),  # pink floor and walls
    "wall_metal": (1.0, 0.45, 0.55),
}
SKY_TINT_RGB = (0.55, 0.8, 1.0)  # light blue sky
# "table_texture": the table's wood texture is blended with a black-and-white checkerboard, by 0.2 per level.
CHECKER_BLEND_PER_LEVEL = 0.2
CHECKER_SQUARE_TEXELS = 32

# Distractors: severity s draws the first s of these objects on the table (geom type, centre xyz in metres,
# MuJoCo size, rgba); each is 8-16 cm across, about the size of MetaWorld's task objects.
# They are drawn into the rendered frames only: they are not part of the physics and collide with nothing.
DISTRACTORS = (
    (mujoco.mjtGeom.mjGEOM_BOX, (-0.2, 0.55, 0.05), (0.05, 0.05, 0.05), (0.95, 0.85, 0.1, 1.0)),
    (mujoco.mjtGeom.mjGEOM_CYLINDER, (0.2, 0.6, 0.06), (0.045, 0.06, 0.0), (0.1, 0.3, 0.95, 1.0)),
    (mujoco.mjtGeom.mjGEOM_SPHERE, (-0.15, 0.85, 0.05), (0.05, 0.05, 0.05), (0.6, 0.2, 0.8, 1.0)),
    (mujoco.mjtGeom.mjGEOM_BOX, (0.25, 0.85, 0.04), (0.08, 0.04, 0.04), (1.0, 0.5, 0.0, 1.0)),
    (mujoco.mjtGeom.mjGEOM_CAPSULE, (0.0, 0.45, 0.11), (0.04, 0.07, 0.0), (1.0, 0.4, 0.7, 1.0)),
)

# Robot initial state: the hand's reset position moves by this many metres per level, in a random direction
# (drawn per episode from the reset seed) that never points down towards the objects.
HAND_OFFSET_M_PER_LEVEL = 0.03


def disable_shadows_and_reflections(model: mujoco.MjModel) -> None:
    """Turns off shadow casting and mirror reflections, the two most expensive parts of MuJoCo's renderer.

    Rendering at 480x480 goes from about 5 to 18 frames per second on a CPU (EGL, software rasterizer).
    """
    model.light_castshadow[:] = 0
    model.mat_reflectance[:] = 0.0


def free_offscreen_viewers(renderer: Any) -> None:
    """Frees each offscreen viewer's `MjrContext` inside the viewer's own GL context.

    Gymnasium's viewer destroys its GL context on close and leaves the `MjrContext` to the garbage collector. Its
    `mjr_freeContext` then deletes GL objects by their numbers in whatever context is current at that moment:
    another env's, whose offscreen framebuffer carries the same numbers, so that env renders black from then on
    (seen in a long process that closes one evaluation's envs and renders the next).

    Args:
        renderer: A Gymnasium `MujocoRenderer` (a MuJoCo env's `mujoco_renderer`).
    """
    for viewer in getattr(renderer, "_viewers", {}).values():
        if hasattr(viewer, "con"):
            viewer.make_context_current()
            # Sets the struct to its defaults, so the collector's later `mjr_freeContext` deletes nothing.
            viewer.con.free()


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
    if kind != "none" and kind not in CAMERA_PERTURBATIONS:
        raise ValueError(f"Unknown camera perturbation {kind!r}; expected one of {CAMERA_PERTURBATIONS}.")
    if kind == "none" or severity == 0:
        return
    camera_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera_name)
    if camera_id < 0:
        raise ValueError(f"The scene has no camera named {camera_name!r}.")
    if kind in ("pose", "pose_fov"):
        orbit_camera(model, camera_id, AZIMUTH_DEG_PER_LEVEL * severity, ELEVATION_DEG_PER_LEVEL * severity)
    if kind in ("fov", "pose_fov"):
        model.cam_fovy[camera_id] *= 1.0 + FOVY_GROWTH_PER_LEVEL * severity


def turn_lights(model: mujoco.MjModel, fraction: float) -> None:
    """Turns every scene light towards `LIGHT_GRAZING_DIR` by `fraction` (the headlight follows the camera).

    The lights of MetaWorld's scene are directional, so only their direction matters, not their position.
    """
    target = np.asarray(LIGHT_GRAZING_DIR) / np.linalg.norm(LIGHT_GRAZING_DIR)
    for light_id in range(model.nlight):
        direction = (1.0 - fraction) * model.light_dir[light_id] + fraction * target
        model.light_dir[light_id] = direction / np.linalg.norm(direction)


def _material_id(model: mujoco.MjModel, name: str) -> int:
    material_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_MATERIAL, name)
    if material_id < 0:
        raise ValueError(f"The scene has no material named {name!r}; is it a MetaWorld scene?")
    return material_id


def tint_table_and_background(model: mujoco.MjModel, fraction: float) -> None:
    """Moves the colour of the table, floor, walls and sky towards their tints by `fraction` (0 to 1).

    A material's rgba multiplies its texture, so the wood grain stays visible under the new colour. Textures
    are uploaded to the renderer when its context is created (the first render), so this must run before the
    first frame, as `MetaworldEBVLAGymEnv` does.
    """
    for name, tint in MATERIAL_TINTS.items():
        rgb = model.mat_rgba[_material_id(model, name), :3]
        rgb += fraction * (np.asarray(tint) - rgb)
    sky_factor = 1.0 + fraction * (np.asarray(SKY_TINT_RGB) - 1.0)
    for texture_id in np.flatnonzero(model.tex_type == mujoco.mjtTexture.mjTEXTURE_SKYBOX):
        texels = _texels(model, texture_id)
        texels[:] = np.round(texels * sky_factor).astype(np.uint8)


def _texels(model: mujoco.MjModel, texture_id: int) -> np.ndarray:
    """A writable (height, width, channels) view of a texture's data in `model.tex_data`."""
    texture = model.texture(texture_id)
    height, width, channels = texture.height[0], texture.width[0], texture.nchannel[0]
    start = texture.adr[0]
    return model.tex_data[start : start + height * width * channels].reshape(height, width, channels)


def checker_table(model: mujoco.MjModel, fraction: float) -> None:
    """Blends the table's texture with a black-and-white checkerboard: 0 keeps the wood, 1 is the board.

    Like `tint_table_and_background`, it must run before the first frame is rendered.
    """
    texture_id = model.mat_texid[_material_id(model, TABLE_MATERIAL), mujoco.mjtTextureRole.mjTEXROLE_RGB]
    if texture_id < 0:
        raise ValueError(f"The material {TABLE_MATERIAL!r} has no texture.")
    texels = _texels(model, texture_id)
    rows, cols = np.indices(texels.shape[:2]) // CHECKER_SQUARE_TEXELS
    board = np.where((rows + cols)[..., None] % 2 == 0, 235.0, 20.0)
    texels[:] = np.round((1.0 - fraction) * texels + fraction * board).astype(np.uint8)


def perturb_model(model: mujoco.MjModel, camera_name: str, perturbation: str, severity: int) -> None:
    """Applies the camera, lighting and table/background perturbations to `model`; others leave it alone.

    Args:
        model: The MuJoCo model, edited in place, before the first frame is rendered.
        camera_name: The camera observations are rendered from (LeRobot's MetaWorld env uses "corner2").
        perturbation: A name of `perturbations.PERTURBATIONS`.
        severity: 0 (no change) to 5; every change grows linearly with it.
    """
    check_perturbation(perturbation, severity)
    level = severity / MAX_SEVERITY
    if perturbation in CAMERA_PERTURBATIONS:
        perturb_camera(model, camera_name, perturbation, severity)
    elif perturbation in LIGHT_INTENSITY_PERTURBATIONS:
        perturb_light_intensity(model, perturbation, severity, MAX_SEVERITY)
    elif perturbation == "light_direction":
        turn_lights(model, level)
    elif perturbation == "table_color":
        tint_table_and_background(model, level)
    elif perturbation == "table_texture":
        checker_table(model, CHECKER_BLEND_PER_LEVEL * severity)


def distractor_markers(severity: int) -> list[dict[str, Any]]:
    """The first `severity` objects of `DISTRACTORS`, as marker arguments of Gymnasium's MuJoCo renderer."""
    return [
        {"type": geom_type, "pos": np.array(pos), "size": np.array(size), "rgba": np.array(rgba)}
        for geom_type, pos, size, rgba in DISTRACTORS[:severity]
    ]


def displaced_hand_position(
    hand_init_pos: np.ndarray, severity: int, rng: np.random.Generator, low: np.ndarray, high: np.ndarray
) -> np.ndarray:
    """The hand's reset position moved by `HAND_OFFSET_M_PER_LEVEL * severity` metres in a random direction.

    The direction is uniform on the upper half sphere (the hand is never pushed down into the objects); an
    axis on which the move would leave MetaWorld's mocap box [low, high] is reversed, then clipped.
    """
    direction = rng.normal(size=3)
    direction[2] = abs(direction[2])
    direction /= np.linalg.norm(direction)
    offset = HAND_OFFSET_M_PER_LEVEL * severity * direction
    moved = hand_init_pos + offset
    outside = (moved < low) | (moved > high)
    moved = np.where(outside, hand_init_pos - offset, moved)
    return np.clip(moved, low, high)


class MetaworldEBVLAGymEnv(MetaworldEnv):
    """LeRobot's MetaWorld env with the scene edits of `MetaworldEBVLAEnv` (see its docstring for the args).

    It also keeps MetaWorld's 39-d state of the last observation (`state_obs`), which the scripted expert
    policies (`expert_policy.get_action(state_obs)`) act on. The sensor perturbations change the observed
    `pixels` only; `render()` (lerobot-eval's videos) shows the scene with its model edits and distractors.
    `render_every=N` draws the observed frame at the reset and at every N-th step only (`envs.frames`); the
    steps between observe the last one, through the sensor perturbation as every frame is. `render()` always
    draws.
    """

    def __init__(
        self,
        task: str,
        fast_render: bool = False,
        perturbation: str = "none",
        perturbation_severity: int = 0,
        max_episode_steps: int | None = None,
        observation_size: int | None = None,
        render_every: int = 1,
        **kwargs: Any,
    ):
        check_perturbation(perturbation, perturbation_severity)
        self._frames = FrameGate(render_every)  # checks render_every
        if observation_size is not None:
            kwargs.update(observation_width=observation_size, observation_height=observation_size)
        super().__init__(task, **kwargs)
        self.observation_size = observation_size
        self.fast_render = fast_render
        self.perturbation = perturbation
        self.perturbation_severity = perturbation_severity
        if max_episode_steps is not None:
            self._max_episode_steps = max_episode_steps
        self.state_obs: np.ndarray | None = None
        # Draws the pixel noise and the hand's displacement; reseeded by `reset(seed=...)`.
        self._rng = np.random.default_rng(0)
        self._hand_init_pos: np.ndarray | None = None

    @property
    def render_every(self) -> int:
        """`--env.render_every`: the frame gate's cadence."""
        return self._frames.every

    def _ensure_env(self) -> None:
        if self._env is not None:
            return
        super()._ensure_env()
        model = self._env.model
        if self.observation_size is not None:
            # MetaWorld renders 480x480 frames; its renderer makes its viewer, at this size, on the first frame.
            renderer = self._env.mujoco_renderer
            renderer.width = renderer.height = self.observation_size
        if self.fast_render:
            disable_shadows_and_reflections(model)
        perturb_model(model, self.camera_name, self.perturbation, self.perturbation_severity)
        if self.render_every > 1:
            self._frames.attach(self._env)
        self._hand_init_pos = np.array(self._env.hand_init_pos, dtype=float)
        # Runs at `close()`, or when the env is collected unclosed; it holds the renderer, not the env.
        self._free_viewers = weakref.finalize(self, free_offscreen_viewers, self._env.mujoco_renderer)
        self._free_viewers.atexit = False

    def reset(self, seed: int | None = None, **kwargs: Any) -> tuple[dict[str, Any], dict[str, Any]]:
        self._ensure_env()
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        if self.perturbation == "robot_init" and self.perturbation_severity > 0:
            # MetaWorld's `reset_model` drives the mocap (and so the hand) to `hand_init_pos`.
            self._env.hand_init_pos = displaced_hand_position(
                self._hand_init_pos,
                self.perturbation_severity,
                self._rng,
                self._env.mocap_low,
                self._env.mocap_high,
            )
        self._frames.restart()
        return super().reset(seed=seed, **kwargs)

    def step(self, action: np.ndarray) -> tuple[dict[str, Any], float, bool, bool, dict[str, Any]]:
        self._frames.advance()
        return super().step(action)

    def _prepare_frame(self) -> None:
        """Makes this env's GL context current and queues the distractors, before each rendered frame."""
        viewer = self._env.mujoco_renderer._get_viewer(self._env.render_mode)
        # Gymnasium makes a viewer's context current only when one renderer holds several; another env's
        # close may have left none (or its own) current since this env last rendered.
        viewer.make_context_current()
        if self.perturbation == "distractor":
            # Gymnasium's offscreen viewer draws its markers into the next frame only, then forgets them.
            for marker in distractor_markers(self.perturbation_severity):
                viewer.add_marker(**marker)

    def render(self) -> np.ndarray:
        self._ensure_env()
        self._prepare_frame()
        with self._frames.uncached():
            return super().render()

    def close(self) -> None:
        if self._env is not None:
            self._free_viewers()
        super().close()

    def _format_raw_obs(self, raw_obs: np.ndarray) -> dict[str, Any]:
        self.state_obs = raw_obs
        if not self._frames.skip:
            # Distractor markers queued for a frame that is not drawn would pile up into the next one.
            self._prepare_frame()
        observation = super()._format_raw_obs(raw_obs)
        if not np.any(observation["pixels"]):
            # A lit scene never renders to exact zeros; an offscreen GL context that died does, and every
            # observation after it would silently be the `blank` perturbation's (seen once, mid-evaluation).
            raise RuntimeError(
                f"MetaWorld rendered an all-black {observation['pixels'].shape} frame before any perturbation: the "
                f"offscreen renderer (MUJOCO_GL={os.environ.get('MUJOCO_GL')!r}) failed. Results from here on would "
                "be a blind policy's; rerun the evaluation."
            )
        observation["pixels"] = perturb_image(
            observation["pixels"], self.perturbation, self.perturbation_severity, self._rng
        )
        return observation


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
            envs[group][task_id] = lazy_async_vector_env(env_fns) if is_async else env_cls(env_fns)
    return envs
