"""`lerobot-rollout` running an ebvla checkpoint on a simulated robot (no hardware).

LeRobot's own rollout tests replace the robot factory the same way; `SimArm` stands in for an SO-100-like arm:
absolute joint-position actions, joint positions as state, one camera.
"""

import sys
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.robots import Robot, RobotConfig

from lerobot_policy_ebvla import EBVLAPolicy
from lerobot_policy_ebvla.runtime import OODCalibration
from tests.conftest import tiny_config
from tests.test_ood_response import BELOW_ALL_ENERGIES, save_checkpoint

JOINT_POSITIONS = (10.0, -20.0, 30.0)
IMAGE_SIZE = 64


@RobotConfig.register_subclass("ebvla_sim_arm")
@dataclass(kw_only=True)
class SimArmConfig(RobotConfig):
    joint_positions: tuple[float, ...] = JOINT_POSITIONS


class SimArm(Robot):
    """A robot without hardware: its joints stay where they are, its camera sees noise, it keeps the actions."""

    config_class = SimArmConfig
    name = "ebvla_sim_arm"

    def __init__(self, config: SimArmConfig):
        super().__init__(config)
        self.config = config
        self.sent_actions: list[dict[str, float]] = []
        self._connected = False
        self._rng = np.random.default_rng(0)

    @property
    def joints(self) -> list[str]:
        return [f"joint_{i}.pos" for i in range(len(self.config.joint_positions))]

    @cached_property
    def observation_features(self) -> dict:
        return {**dict.fromkeys(self.joints, float), "top": (IMAGE_SIZE, IMAGE_SIZE, 3)}

    @cached_property
    def action_features(self) -> dict:
        return dict.fromkeys(self.joints, float)

    @property
    def is_connected(self) -> bool:
        return self._connected

    def connect(self, calibrate: bool = True) -> None:
        self._connected = True

    @property
    def is_calibrated(self) -> bool:
        return True

    def calibrate(self) -> None:
        pass

    def configure(self) -> None:
        pass

    def get_observation(self) -> dict[str, Any]:
        image = self._rng.integers(0, 256, (IMAGE_SIZE, IMAGE_SIZE, 3), dtype=np.uint8)
        return {**dict(zip(self.joints, self.config.joint_positions, strict=True)), "top": image}

    def send_action(self, action: dict[str, Any]) -> dict[str, Any]:
        self.sent_actions.append(dict(action))
        return action

    def disconnect(self) -> None:
        self._connected = False


def sim_arm_policy_config():
    """A tiny policy for `SimArm`: its camera, 3 joint positions in, 3 joint targets out."""
    return tiny_config(
        input_features={
            "observation.images.top": PolicyFeature(FeatureType.VISUAL, (3, IMAGE_SIZE, IMAGE_SIZE)),
            "observation.state": PolicyFeature(FeatureType.STATE, (len(JOINT_POSITIONS),)),
        },
        output_features={"action": PolicyFeature(FeatureType.ACTION, (len(JOINT_POSITIONS),))},
        chunk_size=4,
        n_action_steps=4,
        inference_mcmc_steps=3,
    )


def save_sim_arm_checkpoint(path, calibration: OODCalibration | None = BELOW_ALL_ENERGIES):
    dim = len(JOINT_POSITIONS)
    return save_checkpoint(path, sim_arm_policy_config(), calibration, action_dim=dim, state_dim=dim)


def run_lerobot_rollout(monkeypatch, tmp_path, *flags):
    """Runs `lerobot-rollout`'s main on `SimArm` for 5 s; returns the robot and the loaded policy.

    5 s at 10 fps leaves room for a slow first refinement on a loaded 2-core machine (2 s once sent one action).
    """
    from lerobot.rollout import context
    from lerobot.scripts import lerobot_rollout

    robots, policies = [], []
    monkeypatch.setattr(
        context, "make_robot_from_config", lambda cfg: robots.append(SimArm(cfg)) or robots[-1]
    )
    load_policy = context._load_pretrained_policy
    monkeypatch.setattr(
        context, "_load_pretrained_policy", lambda cfg: policies.append(load_policy(cfg)) or policies[-1]
    )
    checkpoint = save_sim_arm_checkpoint(tmp_path / "checkpoint")
    argv = [
        "lerobot-rollout",
        "--robot.type=ebvla_sim_arm",
        f"--robot.calibration_dir={tmp_path / 'calibration'}",
        f"--policy.path={checkpoint}",
        "--strategy.type=base",
        "--task=reach the goal",
        "--fps=10",
        "--duration=5",
        "--device=cpu",
        "--play_sounds=false",
        "--return_to_initial_position=false",
        *flags,
    ]
    monkeypatch.setattr(sys, "argv", argv)
    torch.manual_seed(0)
    lerobot_rollout.main()
    (robot,), (policy,) = robots, policies
    return robot, policy


def test_lerobot_rollout_drives_a_robot_with_an_ebvla_checkpoint(monkeypatch, tmp_path):
    robot, policy = run_lerobot_rollout(monkeypatch, tmp_path)
    assert isinstance(policy, EBVLAPolicy)
    assert len(robot.sent_actions) >= 4
    assert all(set(action) == set(robot.joints) for action in robot.sent_actions)
    assert all(np.isfinite(list(action.values())).all() for action in robot.sent_actions)
    # The checkpoint's calibration is below every energy: with the default "continue" the chunks are
    # flagged and executed, not held.
    assert policy.last_ood_decision.flagged.all() and not policy.last_ood_decision.held.any()
    assert torch.isfinite(policy.last_energy.final_energy).all()


def test_lerobot_rollout_holds_the_current_joint_positions_when_out_of_distribution(monkeypatch, tmp_path):
    robot, policy = run_lerobot_rollout(
        monkeypatch, tmp_path, "--policy.monitor.response=hold", "--policy.monitor.hold_action=current_state"
    )
    assert policy.last_ood_decision.held.all()
    assert len(robot.sent_actions) >= 4
    for action in robot.sent_actions:
        sent = [action[joint] for joint in robot.joints]
        np.testing.assert_allclose(sent, JOINT_POSITIONS, atol=1e-3)
