"""The recording loop every expert recorder runs, on a fake dataset (no simulator needed)."""

import pytest

from lerobot_policy_ebvla.recording.loop import Episode, format_report, prepare_root, record_episodes


class FakeDataset:
    """The part of a LeRobotDataset in write mode the loop uses."""

    def __init__(self, frames_per_episode: int = 7):
        self.num_episodes = 0
        self.buffer_cleared = 0
        self.finalized = False
        self.frames_per_episode = frames_per_episode

    def has_pending_frames(self):
        return self.frames_per_episode > 0

    def save_episode(self):
        self.num_episodes += 1

    def clear_episode_buffer(self):
        self.buffer_cleared += 1

    def finalize(self):
        self.finalized = True


def episodes(outcomes, closed):
    try:
        for attempt, success in enumerate(outcomes):
            yield Episode(
                "reach",
                {"attempt": attempt, "seed": 10 + attempt},
                f"reach {attempt}",
                lambda s=success: (s, 7),
            )
    finally:
        closed.append(True)


def test_successful_episodes_are_saved_and_failed_ones_cleared_unless_kept():
    dataset, closed = FakeDataset(), []
    reports = record_episodes(dataset, episodes([True, False, True], closed), keep_failed=False)
    assert [r.kept for r in reports] == [True, False, True]
    assert [r.dataset_episode_index for r in reports] == [0, None, 1]
    assert (dataset.num_episodes, dataset.buffer_cleared, dataset.finalized, closed) == (2, 1, True, [True])

    reports = record_episodes(FakeDataset(), episodes([False], []), keep_failed=True)
    assert reports[0].kept and reports[0].dataset_episode_index == 0


def test_a_kept_failure_that_stored_no_frame_is_left_out_not_saved_empty():
    """A recorder that stores part of an attempt (a recovery demonstration's frames from its miss on) can end an
    attempt with nothing stored: LeRobot refuses to save an empty episode, so the loop reports it left out."""
    dataset = FakeDataset(frames_per_episode=0)
    reports = record_episodes(dataset, episodes([False], []), keep_failed=True)
    assert not reports[0].kept and reports[0].dataset_episode_index is None
    assert (dataset.num_episodes, dataset.buffer_cleared) == (0, 1)


def test_an_episode_that_raises_still_closes_the_env_and_finalizes_the_dataset():
    def failing(closed):
        try:
            yield Episode("reach", {"attempt": 0}, "reach 0", lambda: 1 / 0)
        finally:
            closed.append(True)

    dataset, closed = FakeDataset(), []
    with pytest.raises(ZeroDivisionError):
        record_episodes(dataset, failing(closed), keep_failed=False)
    assert closed == [True] and dataset.finalized


def test_the_report_entry_puts_the_start_fields_after_the_task():
    (report,) = record_episodes(FakeDataset(), episodes([True], []), keep_failed=False)
    entry = report.to_dict()
    assert list(entry)[:3] == ["task", "attempt", "seed"]
    assert entry["n_steps"] == 7 and entry["success"]
    assert "1/1 expert episodes succeeded, 1 kept." in format_report([report])


def test_prepare_root_replaces_only_a_dataset_and_only_when_asked(tmp_path):
    dataset_root = tmp_path / "dataset"
    (dataset_root / "meta").mkdir(parents=True)
    (dataset_root / "meta" / "info.json").write_text("{}")
    with pytest.raises(FileExistsError, match="--overwrite=true"):
        prepare_root(dataset_root, overwrite=False)
    prepare_root(dataset_root, overwrite=True)
    assert not dataset_root.exists()

    users_folder = tmp_path / "notes"
    users_folder.mkdir()
    (users_folder / "keep.txt").write_text("mine")
    with pytest.raises(FileExistsError, match="not a LeRobotDataset"):
        prepare_root(users_folder, overwrite=True)
    assert (users_folder / "keep.txt").read_text() == "mine"
