"""EBVLAConfig: the paper's Table V defaults, validation and save/load."""

import dataclasses
import math

import pytest
from lerobot.configs import PreTrainedConfig

from lerobot_policy_ebvla import EBVLAConfig

from .conftest import tiny_config

TABLE_V = {
    "vlm_model_name": "Qwen/Qwen2.5-0.5B",
    "lora_rank": 64,
    "num_latent_tokens": 64,  # K_a
    "num_context_layers": 23,  # N_l
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
        assert getattr(config, name) == value, name
    assert config.backbone == "vlm"
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
        ("context_layers", (1, 2)),
        ("dropout", 1.0),
        ("num_restarts", 0),
        ("restart_energy_threshold", 2.0),  # with num_restarts 1: nothing to restart with
        ("restart_energy_threshold", math.inf),
    ],
)
def test_impossible_values_are_rejected_naming_the_field(field, value):
    with pytest.raises(ValueError, match=f"`{field}`"):
        EBVLAConfig(device="cpu", **{field: value})


def test_save_and_load_keep_every_field(tmp_path):
    config = tiny_config(
        energy_temperature=5.0,
        train_mcmc_steps_range=(2, 3),
        crop_shape=(28, 28),
        num_restarts=3,
        restart_energy_threshold=1.5,
        vlm_config_overrides={"hidden_size": 64},
    )
    config.save_pretrained(tmp_path)
    loaded = PreTrainedConfig.from_pretrained(tmp_path)
    assert isinstance(loaded, EBVLAConfig)
    for f in dataclasses.fields(config):
        assert getattr(loaded, f.name) == getattr(config, f.name), f.name
