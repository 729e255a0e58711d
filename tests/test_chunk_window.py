"""The window score (`ChunkWindow`): one T for the N decisions a run-time monitor makes in a rollout's first N
chunks, and what it changes for a user of `EnergyOODMonitor`: the share of in-distribution rollouts alarmed at
any of those chunks stays at the calibration's rate, where a T fitted on N-chunk means alone lets the noisier
early running scores through."""

import json
import math

import numpy as np
import pytest

from lerobot_policy_ebvla.runtime.calibration import OOD_CALIBRATION_FILENAME, OODCalibration
from lerobot_policy_ebvla.runtime.monitor import EnergyOODMonitor
from lerobot_policy_ebvla.runtime.readout import EnergyReadout
from lerobot_policy_ebvla.runtime.scores import VanillaRollouts
from lerobot_policy_ebvla.runtime.statistics import ChunkWindow, PhaseStatistics
from lerobot_policy_ebvla.runtime.threshold import conformal_threshold, exceeds

N = 3


def running_means(chunk_energies: np.ndarray) -> np.ndarray:
    """(R, N) the running mean of each rollout's first 1..N chunk energies."""
    return np.cumsum(chunk_energies[:, :N], axis=1) / np.arange(1, N + 1)


def vanilla_energies(rng: np.random.Generator, rollouts: int, chunks: int = 6) -> np.ndarray:
    # In-distribution chunk energies whose first chunk is much noisier than the later ones, as the first
    # refinement of an episode is on LIBERO: a mean over fewer chunks spreads more.
    energies = rng.normal(5.0, 0.1, size=(rollouts, chunks))
    energies[:, 0] = rng.normal(5.0, 0.8, size=rollouts)
    return energies


def window_of(means, stds) -> ChunkWindow:
    return ChunkWindow(PhaseStatistics(means, stds))


def test_window_score_is_the_largest_standardized_running_score():
    window = window_of((1.0, 2.0, 3.0), (1.0, 0.5, 2.0))
    # z = (2 - 1) / 1 = 1, (3 - 2) / 0.5 = 2, (3 - 3) / 2 = 0.
    assert window.score([2.0, 3.0, 3.0]) == pytest.approx(2.0)
    assert window.score([2.0]) == pytest.approx(1.0)  # after one chunk, one decision
    assert window.score([2.0, 3.0, 3.0, 100.0]) == pytest.approx(2.0)  # chunk N + 1 is past the window
    assert math.isnan(window.score([2.0, math.nan]))


def test_window_fit_is_the_mean_and_population_std_of_each_chunk_count():
    running = np.array([[1.0, 2.0], [3.0, 2.0], [5.0, 2.0]])
    window = ChunkWindow.fit(running)
    assert window.chunks == 2 and window.running.mean == pytest.approx((3.0, 2.0))
    # sigma_2 = 0 (identical scores) is floored as the phase statistics floor theirs (a tenth of the pooled std),
    # so that W stays finite.
    assert window.running.std == pytest.approx((math.sqrt(8 / 3), 0.1 * running.std()))


def test_leave_one_out_window_scores_standardize_each_rollout_without_it():
    running = np.array([[1.0], [2.0], [3.0], [10.0]])
    scores = ChunkWindow.leave_one_out_scores(running)
    others = running[:3, 0]
    assert scores[3] == pytest.approx((10.0 - others.mean()) / others.std())


def test_window_names_what_it_expects():
    with pytest.raises(ValueError, match=r"\(R, N = 2\).*got shape \(3,\)"):
        window_of((0.0, 0.0), (1.0, 1.0)).scores(np.zeros(3))
    with pytest.raises(ValueError, match="at least one chunk"):
        window_of((0.0,), (1.0,)).score([])
    with pytest.raises(ValueError, match="every std > 0"):
        window_of((0.0,), (0.0,))


def test_a_windowed_calibration_keeps_its_rate_over_every_early_decision():
    rng = np.random.default_rng(0)
    calibration_running = running_means(vanilla_energies(rng, 400))
    alpha = 0.05
    window = ChunkWindow.fit(calibration_running)
    windowed = OODCalibration.fit(
        ChunkWindow.leave_one_out_scores(calibration_running),
        false_alarm_rate=alpha,
        rule="conformal",
        window=window,
    )
    paper = OODCalibration.fit(calibration_running[:, -1], false_alarm_rate=alpha, rule="conformal")

    new = vanilla_energies(rng, 4000)

    def alarmed_by_chunk_n(calibration: OODCalibration) -> float:
        monitor = EnergyOODMonitor(calibration)
        alarmed = 0
        for rollout in new:
            monitor.reset()
            flags = [
                monitor.update(EnergyReadout.of_arrays([energy], chunk_index=[c]))[0].is_ood
                for c, energy in enumerate(rollout[:N])
            ]
            alarmed += any(flags)
        return alarmed / len(new)

    # The N-chunk mean's T, compared to the running mean of chunk 1 (spread 0.8 instead of ~0.27), alarms on
    # about a third of new vanilla rollouts; the window's T on about alpha.
    assert alarmed_by_chunk_n(paper) > 0.2
    assert alarmed_by_chunk_n(windowed) < alpha + 0.02


def test_the_decision_after_chunk_n_stands():
    window = window_of((5.0, 5.0, 5.0), (1.0, 1.0, 1.0))
    monitor = EnergyOODMonitor(OODCalibration(mu_v=0.0, sigma_v=1.0, k=1.0, window=window))
    decisions = [
        monitor.update(EnergyReadout.of_arrays([energy], chunk_index=[c]))[0]
        for c, energy in enumerate([5.0, 5.0, 5.0, 500.0])
    ]
    assert [d.is_ood for d in decisions] == [False, False, False, False]
    assert decisions[-1].energy == decisions[2].energy


def test_a_windowed_calibration_scores_one_chunk_as_a_one_chunk_rollout():
    window = window_of((5.0, 4.0), (2.0, 1.0))
    calibration = OODCalibration(mu_v=0.0, sigma_v=1.0, k=1.0, window=window)
    (decision,) = EnergyOODMonitor(calibration).check(EnergyReadout.of_arrays([8.0]))
    assert decision.energy == pytest.approx(1.5) and decision.is_ood
    assert calibration.score_rollout([[8.0], [4.0]]) == pytest.approx(max(1.5, (6.0 - 4.0) / 1.0))


def test_a_window_is_saved_and_loaded_and_absent_without_one(tmp_path):
    window = window_of((5.0, 4.0), (2.0, 1.0))
    OODCalibration(mu_v=0.1, sigma_v=1.0, window=window).save(tmp_path)
    assert OODCalibration.load(tmp_path).window == window
    (tmp_path / "plain").mkdir()
    OODCalibration(mu_v=0.1, sigma_v=1.0).save(tmp_path / "plain")
    payload = json.loads((tmp_path / "plain" / OOD_CALIBRATION_FILENAME).read_text())
    assert "window" not in payload and OODCalibration.load(tmp_path / "plain").window is None


def test_calibrate_with_a_window_fits_it_on_the_first_chunks_of_each_rollout():
    rng = np.random.default_rng(1)
    energies = vanilla_energies(rng, 40)
    vanilla = VanillaRollouts([EnergyReadout.of_arrays(row) for row in energies])
    calibration = OODCalibration.calibrate(
        "final_energy", vanilla, false_alarm_rate=0.1, rule="conformal", window_chunks=N
    )
    expected = ChunkWindow.fit(running_means(energies))
    assert calibration.window.running == expected.running
    scores = ChunkWindow.leave_one_out_scores(running_means(energies))
    assert calibration.threshold == pytest.approx(conformal_threshold(scores, 0.1))
    assert exceeds(scores, calibration.threshold).mean() <= 0.1
