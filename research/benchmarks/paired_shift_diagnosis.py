"""Issue 32's mild shifts scene by scene: what a shift does to E_c in one scene, and where the default's band puts it.

Every sweep condition runs on the environment seeds of the first held-out vanilla rollouts (3000-3007), and an image
shift leaves the first observation's state as it was: chunk 0 of a shifted rollout and chunk 0 of the vanilla
rollout of the same seed see one scene (the same button position), only the image differs. For the runs
(`metaworld_perturbation_sweep.py` records with E_c, `seed*/<variant>/context_energy_full`):

- **Scene by scene**, per run and condition: the paired move of E_c at chunk 0, E_c(shifted) - E_c(vanilla) of the
  same seed, in units of the scene-to-scene spread (the std of the held-out vanilla rollouts' chunk-0 E_c); how many
  pairs move the majority's way; the default score's signed aggregate a = mean_t z_t over the first 3 chunks
  (`context_energy_two_sided`, calibrated as `--calibrate_to` saves it), median over the condition's rollouts; the
  default's AUROC (its score |a|) against every held-out vanilla rollout. Over the runs: every condition that moves
  chunk-0 E_c by less than `MILD_SPREADS` scene spreads.
- **The band's centre**, per run: the default's per-rollout form |a| with its per-index band mu_v[t], sigma_v[t]
  fitted on the calibration rollouts' E_c by a trimmed mean and std (`TRIMS`: the share cut on each side; 0 is the
  shipped fit) or by the median and IQR / 1.349: pooled AUROC over the conditions, the worst condition, and the
  conditions whose AUROC interval lies wholly under 0.5, on the sweep and on the fresh re-runs of the run's near
  misses (scored against its 100 fresh vanilla rollouts, `context_energy_fresh`) where there are.
- **The band's centre over calibration draws**: every run is calibrated on the same scenes, so the same band fits
  are refitted on `CALIBRATION_DRAWS` sets of `CALIBRATION_SIZE` rollouts drawn from each run's fresh vanilla
  rollouts, counting the sets that leave a sweep condition confidently under 0.5.

    cd benchmarks && python paired_shift_diagnosis.py --results results/metaworld_sweep_margin_full \
        --output results/metaworld_sweep_margin_full/paired_shift_diagnosis.md      # about 2.5 min on one core

`--score=context_phase_energy` ranks by the one-sided a instead of |a| (the default for an E_c trained flat at the
data, `--variant=observation_r1`); the band's fits and draws are then those of that score.
"""

import argparse
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import research_scores  # noqa: F401  (registers the research scores in the package's SCORES)
from scipy import stats
from window_report import score_sets
from window_typicality import conditions_in, episodes_in

from lerobot_policy_ebvla.monitoring.metrics import auroc, markdown_table, marked_auroc
from lerobot_policy_ebvla.runtime.statistics import MIN_SIGMA, PHASE_SIGMA_FLOOR

DEFAULT_SCORE = "context_energy_two_sided"
# The default for an E_c trained flat at the data (`energy_ood_gradient_penalty`): its signed aggregate a, one-sided.
ONE_SIDED_SCORE = "context_phase_energy"
SCORE_CHOICES = (DEFAULT_SCORE, ONE_SIDED_SCORE)
FIRST_CHUNKS = 3
# Shares of the calibration's E_c cut on each side, per chunk index, before its mean and std.
TRIMS = (0.0, 0.05, 0.10, 0.20)
MEDIAN = "median / IQR"
# Calibration sets drawn from each run's fresh vanilla rollouts, and their size (the sweep's calibration size).
CALIBRATION_DRAWS = 30
CALIBRATION_SIZE = 20
# A condition is mild when its median paired move of chunk-0 E_c is under this many scene-to-scene spreads.
MILD_SPREADS = 2.0


@dataclass(frozen=True)
class RunRecords:
    """One run's episodes, each record folder read once: the sweep's calibration, held-out vanilla and condition
    rollouts, and its fresh vanilla rollouts and fresh re-runs of conditions where it has them."""

    calibration: dict
    vanilla: dict
    conditions: dict[str, dict]
    fresh_vanilla: dict | None
    fresh_conditions: dict[str, dict]

    @classmethod
    def read(cls, sweep: Path) -> "RunRecords":
        """The records of a sweep folder and of `context_energy_fresh/` beside it."""
        fresh = sweep.parent / "context_energy_fresh"
        has_fresh = (fresh / "vanilla").is_dir()
        return cls(
            episodes_in(sweep / "calibration"),
            episodes_in(sweep / "vanilla"),
            conditions_in(sweep),
            episodes_in(fresh / "vanilla") if has_fresh else None,
            conditions_in(fresh) if has_fresh else {},
        )


def first_context_energies(episodes: Mapping, chunks: int | None = FIRST_CHUNKS) -> dict[int, np.ndarray]:
    """Each episode's E_c over its first `chunks` chunks (None: all), by environment seed."""
    return {
        episode[0].seed: np.array(
            [r.context_energy for r in sorted(episode, key=lambda r: r.chunk_index)[:chunks]]
        )
        for episode in episodes.values()
    }


def fit_name(fit: float | str) -> str:
    """A band fit's row label."""
    return fit if fit == MEDIAN else f"trimmed {fit:.0%}"


def scene_headers(score: str = DEFAULT_SCORE) -> list[str]:
    """The scene-by-scene table's headers; the last names what the score ranks, |a| or a."""
    ranked = "a" if score == ONE_SIDED_SCORE else "abs a"
    return [
        "condition",
        "chunk-0 E_c move, scene spreads: median [min, max]",
        "pairs the majority's way",
        "shifted a (median)",
        f"default AUROC ({ranked})",
    ]


def ranked(a: np.ndarray, score: str) -> np.ndarray:
    """What `score` ranks rollouts by, from their signed aggregates a: |a| (two-sided) or a."""
    return a if score == ONE_SIDED_SCORE else np.abs(a)


def scene_rows(run: RunRecords, score: str = DEFAULT_SCORE) -> tuple[str, list[list[str]], list[float]]:
    """The scene-by-scene table of one run: its caption, its rows and each row's median move."""
    vanilla, conditions = run.vanilla, run.conditions
    _, scored = score_sets(run.calibration, {"vanilla": vanilla, **conditions}, score, FIRST_CHUNKS)
    # The signed aggregate a is the last window value of either score: (|a|, a) or (a,).
    signed = {
        name: dict(zip((c[0].seed for c in s.episodes.values()), s.values[:, -1], strict=True))
        for name, s in scored.items()
    }
    vanilla_first = {seed: e[0] for seed, e in first_context_energies(vanilla).items()}
    spread = float(np.std(list(vanilla_first.values())))
    rows, medians, scenes = [], [], set()
    for name in conditions:
        shifted = first_context_energies(conditions[name])
        scenes |= set(shifted)
        moves = np.array([e[0] - vanilla_first[seed] for seed, e in shifted.items()]) / spread
        majority = max(int((moves > 0).sum()), int((moves < 0).sum()))
        own = np.array([signed[name][seed] for seed in shifted])
        cell, _ = marked_auroc(ranked(scored["vanilla"].values[:, -1], score), ranked(own, score))
        medians.append(float(np.median(moves)))
        rows.append(
            [
                name,
                f"{medians[-1]:+.2f} [{moves.min():+.2f}, {moves.max():+.2f}]",
                f"{majority}/{moves.size}",
                f"{np.median(own):+.2f}",
                cell,
            ]
        )
    held_out = np.array(list(signed["vanilla"].values()))
    caption = (
        f"Scene-to-scene spread of chunk-0 E_c over {len(vanilla_first)} held-out vanilla rollouts: {spread:.3f}. "
        f"The default's signed aggregate a of the held-out vanilla rollouts: median {np.median(held_out):+.2f}, "
        f"std {held_out.std():.2f} (the calibration's z: std 1 at each chunk index); of the {len(scenes)} vanilla "
        f"rollouts of the conditions' scenes: median {np.median([signed['vanilla'][s] for s in scenes]):+.2f}."
    )
    return caption, rows, medians


def mild_summary(scenes_by_run: Mapping[str, tuple], score: str = DEFAULT_SCORE) -> str:
    """The conditions that move chunk-0 E_c by under `MILD_SPREADS` scene spreads (median), over the runs; how many
    conditions move it one way on every pair; and the default's lowest AUROC over the other conditions."""
    rows, one_way, total, others = [], 0, 0, []
    for run, (_, run_rows, medians) in scenes_by_run.items():
        for row, median in zip(run_rows, medians, strict=True):
            majority, n = (int(k) for k in row[2].split("/"))
            one_way += majority == n
            total += 1
            if abs(median) < MILD_SPREADS:
                rows.append([run, *row])
            else:
                others.append(float(row[4].split()[0]))
    return (
        f"Conditions whose every pair moves chunk-0 E_c one way: {one_way} of {total}. The {total - len(rows)} "
        f"that move it by {MILD_SPREADS:g} scene spreads or more (median) score at least {min(others):.2f} by the "
        f"default; those that move it less:\n\n{markdown_table(['run', *scene_headers(score)], rows)}"
    )


def band(calibration: Mapping[int, np.ndarray], fit: float | str) -> tuple[np.ndarray, np.ndarray]:
    """mu_v[t], sigma_v[t] of the calibration's E_c (whole episodes) at each of the first chunk indices, sigma
    floored as the shipped fit floors it (`PhaseStatistics`: 0.1 times the std of every calibration chunk's E_c)."""
    floor = max(PHASE_SIGMA_FLOOR * float(np.concatenate(list(calibration.values())).std()), MIN_SIGMA)
    means, stds = [], []
    for t in range(FIRST_CHUNKS):
        at_t = np.array([e[t] for e in calibration.values() if e.size > t])
        if fit == MEDIAN:
            low, high = np.percentile(at_t, [25, 75])
            means.append(np.median(at_t))
            stds.append(max((high - low) / 1.349, floor))
        else:
            kept = stats.trimboth(at_t, fit) if fit else at_t
            means.append(kept.mean())
            stds.append(max(kept.std(), floor))
    return np.array(means), np.array(stds)


def rollout_scores(
    episodes: Mapping[int, np.ndarray], mu: np.ndarray, sigma: np.ndarray, score: str = DEFAULT_SCORE
) -> np.ndarray:
    """|mean_t z_t| (or mean_t z_t, one-sided) of each rollout against the band."""
    a = np.array([np.mean((e - mu[: e.size]) / sigma[: e.size]) for e in episodes.values()])
    return ranked(a, score)


def centre_row(run: RunRecords, fit: float | str, score: str = DEFAULT_SCORE) -> list[str]:
    """One band fit's row for one run."""
    mu, sigma = band(first_context_energies(run.calibration, None), fit)
    vanilla = rollout_scores(first_context_energies(run.vanilla), mu, sigma, score)
    conditions = {
        name: rollout_scores(first_context_energies(e), mu, sigma, score)
        for name, e in run.conditions.items()
    }
    cells = {name: marked_auroc(vanilla, scores) for name, scores in conditions.items()}
    worst = min(cells, key=lambda name: cells[name][1])
    under = [f"{name} {cell}" for name, (cell, _) in cells.items() if cell.endswith("!")]
    fresh_cells = []
    if run.fresh_vanilla is not None:
        fresh_vanilla = rollout_scores(first_context_energies(run.fresh_vanilla), mu, sigma, score)
        for name, e in run.fresh_conditions.items():
            cell, _ = marked_auroc(fresh_vanilla, rollout_scores(first_context_energies(e), mu, sigma, score))
            fresh_cells.append(f"{name} {cell}")
    pooled = auroc(vanilla, np.concatenate(list(conditions.values())))
    return [
        fit_name(fit),
        f"{pooled:.3f}",
        f"{worst} {cells[worst][0]}",
        "; ".join(under) or "none",
        "; ".join(fresh_cells) or "-",
    ]


def draw_rows(runs: Mapping[str, RunRecords], score: str = DEFAULT_SCORE) -> list[list[str]]:
    """Per band fit: over `CALIBRATION_DRAWS` calibration sets of `CALIBRATION_SIZE` rollouts drawn from each run's
    fresh vanilla rollouts (one seeded stream per run, the same sets for every fit), how many sets leave a sweep
    condition confidently under 0.5 against the sweep's held-out vanilla rollouts, per run and in all; and the
    pooled AUROC's median and minimum over every set."""
    fits = (*TRIMS, MEDIAN)
    marked = {fit: {} for fit in fits}
    pooled = {fit: [] for fit in fits}
    for run, records in runs.items():
        fresh = list(first_context_energies(records.fresh_vanilla, None).values())
        held_out = first_context_energies(records.vanilla)
        conditions = [first_context_energies(e) for e in records.conditions.values()]
        rng = np.random.default_rng(0)
        for _ in range(CALIBRATION_DRAWS):
            drawn = rng.choice(len(fresh), CALIBRATION_SIZE, replace=False)
            calibration = {i: fresh[i] for i in drawn}
            for fit in fits:
                mu, sigma = band(calibration, fit)
                vanilla = rollout_scores(held_out, mu, sigma, score)
                shifted = [rollout_scores(e, mu, sigma, score) for e in conditions]
                under = any(marked_auroc(vanilla, scores)[0].endswith("!") for scores in shifted)
                marked[fit][run] = marked[fit].get(run, 0) + under
                pooled[fit].append(auroc(vanilla, np.concatenate(shifted)))
    return [
        [
            fit_name(fit),
            *(str(marked[fit][run]) for run in runs),
            f"{sum(marked[fit].values())} of {CALIBRATION_DRAWS * len(runs)}",
            f"{np.median(pooled[fit]):.3f} [{min(pooled[fit]):.3f}]",
        ]
        for fit in fits
    ]


def draws_section(runs: Mapping[str, RunRecords], score: str = DEFAULT_SCORE) -> str:
    """The calibration draws' table, with its caption."""
    headers = ["band fit", *runs, "all", "pooled: median [min]"]
    return (
        f"Calibration sets of {CALIBRATION_SIZE} drawn {CALIBRATION_DRAWS} times per run from its 100 fresh "
        "vanilla rollouts; each column counts the sets that leave a sweep condition confidently under 0.5 against "
        "the sweep's 40 held-out vanilla rollouts (first 3 chunks).\n\n"
        + markdown_table(headers, draw_rows(runs, score))
    )


def centre_rows(run: RunRecords, score: str = DEFAULT_SCORE) -> list[list[str]]:
    """The band's-centre rows of one run, one per band fit."""
    return [centre_row(run, fit, score) for fit in (*TRIMS, MEDIAN)]


CENTRE_HEADERS = ["band fit", "pooled", "worst condition", "confidently under 0.5", "fresh re-runs"]


def calibration_scenes(runs: list[RunRecords]) -> str:
    """Whether the runs are calibrated on the same scenes, and which of them has the highest chunk-0 E_c most often."""
    calibrations = [first_context_energies(run.calibration) for run in runs]
    seeds = [sorted(calibration) for calibration in calibrations]
    same = "the same" if all(s == seeds[0] for s in seeds) else "not all the same"
    highest = Counter(max(c, key=lambda seed: c[seed][0]) for c in calibrations).most_common(1)[0]
    return (
        f"The runs are calibrated on {same} scenes (environment seeds {seeds[0][0]}-{seeds[0][-1]} on the first); "
        f"env seed {highest[0]} has the highest chunk-0 E_c of them on {highest[1]} of {len(runs)} runs."
    )


def centre_summary(rows_by_run: Mapping[str, list[list[str]]]) -> str:
    """Per band fit, over the runs: the pooled AUROCs' range and the runs with a condition confidently under 0.5."""
    rows = []
    for i, fit in enumerate((*TRIMS, MEDIAN)):
        per_run = {run: run_rows[i] for run, run_rows in rows_by_run.items()}
        pooled = [float(row[1]) for row in per_run.values()]
        sweep_under = [run for run, row in per_run.items() if row[3] != "none"]
        fresh_under = [run for run, row in per_run.items() if "!" in row[4]]
        rows.append(
            [
                fit_name(fit),
                f"{min(pooled):.3f}-{max(pooled):.3f}",
                ", ".join(sweep_under) or "none",
                ", ".join(fresh_under) or "none",
            ]
        )
    headers = [
        "band fit",
        "pooled, range over runs",
        "runs confidently under on the sweep",
        "... on fresh re-runs",
    ]
    return markdown_table(headers, rows)


def run_tables(run: RunRecords, score: str = DEFAULT_SCORE) -> tuple[tuple, list[list[str]]]:
    """One run's scene-by-scene table (`scene_rows`) and band's-centre rows (`centre_rows`)."""
    return scene_rows(run, score), centre_rows(run, score)


def run_section(run: str, scenes: tuple, centres: list[list[str]], score: str = DEFAULT_SCORE) -> str:
    """One run's section: both tables."""
    caption, rows, _ = scenes
    return (
        f"## {run}\n\n### Scene by scene\n\n{caption}\n\n{markdown_table(scene_headers(score), rows)}\n\n"
        f"### The band's centre\n\n{markdown_table(CENTRE_HEADERS, centres)}\n"
    )


def run_sections(results: Path, variant: str = "observation", score: str = DEFAULT_SCORE) -> str:
    """The summaries over every training seed with E_c records of `variant` under `results`, then each run's
    section, for `score` (the two-sided default or, for an E_c trained flat, the one-sided one)."""
    sweeps = sorted(results.glob(f"seed*/{variant}/context_energy_full"), key=lambda p: int(p.parts[-3][4:]))
    runs = {sweep.parts[-3]: RunRecords.read(sweep) for sweep in sweeps}
    tables = {name: run_tables(run, score) for name, run in runs.items()}
    scenes = {name: scene for name, (scene, _) in tables.items()}
    centres = {name: centre for name, (_, centre) in tables.items()}
    with_fresh = {name: run for name, run in runs.items() if run.fresh_vanilla is not None}
    sections = [
        f"## Mild shifts over {len(runs)} runs\n\n{mild_summary(scenes, score)}\n",
        f"## The band's centre over {len(runs)} runs\n\n{calibration_scenes(list(runs.values()))}\n\n"
        f"{centre_summary(centres)}\n",
        f"## The band's centre over calibration draws\n\n{draws_section(with_fresh, score)}\n",
    ]
    sections += [run_section(run, scenes[run], centres[run], score) for run in tables]
    return "\n".join(sections)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--results", type=Path, required=True, help="metaworld_sweep_margin_full")
    parser.add_argument(
        "--variant", default="observation", help="seed*/<variant>/: the preset's records, or a variant's"
    )
    parser.add_argument(
        "--score",
        default=DEFAULT_SCORE,
        choices=SCORE_CHOICES,
        help="the score the tables rank by: the two-sided default, or the one-sided one of an E_c trained flat",
    )
    parser.add_argument("--output", type=Path)
    args = parser.parse_args()
    text = run_sections(args.results, args.variant, args.score)
    print(text)
    if args.output:
        args.output.write_text(text)


if __name__ == "__main__":
    main()
