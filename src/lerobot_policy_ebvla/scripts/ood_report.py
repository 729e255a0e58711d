"""`ebvla-ood-report`: energy-based OOD detection report (paper Table III) from `energy_records.jsonl` files.

Vanilla rollouts set mu_v and sigma_v; perturbed rollouts are the positives. Prints Table III and the AUROC,
saves the ROC curve and the histograms of rollout scores, and can write the calibration next to a
checkpoint for the run-time `EnergyOODMonitor`.

Examples:
    ebvla-ood-report --vanilla outputs/eval/vanilla --ood outputs/eval/camera_1 outputs/eval/camera_2 \
        --output-dir outputs/ood_report --per-group
    ebvla-ood-report --records outputs/eval/mixed/energy_records.jsonl --output-dir outputs/ood_report \
        --calibrate-to outputs/train/ebvla/checkpoints/last/pretrained_model --k 1.0
"""

import argparse
import logging
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from lerobot.utils.utils import init_logging

from lerobot_policy_ebvla.monitoring.ood import (
    OOD_CALIBRATION_FILENAME,
    SCORE_AGGREGATIONS,
    TABLE_III_MULTIPLIERS,
    OODCalibration,
    auroc,
    format_detection_table,
    ood_detection_table,
    roc_curve,
    rollout_scores,
)
from lerobot_policy_ebvla.monitoring.records import EnergyRecord, read_energy_records

# A perturbation group: (perturbation name, severity).
Group = tuple[str, float]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="ebvla-ood-report",
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument(
        "--vanilla",
        nargs="+",
        default=[],
        type=Path,
        metavar="PATH",
        help="Record files (or eval folders) of in-distribution rollouts.",
    )
    parser.add_argument(
        "--ood",
        nargs="+",
        default=[],
        type=Path,
        metavar="PATH",
        help="Record files (or eval folders) of perturbed rollouts.",
    )
    parser.add_argument(
        "--records",
        nargs="+",
        default=[],
        type=Path,
        metavar="PATH",
        help='Record files mixing both; rows with perturbation "none" are vanilla.',
    )
    parser.add_argument(
        "--output-dir",
        type=Path,
        default=Path("outputs/ood_report"),
        help="Folder for the PNGs and `ood_report.md`.",
    )
    parser.add_argument(
        "--aggregation",
        choices=SCORE_AGGREGATIONS,
        default="mean",
        help="How a rollout's chunk final energies form its score.",
    )
    parser.add_argument(
        "--multipliers",
        nargs="+",
        type=float,
        default=list(TABLE_III_MULTIPLIERS),
        help="Std multipliers k of the table's rows.",
    )
    parser.add_argument(
        "--per-group",
        action="store_true",
        help="Also report each (perturbation, severity) group against all vanilla rollouts.",
    )
    parser.add_argument(
        "--calibrate-to",
        type=Path,
        default=None,
        metavar="CHECKPOINT_DIR",
        help="Write `ood_calibration.json` (fitted on the vanilla rollouts) into this "
        "`pretrained_model` folder.",
    )
    parser.add_argument("--k", type=float, default=1.0, help="Multiplier k stored in the calibration.")
    parser.add_argument(
        "--overwrite-calibration", action="store_true", help="Replace an existing `ood_calibration.json`."
    )
    return parser


def _split_scores(
    args: argparse.Namespace,
) -> tuple[list[float], dict[Group, list[float]]]:
    """Rollout scores of the vanilla rollouts, and of the OOD rollouts per (perturbation, severity)."""
    vanilla: list[float] = []
    ood: dict[Group, list[float]] = {}

    def add(records: Sequence[EnergyRecord], is_vanilla: bool) -> None:
        # Scores are formed per file: episode indices restart in every evaluation run.
        for key, score in rollout_scores(records, args.aggregation).items():
            if is_vanilla:
                vanilla.append(score)
            else:
                ood.setdefault((key.perturbation, key.severity), []).append(score)

    for path in args.vanilla:
        add(read_energy_records(path), is_vanilla=True)
    for path in args.ood:
        add(read_energy_records(path), is_vanilla=False)
    for path in args.records:
        records = read_energy_records(path)
        add([r for r in records if r.is_vanilla], is_vanilla=True)
        add([r for r in records if not r.is_vanilla], is_vanilla=False)
    return vanilla, ood


def plot_roc(curves: dict[str, tuple[np.ndarray, np.ndarray, float]], path: Path) -> None:
    """Saves ROC curves, one per label: {label: (fpr, tpr, auroc)}."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 5))
    for label, (fpr, tpr, area) in curves.items():
        ax.plot(fpr, tpr, label=f"{label} (AUROC {area:.3f})")
    ax.plot([0, 1], [0, 1], color="gray", linestyle="--", linewidth=1)
    ax.set_xlabel("FPR (vanilla rollouts flagged)")
    ax.set_ylabel("TPR (perturbed rollouts caught)")
    ax.legend(loc="lower right", fontsize="small")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_histograms(
    vanilla: Sequence[float], ood: dict[str, Sequence[float]], calibration: OODCalibration, path: Path
) -> None:
    """Saves histograms of the rollout scores with the threshold T = mu_v + k * sigma_v marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    # Infinite scores (diverged refinement) cannot be binned; the legend counts them instead.
    finite = [np.asarray(s, dtype=float) for s in (vanilla, *ood.values())]
    all_finite = np.concatenate([s[np.isfinite(s)] for s in finite])
    bins = np.histogram_bin_edges(all_finite, bins=30) if all_finite.size else 10
    fig, ax = plt.subplots(figsize=(7, 4))
    for label, scores in zip(["vanilla", *ood], finite, strict=True):
        n_inf = int(np.sum(~np.isfinite(scores)))
        suffix = f", {n_inf} non-finite" if n_inf else ""
        ax.hist(scores[np.isfinite(scores)], bins=bins, alpha=0.5, label=f"{label} (n={scores.size}{suffix})")
    ax.axvline(
        calibration.threshold,
        color="red",
        linestyle="--",
        label=rf"$T = \mu_v + {calibration.k:g}\,\sigma_v$ = {calibration.threshold:.3f}",
    )
    ax.set_xlabel(f"rollout score ({calibration.aggregation} of chunk final energies)")
    ax.set_ylabel("rollouts")
    ax.legend(fontsize="small")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _section(title: str, vanilla: Sequence[float], ood: Sequence[float], multipliers: Sequence[float]) -> str:
    rows = ood_detection_table(vanilla, ood, multipliers)
    calibration = OODCalibration.fit(vanilla)
    header = (
        f"## {title}\n\n{len(vanilla)} vanilla rollouts (mu_v = {calibration.mu_v:.3f}, "
        f"sigma_v = {calibration.sigma_v:.3f}), {len(ood)} OOD rollouts, AUROC = {auroc(vanilla, ood):.3f}\n"
    )
    return f"{header}\n{format_detection_table(rows)}\n"


def main(argv: Sequence[str] | None = None) -> None:
    init_logging()
    parser = build_parser()
    args = parser.parse_args(argv)
    if not (args.vanilla or args.records) or not (args.ood or args.records):
        parser.error("give vanilla and perturbed rollouts: --vanilla and --ood, or --records with both.")
    calibration_file = args.calibrate_to / OOD_CALIBRATION_FILENAME if args.calibrate_to else None
    if calibration_file is not None and calibration_file.exists() and not args.overwrite_calibration:
        parser.error(f"{calibration_file} exists; pass --overwrite-calibration to replace it.")
    vanilla, ood_groups = _split_scores(args)
    if not vanilla:
        parser.error("no vanilla rollouts found (rows with perturbation 'none').")
    ood_all = [s for scores in ood_groups.values() for s in scores]

    sections = [_section("All perturbations", vanilla, ood_all, args.multipliers)]
    if args.per_group:
        sections += [
            _section(f"{name}, severity {severity:g}", vanilla, scores, args.multipliers)
            for (name, severity), scores in sorted(ood_groups.items())
        ]
    report = "\n".join(sections)
    sys.stdout.write(report + "\n")

    args.output_dir.mkdir(parents=True, exist_ok=True)
    (args.output_dir / "ood_report.md").write_text(
        f"# Energy-based OOD detection\n\n{report}", encoding="utf-8"
    )
    calibration = OODCalibration.fit(vanilla, k=args.k, aggregation=args.aggregation)
    groups = {"all perturbations": ood_all}
    if args.per_group:
        groups = {f"{n} {s:g}": scores for (n, s), scores in sorted(ood_groups.items())}
    curves = {}
    for label, scores in {"all perturbations": ood_all, **groups}.items():
        fpr, tpr, _ = roc_curve(vanilla, scores)
        curves[label] = (fpr, tpr, auroc(vanilla, scores))
    plot_roc(curves, args.output_dir / "roc_curve.png")
    plot_histograms(vanilla, groups, calibration, args.output_dir / "energy_histogram.png")
    logging.info(f"Saved ood_report.md, roc_curve.png and energy_histogram.png to {args.output_dir}")

    if args.calibrate_to is not None:
        path = calibration.save(args.calibrate_to, overwrite=args.overwrite_calibration)
        logging.info(f"Saved the OOD calibration (T = {calibration.threshold:.3f}) to {path}")


if __name__ == "__main__":
    main()
