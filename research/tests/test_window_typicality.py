"""research/benchmarks/window_monitor.py and window_report.py: the window typicality test, ranks against a
reference, the monitor, its analysis."""

import math

import numpy as np
import pytest

from lerobot_policy_ebvla.monitoring.baselines import fit_score_reference
from lerobot_policy_ebvla.monitoring.records import EnergyRecord
from lerobot_policy_ebvla.monitoring.scores import episode_scores
from lerobot_policy_ebvla.runtime import OODCalibration, PhaseStatistics
from lerobot_policy_ebvla.runtime.readout import EnergyReadout
from lerobot_policy_ebvla.runtime.scores import FinalEnergy, HeadEnergyTwoSided
from research.tests.conftest import load_benchmark

research_scores = load_benchmark("research_scores")
window_monitor = load_benchmark("window_monitor")
window_report = load_benchmark("window_report")
HIGH_SCORES, SHIFTED, TOO_TYPICAL = (
    window_monitor.HIGH_SCORES,
    window_monitor.SHIFTED,
    window_monitor.TOO_TYPICAL,
)
WindowTypicalityMonitor = window_monitor.WindowTypicalityMonitor
WindowTypicalityTest = window_monitor.WindowTypicalityTest
WindowRates, window_indices = window_report.WindowRates, window_report.window_indices
ContextEnergyTwoSided = research_scores.ContextEnergyTwoSided
FinalEnergyTwoSided = research_scores.FinalEnergyTwoSided
PhaseEnergyDeviation = research_scores.PhaseEnergyDeviation
PhaseEnergyTwoSided = research_scores.PhaseEnergyTwoSided


def test_the_window_test_alarms_on_vanilla_windows_at_most_at_its_false_alarm_rate():
    # Over fresh draws of the reference and of the window, as the conformal guarantee is stated.
    rng = np.random.default_rng(1)
    alarms = [
        WindowTypicalityTest(rng.normal(size=(40, 1)), window=8).check(rng.normal(size=8)).is_atypical
        for _ in range(3000)
    ]
    assert 0.02 < np.mean(alarms) <= 0.05 + 0.01

    def both(values):  # a two-sided score's window values, |a| and a
        return np.stack([np.abs(values), values], axis=1)

    alarms = [
        WindowTypicalityTest(both(rng.normal(size=40)), window=8).check(both(rng.normal(size=8))).is_atypical
        for _ in range(3000)
    ]
    assert 0.015 < np.mean(alarms) <= 0.05 + 0.01


def test_the_window_test_tells_high_scores_from_too_typical_ones():
    # A two-sided score, |z|: near 0 is typical, and a window of rollouts all near 0 is too typical.
    rng = np.random.default_rng(2)
    test = WindowTypicalityTest(np.abs(rng.normal(size=(40, 1))), window=8)
    high = test.check(np.abs(rng.normal(3.0, 0.5, size=8)))
    typical = test.check(np.abs(rng.normal(0.0, 0.05, size=8)))
    vanilla_like = test.check(np.quantile(np.ravel(test.reference), np.linspace(0.05, 0.95, 8)))
    assert high.is_atypical and high.side == HIGH_SCORES and high.aurocs[0] > 0.9
    assert typical.is_atypical and typical.side == TOO_TYPICAL and typical.aurocs[0] < 0.1
    assert not vanilla_like.is_atypical and vanilla_like.side is None
    assert 0.0 < high.p_value <= 0.05 and vanilla_like.p_value > 0.5


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"reference": ((1.0,),)}, r"at least 2 rows of finite vanilla window values, got shape \(1, 1\)"),
        ({"reference": ((1.0,), (math.inf,), (2.0,))}, r"1 value\(s\) not finite"),
        ({"reference": ((1.0,), (2.0,)), "window": 0}, "`window` must be >= 1"),
        ({"reference": ((1.0,), (2.0,)), "false_alarm_rate": 1.0}, r"`false_alarm_rate` must be in \(0, 1\)"),
    ],
)
def test_the_window_test_refuses_a_bad_reference_or_setting(kwargs, match):
    with pytest.raises(ValueError, match=match):
        WindowTypicalityTest(**kwargs)


def test_the_window_test_checks_exactly_one_window():
    test = WindowTypicalityTest(((1.0, 0.0), (2.0, 0.0), (3.0, 0.0)), window=3)
    with pytest.raises(
        ValueError, match=r"A window holds 3 rollouts of 2 window value\(s\) each.*got shape \(2, 2\)"
    ):
        test.check([[1.0, 0.0], [2.0, 0.0]])


def test_a_two_sided_scores_window_also_tests_its_signed_aggregate_at_half_the_rate():
    # |a| of the window inside vanilla's spread, a itself all on one side: only the signed test sees it.
    rng = np.random.default_rng(4)
    signed = rng.normal(size=40)
    test = WindowTypicalityTest(np.stack([np.abs(signed), signed], axis=1), window=8)
    shifted = np.full(8, 0.7) + rng.normal(0, 0.05, size=8)
    decision = test.check(np.stack([np.abs(shifted), shifted], axis=1))
    assert decision.side == SHIFTED and decision.aurocs[1] > 0.75
    assert decision.p_value == pytest.approx(2 * decision.p_values[1]) and decision.p_values[0] > 0.05


def test_the_two_sided_scores_give_the_window_their_signed_aggregate():
    phase = PhaseStatistics((0.0,), (1.0,))
    aggregates = np.array([[-1.5], [2.0]])
    two_sided = [
        FinalEnergyTwoSided(0.0, 1.0),
        PhaseEnergyTwoSided(phase),
        ContextEnergyTwoSided(phase),
        HeadEnergyTwoSided(phase),
    ]
    for score in two_sided:
        values = window_monitor.score_window_values(score, aggregates)
        assert np.allclose(values, [[1.5, -1.5], [2.0, 2.0]]), score.name
    for score in (FinalEnergy(), PhaseEnergyDeviation(phase)):
        assert np.allclose(window_monitor.score_window_values(score, aggregates), [[-1.5], [2.0]]), score.name


def test_a_rollouts_window_values_aggregate_its_chunks_as_the_calibration_does():
    calibration = OODCalibration.fit([1.0, 2.0], aggregation="max", score=FinalEnergyTwoSided(0.0, 1.0))
    # The max of the chunks' signed z, 2.0, then |a| and a.
    assert np.allclose(window_monitor.window_values(calibration, [[-3.0], [2.0], [1.0]]), [2.0, 2.0])


REFERENCE = np.linspace(4.0, 6.0, 40)[:, None]


def test_the_monitor_decides_once_it_has_a_window_and_then_on_the_last_rollouts():
    monitor = WindowTypicalityMonitor(OODCalibration.fit(np.linspace(4.0, 6.0, 20)), REFERENCE, window=3)
    assert monitor.add_values([5.0]) is None and monitor.add_values([5.1]) is None
    first = monitor.add_values([4.9])
    assert first.rollout_values == ((5.0,), (5.1,), (4.9,)) and not first.is_atypical
    for _ in range(3):
        last = monitor.add_values([9.0])
    assert last.rollout_values == ((9.0,),) * 3 and last.is_atypical and last.side == HIGH_SCORES
    monitor.reset()
    assert monitor.add_values([5.0]) is None


def test_the_monitor_scores_a_rollout_as_the_calibration_does():
    monitor = WindowTypicalityMonitor(OODCalibration.fit(np.linspace(4.0, 6.0, 20)), REFERENCE, window=1)
    decision = monitor.add_rollout(EnergyReadout.of_arrays([4.0, 5.0, 6.0]))  # the final energy's mean
    assert decision.rollout_values == ((5.0,),)


def test_the_monitor_reads_the_calibration_from_a_checkpoint_and_takes_its_reference(tmp_path):
    OODCalibration.fit([1.0, 2.0, 4.0]).save(tmp_path)
    reference = [[4.0, -4.0], [5.5, 5.5], [6.0, -6.0]]
    monitor = WindowTypicalityMonitor.from_pretrained(tmp_path, reference, window=2, false_alarm_rate=0.1)
    assert monitor.calibration.mu_v == pytest.approx(7 / 3) and monitor.test.reference == tuple(
        map(tuple, reference)
    )
    assert monitor.test.window == 2 and monitor.test.false_alarm_rate == 0.1


def test_the_window_reference_is_the_held_out_vanilla_rollouts_scored_against_the_calibration(tmp_path):
    rng = np.random.default_rng(5)

    def episodes(n, seed):
        return {
            (f"run{seed}", i): [
                EnergyRecord(
                    i, chunk, 8 * chunk, 7.0, 5.0 + chunk + rng.normal(0, 0.3), True, "reach", seed + i
                )
                for chunk in range(4)
            ]
            for i in range(n)
        }

    calibration_set, vanilla = episodes(8, 0), episodes(6, 100)
    calibration, scored = window_report.score_sets(
        calibration_set, {"vanilla": vanilla}, "phase_energy_two_sided", None
    )
    reference = fit_score_reference(calibration_set, features=False)
    signed = episode_scores(vanilla, "phase_energy", reference=reference)  # each rollout's mean z
    # The held-out rollouts against the calibration's fit, not the calibration rollouts: |a| and a.
    values = scored["vanilla"].values
    assert (
        values.shape == (6, 2)
        and np.allclose(values[:, 1], signed)
        and np.allclose(values[:, 0], np.abs(signed))
    )
    assert calibration.n_rollouts == 8


def test_window_indices_are_every_window_or_distinct_draws():
    assert window_indices(4, 2, max_windows=10) == [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    drawn = window_indices(40, 8, max_windows=50, seed=3)
    assert len(drawn) == len(set(drawn)) == 50 and all(len(set(w)) == 8 for w in drawn)
    assert window_indices(3, 4, max_windows=10) == []


def test_window_rates_count_the_alarmed_windows_and_their_side():
    test = WindowTypicalityTest(np.linspace(0.0, 1.0, 40)[:, None], window=2, false_alarm_rate=0.05)
    # Two far-high rollouts and two at the centre: only the windows of both high ones alarm.
    rates = WindowRates.of(test, np.array([[5.0], [5.0], [0.5], [0.5]]), max_windows=100)
    assert rates.n_windows == 6 and rates.alarmed == pytest.approx(1 / 6)
    assert rates.too_typical == 0.0 and rates.shifted == 0.0
    assert math.isnan(WindowRates.of(test, np.array([[0.5]]), max_windows=100).alarmed)
