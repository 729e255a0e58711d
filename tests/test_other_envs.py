"""An ebvla policy built for LeRobot's other environments runs on their observation formats."""

import numpy as np
import pytest
import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.envs.configs import PushtEnv
from lerobot.envs.utils import preprocess_observation

from lerobot_policy_ebvla import EBVLAPolicy
from lerobot_policy_ebvla.configuration_groups import ResNetBackboneConfig

from .conftest import TINY_HEAD


def test_pusht_env_features_and_real_env_observations():
    gym_pusht = pytest.importorskip("gym_pusht")  # noqa: F841  (registers the env)
    import gymnasium as gym

    # The features of LeRobot's `lerobot/pusht` dataset: gym_pusht renders 96 px observations.
    config_features = {
        "input_features": {
            "observation.image": PolicyFeature(FeatureType.VISUAL, (3, 96, 96)),
            "observation.state": PolicyFeature(FeatureType.STATE, (2,)),
        },
        "output_features": {"action": PolicyFeature(FeatureType.ACTION, (2,))},
    }
    from lerobot_policy_ebvla import EBVLAConfig

    policy = EBVLAPolicy(
        EBVLAConfig(
            backbone="resnet",
            device="cpu",
            resnet=ResNetBackboneConfig(spatial_softmax_num_keypoints=8),
            **TINY_HEAD,
            **config_features,
        )
    ).eval()
    env_config = PushtEnv()
    env = gym.make(f"{env_config.package_name}/{env_config.task}", **env_config.gym_kwargs)
    observation, _ = env.reset(seed=0)
    for _ in range(3):
        batch = preprocess_observation({k: np.asarray(v)[None] for k, v in observation.items()})
        with torch.inference_mode():
            action = policy.select_action(batch)
        assert action.shape == (1, 2) and torch.isfinite(action).all()
        observation, *_ = env.step(action[0].numpy())
    env.close()


def test_libero_features_two_cameras_8d_state_7d_action():
    """LeRobot's LIBERO observations, through its own env processing, fit a policy with HuggingFaceVLA/libero's
    features: two cameras (`image`: agent view, `image2`: wrist), an 8-d state, 7-d actions.

    The raw observation has the layout of LeRobot's `LiberoEnv` (`pixels` by mapped camera name, nested
    `robot_state`); no simulator is needed.
    """
    from lerobot.envs.configs import LiberoEnv
    from lerobot.processor import LiberoProcessorStep

    from lerobot_policy_ebvla import EBVLAConfig

    env_cfg = LiberoEnv(observation_height=128, observation_width=128)
    assert env_cfg.features_map["pixels/agentview_image"] == "observation.images.image"
    assert env_cfg.features_map["pixels/robot0_eye_in_hand_image"] == "observation.images.image2"
    camera = PolicyFeature(FeatureType.VISUAL, (3, 256, 256))  # the dataset's size; the policy resizes
    config = EBVLAConfig(
        backbone="resnet",
        device="cpu",
        resnet=ResNetBackboneConfig(resize_shape=(96, 96), spatial_softmax_num_keypoints=8),
        input_features={
            "observation.images.image": camera,
            "observation.images.image2": camera,
            "observation.state": PolicyFeature(FeatureType.STATE, (8,)),
        },
        output_features={"action": PolicyFeature(FeatureType.ACTION, (7,))},
        **TINY_HEAD,
    )
    policy = EBVLAPolicy(config).eval()
    rng = np.random.default_rng(0)
    quat = rng.normal(size=(2, 4))
    raw = {
        "pixels": {
            name: rng.integers(0, 256, (2, 128, 128, 3), dtype=np.uint8) for name in ("image", "image2")
        },
        "robot_state": {
            "eef": {
                "pos": rng.normal(size=(2, 3)),
                "quat": quat / np.linalg.norm(quat, axis=1, keepdims=True),
                "mat": np.tile(np.eye(3), (2, 1, 1)),
            },
            "gripper": {"qpos": rng.normal(size=(2, 2)), "qvel": rng.normal(size=(2, 2))},
            "joints": {"pos": rng.normal(size=(2, 7)), "vel": rng.normal(size=(2, 7))},
        },
    }
    batch = LiberoProcessorStep().observation(preprocess_observation(raw))
    assert batch["observation.state"].shape == (2, 8)
    assert (
        batch["observation.images.image"].shape
        == batch["observation.images.image2"].shape
        == (2, 3, 128, 128)
    )
    with torch.inference_mode():
        actions = [policy.select_action(batch) for _ in range(3)]
    assert all(a.shape == (2, 7) and torch.isfinite(a).all() for a in actions)
    assert policy.last_energy.final_energy.shape == (2,)
