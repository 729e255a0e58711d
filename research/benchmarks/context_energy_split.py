"""The joint energy split: its context term E_c(C) and the head's part, each scored apart on a sweep (issue 32).

A policy with a joint energy (`energy_ood_margin_on` "context", "context_backbone" or "observation") reports the
final energy E(a^(K_inf), C) + E_c(C), and its records hold E_c apart (`EnergyRecord.context_energy`). For each
sweep condition (a folder of `metaworld_perturbation_sweep.py` records beside `calibration/` and `vanilla/`), and
for each of

- "joint": the final energy, the paper's score on this policy;
- "head": the head's part, final energy - E_c;
- "E_c": the context term alone;
- "|z| E_c": its two-sided form, |E_c - mu| / sigma of the calibration rollouts' scores (a typicality test: E_c
  is held near 0 on the data, so an observation it puts *under* the data is as far off as one above),

a rollout's score is the mean over its first `--chunks` chunks, and the table gives its AUROC against the held-out
vanilla rollouts (stratified bootstrap 95% interval) and the share of rollouts over T = mu + 1.0 sigma of the
calibration rollouts' scores (`OODCalibration.fit`, what `--calibrate_to` ships), set on calibration alone.
The summary: pooled over conditions, the worst condition, the minimum over success-cutting conditions (success 20
points or more under the held-out vanilla rollouts'), failed vs successful over held-out vanilla and every
condition, and `vanilla_extra/` (more vanilla rollouts, not a perturbation) when there.

Rollouts cut after their first chunks (`max_episode_steps` = 3 chunks), which record E_c at a sixth of the cost,
know no outcome: `RUN=CUT_DIR,FULL_DIR` takes each condition's success rate from the full sweep of the same
conditions and environment seeds (`FULL_DIR`), which decides which conditions cut success, and leaves failed vs
successful out. They are not the full sweep's rollouts themselves: the evaluation draws the MCMC noise of every
episode from one stream, so from the second episode on a cut rollout's chunks differ from the full one's.

    python research/benchmarks/context_energy_split.py --runs s8000=CUT_DIR,FULL_DIR --chunks 3 --output split.md
"""

import argparse
from pathlib import Path

import numpy as np
import research_scores  # noqa: F401  (registers the research scores in the package's SCORES)
from energy_margin_report import cell, emit

from lerobot_policy_ebvla.monitoring.records import group_by_episode, read_energy_records, records_file_in
from lerobot_policy_ebvla.runtime.calibration import OODCalibration
from lerobot_policy_ebvla.runtime.threshold import exceeds

PARTS = ("joint", "head", "E_c", "|z| E_c")
NOT_CONDITIONS = ("calibration", "vanilla", "vanilla_extra")
# A condition cuts success when its rollouts succeed this much less often than the held-out vanilla rollouts.
CUTTING_DROP = 0.20


def load(folder: Path, chunks: int) -> dict[int, list]:
    """Each episode's first `chunks` records, by episode index."""
    episodes = group_by_episode(read_energy_records(records_file_in(folder)))
    return {
        key.episode_index: sorted(records, key=lambda r: r.chunk_index)[:chunks]
        for key, records in episodes.items()
    }


def split_scores(episodes: dict[int, list]) -> np.ndarray:
    """(episodes, 3): the mean over each episode's chunks of the joint energy, the head's part and E_c (the
    two-sided column is added once the calibration is known, `with_two_sided`)."""
    rows = []
    for records in episodes.values():
        if any(r.context_energy is None for r in records):
            raise ValueError(
                "These records hold no `context_energy`: record them with a joint-energy policy "
                "(`energy_ood_margin_on` 'context' or 'observation') and this version of the recorder."
            )
        joint = np.array([r.final_energy for r in records])
        context = np.array([r.context_energy for r in records])
        rows.append((joint.mean(), (joint - context).mean(), context.mean()))
    return np.array(rows)


def with_two_sided(scores: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Each folder's scores with |E_c - mu| / sigma appended, mu and sigma of the calibration rollouts' E_c."""
    calibration = scores["calibration"][:, 2]
    mean, std = calibration.mean(), max(calibration.std(ddof=1), 1e-8)
    return {name: np.column_stack([s, np.abs(s[:, 2] - mean) / std]) for name, s in scores.items()}


def success_rate(folder: Path) -> float:
    """The share of a folder's episodes that succeeded."""
    return float(np.mean([ep[0].success for ep in load(folder, 1).values()]))


def run_split(folder: Path, chunks: int, outcomes_dir: Path | None = None) -> dict:
    """Per condition and part: AUROC cells and alarm rates; and the run's summary. With `outcomes_dir` (the full
    sweep of cut rollouts) the success rates are its own, and failed vs successful is left out."""
    folders = {p.name: p for p in sorted(folder.iterdir()) if p.is_dir() and records_file_in(p) is not None}
    scores, success = {}, {}
    for name, sub in folders.items():
        episodes = load(sub, chunks)
        scores[name] = split_scores(episodes)
        success[name] = np.array([records[0].success for records in episodes.values()])
    rates = {name: success[name].mean() for name in folders}
    if outcomes_dir is not None:
        rates = {name: success_rate(outcomes_dir / name) for name in folders}
    scores = with_two_sided(scores)
    thresholds = [OODCalibration.fit(scores["calibration"][:, j]).threshold for j in range(len(PARTS))]
    vanilla = scores["vanilla"]
    vanilla_success = rates["vanilla"]
    rows = {}
    for name in [n for n in folders if n not in ("calibration", "vanilla")]:
        row = {"n": len(scores[name]), "success": rates[name]}
        for j, part in enumerate(PARTS):
            row[part] = cell(vanilla[:, j], scores[name][:, j])
            row[f"{part} alarms"] = exceeds(scores[name][:, j], thresholds[j]).mean()
        rows[name] = row
    conditions = [n for n in rows if n not in NOT_CONDITIONS]
    shifted = np.concatenate([scores[n] for n in conditions])
    held_out_scores = np.concatenate([vanilla, shifted])
    held_out_success = np.concatenate([success["vanilla"], *[success[n] for n in conditions]])
    summary = {
        "vanilla success": vanilla_success,
        "n vanilla": len(vanilla),
        "outcomes": outcomes_dir is None,
    }
    for j, part in enumerate(PARTS):
        values = {n: rows[n][part] for n in conditions}
        worst = min(conditions, key=lambda n: values[n][1])
        cutting = [n for n in conditions if rows[n]["success"] <= vanilla_success - CUTTING_DROP]
        summary[part] = {
            "pooled": cell(vanilla[:, j], shifted[:, j])[0],
            "worst": f"{worst} {values[worst][0]}",
            "under 0.5": sum(values[n][1] < 0.5 for n in conditions),
            "confidently under": [n for n in conditions if values[n][2] < 0.5],
            "cutting min": min((values[n][1] for n in cutting), default=float("nan")),
            "failed vs successful": cell(
                held_out_scores[held_out_success, j], held_out_scores[~held_out_success, j]
            )[0]
            if outcomes_dir is None
            else "- (cut rollouts)",
            "alarms vanilla": exceeds(vanilla[:, j], thresholds[j]).mean(),
            "alarms vanilla_extra": rows["vanilla_extra"][f"{part} alarms"]
            if "vanilla_extra" in rows
            else None,
            "alarms shifted": exceeds(shifted[:, j], thresholds[j]).mean(),
        }
    return {"rows": rows, "summary": summary}


def markdown(results: dict[str, dict], chunks: int) -> str:
    lines = [
        f"First {chunks} chunks; AUROC against the held-out vanilla rollouts [bootstrap 95%]; alarms at T = mu + "
        "1.0 sigma of the calibration rollouts.",
        "",
        "| run | score | pooled | worst condition | under 0.5 (confidently) | success-cutting min | failed vs "
        "successful | alarms: held-out vanilla / vanilla_extra / shifted |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for run, result in results.items():
        summary = result["summary"]
        for part in PARTS:
            s = summary[part]
            confident = ", ".join(s["confidently under"]) or "none"
            extra = "-" if s["alarms vanilla_extra"] is None else f"{100 * s['alarms vanilla_extra']:.0f}%"
            lines.append(
                f"| {run} | {part} | {s['pooled']} | {s['worst']} | {s['under 0.5']} ({confident}) | "
                f"{s['cutting min']:.2f} | {s['failed vs successful']} | "
                f"{100 * s['alarms vanilla']:.0f}% / {extra} / {100 * s['alarms shifted']:.0f}% |"
            )
    for run, result in results.items():
        summary = result["summary"]
        lines += [
            "",
            f"**{run}** ({summary['n vanilla']} held-out vanilla rollouts; success "
            f"{'of these rollouts' if summary['outcomes'] else 'from the full sweep of the same conditions'}: "
            f"vanilla {100 * summary['vanilla success']:.0f}%)",
            "",
            "| condition | success (n) | " + " | ".join(f"{p}: AUROC, alarms" for p in PARTS) + " |",
            "|---|---|" + "---|" * len(PARTS),
        ]
        for name, row in result["rows"].items():
            cells = [f"{row[p][0]}, {100 * row[f'{p} alarms']:.0f}%" for p in PARTS]
            lines.append(f"| {name} | {100 * row['success']:.0f}% ({row['n']}) | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--runs", nargs="+", required=True, help="name=DIR (full rollouts) or name=CUT_DIR,FULL_DIR"
    )
    parser.add_argument("--chunks", type=int, default=3)
    parser.add_argument("--output", type=Path)
    args = parser.parse_args()
    results = {}
    for spec in args.runs:
        name, dirs = spec.split("=", 1)
        records, _, full = dirs.partition(",")
        results[name] = run_split(Path(records), args.chunks, Path(full) if full else None)
    emit(markdown(results, args.chunks).splitlines(), args.output)


if __name__ == "__main__":
    main()
