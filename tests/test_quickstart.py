"""`ebvla-quickstart`: its guards and its summary (the full pipeline is exercised by running it)."""

import math

import pytest

from lerobot_policy_ebvla.monitoring import EnergyRecord, write_energy_records
from lerobot_policy_ebvla.scripts import quickstart


def test_refuses_to_replace_a_previous_run_without_overwrite(tmp_path):
    (tmp_path / "train").mkdir()
    with pytest.raises(SystemExit, match="--overwrite"):
        quickstart.main(["--output_dir", str(tmp_path)])
    assert (tmp_path / "train").is_dir()


def test_refuses_a_run_in_progress_before_train_dir_exists(tmp_path):
    (tmp_path / quickstart.RUN_MARKER).write_text("{}\n")
    with pytest.raises(SystemExit, match="--overwrite"):
        quickstart.main(["--output_dir", str(tmp_path)])


@pytest.mark.parametrize("argument", [["--resize", "32"], ["--train_steps", "0"], ["--eval_episodes", "0"]])
def test_rejects_invalid_sizes(argument):
    with pytest.raises(SystemExit):
        quickstart.parse_args(argument)


def test_summary_splits_final_energy_by_episode_outcome(tmp_path):
    def chunk(episode, index, final, success):
        return EnergyRecord(episode, index, 8 * index, 1.0, final, success, "button-press-v3", 1000 + episode)

    records = [chunk(0, 0, 0.5, True), chunk(0, 1, 1.5, True), chunk(1, 0, 3.0, False)]
    write_energy_records(tmp_path / "energy_records.jsonl", records)

    summary = quickstart.summarise(tmp_path)

    assert summary["n_episodes"] == 2 and summary["n_success"] == 1
    assert summary["success_rate"] == 0.5
    assert math.isclose(summary["mean_final_energy_success"], 1.0)
    assert math.isclose(summary["mean_final_energy_failure"], 3.0)
    assert [e["chunks"] for e in summary["episodes"]] == [2, 1]
