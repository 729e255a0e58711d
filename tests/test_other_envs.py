"""An ebvla policy built for LeRobot's other environments runs on their observation formats."""

import numpy as np
import pytest
import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.envs.configs import PushtEnv
from lerobot.envs.utils import preprocess_observation

from lerobot_policy_ebvla import EBVLAPolicy

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
            backbone="resnet", device="cpu", spatial_softmax_num_keypoints=8, **TINY_HEAD, **config_features
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
    """LIBERO's LeRobot datasets and env processor give two 256 px cameras, an 8-dim state, 7-dim actions."""
    from lerobot_policy_ebvla import EBVLAConfig

    camera = PolicyFeature(FeatureType.VISUAL, (3, 256, 256))
    config = EBVLAConfig(
        backbone="resnet",
        device="cpu",
        resize_shape=(96, 96),
        spatial_softmax_num_keypoints=8,
        input_features={
            "observation.images.image": camera,
            "observation.images.image2": camera,
            "observation.state": PolicyFeature(FeatureType.STATE, (8,)),
        },
        output_features={"action": PolicyFeature(FeatureType.ACTION, (7,))},
        **TINY_HEAD,
    )
    policy = EBVLAPolicy(config).eval()
    batch = {
        "observation.images.image": torch.rand(2, 3, 256, 256),
        "observation.images.image2": torch.rand(2, 3, 256, 256),
        "observation.state": torch.randn(2, 8),
    }
    with torch.inference_mode():
        actions = [policy.select_action(batch) for _ in range(3)]
    assert all(a.shape == (2, 7) and torch.isfinite(a).all() for a in actions)
    assert policy.last_energy.final_energy.shape == (2,)
