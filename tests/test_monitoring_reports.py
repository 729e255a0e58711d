"""The report entry points: every table and PNG from synthetic `energy_records.jsonl` files."""

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


def rollouts(n, level, perturbation="none", severity=0.0, seed=0, n_chunks=6, fail_every=3):
    """n episodes whose final energies hover around `level`; every `fail_every`-th one fails with rising energy."""
    rng = np.random.default_rng(seed)
    records = []
    for episode in range(n):
        failed = episode % fail_every == 0
        for chunk in range(n_chunks):
            trend = 0.3 * chunk if failed else 0.0
            records.append(
                EnergyRecord(
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
            )
    return records


@pytest.fixture
def record_files(tmp_path):
    vanilla = write_energy_records(tmp_path / "vanilla" / ENERGY_RECORDS_FILENAME, rollouts(12, 5.0))
    ood = write_energy_records(
        tmp_path / "camera" / ENERGY_RECORDS_FILENAME,
        rollouts(10, 6.0, "camera", 1.0, seed=1) + rollouts(10, 7.0, "camera", 2.0, seed=2),
    )
    return vanilla, ood


def test_ood_report_prints_table_iii_with_auroc(record_files, tmp_path, capsys):
    vanilla, ood = record_files
    ood_report.main(["--vanilla", str(vanilla), "--ood", str(ood), "--output-dir", str(tmp_path / "out")])
    out = capsys.readouterr().out
    assert "| Multiplier | Threshold | Accuracy | Bal. Acc. |" in out
    assert out.count("σ |") == 9
    assert "12 vanilla rollouts" in out and "20 OOD rollouts" in out and "AUROC = " in out


def test_ood_report_saves_roc_curve_histogram_and_markdown(record_files, tmp_path):
    vanilla, ood = record_files
    out_dir = tmp_path / "out"
    ood_report.main(["--vanilla", str(vanilla), "--ood", str(ood), "--output-dir", str(out_dir)])
    for name in ("roc_curve.png", "energy_histogram.png"):
        assert (out_dir / name).read_bytes()[:8] == PNG_MAGIC
    assert "| Multiplier |" in (out_dir / "ood_report.md").read_text()


def test_ood_report_per_group_adds_one_table_per_perturbation_and_severity(record_files, tmp_path, capsys):
    vanilla, ood = record_files
    ood_report.main(
        ["--vanilla", str(vanilla), "--ood", str(ood), "--output-dir", str(tmp_path / "out"), "--per-group"]
    )
    out = capsys.readouterr().out
    assert "## camera, severity 1" in out and "## camera, severity 2" in out
    assert out.count("| Multiplier |") == 3


def test_ood_report_splits_a_mixed_file_by_perturbation(record_files, tmp_path, capsys):
    vanilla, ood = record_files
    mixed = tmp_path / "mixed.jsonl"
    mixed.write_text(vanilla.read_text() + ood.read_text())
    ood_report.main(["--records", str(mixed), "--output-dir", str(tmp_path / "out")])
    assert "12 vanilla rollouts" in capsys.readouterr().out


def test_ood_report_calibrates_a_checkpoint(record_files, tmp_path):
    vanilla, ood = record_files
    checkpoint = tmp_path / "pretrained_model"
    checkpoint.mkdir()
    args = ["--vanilla", str(vanilla), "--ood", str(ood), "--output-dir", str(tmp_path / "out")]
    ood_report.main([*args, "--calibrate-to", str(checkpoint), "--k", "0.5"])
    calibration = OODCalibration.load(checkpoint)
    assert calibration.k == 0.5 and calibration.n_rollouts == 12 and 4.5 < calibration.mu_v < 5.5


def test_ood_report_refuses_to_overwrite_a_calibration(record_files, tmp_path):
    vanilla, ood = record_files
    checkpoint = tmp_path / "pretrained_model"
    checkpoint.mkdir()
    (checkpoint / OOD_CALIBRATION_FILENAME).write_text(json.dumps({"mu_v": 1.0, "sigma_v": 0.0}))
    args = ["--vanilla", str(vanilla), "--ood", str(ood), "--output-dir", str(tmp_path / "out")]
    with pytest.raises(SystemExit):
        ood_report.main([*args, "--calibrate-to", str(checkpoint)])
    assert OODCalibration.load(checkpoint).mu_v == 1.0
    ood_report.main([*args, "--calibrate-to", str(checkpoint), "--overwrite-calibration"])
    assert OODCalibration.load(checkpoint).mu_v != 1.0


def test_ood_report_needs_vanilla_and_perturbed_rollouts(record_files, tmp_path):
    vanilla, _ = record_files
    with pytest.raises(SystemExit):
        ood_report.main(["--vanilla", str(vanilla), "--output-dir", str(tmp_path / "out")])


def test_ood_report_handles_a_diverged_rollout(tmp_path, capsys):
    records = rollouts(4, 5.0) + rollouts(4, 6.0, "camera", 1.0)
    records[-1] = EnergyRecord(3, 5, 40, math.inf, math.inf, False, "reach", 3, "camera", 1.0)
    path = write_energy_records(tmp_path / ENERGY_RECORDS_FILENAME, records)
    ood_report.main(["--records", str(path), "--output-dir", str(tmp_path / "out")])
    assert (tmp_path / "out" / "energy_histogram.png").exists()


def test_failure_report_prints_table_iv_for_slope_final_and_slope_start(record_files, tmp_path, capsys):
    vanilla, _ = record_files
    failure_report.main(["--records", str(vanilla), "--max-step", "6", "--output-dir", str(tmp_path / "out")])
    out = capsys.readouterr().out
    assert "## Best configurations, Slope Final" in out and "## Best configurations, Slope Start" in out
    assert out.count("| Step | Win. | Std |") == 2
    assert "12 episodes, 4 failed" in out


def test_failure_report_saves_energy_over_time_and_markdown(record_files, tmp_path):
    vanilla, _ = record_files
    out_dir = tmp_path / "out"
    failure_report.main(["--records", str(vanilla), "--max-step", "6", "--output-dir", str(out_dir)])
    assert (out_dir / "energy_over_time.png").read_bytes()[:8] == PNG_MAGIC
    assert "Slope Final" in (out_dir / "failure_report.md").read_text()


def test_failure_report_filters_by_perturbation(record_files, tmp_path, capsys):
    vanilla, ood = record_files
    args = ["--records", str(vanilla), str(ood), "--perturbation", "camera", "--max-step", "3"]
    failure_report.main([*args, "--output-dir", str(tmp_path / "out")])
    assert "20 episodes" in capsys.readouterr().out


def test_failure_report_calibrates_on_reference_records(record_files, tmp_path, capsys):
    vanilla, ood = record_files
    args = ["--records", str(ood), "--reference", str(vanilla), "--max-step", "6"]
    failure_report.main([*args, "--output-dir", str(tmp_path / "out")])
    assert "| 6 |" in capsys.readouterr().out


@pytest.mark.parametrize("script", [ood_report, failure_report, landscape])
def test_scripts_have_help(script, capsys):
    with pytest.raises(SystemExit) as exit_info:
        script.main(["--help"])
    assert exit_info.value.code == 0
    assert "usage:" in capsys.readouterr().out
