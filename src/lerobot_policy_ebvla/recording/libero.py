"""Recording a scripted LIBERO-Object expert as a LeRobotDataset shaped like HuggingFaceVLA/libero.

Every LIBERO-Object task is "pick up the X and place it in the basket". The expert (`LiberoObjectExpert`) reads
the object to move and its container from the task's BDDL goal, the poses of both from the simulator (privileged
information no policy sees), and drives LIBERO's own controller (OSC_POSE, delta end-effector actions in [-1, 1],
gripper -1 open / +1 closed) through waypoints: above the object, down to it, close, lift, over the basket,
down, open (with `regrasp`, the closed hand first rises a little and reopens to grasp again if the object
stayed where it lay). Episodes run in LeRobot's LIBERO env (through `--env.type=libero_ebvla`, so perturbations are
the same options as in evaluation), starting from LIBERO's fixed initial states (attempt i of a task uses state i, or
state `env.first_init_state` + i), or, with `placement_seed`, from object placements LIBERO samples afresh from
the task's BDDL regions (attempt i resets with seed `placement_seed` + `env.first_init_state` + i): scenes that
are never among the 50 fixed initial states on which policies are evaluated.

The dataset has the features of `HuggingFaceVLA/libero` as LeRobot's LIBERO env and docs define them, so a policy
trained on it takes the same inputs as one trained on the real dataset, and evaluates with
`lerobot-eval --env.type=libero` unchanged:

- `observation.images.image` (agent view) and `observation.images.image2` (wrist): 256x256x3 images (or
  `image_size`, rendered at that size), rotated by 180 degrees from the simulator's frames, which is what
  LeRobot's `LiberoProcessorStep` does to the env's frames (`policy_frame`);
- `observation.state`: 8 floats, end-effector position, axis-angle orientation and the two gripper joints, computed
  by that same processor step;
- `action`: the 7 floats sent to the env; the task string. One frame per control step.

Only successful episodes are kept (`keep_failed` keeps all); every attempt is listed, with the expert's success
rate per task, in `<root>/meta/recording_report.json`. An existing dataset is never replaced unless `overwrite`.
"""

import logging
from collections.abc import Generator
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch
from lerobot.utils.constants import ACTION, OBS_IMAGES, OBS_STATE

from ..envs.libero_assets import require_libero_ready
from ..envs.libero_configs import LiberoEBVLAEnv
from .loop import (
    Episode,
    RecordingConfig,
    check_env_records_images_and_state,
    episode_counts,
    prepare_root,
    record_episodes,
    success_rates,
    write_report,
)

# HuggingFaceVLA/libero's metadata: 10 frames per second (each frame one LIBERO control step), robot "panda",
# 256x256 cameras, an 8-d state and a 7-d action with these names.
DATASET_FPS = 10
ROBOT_TYPE = "panda"
IMAGE_SIZE = 256
STATE_NAMES = ["x", "y", "z", "axis_angle1", "axis_angle2", "axis_angle3", "gripper", "gripper"]
ACTION_NAMES = ["x", "y", "z", "axis_angle1", "axis_angle2", "axis_angle3", "gripper"]
CAMERA_KEYS = (f"{OBS_IMAGES}.image", f"{OBS_IMAGES}.image2")

# The expert. LIBERO's OSC_POSE controller moves the end-effector target by 0.05 m per unit of action.
OSC_METRES_PER_UNIT = 0.05
MAX_ACTION = 0.6  # speed limit (0.03 m per step), slow enough that the gripper does not knock objects over
GRIPPER_OPEN, GRIPPER_CLOSED = -1.0, 1.0
HOVER_HEIGHT = 0.10  # above the object before descending, metres
CARRY_HEIGHT = 0.28  # end-effector height while carrying, above the floor of LIBERO-Object's scene
RELEASE_HEIGHT = 0.16  # above the basket's origin when opening
REACHED = 0.012  # waypoint tolerance, metres
GRIP_STEPS = 12  # steps with the gripper closing (or opening) before moving on
# The hand stops this far below the top of a tall object (bottles, cartons): the fingers' length. Objects are
# grasped at their centre or this far below their top, whichever is higher.
FINGER_DEPTH = 0.035
DESCEND_MAX_STEPS = 40  # close the gripper where the hand is if the grasp height is not reached by then
HAND_HALF_WIDTH = 0.12  # the open hand's reach either side of its centre along world y, metres
# A neighbour this far in x from the grasp point (the hand's half depth and a bottle's radius) is clear of it.
HAND_CLEARANCE_X = 0.08
GRASP_END_MARGIN = 0.015  # a grasp slid towards an end of a long object stays this far inside it
GRASP_SLIDE_GAIN = 0.01  # slide only when it gains at least this much clearance
GRASP_SLIDE_ELONGATION = 1.5  # and only along an object at least this much longer in x than wide in y
# With `regrasp`, a closed hand first rises this far (metres), then carries on lifting if the object has risen at
# least `LIFTED` off where it lay, or reopens there.
RAISE_HEIGHT = 0.08
LIFTED = 0.04


@dataclass
class RecordLiberoConfig(RecordingConfig):
    """The recorder's options; images are stored as PNG frames by default, as in HuggingFaceVLA/libero."""

    # The env: suite (`--env.task=libero_object`), tasks (`--env.task_ids=[0,1]`), perturbation, first initial
    # state (`--env.first_init_state`). Frames are rendered at `image_size` (`--env.observation_height/width`
    # are ignored).
    env: LiberoEBVLAEnv = field(default_factory=LiberoEBVLAEnv)
    # Square frame size the cameras render and the dataset stores: HuggingFaceVLA/libero's 256 by default. A
    # policy that resizes to 128 px trains several times faster from frames stored at 128 (fewer PNG bytes to
    # decode per sample); evaluate it with `--env.observation_height=128 --env.observation_width=128`, so that
    # it sees frames rendered as in its data.
    image_size: int = IMAGE_SIZE
    # Dataset repo id (stored locally; nothing is pushed).
    repo_id: str = "local/libero_object_expert"
    # Expert episodes attempted per task; attempt i starts from LIBERO's initial state i of the task.
    episodes_per_task: int = 10
    # Steps after which an attempt counts as failed; None: LeRobot's limit for the suite (280 for libero_object).
    max_steps: int | None = None
    # Start each attempt from object placements LIBERO samples from the task's regions, reset with seed
    # `placement_seed` + `env.first_init_state` + i, instead of from its fixed initial state i. Demonstrations
    # recorded so never share a scene with an evaluation, which starts from the fixed states (LeRobot's env
    # starts episode i at state i). None: the fixed initial states.
    placement_seed: int | None = None
    # After closing the hand, rise a little and, when the object stayed where it lay, reopen and grasp again, instead
    # of carrying nothing to the basket (off: the expert that recorded the datasets before 2026-11-30, whose
    # attempts repeat).
    regrasp: bool = False
    # Recovery demonstrations (needs `regrasp`): the first grasp of every attempt aims this far (metres) from the
    # object along world x, to one side drawn from the attempt's seed, so that it closes on nothing; the expert then
    # reopens and grasps the object. 0: every grasp aims at the object.
    miss_first_grasp: float = 0.0
    # Store the frames of the deliberate miss (the approach, the descent and the hand closing beside the object).
    # Off: a recovery demonstration's frames start where the closed hand rises from its miss, the state a policy is
    # in after missing a grasp of its own: the miss is the expert's device, not behaviour to imitate (a policy
    # fine-tuned on stored misses closed beside the object: research/docs/libero_runs.md, "I").
    store_missed_grasp: bool = False

    def __post_init__(self):
        super().__post_init__()
        if self.env.task != "libero_object":
            raise ValueError(
                "The scripted expert knows LIBERO-Object only: `env.task` must be 'libero_object', "
                f"got {self.env.task!r}."
            )
        check_env_records_images_and_state(self.env)
        if self.image_size < 16:
            raise ValueError(f"`image_size` must be >= 16 pixels, got {self.image_size}.")
        # Frames are rendered at the dataset's size, whatever `--env.observation_*` says.
        self.env.observation_height = self.env.observation_width = self.image_size
        if self.max_steps is not None and self.max_steps < 1:
            raise ValueError(f"`max_steps` must be >= 1 or None, got {self.max_steps}.")
        if self.miss_first_grasp < 0 or (self.miss_first_grasp > 0 and not self.regrasp):
            raise ValueError(
                f"`miss_first_grasp` must be >= 0, and > 0 only with `regrasp=true` (a missed grasp is never "
                f"recovered without it); got {self.miss_first_grasp} with regrasp={self.regrasp}."
            )
        if self.placement_seed is not None:
            if self.placement_seed < 0:
                raise ValueError(f"`placement_seed` must be >= 0 or None, got {self.placement_seed}.")
            # LeRobot's env then leaves the placements LIBERO's reset sampled.
            self.env.init_states = False


def dataset_features(use_videos: bool, image_size: int = IMAGE_SIZE) -> dict[str, dict]:
    """The features of HuggingFaceVLA/libero (keys, dtypes, shapes, names), with square frames of `image_size`."""
    camera = {
        "dtype": "video" if use_videos else "image",
        "shape": (image_size, image_size, 3),
        "names": ["height", "width", "channel"],
    }
    return {
        CAMERA_KEYS[0]: dict(camera),
        CAMERA_KEYS[1]: dict(camera),
        OBS_STATE: {"dtype": "float32", "shape": (8,), "names": {"motors": STATE_NAMES}},
        ACTION: {"dtype": "float32", "shape": (7,), "names": {"motors": ACTION_NAMES}},
    }


class LiberoObjectExpert:
    """Scripted pick-and-place for LIBERO-Object from privileged object poses (see the module docstring).

    Args:
        env: A `LiberoEBVLAGymEnv` (or LeRobot's `LiberoEnv`) that has been reset.
        regrasp: Rise a little after closing the hand (`RAISE_HEIGHT`) and, if the object stayed where it lay,
            reopen and grasp again (`RecordLiberoConfig`).
        miss: Horizontal offset (metres, world x and y) of the first grasp from the object; None: none.
    """

    def __init__(self, env: Any, regrasp: bool = False, miss: np.ndarray | None = None):
        # Here, not at the top: `envs.libero` imports LIBERO, which asks questions on stdin until
        # `require_libero_ready` has pointed it at the assets (an env given here has been built, so it is).
        from ..envs.libero import goal_object_and_container

        self.scene = env._env.env  # LIBERO's robosuite env
        pair = goal_object_and_container(self.scene)
        if pair is None:
            raise ValueError(
                "Expected a LIBERO-Object goal `(In <object> <basket>_contain_region)`, got "
                f"{self.scene.parsed_problem['goal_state']}."
            )
        self.object_name, self.container_name = pair
        self.phase = "approach"
        self.phase_steps = 0
        self._slide: float | None = None
        self.regrasp = regrasp
        self._miss = None if miss is None else np.array([*miss, 0.0])
        self._resting_height = self._position(self.object_name)[2]
        self.grasps = 0  # grasps closed so far: 2 or more after a recovery
        self._raise_to: float | None = None  # height the closed hand rises to before `holds_object` is asked

    def _position(self, name: str) -> np.ndarray:
        return np.array(self.scene.sim.data.body_xpos[self.scene.obj_body_id[name]])

    def _world_extent(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """(lowest, highest) corner of the world-axis box around the object's geoms."""
        model, data = self.scene.sim.model._model, self.scene.sim.data._data
        body = self.scene.obj_body_id[name]
        geoms = np.flatnonzero(model.body_rootid[model.geom_bodyid] == body)
        # Each geom's bounding box is in its own frame: its world half extents are |R| times the local ones.
        centres = np.array(
            [data.geom_xpos[g] + data.geom_xmat[g].reshape(3, 3) @ model.geom_aabb[g][:3] for g in geoms]
        )
        halves = np.array([np.abs(data.geom_xmat[g].reshape(3, 3)) @ model.geom_aabb[g][3:] for g in geoms])
        return (centres - halves).min(axis=0), (centres + halves).max(axis=0)

    def _grasp_slide(self, name: str) -> float:
        """How far along world x to grasp from the object's centre, so that the hand clears its neighbours.

        The fingers close along world y and the hand is wide along y (`HAND_HALF_WIDTH`): next to a long flat
        object (the cream cheese box lies 8 cm long in x, 4 cm wide) a tall neighbour within that width stops the
        hand above the object. For objects elongated along x with a neighbour closer than `HAND_CLEARANCE_X` in x,
        of the centre and the two ends
        (`GRASP_END_MARGIN` inside) the grasp takes the point farthest in x from every other object within the
        hand's width in y: the centre unless an end is `GRASP_SLIDE_GAIN` farther.
        """
        low, high = self._world_extent(name)
        length, width = high[:2] - low[:2]
        reach = length / 2 - GRASP_END_MARGIN
        if length < GRASP_SLIDE_ELONGATION * width or reach <= 0:
            return 0.0  # a round or square object is grasped at its centre
        centre = self._position(name)
        others = [
            self._position(other)
            for other in self.scene.obj_body_id
            if other not in (name, self.container_name)
        ]
        near = [o for o in others if abs(o[1] - centre[1]) < HAND_HALF_WIDTH]

        def clearance(slide: float) -> float:
            return min((abs(o[0] - centre[0] - slide) for o in near), default=np.inf)

        if clearance(0.0) >= HAND_CLEARANCE_X:
            return 0.0
        best = max((-reach, reach), key=clearance)
        return best if clearance(best) > clearance(0.0) + GRASP_SLIDE_GAIN else 0.0

    def _grasp_position(self, name: str) -> np.ndarray:
        """The object's centre, slid along x to clear its neighbours (`_grasp_slide`, chosen once per
        episode), raised to `FINGER_DEPTH` below its top for objects taller than the fingers."""
        if self._slide is None:
            self._slide = self._grasp_slide(name)
        _, high = self._world_extent(name)
        position = self._position(name)
        position[0] += self._slide
        position[2] = max(position[2], high[2] - FINGER_DEPTH)
        return position if self._miss is None else position + self._miss

    def holds_object(self) -> bool:
        """Whether the object has risen off where it lay (`LIFTED`): asked once the closed hand has risen."""
        return self._position(self.object_name)[2] > self._resting_height + LIFTED

    def _waypoint(self, eef: np.ndarray) -> tuple[np.ndarray, float, str | None]:
        """(target position, gripper command, next phase once the target is reached) of the current phase."""
        obj, container = self._grasp_position(self.object_name), self._position(self.container_name)
        if self.phase == "approach":
            return np.array([*obj[:2], obj[2] + HOVER_HEIGHT]), GRIPPER_OPEN, "descend"
        if self.phase == "descend":
            return obj, GRIPPER_OPEN, "grasp"
        if self.phase == "grasp":
            after = "raise" if self.regrasp else "lift"
            return eef, GRIPPER_CLOSED, after if self.phase_steps >= GRIP_STEPS else None
        if self.phase == "raise":
            target = np.array([*eef[:2], self._raise_to])
            return target, GRIPPER_CLOSED, "lift" if self.holds_object() else "reopen"
        if self.phase == "lift":
            return np.array([*eef[:2], CARRY_HEIGHT]), GRIPPER_CLOSED, "carry"
        if self.phase == "reopen":
            return eef, GRIPPER_OPEN, "approach" if self.phase_steps >= GRIP_STEPS else None
        if self.phase == "carry":
            return np.array([*container[:2], CARRY_HEIGHT]), GRIPPER_CLOSED, "lower"
        if self.phase == "lower":
            return np.array([*container[:2], container[2] + RELEASE_HEIGHT]), GRIPPER_CLOSED, "release"
        if self.phase == "release":
            return eef, GRIPPER_OPEN, "retreat" if self.phase_steps >= GRIP_STEPS else None
        # "retreat": up and open, until the env reports success.
        return np.array([*eef[:2], CARRY_HEIGHT]), GRIPPER_OPEN, None

    def act(self, eef_position: np.ndarray) -> np.ndarray:
        """The next 7-d action for an end-effector at `eef_position` (the raw observation's `robot0_eef_pos`)."""
        target, gripper, next_phase = self._waypoint(eef_position)
        error = target - eef_position
        done = self.phase in ("grasp", "release", "reopen") or (
            self.phase == "descend" and self.phase_steps >= DESCEND_MAX_STEPS
        )
        if next_phase is not None and (done or np.linalg.norm(error) < REACHED):
            if self.phase == "grasp":
                self.grasps += 1
                self._raise_to = eef_position[2] + RAISE_HEIGHT
            elif self.phase == "reopen":
                self._miss = None  # the retry aims at the object
            self.phase, self.phase_steps = next_phase, 0
        else:
            self.phase_steps += 1
        move = np.clip(error / OSC_METRES_PER_UNIT, -MAX_ACTION, MAX_ACTION)
        return np.array([*move, 0.0, 0.0, 0.0, gripper], dtype=np.float32)


def policy_frame(observation: dict[str, Any]) -> dict[str, np.ndarray]:
    """The images and state LeRobot's LIBERO env processing gives a policy, as dataset frame values."""
    from lerobot.envs.utils import preprocess_observation
    from lerobot.processor import LiberoProcessorStep

    batch = {k: v[None] if isinstance(v, np.ndarray) else v for k, v in observation["pixels"].items()}
    robot_state = _add_batch_dim(observation["robot_state"])
    processed = LiberoProcessorStep().observation(
        preprocess_observation({"pixels": batch, "robot_state": robot_state})
    )
    frame = {OBS_STATE: processed[OBS_STATE][0].numpy().astype(np.float32)}
    for key in CAMERA_KEYS:
        image = processed[key][0].permute(1, 2, 0)  # (H, W, 3) in [0, 1]
        frame[key] = torch.round(image * 255).to(torch.uint8).numpy()
    return frame


def _add_batch_dim(tree: Any) -> Any:
    if isinstance(tree, dict):
        return {k: _add_batch_dim(v) for k, v in tree.items()}
    return np.asarray(tree)[None]


def first_grasp_miss(distance: float, seed: int) -> np.ndarray | None:
    """The first grasp's offset (world x, y) for `miss_first_grasp`: `distance` along x, to the side `seed` draws."""
    if distance == 0:
        return None
    side = 1.0 if np.random.default_rng(seed).random() < 0.5 else -1.0
    return np.array([side * distance, 0.0])


def record_expert_episode(
    env: Any,
    dataset: Any,
    max_steps: int,
    seed: int | None = None,
    regrasp: bool = False,
    miss: np.ndarray | None = None,
    store_missed_grasp: bool = False,
) -> tuple[bool, int]:
    """Rolls the expert out once from the env's next initial state (or, for an env without fixed initial
    states, from the placements its reset with `seed` samples), adding its frames to the episode buffer: every
    frame, or with a `miss` and not `store_missed_grasp`, those from the first grasp's rise on. `regrasp` and
    `miss` are the expert's (`LiberoObjectExpert`). Returns (success, steps run: the stored frames and any skipped)."""
    observation, _ = env.reset(seed=seed)
    expert = LiberoObjectExpert(env, regrasp=regrasp, miss=miss)
    skip_miss = miss is not None and not store_missed_grasp
    success, n_steps = False, 0
    while n_steps < max_steps and not success:
        # `grasps` counts closings completed: from then on the expert rises from its miss.
        store = not skip_miss or expert.grasps > 0
        action = expert.act(np.asarray(observation["robot_state"]["eef"]["pos"]))
        if store:
            dataset.add_frame({**policy_frame(observation), ACTION: action, "task": env.task_description})
        observation, _, terminated, _, info = env.step(action)
        n_steps += 1
        success = bool(info["is_success"])
        if terminated and not success:
            break
    if expert.grasps > 1:
        logging.info("The expert closed the hand %d times (a recovered grasp).", expert.grasps)
    return success, n_steps


def expert_episodes(
    envs: dict[int, Any],
    episodes_per_task: int,
    max_steps: int,
    dataset: Any,
    first_init_state: int = 0,
    placement_seed: int | None = None,
    regrasp: bool = False,
    miss_first_grasp: float = 0.0,
    store_missed_grasp: bool = False,
) -> Generator[Episode, None, None]:
    """The episodes to attempt, task by task; each task's vector env is closed once its episodes are recorded.

    Attempt i starts from the fixed initial state `first_init_state` + i, or with `placement_seed`, from the
    placements sampled with seed `placement_seed` + `first_init_state` + i. `regrasp`, `miss_first_grasp` and
    `store_missed_grasp` are `RecordLiberoConfig`'s; the side of a missed first grasp is drawn from the attempt's
    seed (or index).
    """
    for task_id, vec_env in envs.items():
        env = vec_env.envs[0]
        record = partial(
            record_expert_episode,
            env,
            dataset,
            max_steps,
            regrasp=regrasp,
            store_missed_grasp=store_missed_grasp,
        )
        try:
            for attempt in range(first_init_state, first_init_state + episodes_per_task):
                if placement_seed is None:
                    start, seed = {"task_id": task_id, "initial_state": attempt}, None
                    where = f"initial state {attempt}"
                else:
                    seed = placement_seed + attempt
                    start, where = {"task_id": task_id, "placement_seed": seed}, f"placements of seed {seed}"
                miss = first_grasp_miss(miss_first_grasp, attempt if seed is None else seed)
                yield Episode(
                    task=env.task,
                    start=start,
                    label=f"task {task_id} ({env.task}) {where}",
                    rollout=partial(record, seed=seed, miss=miss),
                )
        finally:
            vec_env.close()


def record_libero(cfg: RecordLiberoConfig) -> dict:
    """Records the dataset described by `cfg` and returns the report written to `meta/recording_report.json`."""
    from lerobot.datasets import LeRobotDataset
    from lerobot.envs.libero import TASK_SUITE_MAX_STEPS

    require_libero_ready()
    root = Path(cfg.root)
    prepare_root(root, cfg.overwrite)
    envs = cfg.env.create_envs(n_envs=1)[cfg.env.task]
    max_steps = cfg.max_steps or TASK_SUITE_MAX_STEPS[cfg.env.task]
    dataset = LeRobotDataset.create(
        repo_id=cfg.repo_id,
        fps=DATASET_FPS,
        features=dataset_features(cfg.use_videos, cfg.image_size),
        root=root,
        robot_type=ROBOT_TYPE,
        use_videos=cfg.use_videos,
    )
    episodes = record_episodes(
        dataset,
        expert_episodes(
            envs,
            cfg.episodes_per_task,
            max_steps,
            dataset,
            cfg.env.first_init_state,
            cfg.placement_seed,
            cfg.regrasp,
            cfg.miss_first_grasp,
            cfg.store_missed_grasp,
        ),
        cfg.keep_failed,
    )
    report = {
        "repo_id": cfg.repo_id,
        "env": {
            "type": cfg.env.type,
            "task": cfg.env.task,
            "task_ids": cfg.env.task_ids,
            "perturbation": cfg.env.perturbation,
            "perturbation_severity": cfg.env.perturbation_severity,
            "first_init_state": cfg.env.first_init_state,
        },
        "placement_seed": cfg.placement_seed,
        "regrasp": cfg.regrasp,
        "miss_first_grasp": cfg.miss_first_grasp,
        "store_missed_grasp": cfg.store_missed_grasp,
        "image_size": cfg.image_size,
        "max_steps": max_steps,
        "use_videos": cfg.use_videos,
        "keep_failed": cfg.keep_failed,
        **episode_counts(episodes),
        "success_rate_per_task": success_rates(episodes),
        "episodes": [ep.to_dict() for ep in episodes],
    }
    write_report(root, report)
    rates = "\n".join(f"  {task}: {rate:.0%}" for task, rate in report["success_rate_per_task"].items())
    logging.info("Recorded %s at %s; expert success rate per task:\n%s", cfg.repo_id, root, rates)
    return report
