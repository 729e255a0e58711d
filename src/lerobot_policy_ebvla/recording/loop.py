"""The recording loop every simulator's expert recorder runs: attempt episodes, keep or drop each, report.

A recorder (`recording.metaworld`, `recording.libero`) extends `RecordingConfig` with its env and expert
options, creates its LeRobotDataset in a folder made ready by `prepare_root` (which never deletes what is not a
dataset), then hands `record_episodes` a generator of `Episode`s: each rolls the expert out once into the
dataset's episode buffer. The loop saves the episode when the expert succeeded (or `keep_failed`), clears the
buffer otherwise, and returns one `EpisodeReport` per attempt; `write_report` stores them, with their counts, in
`<root>/meta/recording_report.json`.
"""

import json
import logging
import shutil
import time
from collections.abc import Callable, Generator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from lerobot.utils.constants import HF_LEROBOT_HOME

REPORT_FILENAME = "recording_report.json"


@dataclass
class RecordingConfig:
    """The options every expert recorder has: where the dataset goes, how many episodes, which to keep."""

    # Dataset repo id (stored locally; nothing is pushed).
    repo_id: str = "local/expert"
    # Dataset folder; defaults to $HF_LEROBOT_HOME/<repo_id>.
    root: Path | None = None
    # Expert episodes attempted per task.
    episodes_per_task: int = 10
    # Also keep the episodes the expert failed (they are always listed in the report).
    keep_failed: bool = False
    # Store images as MP4 videos instead of PNG frames (smaller, but slower to decode when training).
    use_videos: bool = False
    # Replace an existing dataset at `root`.
    overwrite: bool = False

    def __post_init__(self):
        if self.episodes_per_task < 1:
            raise ValueError(f"`episodes_per_task` must be >= 1, got {self.episodes_per_task}.")
        if self.root is None:
            self.root = HF_LEROBOT_HOME / self.repo_id


def check_env_records_images_and_state(env_cfg: Any) -> None:
    """Raises a ValueError unless the env config gives observations with images and state, as datasets store."""
    if env_cfg.obs_type != "pixels_agent_pos":
        raise ValueError(f"`env.obs_type` must be 'pixels_agent_pos' to record, got {env_cfg.obs_type!r}.")


@dataclass(frozen=True)
class Episode:
    """One expert episode to attempt.

    Args:
        task: The task's name, as the report lists it.
        start: Where the episode starts (e.g. `{"attempt": 0, "seed": 3}`), stored in its report.
        label: How the log names the episode.
        rollout: Rolls the expert out once, adding every frame to the dataset's episode buffer; returns
            (success, number of steps).
    """

    task: str
    start: dict[str, int]
    label: str
    rollout: Callable[[], tuple[bool, int]]


@dataclass
class EpisodeReport:
    """One attempted expert episode: where it started, how it went, whether it is in the dataset."""

    task: str
    start: dict[str, int]
    success: bool
    n_steps: int
    kept: bool
    dataset_episode_index: int | None
    seconds: float

    def to_dict(self) -> dict[str, Any]:
        """The report's JSON entry: the task, the start fields, then the outcome."""
        return {
            "task": self.task,
            **self.start,
            "success": self.success,
            "n_steps": self.n_steps,
            "kept": self.kept,
            "dataset_episode_index": self.dataset_episode_index,
            "seconds": self.seconds,
        }


def prepare_root(root: Path, overwrite: bool) -> None:
    """Makes `root` free for a new dataset; only an existing LeRobotDataset (or an empty folder) is deleted.

    Raises:
        FileExistsError: `root` exists and `overwrite` is False, or it holds files that are not a dataset.
    """
    if not root.exists():
        return
    if not overwrite:
        raise FileExistsError(f"{root} already exists; pass --overwrite=true to replace it.")
    is_dataset = (root / "meta" / "info.json").is_file()
    if not is_dataset and any(root.iterdir()):
        raise FileExistsError(f"{root} is not a LeRobotDataset and not empty; refusing to delete it.")
    shutil.rmtree(root)


def record_episodes(
    dataset: Any, episodes: Generator[Episode, None, None], keep_failed: bool
) -> list[EpisodeReport]:
    """Attempts every episode of `episodes`, saving or clearing the episode buffer; finalizes `dataset`.

    Args:
        dataset: A LeRobotDataset in write mode.
        episodes: The episodes to attempt; closed before the dataset is finalized, so that a generator holding
            an env closes it even when an episode raises.
        keep_failed: Also save the episodes the expert failed (every attempt is reported either way).

    Returns:
        One report per attempted episode, in order.
    """
    reports: list[EpisodeReport] = []
    try:
        for episode in episodes:
            start = time.perf_counter()
            success, n_steps = episode.rollout()
            # A recorder that stores part of an attempt (a recovery's frames from its miss on) may store none.
            kept = (success or keep_failed) and dataset.has_pending_frames()
            index = dataset.num_episodes if kept else None
            if kept:
                dataset.save_episode()
            else:
                dataset.clear_episode_buffer()
            report = EpisodeReport(
                episode.task, episode.start, success, n_steps, kept, index, time.perf_counter() - start
            )
            reports.append(report)
            logging.info(
                "%s: success=%s in %d steps (%.1f steps/s)%s",
                episode.label,
                success,
                n_steps,
                n_steps / report.seconds,
                "" if kept else ", left out",
            )
    finally:
        episodes.close()
        dataset.finalize()
    return reports


def episode_counts(episodes: list[EpisodeReport]) -> dict[str, int]:
    """The report's counts: episodes attempted, successful and kept."""
    return {
        "n_attempted": len(episodes),
        "n_successful": sum(ep.success for ep in episodes),
        "n_kept": sum(ep.kept for ep in episodes),
    }


def success_rates(episodes: list[EpisodeReport]) -> dict[str, float]:
    """The expert's success rate per task, tasks in the order they were recorded."""
    tasks = dict.fromkeys(ep.task for ep in episodes)
    return {task: float(np.mean([ep.success for ep in episodes if ep.task == task])) for task in tasks}


def write_report(root: Path, report: dict[str, Any]) -> None:
    """Writes `report` to `<root>/meta/recording_report.json`."""
    (root / "meta").mkdir(parents=True, exist_ok=True)
    with open(root / "meta" / REPORT_FILENAME, "w") as f:
        json.dump(report, f, indent=2)


def format_report(episodes: list[EpisodeReport]) -> str:
    """A table of the attempted episodes (one row each, the start fields as columns) and the totals."""
    start_keys = list(episodes[0].start) if episodes else []
    widths = {key: max(len(key), 6) for key in start_keys}
    starts = "".join(f" {key:>{widths[key]}}" for key in start_keys)
    header = f"{'task':<28}{starts} {'success':>7} {'steps':>5} {'kept':>5} {'episode':>7}"
    lines = [header, "-" * len(header)]
    for ep in episodes:
        index = "-" if ep.dataset_episode_index is None else str(ep.dataset_episode_index)
        starts = "".join(f" {ep.start[key]:>{widths[key]}}" for key in start_keys)
        lines.append(
            f"{ep.task:<28}{starts} {str(ep.success):>7} {ep.n_steps:>5} {str(ep.kept):>5} {index:>7}"
        )
    n_success, n_kept = sum(ep.success for ep in episodes), sum(ep.kept for ep in episodes)
    lines.append(f"{n_success}/{len(episodes)} expert episodes succeeded, {n_kept} kept.")
    return "\n".join(lines)
