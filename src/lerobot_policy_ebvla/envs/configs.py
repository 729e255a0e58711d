"""`--env.type=metaworld_ebvla`: LeRobot's MetaWorld env with fast rendering and camera perturbations.

The config extends LeRobot's `metaworld` env config, so every `--env.*` option of `--env.type=metaworld`
works unchanged and the observation keys and shapes are the same: a policy trained on data recorded with
`ebvla-record-metaworld` evaluates with either env type. Importing this module needs no MetaWorld install;
the simulator is imported when the env is built.
"""

from dataclasses import dataclass

from lerobot.envs.configs import EnvConfig, _make_vec_env_cls
from lerobot.envs.configs import MetaworldEnv as LeRobotMetaworldEnvConfig

CAMERA_PERTURBATIONS = ("none", "pose", "fov", "pose_fov")
MAX_SEVERITY = 5
# MetaWorld truncates every episode after `max_path_length` = 500 steps; an env step past it raises.
METAWORLD_MAX_PATH_LENGTH = 500


@EnvConfig.register_subclass("metaworld_ebvla")
@dataclass
class MetaworldEBVLAEnv(LeRobotMetaworldEnvConfig):
    """LeRobot's MetaWorld env (`--env.type=metaworld`) plus the scene options EB-VLA's experiments need.

    The camera perturbations follow LIBERO-Plus's camera dimension (pose shifts and focal changes of the
    evaluation camera, at graded severities). They move the camera LeRobot renders from (`corner2`) and
    keep the image size, so observation keys and shapes are those of `--env.type=metaworld`.

    Args:
        fast_render: Turn off the scene's shadows and reflections, which renders about 3x faster. Images
            look different (no shadows), so record and evaluate with the same setting.
        camera_perturbation: "none"; "pose" orbits the camera around the point of the table it looks at,
            by 5 degrees of azimuth and 3 degrees of elevation per severity level; "fov" widens the field
            of view by 10% per level (a shorter focal length); "pose_fov" applies both.
        perturbation_severity: Severity level, 0 (no change) to 5.
        max_episode_steps: Steps after which an episode is cut; None keeps LeRobot's 500 (MetaWorld's own
            limit, which is also the maximum).
    """

    task: str = "reach-v3"
    fast_render: bool = False
    camera_perturbation: str = "none"
    perturbation_severity: int = 0
    max_episode_steps: int | None = None

    def __post_init__(self):
        super().__post_init__()
        if self.camera_perturbation not in CAMERA_PERTURBATIONS:
            raise ValueError(
                f"`camera_perturbation` must be one of {CAMERA_PERTURBATIONS}, got {self.camera_perturbation!r}."
            )
        if not 0 <= self.perturbation_severity <= MAX_SEVERITY:
            raise ValueError(
                f"`perturbation_severity` must be in [0, {MAX_SEVERITY}], got {self.perturbation_severity}."
            )
        if self.camera_perturbation == "none" and self.perturbation_severity != 0:
            raise ValueError(
                "`perturbation_severity` > 0 needs a `camera_perturbation` other than 'none' "
                f"(one of {CAMERA_PERTURBATIONS[1:]})."
            )
        if self.max_episode_steps is not None and not 0 < self.max_episode_steps <= METAWORLD_MAX_PATH_LENGTH:
            raise ValueError(
                f"`max_episode_steps` must be in [1, {METAWORLD_MAX_PATH_LENGTH}] or None, "
                f"got {self.max_episode_steps}."
            )

    @property
    def perturbation(self) -> str:
        """Name of the applied perturbation: "none" when no camera change is applied (severity 0)."""
        return "none" if self.perturbation_severity == 0 else self.camera_perturbation

    @property
    def gym_kwargs(self) -> dict:
        return {
            **super().gym_kwargs,
            "fast_render": self.fast_render,
            "camera_perturbation": self.camera_perturbation,
            "perturbation_severity": self.perturbation_severity,
            "max_episode_steps": self.max_episode_steps,
        }

    def create_envs(self, n_envs: int, use_async_envs: bool = False):
        from .metaworld import create_metaworld_ebvla_envs

        if self.task is None:
            raise ValueError("MetaWorld requires a task to be specified")
        return create_metaworld_ebvla_envs(
            task=self.task,
            n_envs=n_envs,
            gym_kwargs=self.gym_kwargs,
            env_cls=_make_vec_env_cls(use_async_envs, n_envs),
        )
