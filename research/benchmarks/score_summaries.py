"""The score summary of `ebvla-ood-report` for several sweeps, in one file: every score's row, then each condition.

Each run is a folder of `metaworld_perturbation_sweep.py` records: `calibration/`, `vanilla/` (held out) and one
folder per condition (`<perturbation>_s<severity>`); `vanilla_extra/` is left out. A run of fresh rollouts (a
vanilla folder and the conditions re-run, no calibration of its own) names the calibration folder it is scored
against: `NAME=DIR,CALIBRATION_DIR`. For each run the report is
written to a temporary folder with its defaults (first 3 chunks in the summary, 1000 bootstrap resamples, seed 0)
and only its section "Score summary" is kept, under the run's name.

    python research/benchmarks/score_summaries.py --runs s6000=DIR s9000=DIR s6000_fresh=FRESH,CAL --output summaries.md
"""

import argparse
import tempfile
from pathlib import Path

import research_scores  # noqa: F401  (registers the research scores in the package's SCORES)

from lerobot_policy_ebvla.monitoring.ood_report import OODReportConfig, write_ood_report

NOT_CONDITIONS = ("calibration", "vanilla", "vanilla_extra")


def score_summary(records: Path, n_bootstrap: int = 1000, calibration: Path | None = None) -> str:
    """The report's section "Score summary" for one run's record folders (calibrated on `calibration`, by default
    the run's own `calibration/`), without its heading."""
    conditions = sorted(p for p in records.iterdir() if p.is_dir() and p.name not in NOT_CONDITIONS)
    with tempfile.TemporaryDirectory() as out:
        cfg = OODReportConfig(
            calibration=[str(calibration or records / "calibration")],
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
        name, folders = run.split("=", 1)
        records, _, calibration = folders.partition(",")
        summary = score_summary(Path(records), args.n_bootstrap, Path(calibration) if calibration else None)
        sections.append(f"## {name}\n\n{summary}\n")
    args.output.write_text("\n".join(sections))
    print(f"Wrote {args.output}")


if __name__ == "__main__":
    main()
