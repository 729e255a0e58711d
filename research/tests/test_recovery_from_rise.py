"""J's recovery pieces are cut from I's at the rise after the miss: the cut point, on made-up action sequences, and
the committed check that the package's recorder stores the same frames."""

import json
from pathlib import Path

import numpy as np
import pytest

from research.benchmarks.recovery_from_rise import CODEC_TOLERANCE, rise_start

RESULTS = Path(__file__).resolve().parents[1] / "results" / "libero_object10_recover_rise"


def actions(*segments: tuple[int, float, float]) -> np.ndarray:
    """(steps, z move, gripper) segments as 7-d actions."""
    rows = [[0.3, 0.0, z, 0.0, 0.0, 0.0, gripper] for n, z, gripper in segments for _ in range(n)]
    return np.array(rows, dtype=np.float32)


def test_the_cut_starts_at_the_first_closed_step_that_moves_the_hand():
    # approach and descent open, 13 steps closing in place, the rise, the reopening, the second approach
    episode = actions((40, -0.3, -1.0), (13, 0.0, 1.0), (6, 0.6, 1.0), (13, 0.0, -1.0), (20, -0.3, -1.0))
    episode[40:53, :3] = 0.0  # the grasp holds the hand still
    assert rise_start(episode) == 53


def test_an_episode_whose_hand_never_closes_and_moves_has_no_miss_to_cut():
    with pytest.raises(ValueError, match="no missed grasp"):
        rise_start(actions((40, -0.3, -1.0)))
    closing_only = actions((40, -0.3, -1.0), (13, 0.0, 1.0))
    closing_only[40:, :3] = 0.0
    with pytest.raises(ValueError, match="no missed grasp"):
        rise_start(closing_only)


def test_the_committed_check_found_the_recorders_frames_in_the_cut_piece():
    check = json.loads((RESULTS / "check_task5.json").read_text())
    assert check["frames_recorded"] == check["frames_cut"] > 0
    assert check["max_abs_state_difference"] == 0 and check["max_abs_action_difference"] == 0
    assert check["max_mean_abs_pixel_difference"] < CODEC_TOLERANCE and check["equal"]
    cuts = json.loads(
        (RESULTS / "data" / "task5_recoverrise_from0" / "meta" / "recording_report.json").read_text()
    )
    assert (
        cuts["store_missed_grasp"] is False
        and cuts["cuts"][0]["frames"] - cuts["cuts"][0]["first_kept"] == (check["frames_cut"])
    )
