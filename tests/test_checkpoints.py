"""Checkpoints survive: failed saves keep the previous files, training resumes where it stopped."""

import re
from pathlib import Path

import pytest
import torch

from lerobot_policy_ebvla import EBVLAPolicy

from .conftest import tiny_batch, tiny_config, write_tiny_dataset
from .test_lerobot_integration import lerobot_train


def test_a_failed_save_leaves_the_previous_checkpoint_intact(tiny_policy, tmp_path, monkeypatch):
    import lerobot.policies.pretrained as pretrained

    tiny_policy.eval()
    batch = tiny_batch(tiny_policy.config, with_action=False)
    tiny_policy.save_pretrained(tmp_path)
    expected = tiny_policy.predict_action_chunk(batch, generator=torch.Generator().manual_seed(0))

    def crash_midway(weights, target, **kwargs):
        # `target` is the file (save_model_as_safetensor) or the folder (save_torch_state_dict).
        path = Path(target) / "model.safetensors" if Path(target).is_dir() else Path(target)
        path.write_bytes(b"half a file")
        raise OSError("disk full")

    monkeypatch.setattr(pretrained, "save_model_as_safetensor", crash_midway)
    monkeypatch.setattr(pretrained, "save_torch_state_dict", crash_midway)
    with torch.no_grad():
        for p in tiny_policy.parameters():
            p.add_(1.0)
    with pytest.raises(OSError, match="disk full"):
        tiny_policy.save_pretrained(tmp_path)

    loaded = EBVLAPolicy.from_pretrained(tmp_path)
    actual = loaded.predict_action_chunk(batch, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(actual, expected, rtol=0, atol=0)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["config.json", "model.safetensors"]


def logged_losses(log: str) -> dict[int, float]:
    return {
        int(step): float(loss) for step, loss in re.findall(r"step:(\d+) smpl:\d+ .*? loss:([0-9.]+)", log)
    }


def test_resuming_a_lerobot_checkpoint_continues_the_steps_with_the_same_losses(tmp_path):
    root = tmp_path / "data"
    write_tiny_dataset(root)
    straight = lerobot_train(root, tmp_path / "straight", "--seed=7", steps=4, save_freq=2)
    assert straight.returncode == 0, straight.stderr[-3000:]
    halfway = tmp_path / "straight" / "checkpoints" / "000002"
    saved_at_4 = (
        tmp_path / "straight" / "checkpoints" / "000004" / "pretrained_model" / "model.safetensors"
    ).read_bytes()

    # Resumed from the halfway checkpoint into a folder of its own, as a user resumes someone else's run.
    config_path = halfway / "pretrained_model" / "train_config.json"
    resumed = lerobot_train(
        root, tmp_path / "resumed", "--resume=true", f"--config_path={config_path}", steps=4, save_freq=2
    )
    assert resumed.returncode == 0, resumed.stderr[-3000:]

    straight_losses = logged_losses(straight.stdout + straight.stderr)
    resumed_losses = logged_losses(resumed.stdout + resumed.stderr)
    assert sorted(resumed_losses) == [3, 4]
    # Same data, same MCMC draws: equal up to float reduction order (losses are logged to 3 decimals).
    for step in (3, 4):
        assert resumed_losses[step] == pytest.approx(straight_losses[step], abs=2e-3)
    assert (
        tmp_path / "resumed" / "checkpoints" / "000004" / "pretrained_model" / "model.safetensors"
    ).is_file()
    # The run resumed from is left as it was.
    assert (
        tmp_path / "straight" / "checkpoints" / "000004" / "pretrained_model" / "model.safetensors"
    ).read_bytes() == saved_at_4


def _saved(policy, path: Path) -> Path:
    policy.save_pretrained(path)
    return path


def test_a_damaged_calibration_names_the_file_and_the_fields(tiny_policy, tmp_path):
    from lerobot_policy_ebvla import OOD_CALIBRATION_FILENAME

    path = _saved(tiny_policy, tmp_path)
    (path / OOD_CALIBRATION_FILENAME).write_text('{"mu_v": 1.0, "sig', encoding="utf-8")
    with pytest.raises(ValueError, match=rf"{OOD_CALIBRATION_FILENAME} is not a valid OOD calibration.*mu_v"):
        EBVLAPolicy.from_pretrained(path)
    (path / OOD_CALIBRATION_FILENAME).write_text('{"mu_v": 1.0}', encoding="utf-8")
    with pytest.raises(ValueError, match="sigma_v"):
        EBVLAPolicy.from_pretrained(path)


def test_truncated_weights_name_the_file(tiny_policy, tmp_path):
    path = _saved(tiny_policy, tmp_path)
    weights = path / "model.safetensors"
    weights.write_bytes(weights.read_bytes()[: weights.stat().st_size // 2])
    with pytest.raises(ValueError, match=r"model\.safetensors .*damaged"):
        EBVLAPolicy.from_pretrained(path)


def test_an_out_of_range_saved_config_value_names_the_file_and_the_field(tiny_policy, tmp_path):
    import json

    path = _saved(tiny_policy, tmp_path)
    config = json.loads((path / "config.json").read_text(encoding="utf-8"))
    config["energy_temperature"] = -1.0
    (path / "config.json").write_text(json.dumps(config), encoding="utf-8")
    with pytest.raises(ValueError, match=r"config\.json .*`energy_temperature` must be > 0"):
        EBVLAPolicy.from_pretrained(path)


def test_a_checkpoint_loads_at_another_frame_size_with_its_own_keypoint_grid(tmp_path):
    torch.manual_seed(0)
    saved = EBVLAPolicy(tiny_config(joint_energy={"weight": 0.1, "target": "observation"}))
    path = _saved(saved, tmp_path)
    larger = tiny_config(
        resnet={"resize_shape": (96, 96)}, joint_energy={"weight": 0.1, "target": "observation"}
    )
    policy = EBVLAPolicy.from_pretrained(path, config=larger)

    saved_weights, loaded_weights = saved.state_dict(), policy.state_dict()
    grids = [key for key in saved_weights if key.endswith("pool.pos_grid")]
    assert len(grids) == 2  # the policy's encoder and E_c's own
    for key in grids:  # the tiny config's 4 stages: a 2 x 2 map at 64 px, 3 x 3 at 96
        assert loaded_weights[key].shape[0] > saved_weights[key].shape[0]
    for key, value in saved_weights.items():
        if key not in grids:
            torch.testing.assert_close(loaded_weights[key], value, rtol=0, atol=0, msg=key)
    policy.eval()
    action = policy.select_action(tiny_batch(policy.config, with_action=False))
    assert torch.isfinite(action).all()
