"""A checkpoint saved by an earlier version still loads offline and acts the same."""

import dataclasses
import json
from operator import attrgetter
from pathlib import Path

import pytest
import torch
from lerobot.configs import PreTrainedConfig
from lerobot.policies.factory import make_pre_post_processors
from safetensors import safe_open

from lerobot_policy_ebvla import EBVLAConfig, EBVLAPolicy
from lerobot_policy_ebvla.configuration_ebvla import (
    LEGACY_COMPILE_FIELDS,
    LEGACY_FIELDS,
    upgrade_legacy_fields,
)
from lerobot_policy_ebvla.presets import light_policy_config

FIXTURES = sorted((Path(__file__).parent / "fixtures").glob("ebvla_*"))


@pytest.mark.parametrize("checkpoint", FIXTURES, ids=[f.name for f in FIXTURES])
def test_saved_checkpoint_loads_and_reproduces_its_actions(checkpoint):
    with safe_open(checkpoint / "expected.safetensors", framework="pt") as f:
        metadata = f.metadata()
        tensors = {k: f.get_tensor(k) for k in f.keys()}  # noqa: SIM118
    batch = {k.removeprefix("input."): v for k, v in tensors.items() if k.startswith("input.")}
    batch["task"] = metadata["tasks"].split("\n")

    policy = EBVLAPolicy.from_pretrained(checkpoint)
    preprocessor, _ = make_pre_post_processors(policy.config, pretrained_path=str(checkpoint))
    with torch.inference_mode():
        actions = policy.predict_action_chunk(
            preprocessor(batch), generator=torch.Generator().manual_seed(int(metadata["seed"]))
        )
    torch.testing.assert_close(actions, tensors["expected_normalized_actions"], rtol=1e-4, atol=1e-5)


def test_there_is_a_fixture_to_load():
    assert FIXTURES, "tests/fixtures holds no saved checkpoint"


PRE_NESTING = Path(__file__).parent / "fixtures" / "ebvla_light_preset_pre_nesting"
# What fixtures/make_light_preset_fixture.py changed from the light preset, in today's nested form.
SMALL = {
    "resnet": {"vision_backbone_stages": 1, "spatial_softmax_num_keypoints": 8},
    "dim_model": 32,
    "n_heads": 2,
    "n_blocks": 1,
}


def load_pre_nesting_config() -> EBVLAConfig:
    with pytest.warns(FutureWarning, match="saved before its fields were grouped"):
        return EBVLAConfig.from_pretrained(PRE_NESTING)


def test_the_light_preset_saved_before_the_groups_loads_as_todays_light_preset():
    loaded = load_pre_nesting_config()
    features = {"input_features": loaded.input_features, "output_features": loaded.output_features}
    expected = light_policy_config(device="cpu", **features, **SMALL)
    # The preset's starting energy came after the fixture: read only when a head is built, it changes nothing of
    # a saved checkpoint, whose weights hold the bias it trained to; an old config keeps the plain 0.
    assert loaded.energy_bias_init == 0.0 and expected.energy_bias_init == 18.0
    # So did E_c's 32 px encoder and its penalty on one step in 4: an old checkpoint's E_c keeps the frames and the
    # penalty it trained with.
    old_e_c, new_e_c = loaded.joint_energy, expected.joint_energy
    assert (old_e_c.encoder_resize_shape, old_e_c.gradient_penalty_every) == (None, 1)
    assert (new_e_c.encoder_resize_shape, new_e_c.gradient_penalty_every) == ((32, 32), 4)
    assert dataclasses.replace(new_e_c, encoder_resize_shape=None, gradient_penalty_every=1) == old_e_c
    for field in dataclasses.fields(EBVLAConfig):
        if field.name not in ("monitor", "energy_bias_init", "joint_energy"):
            assert getattr(loaded, field.name) == getattr(expected, field.name), field.name
    # A config saved before the monitor group names no score: its training signal decides it, as for a new one
    # (this preset trains E_c on its own encoder); its calibrations, saved apart, name their own score.
    assert loaded.monitor.score == expected.monitor.score == "context_phase_energy"


def test_every_flat_field_of_the_old_config_lands_where_the_table_says():
    saved = json.loads((PRE_NESTING / "config.json").read_text())
    loaded = load_pre_nesting_config()
    current = {field.name for field in dataclasses.fields(EBVLAConfig)}
    legacy = [key for key in saved if key not in current and key != "type"]
    assert legacy and not set(legacy) - set(LEGACY_FIELDS) - set(LEGACY_COMPILE_FIELDS)
    for old in set(legacy) & set(LEGACY_FIELDS):
        value = attrgetter(LEGACY_FIELDS[old])(loaded)
        assert json.loads(json.dumps(value)) == saved[old], old


def test_an_old_config_saved_again_is_read_by_lerobots_own_loader(tmp_path):
    """`lerobot-eval --policy.path=...` reads `PreTrainedConfig.from_pretrained`, which knows only today's form."""
    load_pre_nesting_config().save_pretrained(tmp_path)
    config = PreTrainedConfig.from_pretrained(tmp_path)
    assert isinstance(config, EBVLAConfig) and config.joint_energy.target == "observation"
    assert config.resnet.vision_backbone_stages == 1 and config.contrastive.weight == 0.2


def test_a_flat_field_and_its_group_both_set_are_refused_naming_both():
    with pytest.raises(ValueError, match="`energy_ood_margin_weight`.*`joint_energy.weight`"):
        upgrade_legacy_fields({"energy_ood_margin_weight": 0.1, "joint_energy": {"weight": 0.2}})
