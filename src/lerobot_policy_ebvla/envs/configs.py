"""`--env.type=metaworld_ebvla`: LeRobot's MetaWorld env with fast rendering and graded perturbations.

The config extends LeRobot's `metaworld` env config, so every `--env.*` option of `--env.type=metaworld`
works unchanged and the observation keys and shapes are the same: a policy trained on data recorded with
`ebvla-record-metaworld` evaluates with either env type. Importing this module needs no MetaWorld install;
the simulator is imported when the env is built.
"""

from dataclasses import dataclass

from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig
from lerobot.envs.configs import MetaworldEnv as LeRobotMetaworldEnvConfig

from ..lerobot_private import make_vec_env_cls
from .frames import check_render_every
from .perturbations import PERTURBATIONS, check_perturbation

# MetaWorld truncates every episode after `max_path_length` = 500 steps; an env step past it raises.
METAWORLD_MAX_PATH_LENGTH = 500
# MetaWorld renders 480x480 frames; `observation_size` renders smaller ones.
METAWORLD_FRAME_SIZE = 480


@EnvConfig.register_subclass("metaworld_ebvla")
@dataclass
class MetaworldEBVLAEnv(LeRobotMetaworldEnvConfig):
    """LeRobot's MetaWorld env (`--env.type=metaworld`) plus the scene options EB-VLA's experiments need.

    The perturbations follow LIBERO-Plus's dimensions where MetaWorld allows (camera viewpoint, lighting,
    sensor noise, background/table appearance, distractor objects, robot initial state), each at severities
    1 to 5; the magnitudes per level are the constants of `envs/metaworld.py`, tabulated in docs/metaworld.md.
    They keep the image size, so observation keys and shapes are those of `--env.type=metaworld`.

    Args:
        fast_render: Turn off the scene's shadows and reflections, which renders about 3x faster. Images
            look different (no shadows), so record and evaluate with the same setting.
        perturbation: One of `perturbations.PERTURBATIONS`: "none"; camera "pose", "fov", "pose_fov";
            lighting "light_dim", "light_bright", "light_color", "light_direction"; sensor "noise", "blur",
            "blank" (a black image, to check that a policy uses its camera); scene "table_color",
            "table_texture", "distractor"; robot "robot_init" (the hand starts elsewhere).
        perturbation_severity: Severity level, 0 (no change) to 5. At 0 `perturbation` is set to "none",
            so `perturbation` always names the perturbation actually applied (what energy records store).
        camera_perturbation: Older name of `perturbation`, kept so existing commands work; after
            construction both fields hold the same value.
        max_episode_steps: Steps after which an episode is cut; None keeps LeRobot's 500 (MetaWorld's own
            limit, which is also the maximum).
        observation_size: Side of the square camera frames, rendered at that size (16 to 480 px); None keeps
            MetaWorld's 480. With `fast_render` an env step takes about 20 ms at 128 px against 36 ms at 480 px
            on a CPU core (docs/metaworld.md), and a policy that resizes its images to 64 px loses nothing. Like
            `fast_render`, it changes the images: record and evaluate with the same value.
        render_every: Draw the camera frame only at the reset and at every `render_every`-th step, the frames a
            policy acting in chunks of that many steps reads (its `n_action_steps`); the steps between observe
            the last frame. The frames drawn are those of 1 (every step, LeRobot's), so results do not change;
            drawing was about 30 ms of a 32 ms step on a CPU core (2026-11-28). A policy that reads every frame needs 1.
    """

    task: str = "reach-v3"
    fast_render: bool = False
    perturbation: str = "none"
    perturbation_severity: int = 0
    camera_perturbation: str = "none"
    max_episode_steps: int | None = None
    observation_size: int | None = None
    render_every: int = 1

    def __post_init__(self):
        super().__post_init__()
        check_render_every(self.render_every)
        if self.observation_size is not None:
            if not 16 <= self.observation_size <= METAWORLD_FRAME_SIZE:
                raise ValueError(
                    f"`observation_size` must be between 16 and {METAWORLD_FRAME_SIZE} pixels, or None for "
                    f"MetaWorld's {METAWORLD_FRAME_SIZE}; got {self.observation_size}."
                )
            side = self.observation_size
            for key, feature in self.features.items():
                if feature.type is FeatureType.VISUAL:
                    self.features[key] = PolicyFeature(type=FeatureType.VISUAL, shape=(side, side, 3))
        if self.camera_perturbation not in PERTURBATIONS:
            raise ValueError(
                f"`camera_perturbation` must be one of {PERTURBATIONS}, got {self.camera_perturbation!r}."
            )
        if self.camera_perturbation != "none":
            if self.perturbation not in ("none", self.camera_perturbation):
                raise ValueError(
                    f"`perturbation` ({self.perturbation!r}) and its older name `camera_perturbation` "
                    f"({self.camera_perturbation!r}) disagree: set only `perturbation`."
                )
            self.perturbation = self.camera_perturbation
        check_perturbation(self.perturbation, self.perturbation_severity)
        if self.perturbation_severity == 0:
            self.perturbation = "none"
        self.camera_perturbation = self.perturbation
        if self.max_episode_steps is not None and not 0 < self.max_episode_steps <= METAWORLD_MAX_PATH_LENGTH:
            raise ValueError(
                f"`max_episode_steps` must be in [1, {METAWORLD_MAX_PATH_LENGTH}] or None, "
                f"got {self.max_episode_steps}."
            )

    @property
    def gym_kwargs(self) -> dict:
        return {
            **super().gym_kwargs,
            "fast_render": self.fast_render,
            "perturbation": self.perturbation,
            "perturbation_severity": self.perturbation_severity,
            "max_episode_steps": self.max_episode_steps,
            "observation_size": self.observation_size,
            "render_every": self.render_every,
        }

    def create_envs(self, n_envs: int, use_async_envs: bool = False):
        if self.task is None:
            raise ValueError("MetaWorld requires a task to be specified")
        env_cls = make_vec_env_cls(use_async_envs, n_envs)
        from .metaworld import create_metaworld_ebvla_envs

        return create_metaworld_ebvla_envs(
            task=self.task, n_envs=n_envs, gym_kwargs=self.gym_kwargs, env_cls=env_cls
        )
