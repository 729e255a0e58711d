"""The renderer control of an evaluation split between two machines (`research/benchmarks/render_parity.py`)."""

import math

import numpy as np
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


frames = load_benchmark("reset_frames")


def fake_dump(tasks, states, levels, machine):
    """A dump of len(tasks) resets whose frames are all `levels` (one per reset), as `reset_frames.dump` writes it."""
    n = len(tasks)
    image = np.stack([np.full((4, 4, 3), level, dtype=np.uint8) for level in levels])
    observation = {
        "pixels": {"image": image, "image2": image[:, ::-1]},
        "robot_state": {"joints": {"pos": np.zeros((n, 7))}},
    }
    return {
        **{f"observation/{k}": v for k, v in frames.flatten(observation).items()},
        "task": np.array(tasks),
        "state": np.array(states),
        "instruction": np.array(["pick"] * n),
        "machine": np.array(machine),
    }


def test_reset_frames_pair_the_two_dumps_by_task_and_state_and_measure_their_pixels():
    observation = {
        "pixels": {"image": np.ones((1, 2, 2, 3))},
        "robot_state": {"eef": {"pos": np.zeros((1, 3))}},
    }
    assert frames.unflatten(frames.flatten(observation)).keys() == observation.keys()
    np.testing.assert_array_equal(
        frames.unflatten(frames.flatten(observation))["pixels"]["image"], np.ones((1, 2, 2, 3))
    )

    here = fake_dump([0, 1], [30, 30], [100, 120], "cpu")
    # The other machine dumped them in the other order, each 10 levels brighter.
    there = fake_dump([1, 0], [30, 30], [130, 110], "gpu")
    result = frames.compare(here, there, checkpoint=None)
    assert result["pairs"] == 2 and result["machines"] == ["cpu", "gpu"]
    camera = result["cameras"]["image"]
    assert camera["mean_abs_levels"] == 10.0 and camera["share_over_8_levels"] == 1.0
    assert camera["mean_level_here"] == [110.0] * 3 and camera["mean_level_there"] == [120.0] * 3
    assert "context_energy" not in result
    with pytest.raises(
        ValueError, match=r"no reset of these \(task, state\) pairs of this one: \[\(1, 30\)\]"
    ):
        frames.compare(here, fake_dump([2, 0], [30, 30], [1, 2], "gpu"), checkpoint=None)
