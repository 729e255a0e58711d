"""Energy-slope failure prediction (Sec. III-D, Table IV).

The running example at step 3, window 3 (final energies, slope per step):
    success A [0, 0, 0] slope 0    success B [0, 1, 2] slope 1
    failed  C [0, 2, 4] slope 2    failed  D [0, .5, 1] slope 0.5
Reference slopes (the successful A, B): mean 0.5, population std 0.5.
"""

import dataclasses
import math

import numpy as np
import pytest

from lerobot_policy_ebvla.monitoring.failure import (
    FailurePredictionResult,
    energy_matrix,
    episode_slopes,
    evaluate_configurations,
    evaluate_failure_predictor,
    failure_prediction_sweep,
    first_alarms,
    format_failure_table,
    linear_slope,
    select_check_step,
    select_configurations,
    slope_scores,
)
from lerobot_policy_ebvla.monitoring.lead_time import (
    Alarm,
    LeadTimeSummary,
    failure_onset,
    format_alarms,
    format_lead_time_table,
)
from lerobot_policy_ebvla.monitoring.records import EnergyRecord


def episode(final, success, initial=None, index=0):
    initial = [0.0] * len(final) if initial is None else initial
    return [
        EnergyRecord(index, i, 8 * i, initial[i], final[i], success, "t", None) for i in range(len(final))
    ]


EPISODES = [
    episode([0.0, 0.0, 0.0], True, index=0),
    episode([0.0, 1.0, 2.0], True, index=1),
    episode([0.0, 2.0, 4.0], False, index=2),
    episode([0.0, 0.5, 1.0], False, index=3),
]


def test_linear_slope_is_the_least_squares_slope():
    assert linear_slope([1.0, 3.0, 5.0]) == pytest.approx(2.0)
    assert linear_slope([0.0, 2.0, 1.0, 3.0]) == pytest.approx(0.8)


def test_linear_slope_of_one_point_is_zero():
    assert linear_slope([5.0]) == 0.0


def test_episode_slopes_use_the_window_ending_at_the_step():
    # Step 3, window 2: chunks 2 and 3 of [0, 10, 11] -> slope 1.
    assert episode_slopes([episode([0.0, 10.0, 11.0], True)], step=3, window=2)[0] == pytest.approx(1.0)


def test_episode_slopes_truncate_a_window_reaching_before_step_one():
    assert episode_slopes([episode([0.0, 4.0, 100.0], True)], step=2, window=5)[0] == pytest.approx(4.0)


def test_episode_slopes_of_an_episode_that_ended_are_nan():
    assert math.isnan(episode_slopes([episode([0.0, 1.0], True)], step=3, window=2)[0])


def test_slope_start_uses_the_initial_energy():
    ep = episode([0.0, 0.0, 0.0], True, initial=[3.0, 2.0, 1.0])
    assert episode_slopes([ep], step=3, window=3, metric="start")[0] == pytest.approx(-1.0)


def test_predictor_matches_hand_computation():
    result = evaluate_failure_predictor(EPISODES, step=3, window=3, multiplier=1.0)
    # T = 0.5 + 1.0 * 0.5 = 1: only C (slope 2) is flagged; B's slope 1 equals T and is not.
    assert result.threshold == pytest.approx(1.0)
    assert result.accuracy == pytest.approx(3 / 4)
    assert result.tpr == pytest.approx(1 / 2)
    assert result.specificity == 1.0
    assert result.balanced_accuracy == pytest.approx(3 / 4)


def test_predictor_at_zero_std_matches_hand_computation():
    result = evaluate_failure_predictor(EPISODES, step=3, window=3, multiplier=0.0)
    # T = 0.5: B and C are flagged; D's slope 0.5 equals T.
    assert (result.accuracy, result.tpr, result.specificity) == pytest.approx((0.5, 0.5, 0.5))


def test_predictor_calibrates_on_the_successful_reference_episodes_only():
    reference = [episode([0.0, 0.1, 0.2], True), episode([0.0, 5.0, 10.0], False)]
    result = evaluate_failure_predictor(
        EPISODES, step=3, window=3, multiplier=0.0, reference_episodes=reference
    )
    # The failed reference episode (slope 5) is filtered out: T = 0.1 from the successful one alone;
    # B, C and D are flagged.
    assert result.threshold == pytest.approx(0.1)
    assert (result.tpr, result.specificity) == (1.0, 0.5)


def test_predictor_flags_a_non_finite_slope():
    episodes = [*EPISODES, episode([0.0, 1.0, math.inf], False, index=4)]
    result = evaluate_failure_predictor(episodes, step=3, window=3, multiplier=1.0)
    assert result.tpr == pytest.approx(2 / 3)


def test_predictor_without_reference_slopes_is_undefined():
    result = evaluate_failure_predictor(EPISODES[2:], step=3, window=3, multiplier=1.0)
    assert math.isnan(result.threshold) and math.isnan(result.balanced_accuracy)


def test_without_carry_forward_episodes_shorter_than_the_step_are_excluded():
    episodes = [*EPISODES, episode([0.0, 9.0], False, index=4)]
    result = evaluate_failure_predictor(episodes, step=3, window=3, multiplier=1.0, carry_forward=False)
    assert (result.n_episodes, result.n_failed) == (4, 2)


def test_carry_forward_repeats_the_last_energy_after_an_episode_ends():
    matrix = energy_matrix(
        [episode([1.0, 2.0], True), episode([0.0, 1.0, 2.0, 3.0], False)], carry_forward=True
    )
    np.testing.assert_array_equal(matrix[0], [1.0, 2.0, 2.0, 2.0])


def test_carry_forward_judges_the_same_episodes_at_every_step():
    # Successful episodes end early, failed ones run on: without carry-forward the failure rate climbs.
    episodes = [episode([0.0] * (3 if i % 2 else 8), bool(i % 2), index=i) for i in range(6)]
    steps, windows, multipliers = range(1, 9), [2], [1.0]
    kept = failure_prediction_sweep(episodes, steps, windows, multipliers, carry_forward=True)
    assert {(r.n_episodes, r.failure_rate) for r in kept} == {(6, 0.5)}
    dropped = failure_prediction_sweep(episodes, steps, windows, multipliers, carry_forward=False)
    assert dropped[-1].n_episodes == 3 and dropped[-1].failure_rate == 1.0


def test_held_out_evaluation_keeps_the_configuration_and_threshold_chosen_on_calibration():
    calibration = EPISODES
    chosen = select_configurations(calibration, steps=[3], windows=[2, 3], multipliers=[0.0, 1.0])
    # Held-out: a successful episode rising like C. Its own success cannot move the threshold.
    held_out = [episode([0.0, 2.0, 4.0], True, index=7), episode([0.0, 3.0, 6.0], False, index=8)]
    (result,) = evaluate_configurations(held_out, chosen, reference_episodes=calibration)
    assert (result.window, result.multiplier, result.threshold) == (2, 1.0, chosen[0].threshold)
    assert (result.tpr, result.specificity) == (1.0, 0.0)


def test_sweep_at_step_one_flags_nothing():
    (result,) = failure_prediction_sweep(EPISODES, steps=[1], windows=[2], multipliers=[0.1])
    # A single point has slope 0 everywhere: TPR 0, specificity 1, as in Table IV's first row.
    assert (result.tpr, result.specificity, result.balanced_accuracy) == (0.0, 1.0, 0.5)


def test_sweep_picks_the_best_configuration_by_balanced_accuracy():
    (result,) = failure_prediction_sweep(EPISODES, steps=[3], windows=[2, 3], multipliers=[0.0, 1.0])
    # Window 2 (chunks 2, 3) gives slopes A 0, B 1, C 2, D 0.5, as window 3 does; ties keep the first.
    assert (result.window, result.multiplier) == (2, 1.0)
    assert result.balanced_accuracy == pytest.approx(0.75)


def test_sweep_reports_each_step_reached_in_order():
    results = failure_prediction_sweep(EPISODES, steps=[1, 2, 3, 4], windows=[2], multipliers=[1.0])
    assert [r.step for r in results] == [1, 2, 3]


def test_sweep_without_failures_reports_nan_balanced_accuracy():
    (result,) = failure_prediction_sweep(EPISODES[:2], steps=[3], windows=[2], multipliers=[1.0])
    assert math.isnan(result.balanced_accuracy) and result.specificity == 1.0


def test_episodes_with_missing_chunks_are_rejected():
    broken = [r for r in episode([0.0, 1.0, 2.0], True) if r.chunk_index != 1]
    with pytest.raises(ValueError, match="chunks"):
        failure_prediction_sweep([broken], steps=[2], windows=[2], multipliers=[1.0])


def test_sweep_over_the_default_grid_reports_steps_1_to_20():
    rng = np.random.default_rng(0)
    episodes = [
        episode(list(rng.normal(size=20).cumsum()), bool(rng.random() < 0.7), index=i) for i in range(300)
    ]
    results = failure_prediction_sweep(episodes)
    assert [r.step for r in results] == list(range(1, 21))


def test_format_failure_table_prints_percentages():
    result = evaluate_failure_predictor(EPISODES, step=3, window=3, multiplier=1.0)
    table = format_failure_table([result])
    assert "| 3 | 3 | 1.00 | 75.00% | 75.00% | 50.00% | 100.00% | 4 | 2 | 50.0% |" in table


def test_format_failure_table_adds_the_slope_auroc_of_each_step():
    result = evaluate_failure_predictor(EPISODES, step=3, window=3, multiplier=1.0)
    table = format_failure_table([result], aurocs=["0.750 [0.250, 1.000]"])
    assert "| Episodes judged | Failed | Failure rate | AUROC [95% CI] |" in table
    assert table.splitlines()[2].endswith("| 4 | 2 | 50.0% | 0.750 [0.250, 1.000] |")


# Equal elapsed time (the default) and lead time.


def test_by_default_only_episodes_still_running_at_the_step_are_judged():
    # A failed episode that ended at step 2 is not judged at step 3, and its flat carried energy cannot count.
    episodes = [*EPISODES, episode([0.0, 9.0], False, index=4)]
    result = evaluate_failure_predictor(episodes, step=3, window=3, multiplier=1.0)
    assert (result.n_episodes, result.n_failed) == (4, 2)


def test_slope_scores_split_the_judged_episodes_into_successful_and_failed():
    successful, failed = slope_scores([*EPISODES, episode([0.0, 9.0], False, index=4)], step=3, window=3)
    np.testing.assert_allclose(successful, [0.0, 1.0])
    np.testing.assert_allclose(failed, [2.0, 0.5])


def config(step, window=2, multiplier=1.0):
    return FailurePredictionResult(0, 0, 0, 0, step=step, window=window, multiplier=multiplier)


def test_first_alarm_is_the_first_step_its_chosen_configuration_flags():
    # Steps 2 and 3, window 2: slopes A 0, B 1, C 2, D 0.5; T = 0.5 + 0.5 = 1 flags C from step 2 on.
    alarms = first_alarms(EPISODES, [config(3), config(2)], reference_episodes=EPISODES)
    assert [a.step for a in alarms] == [None, None, 2, None]
    assert (alarms[2].lead_chunks, alarms[2].lead_env_steps, alarms[2].failed) == (1, 8, True)


def test_an_episode_is_never_alarmed_after_its_last_chunk():
    # Carried forward, the ended episode's slope over [0, 5, 5] is 2.5 at step 3: above T, but it has ended.
    ended = episode([0.0, 5.0], False, index=4)
    (alarm,) = first_alarms([ended], [config(3, window=3)], reference_episodes=EPISODES, carry_forward=True)
    assert alarm.step is None


def test_no_reference_at_a_step_raises_no_alarm():
    (alarm,) = first_alarms([episode([0.0, 5.0, 10.0], False)], [config(3)], reference_episodes=[])
    assert alarm.step is None


def with_goal_distances(records, distances):
    return [dataclasses.replace(r, goal_distance=d) for r, d in zip(records, distances, strict=True)]


def test_the_onset_is_the_last_chunk_that_brought_the_object_closer_by_more_than_a_centimetre():
    records = episode([0.0] * 6, False)
    # Closer at steps 2 and 3; step 4's 5 mm and step 6's jitter back are not progress.
    assert failure_onset(with_goal_distances(records, [0.30, 0.20, 0.10, 0.095, 0.12, 0.10])) == 3
    # Creeping 6 mm a chunk is progress each time it adds up to more than 1 cm: at steps 3 and 5.
    assert failure_onset(with_goal_distances(records, [0.30, 0.294, 0.288, 0.282, 0.276, 0.276])) == 5
    assert failure_onset(with_goal_distances(records, [0.3] * 6)) == 1  # never came closer
    assert failure_onset(records) is None  # records without goal distances


def test_a_caught_failure_has_its_lead_to_the_onset_and_the_tables_show_it():
    # Episode C is flagged at step 2 (see above); its object last came closer at step 3.
    failing = with_goal_distances(EPISODES[2], [0.3, 0.2, 0.1])
    episodes = [*EPISODES[:2], failing, EPISODES[3]]
    alarms = first_alarms(episodes, [config(3), config(2)], reference_episodes=EPISODES)
    assert (alarms[2].onset, alarms[2].lead_to_onset_chunks) == (3, 1)
    assert alarms[0].onset is None  # a success has no onset
    summary = LeadTimeSummary.of(alarms)
    assert (
        summary.failed_with_onset,
        summary.failed_alarmed_before_onset,
        summary.median_lead_to_onset_chunks,
    ) == (1, 1, 1.0)
    assert "Median lead to onset (chunks)" in format_lead_time_table({"all": summary})
    assert "| 3 | 1 |" in format_alarms(alarms)
    # Without goal distances the tables keep their columns.
    plain = LeadTimeSummary.of(first_alarms(EPISODES, [config(3), config(2)], reference_episodes=EPISODES))
    assert "onset" not in format_lead_time_table({"all": plain})


def alarm(failed, step=None, n_chunks=5):
    lead = None if step is None else n_chunks - step
    return Alarm("t", 0, None, failed, n_chunks, step, lead, None if step is None else 8 * lead)


def test_lead_time_summary_counts_failures_alarmed_before_their_last_chunk_and_false_alarms():
    alarms = [alarm(True, 2), alarm(True, 5), alarm(True, 4), alarm(True), alarm(False, 3), alarm(False)]
    summary = LeadTimeSummary.of(alarms)
    assert (summary.n_failed, summary.failed_alarmed, summary.failed_alarmed_before_last_chunk) == (4, 3, 2)
    assert (summary.median_lead_chunks, summary.median_lead_env_steps) == (1.0, 8.0)
    assert (summary.n_successful, summary.successful_alarmed) == (2, 1)


def test_lead_time_without_an_alarmed_failure_has_no_median():
    assert math.isnan(LeadTimeSummary.of([alarm(True), alarm(False)]).median_lead_chunks)


def test_format_lead_time_table_prints_fractions_with_their_counts():
    table = format_lead_time_table(
        {"all tasks": LeadTimeSummary.of([alarm(True, 2), alarm(True), alarm(False)])}
    )
    assert table.splitlines()[2] == "| all tasks | 2 | 1 | 1/2 (50.0%) | 1/2 (50.0%) | 3 | 24 | 0/1 (0.0%) |"


def test_format_alarms_lists_each_failed_episode():
    table = format_alarms([alarm(True, 2), alarm(True), alarm(False, 1)])
    assert table.splitlines()[2:] == [
        "| t | 0 | None | 5 | 2 | 3 | 24 |",
        "| t | 0 | None | 5 | never |  |  |",
    ]


def rates(step, balanced, n_episodes, n_failed):
    """A calibration result at `step` with the given balanced accuracy (TPR = it, specificity = it)."""
    tp = round(balanced * n_failed)
    tn = round(balanced * (n_episodes - n_failed))
    return FailurePredictionResult(
        tp,
        n_episodes - n_failed - tn,
        tn,
        n_failed - tp,
        step=step,
        window=2,
        multiplier=1.0,
        n_episodes=n_episodes,
        n_failed=n_failed,
    )


def test_the_check_step_is_the_best_calibration_step_while_most_successes_still_run():
    # 10 successful calibration episodes: at step 9 only 3 still run, so its perfect accuracy does not count.
    chosen = [rates(3, 0.6, 15, 5), rates(5, 0.8, 15, 5), rates(7, 0.8, 10, 5), rates(9, 1.0, 8, 5)]
    assert select_check_step(chosen, n_successful=10).step == 5  # ties keep the earlier step
    assert select_check_step(chosen, n_successful=10, min_running=0.3).step == 9


def test_no_check_step_without_a_defined_accuracy_or_with_a_bad_fraction():
    assert select_check_step([rates(2, 0.5, 10, 0)], n_successful=10) is None  # no failure: NaN
    assert select_check_step([], n_successful=10) is None
    with pytest.raises(ValueError, match="min_running"):
        select_check_step([rates(2, 0.5, 10, 4)], n_successful=6, min_running=0.0)
