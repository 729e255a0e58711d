"""`ebvla-failure-report`: energy-slope failure prediction (paper Table IV), chosen on calibration episodes.

For each step, the (window, k) with the best balanced accuracy is chosen on calibration episodes, with the
slope threshold set by successful reference episodes, then reported unchanged on held-out episodes: across
tasks (all episodes pooled) and within each task. Slope Final and Slope Start both, with the slope's AUROC per
step and the lead time of the alarms. Episodes are compared at equal elapsed time (only those still running at
a step are judged there) unless `--carry_forward=true`.

    ebvla-failure-report --calibration='[outputs/eval/vanilla_seed0]' --records='[outputs/eval/vanilla_seed1]' \\
        --output_dir=outputs/failure_report

Prints and writes `failure_report.md` and `energy_over_time.png` (held-out episodes). `--help` lists every
option; the report is built by `lerobot_policy_ebvla.monitoring.failure_report`.
"""

import logging
import sys

import draccus
from lerobot.utils.utils import init_logging

from lerobot_policy_ebvla.monitoring.failure_report import FailureReportConfig, write_failure_report


def main(args: list[str] | None = None) -> None:
    init_logging()
    cfg = draccus.parse(FailureReportConfig, args=sys.argv[1:] if args is None else args)
    sys.stdout.write(write_failure_report(cfg))
    logging.info(f"Saved failure_report.md and energy_over_time.png to {cfg.output_dir}")


if __name__ == "__main__":
    main()
