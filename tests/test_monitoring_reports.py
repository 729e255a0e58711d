"""The report entry points on synthetic `energy_records.jsonl` files: held-out protocol, baselines, figures."""

import dataclasses
import json
import math

import numpy as np
import pytest

from lerobot_policy_ebvla.monitoring.protocol import check_held_out
from lerobot_policy_ebvla.monitoring.records import (
    ENERGY_RECORDS_FILENAME,
    EnergyRecord,
    load_episodes,
    write_energy_records,
)
from lerobot_policy_ebvla.monitoring.scores import episode_scores
from lerobot_policy_ebvla.runtime.calibration import OOD_CALIBRATION_FILENAME, OODCalibration
from lerobot_policy_ebvla.runtime.failure_alarm import FAILURE_ALARM_FILENAME, FailureAlarm
from lerobot_policy_ebvla.scripts import failure_report, landscape, ood_report

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def rollouts(
    n, level, perturbation="none", severity=0.0, seed=0, n_chunks=6, fail_every=3, features=False, first=0
):
    """n episodes whose final energies hover around `level`; every `fail_every`-th one fails with rising energy.

    Episode i is seeded 1000 * seed + i, as a run started at that seed would be: runs of other `seed`s are
    held out of each other. With `features`, each chunk also carries a restart spread and a 4-d context feature
    centred on `level`.
    """
    rng = np.random.default_rng(seed)
    records = []
    for episode in range(first, first + n):
        failed = episode % fail_every == 0
        for chunk in range(n_chunks):
            trend = 0.3 * chunk if failed else 0.0
            record = EnergyRecord(
                episode_index=episode,
                chunk_index=chunk,
                env_step=8 * chunk,
                initial_energy=float(level + 2 + rng.normal(0, 0.2)),
                final_energy=float(level + trend + rng.normal(0, 0.2)),
                success=not failed,
                task="reach",
                seed=1000 * seed + episode,
                perturbation=perturbation,
                severity=severity,
            )
            if features:
                record = dataclasses.replace(
                    record,
                    restart_spread=float(abs(rng.normal(0.1 * level, 0.05))),
                    context_feature=rng.normal(level, 1.0, size=4).astype(np.float32),
                )
            records.append(record)
    return records


def write(tmp_path, name, records):
    return write_energy_records(tmp_path / name / ENERGY_RECORDS_FILENAME, records).parent


@pytest.fixture
def record_dirs(tmp_path):
    """Calibration and held-out vanilla rollouts (other seeds), and perturbed ones at two severities."""
    calibration = write(tmp_path, "vanilla_a", rollouts(12, 5.0, seed=10, features=True))
    vanilla = write(tmp_path, "vanilla_b", rollouts(12, 5.0, seed=11, features=True))
    ood = write(
        tmp_path,
        "camera",
        rollouts(10, 6.0, "camera", 1.0, seed=1, features=True)
        + rollouts(10, 7.0, "camera", 2.0, seed=2, fail_every=2, features=True),
    )
    return calibration, vanilla, ood


def ood_args(calibration, vanilla, ood, out):
    return [
        f"--calibration=[{calibration}]",
        f"--vanilla=[{vanilla}]",
        f"--ood=[{ood}]",
        f"--output_dir={out}",
    ]


def test_ood_report_prints_the_held_out_tables_with_intervals_and_baselines(record_dirs, tmp_path, capsys):
    ood_report.main([*ood_args(*record_dirs, tmp_path / "out"), "--n_bootstrap=200"])
    out = capsys.readouterr().out
    assert "(held-out)" in out and "IN-SAMPLE" not in out
    assert "12 held-out vanilla rollouts" in out and "20 perturbed rollouts" in out
    for section in ("## Calibration", "## Energy vs success drop", "## AUROC [bootstrap 95% interval]"):
        assert section in out
    assert "## Table III: camera 1" in out and "## Table III: camera 2" in out
    whole_episode = out.split("## Table III on the first")[0]  # the first-3-chunk tables follow
    assert whole_episode.count("| Multiplier |") == 3  # all perturbations, and each severity
    # Every baseline sits beside the final energy in the AUROC table and in every Table III.
    assert (
        "| Condition | Episodes | final_energy | phase_energy | initial_energy | restart_spread | context_distance "
        "| context_knn |" in out
    )
    assert whole_episode.count("Bal. Acc. context_knn") == 3
    assert whole_episode.count("conf. α=5.0%") == 3


def test_ood_report_puts_the_success_drop_beside_the_energy_shift(record_dirs, tmp_path, capsys):
    ood_report.main(ood_args(*record_dirs, tmp_path / "out"))
    out = capsys.readouterr().out
    # Vanilla: 8 of 12 succeed (66.7%); camera 2 fails every other episode: 50.0%, a 16.7-point drop.
    success_table = out.split("## Energy vs success drop")[1].split("##")[0]
    (row,) = [line for line in success_table.splitlines() if line.startswith("| camera 2 |")]
    cells = [c.strip() for c in row.split("|")[1:-1]]
    assert cells[1:4] == ["10", "50.0%", "+16.7 pts"]
    assert float(cells[4]) > 1.5  # mean score ~7 against ~5.2
    low, high = (float(x) for x in cells[6].split("[")[1].rstrip("]").split(","))
    assert low <= float(cells[6].split()[0]) <= high


def test_ood_report_refuses_an_in_sample_report(record_dirs, tmp_path):
    calibration, _, ood = record_dirs
    with pytest.raises(ValueError, match="in_sample"):
        ood_report.main(ood_args(calibration, calibration, ood, tmp_path / "out"))


def test_ood_report_refusal_sees_through_other_spellings_of_a_path(record_dirs, tmp_path, monkeypatch):
    calibration, _, ood = record_dirs
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ValueError, match="in_sample"):
        ood_report.main(ood_args(calibration, f"./{calibration.name}/{ENERGY_RECORDS_FILENAME}", ood, "out"))


def test_ood_report_refuses_calibration_rollouts_that_replay_the_reported_seeds(record_dirs, tmp_path):
    calibration, _, ood = record_dirs
    # The same seeds run again into another folder: the files differ, the episodes do not.
    rerun = write(tmp_path, "vanilla_rerun", rollouts(12, 5.0, seed=10, features=True))
    with pytest.raises(ValueError, match=r"share 12 episode seed.*seeds 10000, 10001.*--in_sample=true"):
        ood_report.main(ood_args(calibration, rerun, ood, tmp_path / "out"))


def test_ood_report_without_calibration_rollouts_is_in_sample(record_dirs, tmp_path):
    _, vanilla, ood = record_dirs
    with pytest.raises(ValueError, match="no `--calibration`"):
        ood_report.main([f"--vanilla=[{vanilla}]", f"--ood=[{ood}]", f"--output_dir={tmp_path}"])


def test_ood_report_labels_an_explicit_in_sample_report(record_dirs, tmp_path, capsys):
    calibration, _, ood = record_dirs
    ood_report.main([*ood_args(calibration, calibration, ood, tmp_path / "out"), "--in_sample=true"])
    assert "# Energy-based OOD detection (IN-SAMPLE" in capsys.readouterr().out


def test_ood_report_saves_the_figures_and_markdown(record_dirs, tmp_path):
    out_dir = tmp_path / "out"
    ood_report.main(ood_args(*record_dirs, out_dir))
    for name in ("roc_curve.png", "roc_baselines.png", "energy_histogram.png"):
        assert (out_dir / name).read_bytes()[:8] == PNG_MAGIC
    assert "| Multiplier |" in (out_dir / "ood_report.md").read_text()


def test_ood_report_accepts_glob_patterns(record_dirs, tmp_path, capsys):
    calibration, vanilla, _ = record_dirs
    ood_report.main(ood_args(calibration, vanilla, tmp_path / "cam*", tmp_path / "out"))
    assert "20 perturbed rollouts" in capsys.readouterr().out


def test_ood_report_without_baseline_data_reports_the_energies_only(tmp_path, capsys):
    calibration = write(tmp_path, "a", rollouts(6, 5.0, seed=3))
    vanilla = write(tmp_path, "b", rollouts(6, 5.0, seed=4))
    ood = write(tmp_path, "c", rollouts(6, 6.0, "camera", 1.0))
    ood_report.main(ood_args(calibration, vanilla, ood, tmp_path / "out"))
    out = capsys.readouterr().out
    assert (
        "| Condition | Episodes | final_energy | phase_energy | initial_energy |\n" in out
        and "knn" not in out
    )


def test_ood_report_calibrates_a_checkpoint_on_the_calibration_rollouts(record_dirs, tmp_path):
    checkpoint = tmp_path / "pretrained_model"
    checkpoint.mkdir()
    args = [
        *ood_args(*record_dirs, tmp_path / "out"),
        f"--calibrate_to={checkpoint}",
        "--k=0.5",
        "--score=final_energy",
    ]
    ood_report.main([*args, "--threshold_rule=conformal", "--false_alarm_rate=0.1"])
    calibration = OODCalibration.load(checkpoint)
    assert calibration.k == 0.5 and calibration.n_rollouts == 12
    assert calibration.rule == "conformal" and calibration.false_alarm_rate == 0.1
    assert calibration.threshold == calibration.conformal_threshold
    # T is of window scores over the first 3 chunks (standardized: mean near 0), their window of raw energies.
    window = calibration.window
    assert window.chunks == 3 and all(4.5 < m < 5.5 for m in window.running.mean)
    assert abs(calibration.mu_v) < 2.0


def test_ood_report_refuses_to_overwrite_a_calibration(record_dirs, tmp_path):
    checkpoint = tmp_path / "pretrained_model"
    checkpoint.mkdir()
    (checkpoint / OOD_CALIBRATION_FILENAME).write_text(json.dumps({"mu_v": 1.0, "sigma_v": 0.0}))
    args = [*ood_args(*record_dirs, tmp_path / "out"), f"--calibrate_to={checkpoint}"]
    with pytest.raises(FileExistsError):
        ood_report.main(args)
    assert OODCalibration.load(checkpoint).mu_v == 1.0
    ood_report.main([*args, "--overwrite_calibration=true"])
    assert OODCalibration.load(checkpoint).mu_v != 1.0


def test_ood_report_rejects_perturbed_rollouts_given_as_vanilla(record_dirs, tmp_path):
    calibration, _, ood = record_dirs
    with pytest.raises(ValueError, match="`--vanilla` must hold vanilla rollouts only.*camera 1"):
        ood_report.main(ood_args(calibration, ood, ood, tmp_path / "out"))


def test_ood_report_needs_perturbed_rollouts(record_dirs, tmp_path):
    calibration, vanilla, _ = record_dirs
    with pytest.raises(ValueError, match="--ood"):
        ood_report.main([f"--calibration=[{calibration}]", f"--vanilla=[{vanilla}]"])


def test_ood_report_handles_a_diverged_rollout(tmp_path):
    calibration = write(tmp_path, "a", rollouts(4, 5.0, seed=3))
    vanilla = write(tmp_path, "b", rollouts(4, 5.0, seed=4))
    records = rollouts(4, 6.0, "camera", 1.0)
    records[-1] = EnergyRecord(3, 5, 40, math.inf, math.inf, False, "reach", 3, "camera", 1.0)
    ood = write(tmp_path, "c", records)
    ood_report.main(ood_args(calibration, vanilla, ood, tmp_path / "out"))
    assert (tmp_path / "out" / "energy_histogram.png").exists()


def section(out, title):
    return out.split(f"## {title}")[1].split("\n## ")[0]


def test_ood_report_prints_each_scores_first_chunk_auroc_beside_the_whole_episodes(
    record_dirs, tmp_path, capsys
):
    ood_report.main([*ood_args(*record_dirs, tmp_path / "out"), "--first_chunks=[1,2]", "--n_bootstrap=50"])
    first = section(capsys.readouterr().out, "Detection on the first chunks")
    assert "Held-out vanilla rollouts (the negatives): 12, success 8/12 (66.7%)." in first
    assert "### camera 2: 10 perturbed rollouts, success 5/10 (50.0%)" in first
    assert first.count("| Score | first 1 chunk | first 2 chunks | whole episode |") == 3
    assert first.count("| context_knn | ") == 3


def test_ood_report_first_chunk_auroc_sees_only_the_first_chunks(tmp_path, capsys):
    # Perturbed rollouts look vanilla for 3 chunks, then their energy jumps: only later chunks separate them.
    late = [
        dataclasses.replace(r, final_energy=r.final_energy + 10 * (r.chunk_index >= 3))
        for r in rollouts(8, 5.0, "camera", 1.0, seed=6)
    ]
    dirs = [write(tmp_path, "a", rollouts(8, 5.0, seed=3)), write(tmp_path, "b", rollouts(8, 5.0, seed=4))]
    ood_report.main([*ood_args(*dirs, write(tmp_path, "c", late), tmp_path / "out"), "--first_chunks=[3,4]"])
    first = section(capsys.readouterr().out, "Detection on the first chunks")
    (row,) = [
        line for line in first.split("### camera 1")[1].splitlines() if line.startswith("| final_energy |")
    ]
    first_3, first_4, whole = (float(cell.split()[0]) for cell in row.split("|")[2:5])
    assert first_3 < 0.9 and first_4 == whole == 1.0


def test_ood_report_states_mu_sigma_auroc_and_counts_beside_each_table_iii(record_dirs, tmp_path, capsys):
    ood_report.main(ood_args(*record_dirs, tmp_path / "out"))
    table = section(capsys.readouterr().out, "Table III: camera 2")
    fit = OODCalibration.fit(episode_scores(load_episodes([record_dirs[0]]), "final_energy"))
    assert f"(mu_v = {fit.mu_v:.3f}, sigma_v = {fit.sigma_v:.3f}, from 12 calibration rollouts only)" in table
    assert "(bootstrap 95% interval); n vanilla = 12, n OOD = 10." in table


def test_ood_report_prints_table_iii_on_the_first_chunks_calibrated_on_their_first_chunks(
    record_dirs, tmp_path, capsys
):
    ood_report.main([*ood_args(*record_dirs, tmp_path / "out"), "--table_iii_first_chunks=2"])
    out = capsys.readouterr().out
    first_2 = load_episodes([record_dirs[0]])
    fit = OODCalibration.fit(episode_scores(first_2, "final_energy", first_chunks=2))
    table = section(out, "Table III, first 2 chunks: camera 1")
    assert f"(mu_v = {fit.mu_v:.3f}, sigma_v = {fit.sigma_v:.3f}," in table
    assert out.count("## Table III, first 2 chunks: ") == 3  # all perturbations, and each severity


def test_ood_report_leaves_the_first_chunk_table_iii_out_when_asked(record_dirs, tmp_path, capsys):
    ood_report.main([*ood_args(*record_dirs, tmp_path / "out"), "--table_iii_first_chunks=0"])
    assert "first 3 chunks:" not in capsys.readouterr().out


def test_ood_report_refuses_to_calibrate_a_score_the_policy_cannot_compute(record_dirs, tmp_path):
    with pytest.raises(ValueError, match="`score`"):
        ood_report.main([*ood_args(*record_dirs, tmp_path / "out"), "--score=knn"])


# ebvla-failure-report


def failure_dirs(tmp_path):
    calibration = write(
        tmp_path, "cal", rollouts(12, 5.0, seed=5) + rollouts(9, 5.0, seed=6, n_chunks=4, first=12)
    )
    held_out = write(tmp_path, "held", rollouts(12, 5.0, seed=7))
    return calibration, held_out


def test_failure_report_chooses_on_calibration_and_reports_held_out(tmp_path, capsys):
    calibration, held_out = failure_dirs(tmp_path)
    args = [f"--calibration=[{calibration}]", f"--records=[{held_out}]", "--max_step=6", "--max_window=4"]
    failure_report.main([*args, f"--output_dir={tmp_path / 'out'}"])
    out = capsys.readouterr().out
    assert "(held-out)" in out and "### Slope Final" in out and "### Slope Start" in out
    assert "12 held-out episodes (4 failed)" in out
    assert out.count("| Bal. Acc. (calibration) |") == 2
    assert (tmp_path / "out" / "energy_over_time.png").read_bytes()[:8] == PNG_MAGIC


def with_context_energy(records, rising_when_failed=True):
    """The records with a context energy E_c that rises chunk by chunk in failed episodes (flat otherwise)."""
    rng = np.random.default_rng(3)
    return [
        dataclasses.replace(
            r,
            context_energy=float(
                (1.0 * r.chunk_index if rising_when_failed and not r.success else 0.0) + rng.normal(0, 0.1)
            ),
        )
        for r in records
    ]


def test_failure_report_measures_the_lead_to_the_onset_when_the_records_carry_goal_distances(
    tmp_path, capsys
):
    """A failed episode's object comes 5 cm closer a chunk for its first 3 chunks, then stays: onset at step 3."""

    def with_goal_distances(records):
        return [
            dataclasses.replace(r, goal_distance=0.3 - 0.05 * min(r.chunk_index, 2 if not r.success else 5))
            for r in records
        ]

    calibration = write(tmp_path, "cal", with_goal_distances(rollouts(12, 5.0, seed=5)))
    held_out = write(tmp_path, "held", with_goal_distances(rollouts(12, 5.0, seed=7)))
    args = [f"--calibration=[{calibration}]", f"--records=[{held_out}]", "--max_step=6", "--max_window=4"]
    failure_report.main([*args, f"--output_dir={tmp_path / 'out'}", "--n_bootstrap=100"])
    out = capsys.readouterr().out
    assert "Median lead to onset (chunks)" in out and "Alarmed by the onset" in out
    onsets = [line.split("|")[-3].strip() for line in out.splitlines() if line.startswith("| reach |")]
    assert onsets and set(onsets) == {"3"}  # every failed episode's row in the alarm table


def test_failure_report_adds_the_context_energys_slope_when_the_records_carry_it(tmp_path, capsys):
    calibration = write(tmp_path, "cal", with_context_energy(rollouts(12, 5.0, seed=5)))
    held_out = write(tmp_path, "held", with_context_energy(rollouts(12, 5.0, seed=7)))
    args = [f"--calibration=[{calibration}]", f"--records=[{held_out}]", "--max_step=6", "--max_window=4"]
    failure_report.main([*args, f"--output_dir={tmp_path / 'out'}", "--n_bootstrap=100"])
    out = capsys.readouterr().out
    assert "### Slope Final" in out and "### Slope Start" in out and "### Slope Context" in out
    assert "## Lead time, Slope Context" in out
    # E_c rises by 1 a chunk in failed episodes: from step 2 on its slope separates them perfectly.
    context = out.split("### Slope Context")[1].split("###")[0]
    step_3 = next(line for line in context.splitlines() if line.startswith("| 3 |"))
    assert "1.000 [1.000, 1.000]" in step_3
    # Without E_c in every record there is no context slope.
    failure_report.main(
        [
            f"--calibration=[{write(tmp_path, 'plain', rollouts(12, 5.0, seed=5))}]",
            *args[1:],
            "--n_bootstrap=100",
        ]
        + [f"--output_dir={tmp_path / 'out2'}"]
    )
    assert "Slope Context" not in capsys.readouterr().out


def test_failure_report_judges_episodes_at_equal_elapsed_time_unless_carried_forward(tmp_path, capsys):
    calibration, _ = failure_dirs(tmp_path)
    # Calibration mixes 6- and 4-chunk episodes: at step 5 only the 12 six-chunk ones are still running.
    args = [f"--records=[{calibration}]", "--in_sample=true", "--max_step=6", "--max_window=3"]
    failure_report.main([*args, f"--output_dir={tmp_path / 'out'}"])
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if line.startswith("| 5 |")]
    assert rows and all("| 12 | 4 | 33.3% |" in row for row in rows)
    assert "Equal elapsed time: at step s only the episodes still running" in out
    # With carry-forward every step counts all 21 episodes.
    failure_report.main([*args, "--carry_forward=true", f"--output_dir={tmp_path / 'out'}"])
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if line.startswith("| 5 |")]
    assert rows and all("| 21 | 7 | 33.3% |" in row for row in rows)
    assert "Carry forward: episodes that ended before a step carry their last energy forward" in out


def test_failure_report_refuses_an_in_sample_report(tmp_path):
    calibration, _ = failure_dirs(tmp_path)
    with pytest.raises(ValueError, match="in_sample"):
        failure_report.main([f"--calibration=[{calibration}]", f"--records=[{calibration}]"])


def test_failure_report_refuses_calibration_episodes_that_replay_the_reported_seeds(tmp_path):
    _, held_out = failure_dirs(tmp_path)
    rerun = write(tmp_path, "held_rerun", rollouts(12, 5.0, seed=7))
    with pytest.raises(ValueError, match=r"seeds 7000, 7001.*--in_sample=true"):
        failure_report.main([f"--calibration=[{rerun}]", f"--records=[{held_out}]"])


def test_failure_report_refuses_reference_episodes_that_replay_the_reported_seeds(tmp_path):
    calibration, held_out = failure_dirs(tmp_path)
    args = [f"--calibration=[{calibration}]", f"--records=[{held_out}]", f"--reference=[{held_out}]"]
    with pytest.raises(ValueError, match="in_sample"):
        failure_report.main(args)


def test_failure_report_keeps_only_successful_reference_episodes_and_says_so(tmp_path, capsys):
    calibration, held_out = failure_dirs(tmp_path)
    reference = write(tmp_path, "ref", rollouts(9, 5.0, seed=8))  # 3 of 9 failed
    args = [f"--calibration=[{calibration}]", f"--records=[{held_out}]", f"--reference=[{reference}]"]
    failure_report.main([*args, "--max_step=4", f"--output_dir={tmp_path / 'out'}"])
    out = capsys.readouterr().out
    assert (
        "the 6 successful episodes of `--reference`" in out and "3 failed episodes were filtered out" in out
    )


def test_failure_report_adds_a_section_per_task(tmp_path, capsys):
    def task(records, name):
        return [dataclasses.replace(r, task=name) for r in records]

    calibration = write(
        tmp_path, "cal", task(rollouts(9, 5.0, seed=1), "a") + task(rollouts(9, 5.0, seed=2), "b")
    )
    held_out = write(
        tmp_path, "held", task(rollouts(6, 5.0, seed=3), "a") + task(rollouts(6, 5.0, seed=4), "b")
    )
    args = [f"--calibration=[{calibration}]", f"--records=[{held_out}]", "--max_step=3", "--max_window=3"]
    failure_report.main([*args, f"--output_dir={tmp_path / 'out'}"])
    out = capsys.readouterr().out
    assert "## Across tasks" in out and "## Within task 'a'" in out and "## Within task 'b'" in out


def test_failure_report_filters_by_perturbation(record_dirs, tmp_path, capsys):
    _, vanilla, ood = record_dirs
    args = [f"--records=[{vanilla},{ood}]", "--perturbation=[camera]", "--in_sample=true", "--max_step=3"]
    failure_report.main([*args, f"--output_dir={tmp_path / 'out'}"])
    assert "20 held-out episodes" in capsys.readouterr().out


def test_failure_report_prints_the_slope_auroc_and_the_lead_time(tmp_path, capsys):
    calibration, held_out = failure_dirs(tmp_path)
    args = [f"--calibration=[{calibration}]", f"--records=[{held_out}]", "--max_step=6", "--max_window=4"]
    failure_report.main([*args, "--n_bootstrap=50", f"--output_dir={tmp_path / 'out'}"])
    out = capsys.readouterr().out
    assert out.count("| AUROC [95% CI] | Bal. Acc. (calibration) |") == 2  # one Table IV per metric
    assert "First alarm of each failed held-out episode (Slope Final" in out
    lead = section(out, "Lead time, Slope Final: pooled and per task")
    (row,) = [line for line in lead.splitlines() if line.startswith("| all tasks |")]
    assert row.startswith("| all tasks | 4 | 8 | ")


def test_failure_report_gives_the_one_check_alarm_and_saves_what_it_reports(tmp_path, capsys):
    calibration, held_out = failure_dirs(tmp_path)
    checkpoint = tmp_path / "pretrained_model"
    checkpoint.mkdir()
    args = [f"--calibration=[{calibration}]", f"--records=[{held_out}]", "--max_step=6", "--max_window=4"]
    failure_report.main([*args, f"--calibrate_to={checkpoint}", f"--output_dir={tmp_path / 'out'}"])
    checks = section(
        capsys.readouterr().out, "The deployable alarm: one check, at the step chosen on calibration"
    )
    alarm = FailureAlarm.load(checkpoint / FAILURE_ALARM_FILENAME)
    title = {"final": "Slope Final", "start": "Slope Start"}[alarm.metric]
    (row,) = [line for line in checks.splitlines() if line.startswith(f"| all tasks | {title} |")]
    cells = [c.strip() for c in row.split("|")[1:-1]]
    assert (int(cells[2]), int(cells[3])) == (alarm.step, alarm.window)
    # The saved alarm, run on the held-out episodes, raises the alarms the report counts.
    episodes = load_episodes([held_out]).values()
    energy = {"final": "final_energy", "start": "initial_energy"}[alarm.metric]
    flags = [(not e[0].success, alarm.check([getattr(r, energy) for r in e])) for e in episodes]
    caught, false_alarms = sum(f and a for f, a in flags), sum(a and not f for f, a in flags)
    assert cells[8] == f"{caught}/4" and cells[9] == f"{false_alarms}/8"
    assert caught == 4  # the failed episodes' energy rises by 0.3 a chunk


def test_failure_report_never_replaces_a_saved_alarm_unless_asked(tmp_path):
    calibration, held_out = failure_dirs(tmp_path)
    saved = FailureAlarm("final", 9, 2, 1.0, 0.0, 1.0, 5).save(tmp_path)
    args = [
        f"--calibration=[{calibration}]",
        f"--records=[{held_out}]",
        "--max_step=6",
        f"--calibrate_to={tmp_path}",
    ]
    with pytest.raises(FileExistsError, match="--overwrite_alarm=true"):
        failure_report.main([*args, f"--output_dir={tmp_path / 'out'}"])
    assert FailureAlarm.load(saved).step == 9 and not (tmp_path / "out").exists()
    failure_report.main([*args, "--overwrite_alarm=true", f"--output_dir={tmp_path / 'out'}"])
    assert FailureAlarm.load(saved).step <= 6


def test_failure_report_saves_no_alarm_from_carried_forward_episodes(tmp_path):
    calibration, held_out = failure_dirs(tmp_path)
    args = [f"--calibration=[{calibration}]", f"--records=[{held_out}]", "--carry_forward=true"]
    with pytest.raises(ValueError, match="carry_forward=false"):
        failure_report.main([*args, f"--calibrate_to={tmp_path}"])


def test_failure_report_leaves_out_tasks_with_too_few_failures_or_successes(tmp_path, capsys):
    def task(records, name):
        return [dataclasses.replace(r, task=name) for r in records]

    calibration = write(
        tmp_path, "cal", task(rollouts(9, 5.0, seed=1), "a") + task(rollouts(9, 5.0, seed=2), "b")
    )
    # Task b's held-out episodes: one failure (episode 0) in two.
    held = task(rollouts(6, 5.0, seed=3), "a") + task(rollouts(2, 5.0, seed=4), "b")
    args = [f"--calibration=[{calibration}]", f"--records=[{write(tmp_path, 'held', held)}]", "--max_step=3"]
    failure_report.main([*args, "--max_window=3", f"--output_dir={tmp_path / 'out'}"])
    out = capsys.readouterr().out
    assert "Left out: 1 failed and 1 successful held-out episodes (a task needs at least 2 of each)." in out
    lead = section(out, "Lead time, Slope Final: pooled and per task")
    assert "| a | 2 | 4 |" in lead and "| b |" not in lead


@pytest.mark.parametrize("script", [ood_report, failure_report, landscape])
def test_scripts_have_help_from_their_config(script, capsys):
    with pytest.raises(SystemExit) as exit_info:
        script.main(["--help"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    assert "usage:" in out and "--output" in out


# The held-out protocol shared by both reports.


def test_held_out_check_passes_disjoint_seeds(tmp_path):
    calibration = load_episodes([write(tmp_path, "a", rollouts(4, 5.0, seed=1))])
    report = load_episodes([write(tmp_path, "b", rollouts(4, 5.0, seed=2))])
    assert check_held_out(calibration, report) is False


def test_held_out_check_names_the_seeds_both_sets_share(tmp_path):
    calibration = load_episodes([write(tmp_path, "a", rollouts(4, 5.0, seed=1))])
    report = load_episodes([write(tmp_path, "b", rollouts(3, 5.0, seed=1, first=2))])
    with pytest.raises(ValueError, match=r"task 'reach' \(vanilla\): seeds 1002, 1003\..*--in_sample=true"):
        check_held_out(calibration, report)


def test_held_out_check_matches_seeds_within_one_task_and_condition_only(tmp_path):
    calibration = load_episodes([write(tmp_path, "a", rollouts(4, 5.0, seed=1))])
    other_task = [dataclasses.replace(r, task="push") for r in rollouts(4, 5.0, seed=1)]
    perturbed = rollouts(4, 6.0, "camera", 1.0, seed=1)
    report = load_episodes([write(tmp_path, "b", other_task), write(tmp_path, "c", perturbed)])
    assert check_held_out(calibration, report) is False


def test_held_out_check_allows_an_in_sample_report_when_asked(tmp_path):
    episodes = load_episodes([write(tmp_path, "a", rollouts(4, 5.0, seed=1))])
    assert check_held_out(episodes, episodes, in_sample=True) is True
    assert check_held_out(None, episodes, in_sample=True) is True


def test_held_out_check_refuses_a_report_without_calibration(tmp_path):
    episodes = load_episodes([write(tmp_path, "a", rollouts(4, 5.0, seed=1))])
    with pytest.raises(ValueError, match="no `--calibration`"):
        check_held_out(None, episodes)
