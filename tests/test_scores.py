"""The package's scores: six, in one registry that research code extends through one hook."""

from dataclasses import dataclass

import numpy as np
import pytest

from lerobot_policy_ebvla.configuration_groups import FAILURE_SCORES, MONITOR_SCORES
from lerobot_policy_ebvla.runtime import EnergyReadout, OODCalibration
from lerobot_policy_ebvla.runtime.scores import (
    PACKAGE_SCORES,
    SCORES,
    ChunkInputs,
    ChunkScore,
    ContextPhaseEnergy,
    ContextStartEnergy,
    FinalEnergy,
    HeadEnergyTwoSided,
    JointPhaseEnergy,
    VanillaRollouts,
    register_score,
    score_rollout,
)
from lerobot_policy_ebvla.runtime.statistics import PhaseStatistics

PHASE = PhaseStatistics((0.0, -10.0), (1.0, 2.0))


def test_the_package_ships_eight_scores_and_the_config_names_each():
    assert PACKAGE_SCORES == (
        "final_energy",
        "context_phase_energy",
        "head_energy_two_sided",
        "joint_phase_energy",
        "context_start_energy",
        "joint_phase_time_energy",
        "success_energy",
        "context_knn",
    )
    assert MONITOR_SCORES == PACKAGE_SCORES
    assert set(FAILURE_SCORES) - {"none"} == set(PACKAGE_SCORES) - {"context_knn"}
    assert set(PACKAGE_SCORES) <= set(SCORES)


def test_a_registered_score_is_found_by_its_name_and_a_name_clash_is_refused(monkeypatch):
    monkeypatch.setattr("lerobot_policy_ebvla.runtime.scores.SCORES", dict(SCORES))
    from lerobot_policy_ebvla.runtime import scores

    @dataclass(frozen=True)
    class Doubled(ChunkScore):
        name = "doubled_energy"

        def components(self, chunks: ChunkInputs) -> np.ndarray:
            return 2 * chunks.final_energy[:, None]

    assert register_score(Doubled) is Doubled and register_score(Doubled) is Doubled
    assert scores.SCORES["doubled_energy"] is Doubled

    @dataclass(frozen=True)
    class Impostor(FinalEnergy):
        pass

    with pytest.raises(ValueError, match="'final_energy' is already registered for FinalEnergy"):
        register_score(Impostor)


def test_the_score_order_is_set_only_as_a_whole(monkeypatch):
    monkeypatch.setattr("lerobot_policy_ebvla.runtime.scores.SCORES", dict(SCORES))
    from lerobot_policy_ebvla.runtime import scores

    names = list(reversed(scores.SCORES))
    scores.set_score_order(names)
    assert list(scores.SCORES) == names
    # A registered score left out would vanish from every report: refused, by name.
    with pytest.raises(ValueError, match=r"missing \['final_energy'\]"):
        scores.set_score_order([n for n in names if n != "final_energy"])
    assert list(scores.SCORES) == names


def test_the_context_phase_energy_reads_e_c_at_the_chunks_index():
    calibration = OODCalibration(mu_v=0.0, sigma_v=1.0, score=ContextPhaseEnergy(PHASE))
    readout = EnergyReadout.of_arrays([7.0, 7.0], [0, 1], context_energy=[-5.0, -5.0])
    np.testing.assert_allclose(calibration.chunk_score(readout), [-5.0, 2.5])


def test_the_head_energy_is_the_final_energy_less_e_c_and_two_sided():
    calibration = OODCalibration(mu_v=0.0, sigma_v=1.0, score=HeadEnergyTwoSided(PHASE))
    readout = EnergyReadout.of_arrays([-3.0, -20.0], [0, 1], context_energy=[2.0, -4.0])
    np.testing.assert_allclose(calibration.chunk_score(readout), [5.0, 3.0])


def test_the_joint_phase_energy_averages_the_two_terms_z_at_the_chunks_index():
    head = PhaseStatistics((1.0, 1.0), (2.0, 0.5))
    score = JointPhaseEnergy(PHASE, head)
    calibration = OODCalibration(mu_v=0.0, sigma_v=1.0, score=score)
    # E_c: z = -5 and 2.5 (as above); E - E_c = 12 and 12: z = 5.5 and 22; one-sided, so a low term lowers it.
    readout = EnergyReadout.of_arrays([7.0, 7.0], [0, 1], context_energy=[-5.0, -5.0])
    np.testing.assert_allclose(calibration.chunk_score(readout), [0.25, 12.25])
    # A rollout: each term's mean over its chunks (-1.25 and 13.75), then their mean.
    assert score_rollout(score, score.components(ChunkInputs.of(readout)), "mean") == pytest.approx(6.25)
    assert score_rollout(score, score.components(ChunkInputs.of(readout)), "max") == pytest.approx(
        (2.5 + 22.0) / 2
    )
    saved = score.to_json()
    assert JointPhaseEnergy.from_json(saved) == score
    with pytest.raises(
        ValueError, match="`head_energy_phase_mean` and `head_energy_phase_std` come together"
    ):
        JointPhaseEnergy.from_json({**saved, "head_energy_phase_std": None})
    with pytest.raises(ValueError, match="joint_phase_energy score needs each chunk's context energy"):
        calibration.chunk_score(EnergyReadout.of_arrays([7.0], [0]))


def test_the_context_start_energy_turns_the_start_terms_sign_and_averages_the_two_terms():
    start = PhaseStatistics((10.0, 10.0), (2.0, 4.0))
    score = ContextStartEnergy(PHASE, start)
    calibration = OODCalibration(mu_v=0.0, sigma_v=1.0, score=score)
    # E_c: z = -5 and 2.5; the head's energy of the start, E(a^(0)) - E_c = 11 and 1: z = 0.5 and -2.25, turned
    # to -0.5 and 2.25: a start energy below vanilla's raises the score.
    readout = EnergyReadout.of_arrays(
        [7.0, 7.0], [0, 1], context_energy=[-5.0, -5.0], initial_energy=[6.0, -4.0]
    )
    np.testing.assert_allclose(calibration.chunk_score(readout), [-2.75, 2.375])
    assert score_rollout(score, score.components(ChunkInputs.of(readout)), "mean") == pytest.approx(-0.1875)
    assert ContextStartEnergy.from_json(score.to_json()) == score
    with pytest.raises(
        ValueError, match="context_start_energy score needs each chunk's E\\(a\\^\\(0\\), C\\)"
    ):
        calibration.chunk_score(EnergyReadout.of_arrays([7.0], [0], context_energy=[1.0]))


def test_the_context_start_energy_is_fitted_on_the_vanilla_start_energies():
    rollouts = [
        EnergyReadout.of_arrays([1.0, 2.0], context_energy=[0.0, 1.0], initial_energy=[5.0, 6.0]),
        EnergyReadout.of_arrays([3.0, 3.0], context_energy=[2.0, 3.0], initial_energy=[9.0, 7.0]),
    ]
    score = ContextStartEnergy.fit(VanillaRollouts(rollouts))
    # The head's start energies, E(a^(0)) - E_c: 5 and 7 at index 0, 5 and 4 at index 1.
    assert score.start.mean == pytest.approx((6.0, 4.5))
    assert score.context == ContextPhaseEnergy.fit(VanillaRollouts(rollouts)).phase


def test_calibrating_a_named_score_scores_each_rollout_against_the_others():
    rollouts = [
        EnergyReadout.of_arrays([1.0, 2.0], context_energy=[0.0, 1.0]),
        EnergyReadout.of_arrays([3.0, 3.0], context_energy=[2.0, 3.0]),
        EnergyReadout.of_arrays([0.0, 5.0], context_energy=[4.0, 2.0]),
    ]
    final = OODCalibration.calibrate("final_energy", VanillaRollouts(rollouts), k=2.0)
    assert (final.mu_v, final.k, final.score) == (pytest.approx(14 / 6), 2.0, FinalEnergy())
    phase = OODCalibration.calibrate("context_phase_energy", VanillaRollouts(rollouts))
    # Each rollout's E_c against the other two at each index: the first at z = -3 and -3, the second at 0 and 3,
    # the third at 3 and 0; the saved score is fitted on all three.
    assert phase.score == ContextPhaseEnergy.fit(VanillaRollouts(rollouts))
    assert (phase.mu_v, phase.sigma_v) == (pytest.approx(0.0), pytest.approx(np.std([-3.0, 1.5, 1.5])))
    with pytest.raises(ValueError, match="context_knn score needs each chunk's pooled context"):
        OODCalibration.calibrate("context_knn", VanillaRollouts(rollouts))
