"""The window typicality test: ranks against a reference, the exact law of their mean, the monitor, its analysis."""

import math

import numpy as np
import pytest

from lerobot_policy_ebvla.monitoring.window_report import WindowRates, window_indices
from lerobot_policy_ebvla.runtime import OODCalibration
from lerobot_policy_ebvla.runtime.window import (
    HIGH_SCORES,
    TOO_TYPICAL,
    WindowTypicalityMonitor,
    WindowTypicalityTest,
)


def test_the_window_test_alarms_on_vanilla_windows_at_most_at_its_false_alarm_rate():
    # Over fresh draws of the reference and of the window, as the conformal guarantee is stated.
    rng = np.random.default_rng(1)
    alarms = [
        WindowTypicalityTest(tuple(rng.normal(size=40)), window=8).check(rng.normal(size=8)).is_atypical
        for _ in range(3000)
    ]
    assert 0.02 < np.mean(alarms) <= 0.05 + 0.01


def test_the_window_test_tells_high_scores_from_too_typical_ones():
    # A two-sided score, |z|: near 0 is typical, and a window of rollouts all near 0 is too typical.
    rng = np.random.default_rng(2)
    test = WindowTypicalityTest(tuple(np.abs(rng.normal(size=40))), window=8)
    high = test.check(np.abs(rng.normal(3.0, 0.5, size=8)))
    typical = test.check(np.abs(rng.normal(0.0, 0.05, size=8)))
    vanilla_like = test.check(np.quantile(test.reference_scores, np.linspace(0.05, 0.95, 8)))
    assert high.is_atypical and high.side == HIGH_SCORES and high.auroc > 0.9
    assert typical.is_atypical and typical.side == TOO_TYPICAL and typical.auroc < 0.1
    assert not vanilla_like.is_atypical and vanilla_like.side is None
    assert 0.0 < high.p_value <= 0.05 and vanilla_like.p_value > 0.5


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"reference_scores": (1.0,)}, "at least 2 finite"),
        ({"reference_scores": (1.0, math.inf, 2.0)}, r"1 not finite"),
        ({"reference_scores": (1.0, 2.0), "window": 0}, "`window` must be >= 1"),
        (
            {"reference_scores": (1.0, 2.0), "false_alarm_rate": 1.0},
            r"`false_alarm_rate` must be in \(0, 1\)",
        ),
    ],
)
def test_the_window_test_refuses_a_bad_reference_or_setting(kwargs, match):
    with pytest.raises(ValueError, match=match):
        WindowTypicalityTest(**kwargs)


def test_the_window_test_checks_exactly_one_window():
    with pytest.raises(ValueError, match="A window holds 3 rollout scores, got 2"):
        WindowTypicalityTest((1.0, 2.0, 3.0), window=3).check([1.0, 2.0])


def calibration_with_reference(reference=None):
    reference = tuple(np.linspace(4.0, 6.0, 40)) if reference is None else reference
    return OODCalibration.fit(np.linspace(4.0, 6.0, 20), reference_scores=reference)


def test_the_monitor_decides_once_it_has_a_window_and_then_on_the_last_rollouts():
    monitor = WindowTypicalityMonitor(calibration_with_reference(), window=3)
    assert monitor.add_score(5.0) is None and monitor.add_score(5.1) is None
    first = monitor.add_score(4.9)
    assert first.rollout_scores == (5.0, 5.1, 4.9) and not first.is_atypical
    for _ in range(3):
        last = monitor.add_score(9.0)
    assert last.rollout_scores == (9.0, 9.0, 9.0) and last.is_atypical and last.side == HIGH_SCORES
    monitor.reset()
    assert monitor.add_score(5.0) is None


def test_the_monitor_scores_a_rollout_as_the_calibration_does():
    monitor = WindowTypicalityMonitor(calibration_with_reference(), window=1)
    decision = monitor.add_rollout(np.array([4.0, 5.0, 6.0]))  # the final energy's mean
    assert decision.rollout_scores == (5.0,)


def test_the_monitor_needs_a_calibration_with_reference_scores():
    with pytest.raises(ValueError, match=r"no `reference_scores`.*ebvla-ood-report --calibrate_to"):
        WindowTypicalityMonitor(OODCalibration.fit([4.0, 5.0, 6.0]))


def test_the_reference_scores_are_saved_with_the_calibration_and_read_back(tmp_path):
    calibration_with_reference((4.0, 5.5, 6.0)).save(tmp_path)
    monitor = WindowTypicalityMonitor.from_pretrained(tmp_path, window=2, false_alarm_rate=0.1)
    assert monitor.calibration.reference_scores == (4.0, 5.5, 6.0)
    assert monitor.test.window == 2 and monitor.test.false_alarm_rate == 0.1
    (tmp_path / "without").mkdir()
    OODCalibration.fit([1.0, 2.0]).save(tmp_path / "without")
    assert OODCalibration.load(tmp_path / "without").reference_scores is None


def test_a_calibration_refuses_non_finite_reference_scores():
    with pytest.raises(ValueError, match="`reference_scores` must be finite"):
        OODCalibration.fit([1.0, 2.0], reference_scores=(1.0, math.nan))


def test_window_indices_are_every_window_or_distinct_draws():
    assert window_indices(4, 2, max_windows=10) == [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    drawn = window_indices(40, 8, max_windows=50, seed=3)
    assert len(drawn) == len(set(drawn)) == 50 and all(len(set(w)) == 8 for w in drawn)
    assert window_indices(3, 4, max_windows=10) == []


def test_window_rates_count_the_alarmed_windows_and_their_side():
    test = WindowTypicalityTest(tuple(np.linspace(0.0, 1.0, 40)), window=2, false_alarm_rate=0.05)
    # Two far-high rollouts and two at the centre: only the windows of both high ones alarm.
    rates = WindowRates.of(test, np.array([5.0, 5.0, 0.5, 0.5]), max_windows=100)
    assert rates.n_windows == 6 and rates.alarmed == pytest.approx(1 / 6) and rates.too_typical == 0.0
    assert math.isnan(WindowRates.of(test, np.array([0.5]), max_windows=100).alarmed)
