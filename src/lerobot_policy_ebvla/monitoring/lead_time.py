"""How far ahead of a failure the energy-slope alarms come (Table IV's lead time), and when the failure began.

`failure.first_alarms` runs the per-step chosen configurations as a monitor and gives one `Alarm` per episode;
`LeadTimeSummary` and the two tables count the failures caught before their last chunk, the median lead and the
successes alarmed. The lead is measured to the last chunk (the failure or the step cap) and, where the records
carry the env's goal distance (LIBERO), to the failure's onset (`failure_onset`): the last chunk at which its object
was still coming closer to the goal, negative for an alarm after the onset.
"""

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .metrics import markdown_table, percent
from .records import Episode

# Closer to the goal than at the last progress by more than this (metres) is progress: the jitter of an object
# held still or resting against the basket is not.
ONSET_PROGRESS_M = 0.01


def failure_onset(episode: Episode, progress_m: float = ONSET_PROGRESS_M) -> int | None:
    """The 1-based step of an episode's last progress: the last chunk whose goal distance was below the one of
    the previous progress by more than `progress_m` (step 1 when it never came closer). From the next chunk
    on, the object came no closer. None when a record has no `goal_distance`."""
    distances = [record.goal_distance for record in episode]
    if not distances or any(d is None for d in distances):
        return None
    onset, best = 1, distances[0]
    for step, distance in enumerate(distances[1:], start=2):
        if distance < best - progress_m:
            onset, best = step, distance
    return onset


@dataclass(frozen=True)
class Alarm:
    """When the per-step chosen configurations first flagged one episode, and how long before its end.

    Args:
        task: The episode's task.
        episode_index: Its index in its run.
        seed: Its env seed.
        failed: Whether it failed (the alarm is a catch) or succeeded (a false alarm).
        n_chunks: Its chunks: its last step is `n_chunks`.
        step: The first step flagged, None when never flagged.
        lead_chunks: Chunks from the alarm's chunk to the last: `n_chunks - step` (0: at the last chunk).
        lead_env_steps: Env steps from the alarm chunk's prediction to the last chunk's.
        onset: A failed episode's `failure_onset`; None for a success or records without goal distances.
        lead_to_onset_chunks: `onset - step`, chunks from the alarm to the onset (negative: after it).
    """

    task: str
    episode_index: int
    seed: int | None
    failed: bool
    n_chunks: int
    step: int | None = None
    lead_chunks: int | None = None
    lead_env_steps: int | None = None
    onset: int | None = None
    lead_to_onset_chunks: int | None = None


@dataclass(frozen=True)
class LeadTimeSummary:
    """How far ahead of the failures the alarms came, and how many successes they flagged.

    Medians are over the failed episodes that were alarmed (NaN when none was).
    """

    n_failed: int
    n_successful: int
    failed_alarmed: int
    failed_alarmed_before_last_chunk: int
    successful_alarmed: int
    median_lead_chunks: float
    median_lead_env_steps: float
    # Over the caught failures with an onset (records with goal distances); NaN when there is none.
    median_lead_to_onset_chunks: float = math.nan
    failed_alarmed_before_onset: int = 0
    failed_with_onset: int = 0

    @classmethod
    def of(cls, alarms: Sequence[Alarm]) -> "LeadTimeSummary":
        caught = [a for a in alarms if a.failed and a.step is not None]
        to_onset = [a.lead_to_onset_chunks for a in caught if a.lead_to_onset_chunks is not None]
        return cls(
            n_failed=sum(a.failed for a in alarms),
            n_successful=sum(not a.failed for a in alarms),
            failed_alarmed=len(caught),
            failed_alarmed_before_last_chunk=sum(a.lead_chunks > 0 for a in caught),
            successful_alarmed=sum(not a.failed and a.step is not None for a in alarms),
            median_lead_chunks=float(np.median([a.lead_chunks for a in caught])) if caught else math.nan,
            median_lead_env_steps=float(np.median([a.lead_env_steps for a in caught]))
            if caught
            else math.nan,
            median_lead_to_onset_chunks=float(np.median(to_onset)) if to_onset else math.nan,
            failed_alarmed_before_onset=sum(lead >= 0 for lead in to_onset),
            failed_with_onset=sum(a.failed and a.onset is not None for a in alarms),
        )


def _fraction(count: int, total: int) -> str:
    return f"{count}/{total} ({percent(count / total if total else math.nan)})"


def format_lead_time_table(summaries: dict[str, LeadTimeSummary]) -> str:
    """One row per scope (pooled, a task): failures alarmed before their last chunk, the median lead, and
    the successes alarmed (false alarms)."""
    headers = [
        "Scope",
        "Failed",
        "Successful",
        "Failures alarmed before their last chunk",
        "Failures alarmed",
        "Median lead (chunks)",
        "Median lead (env steps)",
        "Successes alarmed",
    ]
    rows = [
        [
            scope,
            s.n_failed,
            s.n_successful,
            _fraction(s.failed_alarmed_before_last_chunk, s.n_failed),
            _fraction(s.failed_alarmed, s.n_failed),
            f"{s.median_lead_chunks:g}",
            f"{s.median_lead_env_steps:g}",
            _fraction(s.successful_alarmed, s.n_successful),
        ]
        for scope, s in summaries.items()
    ]
    if any(s.failed_with_onset for s in summaries.values()):  # records with goal distances
        headers += ["Failures alarmed at or before their onset", "Median lead to onset (chunks)"]
        for row, s in zip(rows, summaries.values(), strict=True):
            row += [
                _fraction(s.failed_alarmed_before_onset, s.failed_with_onset),
                f"{s.median_lead_to_onset_chunks:g}",
            ]
    return markdown_table(headers, rows)


def format_alarms(alarms: Sequence[Alarm]) -> str:
    """One row per failed episode: its first alarm and the lead it gave ("never" when not alarmed)."""
    headers = ["Task", "Episode", "Seed", "Chunks", "First alarm (step)", "Lead (chunks)", "Lead (env steps)"]
    failed = [a for a in alarms if a.failed]
    rows = [
        [
            a.task,
            a.episode_index,
            a.seed,
            a.n_chunks,
            *(("never", "", "") if a.step is None else (a.step, a.lead_chunks, a.lead_env_steps)),
        ]
        for a in failed
    ]
    if any(a.onset is not None for a in failed):  # records with goal distances
        headers += ["Onset (step)", "Lead to onset (chunks)"]
        for row, a in zip(rows, failed, strict=True):
            row += [
                a.onset if a.onset is not None else "",
                "" if a.lead_to_onset_chunks is None else a.lead_to_onset_chunks,
            ]
    return markdown_table(headers, rows)
