"""The score summary of `ebvla-ood-report`'s rollouts for several sweeps, in one file: every score's row, then
each condition.

For each score: its pooled AUROC over each episode's first chunks and over the whole episode, each beside the
alarm rates at the shipped threshold T = mu_v + k sigma_v (fitted on the calibration rollouts alone) on the
held-out vanilla and the perturbed rollouts; its worst condition; every condition where it is inverted (AUROC
< 0.5, marked when the bootstrap interval lies wholly below 0.5: confidently wrong); its AUROC on the
conditions that cut success; and failed against successful rollouts. The rollouts are scored as the package's
report scores them (`monitoring.ood_report.score_ood_report`); `report_with_summary` appends this section to that
report.

Each run is a folder of `metaworld_perturbation_sweep.py` records: `calibration/`, `vanilla/` (held out) and one
folder per condition (`<perturbation>_s<severity>`); `vanilla_extra/` is left out. A run of fresh rollouts (a
vanilla folder and the conditions re-run, no calibration of its own) names the calibration folder it is scored
against: `NAME=DIR,CALIBRATION_DIR`. Each run is scored with the report's defaults (1000 bootstrap resamples,
seed 0), and its score summary (first 3 chunks beside the whole episode) is written under the run's name.

    python research/benchmarks/score_summaries.py --runs s6000=DIR s9000=DIR s6000_fresh=FRESH,CAL --output summaries.md
"""

import argparse
from pathlib import Path

import numpy as np
import research_scores  # noqa: F401  (registers the research scores in the package's SCORES)

from lerobot_policy_ebvla.monitoring.metrics import (
    BinaryRates,
    auroc,
    bootstrap_auroc_interval,
    markdown_table,
    percent,
)
from lerobot_policy_ebvla.monitoring.ood_report import (
    OODReportConfig,
    OODScores,
    score_ood_report,
    write_scored_report,
)
from lerobot_policy_ebvla.monitoring.ood_sections import (
    ALL_CONDITIONS,
    auroc_interval,
    chunks_label,
    success_rate,
    successes,
)

NOT_CONDITIONS = ("calibration", "vanilla", "vanilla_extra")
# The summary's early window: every score over each episode's first k chunks beside the whole episode.
SUMMARY_FIRST_CHUNKS = 3
# A condition "cuts success" when its success rate is this many points below the held-out vanilla rollouts'.
SUCCESS_CUT_POINTS = 20.0
# Scores the summary leaves out: `joint_phase_energy` (2026-11-30) is read as a failure check over 16 chunks (the
# report's Table IV), not as an OOD score over the first chunks; `context_start_energy` (2026-12-02) is LIBERO's
# OOD score, chosen and tested on LIBERO's records (`start_energy.py`); the committed sweep summaries predate both.
NOT_SUMMARY_SCORES = ("joint_phase_energy", "context_start_energy")


def summary_section(report: OODScores, first_chunks: int = SUMMARY_FIRST_CHUNKS) -> str:
    """Every score in one row: pooled AUROC with the alarm rates at T = mu_v + k sigma_v, its worst condition,
    its inverted conditions, the conditions that cut success, failed vs successful; then each condition's AUROC
    with its alarm rate, over the first chunks and the whole episode."""
    cfg, vanilla, ood, conditions, names = (
        report.cfg,
        report.vanilla,
        report.ood,
        report.conditions,
        [name for name in report.names if name not in NOT_SUMMARY_SCORES],
    )
    w = first_chunks
    windows = (w, None)
    scored = {k: report.at(k) for k in windows}
    fits = {k: {n: report.fit(n, k) for n in names} for k in windows}
    vanilla_success = success_rate(vanilla)
    single = {c: e for c, e in conditions.items() if c != ALL_CONDITIONS}
    cutting = [
        c for c, e in single.items() if 100 * (vanilla_success - success_rate(e)) >= SUCCESS_CUT_POINTS
    ]
    failed = np.array([not e[0].success for e in [*vanilla.values(), *ood.values()]], dtype=bool)

    def threshold(k, name):
        return fits[k][name].with_k(cfg.k).threshold

    def alarms(k, name, scores):
        return percent(BinaryRates.from_scores([], scores, threshold(k, name)).tpr, 0)

    def per_condition(k, name):
        negatives = scored[k].negatives[name]
        return {
            c: (auroc(negatives, scored[k].positives[c][name]), scored[k].positives[c][name]) for c in single
        }

    def inverted(k, name):
        negatives, listed = scored[k].negatives[name], []
        for c, (area, positives) in per_condition(k, name).items():
            if area < 0.5:
                confident = (
                    bootstrap_auroc_interval(negatives, positives, cfg.n_bootstrap, seed=cfg.seed)[1] < 0.5
                )
                listed.append(f"{c} {area:.2f}{'!' if confident else ''}")
        return ", ".join(listed) or "none"

    rows = []
    for name in names:
        row = [name]
        for k in windows:
            negatives, pooled = scored[k].negatives[name], scored[k].positives[ALL_CONDITIONS][name]
            row += [
                auroc_interval(negatives, pooled, cfg),
                f"{alarms(k, name, negatives)} / {alarms(k, name, pooled)}",
            ]
        worst, (area, _) = min(per_condition(w, name).items(), key=lambda item: item[1][0])
        row += [f"{worst} {area:.3f}", inverted(w, name), inverted(None, name)]
        negatives = scored[w].negatives[name]
        if cutting:
            positives = np.concatenate([scored[w].positives[c][name] for c in cutting])
            lowest = min(auroc(negatives, scored[w].positives[c][name]) for c in cutting)
            row.append(f"{auroc_interval(negatives, positives, cfg)}, min {lowest:.3f}")
        else:
            row.append("no such condition")
        together = np.concatenate([scored[w].negatives[name], scored[w].positives[ALL_CONDITIONS][name]])
        row.append(
            auroc_interval(together[~failed], together[failed], cfg)
            if 0 < failed.sum() < failed.size
            else "n/a"
        )
        rows.append(row)
    first, whole = chunks_label(w), chunks_label(None)
    headers = ["Score", f"Pooled, {first}", "Alarms v / s", f"Pooled, {whole}", "Alarms v / s"]
    headers += [f"Worst, {first}", f"Inverted, {first}", f"Inverted, {whole}"]
    headers += [f"Success-cutting, {first}", f"Failed vs successful, {first}"]
    lines = [
        "## Score summary\n\n"
        f"Held-out vanilla rollouts (negatives): {len(vanilla)}, success {successes(vanilla)}; perturbed "
        f"(positives): {len(ood)} in {len(single)} conditions. AUROC [bootstrap 95% interval]. Alarms v / s: the "
        f"share of held-out vanilla / perturbed rollouts above T = mu_v + {cfg.k:g} sigma_v, fitted on the "
        "calibration rollouts over the same chunks. Inverted: conditions with AUROC < 0.5, `!` where the interval "
        f"lies wholly below 0.5 (confidently wrong). Success-cutting: the conditions {SUCCESS_CUT_POINTS:g}+ "
        f"points below vanilla's success ({', '.join(cutting) or 'none'}) pooled, and the lowest of them. Failed vs "
        f"successful: every held-out rollout, {int(failed.sum())} of {failed.size} failed.",
        markdown_table(headers, rows),
    ]
    for k in windows:
        table = [
            ["held-out vanilla: alarms", len(vanilla), *(alarms(k, n, scored[k].negatives[n]) for n in names)]
        ]
        for c, episodes in single.items():
            cells = []
            for n in names:
                area, positives = per_condition(k, n)[c]
                cells.append(f"{area:.3f} ({alarms(k, n, positives)})")
            table.append([c, len(episodes), *cells])
        lines.append(
            f"### Each condition, {chunks_label(k)} (AUROC, alarm rate at T)\n\n"
            + markdown_table(["Condition", "Episodes", *names], table)
        )
    return "\n\n".join(lines)


def report_with_summary(cfg: OODReportConfig, first_chunks: int = SUMMARY_FIRST_CHUNKS) -> str:
    """`ebvla-ood-report`'s report (written to `cfg.output_dir`, as the command writes it) with the score summary
    appended, the rollouts scored once."""
    report = score_ood_report(cfg)
    return write_scored_report(report) + "\n" + summary_section(report, first_chunks) + "\n"


def score_summary(records: Path, n_bootstrap: int = 1000, calibration: Path | None = None) -> str:
    """The section "Score summary" for one run's record folders (calibrated on `calibration`, by default the
    run's own `calibration/`), without its heading."""
    conditions = sorted(p for p in records.iterdir() if p.is_dir() and p.name not in NOT_CONDITIONS)
    cfg = OODReportConfig(
        calibration=[str(calibration or records / "calibration")],
        vanilla=[str(records / "vanilla")],
        ood=[str(p) for p in conditions],
        n_bootstrap=n_bootstrap,
    )
    return summary_section(score_ood_report(cfg)).removeprefix("## Score summary").strip()


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--runs", nargs="+", required=True, help="NAME=RECORDS_DIR, one per sweep")
    parser.add_argument("--output", type=Path, required=True)
    parser.add_argument("--n_bootstrap", type=int, default=1000)
    args = parser.parse_args()
    sections = []
    for run in args.runs:
        name, folders = run.split("=", 1)
        records, _, calibration = folders.partition(",")
        summary = score_summary(Path(records), args.n_bootstrap, Path(calibration) if calibration else None)
        sections.append(f"## {name}\n\n{summary}\n")
    args.output.write_text("\n".join(sections))
    print(f"Wrote {args.output}")


if __name__ == "__main__":
    main()
