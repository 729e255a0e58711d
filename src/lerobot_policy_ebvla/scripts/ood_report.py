"""`ebvla-ood-report`: energy-based OOD detection (paper Table III) on held-out rollouts, with its baselines.

Calibrate on one set of vanilla rollouts, report on others:

    ebvla-ood-report --calibration='[outputs/eval/vanilla_seed0]' --vanilla='[outputs/eval/vanilla_seed1]' \\
        --ood='[outputs/eval/pose*,outputs/eval/fov*]' --output_dir=outputs/ood_report \\
        --calibrate_to=outputs/train/ebvla/checkpoints/last/pretrained_model

Prints and writes `ood_report.md` (the protocol, the calibration, energy vs success drop per condition,
AUROC with bootstrap 95% intervals per score, the same over each episode's first k chunks (`--first_chunks`),
each score's AUROC of failed against successful rollouts, Table III per condition in the paper's layout with
every score's balanced accuracy beside it, and Table III over the first chunks (`--table_iii_first_chunks`)) and the figures `roc_curve.png`, `roc_baselines.png` and `energy_histogram.png`.
`--calibrate_to` saves the calibration of `--score`, a name of `runtime.scores.SCORES` and a row of the report:
without it `context_knn`, the best held out on the MetaWorld sweep (`phase_energy_two_sided` for records
without context features); `--score=final_energy` is the paper's score, `--score=context_distance` and
`--score=context_knn` save their context statistics or contexts beside the JSON
(`ood_calibration_context.safetensors`, `ood_calibration_neighbours.safetensors`).
`--help` lists every option; the report is built by `lerobot_policy_ebvla.monitoring.ood_report`.
"""

import logging
import sys

import draccus
from lerobot.utils.utils import init_logging

from lerobot_policy_ebvla.monitoring.ood_report import OODReportConfig, write_ood_report


def main(args: list[str] | None = None) -> None:
    init_logging()
    cfg = draccus.parse(OODReportConfig, args=sys.argv[1:] if args is None else args)
    sys.stdout.write(write_ood_report(cfg))
    logging.info(f"Saved ood_report.md and the figures to {cfg.output_dir}")


if __name__ == "__main__":
    main()
