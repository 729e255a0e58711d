"""`--env.type=metaworld_ebvla`: LeRobot's MetaWorld env with fast rendering and graded perturbations."""

import os

import numpy as np
import pytest

from lerobot_policy_ebvla.envs import MetaworldEBVLAEnv
from lerobot_policy_ebvla.envs.perturbations import PERTURBATIONS

CAMERA_XML = """
<mujoco>
  <worldbody>
    <camera name="corner2" pos="0.75 0.075 0.7" xyaxes="-0.3 0.95 0 -0.6 -0.2 0.77"/>
    <geom type="plane" size="1 1 0.1"/>
  </worldbody>
</mujoco>
"""


def test_config_rejects_unknown_perturbations_and_severities():
    with pytest.raises(ValueError, match=r"`perturbation` must be one of \('none', 'pose'"):
        MetaworldEBVLAEnv(perturbation="fog", perturbation_severity=1)
    with pytest.raises(ValueError, match=r"`camera_perturbation` must be one of \('none', 'pose'"):
        MetaworldEBVLAEnv(camera_perturbation="fog")
    for severity in (6, -1, 2.5):
        with pytest.raises(ValueError, match=r"`perturbation_severity` must be an int in \[0, 5\]"):
            MetaworldEBVLAEnv(perturbation="noise", perturbation_severity=severity)
    with pytest.raises(ValueError, match="needs a `perturbation` other than 'none'"):
        MetaworldEBVLAEnv(perturbation_severity=2)
    with pytest.raises(ValueError, match="disagree"):
        MetaworldEBVLAEnv(perturbation="noise", camera_perturbation="pose", perturbation_severity=1)
    with pytest.raises(ValueError, match="max_episode_steps"):
        MetaworldEBVLAEnv(max_episode_steps=501)


def test_config_names_the_applied_perturbation_and_keeps_the_old_field_name_working():
    old_name = MetaworldEBVLAEnv(camera_perturbation="fov", perturbation_severity=3)
    assert (old_name.perturbation, old_name.gym_kwargs["perturbation"]) == ("fov", "fov")
    lighting = MetaworldEBVLAEnv(perturbation="light_dim", perturbation_severity=2)
    assert (lighting.perturbation, lighting.camera_perturbation) == ("light_dim", "light_dim")
    # At severity 0 nothing is applied, and the config says so (energy records store this name).
    assert MetaworldEBVLAEnv(perturbation="blur", perturbation_severity=0).perturbation == "none"


def test_gym_env_rejects_unknown_perturbations():
    pytest.importorskip("metaworld")
    from lerobot_policy_ebvla.envs.metaworld import MetaworldEBVLAGymEnv

    with pytest.raises(ValueError, match="`perturbation` must be one of"):
        MetaworldEBVLAGymEnv(task="reach-v3", perturbation="fog", perturbation_severity=1)
    with pytest.raises(ValueError, match="`perturbation_severity`"):
        MetaworldEBVLAGymEnv(task="reach-v3", perturbation="noise", perturbation_severity=9)


def test_config_keeps_lerobots_metaworld_features():
    from lerobot.envs.configs import MetaworldEnv

    ours = MetaworldEBVLAEnv(task="push-v3", fast_render=True, perturbation="pose", perturbation_severity=5)
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


TASK = "push-v3"  # its puck and goal are visible, as in the gallery (research/benchmarks/metaworld_perturbation_gallery.py)
GRADED_IMAGE_PERTURBATIONS = [p for p in PERTURBATIONS if p not in ("none", "blank", "robot_init")]


def _first_observation(perturbation: str, severity: int, steps: int = 0):
    """The observation after reset(seed=0) and `steps` zero actions, and MetaWorld's 39-d state."""
    pytest.importorskip("metaworld")
    os.environ.setdefault("MUJOCO_GL", "egl")
    from lerobot_policy_ebvla.envs.metaworld import MetaworldEBVLAGymEnv

    cfg = MetaworldEBVLAEnv(task=TASK, fast_render=True)
    kwargs = {**cfg.gym_kwargs, "perturbation": perturbation, "perturbation_severity": severity}
    env = MetaworldEBVLAGymEnv(task=TASK, **kwargs)
    try:
        observation, _ = env.reset(seed=0)
        for _ in range(steps):
            observation, *_ = env.step(np.zeros(4, dtype=np.float32))
        assert env._env.model.light_castshadow.sum() == 0
        return observation, env.state_obs.copy()
    finally:
        env.close()


@pytest.fixture(scope="module")
def vanilla():
    return _first_observation("none", 0)


def _pixel_change(observation, vanilla_observation) -> float:
    return float(np.abs(observation["pixels"].astype(int) - vanilla_observation["pixels"].astype(int)).mean())


@pytest.mark.parametrize("perturbation", PERTURBATIONS[1:])
def test_severity_zero_leaves_the_observation_identical_to_vanilla(perturbation, vanilla):
    observation, state = _first_observation(perturbation, 0)
    np.testing.assert_array_equal(observation["pixels"], vanilla[0]["pixels"])
    np.testing.assert_array_equal(state, vanilla[1])


@pytest.mark.parametrize("perturbation", GRADED_IMAGE_PERTURBATIONS)
def test_image_change_grows_with_severity_and_keeps_keys_and_shapes(perturbation, vanilla):
    changes = []
    for severity in (1, 3, 5):
        observation, state = _first_observation(perturbation, severity)
        assert observation.keys() == vanilla[0].keys() == {"pixels", "agent_pos"}
        assert observation["pixels"].shape == (480, 480, 3) and observation["pixels"].dtype == np.uint8
        assert observation["agent_pos"].shape == (4,)
        np.testing.assert_array_equal(state, vanilla[1])  # the scene looks different, the state is the same
        changes.append(_pixel_change(observation, vanilla[0]))
    assert 0 < changes[0] < changes[1] < changes[2], changes


def test_blank_camera_is_black_at_every_severity(vanilla):
    for severity in (1, 5):
        observation, state = _first_observation("blank", severity)
        assert observation["pixels"].shape == vanilla[0]["pixels"].shape
        assert not observation["pixels"].any()
        np.testing.assert_array_equal(state, vanilla[1])


def test_an_all_black_render_is_refused_not_passed_on_as_an_observation(monkeypatch):
    pytest.importorskip("metaworld")
    os.environ.setdefault("MUJOCO_GL", "egl")
    from lerobot_policy_ebvla.envs.metaworld import MetaworldEBVLAGymEnv

    cfg = MetaworldEBVLAEnv(task=TASK, fast_render=True)
    env = MetaworldEBVLAGymEnv(task=TASK, **cfg.gym_kwargs)
    try:
        env.reset(seed=0)
        # What a dead offscreen GL context hands back.
        monkeypatch.setattr(env._env, "render", lambda: np.zeros((480, 480, 3), dtype=np.uint8))
        with pytest.raises(RuntimeError, match=r"all-black \(480, 480, 3\) frame.*offscreen renderer"):
            env.step(np.zeros(4, dtype=np.float32))
    finally:
        env.close()


@pytest.mark.parametrize("other_env_ends", ["closed_then_collected", "closed_after", "collected_unclosed"])
def test_an_env_renders_the_same_frames_whatever_another_env_in_the_process_does(other_env_ends):
    """Gymnasium's viewers share one thread's GL state: a second env's context, or the collector freeing a
    first env's `MjrContext` in the wrong context, once turned a later env's frames black."""
    pytest.importorskip("metaworld")
    os.environ.setdefault("MUJOCO_GL", "egl")
    import gc

    from lerobot_policy_ebvla.envs.metaworld import MetaworldEBVLAGymEnv

    def make():
        env = MetaworldEBVLAGymEnv(task=TASK, observation_size=32, fast_render=True)
        env.reset(seed=0)
        return env

    alone = make()
    expected = alone.reset(seed=3)[0]["pixels"]
    alone.close()
    other = make()
    if other_env_ends == "closed_then_collected":
        other.close()
    env = make()
    if other_env_ends == "closed_after":
        other.close()
    del other
    gc.collect()
    try:
        np.testing.assert_array_equal(env.reset(seed=3)[0]["pixels"], expected)
    finally:
        env.close()


def test_robot_init_moves_the_hand_by_a_graded_distance_and_leaves_the_objects(vanilla):
    from lerobot_policy_ebvla.envs.metaworld import HAND_OFFSET_M_PER_LEVEL

    for severity in (1, 3, 5):
        observation, state = _first_observation("robot_init", severity)
        moved = np.linalg.norm(observation["agent_pos"][:3] - vanilla[0]["agent_pos"][:3])
        assert moved == pytest.approx(HAND_OFFSET_M_PER_LEVEL * severity, rel=0.1)
        np.testing.assert_array_equal(state[4:7], vanilla[1][4:7])  # the object starts where it did
        assert _pixel_change(observation, vanilla[0]) > 0


def test_distractors_stay_in_every_frame():
    clean, _ = _first_observation("none", 0, steps=2)
    distracted, _ = _first_observation("distractor", 5, steps=2)
    assert _pixel_change(distracted, clean) > 1.0


def test_pixel_noise_has_the_documented_std_and_follows_the_reset_seed(vanilla):
    from lerobot_policy_ebvla.envs.sensor import NOISE_STD_PER_LEVEL

    first, _ = _first_observation("noise", 1)
    again, _ = _first_observation("noise", 1)
    np.testing.assert_array_equal(first["pixels"], again["pixels"])
    residual = first["pixels"].astype(float) - vanilla[0]["pixels"].astype(float)
    assert residual.std() == pytest.approx(NOISE_STD_PER_LEVEL, rel=0.05)


def test_vector_envs_follow_lerobots_task_groups():
    pytest.importorskip("metaworld")
    import gymnasium as gym

    envs = MetaworldEBVLAEnv(task="reach-v3,push-v3", fast_render=True).create_envs(n_envs=1)
    assert {group: list(tasks) for group, tasks in envs.items()} == {"reach-v3": [0], "push-v3": [0]}
    assert isinstance(envs["reach-v3"][0], gym.vector.SyncVectorEnv)
    for tasks in envs.values():
        for env in tasks.values():
            env.close()


def test_observation_size_is_checked_and_changes_only_the_declared_frame_shape():
    for size in (8, 481):
        with pytest.raises(
            ValueError, match=f"`observation_size` must be between 16 and 480 pixels.*got {size}"
        ):
            MetaworldEBVLAEnv(observation_size=size)
    small = MetaworldEBVLAEnv(task="push-v3", observation_size=96)
    assert small.features["pixels/top"].shape == (96, 96, 3)
    assert small.gym_kwargs["observation_size"] == 96
    default = MetaworldEBVLAEnv(task="push-v3")
    assert {k: f for k, f in small.features.items() if k != "pixels/top"} == {
        k: f for k, f in default.features.items() if k != "pixels/top"
    }


def test_small_frames_are_rendered_at_their_size_and_show_the_same_scene(vanilla):
    """A 120 px frame is rendered at 120 px (not resized from 480): it matches the 480 px frame shrunk 4x."""
    import cv2

    from lerobot_policy_ebvla.envs.metaworld import MetaworldEBVLAGymEnv

    env = MetaworldEBVLAGymEnv(task=TASK, fast_render=True, observation_size=120, obs_type="pixels_agent_pos")
    try:
        observation, _ = env.reset(seed=0)
        assert observation["pixels"].shape == (120, 120, 3)
        assert env.observation_space["pixels"].shape == (120, 120, 3)
        assert env._env.mujoco_renderer.viewer.viewport.width == 120  # the renderer's own buffer
        np.testing.assert_array_equal(observation["agent_pos"], vanilla[0]["agent_pos"])
        shrunk = cv2.resize(vanilla[0]["pixels"], (120, 120), interpolation=cv2.INTER_AREA).astype(int)
        shifted = np.roll(shrunk, 3, axis=1)  # the same frame, 3 px to the side
        error = np.abs(observation["pixels"].astype(int) - shrunk).mean()
        assert error < 0.3 * np.abs(shifted - shrunk).mean(), error
    finally:
        env.close()


def test_blur_is_the_same_fraction_of_a_smaller_frame():
    pytest.importorskip("metaworld")
    from lerobot_policy_ebvla.envs.sensor import perturb_image

    rng = np.random.default_rng(0)
    edge = np.zeros((480, 480, 3), np.uint8)
    edge[:, 240:] = 255
    small = edge[::4, ::4].copy()
    row_large = perturb_image(edge, "blur", 5, rng)[240, :, 0].astype(float)
    row_small = perturb_image(small, "blur", 5, rng)[60, :, 0].astype(float)
    # Width of the ramp from 10% to 90%: 4x fewer pixels in the 4x smaller frame.

    def ramp(row):
        return np.count_nonzero((row > 25.5) & (row < 229.5))

    assert ramp(row_large) == pytest.approx(4 * ramp(row_small), rel=0.4)


def _frames_of_a_moving_arm(render_every: int, perturbation: str, steps: int) -> list[np.ndarray]:
    """The observed frames of reset(seed=0) and `steps` steps of a hand moving sideways in view."""
    from lerobot_policy_ebvla.envs.metaworld import MetaworldEBVLAGymEnv

    severity = 0 if perturbation == "none" else 3
    env = MetaworldEBVLAGymEnv(
        task=TASK,
        fast_render=True,
        observation_size=64,
        perturbation=perturbation,
        perturbation_severity=severity,
        render_every=render_every,
    )
    try:
        observation, _ = env.reset(seed=0)
        frames = [observation["pixels"].copy()]
        for _ in range(steps):
            observation, *_ = env.step(np.array([1.0, 0.0, 0.0, 0.0], dtype=np.float32))
            frames.append(observation["pixels"].copy())
        return frames
    finally:
        env.close()


@pytest.mark.parametrize("perturbation", ["none", "noise", "distractor"])
def test_rendering_every_n_th_step_draws_the_frames_a_chunked_policy_reads_unchanged(perturbation):
    """`render_every=4` draws the reset's frame and every 4th step's, pixel for pixel those of an env that draws
    every step (the sensor noise is drawn alike on every step; a distractor is in every drawn frame); the steps
    between repeat the last drawn frame."""
    pytest.importorskip("metaworld")
    os.environ.setdefault("MUJOCO_GL", "egl")
    every = _frames_of_a_moving_arm(1, perturbation, 8)
    fourth = _frames_of_a_moving_arm(4, perturbation, 8)
    for step in (0, 4, 8):
        np.testing.assert_array_equal(every[step], fourth[step])
    if perturbation == "none":
        assert np.abs(every[3].astype(int) - every[0]).mean() > 0.5  # the arm moved in view
        np.testing.assert_array_equal(fourth[3], fourth[0])


def test_render_every_is_checked_and_passed_to_the_env():
    with pytest.raises(ValueError, match="render_every"):
        MetaworldEBVLAEnv(task="push-v3", render_every=0)
    assert MetaworldEBVLAEnv(task="push-v3", render_every=8).gym_kwargs["render_every"] == 8


def test_a_video_frame_is_drawn_fresh_and_leaves_the_observed_frames_as_they_were():
    pytest.importorskip("metaworld")
    os.environ.setdefault("MUJOCO_GL", "egl")
    from lerobot_policy_ebvla.envs.metaworld import MetaworldEBVLAGymEnv

    env = MetaworldEBVLAGymEnv(task=TASK, fast_render=True, observation_size=64, render_every=4)
    try:
        first, _ = env.reset(seed=0)
        move = np.array([1.0, 0.0, 0.0, 0.0], dtype=np.float32)
        for _ in range(3):
            observation, *_ = env.step(move)
        video = env.render()
        assert np.abs(video.astype(int) - first["pixels"]).mean() > 0.5  # the arm has moved since the reset
        observation, *_ = env.step(move)  # step 4's frame is drawn...
        np.testing.assert_array_equal(
            _frames_of_a_moving_arm(1, "none", 4)[4], observation["pixels"]
        )  # ...as an ungated env draws it
    finally:
        env.close()
