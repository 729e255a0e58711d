"""The ten-task check's report (`research/benchmarks/libero_ten_task_report.py`), on records made here: a shift
that raises E_c and cuts success, one that lowers E_c and costs nothing."""

import json

import numpy as np
import pytest

from lerobot_policy_ebvla.monitoring.records import EnergyRecord, write_energy_records
from research.tests.conftest import RESULTS, load_benchmark

report = load_benchmark("libero_ten_task_report")

RUN = "ebvla_joint_fast_cpu"
# Condition folder: (seeds, E_c offset, context feature offset, success of each episode).
SETS = {
    "vanilla_calib": (range(0, 6), 0.0, 0.0, [True] * 6),
    "vanilla_heldout": (range(10, 16), 0.0, 0.0, [True] * 5 + [False]),
    "vanilla_fresh": (range(200000, 200003), 0.0, 0.0, [True, True, False]),
    "pose5": (range(10, 13), 6.0, 4.0, [False, False, True]),
    "light_dim5": (range(10, 13), -6.0, 4.0, [True] * 3),
}


def write_results(root, sets=SETS):
    rng = np.random.default_rng(0)
    for folder, (seeds, offset, feature_offset, outcomes) in sets.items():
        perturbation, severity = (
            ("none", 0) if folder.startswith("vanilla") else (folder.rstrip("0123456789"), int(folder[-1]))
        )
        for task in range(10):
            records = [
                EnergyRecord(
                    episode_index=episode,
                    chunk_index=chunk,
                    env_step=8 * chunk,
                    initial_energy=10.0,
                    # A failed rollout's final energy rises once its grasp has missed (from chunk 1).
                    final_energy=float(rng.normal() + (4.0 if chunk and not outcomes[episode] else 0.0)),
                    success=outcomes[episode],
                    task=f"task {task}",
                    seed=seed,
                    perturbation=perturbation,
                    severity=severity,
                    context_energy=float(rng.normal() + offset),
                    context_feature=(rng.normal(size=4) + feature_offset).astype(np.float32),
                    # The object comes 5 cm closer each chunk, a failed one only until chunk 1.
                    goal_distance=0.3 - 0.05 * (chunk if outcomes[episode] else min(chunk, 1)),
                )
                for episode, seed in enumerate(seeds)
                for chunk in range(3)
            ]
            write_energy_records(
                root / "eval" / RUN / folder / f"task{task}" / "energy_records.jsonl", records
            )
    config = root / "train" / RUN / "last" / "pretrained_model" / "config.json"
    config.parent.mkdir(parents=True)
    config.write_text(json.dumps({"monitor": {"score": "context_phase_energy"}}))
    return root


@pytest.fixture(scope="module")
def groups(tmp_path_factory):
    root = write_results(tmp_path_factory.mktemp("results"))
    output = root / "report"
    report.main([f"--results={root}", f"--run={RUN}", f"--output_dir={output}"])
    saved = json.loads((output / "ten_task_report.json").read_text())
    assert "## seven untouched: tasks 0, 1, 4, 5, 6, 7, 8" in (output / "ten_task_report.md").read_text()
    return {group["group"]: group for group in saved}


def test_each_group_counts_its_own_tasks_rollouts(groups):
    assert list(groups) == ["all ten", "seven untouched", "three of the choice"]
    for name, n_tasks in (("all ten", 10), ("seven untouched", 7), ("three of the choice", 3)):
        success = groups[name]["success"]
        assert success["fixed initial states"] == {"wins": 5 * n_tasks, "n": 6 * n_tasks}
        assert success["fresh placements"] == {"wins": 2 * n_tasks, "n": 3 * n_tasks}
        assert groups[name]["success_per_condition"]["pose 5"] == {"wins": n_tasks, "n": 3 * n_tasks}


def test_the_one_sided_monitor_is_confidently_wrong_where_e_c_falls_and_the_targets_say_so(groups):
    rows = {row["score"]: row for row in groups["all ten"]["rows"]}
    assert [row["score"] for row in groups["all ten"]["rows"]][0] == "context_phase_energy"
    monitor, two_sided = rows["context_phase_energy"], rows["context_energy_two_sided"]
    assert monitor["auroc_per_condition"] == {"light_dim 5": 0.0, "pose 5": 1.0}
    assert two_sided["auroc_per_condition"] == {"light_dim 5": 1.0, "pose 5": 1.0}
    assert rows["context_knn"]["auroc_per_condition"]["light_dim 5"] == 1.0
    targets = {target: (measured, met) for target, measured, met in groups["all ten"]["targets"]}
    assert targets["AUROC >= 0.5 under every condition"] == ("lowest 0.000 (light_dim 5)", False)
    # Pose 5 cuts success from 83 % to 33 %: it must reach 0.85, and does.
    assert targets["AUROC >= 0.85 where success falls 20+ points"] == ("lowest 1.000 (pose 5) of 1", True)
    measured, met = targets["not below context_knn outside its interval"]
    assert not met and measured.endswith("against 1.000")
    assert targets["success on the fixed initial states >= 90%"][1] is False
    assert targets["success on fresh placements >= 80%"][1] is False
    assert "success on the fixed initial states >= 90%" not in {
        t for t, _, _ in groups["seven untouched"]["targets"]
    }


def test_alarms_are_counted_at_the_calibration_threshold_on_both_vanilla_sets(groups):
    for row in groups["all ten"]["rows"]:
        assert 0.0 <= row["heldout_alarm_rate"] <= 1.0 and row["fresh_alarm_rate"] is not None
    monitor = groups["all ten"]["rows"][0]
    # Half the shifted rollouts (pose) are far above T, the other half far below it.
    assert monitor["balanced_accuracy"] == pytest.approx(0.5 * (0.5 + 1.0 - monitor["heldout_alarm_rate"]))
    # ... which the per-shift alarm rates say shift by shift.
    assert monitor["alarm_rate_per_condition"] == {"light_dim 5": 0.0, "pose 5": 1.0}
    assert 0.0 <= monitor["whole_episode_auroc"] <= 1.0


def test_table_iv_counts_the_failures_of_held_out_and_fresh_vanilla_at_the_chosen_check(tmp_path):
    root = write_results(tmp_path / "results")
    choice = tmp_path / "failure_check_choice.json"
    options = ["--failure_score=final_energy", "--failure_chunks=3", "--failure_reference=successful"]
    choice.write_text(json.dumps({"chunks": 3, "report_options": options}))
    report.main(
        [
            f"--results={root}",
            f"--run={RUN}",
            f"--output_dir={tmp_path / 'out'}",
            f"--failure_choice={choice}",
        ]
    )
    groups = {g["group"]: g for g in json.loads((tmp_path / "out" / "ten_task_report.json").read_text())}
    for name, n_tasks in (("all ten", 10), ("seven untouched", 7), ("three of the choice", 3)):
        rows = {row["score"]: row for row in groups[name]["failure_rows"]}
        assert list(rows)[:2] == ["monitor (either check)", "final_energy"] and "chunk_context_nn" in rows
        check = rows["final_energy"]
        # One failed rollout per task in the held-out states and one in the fresh placements; the shifted
        # rollouts are not vanilla and count nowhere here.
        assert (check["failed"], check["successful"]) == (2 * n_tasks, 7 * n_tasks)
        # Mean over chunks 0-2 of a failure: 8/3 above the successes', far above mu + 1 sigma.
        assert check["failed_alarmed"] == 2 * n_tasks and check["auroc"] == 1.0
        assert check["balanced_accuracy"] > 0.8 and rows["monitor (either check)"]["auroc"] is None
        # Caught at chunk 3, one chunk after their onset (step 2: their last progress), their last chunk.
        assert check["caught_before_onset"] == 0
        assert (check["median_lead_to_onset"], check["median_lead_to_end"]) == (-1.0, 0.0)
        targets = {t: (m, ok) for t, m, ok in groups[name]["targets"]}
        assert targets["Table IV: balanced accuracy >= 80% held out"][1] is True
        assert targets["Table IV: not below chunk_context_nn outside its interval"][1] is True
    assert "| `final_energy` | 20/20 | " in (tmp_path / "out" / "ten_task_report.md").read_text()


def test_confirmation_rollouts_get_their_own_alarms_at_the_conformal_t_and_stay_out_of_table_iv(tmp_path):
    # States 30-35: the last of each task's six fails, its E_c far above vanilla (alarmed at any T).
    confirm = (range(30, 36), 0.0, 0.0, [True] * 5 + [False])
    root = write_results(tmp_path / "results", {**SETS, "vanilla_confirm": confirm})
    for task in range(10):
        path = root / "eval" / RUN / "vanilla_confirm" / f"task{task}" / "energy_records.jsonl"
        lines = [json.loads(line) for line in path.read_text().splitlines()]
        for line in lines:
            line["context_energy"] += 20.0 if line["episode_index"] == 5 else 0.0
        path.write_text("".join(json.dumps(line) + "\n" for line in lines))
    choice = tmp_path / "failure_check_choice.json"
    options = ["--failure_score=final_energy", "--failure_chunks=3", "--failure_reference=successful"]
    choice.write_text(json.dumps({"chunks": 3, "report_options": options}))
    out = tmp_path / "out"
    args = [f"--results={root}", f"--run={RUN}", f"--output_dir={out}", f"--failure_choice={choice}"]
    report.main([*args, "--threshold_rule=conformal"])
    groups = {g["group"]: g for g in json.loads((out / "ten_task_report.json").read_text())}
    monitor = groups["all ten"]["rows"][0]
    assert groups["all ten"]["success"]["confirmation (states 30-49)"] == {"wins": 50, "n": 60}
    assert 1 / 6 <= monitor["confirm_alarm_rate"] < 0.5
    caught = np.mean(list(monitor["alarm_rate_per_condition"].values()))  # two shifts of equal size
    assert monitor["confirm_balanced_accuracy"] == pytest.approx(
        0.5 * (caught + 1.0 - monitor["confirm_alarm_rate"])
    )
    targets = {t: (m, ok) for t, m, ok in groups["all ten"]["targets"]}
    assert targets["confirmation (states 30-49): alarms <= 10%"][1] is False
    # Table IV on the held-out states and fresh placements, its failure check at Eq. 5, and on the confirmation.
    check = {row["score"]: row for row in groups["all ten"]["failure_rows"]}["final_energy"]
    assert (check["failed"], check["successful"]) == (20, 70)
    confirmed = {row["score"]: row for row in groups["all ten"]["confirm_failure_rows"]}["final_energy"]
    assert (confirmed["failed"], confirmed["successful"]) == (10, 50) and confirmed["failed_alarmed"] == 10
    assert targets["Table IV: balanced accuracy >= 80% on the confirmation (states 30-49)"][1] is True
    text = (out / "ten_task_report.md").read_text()
    assert "T = the conformal quantile at alpha = 5 %" in text and "Alarms: confirmation vanilla" in text

    # Eq. 5's T sits lower than the 95 % quantile of 60 calibration rollouts: more held-out alarms.
    report.main([*args, f"--output_dir={tmp_path / 'eq5'}"])
    eq5 = json.loads((tmp_path / "eq5" / "ten_task_report.json").read_text())[0]["rows"][0]
    assert eq5["heldout_alarm_rate"] >= monitor["heldout_alarm_rate"]
    assert eq5["confirm_alarm_rate"] >= monitor["confirm_alarm_rate"]


def test_shift_folders_read_as_the_ood_reports_conditions():
    assert report.condition_name("light_dim5") == "light_dim 5"
    assert report.condition_name("pose1") == "pose 1"


def test_on_the_three_task_records_it_agrees_with_the_choice_and_leaves_out_the_unevaluated_tasks(tmp_path):
    """C's committed three-task records: the report's "all ten" group holds tasks 2, 3 and 9 only, the seven
    untouched are left out, and the monitor's row is the choice rule's (computed by other code)."""
    from research.tests.conftest import RESULTS

    report.main([f"--results={RESULTS / 'libero_recipe'}", f"--run={RUN}", f"--output_dir={tmp_path}"])
    saved = {g["group"]: g for g in json.loads((tmp_path / "ten_task_report.json").read_text())}
    assert list(saved) == ["all ten", "three of the choice"] and saved["all ten"]["tasks"] == [2, 3, 9]
    monitor = saved["all ten"]["rows"][0]
    choice = load_benchmark("libero_recipe_choice")
    expected = choice.run_criteria(
        RESULTS / "libero_recipe", RUN, "context_phase_energy", tmp_path / "choice"
    )
    assert monitor["score"] == "context_phase_energy"
    assert monitor["auroc_per_condition"] == pytest.approx(expected.auroc_per_condition)
    assert monitor["balanced_accuracy"] == pytest.approx(expected.balanced_accuracy)
    assert monitor["heldout_alarm_rate"] == pytest.approx(expected.heldout_alarm_rate)


def test_the_committed_ten_task_report_is_recomputed_from_the_committed_records(tmp_path):
    """BENCHMARKS.md's ten-task figures (`ebvla_joint_fast_cpu`, 740 rollouts of 2026-11-28), from the records."""
    results = RESULTS / "libero_object10"
    report.main([f"--results={results}", f"--run={RUN}", f"--output_dir={tmp_path}"])
    got = json.loads((tmp_path / "ten_task_report.json").read_text())
    committed = results / "reports" / RUN / "ten_task" / "ten_task_report.json"
    assert got == json.loads(committed.read_text())
    ten = got[0]
    assert ten["group"] == "all ten"
    assert ten["success"]["fixed initial states"] == {"wins": 166, "n": 200}
    assert ten["success"]["fresh placements"] == {"wins": 89, "n": 100}
    rows = {row["score"]: row for row in ten["rows"]}
    assert rows["context_phase_energy"]["pooled_auroc"] == pytest.approx(0.952, abs=5e-4)
    assert rows["context_knn"]["pooled_auroc"] == pytest.approx(0.909, abs=5e-4)
    assert rows["context_phase_energy"]["balanced_accuracy"] == pytest.approx(0.899, abs=5e-4)
    assert rows["context_phase_energy"]["heldout_alarm_rate"] == 0.0
    assert rows["context_phase_energy"]["alarm_rate_per_condition"]["light_dim 5"] == 0.0


def ds_report(tmp_path, choice: str, folder: str) -> list[dict]:
    """D's ten-task report (`ebvla_joint_fast_cpu_more`, 2026-11-29) at its shipped conformal T with one failure
    check, recomputed from the committed records and compared with the committed one."""
    results, run = RESULTS / "libero_object10_more", "ebvla_joint_fast_cpu_more"
    reports = results / "reports" / run
    report.main(
        [
            f"--results={results}",
            f"--run={run}",
            f"--output_dir={tmp_path}",
            f"--failure_choice={reports / choice}",
            "--threshold_rule=conformal",
        ]
    )
    got = json.loads((tmp_path / "ten_task_report.json").read_text())
    assert got == json.loads((reports / folder / "ten_task_report.json").read_text())
    return got


def test_ds_committed_ten_task_report_is_recomputed_from_the_committed_records(tmp_path):
    """BENCHMARKS.md's figures of D: success, Table III at the conformal T (held out and on the confirmation
    rollouts, fixed states 30-49) and Table IV of its first failure check."""
    ten = ds_report(tmp_path, "failure_check_choice.json", "ten_task")[0]
    assert ten["success"]["fixed initial states"] == {"wins": 183, "n": 200}
    assert ten["success"]["fresh placements"] == {"wins": 98, "n": 100}
    assert ten["success"]["confirmation (states 30-49)"] == {"wins": 170, "n": 200}
    rows = {row["score"]: row for row in ten["rows"]}
    monitor = rows["context_phase_energy"]
    assert list(rows)[0] == "context_phase_energy" and len(monitor["auroc_per_condition"]) == 17
    assert monitor["pooled_auroc"] == pytest.approx(0.956, abs=5e-4)
    assert rows["context_knn"]["pooled_auroc"] == pytest.approx(0.901, abs=5e-4)
    # The rule's targets on the confirmation rollouts, which nothing was chosen on.
    assert (monitor["confirm_alarm_rate"], monitor["heldout_alarm_rate"]) == (0.075, 0.055)
    assert monitor["confirm_balanced_accuracy"] == pytest.approx(0.908, abs=5e-4)
    failure = {row["score"]: row for row in ten["failure_rows"]}
    check, baseline = failure["final_energy"], failure["chunk_context_nn"]
    assert (check["failed_alarmed"], check["failed"], check["successful_alarmed"]) == (14, 19, 21)
    assert check["balanced_accuracy"] == pytest.approx(0.831, abs=5e-4)
    # The feature distance at chunk 10 beats the energy's failure check, outside its interval, on both sets.
    assert baseline["auroc"] > check["auroc_interval"][1]
    confirmed = {row["score"]: row for row in ten["confirm_failure_rows"]}
    assert (confirmed["final_energy"]["failed_alarmed"], confirmed["final_energy"]["failed"]) == (25, 30)
    assert confirmed["chunk_context_nn"]["auroc"] > confirmed["final_energy"]["auroc_interval"][1]


def test_ds_second_failure_check_is_recomputed_and_beats_the_first_on_the_confirmation(tmp_path):
    """D's second failure check (`context_phase_energy` over 16 chunks), which the checkpoint ships: its rule was to
    ship it if its balanced accuracy on the confirmation rollouts is at least the first's (86.7 %)."""
    ten = ds_report(tmp_path, "failure_check_choice_development.json", "ten_task_second_check")[0]
    confirmed = {row["score"]: row for row in ten["confirm_failure_rows"]}
    check, baseline = confirmed["context_phase_energy"], confirmed["chunk_context_nn"]
    assert (check["failed_alarmed"], check["failed"], check["successful_alarmed"]) == (26, 30, 16)
    assert (
        check["balanced_accuracy"] == pytest.approx(0.886, abs=5e-4) and check["balanced_accuracy"] >= 0.867
    )
    assert baseline["auroc"] > check["auroc_interval"][1]
