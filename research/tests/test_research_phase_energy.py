"""The phase energy: each chunk's final energy against the vanilla final energy at the same chunk index.

z_t = (E_t - mu_v[t]) / sigma_v[t], mu_v[t] and sigma_v[t] from vanilla (calibration) episodes; stored in
`OODCalibration` so that the run-time monitor can apply it, and scored offline from records like the
baselines.

The running example: vanilla episodes [0, 2, 10] and [2, 4] give mu_v = [1, 3, 10], sigma_v = [1, 1, floor],
the floor 0.1 times the pooled std of 0, 2, 10, 2, 4 (3.44).
"""

import json
import math

import numpy as np
import pytest
import torch

from lerobot_policy_ebvla.monitoring.baselines import fit_phase_model, fit_score_reference
from lerobot_policy_ebvla.monitoring.records import EnergyRecord
from lerobot_policy_ebvla.monitoring.scores import chunk_scores, episode_scores
from lerobot_policy_ebvla.runtime.calibration import OOD_CALIBRATION_FILENAME, OODCalibration
from lerobot_policy_ebvla.runtime.monitor import EnergyOODMonitor
from lerobot_policy_ebvla.runtime.readout import EnergyReadout
from lerobot_policy_ebvla.runtime.scores import FinalEnergy
from lerobot_policy_ebvla.runtime.statistics import PhaseStatistics
from research.tests.conftest import load_benchmark

research_scores = load_benchmark("research_scores")
PhaseEnergy = research_scores.PhaseEnergy

VANILLA = [[0.0, 2.0, 10.0], [2.0, 4.0]]
POOLED_SIGMA = float(np.std([0.0, 2.0, 10.0, 2.0, 4.0]))


def episode(energies, index=0, success=True):
    return [EnergyRecord(index, t, 8 * t, 0.0, e, success, "t", None) for t, e in enumerate(energies)]


# The statistics.


def test_phase_statistics_are_the_vanilla_mean_and_std_at_each_chunk_index():
    phase = PhaseStatistics.fit(VANILLA)
    assert phase.mean == (1.0, 3.0, 10.0)
    assert phase.std[:2] == (1.0, 1.0)


def test_phase_std_is_floored_at_a_tenth_of_the_pooled_std():
    # Index 2 is reached by one episode only: its std of 0 is floored.
    assert PhaseStatistics.fit(VANILLA).std[2] == pytest.approx(0.1 * POOLED_SIGMA)


def test_phase_std_of_identical_energies_stays_positive():
    assert min(PhaseStatistics.fit([[1.0, 1.0], [1.0, 1.0]]).std) > 0


def test_phase_statistics_leave_non_finite_energies_out():
    assert PhaseStatistics.fit([[0.0, math.inf], [2.0, 4.0]]).mean == (1.0, 4.0)


def test_phase_statistics_without_a_finite_energy_raise():
    with pytest.raises(ValueError, match="finite"):
        PhaseStatistics.fit([[math.inf]])


def test_phase_energy_compares_a_chunk_with_vanilla_at_the_same_index():
    phase = PhaseStatistics.fit(VANILLA)
    # 5 at index 0 is 4 sigma above vanilla's first chunk; at index 1 it is 2 sigma above.
    np.testing.assert_allclose(phase.z([5.0, 5.0], [0, 1]), [4.0, 2.0])


def test_phase_energy_past_the_longest_vanilla_episode_uses_the_last_index():
    phase = PhaseStatistics.fit(VANILLA)
    assert phase.z(10.0, 7)[0] == phase.z(10.0, 2)[0] == 0.0


def test_phase_energy_rejects_a_negative_chunk_index():
    with pytest.raises(ValueError, match="chunk_index"):
        PhaseStatistics.fit(VANILLA).z(1.0, -1)


# The calibration that ships with a checkpoint.


def phase_calibration(**kwargs) -> OODCalibration:
    return OODCalibration.fit([0.0, 1.0], score=PhaseEnergy(PhaseStatistics.fit(VANILLA)), **kwargs)


def test_a_final_energy_calibration_scores_a_chunk_by_its_final_energy():
    assert OODCalibration(mu_v=1.0, sigma_v=1.0).chunk_score(EnergyReadout.of_arrays(3.5, 4)) == [3.5]


def test_a_phase_calibration_scores_a_chunk_against_vanilla_at_its_index():
    calibration = phase_calibration()
    assert calibration.chunk_score(EnergyReadout.of_arrays(5.0, 1)) == pytest.approx([2.0])
    chunks = EnergyReadout.of_arrays(torch.tensor([5.0, 5.0]), [0, 1])
    np.testing.assert_allclose(calibration.chunk_score(chunks), [4.0, 2.0])


def test_a_readout_needs_one_chunk_index_per_chunk():
    with pytest.raises(ValueError, match="`chunk_index` has 3 row"):
        phase_calibration().chunk_score(EnergyReadout.of_arrays([5.0, 5.0], [0, 1, 2]))


def write_calibration(folder, **fields):
    (folder / OOD_CALIBRATION_FILENAME).write_text(json.dumps({"mu_v": 0.0, "sigma_v": 1.0, **fields}))


def test_a_phase_calibration_needs_its_statistics(tmp_path):
    write_calibration(tmp_path, score="phase_energy")
    with pytest.raises(ValueError, match="phase_mean"):
        OODCalibration.load(tmp_path)


def test_a_calibration_of_an_unknown_score_is_rejected(tmp_path):
    write_calibration(tmp_path, score="knn")
    with pytest.raises(LookupError, match="score 'knn', which is not registered"):
        OODCalibration.load(tmp_path)


def test_a_phase_calibration_round_trips_through_json(tmp_path):
    calibration = phase_calibration(k=0.5)
    calibration.save(tmp_path)
    payload = json.loads((tmp_path / OOD_CALIBRATION_FILENAME).read_text())
    assert payload["score"] == "phase_energy" and payload["phase_mean"] == [1.0, 3.0, 10.0]
    assert OODCalibration.load(tmp_path) == calibration


def test_a_calibration_file_without_the_phase_fields_loads_as_the_final_energy(tmp_path):
    old = {"mu_v": 2.5, "sigma_v": 1.0, "k": 1.0, "aggregation": "mean", "n_rollouts": 4, "threshold": 3.5}
    (tmp_path / OOD_CALIBRATION_FILENAME).write_text(json.dumps(old))
    calibration = OODCalibration.load(tmp_path)
    assert calibration.score.name == "final_energy" and calibration.score == FinalEnergy()


def test_the_monitor_counts_chunks_to_apply_a_phase_calibration():
    monitor = EnergyOODMonitor(phase_calibration(k=0.0))
    monitor.update(EnergyReadout(None, torch.tensor([1.0, 5.0]), chunk_index=0))  # z = 0 and 4
    decisions = monitor.update(EnergyReadout(None, torch.tensor([3.0, 5.0]), chunk_index=1))  # z = 0 and 2
    assert [d.energy for d in decisions] == pytest.approx([0.0, 3.0])


def test_the_monitor_checks_a_chunk_of_a_phase_calibration_at_its_index():
    (decision,) = EnergyOODMonitor(phase_calibration(k=0.0)).check(EnergyReadout.of_arrays(5.0, 1))
    assert decision.energy == pytest.approx(2.0) and decision.is_ood


# The offline score.


def test_phase_energy_of_a_held_out_episode_uses_every_calibration_episode():
    calibration = {key: episode(e, index=key) for key, e in enumerate(VANILLA)}
    reference = fit_score_reference(calibration, features=False)
    scores = chunk_scores(episode([5.0, 5.0]), "phase_energy", reference, episode_id="held out")
    np.testing.assert_allclose(scores, [4.0, 2.0])


def test_phase_energy_of_a_calibration_episode_leaves_it_out():
    calibration = {key: episode(e, index=key) for key, e in enumerate([[0.0, 2.0], [2.0, 4.0], [4.0, 0.0]])}
    model = fit_phase_model(calibration)
    left_out = PhaseStatistics.fit([[2.0, 4.0], [4.0, 0.0]])
    np.testing.assert_allclose(
        model.score(np.array([0.0, 2.0]), np.arange(2), 0), left_out.z([0.0, 2.0], [0, 1])
    )


def test_phase_energy_needs_a_reference():
    with pytest.raises(ValueError, match="reference"):
        episode_scores({0: episode([1.0])}, "phase_energy")
