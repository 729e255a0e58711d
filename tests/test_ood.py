"""Energy-based OOD detection (Sec. III-C): the decision rule and its thresholds (Eq. 5, conformal), the
metrics (AUROC with bootstrap intervals), the calibration, the run-time monitor, Table III and baselines.

The running example: vanilla rollout scores [1, 2, 3, 4] (mu_v = 2.5, sigma_v = sqrt(1.25)) and OOD
rollout scores [3, 5, 6].
"""

import json
import math

import numpy as np
import pytest
import torch

from lerobot_policy_ebvla.monitoring.baselines import ContextFeatureModel, available_scores
from lerobot_policy_ebvla.monitoring.metrics import (
    auroc,
    bootstrap_auroc_difference_interval,
    bootstrap_auroc_interval,
    roc_curve,
    wilson_interval,
)
from lerobot_policy_ebvla.monitoring.ood import (
    TABLE_III_MULTIPLIERS,
    format_balanced_accuracy_table,
    format_detection_table,
    format_table_iii,
    ood_detection_table,
)
from lerobot_policy_ebvla.monitoring.records import EnergyRecord, group_by_episode
from lerobot_policy_ebvla.monitoring.scores import episode_scores
from lerobot_policy_ebvla.runtime.calibration import OOD_CALIBRATION_FILENAME, OODCalibration
from lerobot_policy_ebvla.runtime.monitor import EnergyOODMonitor
from lerobot_policy_ebvla.runtime.readout import EnergyReadout
from lerobot_policy_ebvla.runtime.scores import rollout_score
from lerobot_policy_ebvla.runtime.threshold import conformal_threshold, exceeds

VANILLA = [1.0, 2.0, 3.0, 4.0]
OOD = [3.0, 5.0, 6.0]
SIGMA = math.sqrt(1.25)


# The decision rule and its thresholds.


def test_exceeds_flags_scores_above_the_threshold_and_non_finite_scores():
    flags = exceeds([1.0, 2.0, 2.5, math.inf, math.nan], 2.0)
    assert flags.tolist() == [False, False, True, True, True]


@pytest.mark.parametrize("alpha", [0.05, 0.1, 0.2])
def test_conformal_threshold_keeps_the_false_alarm_rate_at_most_alpha(alpha):
    # Many calibration / test splits of the same distribution: the average false-alarm rate is <= alpha
    # and, as scores have no ties, above alpha - 1 / (n + 1).
    rng = np.random.default_rng(0)
    n = 39
    rates = []
    for _ in range(400):
        calibration, test = rng.normal(size=n), rng.normal(size=200)
        rates.append(exceeds(test, conformal_threshold(calibration, alpha)).mean())
    assert alpha - 1 / (n + 1) - 0.01 <= np.mean(rates) <= alpha + 0.01


def test_conformal_threshold_is_the_corrected_order_statistic():
    # n = 19, alpha = 0.1: rank ceil(20 * 0.9) = 18 of the sorted scores 1..19.
    assert conformal_threshold(np.arange(19, 0, -1.0), 0.1) == 18.0


def test_conformal_threshold_with_too_few_scores_flags_nothing():
    assert conformal_threshold([1.0, 2.0, 3.0], 0.05) == math.inf


def test_conformal_threshold_rejects_an_alpha_outside_zero_one():
    with pytest.raises(ValueError, match="alpha"):
        conformal_threshold([1.0, 2.0], 1.5)


# Metrics.


def test_wilson_interval_of_a_success_rate():
    low, high = wilson_interval(22, 34)  # the quickstart's vanilla success, 64.7%
    assert (round(low, 2), round(high, 2)) == (0.48, 0.79)
    assert wilson_interval(0, 8)[0] == 0.0 and 0.3 < wilson_interval(0, 8)[1] < 0.4
    assert wilson_interval(8, 8)[1] == 1.0
    assert all(math.isnan(v) for v in wilson_interval(0, 0))


def test_bootstrap_interval_contains_the_auroc():
    rng = np.random.default_rng(1)
    vanilla, ood = rng.normal(size=40), rng.normal(0.8, size=40)
    low, high = bootstrap_auroc_interval(vanilla, ood, seed=0)
    assert low <= auroc(vanilla, ood) <= high


def test_bootstrap_interval_shrinks_with_more_episodes():
    rng = np.random.default_rng(2)

    def width(n):
        low, high = bootstrap_auroc_interval(rng.normal(size=n), rng.normal(0.8, size=n), seed=0)
        return high - low

    assert width(400) < width(25) / 2


def test_bootstrap_interval_is_reproducible_with_its_seed():
    vanilla, ood = [1.0, 2.0, 3.0, 4.0], [2.5, 5.0, 6.0]
    assert bootstrap_auroc_interval(vanilla, ood, seed=3) == bootstrap_auroc_interval(vanilla, ood, seed=3)


def test_bootstrap_interval_without_positives_is_nan():
    assert all(math.isnan(v) for v in bootstrap_auroc_interval([1.0, 2.0], []))


def test_paired_difference_interval_of_a_score_with_itself_is_zero():
    rng = np.random.default_rng(4)
    vanilla, ood = rng.normal(size=30), rng.normal(1.0, size=20)
    assert bootstrap_auroc_difference_interval(vanilla, ood, vanilla, ood) == (0.0, 0.0)


def test_paired_difference_interval_tells_a_score_from_its_noisier_copy_on_the_same_rollouts():
    rng = np.random.default_rng(5)
    vanilla, ood = rng.normal(size=200), rng.normal(1.5, size=60)
    noisy_vanilla, noisy_ood = vanilla + rng.normal(0, 1.0, 200), ood + rng.normal(0, 1.0, 60)
    difference = auroc(vanilla, ood) - auroc(noisy_vanilla, noisy_ood)
    low, high = bootstrap_auroc_difference_interval(vanilla, ood, noisy_vanilla, noisy_ood, seed=0)
    assert 0 < low <= difference <= high
    # The separate intervals overlap: only the pairing shows the difference.
    assert bootstrap_auroc_interval(vanilla, ood)[0] < bootstrap_auroc_interval(noisy_vanilla, noisy_ood)[1]
    _, reversed_high = bootstrap_auroc_difference_interval(noisy_vanilla, noisy_ood, vanilla, ood, seed=0)
    assert reversed_high < 0


def test_paired_difference_interval_needs_the_same_rollouts():
    with pytest.raises(ValueError, match="3 and 2 negatives, 2 and 2 positives"):
        bootstrap_auroc_difference_interval([1.0, 2.0, 3.0], [4.0, 5.0], [1.0, 2.0], [4.0, 5.0])


# Rollout scores.


@pytest.mark.parametrize(
    ("aggregation", "expected"), [("mean", 3.25), ("max", 6.0), ("last", 2.0), ("median", 3.0)]
)
def test_rollout_score_aggregations(aggregation, expected):
    assert rollout_score([4.0, 1.0, 6.0, 2.0], aggregation) == expected


def test_rollout_score_accepts_a_tensor():
    assert rollout_score(torch.tensor([1.0, 3.0])) == 2.0


def test_rollout_score_rejects_an_unknown_aggregation():
    with pytest.raises(ValueError, match="aggregation"):
        rollout_score([1.0], "min")


def test_rollout_score_rejects_an_empty_rollout():
    with pytest.raises(ValueError, match="at least one"):
        rollout_score([])


def test_rollout_score_of_a_diverged_chunk_is_infinite():
    assert rollout_score([1.0, math.inf]) == math.inf


def test_episode_scores_of_grouped_records_score_each_episode():
    records = [
        EnergyRecord(0, 0, 0, 9.0, 1.0, True, "t", None),
        EnergyRecord(0, 1, 8, 9.0, 3.0, True, "t", None),
        EnergyRecord(1, 0, 0, 9.0, 5.0, False, "t", None),
    ]
    assert episode_scores(group_by_episode(records), "final_energy").tolist() == [2.0, 5.0]


def test_episode_scores_over_the_first_chunks_use_those_chunks_only():
    records = [EnergyRecord(0, i, 8 * i, 9.0, e, True, "t", None) for i, e in enumerate([1.0, 3.0, 5.0, 7.0])]
    assert episode_scores(group_by_episode(records), "final_energy", first_chunks=2).tolist() == [2.0]


def test_episode_scores_of_an_episode_shorter_than_the_first_chunks_use_all_its_chunks():
    records = [EnergyRecord(0, i, 8 * i, 9.0, e, True, "t", None) for i, e in enumerate([1.0, 3.0])]
    assert episode_scores(group_by_episode(records), "final_energy", first_chunks=5).tolist() == [2.0]


def test_episode_scores_reject_fewer_than_one_first_chunk():
    with pytest.raises(ValueError, match="first_chunks"):
        episode_scores({}, "final_energy", first_chunks=0)


def test_fit_computes_mu_v_and_population_sigma_v():
    calibration = OODCalibration.fit(VANILLA, k=2.0)
    assert calibration.mu_v == 2.5
    assert calibration.sigma_v == pytest.approx(SIGMA)
    assert calibration.threshold == pytest.approx(2.5 + 2.0 * SIGMA)
    assert calibration.n_rollouts == 4


def test_fit_on_a_single_rollout_gives_sigma_zero():
    calibration = OODCalibration.fit([5.0], k=3.0)
    assert calibration.sigma_v == 0.0 and calibration.threshold == 5.0


def test_fit_on_equal_energies_flags_only_higher_scores():
    monitor = EnergyOODMonitor(OODCalibration.fit([2.0, 2.0, 2.0]))
    assert monitor.check(EnergyReadout.of_arrays(2.0))[0].in_distribution
    assert monitor.check(EnergyReadout.of_arrays(2.0001))[0].is_ood


def test_fit_leaves_out_non_finite_scores_with_a_warning():
    with pytest.warns(UserWarning, match="1 non-finite"):
        calibration = OODCalibration.fit([1.0, 3.0, math.inf])
    assert calibration.mu_v == 2.0 and calibration.n_rollouts == 2


def test_fit_without_finite_scores_raises():
    with pytest.raises(ValueError, match="finite"), pytest.warns(UserWarning):
        OODCalibration.fit([math.inf])


def test_fit_with_a_false_alarm_rate_adds_the_conformal_threshold():
    calibration = OODCalibration.fit(np.arange(1.0, 20.0), false_alarm_rate=0.1, rule="conformal")
    assert calibration.conformal_threshold == 18.0 and calibration.threshold == 18.0
    assert calibration.with_k(1.0).threshold == pytest.approx(calibration.mu_v + calibration.sigma_v)


def test_conformal_rule_needs_a_conformal_threshold():
    with pytest.raises(ValueError, match="conformal_threshold"):
        OODCalibration(mu_v=1.0, sigma_v=1.0, rule="conformal")


def test_a_calibration_file_without_conformal_fields_still_loads(tmp_path):
    old = {"mu_v": 2.5, "sigma_v": 1.0, "k": 1.0, "aggregation": "mean", "n_rollouts": 4, "threshold": 3.5}
    (tmp_path / OOD_CALIBRATION_FILENAME).write_text(json.dumps(old))
    calibration = OODCalibration.load(tmp_path)
    assert calibration.rule == "mean_std" and calibration.threshold == 3.5


def test_calibration_with_an_infinite_conformal_threshold_round_trips(tmp_path):
    calibration = OODCalibration.fit([1.0, 2.0, 3.0], false_alarm_rate=0.05)
    assert calibration.conformal_threshold == math.inf
    calibration.save(tmp_path)
    assert OODCalibration.load(tmp_path) == calibration


def test_calibration_round_trips_through_json(tmp_path):
    calibration = OODCalibration.fit(VANILLA, k=0.7, aggregation="max")
    path = calibration.save(tmp_path)
    assert path == tmp_path / OOD_CALIBRATION_FILENAME
    assert json.loads(path.read_text())["threshold"] == pytest.approx(calibration.threshold)
    assert OODCalibration.load(tmp_path) == calibration


def test_calibration_save_refuses_to_overwrite(tmp_path):
    OODCalibration.fit(VANILLA).save(tmp_path)
    with pytest.raises(FileExistsError):
        OODCalibration.fit([10.0, 20.0]).save(tmp_path)
    assert OODCalibration.load(tmp_path).mu_v == 2.5


def test_calibration_save_overwrites_when_asked(tmp_path):
    OODCalibration.fit(VANILLA).save(tmp_path)
    OODCalibration.fit([10.0, 20.0]).save(tmp_path, overwrite=True)
    assert OODCalibration.load(tmp_path).mu_v == 15.0


def test_calibration_save_points_to_pretrained_model_folder(tmp_path):
    (tmp_path / "pretrained_model").mkdir()
    with pytest.raises(ValueError, match="pretrained_model"):
        OODCalibration.fit(VANILLA).save(tmp_path)


def test_calibration_save_needs_an_existing_folder(tmp_path):
    with pytest.raises(FileNotFoundError):
        OODCalibration.fit(VANILLA).save(tmp_path / "missing")


def test_monitor_from_pretrained_uses_the_saved_threshold(tmp_path):
    OODCalibration.fit(VANILLA, k=1.0).save(tmp_path)
    monitor = EnergyOODMonitor.from_pretrained(tmp_path)
    assert monitor.threshold == pytest.approx(2.5 + SIGMA)


def test_monitor_from_pretrained_without_calibration_names_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match=OOD_CALIBRATION_FILENAME):
        EnergyOODMonitor.from_pretrained(tmp_path)


def test_monitor_from_pretrained_can_override_k(tmp_path):
    OODCalibration.fit(VANILLA, k=1.0).save(tmp_path)
    assert EnergyOODMonitor.from_pretrained(tmp_path, k=0.0).threshold == 2.5


def test_monitor_check_of_one_chunk_returns_one_decision():
    (decision,) = EnergyOODMonitor(OODCalibration(mu_v=2.0, sigma_v=1.0, k=1.0)).check(
        EnergyReadout.of_arrays(3.5)
    )
    assert decision.is_ood and decision.energy == 3.5 and decision.threshold == 3.0


def test_monitor_check_of_a_batch_returns_one_decision_per_sample():
    monitor = EnergyOODMonitor(OODCalibration(mu_v=2.0, sigma_v=1.0, k=1.0))
    decisions = monitor.check(EnergyReadout(None, torch.tensor([1.0, 3.0, 3.5])))
    assert [d.in_distribution for d in decisions] == [True, True, False]


def test_monitor_flags_non_finite_energies():
    monitor = EnergyOODMonitor(OODCalibration(mu_v=2.0, sigma_v=1.0))
    assert all(d.is_ood for d in monitor.check(EnergyReadout(None, torch.tensor([math.inf, math.nan]))))


def test_monitor_update_checks_each_environments_running_rollout_score():
    monitor = EnergyOODMonitor(OODCalibration(mu_v=2.0, sigma_v=1.0, k=1.0, aggregation="mean"))
    monitor.update(EnergyReadout(None, torch.tensor([2.0, 4.0]), chunk_index=0))
    decisions = monitor.update(EnergyReadout(None, torch.tensor([3.0, 4.0]), chunk_index=1))
    assert [d.energy for d in decisions] == [2.5, 4.0]
    assert [d.in_distribution for d in decisions] == [True, False]


def test_monitor_update_counts_a_readout_it_has_seen_once():
    monitor = EnergyOODMonitor(OODCalibration(mu_v=2.0, sigma_v=1.0, k=1.0))
    readout = EnergyReadout(None, torch.tensor([2.0]))
    first = monitor.update(readout)
    assert monitor.update(readout) is first
    assert monitor.update(EnergyReadout(None, torch.tensor([4.0]), chunk_index=1))[0].energy == 3.0


def test_monitor_update_refuses_a_readout_of_another_episode():
    monitor = EnergyOODMonitor(OODCalibration(mu_v=2.0, sigma_v=1.0, k=1.0))
    monitor.update(EnergyReadout(None, torch.tensor([2.0])))
    with pytest.raises(ValueError, match=r"chunk 0 .* seen 1 chunks: call `monitor.reset\(\)`"):
        monitor.update(EnergyReadout(None, torch.tensor([2.0])))


def test_monitor_reset_forgets_past_energies():
    monitor = EnergyOODMonitor(OODCalibration(mu_v=2.0, sigma_v=1.0, k=1.0))
    monitor.update(EnergyReadout(None, torch.tensor([10.0])))
    monitor.reset()
    assert monitor.update(EnergyReadout(None, torch.tensor([1.0])))[0].energy == 1.0


def test_monitor_check_rollout_uses_the_calibration_aggregation():
    monitor = EnergyOODMonitor(OODCalibration(mu_v=2.0, sigma_v=1.0, k=1.0, aggregation="max"))
    assert monitor.check_rollout(EnergyReadout.of_arrays([1.0, 5.0, 1.0])).energy == 5.0


def test_detection_table_at_one_sigma_matches_hand_computation():
    (row,) = ood_detection_table(VANILLA, OOD, multipliers=[1.0])
    # T = 3.618: vanilla 4 is a false alarm, OOD 3 is missed.
    assert row.threshold == pytest.approx(2.5 + SIGMA)
    assert (row.tp, row.fp, row.tn, row.fn) == (2, 1, 3, 1)
    assert row.accuracy == pytest.approx(5 / 7)
    assert row.tpr == pytest.approx(2 / 3)
    assert row.fpr == pytest.approx(1 / 4)
    assert row.balanced_accuracy == pytest.approx((2 / 3 + 3 / 4) / 2)
    assert row.f1 == pytest.approx(2 / 3)


def test_detection_table_at_zero_sigma_matches_hand_computation():
    (row,) = ood_detection_table(VANILLA, OOD, multipliers=[0.0])
    # T = mu_v = 2.5: vanilla 3 and 4 are false alarms, every OOD rollout is caught.
    assert (row.tp, row.fp, row.tn, row.fn) == (3, 2, 2, 0)
    assert row.f1 == pytest.approx(6 / 8)


def test_detection_table_adds_the_conformal_row_of_the_calibration():
    calibration = OODCalibration.fit(VANILLA, false_alarm_rate=0.2)  # rank ceil(5 * 0.8) = 4: T = 4
    rows = ood_detection_table(VANILLA, OOD, multipliers=[1.0], calibration=calibration)
    assert rows[-1].threshold == 4.0 and rows[-1].name == "conf. α=20.0%"
    assert (rows[-1].fp, rows[-1].tp) == (0, 2)


def test_detection_table_has_one_row_per_multiplier_of_table_iii():
    rows = ood_detection_table(VANILLA, OOD)
    assert [r.multiplier for r in rows] == [0.2, 0.5, 0.7, 0.8, 0.9, 1.0, 1.5, 2.0, 3.0]


def test_detection_table_without_ood_rollouts_has_nan_tpr():
    (row,) = ood_detection_table(VANILLA, [], multipliers=[1.0])
    assert math.isnan(row.tpr) and math.isnan(row.balanced_accuracy)
    assert row.accuracy == pytest.approx(3 / 4)


def test_detection_table_without_vanilla_rollouts_has_nan_fpr():
    calibration = OODCalibration(mu_v=2.5, sigma_v=0.0)
    (row,) = ood_detection_table([], OOD, multipliers=[1.0], calibration=calibration)
    assert math.isnan(row.fpr) and math.isnan(row.balanced_accuracy)
    assert row.tpr == 1.0


def test_format_detection_table_prints_percentages():
    table = format_detection_table(ood_detection_table(VANILLA, OOD, multipliers=[1.0]))
    assert "| 1.0σ | 3.618 | 71.4% | 70.8% | 66.7% | 25.0% | 66.7% | 1 | 1 |" in table


def test_format_detection_table_puts_baselines_beside_the_final_energy():
    rows = ood_detection_table(VANILLA, OOD, multipliers=[1.0])
    baseline = ood_detection_table([1.0, 1.0, 1.0, 1.0], [1.0, 1.0, 1.0], multipliers=[1.0])
    table = format_detection_table(rows, {"initial_energy": baseline})
    assert "Bal. Acc. initial_energy |" in table.splitlines()[0]
    assert table.splitlines()[2].endswith("| 1 | 1 | 50.0% |")


def test_table_iii_is_printed_as_the_paper_prints_it_with_mu_sigma_auroc_and_counts_beside():
    calibration = OODCalibration.fit(VANILLA, false_alarm_rate=0.2)
    rows = ood_detection_table(VANILLA, OOD, calibration=calibration)
    text = format_table_iii(rows, calibration, "0.875 [0.5, 1.0]", n_vanilla=4, n_ood=3)
    lines = text.splitlines()
    assert "(mu_v = 2.500, sigma_v = 1.118, from 4 calibration rollouts only)" in lines[0]
    assert lines[2] == (
        "| Multiplier | Threshold | Accuracy | Bal. Acc. | TPR (Catch) | FPR (False Alarm) | F1-Score | FP | FN |"
    )
    # The paper's nine rows, without the conformal one.
    assert [line.split(" | ")[0] for line in lines[4:13]] == [f"| {k}σ" for k in TABLE_III_MULTIPLIERS]
    assert lines[13] == ""
    assert lines[14] == "AUROC 0.875 [0.5, 1.0] (bootstrap 95% interval); n vanilla = 4, n OOD = 3."


def test_balanced_accuracy_table_sets_every_score_side_by_side_at_each_rule():
    calibration = OODCalibration.fit(VANILLA, false_alarm_rate=0.2)
    rows = {
        "final_energy": ood_detection_table(VANILLA, OOD, [1.0], calibration),
        "initial_energy": ood_detection_table([1.0] * 4, [1.0] * 3, [1.0], calibration),
    }
    lines = format_balanced_accuracy_table(rows).splitlines()
    assert lines[0] == "| Rule | Bal. Acc. final_energy | Bal. Acc. initial_energy |"
    assert lines[2:] == ["| 1.0σ | 70.8% | 50.0% |", "| conf. α=20.0% | 83.3% | 50.0% |"]


def test_auroc_counts_ties_as_one_half():
    # OOD 3 beats vanilla 1 and 2, ties 3, loses to 4; OOD 5 and 6 beat all four: (2.5 + 4 + 4) / 12.
    assert auroc(VANILLA, OOD) == pytest.approx(10.5 / 12)


def test_auroc_of_separable_scores_is_one():
    assert auroc([1.0, 2.0], [3.0, math.inf]) == 1.0


def test_auroc_of_reversed_scores_is_zero():
    assert auroc([3.0, 4.0], [1.0, 2.0]) == 0.0


def test_auroc_of_equal_scores_is_one_half():
    assert auroc([2.0, 2.0], [2.0, 2.0, 2.0]) == 0.5


def test_auroc_without_positives_is_nan():
    assert math.isnan(auroc(VANILLA, []))


def test_auroc_rejects_nan_scores():
    with pytest.raises(ValueError, match="NaN"):
        auroc([1.0, math.nan], [2.0])


def test_roc_curve_matches_hand_computation():
    fpr, tpr, thresholds = roc_curve(VANILLA, OOD)
    np.testing.assert_array_equal(thresholds, [6, 5, 4, 3, 2, 1, -np.inf])
    np.testing.assert_allclose(tpr, [0, 1 / 3, 2 / 3, 2 / 3, 1, 1, 1])
    np.testing.assert_allclose(fpr, [0, 0, 0, 1 / 4, 2 / 4, 3 / 4, 1])


def test_roc_curve_area_equals_auroc():
    rng = np.random.default_rng(0)
    vanilla, ood = rng.integers(0, 5, 40).astype(float), rng.integers(2, 8, 30).astype(float)
    fpr, tpr, _ = roc_curve(vanilla, ood)
    assert np.trapezoid(tpr, fpr) == pytest.approx(auroc(vanilla, ood))


# Baselines.


def chunk(episode, index, final=1.0, initial=2.0, spread=None, feature=None):
    return EnergyRecord(
        episode,
        index,
        8 * index,
        initial,
        final,
        True,
        "t",
        None,
        restart_spread=spread,
        context_feature=feature,
    )


def test_baselines_are_scored_per_rollout_like_the_final_energy():
    episodes = {
        0: [chunk(0, 0, spread=0.1), chunk(0, 1, spread=0.3)],
        1: [chunk(1, 0, initial=5.0, spread=1.0)],
    }
    assert episode_scores(episodes, "restart_spread").tolist() == pytest.approx([0.2, 1.0])
    assert episode_scores(episodes, "initial_energy", aggregation="max").tolist() == [2.0, 5.0]


def test_available_scores_need_every_chunk_to_carry_the_baseline():
    with_spread = [[chunk(0, 0, spread=0.1)], [chunk(1, 0, spread=0.2)]]
    assert available_scores(with_spread) == [
        "final_energy",
        "phase_energy",
        "initial_energy",
        "restart_spread",
    ]
    assert "restart_spread" not in available_scores([*with_spread, [chunk(2, 0)]])


def test_feature_distances_rank_far_contexts_above_calibration_like_ones():
    rng = np.random.default_rng(0)
    calibration = rng.normal(size=(200, 8))
    model = ContextFeatureModel.fit(calibration, episode_ids=[i // 10 for i in range(200)], k=3)
    near, far = rng.normal(size=(50, 8)), rng.normal(size=(50, 8)) + np.r_[4.0, np.zeros(7)]
    assert auroc(model.context_distance(near), model.context_distance(far)) > 0.95
    assert auroc(model.context_knn(near), model.context_knn(far)) > 0.95


def test_knn_skips_the_neighbours_of_the_same_episode():
    model = ContextFeatureModel.fit(np.array([[1.0, 0.0], [1.0, 0.0], [0.0, 1.0]]), ["a", "a", "b"], k=1)
    assert model.context_knn(np.array([[1.0, 0.0]]))[0] == pytest.approx(0.0)
    # Standardized by the calibration std (sqrt(2) / 3 in each dimension): (1, 0) and (0, 1) are 3 apart.
    assert model.context_knn(np.array([[1.0, 0.0]]), episode_id="a")[0] == pytest.approx(3.0)


def test_mahalanobis_of_a_calibration_episode_leaves_its_features_out():
    rng = np.random.default_rng(3)
    features, ids = rng.normal(size=(30, 4)), [i // 5 for i in range(30)]
    model = ContextFeatureModel.fit(features, ids)
    without_episode_0 = ContextFeatureModel.fit(features[5:], ids[5:])
    np.testing.assert_allclose(
        model.context_distance(features[:5], episode_id=0), without_episode_0.context_distance(features[:5])
    )


def test_mahalanobis_of_a_held_out_episode_uses_every_calibration_feature():
    rng = np.random.default_rng(4)
    features = rng.normal(size=(20, 3))
    model = ContextFeatureModel.fit(features, [i // 4 for i in range(20)])
    queries = rng.normal(size=(3, 3))
    np.testing.assert_array_equal(
        model.context_distance(queries, episode_id="held out"), model.context_distance(queries)
    )


def test_mahalanobis_scores_calibration_episodes_leave_one_out_as_held_out_ones_are_scored():
    # In-sample, an episode's own chunks pull its distance down: the threshold fitted on these would be low.
    rng = np.random.default_rng(5)
    features, ids = rng.normal(size=(60, 8)), [i // 6 for i in range(60)]
    model = ContextFeatureModel.fit(features, ids)
    in_sample = np.mean(
        [model.context_distance(features[ids.index(e) : ids.index(e) + 6]).mean() for e in range(10)]
    )
    left_out = np.mean(
        [
            model.context_distance(features[ids.index(e) : ids.index(e) + 6], episode_id=e).mean()
            for e in range(10)
        ]
    )
    held_out = model.context_distance(rng.normal(size=(600, 8))).mean()
    assert in_sample < left_out
    assert abs(left_out - held_out) < abs(in_sample - held_out)
