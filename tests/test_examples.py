"""Each script of `examples/` runs as a user runs it (`python examples/<name>.py --flags`), at a tiny size.

The first example records, trains and evaluates; the others use its checkpoint and dataset.
"""

import json
import re
import runpy
import shutil
import sys
from pathlib import Path

import pytest

from lerobot_policy_ebvla import OOD_CALIBRATION_FILENAME, FailureCalibration, OODCalibration
from lerobot_policy_ebvla.monitoring import read_energy_records

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
# Shorter than any evaluation budget of the examples: 16 env steps, two chunks of 8.
EPISODE_STEPS = 16


def run_example(name: str, *args: str) -> None:
    """Runs examples/<name> as `__main__` with `args` on its command line, in this process."""
    saved = sys.argv
    sys.argv = [str(EXAMPLES / name), *args]
    try:
        runpy.run_path(str(EXAMPLES / name), run_name="__main__")
    finally:
        sys.argv = saved


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """examples/train_and_evaluate_metaworld.py at a tiny size: 1 demonstration, 2 steps, 2 short episodes."""
    pytest.importorskip("metaworld")
    output_dir = tmp_path_factory.mktemp("example_metaworld")
    run_example(
        "train_and_evaluate_metaworld.py",
        f"--output_dir={output_dir}",
        "--episodes=1",
        "--steps=2",
        "--batch_size=2",
        "--eval_episodes=2",
        f"--max_episode_steps={EPISODE_STEPS}",
    )
    return output_dir


@pytest.fixture
def checkpoint(trained, tmp_path):
    """A copy of the trained checkpoint, so that each test writes its own calibration."""
    return Path(
        shutil.copytree(trained / "train" / "checkpoints" / "last" / "pretrained_model", tmp_path / "ckpt")
    )


@pytest.mark.slow
def test_train_and_evaluate_writes_a_checkpoint_and_every_chunk_energy(trained):
    checkpoint = trained / "train" / "checkpoints" / "last" / "pretrained_model"
    n_action_steps = json.loads((checkpoint / "config.json").read_text())["n_action_steps"]

    records = read_energy_records(trained / "eval" / "energy_records.jsonl")

    assert (checkpoint / "model.safetensors").is_file()
    assert sorted({r.episode_index for r in records}) == [0, 1]
    for episode in (0, 1):
        steps = [r.env_step for r in records if r.episode_index == episode]
        assert steps == list(range(0, EPISODE_STEPS, n_action_steps))[: len(steps)] and steps


@pytest.mark.slow
def test_calibration_is_saved_beside_the_checkpoint_from_vanilla_rollouts(checkpoint, capsys):
    run_example(
        "calibrate_ood_threshold.py",
        f"--checkpoint={checkpoint}",
        "--episodes=3",
        f"--max_episode_steps={EPISODE_STEPS}",
    )

    calibration = OODCalibration.load(checkpoint / OOD_CALIBRATION_FILENAME)
    assert calibration.n_rollouts == 3 and calibration.sigma_v > 0
    printed = capsys.readouterr().out
    assert f"T = {calibration.threshold:.3f}" in printed
    # The example trains the light preset, E_c on its own encoder: its failure check is calibrated beside.
    failure = FailureCalibration.load(checkpoint)
    assert failure.score.name == "head_energy_two_sided" and failure.chunks == 3 and failure.n_rollouts == 3
    assert f"T = {failure.threshold:.3f}" in printed
    assert len([line for line in printed.splitlines() if line.startswith("rollout ")]) == 3


@pytest.mark.slow
def test_rollout_holds_every_chunk_above_the_threshold(checkpoint, capsys):
    # A threshold below every energy the policy produces: every chunk is out of distribution.
    OODCalibration(mu_v=-1e6, sigma_v=0.0).save(checkpoint)

    run_rollout_example(checkpoint, "hold")

    lines = [line for line in capsys.readouterr().out.splitlines() if "seed 1000" in line]
    assert len(lines) == 2, lines  # the vanilla scene and the perturbed one
    for line in lines:
        chunks, above, held = map(int, re.search(r"(\d+) chunks, (\d+) above T, (\d+) held", line).groups())
        assert chunks == above == held > 0, line


@pytest.mark.slow
def test_rollout_stops_at_the_first_chunk_above_the_threshold_with_raise(checkpoint, capsys):
    OODCalibration(mu_v=-1e6, sigma_v=0.0).save(checkpoint)

    run_rollout_example(checkpoint, "raise")

    lines = [line for line in capsys.readouterr().out.splitlines() if "seed 1000" in line]
    assert len(lines) == 2 and all(
        "1 chunks, 1 above T, 0 held; stopped: energy" in line for line in lines
    ), lines


def run_rollout_example(checkpoint, response):
    run_example(
        "rollout_with_ood_response.py",
        f"--checkpoint={checkpoint}",
        f"--response={response}",
        "--episodes=1",
        f"--max_episode_steps={EPISODE_STEPS}",
    )


@pytest.mark.slow
def test_best_of_n_scores_candidates_on_dataset_frames(trained, capsys):
    checkpoint = trained / "train" / "checkpoints" / "last" / "pretrained_model"
    run_example(
        "best_of_n_scoring.py",
        f"--checkpoint={checkpoint}",
        f"--dataset_root={trained / 'data'}",
        "--n_candidates=3",
        "--n_frames=4",
    )

    printed = capsys.readouterr().out
    assert "4 observations, 3 candidates each" in printed
    assert "L1 to the expert chunk (normalized): lowest-energy" in printed


def test_libero_command_is_a_valid_lerobot_train_config_of_the_full_vla(capsys):
    import draccus
    from lerobot.configs.train import TrainPipelineConfig

    from lerobot_policy_ebvla import EBVLAConfig

    example = runpy.run_path(str(EXAMPLES / "train_libero_gpu.py"))
    command = example["train_command"](example["LiberoTrainConfig"](num_gpus=1))
    assert command[0] == "lerobot-train"

    cfg = draccus.parse(TrainPipelineConfig, args=command[1:])
    assert isinstance(cfg.policy, EBVLAConfig) and cfg.policy.backbone == "vlm"
    assert cfg.policy.dim_model == EBVLAConfig().dim_model  # the paper's sizes: no policy flag but the type
    assert cfg.dataset.repo_id == "HuggingFaceVLA/libero"


def test_libero_example_prints_without_launching(capsys):
    run_example("train_libero_gpu.py", "--num_gpus=4")

    printed = capsys.readouterr().out
    assert "accelerate launch --multi_gpu --num_processes=4" in printed
    assert "ebvla-eval --policy.path=" in printed
