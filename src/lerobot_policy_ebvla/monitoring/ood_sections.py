"""The sections and figures of the OOD report (`ood_report.write_ood_report`), each from the scored rollouts.

Every function takes the report's configuration (`OODReportConfig`), the fitted calibrations by score name and the
rollout scores of the held-out sets (`ScoredSets` in `ood_report.py`: negatives, and positives per condition), and
returns one markdown section (or writes the figures).
"""

import math

import numpy as np

from ..runtime.threshold import exceeds
from .metrics import BinaryRates, auroc, format_auroc, markdown_table, percent, roc_curve
from .ood import format_balanced_accuracy_table, format_table_iii, ood_detection_table
from .plots import plot_roc, plot_score_histograms

ALL_CONDITIONS = "all perturbations"


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


def first_chunks_section(scored, vanilla, conditions, names, cfg) -> str:
    lengths = [k for k in scored if k is not None and k in cfg.first_chunks]
    lines = [
        "## Detection on the first chunks: AUROC [bootstrap 95% interval]\n\n"
        "Every score over each episode's first k chunks only (an episode shorter than k uses all its "
        "chunks): what a monitor has seen k chunks into an episode, before a failure that follows the "
        "condition. "
        f"Held-out vanilla rollouts (the negatives): {len(vanilla)}, success {successes(vanilla)}."
    ]
    headers = ["Score", *(chunks_label(k) for k in lengths), chunks_label(None)]
    for condition, episodes in conditions.items():
        rows = [
            [
                name,
                *(
                    auroc_interval(scored[k].negatives[name], scored[k].positives[condition][name], cfg)
                    for k in [*lengths, None]
                ),
            ]
            for name in names
        ]
        lines.append(
            f"### {condition}: {len(episodes)} perturbed rollouts, success {successes(episodes)}\n\n"
            + markdown_table(headers, rows)
        )
    return "\n\n".join(lines)


REFERENCE_PERTURBED = "reference: perturbed or not"
REFERENCE_CONDITION_FAILURES = "reference: its condition's failure rate"


def outcome_section(scored, vanilla, ood, names, cfg) -> str:
    """Every score's AUROC of failed (positives) against successful rollouts, per set that has both."""
    lengths = [k for k in scored if k is not None and k in cfg.first_chunks]
    vanilla_failed = np.array([not e[0].success for e in vanilla.values()], dtype=bool)
    ood_failed = np.array([not e[0].success for e in ood.values()], dtype=bool)
    # Labels, not scores: what a detector that knew them would reach (see the section's text).
    ood_failure_rates = condition_failure_rates(ood)
    vanilla_failure_rate = np.full(len(vanilla), vanilla_failed.mean() if len(vanilla) else 0.0)
    sets = {
        "held-out vanilla rollouts": (vanilla_failed, lambda s, name: s.negatives[name], {}),
        "perturbed rollouts, all conditions": (
            ood_failed,
            lambda s, name: s.positives[ALL_CONDITIONS][name],
            {REFERENCE_CONDITION_FAILURES: ood_failure_rates},
        ),
        "held-out vanilla and perturbed rollouts together": (
            np.concatenate([vanilla_failed, ood_failed]),
            lambda s, name: np.concatenate([s.negatives[name], s.positives[ALL_CONDITIONS][name]]),
            {
                REFERENCE_PERTURBED: np.concatenate([np.zeros(len(vanilla)), np.ones(len(ood))]),
                REFERENCE_CONDITION_FAILURES: np.concatenate([vanilla_failure_rate, ood_failure_rates]),
            },
        ),
    }
    lines = [
        "## Failed vs successful rollouts: AUROC [bootstrap 95% interval]\n\n"
        "Every score as a failure detector: positives are the failed rollouts, negatives the successful ones "
        "of the same set, over each episode's first k chunks and the whole episode (a failed episode runs "
        "longer, so its whole-episode score also sees its late, stalled chunks). Among perturbed rollouts a "
        "score that flags the perturbations with the most failures ranks failures high even if it knows "
        "nothing of failure within a condition: the vanilla set alone is the cleaner test. The reference rows "
        "say how far that goes: they are not scores but the rollouts' own labels, what a detector that knew "
        f"them would reach. `{REFERENCE_PERTURBED}` is a perfect OOD detector; "
        f"`{REFERENCE_CONDITION_FAILURES}` ranks each rollout by the share of its set's rollouts that failed "
        "(vanilla's, or its condition's), the most any score that knows nothing within a condition can reach."
    ]
    headers = ["Score", *(chunks_label(k) for k in lengths), chunks_label(None)]
    for title, (failed, of, references) in sets.items():
        if failed.all() or not failed.any():
            lines.append(f"### {title}: {int(failed.sum())} of {failed.size} failed, no AUROC")
            continue
        rows = [
            [
                name,
                *(
                    auroc_interval(of(scored[k], name)[~failed], of(scored[k], name)[failed], cfg)
                    for k in [*lengths, None]
                ),
            ]
            for name in names
        ]
        rows += [
            [f"_{name}_", *(auroc_interval(labels[~failed], labels[failed], cfg) for _ in [*lengths, None])]
            for name, labels in references.items()
        ]
        lines.append(
            f"### {title}: {int(failed.sum())} of {failed.size} failed\n\n" + markdown_table(headers, rows)
        )
    return "\n\n".join(lines)


def condition_failure_rates(ood: dict) -> np.ndarray:
    """Each perturbed rollout's condition's share of failed rollouts, in `ood`'s order: the failed-vs-successful
    ranking of a detector that knows every condition's outcome and nothing within a condition."""
    failed: dict[tuple[str, float], list[bool]] = {}
    for (_, key), episode in ood.items():
        failed.setdefault((key.perturbation, key.severity), []).append(not episode[0].success)
    return np.array([np.mean(failed[(key.perturbation, key.severity)]) for _, key in ood], dtype=float)


def table_iii_sections(title, fits, scored, vanilla, conditions, names, cfg) -> list[str]:
    """Per condition: the final energy's Table III as the paper prints it, then every score's balanced
    accuracy at the same rules."""
    sections = []
    for condition, episodes in conditions.items():
        negatives, positives = scored.negatives, scored.positives[condition]
        rows = {
            name: ood_detection_table(negatives[name], positives[name], cfg.multipliers, fits[name])
            for name in names
        }
        final = "final_energy"
        sections.append(
            f"## {title}: {condition} ({len(vanilla)} vanilla vs {len(episodes)} perturbed rollouts)\n\n"
            + format_table_iii(
                rows[final],
                fits[final],
                auroc_interval(negatives[final], positives[final], cfg),
                len(vanilla),
                len(episodes),
            )
            + "\n\nBalanced accuracy of every score at the same rules:\n\n"
            + format_balanced_accuracy_table(rows)
        )
    return sections


def calibration_table(fits: dict, negatives: dict, cfg) -> str:
    rows = []
    for name, fit in fits.items():
        t_k = fit.with_k(cfg.k).threshold
        rows.append(
            [
                name,
                fit.n_rollouts,
                f"{fit.mu_v:.4g}",
                f"{fit.sigma_v:.4g}",
                f"{t_k:.4g}",
                percent(BinaryRates.from_scores(negatives[name], [], t_k).fpr),
                f"{fit.conformal_threshold:.4g}",
                percent(BinaryRates.from_scores(negatives[name], [], fit.conformal_threshold).fpr),
            ]
        )
    headers = [
        "Score",
        "Rollouts",
        "mu",
        "sigma",
        f"T (k={cfg.k:g})",
        "Held-out FPR",
        f"T conformal (α={percent(cfg.false_alarm_rate)})",
        "Held-out FPR (conformal)",
    ]
    return markdown_table(headers, rows)


def conformal_note(fits: dict, cfg) -> str:
    if np.isfinite(fits["final_energy"].conformal_threshold):
        return ""
    needed = math.ceil(1 / cfg.false_alarm_rate - 1 - 1e-9)
    return (
        f"\n\nThe conformal threshold is +inf (nothing flagged): alpha = {percent(cfg.false_alarm_rate)} needs "
        f"at least {needed} calibration rollouts, {fits['final_energy'].n_rollouts} were given."
    )


def success_table(vanilla, conditions, fits, negatives, positives, cfg) -> str:
    vanilla_success = success_rate(vanilla)
    final = fits["final_energy"]
    held_out = negatives["final_energy"]
    reference = float(np.mean(held_out))
    vanilla_fpr = BinaryRates.from_scores(held_out, [], final.conformal_threshold).fpr
    rows = [
        ["vanilla (held-out)", len(vanilla), percent(vanilla_success), "", "0", "0", "", percent(vanilla_fpr)]
    ]
    for condition, episodes in conditions.items():
        scores = positives[condition]["final_energy"]
        shift = float(np.mean(scores)) - reference
        drop = 100 * (vanilla_success - success_rate(episodes))
        sigma_units = f"{shift / final.sigma_v:+.2f}" if final.sigma_v > 0 else "n/a"
        rows.append(
            [
                condition,
                len(episodes),
                percent(success_rate(episodes)),
                f"{drop:+.1f} pts",
                f"{shift:+.4g}",
                sigma_units,
                auroc_interval(held_out, scores, cfg),
                percent(BinaryRates.from_scores(held_out, scores, final.conformal_threshold).tpr),
            ]
        )
    headers = [
        "Condition",
        "Episodes",
        "Success",
        "Success drop",
        "Score shift",
        "Shift / sigma_v",
        "AUROC [95% CI]",
        "Flagged at conformal T",
    ]
    return markdown_table(headers, rows)


def auroc_table(conditions, names, negatives, positives, cfg) -> str:
    rows = [
        [
            condition,
            len(episodes),
            *(auroc_interval(negatives[n], positives[condition][n], cfg) for n in names),
        ]
        for condition, episodes in conditions.items()
    ]
    return markdown_table(["Condition", "Episodes", *names], rows)


def figures(cfg, fits, calibration_scores, negatives, positives, names) -> None:
    def curve(negative, positive):
        fpr, tpr, _ = roc_curve(negative, positive)
        return fpr, tpr, auroc(negative, positive)

    final = "final_energy"
    plot_roc(
        {c: curve(negatives[final], p[final]) for c, p in positives.items()}, cfg.output_dir / "roc_curve.png"
    )
    plot_roc(
        {n: curve(negatives[n], positives[ALL_CONDITIONS][n]) for n in names},
        cfg.output_dir / "roc_baselines.png",
    )
    fit = fits[final]
    groups = {"calibration": calibration_scores, "vanilla (held-out)": negatives[final]}
    groups.update({c: p[final] for c, p in positives.items() if c != ALL_CONDITIONS})
    thresholds = {
        f"T = mu_v + {cfg.k:g} sigma_v": fit.with_k(cfg.k).threshold,
        f"T conformal (α={percent(cfg.false_alarm_rate)})": fit.conformal_threshold,
    }
    xlabel = f"rollout score ({cfg.aggregation} of chunk final energies)"
    plot_score_histograms(groups, thresholds, cfg.output_dir / "energy_histogram.png", xlabel)


def saved_score_note(cfg, scored) -> str:
    """The report's note on the score `--calibrate_to` saves (`ood_report.OODScores`, its config): which table rows
    it is and the threshold the run-time monitor applies."""
    saved_score, default = scored.saved_score, ""
    if cfg.score is None and cfg.calibrate_to is not None:
        default = f"\n\nWithout `--score`, `--calibrate_to` saves the checkpoint's `monitor.score`: `{saved_score}`."
    if cfg.calibrate_to is not None:
        fit = scored.saved_fit
        rule = (
            f" (the conformal quantile at alpha = {percent(fit.false_alarm_rate)})."
            if fit.rule == "conformal"
            else "."
        )
        if fit.window is None:
            default += (
                f"\n\nThe saved threshold is fitted on the calibration rollouts' `{saved_score}` over whole "
                f"episodes (the T the run-time monitor compares each chunk's running score to): mu_v = "
                f"{fit.mu_v:.4g}, sigma_v = {fit.sigma_v:.4g}, T = {fit.threshold:.4g}{rule}"
            )
        else:
            n = fit.window.chunks
            vanilla = exceeds(scored.saved_scores(scored.vanilla_chunks), fit.threshold)
            default += (
                f"\n\nThe saved threshold is fitted on the calibration rollouts' window score over their first {n} "
                f"chunks: the running `{saved_score}` after each of chunks 1..{n}, standardized by the calibration's "
                f"mu_n and sigma_n, its max (`ChunkWindow`; mu_n = "
                f"{', '.join(f'{m:.4g}' for m in fit.window.running.mean)}; sigma_n = "
                f"{', '.join(f'{v:.4g}' for v in fit.window.running.std)}). The run-time monitor compares the window "
                f"score so far to T after every chunk, and its decision after chunk {n} stands, so T bounds the "
                f"alarms of all {n} decisions together: mu_v = {fit.mu_v:.4g}, sigma_v = {fit.sigma_v:.4g}, "
                f"T = {fit.threshold:.4g}{rule} At T, {int(vanilla.sum())} of the {vanilla.size} held-out vanilla "
                f"rollouts are alarmed within their first {n} chunks. The Table III rows on the first {n} chunks "
                f"are the paper's decision (the {n}-chunk mean at its own T, once at chunk {n})."
            )
    what = {
        "context_distance": "of every table: the same features, fit and leave-one-episode-out calibration scores.",
        "context_knn": f"of every table (k = {cfg.knn_k}): the same features, standardization and "
        "leave-one-episode-out calibration scores; the saved calibration keeps every calibration context.",
        "energy_and_context": "of the whole-episode tables: the final energy and the `context_distance` "
        "score, standardized by the calibration rollouts' mean and std of each, and their max.",
    }
    if saved_score not in what:
        return default
    return default + (
        f"\n\n`--score={saved_score}`, the score a calibration saved by this report has `monitor.response` act on, is "
        f"the `{saved_score}` score {what[saved_score]}"
    )
