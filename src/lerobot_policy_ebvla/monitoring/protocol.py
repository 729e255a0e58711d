"""The held-out protocol both reports follow: nothing a report is judged on may have calibrated it.

A report has a calibration side (the episodes that fit its thresholds, choose its configurations, set its
reference) and a report side (the episodes it is judged on). It is in-sample when

- no calibration episodes were given (the report set calibrates itself),
- both sides share a record file (whatever the spelling of its path), or
- both sides share an episode seed of the same task and condition (perturbation, severity): two runs of the
  same seeds replay the same episodes, even when their records sit in other files.

An in-sample report is refused unless asked for (`--in_sample=true`), and then labelled IN-SAMPLE. Unseeded
episodes (`seed` None) cannot be matched by seed; only their files count.
"""

from collections.abc import Iterable, Mapping
from typing import NamedTuple

from .records import VANILLA_PERTURBATION, Episode, EpisodeKey

# Seeds named per (task, condition) in the error; the rest are counted.
_MAX_SEEDS_NAMED = 10


class SeededEpisode(NamedTuple):
    """What makes two episodes the same rollout: the env seed of one task under one condition."""

    task: str
    perturbation: str
    severity: float
    seed: int


def seeded_episodes(episodes: Iterable[Episode]) -> set[SeededEpisode]:
    """The (task, perturbation, severity, seed) of each seeded episode."""
    return {
        SeededEpisode(e[0].task, e[0].perturbation, e[0].severity, e[0].seed)
        for e in episodes
        if e and e[0].seed is not None
    }


def _describe_seeds(shared: set[SeededEpisode]) -> str:
    groups: dict[tuple[str, str, float], list[int]] = {}
    for episode in sorted(shared):
        groups.setdefault(episode[:3], []).append(episode.seed)
    described = []
    for (task, perturbation, severity), seeds in groups.items():
        condition = "vanilla" if perturbation == VANILLA_PERTURBATION else f"{perturbation} {severity:g}"
        named = ", ".join(str(s) for s in seeds[:_MAX_SEEDS_NAMED])
        more = f", ... ({len(seeds)} in all)" if len(seeds) > _MAX_SEEDS_NAMED else ""
        described.append(f"task {task!r} ({condition}): seeds {named}{more}")
    return "; ".join(described)


def check_held_out(
    calibration: Mapping[tuple[str, EpisodeKey], Episode] | None,
    report: Mapping[tuple[str, EpisodeKey], Episode],
    in_sample: bool = False,
) -> bool:
    """Whether a report is in-sample (see the module docstring); refuses it unless `in_sample` allows it.

    Args:
        calibration: The calibration side's episodes keyed by (record file, episode), as
            `records.load_episodes` returns them; None when no calibration episodes were given.
        report: The report side's episodes, keyed alike.
        in_sample: Allow an in-sample report (`--in_sample=true`).

    Returns:
        True when the report is in-sample (and allowed), False when it is held out.

    Raises:
        ValueError: The report is in-sample and `in_sample` is False; the message names the shared files or
            seeds and how to allow it.
    """
    if calibration is None:
        why = "no `--calibration` episodes were given"
    elif shared_files := sorted({f for f, _ in calibration} & {f for f, _ in report}):
        why = f"the calibration and report sets share the record file(s) {shared_files}"
    elif shared_seeds := seeded_episodes(calibration.values()) & seeded_episodes(report.values()):
        why = (
            f"the calibration and report sets share {len(shared_seeds)} episode seed(s), the same rollouts "
            f"run twice: {_describe_seeds(shared_seeds)}"
        )
    else:
        return False
    if not in_sample:
        raise ValueError(
            f"Refusing an in-sample report: {why}. Calibrate on other episodes (other seeds) with "
            "`--calibration`, or pass `--in_sample=true` to report in-sample (labelled as such)."
        )
    return True
