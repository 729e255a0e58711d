"""The failure check's decision chunk N, chosen on calibration rollouts alone (`failure_check_choice.py`)."""

import json
from dataclasses import replace

import numpy as np
import pytest

from lerobot_policy_ebvla.monitoring.records import (
    ENERGY_RECORDS_FILENAME,
    EnergyRecord,
    write_energy_records,
)
from research.tests.conftest import RESULTS, load_benchmark

choice = load_benchmark("failure_check_choice")


def rollout(seed: int, energies, success: bool) -> list[EnergyRecord]:
    return [EnergyRecord(seed, c, 8 * c, 9.0, float(e), success, "t", seed) for c, e in enumerate(energies)]


def test_the_chosen_n_is_the_first_at_which_failures_rise_above_the_successful_rollouts(tmp_path):
    rng = np.random.default_rng(0)
    # Every rollout alike for 6 chunks; a failed one's energy then rises by 3 (its grasp missed).
    episodes = [rollout(i, rng.normal(0.0, 0.1, 16), success=True) for i in range(12)]
    episodes += [
        rollout(100 + i, np.r_[rng.normal(0.0, 0.1, 6), rng.normal(3.0, 0.1, 10)], success=False)
        for i in range(4)
    ]
    picked = choice.choose(episodes)
    rows = {row["chunks"]: row for row in picked["candidates"]}
    assert rows[3]["balanced_accuracy"] < 0.7 and rows[10]["balanced_accuracy"] == pytest.approx(
        1.0, abs=0.05
    )
    best = max(row["balanced_accuracy"] for row in picked["candidates"])
    assert picked["chunks"] == min(n for n, row in rows.items() if row["balanced_accuracy"] == best)
    assert picked["chunks"] > 6  # after the rollouts part
    assert picked["report_options"][1] == f"--failure_chunks={picked['chunks']}"
    # The threshold is the successful rollouts' mean + 1 std over the first N chunks: the failed ones set nothing.
    successful = choice.first_chunk_means(episodes[:12], picked["chunks"])
    assert rows[picked["chunks"]]["threshold"] == pytest.approx(successful.mean() + successful.std())

    with pytest.raises(ValueError, match="needs failed and at least 2 successful"):
        choice.choose(episodes[:12])

    folder = tmp_path / "calibration"
    write_energy_records(folder / ENERGY_RECORDS_FILENAME, [r for e in episodes for r in e])
    choice.main([f"--calibration={folder}", f"--output={tmp_path / 'choice.json'}"])
    assert json.loads((tmp_path / "choice.json").read_text())["chunks"] == picked["chunks"]


def joint_rollout(seed: int, context_energies, success: bool) -> list[EnergyRecord]:
    rng = np.random.default_rng(seed)
    return [
        EnergyRecord(
            seed, c, 8 * c, 9.0, float(rng.normal(0.0, 0.1)), success, "t", seed, context_energy=float(e)
        )
        for c, e in enumerate(context_energies)
    ]


def test_with_scores_and_development_rollouts_the_energy_that_sees_the_failures_is_chosen():
    rng = np.random.default_rng(1)

    # The final energy knows nothing of the failures; E_c rises from chunk 8 in the failed rollouts only.
    def episodes(first, n_ok, n_failed):
        ok = [joint_rollout(first + i, rng.normal(0.0, 0.1, 16), True) for i in range(n_ok)]
        failed = [
            joint_rollout(first + 100 + i, np.r_[rng.normal(0.0, 0.1, 8), rng.normal(2.0, 0.1, 8)], False)
            for i in range(n_failed)
        ]
        return ok + failed

    calibration, development = episodes(0, 12, 3), episodes(1000, 20, 5)
    scores = ("final_energy", "context_phase_energy")
    picked = choice.choose(calibration, scores=scores, development=development)
    assert picked["score"] == "context_phase_energy" and picked["chunks"] >= 10
    assert picked["report_options"][0] == "--failure_score=context_phase_energy"
    assert (picked["development_rollouts"], picked["development_failed"]) == (25, 5)
    rows = {(row["score"], row["chunks"]): row for row in picked["candidates"]}
    assert len(rows) == 2 * len(choice.CANDIDATES)
    assert rows["context_phase_energy", picked["chunks"]]["balanced_accuracy"] > 0.9
    assert max(row["balanced_accuracy"] for (s, _), row in rows.items() if s == "final_energy") < 0.8
    # T comes from the successful calibration rollouts alone: the development ones judge, they set nothing.
    alone = choice.choose(calibration, scores=scores)
    assert all(
        a["threshold"] == pytest.approx(b["threshold"])
        for a, b in zip(alone["candidates"], picked["candidates"], strict=True)
    )
    with pytest.raises(ValueError, match="The failure check reads one of"):
        choice.choose(calibration, scores=("context_knn",))


@pytest.mark.skipif(
    not (RESULTS / "libero_object10" / "eval").is_dir(), reason="the ten-task records are not committed here"
)
def test_on_cs_ten_task_calibration_rollouts_the_choice_is_chunk_12():
    """The development figure libero_runs.md states ("D's failure check"), from C's committed calibration records."""
    calibration = RESULTS / "libero_object10/eval/ebvla_joint_fast_cpu/vanilla_calib"
    picked = choice.choose(list(choice.load_episodes([str(calibration / "task*")]).values()))
    assert picked["chunks"] == 12 and picked["calibration_failed"] == 13
    assert max(row["balanced_accuracy"] for row in picked["candidates"]) == pytest.approx(0.948, abs=5e-4)


def test_ds_committed_choice_is_recomputed_from_its_calibration_rollouts_alone():
    """D's failure check (libero_runs.md, "D's failure check"), chosen before its report: N = 10."""
    folder = RESULTS / "libero_object10_more/eval/ebvla_joint_fast_cpu_more/vanilla_calib"
    picked = choice.choose(list(choice.load_episodes([str(folder / "task*")]).values()))
    committed = RESULTS / "libero_object10_more/reports/ebvla_joint_fast_cpu_more/failure_check_choice.json"
    assert json.loads(json.dumps(picked)) == json.loads(committed.read_text())
    assert picked["chunks"] == 10 and picked["calibration_failed"] == 13
    assert picked["calibration_rollouts"] == 100


def replayed_alarms(results: str, run: str, output, *extra: str) -> dict:
    """`runtime_alarm_rates.py` on a committed run: its shipped monitor replayed on its committed records."""
    root = RESULTS / results
    load_benchmark("runtime_alarm_rates").main(
        [
            f"--checkpoint={root / 'train' / run / 'last' / 'pretrained_model'}",
            f"--records={root / 'eval' / run}",
            f"--output={output}",
            *extra,
        ]
    )
    return json.loads(output.read_text())


@pytest.mark.skipif(
    not (RESULTS / "libero_object10" / "eval").is_dir(), reason="the ten-task records are not committed here"
)
def test_the_committed_run_time_alarm_rates_are_what_the_shipped_monitor_gives_on_the_records(tmp_path):
    """`runtime_alarms.json` (BENCHMARKS.md, "Ten tasks": what a user of C's monitor gets) recomputed."""
    committed = RESULTS / "libero_object10/reports/ebvla_joint_fast_cpu/runtime_alarms.json"
    got = replayed_alarms("libero_object10", "ebvla_joint_fast_cpu", tmp_path / "alarms.json")
    assert got == json.loads(committed.read_text())
    heldout = got["conditions"]["vanilla_heldout"]
    # 200 held-out vanilla rollouts: 4 flagged at chunk 3, 45 at one of chunks 1-3, 67 at some chunk.
    assert [heldout[key]["alarmed"] for key in ("at_chunk_3", "by_chunk_3", "ever")] == [4, 45, 67]

    # With T refitted on the calibration rollouts' first 3 chunks, as the reports fit theirs.
    refitted = replayed_alarms(
        "libero_object10", "ebvla_joint_fast_cpu", tmp_path / "first3.json", "--refit_first_chunks=3"
    )
    assert refitted == json.loads(committed.with_name("runtime_alarms_first3.json").read_text())
    heldout = refitted["conditions"]["vanilla_heldout"]
    assert [heldout[key]["alarmed"] for key in ("at_chunk_3", "by_chunk_3", "ever")] == [0, 7, 13]


def test_ds_committed_run_time_alarm_rates_are_what_its_shipped_monitor_gives_on_the_records(tmp_path):
    """D's `runtime_alarms.json` (BENCHMARKS.md: its shipped monitor, the conformal T on the window score of the
    first 3 chunks and the joint failure check, replayed chunk by chunk) recomputed, and
    `runtime_alarms_mean3.json`, the same monitor with its T refitted on the 3-chunk mean (no window)."""
    committed = RESULTS / "libero_object10_more/reports/ebvla_joint_fast_cpu_more/runtime_alarms.json"
    got = replayed_alarms("libero_object10_more", "ebvla_joint_fast_cpu_more", tmp_path / "alarms.json")
    assert got == json.loads(committed.read_text())
    # Since 2026-12-07 D's OOD check is LIBERO's score, `context_start_energy` (libero_runs.md, "The starting
    # sample's energy beside E_c"; `context_phase_energy` before: 11, 13 and 0 alarmed below, 91.1 % and 90.6 %);
    # since 2026-11-30 the failure check is `joint_phase_energy` (libero_runs.md, "A failure check on both terms
    # of the joint energy").
    assert got["ood_score"] == "context_start_energy"
    assert got["failure_check"] == {"score": "joint_phase_energy", "chunks": 16}
    keys = ("at_chunk_3", "by_chunk_3", "ever")
    conditions = got["conditions"]
    # The decision after chunk 3 stands: a rollout alarmed at all is alarmed by chunk 3.
    assert [conditions["vanilla_heldout"][key]["alarmed"] for key in keys] == [11, 11, 11]
    assert [conditions["vanilla_confirm"][key]["alarmed"] for key in keys] == [10, 10, 10]
    assert [conditions["vanilla_fresh"][key]["alarmed"] for key in keys] == [0, 0, 0]
    # Where success barely falls, the start term catches more than E_c did (light_dim 5: 2 of 20 before).
    weak = ("light_dim5", "noise3", "blur3")
    assert [conditions[name]["by_chunk_3"]["alarmed"] for name in weak] == [7, 3, 11]
    accuracy = got["balanced_accuracy_by_chunk_3"]
    assert accuracy["vanilla_confirm"] == pytest.approx(0.9132, abs=5e-5)
    assert accuracy["vanilla_heldout"] == pytest.approx(0.9107, abs=5e-5)

    before = replayed_alarms(
        "libero_object10_more", "ebvla_joint_fast_cpu_more", tmp_path / "mean3.json", "--refit_first_chunks=3"
    )
    assert before == json.loads(committed.with_name("runtime_alarms_mean3.json").read_text())
    conditions = before["conditions"]
    assert before["ood_threshold"] == pytest.approx(0.8076, abs=5e-5)
    # Without the window, T bounds the decision at chunk 3 alone: chunks 1-2 alarm far more.
    assert [conditions["vanilla_heldout"][key]["alarmed"] for key in keys] == [12, 46, 57]
    assert [conditions["vanilla_confirm"][key]["alarmed"] for key in keys] == [11, 42, 50]
    assert [conditions["vanilla_fresh"][key]["alarmed"] for key in keys] == [0, 0, 2]


def test_ds_second_failure_check_is_recomputed_from_the_rollouts_it_was_chosen_on():
    """`failure_check_choice_development.json` (libero_runs.md, "D's second failure check"): chosen on the calibration,
    held-out and fresh rollouts, before the confirmation rollouts existed."""
    folder = RESULTS / "libero_object10_more/eval/ebvla_joint_fast_cpu_more"
    episodes = lambda name: list(choice.load_episodes([str(folder / name / "task*")]).values())  # noqa: E731
    picked = choice.choose(
        episodes("vanilla_calib"),
        scores=("final_energy", "context_phase_energy", "head_energy_two_sided"),
        development=episodes("vanilla_heldout") + episodes("vanilla_fresh"),
    )
    committed = (
        RESULTS
        / "libero_object10_more/reports/ebvla_joint_fast_cpu_more/failure_check_choice_development.json"
    )
    assert json.loads(json.dumps(picked)) == json.loads(committed.read_text())
    assert (picked["score"], picked["chunks"]) == ("context_phase_energy", 16)
    assert (picked["development_rollouts"], picked["development_failed"]) == (300, 19)


def test_ds_joint_choice_is_recomputed_from_the_rollouts_it_was_chosen_on():
    """`failure_check_choice_joint.json` (libero_runs.md, "A failure check on both terms of the joint energy"): the
    four energy scores, chosen on D's calibration and every vanilla rollout of D seen before."""
    folder = RESULTS / "libero_object10_more/eval/ebvla_joint_fast_cpu_more"
    episodes = lambda name: list(choice.load_episodes([str(folder / name / "task*")]).values())  # noqa: E731
    development = [
        episode
        for name in ("vanilla_heldout", "vanilla_fresh", "vanilla_confirm", "vanilla_fresh_arm_set")
        for episode in episodes(name)
    ]
    picked = choice.choose(
        episodes("vanilla_calib"),
        scores=("final_energy", "context_phase_energy", "head_energy_two_sided", "joint_phase_energy"),
        development=development,
    )
    committed = (
        RESULTS / "libero_object10_more/reports/ebvla_joint_fast_cpu_more/failure_check_choice_joint.json"
    )
    assert json.loads(json.dumps(picked)) == json.loads(committed.read_text())
    assert (picked["score"], picked["chunks"]) == ("joint_phase_energy", 16)
    rows = {(row["score"], row["chunks"]): row["balanced_accuracy"] for row in picked["candidates"]}
    assert rows["joint_phase_energy", 16] == pytest.approx(0.945, abs=5e-4)
    assert rows["context_phase_energy", 16] == pytest.approx(0.908, abs=5e-4)


tester = load_benchmark("failure_check_test")


def test_the_test_judges_a_fixed_choice_at_the_tested_checkpoints_own_calibration_t(tmp_path):
    rng = np.random.default_rng(2)

    # E_c rises from chunk 8 in failed rollouts, on this checkpoint's own scale (shifted by 5 from the one the
    # choice was made on): T must come from these calibration rollouts, not from the choice's JSON.
    def episodes(first, n_ok, n_failed):
        ok = [joint_rollout(first + i, 5.0 + rng.normal(0.0, 0.1, 16), True) for i in range(n_ok)]
        failed = [
            joint_rollout(
                first + 100 + i, 5.0 + np.r_[rng.normal(0.0, 0.1, 8), rng.normal(2.0, 0.1, 8)], False
            )
            for i in range(n_failed)
        ]
        # The pooled context follows E_c here, so the feature baseline sees the failures too.
        return {
            (first, i): [replace(r, context_feature=[r.context_energy, 0.0]) for r in e]
            for i, e in enumerate(ok + failed)
        }

    fixed = {"score": "context_phase_energy", "chunks": 12, "k": 1.0}
    calibration = episodes(0, 12, 3)
    result = tester.test_choice(fixed, calibration, {"held": episodes(1000, 20, 5)}, ["final_energy"])
    rows = {row["score"]: row for row in result["sets"]["all held out"]["rows"]}
    assert list(rows) == ["context_phase_energy", "final_energy", "chunk_context_nn"]
    chosen = rows["context_phase_energy"]
    assert (chosen["failed_alarmed"], chosen["failed"], chosen["successful"]) == (5, 5, 20)
    assert chosen["auroc"] == 1.0
    assert chosen["balanced_accuracy"] == pytest.approx(0.5 * (1 + 1 - chosen["successful_alarmed"] / 20))
    # T is mu + 1 sigma of this checkpoint's successful calibration rollouts, each against the others.
    values = choice.calibration_scores(list(calibration.values()), "context_phase_energy", (12,))[12][:12]
    assert chosen["threshold"] == pytest.approx(values.mean() + values.std())
    assert rows["final_energy"]["auroc"] < 0.8
    # No goal distances in these records: no onset, but the lead to the end (16 - 12 chunks).
    assert result["sets"]["held"]["leads"] == {
        "caught": 5,
        "at_or_before_onset": 0,
        "median_lead_to_onset": None,
        "median_lead_to_end": 4.0,
    }
    targets = {name: met for name, met, _ in tester.targets(result)}
    assert targets["balanced accuracy >= 80%"] and targets["at least final_energy's balanced accuracy"]
    with pytest.raises(ValueError, match="needs failed and at least 2 successful calibration rollouts"):
        tester.test_choice(fixed, episodes(0, 12, 0), {}, [])


def test_run_on_ds_own_confirmation_the_test_gives_ds_committed_table_iv_figures():
    """The script against figures committed before it: D's second check on its confirmation rollouts (libero_runs.md,
    "The confirmation's results": 26/30 and 16/170, 88.6 %; `chunk_context_nn` at chunk 16 96.8 %)."""
    folder = RESULTS / "libero_object10_more/eval/ebvla_joint_fast_cpu_more"
    load = lambda name: choice.load_episodes([str(folder / name / "task*")])  # noqa: E731
    fixed = {"score": "context_phase_energy", "chunks": 16, "k": 1.0}
    result = tester.test_choice(fixed, load("vanilla_calib"), {"confirm": load("vanilla_confirm")}, [])
    rows = {row["score"]: row for row in result["sets"]["confirm"]["rows"]}
    check, baseline = rows["context_phase_energy"], rows["chunk_context_nn"]
    assert [check[k] for k in ("failed_alarmed", "failed", "successful_alarmed", "successful")] == [
        26,
        30,
        16,
        170,
    ]
    assert check["balanced_accuracy"] == pytest.approx(0.886, abs=5e-4)
    assert baseline["balanced_accuracy"] == pytest.approx(0.968, abs=5e-4)


def test_es_committed_test_of_the_joint_check_and_its_window_alarms_are_recomputed(tmp_path):
    """E's pre-registered test (libero_runs.md, "The test's result"), from E's committed records: the joint check
    confirmed (92.6 % against E_c's 91.3 %), `chunk_context_nn` above its interval."""
    root = RESULTS / "libero_object10_arm"
    folder = root / "eval/ebvla_joint_fast_cpu_arm"
    tester.main(
        [
            f"--choice={RESULTS / 'libero_object10_more/reports/ebvla_joint_fast_cpu_more/failure_check_choice_joint.json'}",
            f"--calibration={folder / 'vanilla_calib' / 'task*'}",
            "--held_out",
            *(
                str(folder / name / "task*")
                for name in ("vanilla_heldout", "vanilla_confirm", "vanilla_fresh")
            ),
            "--beside",
            "context_phase_energy",
            "final_energy",
            f"--output={tmp_path / 'test.json'}",
        ]
    )
    got = json.loads((tmp_path / "test.json").read_text())
    committed = root / "reports/ebvla_joint_fast_cpu_arm/failure_check_test.json"
    assert got == json.loads(committed.read_text())
    assert [t["met"] for t in got["targets"]] == [True, True, True, False]
    rows = {r["score"]: r for r in got["sets"]["all held out"]["rows"]}
    assert rows["joint_phase_energy"]["balanced_accuracy"] == pytest.approx(0.926, abs=5e-4)
    assert rows["context_phase_energy"]["balanced_accuracy"] == pytest.approx(0.913, abs=5e-4)
    assert rows["chunk_context_nn"]["auroc"] == pytest.approx(0.980, abs=5e-4)
    # The run-time window on E's new rollouts: E's monitor (calibrated on its calibration rollouts) replayed.
    alarms = replayed_alarms("libero_object10_arm", "ebvla_joint_fast_cpu_arm", tmp_path / "alarms.json")
    assert alarms == json.loads((root / "reports/ebvla_joint_fast_cpu_arm/runtime_alarms.json").read_text())
    by_chunk_3 = {name: c["by_chunk_3"]["alarmed"] for name, c in alarms["conditions"].items()}
    assert (by_chunk_3["vanilla_heldout"], by_chunk_3["vanilla_confirm"], by_chunk_3["vanilla_fresh"]) == (
        13,
        19,
        0,
    )
