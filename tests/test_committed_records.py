"""A reported table recomputed from committed records: the OOD report on the compressed records under
`tests/fixtures/ood_records/` (written by `make_ood_records_fixture.py`), against numbers computed here from
the raw JSON lines, without the package's readers, scores or metrics.
"""

import gzip
import json
import statistics
from pathlib import Path

import pytest

from lerobot_policy_ebvla.monitoring.ood_report import OODReportConfig, write_ood_report

RECORDS = Path(__file__).parent / "fixtures" / "ood_records"


def rollout_scores(folder: str, first_chunks: int | None) -> list[float]:
    """Each episode's mean final energy over its first chunks, read straight from the gzip JSON lines."""
    episodes: dict[int, list[tuple[int, float]]] = {}
    with gzip.open(RECORDS / folder / "energy_records.jsonl.gz", "rt", encoding="utf-8") as f:
        for line in f:
            row = json.loads(line)
            episodes.setdefault(row["episode_index"], []).append((row["chunk_index"], row["final_energy"]))
    energies = [[e for _, e in sorted(chunks)][:first_chunks] for chunks in episodes.values()]
    return [sum(e) / len(e) for e in energies]


def expected_row(k: float, first_chunks: int | None) -> str:
    """The Table III row at multiplier k, as the paper prints it."""
    calibration = rollout_scores("vanilla_calibration", first_chunks)
    threshold = statistics.fmean(calibration) + k * statistics.pstdev(calibration)
    vanilla, ood = rollout_scores("vanilla_held_out", first_chunks), rollout_scores("camera_1", first_chunks)
    tp, fp = sum(s > threshold for s in ood), sum(s > threshold for s in vanilla)
    fn, tn = len(ood) - tp, len(vanilla) - fp
    tpr, fpr = tp / (tp + fn), fp / (fp + tn)
    rates = [(tp + tn) / (tp + tn + fp + fn), (tpr + 1 - fpr) / 2, tpr, fpr, 2 * tp / (2 * tp + fp + fn)]
    return f"| {k:.1f}σ | {threshold:.3f} | " + " | ".join(f"{r:.1%}" for r in rates) + f" | {fp} | {fn} |"


def expected_auroc(first_chunks: int | None) -> str:
    vanilla, ood = rollout_scores("vanilla_held_out", first_chunks), rollout_scores("camera_1", first_chunks)
    wins = sum((o > v) + 0.5 * (o == v) for o in ood for v in vanilla)
    return f"AUROC {wins / (len(ood) * len(vanilla)):.3f} ["


@pytest.fixture(scope="module")
def report(tmp_path_factory) -> str:
    cfg = OODReportConfig(
        calibration=[str(RECORDS / "vanilla_calibration")],
        vanilla=[str(RECORDS / "vanilla_held_out")],
        ood=[str(RECORDS / "camera_1")],
        output_dir=tmp_path_factory.mktemp("ood_report"),
        n_bootstrap=100,
        table_iii_first_chunks=3,
    )
    return write_ood_report(cfg)


def table(report: str, title: str) -> str:
    return report.split(f"## {title}: camera 1 ")[1].split("\n## ")[0]


@pytest.mark.parametrize(("title", "first_chunks"), [("Table III", None), ("Table III, first 3 chunks", 3)])
@pytest.mark.parametrize("k", [0.2, 1.0, 3.0])
def test_a_table_iii_row_recomputed_from_the_committed_records_matches_the_report(
    report, title, first_chunks, k
):
    assert expected_row(k, first_chunks) in table(report, title).splitlines()


@pytest.mark.parametrize(("title", "first_chunks"), [("Table III", None), ("Table III, first 3 chunks", 3)])
def test_the_auroc_beside_table_iii_recomputed_from_the_committed_records_matches_the_report(
    report, title, first_chunks
):
    assert expected_auroc(first_chunks) in table(report, title)


def test_the_committed_records_are_small():
    assert sum(f.stat().st_size for f in RECORDS.rglob("*.gz")) < 20_000
