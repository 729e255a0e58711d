"""The run-time failure alarm: one energy-slope check at a chosen step (`runtime.failure_alarm`)."""

import json
import math

import numpy as np
import pytest
import torch

from lerobot_policy_ebvla.monitoring.failure import FailurePredictionResult, episode_slopes, failure_alarm
from lerobot_policy_ebvla.monitoring.records import EnergyRecord
from lerobot_policy_ebvla.runtime import EnergyReadout
from lerobot_policy_ebvla.runtime.failure_alarm import (
    FAILURE_ALARM_FILENAME,
    EnergyFailureMonitor,
    FailureAlarm,
)

# T = 0.5 + 1.0 * 0.5 = 1.0 at step 3 over a window of 2.
ALARM = FailureAlarm(metric="final", step=3, window=2, k=1.0, mu_ref=0.5, sigma_ref=0.5, n_reference=2)


def readout(final_energy, chunk_index, **kwargs) -> EnergyReadout:
    """The policy's readout of one chunk per environment."""
    return EnergyReadout(None, torch.tensor(final_energy), chunk_index=chunk_index, **kwargs)


def episode(final, success, index=0):
    return [EnergyRecord(index, i, 8 * i, 0.0, final[i], success, "t", None) for i in range(len(final))]


def test_the_slope_is_the_least_squares_slope_of_the_window_ending_at_the_step():
    energies = [9.0, 0.0, 2.0, 100.0]  # steps 2-3 in the window; step 4 comes after the check
    assert ALARM.slope(energies) == pytest.approx(2.0)
    assert ALARM.check(energies) and not ALARM.check([0.0, 0.0, 0.5])


def test_the_run_time_slope_equals_the_reports():
    rng = np.random.default_rng(0)
    episodes = [episode(list(rng.normal(0, 1, 6)), True, index=i) for i in range(5)]
    alarm = FailureAlarm("final", step=5, window=4, k=0.0, mu_ref=0.0, sigma_ref=1.0, n_reference=1)
    report_slopes = episode_slopes(episodes, step=5, window=4)
    run_time = [alarm.slope([r.final_energy for r in e]) for e in episodes]
    np.testing.assert_allclose(run_time, report_slopes)


def test_a_non_finite_energy_raises_the_alarm():
    assert ALARM.check([0.0, 0.0, math.inf])


def test_the_check_needs_the_energies_up_to_its_step():
    with pytest.raises(ValueError, match="step 3; got the energies of 2 steps"):
        ALARM.check([0.0, 1.0])


def test_an_unknown_metric_or_a_bad_reference_is_refused():
    with pytest.raises(ValueError, match="`metric`"):
        FailureAlarm("middle", 3, 2, 1.0, 0.5, 0.5, 2)
    with pytest.raises(ValueError, match="sigma_ref"):
        FailureAlarm("final", 3, 2, 1.0, 0.5, math.nan, 2)
    with pytest.raises(ValueError, match="`step` and `window`"):
        FailureAlarm("final", 0, 2, 1.0, 0.5, 0.5, 2)


def test_failure_alarm_takes_the_chosen_configuration_and_the_references_statistics():
    reference = [
        episode([0.0, 0.0, 0.0], True, 0),
        episode([0.0, 1.0, 2.0], True, 1),
        episode([0, 5, 9], False, 2),
    ]
    chosen = FailurePredictionResult(3, 1, 4, 2, step=3, window=2, multiplier=1.0)
    alarm = failure_alarm(chosen, reference)
    # The failed episode is no reference: slopes 0 and 1 give mu 0.5, sigma 0.5.
    assert (alarm.step, alarm.window, alarm.k, alarm.mu_ref, alarm.sigma_ref, alarm.n_reference) == (
        3,
        2,
        1.0,
        0.5,
        0.5,
        2,
    )
    assert alarm.threshold == pytest.approx(1.0)
    assert alarm.calibration_balanced_accuracy == pytest.approx(chosen.balanced_accuracy)


def test_failure_alarm_without_a_reference_at_its_step_is_refused():
    chosen = FailurePredictionResult(1, 0, 1, 0, step=5, window=2, multiplier=1.0)
    with pytest.raises(ValueError, match="reaches step 5"):
        failure_alarm(chosen, [episode([0.0, 1.0], True)])


def test_save_and_load_round_trip(tmp_path):
    path = ALARM.save(tmp_path)
    assert path.name == FAILURE_ALARM_FILENAME
    assert json.loads(path.read_text())["threshold"] == pytest.approx(1.0)  # written for the reader
    loaded = FailureAlarm.from_pretrained(tmp_path)
    assert (
        loaded.step == 3
        and loaded.threshold == ALARM.threshold
        and math.isnan(loaded.calibration_balanced_accuracy)
    )


def test_saving_never_overwrites_an_alarm_unless_asked(tmp_path):
    ALARM.save(tmp_path)
    with pytest.raises(FileExistsError, match="overwrite=True"):
        FailureAlarm("final", 5, 4, 0.6, 0.0, 1.0, 3).save(tmp_path)
    assert FailureAlarm.load(tmp_path).step == 3
    FailureAlarm("final", 5, 4, 0.6, 0.0, 1.0, 3).save(tmp_path, overwrite=True)
    assert FailureAlarm.load(tmp_path).step == 5


def test_a_malformed_file_names_the_fields_it_needs(tmp_path):
    (tmp_path / FAILURE_ALARM_FILENAME).write_text(json.dumps({"metric": "final", "step": 3}))
    with pytest.raises(ValueError, match="mu_ref, sigma_ref"):
        FailureAlarm.load(tmp_path)


def test_a_missing_alarm_says_how_to_make_one(tmp_path):
    with pytest.raises(FileNotFoundError, match="--calibrate_to"):
        FailureAlarm.from_pretrained(tmp_path / "no_such_checkpoint")


def test_the_monitor_decides_once_at_the_step_and_keeps_the_decision():
    monitor = EnergyFailureMonitor(ALARM)
    # Two environments: the first's energy rises by 2 a step (slope 2 > T = 1), the second's stays flat.
    answers = [monitor.update(readout([2.0 * s, 0.0], s)) for s in range(5)]
    assert [[d.alarm for d in a] for a in answers] == [
        [None, None],
        [None, None],
        [True, False],
        [True, False],
        [True, False],
    ]
    assert (
        answers[2][0].slope == pytest.approx(2.0) and answers[4][0].step == 5 and answers[0][0].slope is None
    )


def test_the_monitor_reads_the_energy_of_its_metric_from_a_readout():
    start = EnergyFailureMonitor(FailureAlarm("start", 2, 2, 0.0, 0.0, 1.0, 2))
    readouts = [
        EnergyReadout(torch.tensor([v]), torch.tensor([0.0]), chunk_index=i) for i, v in enumerate((0, 3))
    ]
    assert [start.update(r)[0].alarm for r in readouts] == [None, True]


def test_the_monitor_reads_the_context_energy_for_a_context_slope_and_names_it_when_missing():
    context = EnergyFailureMonitor(FailureAlarm("context", 2, 2, 0.0, 0.0, 1.0, 2))
    readouts = [readout([0.0], i, context_energy=torch.tensor([v])) for i, v in enumerate((0.0, 3.0))]
    assert [context.update(r)[0].alarm for r in readouts] == [None, True]
    context.reset()
    with pytest.raises(ValueError, match="slope of `context_energy`, which this readout does not have"):
        context.update(readout([0.0], 0))


def test_the_monitor_refuses_a_changed_number_of_environments_and_forgets_on_reset():
    monitor = EnergyFailureMonitor(ALARM)
    monitor.update(readout([0.0, 0.0], 0))
    with pytest.raises(ValueError, match="Expected 2 energies"):
        monitor.update(readout([0.0, 0.0, 0.0], 1))
    monitor.reset()
    assert monitor.update(readout([1.0], 0))[0].alarm is None


def test_the_monitor_counts_a_readout_it_has_seen_once():
    monitor = EnergyFailureMonitor(ALARM)
    first = readout([0.0], 0)
    assert [monitor.update(first)[0].step, monitor.update(first)[0].step] == [1, 1]
    assert monitor.update(readout([0.0], 1))[0].step == 2
