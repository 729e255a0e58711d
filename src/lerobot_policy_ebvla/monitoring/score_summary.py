"""The OOD report's score summary: every score in one row, with its worst and inverted conditions.

For each score: its pooled AUROC over each episode's first chunks and over the whole episode, each beside the
alarm rates at the shipped threshold T = mu_v + k sigma_v (fitted on the calibration rollouts alone) on the
held-out vanilla and the perturbed rollouts; its worst condition; every condition where it is inverted (AUROC
< 0.5, marked when the bootstrap interval lies wholly below 0.5: confidently wrong); its AUROC on the
conditions that cut success; and failed against successful rollouts. `ood_report.write_ood_report` calls
`summary_section`; the small helpers here are shared with it.
"""

import numpy as np

from .metrics import BinaryRates, auroc, bootstrap_auroc_interval, format_auroc, markdown_table, percent

ALL_CONDITIONS = "all perturbations"
# A condition "cuts success" when its success rate is this many points below the held-out vanilla rollouts'.
SUCCESS_CUT_POINTS = 20.0


def success_rate(episodes: dict) -> float:
    return float(np.mean([e[0].success for e in episodes.values()])) if episodes else float("nan")


def successes(episodes: dict) -> str:
    n_success = sum(e[0].success for e in episodes.values())
    return f"{n_success}/{len(episodes)} ({percent(success_rate(episodes))})"


def auroc_interval(negatives: np.ndarray, positives: np.ndarray, cfg) -> str:
    """AUROC [bootstrap 95% interval] with the report config's resamples and seed."""
    return format_auroc(negatives, positives, cfg.n_bootstrap, cfg.seed)


def chunks_label(first_chunks: int | None) -> str:
    if first_chunks is None:
        return "whole episode"
    return f"first {first_chunks} chunk{'s' if first_chunks > 1 else ''}"


def summary_section(scored, fits, vanilla, ood, conditions, names, cfg) -> str:
    """Every score in one row: pooled AUROC with the alarm rates at T = mu_v + k sigma_v, its worst condition,
    its inverted conditions, the conditions that cut success, failed vs successful; then each condition's AUROC
    with its alarm rate, over the first chunks and the whole episode."""
    w = cfg.summary_first_chunks
    windows = (w, None)
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
