"""Shared fixtures: tiny policies and a tiny LeRobotDataset written locally (the Hub is not needed)."""

import os

import numpy as np
import pytest
import torch
from lerobot.configs.types import FeatureType, PolicyFeature

from lerobot_policy_ebvla import EBVLAConfig, EBVLAPolicy
from lerobot_policy_ebvla.presets import ebvla_config

# Under pytest-xdist the suite runs as two worker processes, one per core of our 2-core CI. torch's default of one
# intra-op thread per core would put four busy threads on two cores, whose OpenMP barriers then wait on each other
# (training steps several times slower). One thread per worker, and for the programs a test launches.
if os.environ.get("PYTEST_XDIST_WORKER"):
    torch.set_num_threads(1)
    os.environ.setdefault("OMP_NUM_THREADS", "1")

# The longest files first: with one file per worker (`--dist loadfile`), the camera-reading learning test (minutes on
# one thread) would otherwise start late and leave the other worker idle at the end.
SLOW_FILES_FIRST = ("test_learning.py", "test_checkpoints.py")


def pytest_collection_modifyitems(items):
    items.sort(key=lambda item: item.path.name not in SLOW_FILES_FIRST)  # stable: the rest keep their order


TINY_HEAD = {"dim_model": 32, "n_heads": 2, "n_blocks": 2}
IMAGE_SHAPE = (3, 64, 64)


def tiny_config(**overrides) -> EBVLAConfig:
    """A light-backbone config small enough for CPU tests; keyword arguments override any field, a group's as a
    dict of the fields it changes (`joint_energy={"weight": 0.5}`) or as its dataclass (`presets.ebvla_config`)."""
    fields = {
        "backbone": "resnet",
        "device": "cpu",
        "resnet": {"spatial_softmax_num_keypoints": 8},
        "input_features": {
            "observation.images.top": PolicyFeature(FeatureType.VISUAL, IMAGE_SHAPE),
            "observation.state": PolicyFeature(FeatureType.STATE, (4,)),
        },
        "output_features": {"action": PolicyFeature(FeatureType.ACTION, (3,))},
        **TINY_HEAD,
    }
    return ebvla_config(fields, overrides)


def tiny_batch(config: EBVLAConfig, batch_size: int = 2, seed: int = 0, with_action: bool = True) -> dict:
    g = torch.Generator().manual_seed(seed)
    batch = {key: torch.rand(batch_size, *ft.shape, generator=g) for key, ft in config.image_features.items()}
    if config.state_dim:
        batch["observation.state"] = torch.randn(batch_size, config.state_dim, generator=g)
    if with_action:
        batch["action"] = torch.randn(batch_size, config.chunk_size, config.action_dim, generator=g)
        batch["action_is_pad"] = torch.zeros(batch_size, config.chunk_size, dtype=torch.bool)
    return batch


@pytest.fixture
def tiny_policy() -> EBVLAPolicy:
    torch.manual_seed(0)
    return EBVLAPolicy(tiny_config())


def write_tiny_dataset(root, repo_id: str = "local/ebvla_tiny", n_episodes: int = 2, n_frames: int = 24):
    """Writes a LeRobotDataset (images, state, action, task) whose actions depend on the state."""
    from lerobot.datasets import LeRobotDataset

    features = {
        "observation.images.top": {
            "dtype": "image",
            "shape": (64, 64, 3),
            "names": ["height", "width", "channels"],
        },
        "observation.state": {"dtype": "float32", "shape": (4,), "names": None},
        "action": {"dtype": "float32", "shape": (3,), "names": None},
    }
    dataset = LeRobotDataset.create(repo_id=repo_id, fps=10, features=features, root=root, use_videos=False)
    rng = np.random.default_rng(0)
    for _ in range(n_episodes):
        for t in range(n_frames):
            state = rng.normal(size=4).astype(np.float32)
            dataset.add_frame(
                {
                    "observation.images.top": (rng.random((64, 64, 3)) * 255).astype(np.uint8),
                    "observation.state": state,
                    "action": np.tanh(state[:3] + 0.1 * t).astype(np.float32),
                    "task": "reach the goal",
                }
            )
        dataset.save_episode()
    dataset.finalize()
    return root


def context_rollouts(n, seed, perturbation="none", energy=5.0, context=0.0, fail_every=3, n_chunks=5, dim=4):
    """Energy records of n episodes with final energies around `energy` and `dim`-d context features around
    `context`; every `fail_every`-th one fails. Episode i is seeded 1000 * seed + i, so runs of other `seed`s are
    held out."""
    import dataclasses

    from lerobot_policy_ebvla.monitoring.records import EnergyRecord

    rng = np.random.default_rng(seed)
    records = []
    for episode in range(n):
        for chunk in range(n_chunks):
            record = EnergyRecord(
                episode_index=episode,
                chunk_index=chunk,
                env_step=8 * chunk,
                initial_energy=float(energy + 2 + rng.normal(0, 0.2)),
                final_energy=float(energy + rng.normal(0, 0.2)),
                success=episode % fail_every != 0,
                task="reach",
                seed=1000 * seed + episode,
                perturbation=perturbation,
                severity=0.0 if perturbation == "none" else 1.0,
            )
            features = rng.normal(context, 1.0, dim).astype(np.float32)
            records.append(dataclasses.replace(record, context_feature=features))
    return records


def write_records(folder, records) -> str:
    """Writes `records` as the energy records of `folder`; returns the folder, as a report option takes it."""
    from lerobot_policy_ebvla.monitoring.records import ENERGY_RECORDS_FILENAME, write_energy_records

    return str(write_energy_records(folder / ENERGY_RECORDS_FILENAME, records).parent)


def write_calibration_vanilla_and_ood(root, perturbation: str, energy: float) -> tuple[str, str, str]:
    """Record folders of 8 calibration and 8 held-out vanilla rollouts, and 8 rollouts of `perturbation` whose
    final energy sits at `energy` (vanilla's: 5.0)."""
    return (
        write_records(root / "calibration", context_rollouts(8, seed=10)),
        write_records(root / "vanilla", context_rollouts(8, seed=11)),
        write_records(root / "ood", context_rollouts(8, 1, perturbation, energy=energy)),
    )
