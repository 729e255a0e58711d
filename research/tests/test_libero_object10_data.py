"""The committed LIBERO-Object ten-task demonstrations (issue 52, item 2): each recorded piece is a LeRobot video
dataset whose episodes are the successful attempts its report lists, attempt i placed by seed 100000 + i (sampled
placements, which tests/test_libero.py checks are none of the fixed initial states evaluation starts from)."""

import json

import pyarrow.parquet as pq
import pytest

from research.tests.conftest import RESULTS

DATA = RESULTS / "libero_object10" / "data"
PIECES = sorted(DATA.glob("task*_from*"))


def test_every_task_has_44_demonstrations_and_the_summary_counts_them():
    kept: dict[int, int] = {}
    for piece in PIECES:
        report = json.loads((piece / "meta" / "recording_report.json").read_text())
        (task,) = report["env"]["task_ids"]
        kept[task] = kept.get(task, 0) + report["n_kept"]
    assert kept == dict.fromkeys(range(10), 44)
    summary = json.loads((DATA.parent / "recording_summary.json").read_text())
    assert {int(t): (e["attempts"], e["kept"]) for t, e in summary["tasks"].items()} == dict.fromkeys(
        range(10), (44, 44)
    )


def test_the_three_rule_tasks_repeat_the_earlier_recording_step_for_step():
    """Tasks 2, 3 and 9 were recorded before (research/results/libero_cpu, as images, in pieces of 22) from the
    same seeds: the expert takes the same number of steps in every episode, so the simulation repeats."""
    earlier = json.loads((RESULTS / "libero_cpu" / "recording_summary.json").read_text())["tasks"]
    now = json.loads((DATA.parent / "recording_summary.json").read_text())["tasks"]
    for task in ("2", "3", "9"):
        assert now[task]["steps_of_kept"] == earlier[task]["steps_of_kept"], task


@pytest.mark.parametrize("piece", PIECES, ids=lambda p: p.name)
def test_each_piece_holds_the_successful_attempts_of_its_report_from_sampled_placements(piece):
    report = json.loads((piece / "meta" / "recording_report.json").read_text())
    info = json.loads((piece / "meta" / "info.json").read_text())
    assert report["placement_seed"] == 100000 and report["use_videos"] and report["image_size"] == 128
    # Attempt i of the piece starting at attempt `first` is placed by seed 100000 + first + i.
    first = report["env"]["first_init_state"]
    seeds = [e["placement_seed"] for e in report["episodes"]]
    assert seeds == list(range(100000 + first, 100000 + first + report["n_attempted"]))
    kept = [e for e in report["episodes"] if e["kept"]]
    assert all(e["success"] for e in kept)
    assert info["total_episodes"] == report["n_kept"] == len(kept)
    assert info["total_frames"] == sum(e["n_steps"] for e in kept)
    frames = pq.read_table(piece / "data" / "chunk-000" / "file-000.parquet", columns=["episode_index"])
    assert frames.num_rows == info["total_frames"]
    for camera in ("observation.images.image", "observation.images.image2"):
        assert (piece / "videos" / camera / "chunk-000" / "file-000.mp4").stat().st_size > 0
