"""research/docs/benchmarks_speed.md, "The energy's starting level": the main job's runs with and without the head's
raised starting energy (`energy_bias_init`), recomputed from their committed records under
`research/results/quickstart_budget/`: successes, the training curve's L1, the default monitor on both shifts and the
failure check over the printed rollouts; then the rule fixed before seeds 2000 and 3000 ran. Also the first stage of
"Both E_c levers with the raised starting energy" (`levers_b18_*`: E_c's encoder at 32 px, its penalty on one step in 4).
"""

import json
from pathlib import Path

import pytest

from lerobot_policy_ebvla.monitoring.metrics import auroc
from lerobot_policy_ebvla.monitoring.ood_report import OODReportConfig, score_ood_report
from lerobot_policy_ebvla.monitoring.records import group_by_episode, read_energy_records
from lerobot_policy_ebvla.monitoring.summary import condition_summary, monitor_summary
from research.tests.conftest import RESULTS

BUDGET = RESULTS / "quickstart_budget"
CONDITIONS = ("vanilla", "blank", "pose_s3")


def successes(run: Path) -> tuple[int, ...]:
    return tuple(
        condition_summary(group_by_episode(read_energy_records(run / "eval" / c)))["n_success"]
        for c in CONDITIONS
    )


def curve_l1(run: Path, step: int) -> float:
    """The logged L1 at `step`, or at the last logged step at or before it."""
    logged = json.loads((run / "training_curve.json").read_text())["log_every"]
    return [row["l1_loss"] for row in logged if row["step"] <= step][-1]


def scored_report(
    run: Path,
    output_dir: Path,
    failure_score: str = "head_energy_two_sided",
    calibration: tuple[str, ...] = ("calibration",),
    vanilla: str = "vanilla",
    ood: tuple[str, ...] = CONDITIONS[1:],
):
    """The main job's monitor (`context_phase_energy`) fitted on the run's `calibration` folders and scored on its
    `vanilla` and `ood` ones (`score_ood_report`), its failure check scored by `failure_score`."""
    eval_root = run / "eval"
    return score_ood_report(
        OODReportConfig(
            calibration=[str(eval_root / c) for c in calibration],
            vanilla=[str(eval_root / vanilla)],
            ood=[str(eval_root / c) for c in ood],
            output_dir=output_dir,
            score="context_phase_energy",
            failure_score=failure_score,
            n_bootstrap=20,
        )
    )


def monitor(run: Path, failure_score: str, tmp_path: Path) -> dict:
    """What the main job's monitor says of the run (`monitor_summary`), its failure check scored by `failure_score`."""
    return monitor_summary(scored_report(run, tmp_path / f"{run.name}_{failure_score}", failure_score))


# run: (vanilla, blank, pose_s3 successes), L1 at step 400 and at the end, camera check (%),
# (head_energy_two_sided, joint_phase_energy) failed vs successful over the 30 printed rollouts, n failed.
RUNS = {
    "bias0_steps1000_seed1000": ((7, 5, 5), 0.937, 0.732, 55.8, (0.525, 0.520), 13),
    "bias0_episodes40_steps1000_seed1000": ((7, 6, 4), 0.917, 0.686, 59.5, (0.398, 0.584), 13),
    "bias10_steps1000_seed1000": ((10, 4, 2), 0.639, 0.377, 68.1, (0.737, 0.732), 14),
    "bias18_steps1000_seed1000": ((10, 3, 4), 0.502, 0.310, 62.6, (0.439, 0.873), 13),
    "bias18_steps600_seed1000": ((10, 6, 5), 0.506, 0.388, 61.5, (0.794, 0.683), 9),
    "bias18_steps500_seed1000": ((6, 6, 6), 0.583, 0.533, 49.6, (0.486, 0.486), 12),
    "bias18_steps500_lr1e-3_seed1000": ((7, 6, 7), 0.561, 0.511, 45.2, (0.315, 0.585), 10),
    "bias18_steps600_seed2000": ((7, 5, 3), 0.491, 0.381, 68.7, (0.724, 0.507), 15),
    "bias18_steps600_seed3000": ((9, 3, 2), 0.452, 0.403, 58.3, (0.839, 0.759), 16),
    "bias18_steps1000_seed2000": ((9, 2, 2), 0.454, 0.318, 63.5, (0.457, 0.756), 17),
    "bias18_steps1000_seed3000": ((10, 2, 3), 0.468, 0.254, 71.4, (0.844, 0.809), 15),
    "bias18_steps1000_fp32_seed1000": ((10, 5, 3), 0.476, 0.291, 64.0, (0.843, 0.759), 12),
    "bias0_steps1000_seed2000": ((4, 0, 5), 0.931, 0.709, 83.9, (0.381, 0.693), 21),
    "bias0_steps1000_seed3000": ((6, 4, 3), 0.917, 0.652, 54.8, (0.570, 0.566), 17),
    "levers_b18_steps1000_seed1000": ((10, 4, 1), 0.477, 0.297, 72.8, (0.884, 0.756), 15),
    "levers_b18_steps1000_seed2000": ((10, 0, 2), 0.449, 0.312, 194.3, (0.704, 0.954), 18),
    "levers_b18_steps1000_seed3000": ((9, 3, 2), 0.501, 0.257, 58.8, (0.768, 0.790), 16),
    "fresh_clone_5aa37fd_seed1000": ((10, 4, 1), 0.477, 0.297, 72.8, (0.884, 0.756), 15),
    "preset_5aa37fd_seed4000": ((10, 6, 4), 0.440, 0.299, 66.3, (0.730, 0.700), 10),
    "preset_5aa37fd_seed5000": ((10, 4, 4), 0.495, 0.307, 67.8, (0.630, 0.769), 12),
    "preset_5aa37fd_seed6000": ((10, 8, 5), 0.488, 0.306, 92.7, (0.739, 0.609), 7),
    "avx2_imitated_5aa37fd_seed1000": ((10, 3, 1), 0.459, 0.288, 59.8, (0.701, 0.804), 16),
    "fresh_clone_676afef_avx2_seed1000": ((10, 3, 1), 0.459, 0.288, 59.8, (0.701, 0.804), 16),
    "fresh_clone_b0821f5_intel_seed1000": ((10, 5, 6), 0.462, 0.285, 51.1, (0.646, 0.709), 9),
}


@pytest.mark.parametrize("name", RUNS)
def test_each_runs_reported_figures_come_out_of_its_records(name, tmp_path):
    run = BUDGET / name
    wins, l1_400, l1_end, camera, (head, joint), n_failed = RUNS[name]
    assert successes(run) == wins
    assert (curve_l1(run, 400), curve_l1(run, 10**6)) == (l1_400, l1_end)
    summary = json.loads((run / "summary.json").read_text())
    assert round(100 * summary["camera_check"]["chunk_change"], 1) == camera
    said = {score: monitor(run, score, tmp_path) for score in ("head_energy_two_sided", "joint_phase_energy")}
    for (score, summary), expected in zip(said.items(), (head, joint), strict=True):
        assert summary["failing"]["auroc"] == pytest.approx(expected, abs=5e-4), score
        assert summary["failing"]["n_failed"] == n_failed
    # The default monitor flags every blanked and moved-camera rollout in every run but the one at a peak rate of
    # 1e-3, whose moved camera it reads as more familiar than vanilla (0.14); the failure score does not change it.
    unfamiliar = said["head_energy_two_sided"]["unfamiliar"]
    assert unfamiliar == said["joint_phase_energy"]["unfamiliar"]
    aurocs = [row["auroc_first_chunks"] for c, row in unfamiliar.items() if c != "vanilla"]
    assert aurocs == ([1.0, pytest.approx(0.14, abs=5e-3)] if "lr1e-3" in name else [1.0, 1.0])


def test_the_rules_verdicts_come_out_of_the_records():
    """600 steps: item 1 (vanilla >= 9/10) fails on seed 2000, so the main job keeps 1000. b = 18 at 1000 steps:
    vanilla at least b = 0's on both seeds (9 against 4, 10 against 6), camera check >= 30 %, the default monitor
    1.00 on both shifts (the parametrized test above): the preset keeps b = 18."""
    assert [successes(BUDGET / f"bias18_steps600_seed{s}")[0] >= 9 for s in (2000, 3000)] == [False, True]
    for seed in (2000, 3000):
        raised, plain = (successes(BUDGET / f"bias{b}_steps1000_seed{seed}")[0] for b in (18, 0))
        assert raised >= plain and (raised, plain) == {2000: (9, 4), 3000: (10, 6)}[seed]


def test_forty_more_vanilla_rollouts_of_seed_2000s_checkpoint_all_succeed():
    """The failure check on vanilla alone cannot be read on this checkpoint: none of 40 fresh rollouts failed."""
    extra = group_by_episode(
        read_energy_records(BUDGET / "bias18_steps1000_seed2000" / "eval" / "vanilla_extra")
    )
    assert len(extra) == 40 and all(chunks[0].success for chunks in extra.values())
    assert {chunks[0].seed for chunks in extra.values()} == set(range(5000, 5040))


def test_both_e_c_levers_with_b_18_hold_the_main_jobs_first_stage(tmp_path):
    """ "Both E_c levers with the raised starting energy", stage 1: on seeds 1000-3000 the job takes at most 5.0 minutes
    (its timed stages), vanilla succeeds at least 9/10 and the camera check is at least 30 % (the monitor's 1.00 on
    both shifts: the parametrized test). Beside it: seed 3000's default monitor alarms on 5 of 10 held-out vanilla
    rollouts, where every other run at 1000 steps alarms on at most 1."""
    for seed, seconds in ((1000, 291.1), (2000, 273.6), (3000, 257.5)):
        run = BUDGET / f"levers_b18_steps1000_seed{seed}"
        summary = json.loads((run / "summary.json").read_text())
        assert sum(summary["timings_s"].values()) == pytest.approx(seconds, abs=0.05) and seconds <= 300
        assert successes(run)[0] >= 9 and summary["camera_check"]["chunk_change"] >= 0.30
    alarmed = {
        name: monitor(BUDGET / name, "head_energy_two_sided", tmp_path)["unfamiliar"]["vanilla"]["alarmed"]
        for name in ("levers_b18_steps1000_seed3000", "bias18_steps1000_seed3000", "bias0_steps1000_seed3000")
    }
    assert alarmed == {
        "levers_b18_steps1000_seed3000": [5, 10],
        "bias18_steps1000_seed3000": [1, 10],
        "bias0_steps1000_seed3000": [0, 10],
    }


def extra_vanilla(run: Path, tmp_path: Path) -> tuple[int, list[int], float | None]:
    """The checkpoint's 40 extra vanilla rollouts (`eval/vanilla_extra`) scored by its own calibration: successes,
    rollouts the default monitor alarms by chunk 3, and the failure check's AUROC on them alone (None: none failed)."""
    scored = scored_report(run, tmp_path / run.name, vanilla="vanilla_extra", ood=("blank",))
    # The held-out rollouts are the vanilla ones first, then the shift's.
    failed, scores = scored.held_out_failed()[:40], scored.held_out("head_energy_two_sided", 3)[:40]
    alarmed = monitor_summary(scored)["unfamiliar"]["vanilla"]["alarmed"]
    return 40 - int(failed.sum()), alarmed, (auroc(scores[~failed], scores[failed]) if failed.any() else None)


def test_the_fresh_clone_of_the_new_preset_trains_stage_1s_realization():
    """The README's job from a fresh clone of 5aa37fd on the newer AVX512-BF16 CPU (family 26 model 2): every logged L1
    as stage 1's seed 1000 on the older one (the parametrized test recomputes the printed figures), in 2.8 minutes of
    timed stages; torch held to AVX2 kernels, another realization, 3.6 minutes."""
    fresh, stage_1 = (
        BUDGET / name for name in ("fresh_clone_5aa37fd_seed1000", "levers_b18_steps1000_seed1000")
    )
    logged = [json.loads((run / "training_curve.json").read_text())["log_every"] for run in (fresh, stage_1)]
    assert logged[0] == logged[1]
    minutes = {
        name: sum(json.loads((BUDGET / name / "summary.json").read_text())["timings_s"].values()) / 60
        for name in ("fresh_clone_5aa37fd_seed1000", "avx2_imitated_5aa37fd_seed1000")
    }
    assert minutes == {
        "fresh_clone_5aa37fd_seed1000": pytest.approx(2.83, abs=0.005),
        "avx2_imitated_5aa37fd_seed1000": pytest.approx(3.61, abs=0.005),
    }


def test_an_avx2_only_cpu_trains_the_realization_its_imitation_trained():
    """The README's job from a fresh clone of 676afef on a 2-core AMD EPYC without AVX512 (family 25 model 1): every
    logged L1 and every episode's mean energies equal those of the run with torch held to AVX2 kernels on the
    AVX512-BF16 CPU, so the imitation measured this CPU kind's realization; its timed stages take 9.3 minutes
    (issue 55 asks at most 5), training 7.5 of them."""
    real, imitated = (
        BUDGET / name for name in ("fresh_clone_676afef_avx2_seed1000", "avx2_imitated_5aa37fd_seed1000")
    )
    curves = [json.loads((run / "training_curve.json").read_text())["log_every"] for run in (real, imitated)]
    assert curves[0] == curves[1]
    summaries = [json.loads((run / "summary.json").read_text()) for run in (real, imitated)]
    for condition in CONDITIONS:
        episodes = [summary["conditions"][condition]["episodes"] for summary in summaries]
        assert [e["mean_final_energy"] for e in episodes[0]] == [e["mean_final_energy"] for e in episodes[1]]
    timings = summaries[0]["timings_s"]
    assert sum(timings.values()) / 60 == pytest.approx(9.30, abs=0.005)
    assert timings["train_s"] / 60 == pytest.approx(7.5, abs=0.01)


@pytest.mark.parametrize("name", ["fresh_clone_676afef_avx2_seed1000", "fresh_clone_b0821f5_intel_seed1000"])
def test_forty_more_vanilla_rollouts_on_the_avx2_only_cpu_and_the_xeon_all_succeed(name, tmp_path):
    """Each checkpoint's 40 extra vanilla rollouts (seeds 5000-5039) all succeed, so the failure check on vanilla
    alone cannot be read there; the default monitor alarms on none of them."""
    run = BUDGET / name
    extra = group_by_episode(read_energy_records(run / "eval" / "vanilla_extra"))
    assert {chunks[0].seed for chunks in extra.values()} == set(range(5000, 5040))
    assert extra_vanilla(run, tmp_path) == (40, [0, 40], None)


def test_an_intel_xeon_with_avx512_bf16_trains_a_third_realization_in_6_3_minutes():
    """The README's job from a fresh clone of b0821f5 on a 2-core Intel Xeon (family 6 model 207, AVX512-BF16, no
    AMX): neither AMD kind's realization (its L1 at step 400 is 0.462, theirs 0.477 and 0.459); 6.3 minutes of timed
    stages, training 5.2 of them (issue 55 asks at most 5); failure check 0.65 with 9 failed (issue 55 asks 0.75)."""
    run = BUDGET / "fresh_clone_b0821f5_intel_seed1000"
    timings = json.loads((run / "summary.json").read_text())["timings_s"]
    assert sum(timings.values()) / 60 == pytest.approx(6.34, abs=0.005)
    assert timings["train_s"] / 60 == pytest.approx(5.17, abs=0.005)
    others = [
        curve_l1(BUDGET / name, 400)
        for name in ("fresh_clone_5aa37fd_seed1000", "fresh_clone_676afef_avx2_seed1000")
    ]
    assert curve_l1(run, 400) not in others


@pytest.mark.parametrize(
    ("name", "seeds", "expected"),
    [
        ("fresh_clone_5aa37fd_seed1000", range(5000, 5040), (38, [0, 40], 0.658)),
        ("preset_5aa37fd_seed4000", range(9000, 9040), (39, [0, 40], 0.821)),
        ("preset_5aa37fd_seed5000", range(9000, 9040), (35, [1, 40], 0.897)),
        ("preset_5aa37fd_seed6000", range(9000, 9040), (40, [2, 40], None)),
    ],
)
def test_the_new_presets_extra_vanilla_rollouts(name, seeds, expected, tmp_path):
    """40 more vanilla rollouts of each checkpoint: 152 of 160 succeed, the default monitor alarms on 3, and the
    failure check on vanilla alone is never inverted where a rollout failed (0.66 with 2 failed, 0.82 with 1, 0.90
    with 5)."""
    run = BUDGET / name
    extra = group_by_episode(read_energy_records(run / "eval" / "vanilla_extra"))
    assert {chunks[0].seed for chunks in extra.values()} == set(seeds)
    successes_, alarmed, failure_auroc = extra_vanilla(run, tmp_path)
    assert (successes_, alarmed) == expected[:2]
    assert failure_auroc == (None if expected[2] is None else pytest.approx(expected[2], abs=5e-4))


def test_thirty_calibration_rollouts_do_not_lift_the_failure_check(tmp_path):
    """The job's 10 calibration rollouts against 30 (20 more of the next seeds, `eval/calibration_extra`) on four
    checkpoints of the preset: the failure check over the printed rollouts moves by at most 0.05 and falls on seed
    5000, and the default monitor alarms on more held-out vanilla rollouts (6/40 against 2/40)."""
    found = {}
    for name in (
        "fresh_clone_5aa37fd_seed1000",
        "preset_5aa37fd_seed4000",
        "preset_5aa37fd_seed5000",
        "preset_5aa37fd_seed6000",
    ):
        for extra in ((), ("calibration_extra",)):
            scored = scored_report(
                BUDGET / name, tmp_path / f"{name}{len(extra)}", calibration=("calibration", *extra)
            )
            said = monitor_summary(scored)
            found[name, 10 + 20 * len(extra)] = (
                round(said["failing"]["auroc"], 3),
                said["unfamiliar"]["vanilla"]["alarmed"][0],
            )
    assert found == {
        ("fresh_clone_5aa37fd_seed1000", 10): (0.884, 0),
        ("fresh_clone_5aa37fd_seed1000", 30): (0.88, 0),
        ("preset_5aa37fd_seed4000", 10): (0.73, 1),
        ("preset_5aa37fd_seed4000", 30): (0.73, 2),
        ("preset_5aa37fd_seed5000", 10): (0.63, 1),
        ("preset_5aa37fd_seed5000", 30): (0.579, 1),
        ("preset_5aa37fd_seed6000", 10): (0.739, 0),
        ("preset_5aa37fd_seed6000", 30): (0.745, 3),
    }


def test_the_main_job_after_the_scores_split_prints_what_b0821f5_printed_on_the_same_cpu():
    """research/docs/benchmarks_speed.md, "The main job on an Intel Xeon with AVX512-BF16": the README's command from a
    fresh clone of 404e15c (runtime/scores.py split in three) on the same kind of Xeon gives b0821f5's summary figure
    for figure (vanilla 10/10, blank 5/10, pose_s3 6/10, camera 51.1 %, the monitor 1.00 / 1.00, failure 0.65); only the
    timings differ."""
    before = json.loads((BUDGET / "fresh_clone_b0821f5_intel_seed1000" / "summary.json").read_text())
    after = json.loads((BUDGET / "fresh_clone_404e15c_intel_seed1000" / "summary.json").read_text())
    assert {k for k in after if after[k] != before[k]} == {"timings_s"}
    assert sum(after["timings_s"].values()) / 60 == pytest.approx(7.1, abs=0.05)
