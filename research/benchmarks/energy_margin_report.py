"""Per-condition table of sweep records: success, and the final energy's AUROC one- and two-sided (issue 32).

For each run (a folder of `metaworld_perturbation_sweep.py` records: `calibration/`, `vanilla/`, one folder per
condition) and each condition: the success rate of the 8 (or n) held-out rollouts; the AUROC of the rollout
score against the held-out vanilla rollouts, with a stratified bootstrap 95% interval, where a rollout's score is
the mean over its first `--chunks` chunks of

- one-sided: the raw final energy E(a^(K_inf), C) (the paper's score);
- two-sided: the mean of |z_k|, z_k = (E_k - mu_v[k]) / sigma_v[k] against the calibration rollouts' final
  energy at the same chunk index k: the `phase_energy_deviation` score (shipped when this report was written, now
  `research_scores.py`), fitted on the calibration rollouts;

and whether the condition is inverted (AUROC < 0.5).

Below it, each run's vanilla success over every vanilla rollout it has (`vanilla/` and `vanilla_extra/`, extra
seeds that are not a perturbation) and, on the seeds it shares with the first run, the episodes it won and lost
against it with the exact sign test: with 40 rollouts a side, two training realizations of one recipe differ by
10 points.

Conditions re-run on fresh rollouts (`--fresh name=RUN_DIR,FRESH_DIR`) get a last table: each against the
run's `vanilla_extra/` rollouts, so that neither side took part in choosing them.

    python research/benchmarks/energy_margin_report.py --runs without=DIR1 with=DIR2 --output=table.md
"""

import argparse
from pathlib import Path

import numpy as np
from best_of_n_closed_loop import paired_against, success_cell
from research_scores import PhaseEnergyDeviation

from lerobot_policy_ebvla.monitoring.baselines import episode_readout
from lerobot_policy_ebvla.monitoring.metrics import auroc, bootstrap_auroc_interval
from lerobot_policy_ebvla.monitoring.records import group_by_episode, read_energy_records, records_file_in
from lerobot_policy_ebvla.runtime.calibration import OODCalibration
from lerobot_policy_ebvla.runtime.scores import ChunkInputs, VanillaRollouts, score_rollout
from lerobot_policy_ebvla.runtime.threshold import exceeds


def episodes(folder: Path) -> list[list]:
    records = read_energy_records(records_file_in(folder))
    return [sorted(chunks, key=lambda r: r.chunk_index) for chunks in group_by_episode(records).values()]


def energies(episode: list) -> np.ndarray:
    return np.array([r.final_energy for r in episode])


def fit_deviation(calibration: list[list]) -> PhaseEnergyDeviation:
    return PhaseEnergyDeviation.fit(VanillaRollouts([episode_readout(ep) for ep in calibration]))


def mean_energies(eps: list[list], chunks: int | None) -> np.ndarray:
    """Each episode's raw final energy, the mean over its first `chunks` chunks (None: the whole episode)."""
    return np.array([energies(ep[:chunks]).mean() for ep in eps])


def scores(eps: list[list], chunks: int, deviation: PhaseEnergyDeviation) -> tuple[np.ndarray, np.ndarray]:
    """Each episode's raw final energy and `phase_energy_deviation`, both the mean over its first chunks."""
    two_sided = [
        score_rollout(deviation, deviation.components(ChunkInputs.of(episode_readout(ep[:chunks]))), "mean")
        for ep in eps
    ]
    return mean_energies(eps, chunks), np.array(two_sided)


def cell(negatives: np.ndarray, positives: np.ndarray) -> tuple[str, float, float]:
    """'AUROC [low, high]' (marked **inv** under 0.5), the AUROC, and the interval's upper bound (under 0.5:
    confidently under)."""
    value = auroc(negatives, positives)
    low, high = bootstrap_auroc_interval(negatives, positives)
    mark = " **inv**" if value < 0.5 else ""
    return f"{value:.2f} [{low:.2f}, {high:.2f}]{mark}", value, high


def condition_row(eps: list[list], rollout_scores: tuple, vanilla_scores: tuple) -> dict:
    """A condition's n, success and AUROCs against vanilla: its rollouts' and the vanilla rollouts' (raw,
    two-sided) scores, one-sided from the first, two-sided from the second."""
    return {
        "n": len(eps),
        "success": np.mean([ep[0].success for ep in eps]),
        "one_sided": cell(vanilla_scores[0], rollout_scores[0]),
        "two_sided": cell(vanilla_scores[1], rollout_scores[1]),
    }


def run_table(folder: Path, chunks: int) -> dict[str, dict]:
    deviation = fit_deviation(episodes(folder / "calibration"))
    vanilla = episodes(folder / "vanilla")
    v_raw, v_two = scores(vanilla, chunks, deviation)
    rows = {"vanilla": {"n": len(vanilla), "success": np.mean([ep[0].success for ep in vanilla])}}
    # (success, raw, two-sided) of every held-out rollout, by where it comes from.
    held_out = {"vanilla": list(zip([ep[0].success for ep in vanilla], v_raw, v_two, strict=True))}
    for sub in sorted(p for p in folder.iterdir() if p.is_dir() and p.name not in ("calibration", "vanilla")):
        if records_file_in(sub) is None:
            continue
        eps = episodes(sub)
        raw, two = scores(eps, chunks, deviation)
        rows[sub.name] = condition_row(eps, (raw, two), (v_raw, v_two))
        # Extra vanilla rollouts are not a perturbation.
        group = "vanilla_extra" if sub.name == "vanilla_extra" else "shifted"
        held_out.setdefault(group, []).extend(zip([ep[0].success for ep in eps], raw, two, strict=True))
    shifted = np.array(held_out["shifted"])
    rows["all perturbations pooled"] = {
        "n": len(shifted),
        "success": shifted[:, 0].mean(),
        "one_sided": cell(v_raw, shifted[:, 1]),
        "two_sided": cell(v_two, shifted[:, 2]),
    }
    # Failed vs successful, both forms over the first chunks: over the 40 held-out vanilla and the perturbed
    # rollouts together (the figure), then apart: a score that flags every shift, whether the policy
    # copes or not, splits the pool by condition, not by outcome.
    sets = {
        "all held out": held_out["vanilla"] + held_out["shifted"],
        "vanilla only": held_out["vanilla"] + held_out.get("vanilla_extra", []),
        "perturbed only": held_out["shifted"],
    }
    for name, rollouts in sets.items():
        rollouts = np.array(rollouts)
        succeeded = rollouts[:, 0].astype(bool)
        rows[f"failed vs successful ({name})"] = {
            "n": len(rollouts),
            "success": succeeded.mean(),
            "one_sided": cell(rollouts[succeeded, 1], rollouts[~succeeded, 1]),
            "two_sided": cell(rollouts[succeeded, 2], rollouts[~succeeded, 2]),
        }
    return rows


def fresh_table(folder: Path, fresh: Path, chunks: int) -> dict[str, dict]:
    """The conditions re-run on fresh rollouts (`fresh/<condition>/`, new environment seeds), each scored
    against the run's `vanilla_extra/` rollouts: neither took part in choosing which conditions to re-run (the
    sweep's own rollouts against `vanilla/` did), so these AUROCs are free of that selection.

    Beside the first chunks' AUROCs: the raw final energy's AUROC over the whole episode, and the share of each
    side's rollouts over the threshold a user ships: `OODCalibration.fit` on the calibration rollouts' first-chunk
    scores, as `--calibrate_to` saves it by default (T = mu_v + 1.0 sigma_v), set on the calibration alone."""
    calibration = episodes(folder / "calibration")
    deviation = fit_deviation(calibration)
    threshold = OODCalibration.fit(mean_energies(calibration, chunks)).threshold
    vanilla_episodes = episodes(folder / "vanilla_extra")
    vanilla = scores(vanilla_episodes, chunks, deviation)
    vanilla_whole = mean_energies(vanilla_episodes, None)
    rows = {}
    for sub in sorted(p for p in fresh.iterdir() if p.is_dir() and records_file_in(p) is not None):
        eps = episodes(sub)
        first = scores(eps, chunks, deviation)
        row = condition_row(eps, first, vanilla)
        row["n_vanilla"] = len(vanilla[0])
        row["whole_episode"] = cell(vanilla_whole, mean_energies(eps, None))
        row["alarms"] = exceeds(first[0], threshold).mean()
        row["vanilla_alarms"] = exceeds(vanilla[0], threshold).mean()
        rows[sub.name] = row
    return rows


def vanilla_outcomes(folder: Path) -> dict[str, dict]:
    """The success of each vanilla rollout of a run, by rollout seed, in `vanilla/` and `vanilla_extra/`."""
    return {
        c: {"outcomes": {ep[0].seed: ep[0].success for ep in episodes(folder / c)}}
        for c in ("vanilla", "vanilla_extra")
        if (folder / c).is_dir()
    }


def paired_success(rows: dict[str, dict]) -> dict[str, tuple[int, int, int, int, float]]:
    """Per run: successes and n over its vanilla rollouts, and on the rollouts it shares with the first run
    (same folder and seed), (wins, losses, sign-test p) against it."""
    base = next(iter(rows.values()))
    out = {}
    for name, row in rows.items():
        shared = {
            c: {"outcomes": {s: o for s, o in row[c]["outcomes"].items() if s in base[c]["outcomes"]}}
            for c in row
            if c in base
        }
        outcomes = [o for c in row for o in row[c]["outcomes"].values()]
        out[name] = (sum(outcomes), len(outcomes), *paired_against(base, shared, list(shared)))
    return out


def vanilla_success(folders: dict[str, Path]) -> dict[str, tuple[int, int, int, int, float]]:
    """Per run: vanilla successes and n over `vanilla/` and `vanilla_extra/`, and on the seeds shared with the
    first run, (wins, losses, sign-test p) against it."""
    return paired_success({name: vanilla_outcomes(folder) for name, folder in folders.items()})


def vanilla_success_over_seeds(runs: dict[str, list[Path]]) -> dict[str, tuple[int, int, int, int, float]]:
    """`vanilla_success` of each recipe pooled over its training seeds: `runs` gives each recipe's run folders,
    one per training seed in the same order for every recipe, and a rollout is paired with the first recipe's
    rollout of the same training seed and rollout seed."""
    return paired_success(
        {
            name: {
                f"{i}/{c}": row
                for i, folder in enumerate(folders)
                for c, row in vanilla_outcomes(folder).items()
            }
            for name, folders in runs.items()
        }
    )


def emit(lines: list[str], output: Path | None) -> None:
    """Print a table's lines, and write them to `output` when given."""
    text = "\n".join(lines)
    print(text)
    if output:
        output.write_text(text + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", nargs="+", required=True, help="name=folder of sweep records")
    parser.add_argument(
        "--seeds",
        nargs="*",
        default=[],
        help="name=DIR1,DIR2,...: a recipe's runs, one per training seed, for the vanilla success pooled over seeds",
    )
    parser.add_argument(
        "--fresh",
        nargs="*",
        default=[],
        help="name=RUN_DIR,FRESH_DIR: conditions re-run on fresh rollouts, against RUN_DIR's vanilla_extra",
    )
    parser.add_argument("--chunks", type=int, default=3)
    parser.add_argument("--output", type=Path)
    args = parser.parse_args()
    runs = dict(item.split("=", 1) for item in args.runs)
    tables = {name: run_table(Path(folder), args.chunks) for name, folder in runs.items()}
    conditions = list(next(iter(tables.values())))
    header = ["condition"]
    for name in runs:
        header += [f"{name}: success (n)", f"{name}: AUROC E, first {args.chunks}", f"{name}: AUROC abs(z)"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for condition in conditions:
        cells = [condition]
        for table in tables.values():
            row = table.get(condition)
            if row is None:
                cells += ["-", "-", "-"]
                continue
            cells.append(f"{100 * row['success']:.0f}% ({row['n']})")
            cells += [row["one_sided"][0], row["two_sided"][0]] if "one_sided" in row else ["-", "-"]
        lines.append("| " + " | ".join(cells) + " |")
    first = next(iter(runs))
    lines += [
        "",
        f"| run | vanilla success [Wilson 95%] | won / lost against {first}, same seeds | sign test p |",
    ]
    lines.append("|---|---|---|---|")
    for name, (successes, n, wins, losses, p) in vanilla_success(
        {name: Path(folder) for name, folder in runs.items()}
    ).items():
        lines.append(f"| {name} | {success_cell(successes, n)} | +{wins} / -{losses} | {p:.2f} |")
    if args.seeds:
        seeds = {
            name: [Path(f) for f in folders.split(",")]
            for name, folders in (i.split("=", 1) for i in args.seeds)
        }
        first = next(iter(seeds))
        lines += [
            "",
            f"| recipe, pooled over training seeds | vanilla success [Wilson 95%] | won / lost against {first} | sign test p |",
            "|---|---|---|---|",
        ]
        for name, (successes, n, wins, losses, p) in vanilla_success_over_seeds(seeds).items():
            lines.append(f"| {name} | {success_cell(successes, n)} | +{wins} / -{losses} | {p:.2f} |")
    if args.fresh:
        lines += [
            "",
            f"| run | re-run condition | success (n) | AUROC E, first {args.chunks}, vs vanilla_extra (n) | AUROC abs(z) "
            f"| AUROC E, whole episode | alarms at T, condition / vanilla_extra |",
            "|---|---|---|---|---|---|---|",
        ]
        for item in args.fresh:
            name, folders = item.split("=", 1)
            run_folder, fresh_folder = (Path(f) for f in folders.split(","))
            for condition, row in fresh_table(run_folder, fresh_folder, args.chunks).items():
                lines.append(
                    f"| {name} | {condition} | {100 * row['success']:.0f}% ({row['n']}) | "
                    f"{row['one_sided'][0]} ({row['n_vanilla']}) | {row['two_sided'][0]} | "
                    f"{row['whole_episode'][0]} | {100 * row['alarms']:.0f}% / {100 * row['vanilla_alarms']:.0f}% |"
                )
    emit(lines, args.output)


if __name__ == "__main__":
    main()
