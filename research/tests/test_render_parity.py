"""The renderer control of an evaluation split between two machines (`research/benchmarks/render_parity.py`)."""

import math

import pytest

from lerobot_policy_ebvla.monitoring.records import EnergyRecord, write_energy_records
from research.tests.conftest import load_benchmark

parity = load_benchmark("render_parity")


def write_run(folder, context_energies, goal_offset=0.0):
    """One task folder of episodes whose chunk c has E_c context_energies[episode][c]."""
    records = [
        EnergyRecord(
            episode_index=episode,
            chunk_index=chunk,
            env_step=8 * chunk,
            initial_energy=10.0,
            final_energy=1.0,
            success=True,
            task="pick_up_the_salad_dressing",
            seed=1000 + episode,
            perturbation="none",
            severity=0,
            context_energy=value,
            goal_distance=0.3 + 0.01 * episode + goal_offset,
        )
        for episode, values in enumerate(context_energies)
        for chunk, value in enumerate(values)
    ]
    write_energy_records(folder / "task2" / "energy_records.jsonl", records)
    return folder


def test_identical_renderings_leave_no_footprint(tmp_path):
    runs = [[1.0 + e, 2.0, 3.0] for e in range(6)]
    result = parity.render_parity(write_run(tmp_path / "a", runs), write_run(tmp_path / "b", runs))
    assert result.pairs == 6
    assert result.context_energy_at_reset_mean_abs_difference == 0.0
    assert result.max_goal_distance_difference_at_reset == 0.0
    assert result.mean_context_energy_first_chunks_auroc == 0.5


def test_a_renderer_the_energy_sees_is_told_apart_and_its_reset_difference_measured(tmp_path):
    runs = [[1.0 + 0.1 * e, 2.0, 3.0] for e in range(6)]
    shifted = [[v + 5.0 for v in values] for values in runs]
    result = parity.render_parity(write_run(tmp_path / "a", runs), write_run(tmp_path / "b", shifted, 1e-3))
    assert result.context_energy_at_reset_mean_abs_difference == pytest.approx(5.0)
    assert result.mean_context_energy_first_chunks_auroc == 1.0
    assert result.max_goal_distance_difference_at_reset == pytest.approx(1e-3)
    assert "AUROC 1.000" in result.summary()


def test_only_episodes_run_on_both_are_paired_and_none_is_an_error(tmp_path):
    a = write_run(tmp_path / "a", [[1.0, 1.0, 1.0]] * 5)
    b = write_run(tmp_path / "b", [[1.0, 1.0, 1.0]] * 3)
    assert parity.render_parity(a, b).pairs == 3
    (tmp_path / "c").mkdir()
    with pytest.raises(ValueError, match="no episode"):
        parity.render_parity(a, tmp_path / "c")
    assert not math.isnan(parity.render_parity(a, b).context_energy_at_reset_spread)
