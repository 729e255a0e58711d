"""The score summary of `ebvla-ood-report` for several sweeps, in one file: every score's row, then each condition.

Each run is a folder of `metaworld_perturbation_sweep.py` records: `calibration/`, `vanilla/` (held out) and one
folder per condition (`<perturbation>_s<severity>`); `vanilla_extra/` is left out. For each run the report is
written to a temporary folder with its defaults (first 3 chunks in the summary, 1000 bootstrap resamples, seed 0)
and only its section "Score summary" is kept, under the run's name.

    python benchmarks/score_summaries.py --runs s6000=DIR s9000=DIR --output summaries.md
"""

import argparse
import tempfile
from pathlib import Path

from lerobot_policy_ebvla.monitoring.ood_report import OODReportConfig, write_ood_report

NOT_CONDITIONS = ("calibration", "vanilla", "vanilla_extra")


def score_summary(records: Path, n_bootstrap: int = 1000) -> str:
    """The report's section "Score summary" for one run's record folders, without its heading."""
    conditions = sorted(p for p in records.iterdir() if p.is_dir() and p.name not in NOT_CONDITIONS)
    with tempfile.TemporaryDirectory() as out:
        cfg = OODReportConfig(
            calibration=[str(records / "calibration")],
            vanilla=[str(records / "vanilla")],
            ood=[str(p) for p in conditions],
            output_dir=Path(out),
            n_bootstrap=n_bootstrap,
        )
        report = write_ood_report(cfg)
    return report.split("## Score summary\n")[1].split("\n## ")[0].strip()


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
        name, folder = run.split("=", 1)
        sections.append(f"## {name}\n\n{score_summary(Path(folder), args.n_bootstrap)}\n")
    args.output.write_text("\n".join(sections))
    print(f"Wrote {args.output}")


if __name__ == "__main__":
    main()
