"""`ebvla-ood-report`: energy-based OOD detection (paper Table III) on held-out rollouts, with its baselines.

Calibrate on one set of vanilla rollouts, report on others:

    ebvla-ood-report --calibration='[outputs/eval/vanilla_seed0]' --vanilla='[outputs/eval/vanilla_seed1]' \\
        --ood='[outputs/eval/pose*,outputs/eval/fov*]' --output_dir=outputs/ood_report \\
        --calibrate_to=outputs/train/ebvla/checkpoints/last/pretrained_model

Prints and writes `ood_report.md` (the protocol, the calibration, energy vs success drop per condition,
AUROC with bootstrap 95% intervals per score, Table III per condition with the baselines' balanced
accuracy beside the final energy's) and the figures `roc_curve.png`, `roc_baselines.png` and
`energy_histogram.png`. `--help` lists every option.
"""

import logging
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path

import draccus
import numpy as np
from lerobot.utils.utils import init_logging

from lerobot_policy_ebvla.monitoring.baselines import available_scores, episode_scores, fit_feature_model
from lerobot_policy_ebvla.monitoring.metrics import (
    auroc,
    bootstrap_auroc_interval,
    markdown_table,
    percent,
    roc_curve,
)
from lerobot_policy_ebvla.monitoring.ood import (
    OOD_CALIBRATION_FILENAME,
    SCORE_AGGREGATIONS,
    TABLE_III_MULTIPLIERS,
    THRESHOLD_RULES,
    OODCalibration,
    format_detection_table,
    ood_detection_table,
)
from lerobot_policy_ebvla.monitoring.plots import plot_roc, plot_score_histograms
from lerobot_policy_ebvla.monitoring.records import load_episodes, resolve_record_files
from lerobot_policy_ebvla.monitoring.threshold import exceeds

ALL_CONDITIONS = "all perturbations"


@dataclass
class OODReportConfig:
    """Energy-based OOD detection report (Table III) on held-out rollouts, with the baselines side by side.

    Calibrate (mu_v, sigma_v of Eq. 5, the conformal threshold, the feature baselines) on `calibration`
    vanilla rollouts; report on held-out `vanilla` rollouts (the negatives) and `ood` rollouts (the
    positives, one condition per perturbation and severity their records carry). Each path is a records
    file, an eval folder or a glob pattern; lists are written `--ood='[outputs/eval/pose*,outputs/eval/fov2]'`.
    """

    # Vanilla rollouts that set mu_v, sigma_v, the conformal threshold and the feature baselines.
    calibration: list[str] = field(default_factory=list)
    # Held-out vanilla rollouts (other seeds than the calibration's): the negatives.
    vanilla: list[str] = field(default_factory=list)
    # Perturbed rollouts: the positives, reported per (perturbation, severity) and all together.
    ood: list[str] = field(default_factory=list)
    # Allow a report set that shares files with `calibration`, or no `calibration` (then `vanilla`
    # calibrates): the report is labelled IN-SAMPLE. Without it such a report is refused.
    in_sample: bool = False
    # Folder for ood_report.md and the figures.
    output_dir: Path = Path("outputs/ood_report")
    # How a rollout's chunk scores form its score: mean, max, last or median.
    aggregation: str = "mean"
    # Std multipliers k of Table III's rows (T = mu_v + k sigma_v).
    multipliers: list[float] = field(default_factory=lambda: list(TABLE_III_MULTIPLIERS))
    # False-alarm rate alpha of the conformal threshold (its last row in Table III).
    false_alarm_rate: float = 0.05
    # Bootstrap resamples of the AUROC intervals.
    n_bootstrap: int = 1000
    # Seed of the bootstrap generator.
    seed: int = 0
    # Neighbours of the k-NN feature baseline.
    knn_k: int = 5
    # Write ood_calibration.json (final energy, fitted on `calibration`) into this pretrained_model folder.
    calibrate_to: Path | None = None
    # k saved in the calibration.
    k: float = 1.0
    # Threshold the policy's monitor applies from the saved calibration: mean_std (Eq. 5) or conformal.
    threshold_rule: str = "mean_std"
    # Replace an existing ood_calibration.json.
    overwrite_calibration: bool = False

    def validate(self) -> None:
        # Not __post_init__: draccus would wrap the ValueError in a less readable ParsingError.
        if self.aggregation not in SCORE_AGGREGATIONS:
            raise ValueError(f"`aggregation` must be one of {SCORE_AGGREGATIONS}, got {self.aggregation!r}.")
        if self.threshold_rule not in THRESHOLD_RULES:
            raise ValueError(
                f"`threshold_rule` must be one of {THRESHOLD_RULES}, got {self.threshold_rule!r}."
            )


def _condition_name(perturbation: str, severity: float) -> str:
    return f"{perturbation} {severity:g}" if perturbation != "none" else "unperturbed (from --ood)"


def _success_rate(episodes: dict) -> float:
    return float(np.mean([e[0].success for e in episodes.values()])) if episodes else float("nan")


def _interval(negatives: np.ndarray, positives: np.ndarray, cfg: OODReportConfig) -> str:
    low, high = bootstrap_auroc_interval(negatives, positives, cfg.n_bootstrap, seed=cfg.seed)
    return f"{auroc(negatives, positives):.3f} [{low:.3f}, {high:.3f}]"


def protocol(cfg: OODReportConfig) -> tuple[list[Path], bool]:
    """The calibration files, and whether the report is in-sample; refuses an unflagged in-sample report."""
    cfg.validate()
    if not cfg.vanilla or not cfg.ood:
        raise ValueError("Give held-out vanilla (`--vanilla`) and perturbed (`--ood`) rollouts to report on.")
    calibration = resolve_record_files(cfg.calibration)
    report = set(resolve_record_files(cfg.vanilla)) | set(resolve_record_files(cfg.ood))
    shared = sorted(str(f) for f in set(calibration) & report)
    in_sample = not calibration or bool(shared)
    if in_sample and not cfg.in_sample:
        why = f"they share {shared}" if shared else "no `--calibration` rollouts were given"
        raise ValueError(
            f"Refusing an in-sample report: {why}. Calibrate on other vanilla rollouts (other seeds) with "
            "`--calibration`, or pass `--in_sample=true` to report in-sample (labelled as such)."
        )
    return calibration or resolve_record_files(cfg.vanilla), in_sample


def run(cfg: OODReportConfig) -> str:
    """Builds the report, writes it and the figures to `cfg.output_dir`, and returns its markdown."""
    calibration_files, in_sample = protocol(cfg)
    calibration_file = cfg.calibrate_to / OOD_CALIBRATION_FILENAME if cfg.calibrate_to else None
    if calibration_file is not None and calibration_file.exists() and not cfg.overwrite_calibration:
        raise FileExistsError(
            f"{calibration_file} exists; pass `--overwrite_calibration=true` to replace it."
        )

    calibration_set = load_episodes(calibration_files)
    vanilla = load_episodes(cfg.vanilla)
    ood = load_episodes(cfg.ood)
    for flag, episodes in (("--calibration", calibration_set), ("--vanilla", vanilla)):
        perturbed = sorted(
            {f"{key.perturbation} {key.severity:g}" for _, key in episodes if key.perturbation != "none"}
        )
        if perturbed:
            raise ValueError(
                f"`{flag}` must hold vanilla rollouts only, but has perturbed ones: {perturbed}."
            )
    conditions: dict[str, dict] = {ALL_CONDITIONS: ood}
    for key, episode in sorted(ood.items(), key=lambda item: (item[0][1].perturbation, item[0][1].severity)):
        conditions.setdefault(_condition_name(key[1].perturbation, key[1].severity), {})[key] = episode

    names = available_scores([*calibration_set.values(), *vanilla.values(), *ood.values()])
    feature_model = None
    if "mahalanobis" in names:
        feature_model = fit_feature_model(calibration_set, k=cfg.knn_k)

    def scores(episodes: dict, name: str) -> np.ndarray:
        return episode_scores(episodes, name, cfg.aggregation, feature_model)

    fits = {
        name: OODCalibration.fit(
            scores(calibration_set, name), cfg.k, cfg.aggregation, cfg.false_alarm_rate, cfg.threshold_rule
        )
        for name in names
    }
    negatives = {name: scores(vanilla, name) for name in names}
    positives = {c: {name: scores(eps, name) for name in names} for c, eps in conditions.items()}

    label = "IN-SAMPLE (calibration and report sets overlap: optimistic)" if in_sample else "held-out"
    sections = [
        f"# Energy-based OOD detection ({label})",
        f"Calibration: {len(calibration_set)} vanilla rollouts from {len(calibration_files)} record file(s). "
        f"Report: {len(vanilla)} held-out vanilla rollouts (negatives), {len(ood)} perturbed rollouts "
        f"(positives). Rollout score: {cfg.aggregation} of the chunk scores. Thresholds: T = mu + k sigma "
        f"(Eq. 5) and the conformal threshold at false-alarm rate alpha = {percent(cfg.false_alarm_rate)}. "
        f"Scores: {', '.join(names)}"
        + (" (feature baselines fitted on the calibration rollouts' contexts)." if feature_model else "."),
        "## Calibration\n\n" + _calibration_table(fits, negatives, cfg) + _conformal_note(fits, cfg),
        "## Energy vs success drop (final energy)\n\n"
        + _success_table(vanilla, conditions, fits, negatives, positives, cfg),
        "## AUROC [bootstrap 95% interval] by score\n\n"
        + _auroc_table(conditions, names, negatives, positives, cfg),
    ]
    for condition in conditions:
        rows = {
            name: ood_detection_table(
                negatives[name], positives[condition][name], cfg.multipliers, fits[name]
            )
            for name in names
        }
        baselines = {name: rows[name] for name in names if name != "final_energy"}
        n_pos = len(conditions[condition])
        sections.append(
            f"## Table III: {condition} ({len(vanilla)} vanilla vs {n_pos} perturbed rollouts)\n\n"
            + format_detection_table(rows["final_energy"], baselines)
        )
    report = "\n\n".join(sections) + "\n"

    cfg.output_dir.mkdir(parents=True, exist_ok=True)
    (cfg.output_dir / "ood_report.md").write_text(report, encoding="utf-8")
    _figures(cfg, calibration_set, fits, negatives, positives, names)
    if cfg.calibrate_to is not None:
        path = fits["final_energy"].save(cfg.calibrate_to, overwrite=cfg.overwrite_calibration)
        logging.info(f"Saved the OOD calibration (T = {fits['final_energy'].threshold:.3f}) to {path}")
    return report


def _calibration_table(fits: dict, negatives: dict, cfg: OODReportConfig) -> str:
    rows = []
    for name, fit in fits.items():
        t_k = fit.with_k(cfg.k).threshold
        fpr_k = float(np.mean(exceeds(negatives[name], t_k)))
        fpr_conformal = float(np.mean(exceeds(negatives[name], fit.conformal_threshold)))
        rows.append(
            [
                name,
                fit.n_rollouts,
                f"{fit.mu_v:.4g}",
                f"{fit.sigma_v:.4g}",
                f"{t_k:.4g}",
                percent(fpr_k),
                f"{fit.conformal_threshold:.4g}",
                percent(fpr_conformal),
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


def _conformal_note(fits: dict, cfg: OODReportConfig) -> str:
    if np.isfinite(fits["final_energy"].conformal_threshold):
        return ""
    needed = math.ceil(1 / cfg.false_alarm_rate - 1 - 1e-9)
    return (
        f"\n\nThe conformal threshold is +inf (nothing flagged): alpha = {percent(cfg.false_alarm_rate)} needs "
        f"at least {needed} calibration rollouts, {fits['final_energy'].n_rollouts} were given."
    )


def _success_table(vanilla, conditions, fits, negatives, positives, cfg) -> str:
    vanilla_success = _success_rate(vanilla)
    final = fits["final_energy"]
    reference = float(np.mean(negatives["final_energy"]))
    rows = [
        [
            "vanilla (held-out)",
            len(vanilla),
            percent(vanilla_success),
            "",
            "0",
            "0",
            "",
            percent(float(np.mean(exceeds(negatives["final_energy"], final.conformal_threshold)))),
        ]
    ]
    for condition, episodes in conditions.items():
        scores = positives[condition]["final_energy"]
        shift = float(np.mean(scores)) - reference
        drop = 100 * (vanilla_success - _success_rate(episodes))
        sigma_units = f"{shift / final.sigma_v:+.2f}" if final.sigma_v > 0 else "n/a"
        rows.append(
            [
                condition,
                len(episodes),
                percent(_success_rate(episodes)),
                f"{drop:+.1f} pts",
                f"{shift:+.4g}",
                sigma_units,
                _interval(negatives["final_energy"], scores, cfg),
                percent(float(np.mean(exceeds(scores, final.conformal_threshold)))),
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


def _auroc_table(conditions, names, negatives, positives, cfg) -> str:
    rows = [
        [condition, len(episodes), *(_interval(negatives[n], positives[condition][n], cfg) for n in names)]
        for condition, episodes in conditions.items()
    ]
    return markdown_table(["Condition", "Episodes", *names], rows)


def _figures(cfg, calibration_set, fits, negatives, positives, names) -> None:
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
    groups = {"calibration": episode_scores(calibration_set, final, cfg.aggregation)}
    groups["vanilla (held-out)"] = negatives[final]
    groups.update({c: p[final] for c, p in positives.items() if c != ALL_CONDITIONS})
    thresholds = {
        f"T = mu_v + {cfg.k:g} sigma_v": fit.with_k(cfg.k).threshold,
        f"T conformal (α={percent(cfg.false_alarm_rate)})": fit.conformal_threshold,
    }
    xlabel = f"rollout score ({cfg.aggregation} of chunk final energies)"
    plot_score_histograms(groups, thresholds, cfg.output_dir / "energy_histogram.png", xlabel)


def main(args: list[str] | None = None) -> None:
    init_logging()
    cfg = draccus.parse(OODReportConfig, args=sys.argv[1:] if args is None else args)
    report = run(cfg)
    sys.stdout.write(report)
    logging.info(f"Saved ood_report.md and the figures to {cfg.output_dir}")


if __name__ == "__main__":
    main()
