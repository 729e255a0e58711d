"""research/benchmarks/context_energy_split.py: the joint energy scored apart as E_c and the head's part (issue 32)."""

import dataclasses

import numpy as np
import pytest

from lerobot_policy_ebvla.monitoring.records import (
    ENERGY_RECORDS_FILENAME,
    EnergyRecord,
    write_energy_records,
)
from research.tests.conftest import load_benchmark

split = load_benchmark("context_energy_split")


def write_folder(root, name, head, context, success, chunks=3, perturbation="none"):
    """Records of len(head) episodes: chunk k's final energy head[i] + context[i] (+ k, the task's phase)."""
    records = [
        EnergyRecord(
            episode_index=i,
            chunk_index=k,
            env_step=8 * k,
            initial_energy=9.0,
            final_energy=float(h + c + k),
            success=bool(s),
            task="t",
            seed=i,
            perturbation=perturbation,
            severity=0.0 if perturbation == "none" else 3.0,
            context_energy=float(c),
        )
        for i, (h, c, s) in enumerate(zip(head, context, success, strict=True))
        for k in range(chunks)
    ]
    folder = root / name
    folder.mkdir(parents=True)
    write_energy_records(folder / ENERGY_RECORDS_FILENAME, records)
    return records


def sweep(root, rng):
    """A sweep where a mild shift lowers the head's part a little and raises E_c clearly, and fails more."""
    n = 40
    write_folder(root, "calibration", rng.normal(0, 1, 20), rng.normal(0, 0.05, 20), [True] * 20)
    write_folder(root, "vanilla", rng.normal(0, 1, n), rng.normal(0, 0.05, n), [True] * 30 + [False] * 10)
    write_folder(
        root,
        "mild_s3",
        rng.normal(-0.5, 1, 16),
        rng.normal(0.3, 0.05, 16),
        [True] * 4 + [False] * 12,
        3,
        "mild",
    )


def test_the_split_sees_a_shift_through_the_context_term_that_the_head_part_hides(tmp_path):
    sweep(tmp_path, np.random.default_rng(0))
    result = split.run_split(tmp_path, chunks=3)
    row = result["rows"]["mild_s3"]
    assert row["E_c"][1] > 0.95 and row["E_c alarms"] > 0.9
    assert row["head"][1] < 0.5 and row["joint"][1] < row["E_c"][1]
    summary = result["summary"]
    assert summary["E_c"]["under 0.5"] == 0 and summary["head"]["under 0.5"] == 1
    assert summary["E_c"]["cutting min"] == pytest.approx(row["E_c"][1])  # 25% success against vanilla's 75%
    assert "| mild_s3 | 25% (16) |" in split.markdown({"toy": result}, 3)


def test_cut_rollouts_take_each_conditions_success_rate_from_the_full_sweep(tmp_path):
    rng = np.random.default_rng(1)
    cut, full = tmp_path / "cut", tmp_path / "full"
    sweep(full, rng)
    for folder in ("calibration", "vanilla", "mild_s3"):
        records = split.load(full / folder, chunks=3)
        (cut / folder).mkdir(parents=True)
        # Cut rollouts know no outcome (they ended at the third chunk): every one is recorded as failed.
        rows = [dataclasses.replace(r, success=False) for episode in records.values() for r in episode[:2]]
        write_energy_records(cut / folder / ENERGY_RECORDS_FILENAME, rows)
    result = split.run_split(cut, chunks=2, outcomes_dir=full)
    assert result["rows"]["mild_s3"]["success"] == 0.25
    assert result["summary"]["vanilla success"] == 0.75
    assert result["summary"]["E_c"]["failed vs successful"] == "- (cut rollouts)"
    assert result["summary"]["E_c"]["cutting min"] > 0.95


def test_records_without_the_context_energy_are_refused_by_name(tmp_path):
    records = write_folder(tmp_path, "vanilla", [0.0], [0.0], [True])
    folder = tmp_path / "old"
    folder.mkdir()
    write_energy_records(
        folder / ENERGY_RECORDS_FILENAME, [dataclasses.replace(r, context_energy=None) for r in records]
    )
    with pytest.raises(ValueError, match="context_energy"):
        split.split_scores(split.load(folder, chunks=3))
