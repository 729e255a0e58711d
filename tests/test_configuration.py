"""EBVLAConfig: the paper's Table V defaults, validation and save/load."""

import dataclasses
import json
import math
from operator import attrgetter

import pytest
from lerobot.configs import PreTrainedConfig

from lerobot_policy_ebvla import EBVLAConfig
from lerobot_policy_ebvla.monitoring.ood_report import checkpoint_monitor_score
from lerobot_policy_ebvla.presets import ebvla_config

from .conftest import tiny_config

TABLE_V = {
    "vlm.model_name": "Qwen/Qwen2.5-0.5B",
    "vlm.lora_rank": 64,
    "vlm.num_latent_tokens": 64,  # K_a
    "vlm.num_context_layers": 23,  # N_l
    "n_blocks": 4,  # L
    "n_heads": 8,
    "dim_model": 896,  # D
    "ffn_multiplier": 4,
    "chunk_size": 8,  # H
    "energy_temperature": 9.0,  # tau
    "init_action_std": 1.0,  # sigma_init
    "langevin_noise_std": 0.001,  # sigma_L
    "grad_clip": 1.0,  # c
    "action_clamp": 10.0,  # a_max
    "inference_step_size": 0.22,  # alpha
    "train_step_size_range": (0.05, 0.4),
    "train_mcmc_steps_range": (8, 15),
    "inference_mcmc_steps": 15,  # K_inf
}


def test_defaults_are_the_papers_table_v():
    config = EBVLAConfig(device="cpu")
    for name, value in TABLE_V.items():
        assert attrgetter(name)(config) == value, name
    assert config.backbone == "vlm"
    assert (
        config.contrastive.weight == 0 and config.joint_energy.weight == 0
    )  # no training signal beyond Eq. 4
    assert config.num_restarts == 1 and config.early_stop_tol is None


def test_is_registered_as_ebvla():
    assert PreTrainedConfig.get_choice_class("ebvla") is EBVLAConfig
    assert EBVLAConfig(device="cpu").type == "ebvla"


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("backbone", "vit"),
        ("n_obs_steps", 2),
        ("n_action_steps", 9),
        ("dim_model", 100),
        ("energy_temperature", 0.0),
        ("langevin_noise_std", -1.0),
        ("train_step_size_range", (0.4, 0.05)),
        ("train_mcmc_steps_range", (0, 3)),
        ("inference_mcmc_steps", 0),
        ("vlm.context_layers", (1, 2)),  # one per head block (n_blocks=4)
        ("vlm.context_layers", (-1, 0, 1, 2)),
        ("vlm.lora_rank", 0),
        ("vlm.frozen_weights_dtype", "float16"),
        ("resnet.vision_backbone_stages", 5),
        ("resnet.state_dropout", 1.0),
        ("resnet.camera_tokens", "patches"),
        ("contrastive.weight", -0.1),
        ("contrastive.anchors", 0),
        ("contrastive.dtype", "float16"),
        ("joint_energy.weight", -1.0),
        ("joint_energy.margin", 0.0),
        ("joint_energy.target", "everything"),
        ("joint_energy.corruptions", ("rain",)),
        ("joint_energy.corruption_strength", (0.5, 0.2)),
        ("joint_energy.gradient_penalty", 0.1),  # needs target "observation" and a weight
        ("dropout", 1.0),
        ("energy_bias_init", math.nan),
        ("num_restarts", 0),
        ("restart_energy_threshold", 2.0),  # with num_restarts 1: nothing to restart with
        ("restart_energy_threshold", math.inf),
    ],
)
def test_impossible_values_are_rejected_naming_the_field(field, value):
    group, _, name = field.rpartition(".")
    fields = {group: {name: value}} if group else {field: value}
    with pytest.raises(ValueError, match=f"`{field}`"):
        ebvla_config({"device": "cpu"}, fields)


def test_the_config_adds_at_most_45_top_level_fields_to_lerobots():
    own = {f.name for f in dataclasses.fields(EBVLAConfig)} - {
        f.name for f in dataclasses.fields(PreTrainedConfig)
    }
    assert len(own) <= 45, sorted(own)


def test_a_group_given_as_anything_but_its_dataclass_is_rejected_naming_it():
    with pytest.raises(ValueError, match="`joint_energy` must be a `JointEnergyConfig`"):
        EBVLAConfig(device="cpu", joint_energy={"weight": 0.1})


def test_a_groups_fields_parse_from_the_command_line_next_to_a_saved_config(tmp_path):
    """`lerobot-train --policy.path=... --policy.joint_energy.weight=0.1` reaches the nested field."""
    tiny_config().save_pretrained(tmp_path)
    overrides = [
        "--joint_energy.weight=0.1",
        "--joint_energy.target=observation",
        "--resnet.state_dropout=0.25",
    ]
    config = PreTrainedConfig.from_pretrained(tmp_path, cli_overrides=overrides)
    assert (config.joint_energy.weight, config.joint_energy.target) == (0.1, "observation")
    assert config.resnet.state_dropout == 0.25 and config.context_energy_on_own_encoder


def test_save_and_load_keep_every_field(tmp_path):
    config = tiny_config(
        energy_temperature=5.0,
        train_mcmc_steps_range=(2, 3),
        resnet={"crop_shape": (28, 28), "state_dropout": 0.25},
        contrastive={"weight": 0.2, "anchors": 4},
        joint_energy={"weight": 0.01, "target": "observation", "gradient_penalty": 0.1},
        vlm={"model_config_overrides": {"hidden_size": 64}},
        num_restarts=3,
        restart_energy_threshold=1.5,
    )
    config.save_pretrained(tmp_path)
    loaded = PreTrainedConfig.from_pretrained(tmp_path)
    assert isinstance(loaded, EBVLAConfig)
    for f in dataclasses.fields(config):
        assert getattr(loaded, f.name) == getattr(config, f.name), f.name


# The monitor score: decided by the training signal when the config is made, and saved with the checkpoint.

OWN_ENCODER = {"target": "observation", "weight": 0.01}


def test_the_monitor_score_follows_the_training_signal():
    assert tiny_config().monitor.score == "final_energy"
    assert tiny_config(joint_energy=OWN_ENCODER).monitor.score == "context_phase_energy"
    # A joint energy read off the policy's own backbone has no E_c to monitor with: the paper's energy.
    assert tiny_config(joint_energy={"target": "context", "weight": 0.01}).monitor.score == "final_energy"


def test_a_named_monitor_score_is_kept_and_saved(tmp_path):
    config = tiny_config(joint_energy=OWN_ENCODER, monitor={"score": "final_energy"})
    assert config.monitor.score == "final_energy"
    config.save_pretrained(tmp_path)
    assert json.loads((tmp_path / "config.json").read_text())["monitor"]["score"] == "final_energy"
    assert checkpoint_monitor_score(tmp_path) == "final_energy"
    assert checkpoint_monitor_score(None) == "final_energy"


def test_a_checkpoint_saved_without_a_monitor_score_is_monitored_as_its_training_signal_says(tmp_path):
    tiny_config(joint_energy=OWN_ENCODER).save_pretrained(tmp_path)
    saved = json.loads((tmp_path / "config.json").read_text())
    del saved["monitor"]
    (tmp_path / "config.json").write_text(json.dumps(saved))
    assert checkpoint_monitor_score(tmp_path) == "context_phase_energy"


def test_an_energy_only_score_without_its_encoder_is_refused():
    with pytest.raises(ValueError, match="reads the joint energy's context term E_c on its own encoder"):
        tiny_config(monitor={"score": "context_phase_energy"})


def test_the_failure_check_follows_the_training_signal(tmp_path):
    assert tiny_config().monitor.failure_score == "none"
    config = tiny_config(joint_energy=OWN_ENCODER)
    assert config.monitor.failure_score == "head_energy_two_sided" and config.monitor.failure_chunks == 3
    config.save_pretrained(tmp_path)
    saved = json.loads((tmp_path / "config.json").read_text())
    assert saved["monitor"]["failure_score"] == "head_energy_two_sided"
    # A checkpoint saved before the failure check existed gets it from its training signal.
    del saved["monitor"]["failure_score"]
    (tmp_path / "config.json").write_text(json.dumps(saved))
    assert EBVLAConfig.from_pretrained(tmp_path).monitor.failure_score == "head_energy_two_sided"


@pytest.mark.parametrize(
    ("monitor", "match"),
    [
        ({"failure_score": "context_knn"}, r"`monitor.failure_score` must be one of \('none'"),
        ({"failure_chunks": 0}, "`monitor.failure_chunks` must be >= 1. Got 0"),
        ({"failure_score": "head_energy_two_sided"}, "`monitor.failure_score='head_energy_two_sided'` reads"),
    ],
)
def test_a_failure_check_the_policy_cannot_have_is_refused(monitor, match):
    with pytest.raises(ValueError, match=match):
        tiny_config(monitor=monitor)
