"""Issue 32's failed-vs-successful target against what knowing the conditions, or the scenes, would reach.

The target asks a score over the first 3 chunks to rank the failed rollouts of a sweep (held-out vanilla and every
condition pooled) over the successful ones at AUROC >= 0.75. An OOD score ranks rollouts by how far their
observations are from vanilla's; how far that can carry is bounded by how the sweep's failures fall. For each run
(`metaworld_perturbation_sweep.py` records, `seed*/<variant>/context_energy_full`) this sets the score beside three
references, each the rollouts' own labels rather than a score (what a detector that knew them would reach):

- **perturbed or not**: a perfect OOD detector;
- **the condition's failure rate**: each rollout ranked by the share of its set (vanilla or its condition) that
  failed, the most a score that knows nothing within a condition can reach;
- **the scene's failure rate elsewhere**: each rollout ranked by how often the other rollouts of its environment
  seed (its scene: the button's position) failed, leave-one-out; only the rollouts whose scene ran elsewhere (every
  condition runs on the scenes of the first held-out vanilla rollouts, 3000-3007).

Then **within a scene**: the score's AUROC over the pairs of a failed and a successful rollout of the same scene (a
shifted rollout that fails against the same scene's vanilla success, and the like), with a bootstrap interval over
scenes, beside the condition-rate reference on the same pairs. The score is calibrated as `ebvla-ood-report
--calibrate_to` would save it, on the run's calibration rollouts (`window_report.score_sets`), and the last column
is what its alarms at that threshold (k = 1) catch: the share of failed and of successful rollouts over it.

    cd benchmarks && python outcome_ceiling.py --results results/metaworld_sweep_margin_full \
        --variant observation_r1 --score context_phase_energy \
        --output results/metaworld_sweep_margin_full/outcome_ceiling_r1.md
"""

import argparse
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import research_scores  # noqa: F401  (registers the research scores in the package's SCORES)
from window_report import score_sets
from window_typicality import conditions_in, episodes_in

from lerobot_policy_ebvla.monitoring.metrics import auroc, format_auroc, markdown_table
from lerobot_policy_ebvla.monitoring.ood_sections import condition_failure_rates

FIRST_CHUNKS = 3
N_BOOTSTRAP = 1000
VANILLA = "vanilla"


@dataclass(frozen=True)
class Rollouts:
    """A run's held-out rollouts (vanilla and every condition): set name, scene, outcome, score, and the share of
    its set's rollouts that failed."""

    sets: np.ndarray
    scenes: np.ndarray
    failed: np.ndarray
    scores: np.ndarray
    set_failure_rates: np.ndarray
    threshold: float


def scored_rollouts(run: Path, score: str, first_chunks: int | None = FIRST_CHUNKS) -> Rollouts:
    """Every held-out rollout of a sweep's records, scored over its first chunks against the run's calibration."""
    sets = {VANILLA: episodes_in(run / VANILLA), **conditions_in(run)}
    calibration, scored = score_sets(episodes_in(run / "calibration"), sets, score, first_chunks)
    names, scenes, failed, scores = [], [], [], []
    for name, scored_set in scored.items():
        for episode, value in zip(scored_set.episodes.values(), scored_set.scores, strict=True):
            names.append(name)
            scenes.append(episode[0].seed)
            failed.append(not episode[0].success)
            scores.append(value)
    # Vanilla's rollouts are one condition ("none") to the report's grouping, as each shift's are.
    every_episode = {key: episode for s in scored.values() for key, episode in s.episodes.items()}
    return Rollouts(
        np.array(names),
        np.array(scenes),
        np.array(failed, dtype=bool),
        np.array(scores, dtype=float),
        condition_failure_rates(every_episode),
        calibration.threshold,
    )


def scene_failure_rates(rollouts: Rollouts) -> np.ndarray:
    """How often the other rollouts of each rollout's scene failed; NaN where its scene ran nowhere else."""
    rates = np.full(len(rollouts.failed), np.nan)
    for i, scene in enumerate(rollouts.scenes):
        others = (rollouts.scenes == scene) & (np.arange(len(rates)) != i)
        if others.any():
            rates[i] = rollouts.failed[others].mean()
    return rates


def pair_wins(scores: np.ndarray, failed: np.ndarray, scenes: np.ndarray) -> dict:
    """Per scene, the wins (a tie a half) of its failed rollouts over its successful ones, and the pair count."""
    wins = {}
    for scene in np.unique(scenes):
        here = scenes == scene
        positives, negatives = scores[here & failed], scores[here & ~failed]
        if positives.size and negatives.size:
            pairs = positives.size * negatives.size
            wins[scene] = (auroc(negatives, positives) * pairs, pairs)
    return wins


def within_scene_auroc(
    scores: np.ndarray, failed: np.ndarray, scenes: np.ndarray, n_bootstrap: int = N_BOOTSTRAP, seed: int = 0
) -> tuple[float, float, float, int, int]:
    """AUROC over the same-scene (failed, successful) pairs, its 95% interval over scenes resampled with
    replacement, the pair count and the scene count."""
    wins = pair_wins(scores, failed, scenes)
    if not wins:
        return np.nan, np.nan, np.nan, 0, 0
    won, pairs = np.array(list(wins.values())).T
    rng = np.random.default_rng(seed)
    draws = rng.integers(0, len(won), size=(n_bootstrap, len(won)))
    resampled = won[draws].sum(axis=1) / pairs[draws].sum(axis=1)
    low, high = np.percentile(resampled, [2.5, 97.5])
    return won.sum() / pairs.sum(), float(low), float(high), int(pairs.sum()), len(won)


def ranked(labels: np.ndarray, failed: np.ndarray) -> str:
    """AUROC [95%] of failed (positives) over successful rollouts by `labels`, over the rollouts that have one."""
    known = ~np.isnan(labels)
    return format_auroc(labels[known & ~failed], labels[known & failed], N_BOOTSTRAP, 0)


def alarm_rates(rollouts: Rollouts) -> str:
    """The share of failed and of successful rollouts over T, the threshold set on the calibration rollouts alone
    (T = mu + k sigma, k = 1): what a user acting on the score's alarms gets."""
    alarmed = rollouts.scores > rollouts.threshold
    failed = rollouts.failed
    return (
        f"{alarmed[failed].sum()}/{failed.sum()} ({alarmed[failed].mean():.0%}) / "
        f"{alarmed[~failed].sum()}/{(~failed).sum()} ({alarmed[~failed].mean():.0%})"
    )


def run_row(name: str, rollouts: Rollouts) -> list[str]:
    failed = rollouts.failed
    perturbed = (rollouts.sets != VANILLA).astype(float)
    by_set, by_scene = rollouts.set_failure_rates, scene_failure_rates(rollouts)
    score_pairs = within_scene_auroc(rollouts.scores, failed, rollouts.scenes)
    rate_pairs = within_scene_auroc(by_set, failed, rollouts.scenes)
    return [
        name,
        f"{len(failed)} ({int(failed.sum())})",
        ranked(rollouts.scores, failed),
        ranked(perturbed, failed),
        ranked(by_set, failed),
        f"{ranked(by_scene, failed)} (n {int((~np.isnan(by_scene)).sum())})",
        f"{score_pairs[0]:.3f} [{score_pairs[1]:.3f}, {score_pairs[2]:.3f}] ({score_pairs[3]} pairs, "
        f"{score_pairs[4]} scenes)",
        f"{rate_pairs[0]:.3f} [{rate_pairs[1]:.3f}, {rate_pairs[2]:.3f}]",
        alarm_rates(rollouts),
    ]


HEADERS = [
    "run",
    "held-out rollouts (failed)",
    "score",
    "reference: perturbed or not",
    "reference: the condition's failure rate",
    "reference: the scene's failure rate elsewhere",
    "score within a scene [95% over scenes]",
    "condition's failure rate within a scene",
    "alarms at T (k = 1, calibration only): failed / successful",
]


def ceiling_table(runs: Mapping[str, Path], score: str, first_chunks: int | None = FIRST_CHUNKS) -> str:
    return markdown_table(
        HEADERS,
        [run_row(name, scored_rollouts(path, score, first_chunks)) for name, path in runs.items()],
    )


def variant_runs(results: Path, variant: str) -> dict[str, Path]:
    """Every training seed's full sweep of `variant`, by seed."""
    found = sorted(results.glob(f"seed*/{variant}/context_energy_full"), key=lambda p: int(p.parts[-3][4:]))
    return {path.parts[-3]: path for path in found}


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--results", type=Path, required=True, help="the folder of seed<SEED>/<variant>/ records"
    )
    parser.add_argument("--variant", action="append", required=True, help="repeatable")
    parser.add_argument("--score", default="context_phase_energy")
    parser.add_argument("--output", type=Path, required=True)
    parser.add_argument(
        "--first_chunks",
        type=int,
        default=FIRST_CHUNKS,
        help="each rollout's first k chunks; 0: whole episodes",
    )
    args = parser.parse_args()
    first_chunks = args.first_chunks or None
    span = f"first {first_chunks} chunks" if first_chunks else "whole episodes"
    span_flag = "" if args.first_chunks == FIRST_CHUNKS else f" --first_chunks={args.first_chunks}"
    sections = []
    for variant in args.variant:
        runs = variant_runs(args.results, variant)
        if not runs:
            raise SystemExit(f"No seed*/{variant}/context_energy_full under {args.results}.")
        sections.append(
            f"## {variant}: `{args.score}`, {span}, failed vs successful\n\n"
            + ceiling_table(runs, args.score, first_chunks)
        )
    args.output.write_text(
        "# Failed vs successful: the score beside what knowing the conditions or the scenes reaches\n\n"
        f"Written by `research/benchmarks/outcome_ceiling.py --score={args.score}{span_flag}`; AUROC [bootstrap 95% interval], "
        "failed rollouts positive.\n\n" + "\n\n".join(sections) + "\n"
    )
    print(f"Wrote {args.output}")


if __name__ == "__main__":
    main()
