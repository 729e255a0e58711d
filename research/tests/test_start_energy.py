"""research/docs/libero_runs.md, "The starting sample's energy beside E_c": `context_start_energy` chosen on D's
records and tested on C's, by a rule fixed before C's were read by it. C's Table III is recomputed from its committed
records and the rule's five items read from it; D's development figures are checked against the shipped monitor's
committed report."""

import json

import pytest

from research.tests.conftest import RESULTS, load_benchmark

start_energy = load_benchmark("start_energy")

C_REPORT = RESULTS / "libero_object10" / "reports" / "ebvla_joint_fast_cpu" / "start_energy"
D_REPORTS = RESULTS / "libero_object10_more" / "reports" / "ebvla_joint_fast_cpu_more"


def all_ten(report: list[dict]) -> dict[str, dict]:
    """The rows of the "all ten" group, by score."""
    (group,) = [g for g in report if g["group"] == "all ten"]
    return {row["score"]: row for row in group["rows"]}


def worst(row: dict) -> float:
    return min(row["auroc_per_condition"].values())


def test_cs_report_is_recomputed_from_its_records_and_the_rule_holds(tmp_path):
    start_energy.report(RESULTS / "libero_object10", "ebvla_joint_fast_cpu", tmp_path)
    recomputed = json.loads((tmp_path / "ten_task_report.json").read_text())
    assert recomputed == json.loads((C_REPORT / "ten_task_report.json").read_text())
    rows = all_ten(recomputed)
    new, shipped = rows["context_start_energy"], rows["context_phase_energy"]
    # 1. its worst condition above the shipped score's; 2. pooled at least the shipped score's less 0.01.
    assert (round(worst(new), 3), round(worst(shipped), 3)) == (0.781, 0.63)
    assert (round(new["pooled_auroc"], 3), round(shipped["pooled_auroc"], 3)) == (0.972, 0.952)
    # 3. and 4.: issue 52's targets, as the report checks them for its first score.
    (group,) = [g for g in recomputed if g["group"] == "all ten"]
    met = {target: ok for target, _, ok in group["targets"]}
    assert met["AUROC >= 0.5 under every condition"] and met["AUROC >= 0.85 where success falls 20+ points"]
    assert new["heldout_alarm_rate"] == pytest.approx(0.045) and met["alarms on held-out vanilla <= 10%"]
    # 5. balanced accuracy at T at least the shipped score's less 1 point.
    assert (round(new["balanced_accuracy"], 3), round(shipped["balanced_accuracy"], 3)) == (0.923, 0.908)
    assert round(rows["context_knn"]["pooled_auroc"], 3) == 0.909


def test_ds_development_figures_beside_the_shipped_monitors_report():
    """D's report of the new score holds the shipped report's rows unchanged beside it (one scoring of the same
    records), and the figures the look cites: 0.972 pooled, worst 0.797 (noise 3), against 0.956 and 0.645."""
    development = all_ten(json.loads((D_REPORTS / "start_energy" / "ten_task_report.json").read_text()))
    shipped = all_ten(json.loads((D_REPORTS / "ten_task" / "ten_task_report.json").read_text()))
    for score in ("context_phase_energy", "context_knn", "final_energy"):
        assert development[score] == shipped[score]
    new = development["context_start_energy"]
    assert (round(new["pooled_auroc"], 3), round(worst(new), 3)) == (0.972, 0.797)
    assert round(new["auroc_per_condition"]["light_dim 5"], 3) == 0.825
    old = development["context_phase_energy"]
    assert (round(old["pooled_auroc"], 3), round(worst(old), 3)) == (0.956, 0.645)
