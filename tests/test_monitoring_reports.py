"""The report entry points on synthetic `energy_records.jsonl` files: held-out protocol, baselines, figures."""

import dataclasses
import json
import math

import numpy as np
import pytest

from lerobot_policy_ebvla.monitoring.ood import OOD_CALIBRATION_FILENAME, OODCalibration
from lerobot_policy_ebvla.monitoring.records import (
    ENERGY_RECORDS_FILENAME,
    EnergyRecord,
    write_energy_records,
)
from lerobot_policy_ebvla.scripts import failure_report, landscape, ood_report

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def rollouts(
    n, level, perturbation="none", severity=0.0, seed=0, n_chunks=6, fail_every=3, features=False, first=0
):
    """n episodes whose final energies hover around `level`; every `fail_every`-th one fails with rising energy.

    With `features`, each chunk also carries a restart spread and a 4-d context feature centred on `level`.
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
                seed=episode,
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
    assert out.count("| Multiplier |") == 3  # all perturbations, and each severity
    # Every baseline sits beside the final energy in the AUROC table and in every Table III.
    assert (
        "| Condition | Episodes | final_energy | initial_energy | restart_spread | mahalanobis | knn |" in out
    )
    assert out.count("Bal. Acc. knn") == 3
    assert out.count("conf. α=5.0%") == 3


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
    assert "| Condition | Episodes | final_energy | initial_energy |\n" in out and "knn" not in out


def test_ood_report_calibrates_a_checkpoint_on_the_calibration_rollouts(record_dirs, tmp_path):
    checkpoint = tmp_path / "pretrained_model"
    checkpoint.mkdir()
    args = [*ood_args(*record_dirs, tmp_path / "out"), f"--calibrate_to={checkpoint}", "--k=0.5"]
    ood_report.main([*args, "--threshold_rule=conformal", "--false_alarm_rate=0.1"])
    calibration = OODCalibration.load(checkpoint)
    assert calibration.k == 0.5 and calibration.n_rollouts == 12 and 4.5 < calibration.mu_v < 5.5
    assert calibration.rule == "conformal" and calibration.false_alarm_rate == 0.1
    assert calibration.threshold == calibration.conformal_threshold


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


def test_failure_report_carries_ended_episodes_forward_by_default(tmp_path, capsys):
    calibration, _ = failure_dirs(tmp_path)
    # Calibration mixes 6- and 4-chunk episodes: with carry-forward every step counts all 21 episodes.
    args = [f"--records=[{calibration}]", "--in_sample=true", "--max_step=6", "--max_window=3"]
    failure_report.main([*args, f"--output_dir={tmp_path / 'out'}"])
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| 5 |")]
    assert rows and all("| 21 | 7 | 33.3% |" in row for row in rows)
    failure_report.main([*args, "--carry_forward=false", f"--output_dir={tmp_path / 'out'}"])
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| 5 |")]
    assert rows and all("| 12 | 4 | 33.3% |" in row for row in rows)


def test_failure_report_refuses_an_in_sample_report(tmp_path):
    calibration, _ = failure_dirs(tmp_path)
    with pytest.raises(ValueError, match="in_sample"):
        failure_report.main([f"--calibration=[{calibration}]", f"--records=[{calibration}]"])


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


@pytest.mark.parametrize("script", [ood_report, failure_report, landscape])
def test_scripts_have_help_from_their_config(script, capsys):
    with pytest.raises(SystemExit) as exit_info:
        script.main(["--help"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    assert "usage:" in out and "--output" in out
