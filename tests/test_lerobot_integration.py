"""The installed plugin through LeRobot's own tools: discovery, lerobot-train, checkpoint loading."""

import contextlib
import os
import resource
import signal
import subprocess
import sys
from pathlib import Path

import psutil
import pytest
import torch
from lerobot.policies.factory import make_pre_post_processors

from lerobot_policy_ebvla import EBVLAPolicy

from .conftest import write_tiny_dataset

TRAIN_STEPS = 4


def console_script(name: str) -> str:
    """The console script installed beside this interpreter (the venv's bin need not be on PATH)."""
    return str(Path(sys.executable).parent / name)


def lerobot_train(
    dataset_root, output_dir, *extra, steps=TRAIN_STEPS, save_freq=TRAIN_STEPS, launcher=None, timeout=600
):
    """Runs LeRobot's trainer on the tiny dataset with a tiny light-backbone ebvla policy."""
    command = [
        *(launcher or [console_script("lerobot-train")]),
        "--dataset.repo_id=local/ebvla_tiny",
        f"--dataset.root={dataset_root}",
        "--policy.type=ebvla",
        "--policy.backbone=resnet",
        "--policy.dim_model=32",
        "--policy.n_heads=2",
        "--policy.n_blocks=2",
        "--policy.resnet.spatial_softmax_num_keypoints=8",
        "--policy.train_mcmc_steps_range=[2,3]",
        "--policy.device=cpu",
        "--policy.push_to_hub=false",
        f"--steps={steps}",
        "--batch_size=4",
        f"--save_freq={save_freq}",
        "--log_freq=1",
        "--num_workers=0",
        "--wandb.enable=false",
        f"--output_dir={output_dir}",
        *extra,
    ]
    return run_to_completion(command, timeout=timeout)


def _no_core_files() -> None:
    resource.setrlimit(resource.RLIMIT_CORE, (0, resource.getrlimit(resource.RLIMIT_CORE)[1]))


def run_to_completion(command: list[str], timeout: float) -> subprocess.CompletedProcess:
    """`subprocess.run(command, capture_output=True, text=True, timeout=timeout)`, but one that times out fails
    the test with what is needed to see why: the processes still running, the Python stack of each
    (faulthandler, on SIGABRT) and the log's tail. Every process the command started is then killed: torchrun
    starts its ranks in sessions of their own, so killing torchrun alone, as `subprocess.run` does, leaves a
    hung rank running after the test."""
    process = subprocess.Popen(
        command,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONFAULTHANDLER": "1"},
        preexec_fn=_no_core_files,  # in the command's processes only: no core files from the SIGABRT below
    )
    try:
        stdout, stderr = process.communicate(timeout=timeout)
        return subprocess.CompletedProcess(command, process.returncode, stdout, stderr)
    except subprocess.TimeoutExpired:
        running, stdout, stderr = _stop_with_stacks(process)
    # Outside the `except`, and without pytest's traceback: CI prints the head of a failure and its last lines,
    # so the stacks come first, before the long log (a chained traceback once pushed them out of view).
    log, stacks = _split_off_the_stacks(stderr)
    pytest.fail(
        f"{command[0]} timed out after {timeout} s; still running then:\n{running}\n"
        f"their stacks (faulthandler, most recent call first):\n{stacks[-8000:]}\n"
        f"stdout tail:\n{stdout[-1500:]}\nstderr tail before the stacks:\n{log[-3000:]}",
        pytrace=False,
    )


def _stop_with_stacks(process: subprocess.Popen) -> tuple[str, str, str]:
    """Makes every process of `process`'s tree write its Python stack, kills them all, and returns the list of
    those that were running (pid, state, command line) with the command's stdout and stderr."""
    tree, running = [], []
    with contextlib.suppress(psutil.Error):
        root = psutil.Process(process.pid)
        tree = [root, *root.children(recursive=True)]
    for proc in tree:
        with contextlib.suppress(psutil.Error):
            running.append(f"{proc.pid} {proc.status()} {' '.join(proc.cmdline())[:300]}")
    for proc in tree:
        # faulthandler writes the stack of each thread to stderr; one process at a time, since they share
        # the pipe and two dumping at once interleave their lines.
        with contextlib.suppress(psutil.Error):
            proc.send_signal(signal.SIGABRT)
            psutil.wait_procs([proc], timeout=3)
    for proc in tree:
        with contextlib.suppress(psutil.Error):
            proc.kill()
    try:
        stdout, stderr = process.communicate(timeout=60)
    except subprocess.TimeoutExpired as again:  # a process outside the tree still holds the pipes
        stdout, stderr = ((out or b"").decode(errors="replace") for out in (again.stdout, again.stderr))
    return "\n".join(running), stdout, stderr


def _split_off_the_stacks(stderr: str) -> tuple[str, str]:
    """`stderr` cut where the first faulthandler dump begins: (the log before it, the dumps)."""
    start = stderr.find("Fatal Python error")
    if start < 0:
        return stderr, "(no process wrote its stack)"
    return stderr[:start], stderr[start:]


@pytest.fixture(scope="module")
def trained_checkpoint(tmp_path_factory):
    root = tmp_path_factory.mktemp("data") / "ebvla_tiny"
    write_tiny_dataset(root)
    output_dir = tmp_path_factory.mktemp("train") / "run"
    result = lerobot_train(root, output_dir)
    assert result.returncode == 0, result.stderr[-3000:]
    return root, output_dir, result.stdout + result.stderr


def test_register_third_party_plugins_finds_ebvla():
    code = (
        "from lerobot.utils.import_utils import register_third_party_plugins\n"
        "from lerobot.configs import PreTrainedConfig\n"
        "register_third_party_plugins()\n"
        "from lerobot.policies.factory import get_policy_class\n"
        "print(get_policy_class('ebvla').__name__)\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert result.stdout.strip().endswith("EBVLAPolicy"), result.stderr[-2000:]


def test_lerobot_train_logs_the_loss_and_writes_a_checkpoint(trained_checkpoint):
    _, output_dir, log = trained_checkpoint
    assert f"step:{TRAIN_STEPS}" in log and "l1_loss:" in log
    pretrained = output_dir / "checkpoints" / "last" / "pretrained_model"
    for name in ("config.json", "model.safetensors", "policy_preprocessor.json", "policy_postprocessor.json"):
        assert (pretrained / name).is_file(), name


def test_checkpoint_loads_like_lerobot_eval_and_gives_finite_in_range_actions(trained_checkpoint):
    root, output_dir, _ = trained_checkpoint
    from lerobot.datasets import LeRobotDataset

    pretrained = output_dir / "checkpoints" / "last" / "pretrained_model"
    policy = EBVLAPolicy.from_pretrained(pretrained)
    preprocessor, postprocessor = make_pre_post_processors(policy.config, pretrained_path=str(pretrained))
    dataset = LeRobotDataset("local/ebvla_tiny", root=root)
    frame = dataset[0]
    observation = {k: v for k, v in frame.items() if k.startswith("observation.")}
    observation["task"] = frame["task"]
    with torch.inference_mode():
        action = postprocessor(policy.select_action(preprocessor(observation)))
    assert action.shape == (1, 3)
    assert torch.isfinite(action).all()
    # Refined actions are clamped to a_max standard deviations around the dataset mean.
    mean = torch.as_tensor(dataset.meta.stats["action"]["mean"]).float()
    std = torch.as_tensor(dataset.meta.stats["action"]["std"]).float()
    assert ((action - mean).abs() <= policy.config.action_clamp * std + 1e-5).all()
    assert policy.last_energy.final_energy.shape == (1,)
    assert torch.isfinite(policy.last_energy.final_energy).all()


def test_ebvla_train_trains_exactly_as_lerobot_train(trained_checkpoint, tmp_path):
    """`ebvla-train` (lerobot-train with action chunks read from their column alone) gives the same weights."""
    from safetensors.torch import load_file

    root, output_dir, _ = trained_checkpoint
    result = lerobot_train(root, tmp_path / "run", launcher=[console_script("ebvla-train")])
    assert result.returncode == 0, result.stderr[-3000:]
    weights = [
        load_file(run / "checkpoints" / "last" / "pretrained_model" / "model.safetensors")
        for run in (output_dir, tmp_path / "run")
    ]
    assert weights[0].keys() == weights[1].keys()
    for name, tensor in weights[0].items():
        torch.testing.assert_close(weights[1][name], tensor, rtol=1e-5, atol=1e-6, msg=name)
