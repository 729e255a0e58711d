"""LeRobot's LIBERO gym env with LIBERO-Plus-style perturbations (`--env.type=libero_ebvla`).

`LiberoEBVLAGymEnv` is LeRobot's `LiberoEnv` whose MuJoCo model is edited at every reset, right after LIBERO
builds the scene and before LeRobot's settling steps (a hard reset rebuilds the model from its XML, so the
edits are re-applied to each new model):

- camera: the agent-view camera ("agentview", LeRobot's `observation.images.image`) is moved with LIBERO-Plus's
  own geometry (its `_setup_camera`): a horizontal rotation about the world's vertical axis with a vertical
  rotation about the y-parallel axis through `LIBERO_PLUS_PIVOT`, or a distance scale from that pivot, or a turn
  of the camera in place (yaw, then pitch); or its field of view is widened.
- lighting: the intensity or colour of every light (the headlight included), or the direction the scene's spot
  lights shine from.
- background ("table_color"): the colour of the table, the floor and the walls.

and the sensor perturbations ("noise", "blur": `sensor.perturb_image`) on every camera's frame of every
observation, with a generator seeded by `reset(seed=...)`.

`render_every=N` (`--env.render_every`) renders the cameras only for the observations a chunked policy reads: the
reset's and every N-th step's (N = the policy's `n_action_steps`); the steps between return the last frames. On two
CPU cores rendering is most of a LIBERO rollout's time; the frames that are read are the ones rendered at
`render_every=1`, so results do not change. A policy that reads every frame (Diffusion Policy's observation
history) needs the default 1.

Every perturbation is graded by a severity 1..5 (0: none). The camera magnitudes are LIBERO-Plus's ranges
(horizontal 0-75 deg, vertical 0-15 deg, distance x1.0-2.0, turn 0-10 deg) scaled by severity / 5; the
constants below are tabulated in docs/libero.md. Import this module only once LIBERO is set up
(`ebvla-install-libero-assets`): `lerobot.envs.libero` imports `libero`, which otherwise asks questions on stdin.
"""

import weakref
from collections.abc import Callable, Sequence
from functools import partial
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np
from lerobot.envs.libero import LiberoEnv
from lerobot.envs.utils import parse_camera_names
from scipy.spatial.transform import Rotation

from ..lerobot_private import get_libero_suite, lazy_async_vector_env, select_libero_task_ids
from .frames import FrameGate
from .lighting import LIGHT_INTENSITY_PERTURBATIONS, perturb_light_intensity
from .perturbations import (
    LIBERO_SENSOR_PERTURBATIONS,
    MAX_SEVERITY,
    check_libero_perturbation,
    check_robot_init_noise,
)
from .sensor import perturb_image

# The MuJoCo camera behind LeRobot's `agentview_image` (`observation.images.image`).
AGENTVIEW_CAMERA = "agentview"
# Keys the arm-start generator apart from the sensor-noise one seeded with the same reset seed.
_ARM_STREAM = 1
# LIBERO-Plus rotates the camera vertically about the y-parallel axis through this point and scales its distance
# from it (`rotate_around_y`, `scale_distance_from_pivot` in its problem files); horizontal rotations are about
# the world's z axis through the origin (`rotate_around_z`).
LIBERO_PLUS_PIVOT = np.array([0.0, 0.0, 0.8])
# Camera magnitudes at severity 5, the largest of LIBERO-Plus's camera variants (file names `_view_H_V_S_R_E`;
# each variant changes H and V, or S, or R and E): horizontal rotation H up to 75 deg, vertical V up to 15 deg,
# distance S up to 200 %, turns R and E up to 10 deg.
MAX_HORIZONTAL_DEG = 75.0
MAX_VERTICAL_DEG = 15.0
MAX_DISTANCE_SCALE = 2.0
MAX_TURN_DEG = 10.0
# "fov": relative widening of the field of view per level (LIBERO's 45 deg becomes 67.5 deg at severity 5).
FOVY_GROWTH_PER_LEVEL = 0.10

# Lighting: intensity and colour as for MetaWorld (envs/lighting.py); "light_direction" tilts every spot light
# about its aim point by 12 deg per level, so at severity 5 the light comes from 60 deg off the vertical
# (LIBERO's lights shine almost straight down).
LIGHT_TILT_DEG_PER_LEVEL = 12.0

# Background: "table_color" moves the colour of these materials (which multiplies their textures, so the wood grain
# and the floor's pattern stay) linearly towards a tint, reached at severity 5: the table blue, the floor and the
# walls pink, as MetaWorld's (envs/metaworld.py). A scene without one of them keeps it as it is.
LIBERO_MATERIAL_TINTS = {
    "table_mat": (0.25, 0.45, 1.0),
    "table_texture": (0.25, 0.45, 1.0),
    "table_legs": (0.25, 0.45, 1.0),
    "floorplane": (1.0, 0.45, 0.55),
    "walls_mat": (1.0, 0.45, 0.55),
    "living_room": (1.0, 0.45, 0.55),
}


def _quat_wxyz_to_rotation(quat: np.ndarray) -> Rotation:
    return Rotation.from_quat([quat[1], quat[2], quat[3], quat[0]])


def _rotation_to_quat_wxyz(rotation: Rotation) -> np.ndarray:
    x, y, z, w = rotation.as_quat()
    return np.array([w, x, y, z])


def libero_plus_camera_pose(
    position: np.ndarray,
    quat: np.ndarray,
    horizontal_deg: float = 0.0,
    vertical_deg: float = 0.0,
    distance_scale: float = 1.0,
    turn_yaw_deg: float = 0.0,
    turn_pitch_deg: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """A camera pose moved as LIBERO-Plus's `_setup_camera` moves the agent-view camera.

    Args:
        position: World position of the camera (3,).
        quat: World orientation, MuJoCo's (w, x, y, z) order.
        horizontal_deg: Rotation of position and orientation about the world's z axis (counter-clockwise).
        vertical_deg: Rotation about the y-parallel axis through `LIBERO_PLUS_PIVOT` (positive raises a camera
            in front of the robot, as LIBERO-Plus's `rotate_around_y` with its sign convention).
        distance_scale: Scale of the camera's offset from `LIBERO_PLUS_PIVOT`.
        turn_yaw_deg, turn_pitch_deg: Rotation of the orientation only, about world z then world y (the
            camera turns in place: LIBERO-Plus's `end_point_rot` and `end_point_vertical`).

    Returns:
        (position, quat) of the moved camera.
    """
    position = np.asarray(position, dtype=float)
    rotation = _quat_wxyz_to_rotation(quat)
    if vertical_deg:
        tilt = Rotation.from_rotvec(np.radians(-vertical_deg) * np.array([0.0, 1.0, 0.0]))
        position = tilt.apply(position - LIBERO_PLUS_PIVOT) + LIBERO_PLUS_PIVOT
        rotation = tilt * rotation
    if horizontal_deg:
        spin = Rotation.from_euler("z", horizontal_deg, degrees=True)
        position = spin.apply(position)
        rotation = spin * rotation
    if distance_scale != 1.0:
        position = LIBERO_PLUS_PIVOT + distance_scale * (position - LIBERO_PLUS_PIVOT)
    if turn_yaw_deg:
        rotation = Rotation.from_euler("z", turn_yaw_deg, degrees=True) * rotation
    if turn_pitch_deg:
        rotation = Rotation.from_rotvec(np.radians(-turn_pitch_deg) * np.array([0.0, 1.0, 0.0])) * rotation
    return position, _rotation_to_quat_wxyz(rotation)


def perturb_camera(model: mujoco.MjModel, camera_name: str, kind: str, severity: int) -> None:
    """Applies a LIBERO-Plus camera perturbation of a given severity to a world camera of `model` (in place)."""
    camera_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera_name)
    if camera_id < 0:
        raise ValueError(f"The scene has no camera named {camera_name!r}.")
    if model.cam_bodyid[camera_id] != 0:
        raise ValueError(f"Camera {camera_name!r} is not attached to the world body; it cannot be moved.")
    level = severity / MAX_SEVERITY
    if kind == "fov":
        model.cam_fovy[camera_id] *= 1.0 + FOVY_GROWTH_PER_LEVEL * severity
        return
    moves = {
        "pose": {"horizontal_deg": MAX_HORIZONTAL_DEG * level, "vertical_deg": MAX_VERTICAL_DEG * level},
        "distance": {"distance_scale": 1.0 + (MAX_DISTANCE_SCALE - 1.0) * level},
        "rotation": {"turn_yaw_deg": MAX_TURN_DEG * level, "turn_pitch_deg": MAX_TURN_DEG * level},
    }
    if kind not in moves:
        raise ValueError(f"Unknown camera perturbation {kind!r}; expected one of {(*moves, 'fov')}.")
    position, quat = libero_plus_camera_pose(
        model.cam_pos[camera_id], model.cam_quat[camera_id], **moves[kind]
    )
    model.cam_pos[camera_id] = position
    model.cam_quat[camera_id] = quat


def tilt_lights(model: mujoco.MjModel, degrees: float) -> None:
    """Swings every light about the point it aims at (at the pivot's height), towards +x, by `degrees`.

    The aim point stays lit; the light reaches it from further off the vertical, so shading changes.
    """
    tilt = Rotation.from_rotvec(np.radians(degrees) * np.array([0.0, 1.0, 0.0]))
    for light_id in range(model.nlight):
        position, direction = model.light_pos[light_id].copy(), model.light_dir[light_id].copy()
        if direction[2] >= 0:
            continue  # a light that does not shine downwards has no aim point on the scene
        aim = position + (LIBERO_PLUS_PIVOT[2] - position[2]) / direction[2] * direction
        model.light_pos[light_id] = aim + tilt.apply(position - aim)
        model.light_dir[light_id] = tilt.apply(direction)


def tint_background(model: mujoco.MjModel, fraction: float) -> list[str]:
    """Moves the colour of the table, floor and walls towards their tints by `fraction` (0 to 1), in place.

    Materials are read at every frame, so unlike a texture edit this also works once the renderer exists.
    Returns the names of the materials it changed.
    """
    changed = []
    for name, tint in LIBERO_MATERIAL_TINTS.items():
        material_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_MATERIAL, name)
        if material_id >= 0:
            rgb = model.mat_rgba[material_id, :3]
            rgb += fraction * (np.asarray(tint) - rgb)
            changed.append(name)
    return changed


def perturb_libero_model(
    model: mujoco.MjModel, perturbation: str, severity: int, camera_name: str = AGENTVIEW_CAMERA
) -> None:
    """Applies a camera, lighting or background perturbation of `severity` (0: none) to a LIBERO scene's model,
    in place; the sensor perturbations leave the model as it is (they act on the frames)."""
    check_libero_perturbation(perturbation, severity)
    if perturbation == "none" or severity == 0 or perturbation in LIBERO_SENSOR_PERTURBATIONS:
        return
    if perturbation == "table_color":
        if not tint_background(model, severity / MAX_SEVERITY):
            raise ValueError(
                f"The scene has none of the materials {list(LIBERO_MATERIAL_TINTS)}: is it LIBERO's?"
            )
    elif perturbation in LIGHT_INTENSITY_PERTURBATIONS:
        perturb_light_intensity(model, perturbation, severity, MAX_SEVERITY)
    elif perturbation == "light_direction":
        tilt_lights(model, LIGHT_TILT_DEG_PER_LEVEL * severity)
    else:
        perturb_camera(model, camera_name, perturbation, severity)


def _offscreen_context(libero_env: Any) -> Any:
    """The robosuite offscreen render context of a LIBERO env's current simulator, or None once it is closed."""
    sim = getattr(libero_env, "sim", None)
    return getattr(sim, "_render_context_offscreen", None)


def make_render_context_current(libero_env: Any) -> None:
    """Makes a LIBERO env's GL context current before it renders or destroys its simulator.

    robosuite renders into whatever GL context is current, and frees a simulator's `MjrContext` (on close and at
    every hard reset) in the current context too, deleting GL objects by their numbers. With another env's context
    current, frames come out drawn with that env's meshes and textures, or broken once that env's objects are
    deleted: measured on two LIBERO-Object tasks in one process, before this was called.
    """
    context = _offscreen_context(libero_env)
    if context is not None:
        context.gl_ctx.make_current()


def free_render_context(libero_env: Any) -> None:
    """Frees a LIBERO env's `MjrContext` inside its own GL context; robosuite's later free then deletes nothing."""
    context = _offscreen_context(libero_env)
    if context is not None:
        context.gl_ctx.make_current()
        context.con.free()


def goal_object_and_container(scene: Any) -> tuple[str, str] | None:
    """The (object, container) body names of a LIBERO goal `(In <object> <container>_contain_region)`, the goal
    of every LIBERO-Object task, from the robosuite env `scene`; None for any other goal."""
    goal = scene.parsed_problem["goal_state"]
    if len(goal) != 1 or goal[0][0].lower() != "in":
        return None
    return goal[0][1], goal[0][2].removesuffix("_contain_region")


def goal_distance(scene: Any) -> float:
    """How far, in metres, the goal's object is from its container (their body origins): how much of the task is
    left. Table IV's failure onset is read from it (the last step at which the object still came closer). NaN for
    a goal that is not an `In` goal over two bodies of the scene."""
    pair = goal_object_and_container(scene)
    if pair is None or any(name not in scene.obj_body_id for name in pair):
        return float("nan")
    obj, container = (np.asarray(scene.sim.data.body_xpos[scene.obj_body_id[name]]) for name in pair)
    return float(np.linalg.norm(obj - container))


class LiberoEBVLAGymEnv(LiberoEnv):
    """LeRobot's `LiberoEnv` with the scene perturbation of `LiberoEBVLAEnv` (see its docstring).

    Args:
        perturbation: A name of `perturbations.LIBERO_PERTURBATIONS`.
        perturbation_severity: 0 (no change) to 5.
        render_every: Render the cameras for the reset's observation and every `render_every`-th step's only
            (the module docstring); 1 renders every step, as LeRobot's env.
        robot_init_noise: Std (radians) of a Gaussian draw added to each arm joint's starting angle at a sampled
            reset (`init_states=False`); 0 starts the arm at its default pose every time, as LIBERO's env does.
            LIBERO's fixed initial states store an arm drawn at robosuite's default, 0.02, and start it the way
            this does: the reset loads the controller at the default pose, then the arm is moved (`set_init_state`),
            so the controller's posture target stays at the default.
        *args, **kwargs: LeRobot's `LiberoEnv` arguments.
    """

    def __init__(
        self,
        *args: Any,
        perturbation: str = "none",
        perturbation_severity: int = 0,
        render_every: int = 1,
        robot_init_noise: float = 0.0,
        **kwargs: Any,
    ):
        check_libero_perturbation(perturbation, perturbation_severity)
        check_robot_init_noise(robot_init_noise)
        frames = FrameGate(render_every)  # checks render_every
        super().__init__(*args, **kwargs)
        self.perturbation = perturbation
        self.perturbation_severity = perturbation_severity
        self.robot_init_noise = robot_init_noise
        self._frames = frames
        # Settling steps of the reset still to come (LeRobot's `num_steps_wait`); policy steps follow them.
        self._settling_left = 0
        self._perturbed_model: mujoco.MjModel | None = None
        # Draws the sensor noise; reseeded by `reset(seed=...)`.
        self._sensor_rng = np.random.default_rng(0)
        # Draws the arm's start (`robot_init_noise`); reseeded by `reset(seed=...)`.
        self._arm_rng = np.random.default_rng((0, _ARM_STREAM))

    @property
    def render_every(self) -> int:
        """`--env.render_every`: the frame gate's cadence."""
        return self._frames.every

    def _perturb_current_model(self) -> None:
        """Perturbs the simulator's model once; a hard reset builds a new model, which is perturbed again."""
        model = self._env.sim.model._model
        if model is not self._perturbed_model:
            perturb_libero_model(model, self.perturbation, self.perturbation_severity)
            self._perturbed_model = model

    def _ensure_env(self) -> None:
        if self._env is not None:
            return
        super()._ensure_env()
        reset_scene, step_scene = self._env.reset, self._env.step

        def reset_scene_and_perturb() -> dict[str, Any]:
            # LeRobot's `reset` then sets the initial state and steps the simulator to let objects settle, so
            # the observation it returns is rendered from the perturbed model by LIBERO's own step.
            observation = reset_scene()
            if self.robot_init_noise > 0 and not self.init_states:
                observation = self._move_arm_off_default()
            self._perturb_current_model()
            if self.render_every > 1:
                self._frames.attach(self._env.env.sim)
            return observation

        def step_rendering_what_is_read(action: np.ndarray) -> tuple:
            if self._settling_left > 0:  # only the last settling step's frame is the reset's observation
                self._settling_left -= 1
                self._frames.skip = self._settling_left > 0
            else:
                self._frames.advance()
            return step_scene(action)

        self._env.reset = reset_scene_and_perturb
        if self.render_every > 1:
            self._env.step = step_rendering_what_is_read
        # Runs at `close()`, or when the env is collected unclosed; it holds LIBERO's env, not this one.
        self._free_render_context = weakref.finalize(self, free_render_context, self._env)
        self._free_render_context.atexit = False

    def _move_arm_off_default(self) -> dict[str, Any]:
        """Adds N(0, robot_init_noise^2) to each arm joint of the reset's pose and regenerates the observation, as
        LIBERO's `set_init_state` moves the arm of a fixed state. robosuite's own `initialization_noise` would load
        the controller at the noisy pose, and its posture target with it: a start D failed on 69 of 80 fresh
        placements, against 12 points lost on the fixed states (research/docs/libero_runs.md, "The arm's start")."""
        scene = self._env
        for robot in scene.robots:
            joints = robot._ref_joint_pos_indexes
            scene.sim.data.qpos[joints] += self._arm_rng.normal(0.0, self.robot_init_noise, len(joints))
        return scene.regenerate_obs_from_state(scene.get_sim_state())

    def _activate(self) -> None:
        """Builds the env if needed and makes its GL context current: everything that renders or rebuilds the
        simulator (reset, step, render) starts here."""
        self._ensure_env()
        make_render_context_current(self._env)

    def _format_raw_obs(self, raw_obs: dict[str, Any]) -> dict[str, Any]:
        """LeRobot's observation, each camera's frame through the sensor perturbation (none without one)."""
        observation = super()._format_raw_obs(raw_obs)
        if self.perturbation in LIBERO_SENSOR_PERTURBATIONS:
            observation["pixels"] = {
                camera: perturb_image(frame, self.perturbation, self.perturbation_severity, self._sensor_rng)
                for camera, frame in observation["pixels"].items()
            }
        return observation

    def reset(self, seed: int | None = None, **kwargs: Any) -> tuple[dict[str, Any], dict[str, Any]]:
        self._activate()
        self._sensor_rng = np.random.default_rng(seed)
        # Its own stream, so that the placements (numpy's global generator, seeded by LIBERO) stay the seed's.
        self._arm_rng = np.random.default_rng(None if seed is None else (seed, _ARM_STREAM))
        # Before the settling steps, frames are drawn for nobody (with none, the initial state's frame is read).
        self._settling_left = self.num_steps_wait
        self._frames.restart()
        self._frames.skip = self.render_every > 1 and self.num_steps_wait > 0
        observation, info = super().reset(seed=seed, **kwargs)
        return observation, self._with_goal_distance(info)

    def step(self, action: np.ndarray) -> tuple[dict[str, Any], float, bool, bool, dict[str, Any]]:
        self._activate()
        observation, reward, terminated, truncated, info = super().step(action)
        return observation, reward, terminated, truncated, self._with_goal_distance(info)

    def _with_goal_distance(self, info: dict[str, Any]) -> dict[str, Any]:
        """`info` with `goal_distance`, which the energy recorder stores with each chunk (`EnergyRecord`)."""
        return {**info, "goal_distance": goal_distance(self._env.env)}

    def render(self) -> np.ndarray:
        self._activate()
        return super().render()

    def close(self) -> None:
        if self._env is not None:
            self._free_render_context()
        super().close()


def create_libero_ebvla_envs(
    task: str,
    n_envs: int,
    gym_kwargs: dict[str, Any],
    camera_name: str | Sequence[str],
    init_states: bool,
    env_cls: Callable[[Sequence[Callable[[], Any]]], Any],
    control_mode: str = "relative",
    episode_length: int | None = None,
    camera_name_mapping: dict[str, str] | None = None,
) -> dict[str, dict[int, Any]]:
    """`lerobot.envs.libero.create_libero_envs` for `LiberoEBVLAGymEnv`: {suite: {task_id: vec_env}}."""
    if not isinstance(n_envs, int) or n_envs <= 0:
        raise ValueError(f"n_envs must be a positive int; got {n_envs}.")
    gym_kwargs = dict(gym_kwargs)
    task_ids = gym_kwargs.pop("task_ids", None)
    # LeRobot ties env i to initial state i (`episode_index`, then + n_envs at every reset): shifting the index
    # shifts the states.
    first_init_state = gym_kwargs.pop("first_init_state", 0)
    suite_names = [name.strip() for name in str(task).split(",") if name.strip()]
    if not suite_names:
        raise ValueError("`task` must contain at least one LIBERO suite name.")
    is_async = env_cls is gym.vector.AsyncVectorEnv
    envs: dict[str, dict[int, Any]] = {}
    for suite_name in suite_names:
        suite = get_libero_suite(suite_name)
        envs[suite_name] = {}
        for task_id in select_libero_task_ids(len(suite.tasks), task_ids):
            env_fns = [
                partial(
                    LiberoEBVLAGymEnv,
                    task_suite=suite,
                    task_id=task_id,
                    task_suite_name=suite_name,
                    camera_name=parse_camera_names(camera_name),
                    init_states=init_states,
                    episode_length=episode_length,
                    episode_index=first_init_state + episode_index,
                    n_envs=n_envs,
                    control_mode=control_mode,
                    camera_name_mapping=camera_name_mapping,
                    **gym_kwargs,
                )
                for episode_index in range(n_envs)
            ]
            if is_async:
                envs[suite_name][task_id] = lazy_async_vector_env(env_fns)
            elif env_cls is gym.vector.SyncVectorEnv:
                # As LeRobot's LIBERO envs: the terminal observation is returned, the reset comes next step.
                envs[suite_name][task_id] = gym.vector.SyncVectorEnv(
                    env_fns, autoreset_mode=gym.vector.AutoresetMode.NEXT_STEP
                )
            else:
                envs[suite_name][task_id] = env_cls(env_fns)
    return envs
