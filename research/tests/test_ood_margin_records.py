"""The with/without table of the OOD margin (research/results/metaworld_sweep_ood_margin/summary.md, issue 32),
recomputed from its committed records by the script that printed it."""

import json
from pathlib import Path

import numpy as np
import pytest

from lerobot_policy_ebvla.monitoring.failure_report import FailureReportConfig, write_failure_report
from lerobot_policy_ebvla.monitoring.metrics import format_auroc
from lerobot_policy_ebvla.monitoring.records import load_episodes
from research.tests.conftest import RESULTS as ALL_RESULTS
from research.tests.conftest import load_benchmark
from research.tests.test_metaworld_records import first_chunks_row, records_report, summary_rows

RESULTS = ALL_RESULTS / "metaworld_sweep_ood_margin"


report = load_benchmark("energy_margin_report")


def auroc(rows: dict, condition: str, form: str = "one_sided") -> float:
    return round(rows[condition][form][1], 2)


def test_without_the_margin_the_energy_is_confidently_wrong_under_light_and_right_under_blank_and_pose():
    rows = report.run_table(RESULTS / "without" / "records", 3)
    assert [auroc(rows, c) for c in ("light_color_s5", "light_dim_s5", "light_direction_s5")] == [
        0.11,
        0.25,
        0.22,
    ]
    assert auroc(rows, "blank_s5") == auroc(rows, "pose_s5") == 1.0
    # Two-sided, light colour is recovered and the pool rises, while table texture turns below 0.5.
    assert auroc(rows, "light_color_s5", "two_sided") == 0.91
    assert auroc(rows, "table_texture_s5", "two_sided") == 0.41
    assert (
        auroc(rows, "all perturbations pooled"),
        auroc(rows, "all perturbations pooled", "two_sided"),
    ) == (
        0.57,
        0.8,
    )
    assert auroc(rows, "failed vs successful (all held out)") == 0.45


@pytest.mark.parametrize(
    ("run", "pooled", "shifted_success"),
    [("margin_head_all", 0.94, 9 / 56), ("margin_head_img", 0.97, 12 / 56), ("joint_context", 0.86, 25 / 56)],
)
def test_each_margin_lifts_the_pooled_auroc_and_only_the_joint_energy_keeps_the_policys_success(
    run, pooled, shifted_success
):
    rows = report.run_table(RESULTS / run / "records", 3)
    assert auroc(rows, "all perturbations pooled") == pooled
    assert rows["all perturbations pooled"]["success"] == pytest.approx(shifted_success)
    if run == "joint_context":  # no light shift inverted, none confidently caught either
        lights = [auroc(rows, c) for c in ("light_color_s5", "light_dim_s5", "light_direction_s5")]
        assert lights == [0.78, 0.8, 0.72]


FULL = RESULTS.parent / "metaworld_sweep_margin_full"


def never_confidently_under_half(rows: dict, conditions: list[str]) -> bool:
    """Every condition's interval reaches above 0.5 where its AUROC is under it (the upper bound of "0.38 [0.15, 0.63]")."""
    below = [c for c in conditions if rows[c]["one_sided"][1] < 0.5]
    return all(float(rows[c]["one_sided"][0].split(", ")[1].split("]")[0]) > 0.5 for c in below)


def success_cutting(rows: dict) -> list[str]:
    """The conditions whose success is 20+ points under vanilla's (issue 32's success-cutting perturbations)."""
    vanilla = rows["vanilla"]["success"]
    return [c for c, r in rows.items() if c.endswith(("_s3", "_s5")) and r["success"] <= vanilla - 0.2]


def test_on_the_full_sweep_the_image_margin_sees_every_success_cutting_shift_and_costs_the_policy():
    without = report.run_table(FULL / "without" / "records", 3)
    margin = report.run_table(FULL / "margin_head_img" / "records", 3)
    assert len([c for c in margin if c.endswith(("_s3", "_s5"))]) == 26
    # Without the term the raw energy pools to chance and inverts under every light shift.
    assert auroc(without, "all perturbations pooled") == 0.52
    assert all(auroc(without, f"light_{k}_s5") < 0.5 for k in ("color", "dim", "direction"))
    # With it: at least 0.98 on every success-cutting condition, one condition just under 0.5 (not confidently).
    assert auroc(margin, "all perturbations pooled") == 0.94
    assert min(auroc(margin, c) for c in success_cutting(margin)) >= 0.98
    worst = min((c for c in margin if c.endswith(("_s3", "_s5"))), key=lambda c: margin[c]["one_sided"][1])
    assert (worst, auroc(margin, worst)) == ("light_direction_s3", 0.47)
    assert auroc(margin, "failed vs successful (all held out)") == 0.70
    # ... and the policy pays: 70% -> 57.5% vanilla (40 rollouts each), 50% -> 23% under the shifts.
    assert (without["vanilla"]["success"], margin["vanilla"]["success"]) == (0.7, 0.575)
    assert round(without["all perturbations pooled"]["success"], 2) == 0.5
    assert round(margin["all perturbations pooled"]["success"], 2) == 0.23


def test_at_weight_0_3_the_margin_costs_as_much_success_and_light_direction_inverts_confidently():
    rows = report.run_table(FULL / "margin_head_img_w03" / "records", 3)
    assert rows["vanilla"]["success"] == 0.575
    assert round(rows["all perturbations pooled"]["success"], 2) == 0.42
    assert auroc(rows, "all perturbations pooled") == 0.87
    assert min(auroc(rows, c) for c in success_cutting(rows)) >= 0.94
    assert (auroc(rows, "light_direction_s3"), auroc(rows, "light_direction_s5")) == (0.17, 0.1)
    assert rows["light_direction_s5"]["one_sided"][0].endswith("**inv**")


def test_the_joint_energy_is_never_confidently_wrong_on_the_full_sweep_but_weak():
    rows = report.run_table(FULL / "joint_context" / "records", 3)
    conditions = [c for c in rows if c.endswith(("_s3", "_s5"))]
    inverted = [c for c in conditions if rows[c]["one_sided"][1] < 0.5]
    assert sorted(inverted) == ["blur_s3", "blur_s5", "light_direction_s3", "noise_s3", "noise_s5"]
    assert never_confidently_under_half(rows, inverted)
    assert auroc(rows, "all perturbations pooled") == 0.7
    assert round(min(rows[c]["one_sided"][1] for c in success_cutting(rows)), 2) == 0.84


def test_the_joint_energy_through_the_backbone_sees_the_image_shifts_and_keeps_the_policys_success_under_them():
    rows = report.run_table(FULL / "context_backbone" / "records", 3)
    without = report.run_table(FULL / "without" / "records", 3)
    assert auroc(rows, "all perturbations pooled") == 0.88
    # Every success-cutting image shift at 0.97-0.98; the robot's initial state (no image corruption teaches it) not.
    cutting = {c: auroc(rows, c) for c in success_cutting(rows)}
    assert {c for c, a in cutting.items() if a < 0.85} == {"robot_init_s3", "robot_init_s5"}
    assert min(a for c, a in cutting.items() if not c.startswith("robot_init")) == 0.97
    # Two conditions under 0.5, neither confidently (each interval reaches above it).
    inverted = [c for c in rows if c.endswith(("_s3", "_s5")) and rows[c]["one_sided"][1] < 0.5]
    assert sorted(inverted) == ["blur_s3", "light_direction_s3"]
    assert never_confidently_under_half(rows, inverted)
    # Success under the shifts as without the term (51% -> 50% of 208); vanilla 62.5% against 70% (40 each).
    assert round(rows["all perturbations pooled"]["success"], 2) == 0.5
    assert round(without["all perturbations pooled"]["success"], 2) == 0.5
    assert rows["vanilla"]["success"] == 0.625
    assert auroc(rows, "failed vs successful (all held out)") == 0.48


def test_with_state_noise_the_joint_energy_is_never_under_0_5_two_sided_and_sees_the_robots_initial_state():
    rows = report.run_table(FULL / "context_backbone_state" / "records", 3)
    conditions = [c for c in rows if c.endswith(("_s3", "_s5"))]
    # Two-sided (the shipped phase_energy_deviation, mean |z_t|): at least 0.51 everywhere, 0.86 and 0.98
    # on the two success-cutting conditions (the robot's initial state); one-sided it reaches 0.77 and 0.71 there.
    assert round(min(rows[c]["two_sided"][1] for c in conditions), 2) == 0.51
    assert success_cutting(rows) == ["robot_init_s3", "robot_init_s5"]
    assert [auroc(rows, c, "two_sided") for c in success_cutting(rows)] == [0.86, 0.98]
    assert [auroc(rows, c) for c in success_cutting(rows)] == [0.77, 0.71]
    assert auroc(rows, "all perturbations pooled", "two_sided") == 0.93
    assert auroc(rows, "failed vs successful (all held out)") == 0.56


def test_vanilla_success_over_140_shared_seeds_differs_as_much_between_training_realizations_as_with_the_term():
    runs = ("without", "joint_context", "margin_head_img", "context_backbone", "context_backbone_state")
    table = report.vanilla_success({run: FULL / run / "records" for run in runs})
    assert {run: table[run][:2] for run in runs} == {
        "without": (93, 140),
        "joint_context": (79, 140),
        "margin_head_img": (74, 140),
        "context_backbone": (82, 140),
        "context_backbone_state": (84, 140),
    }
    # joint_context trains the backbone and head as without the term (E_c reads detached contexts), yet loses
    # 21 and wins 7 of the same seeds: the realization, not the term.
    assert table["joint_context"][2:4] == (7, 21)
    assert table["joint_context"][4] < 0.05


def test_on_a_second_training_seed_the_backbone_joint_energy_succeeds_less_than_without_and_than_its_control():
    seed2000 = FULL / "seed2000"
    runs = ("without", "joint_context", "context_backbone")
    table = report.vanilla_success({run: seed2000 / run / "records" for run in runs})
    assert table["without"][:2] == (84, 140)
    assert table["context_backbone"][:4] == (72, 140, 7, 19)
    assert table["context_backbone"][4] < 0.05
    # This seed's realization control succeeds as without does (+16 / -13), and the backbone variant loses to it.
    assert table["joint_context"][:4] == (87, 140, 16, 13)
    control = report.vanilla_success({run: seed2000 / run / "records" for run in runs[1:]})
    assert control["context_backbone"][2:4] == (11, 26) and control["context_backbone"][4] < 0.05


def test_on_seed_2000_the_backbone_joint_energy_is_never_under_0_5_and_misses_only_the_robots_initial_state():
    rows = report.run_table(FULL / "seed2000" / "context_backbone" / "records", 3)
    conditions = [c for c in rows if c.endswith(("_s3", "_s5"))]
    assert len(conditions) == 26
    assert min(rows[c]["one_sided"][1] for c in conditions) >= 0.5
    assert auroc(rows, "all perturbations pooled") == 0.93
    cutting = {c: auroc(rows, c) for c in success_cutting(rows)}
    assert cutting == {
        "noise_s5": 1.0,
        "robot_init_s3": 0.76,
        "robot_init_s5": 0.85,
        "table_color_s5": 1.0,
        "table_texture_s5": 1.0,
    }


def test_the_first_chunks_do_not_tell_failure_from_success_within_vanilla_or_within_the_shifts():
    """Why failed vs successful stays near chance: apart, within the vanilla rollouts (140) and within the
    perturbed ones (208), the first 3 chunks' energy tells failure weakly, and its sign changes from checkpoint
    to checkpoint; the backbone joint energy flags a shift whether the policy copes with it or not."""
    without = report.run_table(FULL / "without" / "records", 3)
    backbone = report.run_table(FULL / "context_backbone_state" / "records", 3)
    seed2000 = report.run_table(FULL / "seed2000" / "context_backbone" / "records", 3)
    vanilla, perturbed = "failed vs successful (vanilla only)", "failed vs successful (perturbed only)"
    assert without[vanilla]["n"] == backbone[vanilla]["n"] == 140 and without[perturbed]["n"] == 208
    # Failed vanilla rollouts sit *below* the successful ones without the term, above them on seed 2000's backbone.
    assert (auroc(without, vanilla), auroc(without, vanilla, "two_sided")) == (0.17, 0.7)
    assert auroc(seed2000, vanilla) == 0.81
    assert [
        auroc(backbone, c, form) for c in (vanilla, perturbed) for form in ("one_sided", "two_sided")
    ] == [
        0.6,
        0.53,
        0.53,
        0.53,
    ]
    assert auroc(backbone, "failed vs successful (all held out)", "two_sided") == 0.56


def test_with_60_calibration_rollouts_the_default_monitor_reaches_0_90_on_the_default_policy(tmp_path):
    """The default policy (`without`): context_knn pools to 0.879 over the first 3 chunks with the sweep's 20
    calibration rollouts, 0.905 with 40 more (seeds 4020-4059), never under 0.5; the k-NN's vanilla contexts
    are denser, so held-out vanilla sits nearer them (alarms at T on vanilla 22% -> 12%)."""
    records = FULL / "without" / "records"
    rows = {}
    for name, extra in (("20", []), ("60", [str(FULL / "without" / "calibration_extra")])):
        calibration = [str(records / "calibration"), *extra]
        report_text = records_report(records, tmp_path / name, calibration=calibration, first_chunks=[3])
        rows[name] = summary_rows(report_text)["context_knn"]
    assert rows["20"][0].startswith("0.879") and rows["20"][1] == "22% / 80%"
    assert rows["60"][0].startswith("0.905") and rows["60"][1] == "12% / 76%"
    assert rows["60"][4] == "light_direction 3 0.606" and rows["60"][5] == "none"


def test_vanilla_success_pools_over_training_seeds_pairing_each_rollout_within_its_seed():
    runs = {
        name: [FULL / name / "records", FULL / "seed2000" / name / "records"]
        for name in ("without", "context_backbone", "joint_context")
    }
    table = report.vanilla_success_over_seeds(runs)
    assert table["without"] == (177, 280, 0, 0, 1.0)
    # The per-seed tables' wins and losses, summed: +4 / -15 on seed 1000, +7 / -19 on seed 2000.
    assert table["context_backbone"][:4] == (154, 280, 11, 34)
    assert table["joint_context"][:4] == (166, 280, 23, 34)


def seed_run(seed: int, name: str) -> Path:
    """A training seed's run folder of `metaworld_sweep_margin_full` (seed 1000's at the top)."""
    return FULL / name if seed == 1000 else FULL / f"seed{seed}" / name


def seed_runs(name: str) -> list[Path]:
    """A recipe's records on training seeds 1000, 2000 and 3000."""
    return [seed_run(seed, name) / "records" for seed in (1000, 2000, 3000)]


def test_over_three_training_seeds_the_realization_moves_success_more_than_the_backbone_term_costs():
    """Vanilla success, 140 rollouts a run (seeds 3000-3039 and 5000-5099). `without`, `joint_context` and
    `observation` train the policy's backbone and head identically (only the random stream differs): their spread
    on one training seed is the realization's. The backbone joint energy with the state corruption costs 4.8 points
    against their mean over three seeds, and 6 at weight 0.3."""
    recipes = (
        "without",
        "joint_context",
        "observation",
        "context_backbone_state",
        "context_backbone_state_w03",
    )
    per_seed = {
        name: [report.vanilla_success({name: folder})[name][:2] for folder in seed_runs(name)]
        for name in recipes
    }
    assert all(n == 140 for runs in per_seed.values() for _, n in runs)
    successes = {name: [s for s, _ in runs] for name, runs in per_seed.items()}
    assert successes == {
        "without": [93, 84, 88],
        "joint_context": [79, 87, 98],
        "observation": [72, 91, 89],
        "context_backbone_state": [84, 84, 72],
        "context_backbone_state_w03": [84, 76, 75],
    }
    # On training seed 1000 alone, three realizations of one policy training span 72-93 of 140 (15 points).
    assert (
        max(s[0] for s in list(successes.values())[:3]) - min(s[0] for s in list(successes.values())[:3])
        == 21
    )
    identical = sum(sum(successes[n]) for n in recipes[:3]) / 3 / 420
    assert round(100 * (sum(successes["context_backbone_state"]) / 420 - identical), 1) == -4.8
    assert round(100 * (sum(successes["context_backbone_state_w03"]) / 420 - identical), 1) == -6.0
    pooled = report.vanilla_success_over_seeds({name: seed_runs(name) for name in recipes})
    assert pooled["context_backbone_state"][:4] == (240, 420, 32, 57)


def test_the_observation_energy_keeps_its_gradients_out_of_the_clipped_norm_at_weight_0_01():
    """LeRobot clips the gradient norm of all the policy's parameters at 10: at weight 1 the observation encoder's
    gradients held the norm at 18-34 over the first 400 steps, shrinking the policy's updates; at 0.01 the norm is
    the policy's alone (Adam normalizes the encoder's and E_c's own updates, so their learning does not change)."""
    logs = json.loads((FULL / "training_logs.json").read_text())
    assert min(logs["observation_w1"]["grad_norm"][:4]) > 18
    for seed in ("", "seed2000/", "seed3000/"):
        without, observation = logs[f"{seed}without"]["grad_norm"], logs[f"{seed}observation"]["grad_norm"]
        assert max(observation[1:]) < 10 and abs(observation[0] - without[0]) < 1


def test_the_observation_energy_is_never_confidently_wrong_on_three_training_seeds():
    """The joint energy on its own encoder (`observation`, weight 0.01), raw final energy over the first 3 chunks:
    pooled 0.93 / 0.91 / 0.95; every condition under 0.5 has an interval reaching above it; on seed 3000 it meets
    the energy-only target (>= 0.85 on every success-cutting shift, >= 0.5 on all 26), on seed 1000 it misses the
    floor by blur 3 (0.48), on seed 2000 the cutting target by fov 3 (0.53)."""
    tables = [report.run_table(folder, 3) for folder in seed_runs("observation")]
    assert [auroc(t, "all perturbations pooled") for t in tables] == [0.93, 0.91, 0.95]
    for rows in tables:
        conditions = [c for c in rows if c.endswith(("_s3", "_s5"))]
        assert len(conditions) == 26
        assert never_confidently_under_half(rows, conditions)
    seed1000, seed2000, seed3000 = tables
    assert [c for c in seed1000 if c.endswith(("_s3", "_s5")) and seed1000[c]["one_sided"][1] < 0.5] == [
        "blur_s3"
    ]
    assert auroc(seed1000, "blur_s3") == 0.48
    assert auroc(seed2000, "fov_s3") == 0.53 and "fov_s3" in success_cutting(seed2000)
    assert min(auroc(seed3000, c) for c in success_cutting(seed3000)) >= 0.85
    assert min(seed3000[c]["one_sided"][1] for c in seed3000 if c.endswith(("_s3", "_s5"))) >= 0.5


def test_on_a_policy_trained_as_the_default_the_context_knn_can_be_confidently_wrong(tmp_path):
    """Seed 2000's `observation` checkpoint: its policy trains as `without` does, and there the default monitor
    (`context_knn`) pools to 0.807 and is confidently inverted under light_direction 3 (0.28), where the joint
    energy stays at 0.47 (not confidently) and pools to 0.912."""
    records = FULL / "seed2000" / "observation" / "records"
    rows = summary_rows(records_report(records, tmp_path, n_bootstrap=200, first_chunks=[3]))
    assert rows["context_knn"][0].startswith("0.807") and "light_direction 3 0.28!" in rows["context_knn"][5]
    assert rows["final_energy"][0].startswith("0.912") and "!" not in rows["final_energy"][5]


def test_on_two_more_training_seeds_the_observation_energy_stays_safe_and_the_context_knn_does_not(tmp_path):
    """Seeds 4000 and 5000: the joint energy pools to 0.91 on both, no condition confidently under 0.5; the context
    k-NN on the same records pools to 0.771 / 0.786 and is confidently inverted twice on seed 5000."""
    for seed, knn_pooled in ((4000, "0.771"), (5000, "0.786")):
        records = FULL / f"seed{seed}" / "observation" / "records"
        rows = report.run_table(records, 3)
        assert auroc(rows, "all perturbations pooled") == 0.91
        assert never_confidently_under_half(rows, [c for c in rows if c.endswith(("_s3", "_s5"))])
        summary = summary_rows(
            records_report(records, tmp_path / str(seed), n_bootstrap=200, first_chunks=[3])
        )
        assert summary["context_knn"][0].startswith(knn_pooled)
        assert "!" not in summary["final_energy"][5]
        if seed == 5000:
            assert summary["context_knn"][5].count("!") == 2


def fresh_rows(name: str) -> dict[tuple[int, str], dict]:
    """`energy_margin_report.fresh_table` of every training seed's `name` run with fresh rollouts, by (seed,
    condition)."""
    runs = {seed: seed_run(seed, name) for seed in (1000, 2000, 3000, 4000, 5000)}
    return {
        (seed, condition): row
        for seed, run in runs.items()
        if (run / "fresh").is_dir()
        for condition, row in report.fresh_table(run / "records", run / "fresh", 3).items()
    }


def test_on_fresh_rollouts_the_observation_energys_near_misses_sit_at_chance_and_one_is_confidently_under(
    tmp_path,
):
    """The eight conditions whose first-3 AUROC was under 0.60 on the five `observation` sweeps, re-run on 24 fresh
    rollouts each (environment seed 6000) and scored against the 100 `vanilla_extra` rollouts (seed 5000), neither
    of which took part in choosing them: 0.36-0.59, and light_direction 3 on seed 2000 (a shift that costs no
    success) confidently under 0.5. Against the sweep's 40 vanilla rollouts the same fresh rollouts give 0.47 there,
    and neither of the context k-NN's n=8 inversions (0.28, 0.28) comes back (0.58, 0.46)."""
    runs = {seed: seed_run(seed, "observation") for seed in (1000, 2000, 4000, 5000)}
    fresh = fresh_rows("observation")
    assert len(fresh) == 8 and all(row["n"] == 24 and row["n_vanilla"] == 100 for row in fresh.values())
    values = {key: round(row["one_sided"][1], 2) for key, row in fresh.items()}
    assert min(values.values()) == 0.36 and max(values.values()) == 0.59
    confidently_under = [k for k, row in fresh.items() if not never_confidently_under_half({k: row}, [k])]
    assert confidently_under == [(2000, "light_direction_s3")]
    assert fresh[(2000, "light_direction_s3")]["success"] == pytest.approx(16 / 24)
    # What a user gets at the threshold set on the 20 calibration rollouts alone: no alarm under that shift,
    # against 22% of the extra vanilla rollouts; over the whole episode the energy stays under vanilla (0.38).
    inverted = fresh[(2000, "light_direction_s3")]
    assert inverted["alarms"] == 0.0 and inverted["vanilla_alarms"] == pytest.approx(0.22)
    assert round(inverted["whole_episode"][1], 2) == 0.38

    run = runs[2000]
    fresh_report = records_report(
        run / "records", tmp_path, first_chunks=[3], ood=[str(run / "fresh" / "light_direction_s3")]
    )
    assert first_chunks_row(fresh_report, "light_direction 3", "final_energy")[0] == 0.465
    assert first_chunks_row(fresh_report, "light_direction 3", "context_knn")[0] == 0.579
    run = runs[5000]  # the k-NN's other n=8 inversion, blur 3 on seed 5000 (0.28), on the fresh rollouts
    fresh_report = records_report(
        run / "records", tmp_path / "s5000", first_chunks=[3], ood=[str(run / "fresh" / "blur_s3")]
    )
    assert first_chunks_row(fresh_report, "blur 3", "context_knn")[0] == 0.463


def test_random_convolutions_lift_most_fresh_near_misses_and_leave_the_sweeps_as_they_were():
    """`observation_randconv` (`random_conv` added to the corruptions) on the five training seeds: on the same fresh
    rollouts it lifts five of eight conditions (fov 3 on seed 2000 to 0.99, blur 5 on seed 4000 to 0.96) and no
    condition is confidently under 0.5; the sweeps pool at 0.906-0.928 against `observation`'s 0.912-0.953; vanilla
    success 399/700 against 426/700."""
    seeds = (1000, 2000, 3000, 4000, 5000)
    before, after = fresh_rows("observation"), fresh_rows("observation_randconv")
    assert set(before) == set(after) and len(after) == 8
    lifted = [k for k in after if after[k]["one_sided"][1] > before[k]["one_sided"][1]]
    assert len(lifted) == 5
    assert round(after[(2000, "fov_s3")]["one_sided"][1], 2) == 0.99
    assert round(after[(4000, "blur_s5")]["one_sided"][1], 2) == 0.96
    # ... and at the calibrated threshold: every fov 3 rollout alarms (19% of the extra vanilla ones), 88% of blur 5.
    assert after[(2000, "fov_s3")]["alarms"] == 1.0 and after[(2000, "fov_s3")][
        "vanilla_alarms"
    ] == pytest.approx(0.19)
    assert after[(4000, "blur_s5")]["alarms"] == pytest.approx(21 / 24)
    assert never_confidently_under_half(after, list(after))
    assert not never_confidently_under_half(before, list(before))  # seed 2000's light_direction 3
    pooled = {
        seed: tuple(
            round(
                report.run_table(seed_run(seed, name) / "records", 3)["all perturbations pooled"][
                    "one_sided"
                ][1],
                3,
            )
            for name in ("observation", "observation_randconv")
        )
        for seed in seeds
    }
    assert pooled == {
        1000: (0.934, 0.923),
        2000: (0.912, 0.928),
        3000: (0.953, 0.906),
        4000: (0.912, 0.909),
        5000: (0.913, 0.909),
    }
    success = report.vanilla_success_over_seeds(
        {
            name: [seed_run(seed, name) / "records" for seed in seeds]
            for name in ("observation", "observation_randconv")
        }
    )
    assert success["observation"][:2] == (426, 700) and success["observation_randconv"][:4] == (
        399,
        700,
        54,
        81,
    )


def test_the_first_chunks_carry_the_outcome_within_vanilla_but_a_probe_fitted_there_misses_shift_failures():
    """research/benchmarks/outcome_probe.py on two of the five `observation` sweeps (summary.md, "What the first chunks
    know"): a supervised probe on the first 3 chunks' pooled context tells vanilla failures at 0.85 and 0.93
    (cross-validated), and fitted on those vanilla outcomes it scores the perturbed rollouts' at 0.57 and 0.49; the
    final energy tells the vanilla failures at 0.38 and 0.22 (its sign flips between checkpoints)."""
    probe = load_benchmark("outcome_probe")
    for seed, within, shifted, failures in ((1000, 0.85, 0.57, 28), (4000, 0.93, 0.49, 19)):
        vanilla, perturbed = probe.vanilla_and_perturbed(seed_run(seed, "observation") / "records", chunks=3)
        assert len(vanilla[1]) == 60 and (~vanilla[1]).sum() == failures and len(perturbed[1]) == 208
        assert probe.cross_validated(*vanilla, l2=0.01, folds=5, repeats=5) == pytest.approx(
            within, abs=0.015
        )
        assert probe.transfer(vanilla, perturbed, l2=0.01)[0] == pytest.approx(shifted, abs=0.015)
    # The energy over the same chunks, on the same checkpoints' 140 vanilla rollouts: its sign flips.
    energy = {
        seed: auroc(
            report.run_table(seed_run(seed, "observation") / "records", 3),
            "failed vs successful (vanilla only)",
        )
        for seed in (1000, 4000)
    }
    assert energy == {1000: 0.38, 4000: 0.22}


def test_graded_strengths_see_blur_and_noise_on_two_fresh_seeds_and_invert_on_the_third():
    """`observation_graded` (corruptions moved s ~ U(0.1, 1) of the way, margin s m) against `observation` on
    training seeds 6000-8000 (summary.md, "Graded corruption strengths"): blur 5 and noise 5 lifted on seeds 6000
    and 7000, but on seed 8000 the pool falls to 0.851 and light_direction 3 is confidently under 0.5; so the rule
    written before the paired sweeps were read keeps it opt-in."""
    seeds = (6000, 7000, 8000)
    tables = {
        (seed, name): report.run_table(seed_run(seed, name) / "records", 3)
        for seed in seeds
        for name in ("observation", "observation_graded")
    }
    pooled = {key: round(rows["all perturbations pooled"]["one_sided"][1], 3) for key, rows in tables.items()}
    assert [pooled[(s, "observation")] for s in seeds] == [0.887, 0.907, 0.917]
    assert [pooled[(s, "observation_graded")] for s in seeds] == [0.928, 0.911, 0.851]
    for seed in (6000, 7000):
        for condition, lift in (("blur_s5", 0.3), ("noise_s5", 0.05)):
            before, after = (
                auroc(tables[(seed, n)], condition) for n in ("observation", "observation_graded")
            )
            assert after > before + lift, (seed, condition, before, after)
    worst = tables[(8000, "observation_graded")]
    assert auroc(worst, "light_direction_s3") == 0.21
    assert not never_confidently_under_half(worst, ["light_direction_s3"])
    for seed in seeds:  # the preset's energy: no condition confidently under 0.5 on any fresh seed
        rows = tables[(seed, "observation")]
        assert never_confidently_under_half(rows, [c for c in rows if c.endswith(("_s3", "_s5"))])


def test_graded_strengths_on_fresh_rollouts_lift_blur_everywhere_and_leave_light_direction_confidently_under():
    """The fresh rollouts of the same comparison (24 per condition against 100 vanilla_extra): graded is higher on 8
    of 11 conditions, among them blur 3 on all three seeds, but confidently under 0.5 on seed 8000's
    light_direction 3 (0.38), where the preset's energy is never confidently under."""
    rows = {
        (seed, name): report.fresh_table(seed_run(seed, name) / "records", seed_run(seed, name) / "fresh", 3)
        for seed in (6000, 7000, 8000)
        for name in ("observation", "observation_graded")
    }
    pairs = [
        (
            rows[(seed, "observation")][c]["one_sided"][1],
            rows[(seed, "observation_graded")][c]["one_sided"][1],
        )
        for seed in (6000, 7000, 8000)
        for c in rows[
            (seed, "observation_graded")
        ]  # the preset has one more on seed 8000 (the shading rule's)
    ]
    assert len(pairs) == 11 and sum(after > before for before, after in pairs) == 8
    for seed in (6000, 7000, 8000):
        graded = rows[(seed, "observation_graded")]
        assert (
            graded["blur_s3"]["one_sided"][1] > 0.7 > rows[(seed, "observation")]["blur_s3"]["one_sided"][1]
        )
        assert never_confidently_under_half(rows[(seed, "observation")], list(rows[(seed, "observation")]))
    inverted = rows[(8000, "observation_graded")]
    assert round(inverted["light_direction_s3"]["one_sided"][1], 2) == 0.38
    assert not never_confidently_under_half(inverted, ["light_direction_s3"])


def test_every_checkpoint_of_the_margin_study_reads_its_camera():
    """camera_checks.json: the refined chunk changes by 41% or more with the cameras blanked, on all 47."""
    checks = json.loads((FULL / "camera_checks.json").read_text())
    changes = {run: check["chunk_change"] for run, check in checks.items() if not run.startswith("_")}
    assert len(changes) == 47 and min(changes.values()) > 0.41
    assert all(check["num_frames"] == 32 for run, check in checks.items() if not run.startswith("_"))


def test_a_shading_corruption_with_graded_strengths_still_puts_light_direction_confidently_under():
    """`observation_shaded` (graded strengths plus the "shading" corruption) against `observation` on training
    seeds 6000-9000 (summary.md, "A shading corruption"): the rule written before its runs fails on both counts,
    a lower mean pool and seed 8000's light_direction 3 confidently under 0.5 again."""
    seeds = (6000, 7000, 8000, 9000)
    tables = {
        (seed, name): report.run_table(seed_run(seed, name) / "records", 3)
        for seed in seeds
        for name in ("observation", "observation_shaded")
    }
    pooled = {key: round(rows["all perturbations pooled"]["one_sided"][1], 3) for key, rows in tables.items()}
    assert [pooled[(s, "observation")] for s in seeds] == [0.887, 0.907, 0.917, 0.953]
    assert [pooled[(s, "observation_shaded")] for s in seeds] == [0.926, 0.902, 0.863, 0.922]
    worst = tables[(8000, "observation_shaded")]
    assert auroc(worst, "light_direction_s3") == 0.3
    assert not never_confidently_under_half(worst, ["light_direction_s3"])
    untouched = tables[(9000, "observation")]  # the preset on the seed nothing was chosen on
    assert min(untouched[c]["one_sided"][1] for c in untouched if c.endswith(("_s3", "_s5"))) > 0.6


split = load_benchmark("context_energy_split")


def test_the_context_term_alone_sees_the_shifts_the_head_part_hides_on_four_training_seeds():
    """The preset's joint energy split (`context_energy` recorded on the sweep's conditions and seeds, rollouts cut
    after 3 chunks; summary.md, "The joint energy split"): the head's part inverts under many shifts, E_c alone
    pools higher than the sum on every seed and sees every success-cutting shift; its two-sided form is never
    confidently under 0.5."""
    results = {
        seed: split.run_split(
            seed_run(seed, "observation") / "context_energy", 3, seed_run(seed, "observation") / "records"
        )["summary"]
        for seed in (6000, 7000, 8000, 9000)
    }
    pooled = {part: [float(r[part]["pooled"][:4]) for r in results.values()] for part in split.PARTS}
    assert pooled["joint"] == [0.91, 0.88, 0.91, 0.97]
    assert pooled["E_c"] == [0.94, 0.95, 0.99, 0.99]
    assert pooled["|z| E_c"] == [0.97, 0.94, 0.99, 0.99]
    assert all(e > j for e, j in zip(pooled["E_c"], pooled["joint"], strict=True))
    assert [r["head"]["under 0.5"] for r in results.values()] == [5, 22, 11, 7]
    assert all(
        r["E_c"]["cutting min"] > 0.98 and r["|z| E_c"]["cutting min"] > 0.98 for r in results.values()
    )
    assert [r["E_c"]["confidently under"] for r in results.values()] == [
        ["blur_s3", "light_direction_s3"],
        [],
        [],
        [],
    ]
    assert all(r["|z| E_c"]["confidently under"] == [] for r in results.values())
    assert [r["|z| E_c"]["under 0.5"] for r in results.values()] == [1, 1, 0, 0]


def test_on_full_rollouts_the_context_term_flags_shifts_not_failures():
    """Seeds 6000 and 9000 re-run in full with `context_energy` recorded (the same rollouts as the sweep's, energy
    for energy): E_c pools at 0.95 and 0.99 but tells failed from successful at chance."""
    results = {
        seed: split.run_split(seed_run(seed, "observation") / "context_energy_full", 3)["summary"]
        for seed in (6000, 9000)
    }
    assert [r["E_c"]["pooled"][:4] for r in results.values()] == ["0.95", "0.99"]
    assert [r["E_c"]["failed vs successful"][:4] for r in results.values()] == ["0.50", "0.43"]
    # The joint energy of these rollouts is the sweep's own: its pooled AUROC is energy_margin_report's.
    assert [r["joint"]["pooled"][:4] for r in results.values()] == ["0.89", "0.95"]


def test_on_two_untouched_training_seeds_the_two_sided_context_term_passes_the_rule_written_before_them():
    """Seeds 10000 and 11000, trained after the rule was written (summary.md, "The untouched check"): |z| E_c is
    never confidently under 0.5, pools >= 0.90, sees every success-cutting shift and alarms on <= 20% of vanilla;
    the shipped sum is confidently under 0.5 on seed 11000's light_direction 3."""
    results = {
        seed: split.run_split(seed_run(seed, "observation") / "context_energy_full", 3)["summary"]
        for seed in (10000, 11000)
    }
    for summary in results.values():
        two_sided = summary["|z| E_c"]
        assert two_sided["confidently under"] == []
        assert float(two_sided["pooled"][:4]) >= 0.90 and two_sided["cutting min"] >= 0.85
        assert two_sided["alarms vanilla"] <= 0.20
    assert [r["|z| E_c"]["pooled"][:4] for r in results.values()] == ["0.98", "0.97"]
    assert results[11000]["joint"]["confidently under"] == ["light_direction_s3"]
    assert results[11000]["E_c"]["confidently under"] == ["light_direction_s3"]


summaries = load_benchmark("score_summaries")


def section(markdown: str, run: str) -> str:
    return markdown.split(f"## {run}\n\n")[1].split("\n## ")[0].strip()


def table_cells(line: str) -> list[str]:
    """A markdown table row's cells."""
    return [cell.strip() for cell in line.strip().strip("|").split("|")]


def test_the_run_time_context_energy_score_is_never_confidently_wrong_on_four_training_seeds():
    """context_energy_default.md, recomputed for seed 11000 (where the shipped final energy and the one-sided E_c
    are confidently under 0.5 on light_direction 3): the default of a joint-energy checkpoint,
    context_energy_two_sided, is under 0.5 nowhere there and confidently nowhere on any of the four seeds."""
    committed = (FULL / "context_energy_default.md").read_text()
    recomputed = summaries.score_summary(seed_run(11000, "observation") / "context_energy_full")
    assert recomputed == section(committed, "seed11000")
    for seed in (6000, 9000, 10000, 11000):
        rows = summary_rows(f"## Score summary\n{section(committed, f'seed{seed}')}")
        two_sided = rows["context_energy_two_sided"]
        assert "!" not in two_sided[5] and "!" not in two_sided[6], seed
        assert float(two_sided[0].split()[0]) >= 0.96 and two_sided[7].endswith("min 1.000"), seed
    rows = summary_rows(f"## Score summary\n{section(committed, 'seed11000')}")
    assert "light_direction 3 0.24!" in rows["final_energy"][5]
    assert "light_direction 3 0.21!" in rows["context_energy"][5]
    assert rows["context_energy_two_sided"][5] == "none"


def test_on_four_untouched_training_seeds_the_default_passes_three_and_is_confidently_wrong_on_one():
    """context_energy_default_untouched.md (seeds 12000-15000, trained after the rule was written), recomputed for
    seed 12000: context_energy_two_sided is confidently under 0.5 there (light_direction 3, 0.16), where the final
    energy is not; on 13000-15000 it passes (no condition confidently under, pooled >= 0.90, <= 20% vanilla alarms)."""
    committed = (FULL / "context_energy_default_untouched.md").read_text()
    recomputed = summaries.score_summary(seed_run(12000, "observation") / "context_energy_full")
    assert recomputed == section(committed, "seed12000")
    rows = {
        seed: summary_rows(f"## Score summary\n{section(committed, f'seed{seed}')}")
        for seed in range(12000, 16000, 1000)
    }
    assert "light_direction 3 0.16!" in rows[12000]["context_energy_two_sided"][5]
    assert "!" not in rows[12000]["final_energy"][5]
    for seed in (13000, 14000, 15000):
        two_sided = rows[seed]["context_energy_two_sided"]
        assert "!" not in two_sided[5] and float(two_sided[0].split()[0]) >= 0.90, seed
        assert int(two_sided[1].split("%")[0]) <= 20, seed
    assert [rows[s]["context_energy_two_sided"][0][:5] for s in rows] == ["0.912", "0.947", "0.991", "0.962"]
    assert [rows[s]["final_energy"][0][:5] for s in rows] == ["0.890", "0.873", "0.914", "0.910"]


def test_on_fresh_rollouts_the_default_is_confidently_under_on_three_mild_shifts_that_cost_no_success():
    """context_energy_fresh.md, recomputed for seed 12000: 24 fresh rollouts of each near miss against 100 fresh
    vanilla ones; context_energy_two_sided is confidently under 0.5 on seed 12000's light_direction 3 and noise 3
    and seed 15000's blur 3, where the final energy is at chance; none of the shifts costs success."""
    committed = (FULL / "context_energy_fresh.md").read_text()
    fresh = seed_run(12000, "observation") / "context_energy_fresh"
    calibration = seed_run(12000, "observation") / "context_energy_full" / "calibration"
    assert summaries.score_summary(fresh, calibration=calibration) == section(committed, "seed12000_fresh")
    rows = {
        seed: summary_rows(f"## Score summary\n{section(committed, f'seed{seed}_fresh')}")
        for seed in (6000, 9000, 12000, 13000, 15000)
    }
    confident = {
        seed: [c for c in row["context_energy_two_sided"][5].split(", ") if c.endswith("!")]
        for seed, row in rows.items()
    }
    assert confident == {
        6000: [],
        9000: [],
        12000: ["light_direction 3 0.18!", "noise 3 0.33!"],
        13000: [],
        15000: ["blur 3 0.36!"],
    }
    assert all("!" not in row["final_energy"][5] for row in rows.values())
    assert all(row["context_energy_two_sided"][7] == "no such condition" for row in rows.values())


window = load_benchmark("window_typicality")


def window_rows(markdown: str, run: str) -> dict[str, list[str]]:
    """A run's window table, by set: n, success, rollout AUROC, rollout alarms at T, windows alarmed."""
    lines = [line for line in section(markdown, run).splitlines() if line.startswith("| ")][1:]  # no header
    return {cells[0]: cells[1:] for cells in map(table_cells, lines)}


def windows_alarmed(cell: str) -> tuple[float, float, float]:
    """ "83% (80% / 3%) of 5000" -> (0.83, 0.80, 0.03): the share of windows alarmed, and alarmed as too typical
    and as shifted."""
    shares = cell.split(" of ")[0].replace("(", "").replace(")", "").replace("/", "").split()
    return tuple(float(share.rstrip("%")) / 100 for share in shares)


def sweep_conditions(rows: dict) -> list[str]:
    return [name for name in rows if name != "held-out vanilla" and not name.startswith("fresh")]


def test_the_window_test_flags_the_mild_shifts_the_default_is_confidently_wrong_on_in_windows_of_eight():
    """window_typicality.md (the shipped form: the score |a| and its signed aggregate a, each at alpha / 2),
    recomputed for seed 12000 with its fresh rollouts. Against 40 reference rollouts, windows of 8 of 100 fresh
    vanilla rollouts alarm on 2-5% on five seeds; 24-25 of 26 sweep conditions alarm; both sweep conditions the
    per-rollout default is confidently wrong on (seed 12000's light_direction 3, too typical; noise 3, shifted)
    alarm; of the fresh near misses 9000's light_direction 3 (66%), 12000's light_direction 3 (55%) and noise 3
    (91%) mostly alarm, the three blur 3 and 13000's two not (<= 8%). With 20 reference rollouts (the split runs)
    false alarms reach 21%."""
    committed = (FULL / "window_typicality.md").read_text()
    full, fresh = (seed_run(12000, "observation") / f"context_energy_{k}" for k in ("full", "fresh"))
    recomputed = window.run_section("s12000", full, fresh)
    assert recomputed.strip() == f"## s12000\n\n{section(committed, 's12000')}"
    runs = {seed: window_rows(committed, f"s{seed}") for seed in (6000, 9000, 12000, 13000, 15000)}
    false_alarms = [windows_alarmed(rows["held-out vanilla"][4])[0] for rows in runs.values()]
    assert max(false_alarms) <= 0.05 and min(false_alarms) >= 0.02
    alarmed = {
        s: sum(windows_alarmed(r[c][4])[0] == 1.0 for c in sweep_conditions(r)) for s, r in runs.items()
    }
    assert alarmed == {6000: 24, 9000: 25, 12000: 25, 13000: 25, 15000: 24}
    confident = {(s, c) for s, r in runs.items() for c in sweep_conditions(r) if r[c][2].endswith("!")}
    assert confident == {(12000, "light_direction_s3"), (12000, "noise_s3")}
    assert windows_alarmed(runs[12000]["light_direction_s3"][4]) == (1.0, 1.0, 0.0)
    assert windows_alarmed(runs[12000]["noise_s3"][4]) == (1.0, 0.0, 1.0)
    fresh_alarms = {
        (s, c.removeprefix("fresh ")): windows_alarmed(r[c][4])[0]
        for s, r in runs.items()
        for c in r
        if "fresh" in c
    }
    assert {k: v for k, v in fresh_alarms.items() if v >= 0.5} == {
        (9000, "light_direction_s3"): 0.66,
        (12000, "light_direction_s3"): 0.55,
        (12000, "noise_s3"): 0.91,
    }
    assert max(v for v in fresh_alarms.values() if v < 0.5) <= 0.08
    split = windows_alarmed(window_rows(committed, "s15000_split")["held-out vanilla"][4])[0]
    assert split == 0.21


def test_the_window_tests_first_form_sees_one_too_typical_shift():
    """window_typicality_score_only.md (the score alone, the first form): the same protocol alarms on 75% of seed
    12000's fresh light_direction 3 windows, 19% of its noise 3 and 5% of seed 15000's blur 3; the sweep's noise 3
    (confidently under per rollout) is not alarmed. With 20 reference rollouts false alarms reach 29%."""
    committed = (FULL / "window_typicality_score_only.md").read_text()
    full = seed_run(13000, "observation") / "context_energy_full"
    fresh = seed_run(13000, "observation") / "context_energy_fresh"
    recomputed = window.run_section("s13000", full, fresh, score_only=True)
    assert recomputed.strip() == f"## s13000\n\n{section(committed, 's13000')}"
    rows = {seed: window_rows(committed, f"s{seed}") for seed in (12000, 15000)}
    assert windows_alarmed(rows[12000]["fresh light_direction_s3"][4]) == (0.75, 0.75, 0.0)
    assert windows_alarmed(rows[12000]["fresh noise_s3"][4])[0] == 0.19
    assert windows_alarmed(rows[12000]["noise_s3"][4])[0] == 0.0
    assert windows_alarmed(rows[15000]["fresh blur_s3"][4])[0] == 0.05
    split = [
        windows_alarmed(window_rows(committed, f"s{s}_split")["held-out vanilla"][4])[0]
        for s in (6000, 15000)
    ]
    assert split == [0.04, 0.29]


def test_on_two_untouched_training_seeds_the_window_test_passes_the_rule_written_before_them():
    """window_typicality_untouched.md (seeds 16000 and 17000, the first form, rule in summary.md written before
    their records were read), recomputed for 16000: <= 10% false alarms on 100 fresh vanilla rollouts, >= 20 of 26
    conditions alarmed. Neither seed has a condition the per-rollout default is confidently under, so the
    too-typical side went untested there. context_energy_default_untouched2.md: the default pools to 0.970 and
    1.000."""
    committed = (FULL / "window_typicality_untouched.md").read_text()
    full, fresh = (seed_run(16000, "observation") / f"context_energy_{k}" for k in ("full", "fresh"))
    recomputed = window.run_section("s16000", full, fresh, score_only=True)
    assert recomputed.strip() == f"## s16000\n\n{section(committed, 's16000')}"
    for seed in (16000, 17000):
        rows = window_rows(committed, f"s{seed}")
        assert windows_alarmed(rows["held-out vanilla"][4])[0] <= 0.10
        conditions = sweep_conditions(rows)
        assert sum(windows_alarmed(rows[c][4])[0] == 1.0 for c in conditions) >= 20
        assert not any(rows[c][2].endswith("!") for c in conditions)
    summaries_md = (FULL / "context_energy_default_untouched2.md").read_text()
    pooled = [
        summary_rows(f"## Score summary\n{section(summaries_md, f'seed{s}')}")["context_energy_two_sided"][0][
            :5
        ]
        for s in (16000, 17000)
    ]
    assert pooled == ["0.970", "1.000"]


def window_pair(table: str, seeds: tuple[int, int], recompute: int) -> dict[int, dict]:
    """Rows of a window table of two untouched seeds, one seed's section recomputed from its records first."""
    committed = (FULL / table).read_text()
    full, fresh = (seed_run(recompute, "observation") / f"context_energy_{k}" for k in ("full", "fresh"))
    recomputed = window.run_section(f"s{recompute}", full, fresh)
    assert recomputed.strip() == f"## s{recompute}\n\n{section(committed, f's{recompute}')}"
    return {seed: window_rows(committed, f"s{seed}") for seed in seeds}


def default_rows(
    table: str, seeds: tuple[int, ...], score: str = "context_energy_two_sided"
) -> dict[int, list[str]]:
    """A score's row (by default the preset's default) of each seed's score summary in a committed table."""
    summaries_md = (FULL / table).read_text()
    return {
        seed: summary_rows(f"## Score summary\n{section(summaries_md, f'seed{seed}')}")[score]
        for seed in seeds
    }


def test_on_two_more_untouched_seeds_the_shipped_window_test_passes_its_rule():
    """window_typicality_untouched2.md (seeds 18000 and 19000, rule written before their records were read),
    recomputed for 19000: 1% and 3% false alarms on 100 fresh vanilla rollouts, 26 and 25 of 26 conditions alarmed,
    no condition confidently under per rollout. context_energy_default_untouched3.md: the default pools 0.987 and
    0.963, never confidently under 0.5."""
    rows = window_pair("window_typicality_untouched2.md", (18000, 19000), recompute=19000)
    assert [windows_alarmed(r["held-out vanilla"][4])[0] for r in rows.values()] == [0.01, 0.03]
    alarmed = [sum(windows_alarmed(r[c][4])[0] == 1.0 for c in sweep_conditions(r)) for r in rows.values()]
    assert alarmed == [26, 25]
    assert not any(r[c][2].endswith("!") for r in rows.values() for c in sweep_conditions(r))
    defaults = default_rows("context_energy_default_untouched3.md", (18000, 19000))
    assert [row[0][:5] for row in defaults.values()] == ["0.987", "0.963"]
    assert not any("!" in row[5] for row in defaults.values())


def test_on_a_third_untouched_pair_of_seeds_the_default_and_the_window_pass_their_rule():
    """window_typicality_untouched3.md and context_energy_default_untouched4.md (seeds 20000 and 21000, trained,
    swept and read after summary.md's rule was committed), recomputed for 21000: window false alarms 3% and 1%, 26
    and 25 of 26 conditions alarmed; the default pools 0.992 and 0.966, at most 20% vanilla alarms, never
    confidently under 0.5."""
    rows = window_pair("window_typicality_untouched3.md", (20000, 21000), recompute=21000)
    assert [windows_alarmed(r["held-out vanilla"][4])[0] for r in rows.values()] == [0.03, 0.01]
    alarmed = [sum(windows_alarmed(r[c][4])[0] == 1.0 for c in sweep_conditions(r)) for r in rows.values()]
    assert alarmed == [26, 25]
    defaults = default_rows("context_energy_default_untouched4.md", (20000, 21000))
    assert [row[0][:5] for row in defaults.values()] == ["0.992", "0.966"]
    assert all(int(row[1].split("%")[0]) <= 20 and "!" not in row[5] for row in defaults.values())


DEVELOPMENT_SEEDS = (6000, 9000, 10000, 11000, 12000, 13000, 14000, 15000)


def test_the_energy_slopes_predict_failure_weakly_and_the_context_terms_slope_not_at_all(tmp_path):
    """failure_slopes/seed*.md: ebvla-failure-report on the eight development seeds (calibration + vanilla choose,
    the 26 conditions held out), recomputed for seed 11000. The deployable one-check alarm's held-out AUROC: Slope
    Context 0.38-0.57 (never above chance), Slope Final 0.46-0.71, Slope Start 0.32-0.76: none reaches 0.75 throughout."""

    def deployable(report: str) -> dict[str, float]:
        rows = [line.split("|") for line in report.splitlines() if line.startswith("| all tasks | Slope")]
        return {cells[2].strip(): float(cells[8].split()[0]) for cells in rows}

    run = seed_run(11000, "observation") / "context_energy_full"
    conditions = sorted(str(p) for p in run.iterdir() if p.name.endswith(("_s3", "_s5")))
    cfg = FailureReportConfig(
        calibration=[str(run / "calibration"), str(run / "vanilla")],
        records=conditions,
        output_dir=tmp_path,
        n_bootstrap=200,
    )
    committed = {s: (FULL / "failure_slopes" / f"seed{s}.md").read_text() for s in DEVELOPMENT_SEEDS}
    assert deployable(write_failure_report(cfg)) == deployable(committed[11000])
    aurocs = {s: deployable(report) for s, report in committed.items()}
    assert all(0.37 < a["Slope Context"] < 0.58 for a in aurocs.values())
    assert max(a["Slope Final"] for a in aurocs.values()) < 0.72
    assert sum(a[m] >= 0.75 for a in aurocs.values() for m in a) == 1  # Slope Start on seed 6000, 0.762


def test_a_shift_that_moves_nothing_is_marked_confidently_wrong_only_at_the_intervals_chance_rate():
    """research/benchmarks/null_inversion_rate.py (summary.md, "How often ... by chance"): both sides drawn from one
    distribution, 8 against 40, the reports' bootstrap interval lies wholly below 0.5 about as often as a one-sided
    2.5-5% test would (3.8% at 2000 draws)."""
    null = load_benchmark("null_inversion_rate")
    rate = null.null_inversion_rate(8, 40, trials=300)
    assert 0.005 <= rate <= 0.09


paired = load_benchmark("paired_shift_diagnosis")


def test_every_shift_moves_e_c_scene_by_scene_and_the_mild_ones_less_than_scenes_differ():
    """paired_shift_diagnosis.md, recomputed for seed 12000 (the shipped default's confidently wrong sweep): 362 of
    364 sweep conditions move chunk-0 E_c one way on every pair of rollouts in one scene; every default AUROC under
    0.5 is a condition that moves it by less than 2 scene-to-scene spreads; the band refitted as shipped reproduces
    the default's AUROC; and moving the band's centre moves the confidently-wrong run."""
    committed = (FULL / "paired_shift_diagnosis.md").read_text()
    scenes, centres = paired.run_tables(
        paired.RunRecords.read(seed_run(12000, "observation") / "context_energy_full")
    )
    recomputed = paired.run_section("seed12000", scenes, centres).strip()
    assert recomputed == f"## seed12000\n\n{section(committed, 'seed12000')}"
    mild = section(committed, "Mild shifts over 14 runs")
    assert mild.startswith("Conditions whose every pair moves chunk-0 E_c one way: 362 of 364. The 346")
    assert "score at least 0.57 by the default" in mild
    mild_rows = [table_cells(line) for line in mild.splitlines() if line.startswith("| seed")]
    under_half = [(row[0], row[1]) for row in mild_rows if float(row[-1].split()[0]) < 0.5]
    assert len(under_half) == 11 and ("seed12000", "light_direction_s3") in under_half
    by_condition = {row[0]: row for row in scenes[1]}
    assert centres[0][2] == f"light_direction_s3 {by_condition['light_direction_s3'][4]}"
    summary = section(committed, "The band's centre over 14 runs").splitlines()[2:]
    runs_under = {row[0]: (row[2], row[3]) for row in map(table_cells, summary)}
    assert runs_under["trimmed 0%"] == ("seed12000", "seed12000, seed15000")
    assert [fit for fit, runs in runs_under.items() if runs == ("none", "none")] == ["trimmed 10%"]
    assert runs_under["trimmed 5%"][0] != "none" and runs_under["trimmed 20%"][0] != "none"


def test_over_calibration_draws_no_band_fit_is_safer_it_moves_the_confidently_wrong_seed():
    """paired_shift_diagnosis.md's calibration draws, recomputed for seed 12000: every run is calibrated on the same
    scenes, one of which has the highest chunk-0 E_c on all fourteen; refitted on 330 drawn calibration sets, each
    band fit leaves a condition confidently under 0.5 on 19-35 of them, the shipped fit mostly on seed 12000 and
    the trimmed and median fits mostly on seed 15000."""
    committed = (FULL / "paired_shift_diagnosis.md").read_text()
    assert "env seed 4001 has the highest chunk-0 E_c of them on 14 of 14 runs" in committed
    lines = section(committed, "The band's centre over calibration draws").splitlines()
    header = table_cells(lines[2])
    rows = {cells[0]: dict(zip(header, cells, strict=True)) for cells in map(table_cells, lines[4:])}
    recomputed = paired.draw_rows(
        {"seed12000": paired.RunRecords.read(seed_run(12000, "observation") / "context_energy_full")}
    )
    assert [row[1] for row in recomputed] == [row["seed12000"] for row in rows.values()]
    totals = {fit: int(row["all"].split()[0]) for fit, row in rows.items()}
    assert all(19 <= total <= 35 for total in totals.values())
    assert int(rows["trimmed 0%"]["seed12000"]) > int(rows["trimmed 0%"]["seed15000"])
    for fit in ("trimmed 10%", "trimmed 20%", "median / IQR"):
        assert int(rows[fit]["seed15000"]) > int(rows[fit]["seed12000"])


def test_e_c_trained_on_appearance_corruptions_fails_its_untouched_check():
    """paired_shift_diagnosis_appearance.md (recomputed for seed 22000) and context_energy_appearance_untouched.md:
    E_c trained on channel gains and state noise only (no spatial corruption) shrinks its scene-to-scene spread, but
    on the two seeds trained after summary.md's rule it fails the rule: a mild condition moves chunk-0 E_c by less than
    one scene spread on both, and the default pools under 0.90 on seed 23000."""
    committed = (FULL / "paired_shift_diagnosis_appearance.md").read_text()
    scenes, centres = paired.run_tables(
        paired.RunRecords.read(seed_run(22000, "observation_appearance") / "context_energy_full")
    )
    recomputed = paired.run_section("seed22000", scenes, centres).strip()
    assert recomputed == f"## seed22000\n\n{section(committed, 'seed22000')}"
    for seed in (22000, 23000):
        rows = [
            table_cells(line)
            for line in section(committed, f"seed{seed}").splitlines()
            if line.startswith("| ")
        ]
        mild = [
            abs(float(r[1].split()[0])) for r in rows if r[0] in ("blur_s3", "light_direction_s3", "noise_s3")
        ]
        assert len(mild) == 3 and min(mild) < 1, seed
    defaults = default_rows("context_energy_appearance_untouched.md", (22000, 23000))
    assert [row[0][:5] for row in defaults.values()] == ["0.917", "0.896"]
    assert not any("!" in row[5] for row in defaults.values())


def test_the_cheaper_context_energy_passes_its_rule_with_the_raised_starting_energy():
    """context_energy_r1_fast_b18.md and paired_shift_diagnosis_r1_fast_b18.md (the same variant on the preset with
    `energy_bias_init=18`; summary.md, "A cheaper E_c with the raised starting energy", rule written before the seeds
    ran), recomputed for seed 25000: no condition moves chunk-0 E_c down by a scene spread; `context_phase_energy`
    pools 0.973 on both seeds (at most 0.03 below observation_r1's 0.962 and 0.984), with at most 20 % held-out
    alarms, nothing confidently under 0.5 and every success-cutting shift at 1.000: light_direction 3, still near
    0.5, no longer costs success."""
    run = seed_run(25000, "observation_r1_fast_b18") / "context_energy_full"
    summaries_md = (FULL / "context_energy_r1_fast_b18.md").read_text()
    assert summaries.score_summary(run) == section(summaries_md, "seed25000")
    committed = (FULL / "paired_shift_diagnosis_r1_fast_b18.md").read_text()
    scenes, centres = paired.run_tables(paired.RunRecords.read(run), "context_phase_energy")
    assert (
        paired.run_section("seed25000", scenes, centres, "context_phase_energy").strip()
        == f"## seed25000\n\n{section(committed, 'seed25000')}"
    )
    rows = default_rows("context_energy_r1_fast_b18.md", (24000, 25000), "context_phase_energy")
    for seed, reference in ((24000, 0.962), (25000, 0.984)):
        moves = {
            r[0]: float(r[1].split()[0])
            for r in (
                table_cells(line)
                for line in section(committed, f"seed{seed}").splitlines()
                if line.startswith("| ")
            )
            if r[0].endswith(("_s3", "_s5"))
        }
        assert len(moves) == 26 and min(moves.values()) > -1, seed
        pooled, alarms, inverted, cutting = (
            float(rows[seed][0].split()[0]),
            rows[seed][1],
            rows[seed][5],
            rows[seed][7],
        )
        assert pooled == 0.973 and pooled >= reference - 0.03, seed
        assert (
            int(alarms.split("%")[0]) <= 20 and "!" not in inverted and float(cutting.split("min ")[1]) == 1.0
        ), seed
        cutting_conditions = (
            section(summaries_md, f"seed{seed}").split("below vanilla's success (")[1].split(")")[0]
        )
        assert (
            "light_direction 3" not in cutting_conditions.split(", ")
            and "light_direction 3 0.5" in rows[seed][4]
        )


R1_DESIGN, R1_UNTOUCHED = (12000, 15000), (24000, 25000)


def test_e_c_flat_at_the_data_rises_under_every_shift_and_its_one_sided_score_passes_the_untouched_check():
    """paired_shift_diagnosis_r1.md (recomputed for seed 24000) and context_energy_r1.md (recomputed for seed 25000):
    E_c trained with the gradient penalty (`observation_r1`) rises under every sweep shift; no condition lowers it by
    a scene spread on any of the four seeds. On the two seeds trained after summary.md's rule,
    `context_phase_energy` pools >= 0.90 with <= 20% vanilla alarms, sees every success-cutting shift (>= 0.85) and
    is confidently under 0.5 nowhere; the two-sided form was, on design seed 15000's blur 3."""
    committed = (FULL / "paired_shift_diagnosis_r1.md").read_text()
    scenes, centres = paired.run_tables(
        paired.RunRecords.read(seed_run(24000, "observation_r1") / "context_energy_full")
    )
    assert (
        paired.run_section("seed24000", scenes, centres).strip()
        == f"## seed24000\n\n{section(committed, 'seed24000')}"
    )
    for seed in R1_DESIGN + R1_UNTOUCHED:
        rows = [
            table_cells(line)
            for line in section(committed, f"seed{seed}").splitlines()
            if line.startswith("| ")
        ]
        moves = {r[0]: float(r[1].split()[0]) for r in rows if r[0].endswith(("_s3", "_s5"))}
        assert len(moves) == 26 and min(moves.values()) > -1, seed
    summaries_md = (FULL / "context_energy_r1.md").read_text()
    recomputed = summaries.score_summary(seed_run(25000, "observation_r1") / "context_energy_full")
    assert recomputed == section(summaries_md, "seed25000")
    one_sided = default_rows("context_energy_r1.md", R1_DESIGN + R1_UNTOUCHED, "context_phase_energy")
    for seed, row in one_sided.items():
        pooled, alarms, inverted, cutting = float(row[0].split()[0]), row[1], row[5], row[7]
        assert pooled >= 0.90 and int(alarms.split("%")[0]) <= 20, seed
        assert "!" not in inverted and float(cutting.split("min ")[1]) >= 0.85, seed
    two_sided = default_rows("context_energy_r1.md", R1_DESIGN)
    assert "blur 3 0.22!" in two_sided[15000][5]


def test_on_fresh_rollouts_of_the_design_seeds_near_misses_the_one_sided_score_stays_above_chance():
    """context_energy_r1_fresh.md, recomputed for seed 15000: 24 fresh rollouts of each mild shift against 100 fresh
    vanilla ones (the protocol of context_energy_fresh.md); `context_phase_energy` scores every one above 0.5 on both
    design seeds, where the two-sided form is confidently under on 15000's light_direction 3."""
    committed = (FULL / "context_energy_r1_fresh.md").read_text()
    fresh = seed_run(15000, "observation_r1") / "context_energy_fresh"
    calibration = seed_run(15000, "observation_r1") / "context_energy_full" / "calibration"
    assert summaries.score_summary(fresh, calibration=calibration) == section(committed, "seed15000_fresh")
    for run in ("seed12000_fresh", "seed15000_fresh"):
        rows = summary_rows(f"## Score summary\n{section(committed, run)}")
        assert rows["context_phase_energy"][5] == "none", run
        assert float(rows["context_phase_energy"][4].split()[-1]) > 0.55, run
    assert (
        "light_direction 3 0.34!"
        in summary_rows(f"## Score summary\n{section(committed, 'seed15000_fresh')}")[
            "context_energy_two_sided"
        ][5]
    )


def test_for_the_flat_e_c_no_calibration_draw_leaves_the_one_sided_score_confidently_wrong():
    """paired_shift_diagnosis_r1_one_sided.md (`--score=context_phase_energy`), recomputed for seed 15000, where the
    two-sided form is confidently wrong: refitted on 30 calibration sets drawn from each seed's fresh vanilla
    rollouts, by every band fit, no set leaves a sweep condition confidently under 0.5 on any of the four seeds
    (the preset's two-sided default: 29 of 330 sets)."""
    committed = (FULL / "paired_shift_diagnosis_r1_one_sided.md").read_text()
    one_sided = paired.ONE_SIDED_SCORE
    run = paired.RunRecords.read(seed_run(15000, "observation_r1") / "context_energy_full")
    scenes, centres = paired.run_tables(run, one_sided)
    recomputed = paired.run_section("seed15000", scenes, centres, one_sided).strip()
    assert recomputed == f"## seed15000\n\n{section(committed, 'seed15000')}"
    assert [row[1] for row in paired.draw_rows({"seed15000": run}, one_sided)] == ["0"] * 5
    lines = section(committed, "The band's centre over calibration draws").splitlines()
    assert [table_cells(line)[5] for line in lines[4:]] == ["0 of 120"] * 5
    two_sided = (FULL / "paired_shift_diagnosis.md").read_text()
    assert "| trimmed 0% |" in two_sided and "| 29 of 330 |" in section(
        two_sided, "The band's centre over calibration draws"
    )


ceiling = load_benchmark("outcome_ceiling")


def ceiling_row(committed: str, run: str) -> list[str]:
    (line,) = [line for line in committed.splitlines() if line.startswith(f"| {run} |")]
    return table_cells(line)


@pytest.mark.parametrize(
    ("table", "variant", "score", "seed"),
    [
        ("outcome_ceiling_r1.md", "observation_r1", "context_phase_energy", 25000),
        ("outcome_ceiling_preset.md", "observation", "context_energy_two_sided", 17000),
    ],
)
def test_failed_vs_successful_sits_under_what_knowing_each_conditions_failure_rate_reaches(
    table, variant, score, seed
):
    """outcome_ceiling_{r1,preset}.md, recomputed for one seed each: pooled over held-out vanilla and every condition,
    a perfect OOD detector ranks failures over successes at 0.45-0.58 and each condition's own failure rate at
    0.59-0.81 (under the 0.75 target on 13 of 14 preset seeds and 3 of 4 flat-E_c seeds), while the scene's failure
    rate in its other rollouts reaches 0.66-0.96, above the condition's on 16 of 18 seeds: the sweep's outcome is
    largely the scene's."""
    committed = (FULL / table).read_text()
    rollouts = ceiling.scored_rollouts(seed_run(seed, variant) / "context_energy_full", score)
    assert ceiling.run_row(f"seed{seed}", rollouts) == ceiling_row(committed, f"seed{seed}")
    rows = [table_cells(line) for line in committed.splitlines() if line.startswith("| seed")]
    perfect, by_condition, by_scene = ([float(row[c].split()[0]) for row in rows] for c in (3, 4, 5))
    assert max(perfect) < 0.6 and all(p < c for p, c in zip(perfect, by_condition, strict=True))
    scene_above = sum(s > c for c, s in zip(by_condition, by_scene, strict=True))
    met = sum(c >= 0.75 for c in by_condition)
    assert (len(rows), scene_above, met) == ((4, 4, 1) if variant == "observation_r1" else (14, 12, 1))


def test_restart_spread_tells_the_failed_scenes_only_once_the_arm_stalls():
    """summary.md, "Does the landscape know the hard scenes?": eight more chains per chunk on seed 12000's flat-E_c
    checkpoint, in the sweep's 40 vanilla scenes (the same outcomes): the chains' spread ranks failed over
    successful rollouts at 0.63 over the first 3 chunks, 0.89 over the whole episode."""
    run = seed_run(12000, "observation_r1")
    spread = load_episodes([str(run / "restart_spread_vanilla")])
    sweep = {
        e[0].seed: e[0].success
        for e in load_episodes([str(run / "context_energy_full" / "vanilla")]).values()
    }
    assert {e[0].seed: e[0].success for e in spread.values()} == sweep
    succeeded = np.array([e[0].success for e in spread.values()])
    assert succeeded.sum() == 28

    def by_spread(chunks):
        scores = np.array([np.mean([r.restart_spread for r in e[:chunks]]) for e in spread.values()])
        return format_auroc(scores[succeeded], scores[~succeeded], 1000, 0)

    assert (by_spread(1), by_spread(3), by_spread(None)) == (
        "0.497 [0.312, 0.673]",
        "0.631 [0.414, 0.833]",
        "0.887 [0.795, 0.967]",
    )


def test_ten_times_the_gradient_penalty_brings_back_a_shift_that_lowers_e_c():
    """summary.md, "A stronger penalty, gamma = 1.0": on design seed 15000 light direction 3 lowers chunk-0 E_c in all
    eight paired scenes by a scene spread and `context_phase_energy` is confidently under 0.5 there (0.28), where
    gamma = 0.1 leaves it above (0.53): the preset keeps 0.1."""
    committed = (FULL / "context_energy_r1g1.md").read_text()
    run = seed_run(15000, "observation_r1g1") / "context_energy_full"
    assert summaries.score_summary(run) == section(committed, "seed15000")
    rows = summary_rows(f"## Score summary\n{section(committed, 'seed15000')}")
    assert rows["context_phase_energy"][5] == "blur 3 0.46, light_direction 3 0.28!"
    _, scenes, _ = paired.scene_rows(paired.RunRecords.read(run), paired.ONE_SIDED_SCORE)
    (light,) = [row for row in scenes if row[0] == "light_direction_s3"]
    assert light[1].startswith("-1.00") and light[2] == "8/8"


def test_on_fresh_rollouts_of_the_untouched_seeds_near_misses_mild_blur_is_above_chance():
    """context_energy_r1_fresh_untouched.md, recomputed for seed 24000 (whose sweep put blur 3 at 0.45): on 24 fresh
    rollouts against 100 fresh vanilla ones `context_phase_energy` scores blur 3 0.74 and light direction 3 0.77;
    seed 25000's blur 3 0.62."""
    committed = (FULL / "context_energy_r1_fresh_untouched.md").read_text()
    run = seed_run(24000, "observation_r1")
    recomputed = summaries.score_summary(
        run / "context_energy_fresh", calibration=run / "context_energy_full" / "calibration"
    )
    assert recomputed == section(committed, "seed24000_fresh")
    for name, worst in (("seed24000_fresh", "blur 3 0.739"), ("seed25000_fresh", "blur 3 0.621")):
        rows = summary_rows(f"## Score summary\n{section(committed, name)}")
        assert (rows["context_phase_energy"][4], rows["context_phase_energy"][5]) == (worst, "none")


def default_monitor_row(summaries_table: str, seed: str, pooled: str, worst: str) -> list[str]:
    """The `context_phase_energy` row of a seed's score summary, checked against the OOD targets as reported: its
    pooled AUROC and worst condition, none inverted, every success-cutting condition at 1.000."""
    rows = summary_rows(f"## Score summary\n{section(summaries_table, seed)}")
    phase = rows["context_phase_energy"]
    assert (phase[0].split()[0], phase[4], phase[5], phase[7].split()[0]) == (pooled, worst, "none", "1.000")
    return phase


def test_a_stronger_policy_fails_in_the_shifts_and_the_monitor_alarms_on_benign_ones_too():
    """summary.md, "A stronger policy": three times the demonstrations and training (seeds 26000, 27000, flat E_c).
    Vanilla fails 0-4 of 40, so each condition's failure rate now ranks failed over successful rollouts at 0.91-0.93;
    `context_phase_energy` sees every shift (pooled 0.999 / 1.000, worst 0.963 / 0.994, none inverted) and alarms on
    all of them, the harmless ones too, so it tells failed from successful at 0.68 only, under the 0.75 target."""
    committed = (FULL / "outcome_ceiling_r1_strong.md").read_text()
    rollouts = ceiling.scored_rollouts(
        seed_run(26000, "observation_r1_strong") / "context_energy_full", "context_phase_energy"
    )
    assert ceiling.run_row("seed26000", rollouts) == ceiling_row(committed, "seed26000")
    for seed, score, by_condition in (("seed26000", "0.677", "0.929"), ("seed27000", "0.681", "0.912")):
        row = ceiling_row(committed, seed)
        assert (row[2].split()[0], row[4].split()[0]) == (score, by_condition)
    summaries_table = (FULL / "context_energy_r1_strong.md").read_text()
    run = seed_run(27000, "observation_r1_strong") / "context_energy_full"
    assert summaries.score_summary(run) == section(summaries_table, "seed27000")
    for seed, pooled, worst in (
        ("seed26000", "0.999", "blur 3 0.963"),
        ("seed27000", "1.000", "blur 3 0.994"),
    ):
        phase = default_monitor_row(summaries_table, seed, pooled, worst)
        assert float(phase[8].split()[0]) < 0.75


def first_chunk_z(
    run: Path, folders: list[str], score_class, first_chunks: int = 3
) -> tuple[list, np.ndarray]:
    """Each rollout's z_t over its first chunks (the signed components of a phase score, before a two-sided score
    takes a magnitude), against the run's calibration rollouts at each chunk index, and whether it failed."""
    from lerobot_policy_ebvla.monitoring.baselines import episode_readout, vanilla_rollouts
    from lerobot_policy_ebvla.runtime.scores import ChunkInputs

    score = score_class.fit(vanilla_rollouts(load_episodes([str(run / "calibration")])))
    episodes = load_episodes([str(run / folder) for folder in folders]).values()
    z = [score.components(ChunkInputs.of(episode_readout(e[:first_chunks])))[:, 0] for e in episodes]
    return z, np.array([not e[0].success for e in episodes])


def test_the_heads_energy_tells_failed_from_successful_rollouts_on_two_untouched_seeds():
    """summary.md, "A failure score from the head's energy": the rule (commit 2c9fa06) named
    `head_energy_two_sided` and >= 0.75 failed vs successful on both untouched seeds 28000 and 29000 (first 3
    chunks, 248 held-out rollouts each): 0.870 and 0.813, where the OOD default `context_phase_energy` scores 0.658
    and 0.650 and the raw final energy 0.717 and 0.777. Its alarms at the calibration's threshold catch 94% / 82% of
    the failed rollouts, on 31% / 28% of the successful ones. The OOD targets hold on both seeds with the default."""
    tables = {
        score: (FULL / f"outcome_ceiling_r1_strong{suffix}.md").read_text()
        for score, suffix in (
            ("head_energy_two_sided", "_head"),
            ("context_phase_energy", ""),
            ("final_energy", "_final"),
        )
    }
    run = seed_run(28000, "observation_r1_strong") / "context_energy_full"
    rollouts = ceiling.scored_rollouts(run, "head_energy_two_sided")
    assert ceiling.run_row("seed28000", rollouts) == ceiling_row(tables["head_energy_two_sided"], "seed28000")
    expected = {
        "seed26000": ("0.841", "0.677", "0.746"),
        "seed27000": ("0.824", "0.681", "0.715"),
        "seed28000": ("0.870", "0.658", "0.717"),
        "seed29000": ("0.813", "0.650", "0.777"),
    }
    for seed, figures in expected.items():
        got = tuple(ceiling_row(tables[score], seed)[2].split()[0] for score in tables)
        assert got == figures, seed
    # Over whole episodes the head's score is weaker on the untouched seeds (0.661, 0.642; the default 0.38-0.40).
    whole = (FULL / "outcome_ceiling_r1_strong_head_whole.md").read_text()
    rollouts = ceiling.scored_rollouts(run, "head_energy_two_sided", first_chunks=None)
    assert ceiling.run_row("seed28000", rollouts) == ceiling_row(whole, "seed28000")
    assert ceiling_row(whole, "seed29000")[2].split()[0] == "0.642"
    for seed, alarms in (
        ("seed28000", "49/52 (94%) / 60/196 (31%)"),
        ("seed29000", "41/50 (82%) / 56/198 (28%)"),
    ):
        assert ceiling_row(tables["head_energy_two_sided"], seed)[-1] == alarms
    from lerobot_policy_ebvla.runtime.scores import HeadEnergyTwoSided

    run = seed_run(29000, "observation_r1_strong") / "context_energy_full"
    held_out = [p.name for p in sorted(run.iterdir()) if p.is_dir() and p.name != "calibration"]
    z, failed = first_chunk_z(run, held_out, HeadEnergyTwoSided)
    mean_abs = np.array(
        [np.abs(rollout).mean() for rollout in z]
    )  # the mean |z_t| form beside the shipped one
    assert format_auroc(mean_abs[~failed], mean_abs[failed], 1000, 0) == "0.858 [0.813, 0.906]"
    summaries_table = (FULL / "context_energy_r1_strong_untouched.md").read_text()
    for seed, pooled, worst in (
        ("seed28000", "0.979", "blur 3 0.553"),
        ("seed29000", "0.991", "blur 3 0.778"),
    ):
        default_monitor_row(summaries_table, seed, pooled, worst)


def median_mean_z(run: Path, condition: str, score_class) -> float:
    """The median over a condition's rollouts of their first 3 chunks' mean z_t."""
    z, _ = first_chunk_z(run, [condition], score_class)
    return float(np.median([rollout.mean() for rollout in z]))


def test_the_heads_energy_leaves_the_band_under_the_harmful_shifts_and_e_c_under_all():
    """research/docs/energy_study.md section 8.14's table, a few cells each way: E_c's z follows how far the image moved
    (a retextured table, no failure, above a moved camera), E_head's leaves the band only under the shifts that cut
    success, below it under seed 27000's fov 5."""
    from lerobot_policy_ebvla.runtime.scores import ContextPhaseEnergy, HeadEnergyTwoSided

    for condition, seed, context_z, head_z in (
        ("blank_s3", 26000, "330", "3.05"),
        ("table_texture_s5", 26000, "341", "-0.78"),
        ("pose_s5", 27000, "200", "0.60"),
        ("fov_s5", 27000, "184", "-1.87"),
    ):
        run = seed_run(seed, "observation_r1_strong") / "context_energy_full"
        assert f"{median_mean_z(run, condition, ContextPhaseEnergy):.0f}" == context_z, condition
        assert f"{median_mean_z(run, condition, HeadEnergyTwoSided):.2f}" == head_z, condition


def test_the_cheaper_context_energy_fails_its_rule_on_one_seed_of_two():
    """context_energy_r1_fast.md (E_c's encoder at 32 px, the penalty on one step in 4; rule in summary.md, "A
    cheaper E_c", written before the seeds ran), recomputed for seed 24000 from its records: `context_phase_energy`
    pools 0.968 and 0.983 with no condition confidently under 0.5 and at most 20 % held-out alarms, but seed 24000's
    success-cutting light_direction 3 scores 0.584, under the rule's 0.85, so the preset keeps its 64 px E_c."""
    summaries_md = (FULL / "context_energy_r1_fast.md").read_text()
    recomputed = summaries.score_summary(seed_run(24000, "observation_r1_fast") / "context_energy_full")
    assert recomputed == section(summaries_md, "seed24000")
    rows = default_rows("context_energy_r1_fast.md", (24000, 25000), "context_phase_energy")
    cutting_min = {}
    for seed, row in rows.items():
        pooled, alarms, inverted, cutting = float(row[0].split()[0]), row[1], row[5], row[7]
        assert pooled >= 0.90 and int(alarms.split("%")[0]) <= 20 and "!" not in inverted, seed
        cutting_min[seed] = float(cutting.split("min ")[1])
    assert cutting_min == {24000: 0.584, 25000: 1.0}
    assert "light_direction 3 0.584" in rows[24000][4]
