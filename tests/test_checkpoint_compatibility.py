"""A checkpoint saved by an earlier version still loads offline and acts the same."""

from pathlib import Path

import pytest
import torch
from lerobot.policies.factory import make_pre_post_processors
from safetensors import safe_open

from lerobot_policy_ebvla import EBVLAPolicy

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
