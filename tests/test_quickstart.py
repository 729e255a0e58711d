"""`ebvla-quickstart`: its command line, its guards, its summary (`monitoring.summary`), and the whole
pipeline at a tiny size."""

import json
import math
from operator import attrgetter

import pytest

from lerobot_policy_ebvla import EnergyMonitor
from lerobot_policy_ebvla.monitoring import (
    EnergyRecord,
    group_by_episode,
    read_energy_records,
    write_energy_records,
)
from lerobot_policy_ebvla.monitoring.summary import condition_summary, energy_aurocs
from lerobot_policy_ebvla.pipelines.quickstart import RUN_MARKER, SUMMARY_FILENAME, QuickstartConfig
from lerobot_policy_ebvla.presets import LIGHT_POLICY
from lerobot_policy_ebvla.scripts import quickstart

# The whole pipeline in about 30 s on a 2-core CPU: one expert episode, two training steps of a tiny head,
# one 8-step rollout per condition, two frames for the camera check.
TINY = [
    "--record_episodes=1",
    "--image_size=48",
    "--steps=2",
    "--batch_size=2",
    "--eval_episodes=1",
    "--calibration_episodes=2",
    "--max_episode_steps=8",
    "--vision_frames=2",
    "--perturbation=light_dim",
    "--perturbation_severity=5",
    "--policy.dim_model=16",
    "--policy.n_heads=2",
    "--policy.n_blocks=1",
    "--policy.resnet.resize_shape=[40,40]",
    "--policy.resnet.spatial_softmax_num_keypoints=4",
    "--policy.inference_mcmc_steps=2",
    "--policy.train_mcmc_steps_range=[1,1]",
]


def test_policy_flags_override_the_light_policy_and_keep_its_other_values():
    cfg = quickstart.parse_config(["--policy.dim_model=64", "--task=push-v3"])

    assert cfg.task == "push-v3" and cfg.policy.dim_model == 64
    for name in ("backbone", "n_heads", "n_blocks", "train_mcmc_steps_range"):
        assert getattr(cfg.policy, name) == LIGHT_POLICY[name], name
    assert cfg.policy.resnet.resize_shape == LIGHT_POLICY["resnet"]["resize_shape"]


def test_a_groups_flag_overrides_that_field_and_keeps_the_groups_other_light_policy_values():
    cfg = quickstart.parse_config(["--policy.joint_energy.weight=0.1"])

    assert cfg.policy.joint_energy.weight == 0.1
    assert cfg.policy.joint_energy.gradient_penalty == LIGHT_POLICY["joint_energy"]["gradient_penalty"]
    assert cfg.policy.joint_energy.target == "observation"


def light_policy_leaves():
    """(dotted name, value) of every field `LIGHT_POLICY` sets, a group's as `group.field`."""
    for name, value in LIGHT_POLICY.items():
        if isinstance(value, dict):
            yield from ((f"{name}.{field}", v) for field, v in value.items())
        else:
            yield name, value


def test_defaults_are_the_light_policy_from_the_command_line_and_from_python():
    from_cli, from_python = quickstart.parse_config([]), QuickstartConfig()

    for name, value in light_policy_leaves():
        assert attrgetter(name)(from_cli.policy) == attrgetter(name)(from_python.policy) == value, name


def test_help_lists_the_quickstart_options(capsys):
    with pytest.raises(SystemExit) as exit_info:
        quickstart.parse_config(["--help"])

    assert exit_info.value.code == 0
    help_text = capsys.readouterr().out
    for option in (
        "--task",
        "--output_dir",
        "--steps",
        "--perturbation",
        "--policy.dim_model",
        "--policy.joint_energy.weight",
    ):
        assert option in help_text, option


@pytest.mark.parametrize(
    ("argument", "field"),
    [
        ("--steps=0", "steps"),
        ("--eval_episodes=0", "eval_episodes"),
        ("--calibration_episodes=1", "calibration_episodes"),
        ("--policy.resnet.resize_shape=[8,8]", "resize_shape"),
        ("--perturbation=rain", "perturbation"),
        ("--policy.backbone=vlm", "backbone"),
    ],
)
def test_rejects_invalid_values_naming_the_field(argument, field):
    with pytest.raises(ValueError, match=field):
        quickstart.parse_config([argument])


def test_perturbed_condition_is_evaluated_beside_vanilla_and_blank():
    cfg = quickstart.parse_config(["--perturbation=fov", "--perturbation_severity=4"])

    assert cfg.conditions() == {"vanilla": ("none", 0), "blank": ("blank", 1), "fov_s4": ("fov", 4)}
    assert list(quickstart.parse_config(["--perturbation=none"]).conditions()) == ["vanilla", "blank"]


def test_refuses_to_replace_a_previous_run_without_overwrite(tmp_path):
    (tmp_path / "train").mkdir()
    with pytest.raises(SystemExit, match="--overwrite"):
        quickstart.main([f"--output_dir={tmp_path}"])
    assert (tmp_path / "train").is_dir()


def test_refuses_a_run_in_progress_before_train_dir_exists(tmp_path):
    (tmp_path / RUN_MARKER).write_text("{}\n")
    with pytest.raises(SystemExit, match="--overwrite"):
        quickstart.main([f"--output_dir={tmp_path}"])


def test_summary_splits_final_energy_by_episode_outcome(tmp_path):
    def chunk(episode, index, final, success):
        return EnergyRecord(episode, index, 8 * index, 1.0, final, success, "button-press-v3", 1000 + episode)

    records = [chunk(0, 0, 0.5, True), chunk(0, 1, 1.5, True), chunk(1, 0, 3.0, False)]
    write_energy_records(tmp_path / "energy_records.jsonl", records)

    summary = condition_summary(group_by_episode(read_energy_records(tmp_path)))

    assert summary["n_episodes"] == 2 and summary["n_success"] == 1
    assert summary["success_rate"] == 0.5
    assert math.isclose(summary["mean_final_energy_success"], 1.0)
    assert math.isclose(summary["mean_final_energy_failure"], 3.0)
    assert [e["chunks"] for e in summary["episodes"]] == [2, 1]


def test_energy_aurocs_rank_each_condition_against_vanilla_and_failures_against_successes():
    def episode(final, success):
        return {"mean_final_energy": final, "success": success}

    conditions = {
        "vanilla": {"episodes": [episode(-5.0, True), episode(-4.0, True), episode(-3.0, False)]},
        "blank": {"episodes": [episode(-2.0, False), episode(-4.5, True)]},
    }

    aurocs = energy_aurocs(conditions, reference="vanilla")

    # Pairs where blank is higher: -4.5 beats -5.0 only (1 of 3), -2.0 beats all three (3 of 3): 4 / 6.
    assert math.isclose(aurocs["blank"], 4 / 6)
    # failed (-3.0, -2.0) against successful (-5.0, -4.0, -4.5): always higher.
    assert aurocs["failed_vs_successful"] == 1.0
    assert "vanilla" not in aurocs


@pytest.mark.slow
def test_records_trains_evaluates_three_conditions_and_checks_the_camera(tmp_path, capsys):
    quickstart.main([f"--output_dir={tmp_path}", *TINY])

    summary = json.loads((tmp_path / SUMMARY_FILENAME).read_text())
    assert list(summary["conditions"]) == ["vanilla", "blank", "light_dim_s5"]
    for name, condition in summary["conditions"].items():
        assert condition["n_episodes"] == 1, name
        assert math.isfinite(condition["mean_final_energy"]), name
        assert (tmp_path / "eval" / name / "energy_records.jsonl").is_file()
    assert set(summary["energy_auroc"]) == {"blank", "light_dim_s5", "failed_vs_successful"}
    # The checkpoint's monitor, calibrated on two vanilla rollouts of other seeds and saved beside the weights.
    checkpoint = tmp_path / "train" / "checkpoints" / "last" / "pretrained_model"
    monitor = EnergyMonitor.from_pretrained(checkpoint)
    assert monitor.ood.n_rollouts == 2 and monitor.failure.n_rollouts == 2
    calibration = group_by_episode(read_energy_records(tmp_path / "eval" / "calibration"))
    assert {episode[0].seed for episode in calibration.values()} == {101000, 101001}  # evaluation: 1000 on
    assert summary["monitor"]["score"] == "context_phase_energy" and summary["monitor"]["n_calibration"] == 2
    assert set(summary["monitor"]["unfamiliar"]) == {"vanilla", "blank", "light_dim_s5"}
    assert summary["monitor"]["unfamiliar"]["blank"]["alarmed"][1] == 1
    failing = summary["monitor"]["failing"]
    assert failing["score"] == "head_energy_two_sided" and failing["n_failed"] + failing["n_successful"] == 3
    assert (tmp_path / "monitor" / "ood_report.md").is_file()
    assert summary["camera_check"]["num_frames"] == 2
    assert math.isfinite(summary["camera_check"]["energy_blank"])
    assert (tmp_path / "train" / "checkpoints" / "last" / "pretrained_model" / "model.safetensors").is_file()
    printed = capsys.readouterr().out
    assert "Camera check on 2 dataset frames" in printed and "light_dim_s5" in printed
    assert "The paper's raw final energy, AUROC of the episodes' mean" in printed
    assert (
        "unfamiliar (context_phase_energy)" in printed
        and "failing (head_energy_two_sided, first 3 chunks)" in printed
    )
