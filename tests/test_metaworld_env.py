"""`--env.type=metaworld_ebvla`: LeRobot's MetaWorld env with fast rendering and camera perturbations."""

import os

import numpy as np
import pytest

from lerobot_policy_ebvla.envs import MetaworldEBVLAEnv

CAMERA_XML = """
<mujoco>
  <worldbody>
    <camera name="corner2" pos="0.75 0.075 0.7" xyaxes="-0.3 0.95 0 -0.6 -0.2 0.77"/>
    <geom type="plane" size="1 1 0.1"/>
  </worldbody>
</mujoco>
"""


def test_config_rejects_unknown_perturbations_and_severities():
    with pytest.raises(ValueError, match="camera_perturbation"):
        MetaworldEBVLAEnv(camera_perturbation="blur")
    with pytest.raises(ValueError, match="perturbation_severity"):
        MetaworldEBVLAEnv(camera_perturbation="pose", perturbation_severity=6)
    with pytest.raises(ValueError, match="camera_perturbation"):
        MetaworldEBVLAEnv(perturbation_severity=2)
    with pytest.raises(ValueError, match="max_episode_steps"):
        MetaworldEBVLAEnv(max_episode_steps=501)


def test_config_keeps_lerobots_metaworld_features():
    from lerobot.envs.configs import MetaworldEnv

    ours = MetaworldEBVLAEnv(
        task="push-v3", fast_render=True, camera_perturbation="pose", perturbation_severity=5
    )
    assert ours.features == MetaworldEnv(task="push-v3").features
    assert ours.features_map == MetaworldEnv(task="push-v3").features_map


def _camera_model():
    mujoco = pytest.importorskip("mujoco")
    return mujoco, mujoco.MjModel.from_xml_string(CAMERA_XML)


def _optical_axis(mujoco, model, camera_id):
    forward = np.zeros(3)
    mujoco.mju_rotVecQuat(forward, np.array([0.0, 0.0, -1.0]), model.cam_quat[camera_id])
    return model.cam_pos[camera_id].copy(), forward


def _table_point(position, forward):
    return position - position[2] / forward[2] * forward


def test_pose_perturbation_orbits_the_camera_around_the_point_it_looks_at():
    pytest.importorskip("metaworld")
    from lerobot_policy_ebvla.envs.metaworld import perturb_camera

    mujoco, model = _camera_model()
    position, forward = _optical_axis(mujoco, model, 0)
    perturb_camera(model, "corner2", "pose", 3)
    new_position, new_forward = _optical_axis(mujoco, model, 0)
    np.testing.assert_allclose(
        _table_point(new_position, new_forward), _table_point(position, forward), atol=1e-6
    )
    pivot = _table_point(position, forward)
    assert np.linalg.norm(new_position - pivot) == pytest.approx(np.linalg.norm(position - pivot))
    assert new_position[2] > position[2]  # positive elevation raises the camera
    assert model.cam_fovy[0] == pytest.approx(45.0)  # MuJoCo's default, untouched by "pose"


def test_fov_perturbation_widens_the_field_of_view_with_severity():
    pytest.importorskip("metaworld")
    from lerobot_policy_ebvla.envs.metaworld import perturb_camera

    mujoco, model = _camera_model()
    position = model.cam_pos[0].copy()
    perturb_camera(model, "corner2", "fov", 5)
    assert model.cam_fovy[0] == pytest.approx(45.0 * 1.5)
    np.testing.assert_array_equal(model.cam_pos[0], position)


def test_severity_zero_changes_nothing():
    pytest.importorskip("metaworld")
    from lerobot_policy_ebvla.envs.metaworld import perturb_camera

    mujoco, model = _camera_model()
    before = (model.cam_pos.copy(), model.cam_quat.copy(), model.cam_fovy.copy())
    perturb_camera(model, "corner2", "pose_fov", 0)
    for a, b in zip(before, (model.cam_pos, model.cam_quat, model.cam_fovy), strict=True):
        np.testing.assert_array_equal(a, b)


def test_perturbed_fast_env_keeps_observation_keys_and_shapes_but_changes_the_image():
    pytest.importorskip("metaworld")
    os.environ.setdefault("MUJOCO_GL", "egl")
    from lerobot_policy_ebvla.envs.metaworld import MetaworldEBVLAGymEnv

    observations = {}
    for perturbation, severity in (("none", 0), ("pose", 2)):
        cfg = MetaworldEBVLAEnv(
            task="reach-v3",
            fast_render=True,
            camera_perturbation=perturbation,
            perturbation_severity=severity,
        )
        env = MetaworldEBVLAGymEnv(task="reach-v3", **cfg.gym_kwargs)
        observations[perturbation], _ = env.reset(seed=0)
        assert env.state_obs.shape == (39,)  # what the scripted experts act on
        assert env._env.model.light_castshadow.sum() == 0
        env.close()
    vanilla, perturbed = observations["none"], observations["pose"]
    assert vanilla.keys() == perturbed.keys() == {"pixels", "agent_pos"}
    assert vanilla["pixels"].shape == perturbed["pixels"].shape == (480, 480, 3)
    np.testing.assert_array_equal(vanilla["agent_pos"], perturbed["agent_pos"])
    assert np.abs(vanilla["pixels"].astype(int) - perturbed["pixels"].astype(int)).mean() > 5


def test_vector_envs_follow_lerobots_task_groups():
    pytest.importorskip("metaworld")
    import gymnasium as gym

    envs = MetaworldEBVLAEnv(task="reach-v3,push-v3", fast_render=True).create_envs(n_envs=1)
    assert {group: list(tasks) for group, tasks in envs.items()} == {"reach-v3": [0], "push-v3": [0]}
    assert isinstance(envs["reach-v3"][0], gym.vector.SyncVectorEnv)
    for tasks in envs.values():
        for env in tasks.values():
            env.close()
