"""A new OOD score is one `ChunkScore` class and one registry entry, nothing else.

The toy score below (a chunk's final energy standardized by the mean and std of every vanilla chunk's) is
registered in this file only, and goes through `ebvla-ood-report` (its rows, its saved calibration), the
calibration's save and load, the run-time monitor and the policy's response.
"""

from dataclasses import dataclass

import numpy as np
import pytest
import torch

from lerobot_policy_ebvla.configuration_ebvla import MonitorConfig
from lerobot_policy_ebvla.monitoring.ood_report import OODReportConfig, write_ood_report
from lerobot_policy_ebvla.monitoring.records import load_episodes
from lerobot_policy_ebvla.runtime import (
    SCORES,
    ChunkInputs,
    ChunkScore,
    ChunkWindow,
    EnergyOODError,
    EnergyOODMonitor,
    EnergyOODResponse,
    OODCalibration,
    VanillaRollouts,
)
from lerobot_policy_ebvla.runtime.readout import EnergyReadout

from .conftest import tiny_config, write_calibration_vanilla_and_ood


@dataclass(frozen=True)
class PooledEnergyZ(ChunkScore):
    """(E - mean) / std, mean and std of every vanilla chunk's final energy."""

    mean: float
    std: float

    name = "pooled_energy_z"
    json_fields = ("mean", "std")

    @classmethod
    def fit(cls, vanilla: VanillaRollouts) -> "PooledEnergyZ":
        energies = np.concatenate(vanilla.final_energies)
        return cls(float(energies.mean()), float(energies.std()))

    def components(self, chunks: ChunkInputs) -> np.ndarray:
        return ((chunks.final_energy - self.mean) / self.std)[:, None]

    def to_json(self) -> dict:
        return {"mean": self.mean, "std": self.std}

    @classmethod
    def from_json(cls, fields: dict) -> "PooledEnergyZ":
        return cls(fields["mean"], fields["std"])


@pytest.fixture
def registered(monkeypatch):
    monkeypatch.setitem(SCORES, PooledEnergyZ.name, PooledEnergyZ)


@pytest.fixture(scope="module")
def record_dirs(tmp_path_factory):
    """Calibration and held-out vanilla rollouts, and rollouts whose final energy is higher."""
    return write_calibration_vanilla_and_ood(tmp_path_factory.mktemp("records"), "energy", 5.5)


def energies(episode) -> np.ndarray:
    return np.array([r.final_energy for r in episode])


def toy_report(record_dirs, out) -> tuple[str, OODCalibration]:
    calibration, vanilla, ood = record_dirs
    checkpoint = out / "pretrained_model"
    checkpoint.mkdir(parents=True)
    cfg = OODReportConfig(
        calibration=[calibration],
        vanilla=[vanilla],
        ood=[ood],
        output_dir=out / "report",
        n_bootstrap=20,
        calibrate_to=checkpoint,
        score=PooledEnergyZ.name,
    )
    return write_ood_report(cfg), OODCalibration.load(checkpoint)


def test_the_report_scores_and_saves_a_registered_score_it_has_no_line_for(registered, record_dirs, tmp_path):
    report, calibration = toy_report(record_dirs, tmp_path)
    calibration_set = load_episodes([record_dirs[0]])
    everything = np.concatenate([energies(e) for e in calibration_set.values()])
    assert calibration.score == PooledEnergyZ(float(everything.mean()), float(everything.std()))
    # Each calibration rollout scored against the score fitted without it, as the report's other fitted scores
    # are. The saved calibration is of the window of each rollout's first 3 chunks (its running scores after
    # chunks 1, 2 and 3); the report's calibration table is over whole episodes.
    left_out, running = [], []
    for key, episode in calibration_set.items():
        others = np.concatenate([energies(e) for k, e in calibration_set.items() if k != key])
        z = (energies(episode) - others.mean()) / others.std()
        left_out.append(np.mean(z))
        running.append([np.mean(z[:n]) for n in (1, 2, 3)])
    assert calibration.window.running.mean == pytest.approx(tuple(np.mean(running, axis=0)))
    window_scores = ChunkWindow.leave_one_out_scores(running)
    assert calibration.mu_v == pytest.approx(np.mean(window_scores))
    assert calibration.sigma_v == pytest.approx(np.std(window_scores))
    assert f"| {PooledEnergyZ.name} | 8 | {np.mean(left_out):.4g} | {np.std(left_out):.4g} |" in report
    auroc_header = report.split("## AUROC")[1].split("\n\n")[1].splitlines()[0]
    assert auroc_header.endswith(f"| {PooledEnergyZ.name} |")


def test_a_registered_score_is_saved_loaded_and_monitored_as_the_report_scores_it(
    registered, record_dirs, tmp_path
):
    _, calibration = toy_report(record_dirs, tmp_path)
    (tmp_path / "copy").mkdir()
    calibration.save(tmp_path / "copy")
    assert OODCalibration.load(tmp_path / "copy") == calibration
    held_out = load_episodes([record_dirs[2]])
    monitor = EnergyOODMonitor(calibration)
    for episode in held_out.values():
        z = (energies(episode) - calibration.score.mean) / calibration.score.std
        expected = calibration.window.score([np.mean(z[:n]) for n in (1, 2, 3)])
        assert monitor.check_rollout(EnergyReadout.of_arrays(energies(episode))).energy == pytest.approx(
            expected
        )
    first = energies(next(iter(held_out.values())))
    for index, energy in enumerate(first):
        running = monitor.update(EnergyReadout(None, torch.tensor([energy]), chunk_index=index))
    assert running[0].energy == pytest.approx(monitor.check_rollout(EnergyReadout.of_arrays(first)).energy)


def test_the_policy_responds_to_a_registered_score(registered, record_dirs, tmp_path):
    _, calibration = toy_report(record_dirs, tmp_path)
    response = EnergyOODResponse(
        tiny_config(monitor=MonitorConfig(response="raise")), calibration.with_k(0.0)
    )
    actions = torch.zeros(2, 3, 2)
    # A chunk is scored as a one-chunk rollout: its z standardized by the window's first mu and sigma. One just
    # under T (= mu_v at k = 0) passes; one 10 window sigmas higher raises.
    below = calibration.with_k(0.0).threshold - 0.01
    z = calibration.window.running.mean[0] + below * calibration.window.running.std[0]
    in_distribution = torch.full((2,), calibration.score.mean + z * calibration.score.std)
    _, decision = response(actions, EnergyReadout(None, in_distribution), {})
    assert not decision.is_ood
    higher = 10 * calibration.window.running.std[0] * calibration.score.std
    with pytest.raises(EnergyOODError, match=PooledEnergyZ.name):
        response(actions, EnergyReadout(None, in_distribution + higher), {})
