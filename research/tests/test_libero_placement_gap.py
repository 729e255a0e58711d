"""research/docs/libero_placement_gap.md's tables, recomputed from the resets its JSON keeps (`raw`): the analysis
reads D's committed records and the cached poses, and runs no simulator."""

import json
import shutil
import sys
from pathlib import Path

import pytest

from .conftest import load_benchmark

RESULTS = Path(__file__).resolve().parents[1] / "results"
COMMITTED = RESULTS / "libero_object10_more" / "placement_gap.json"


@pytest.mark.skipif(not COMMITTED.exists(), reason="the placement-gap measurements are not committed here")
def test_the_committed_placement_gap_is_recomputed_from_its_cached_resets(tmp_path, monkeypatch):
    output = tmp_path / "placement_gap.json"
    shutil.copyfile(COMMITTED, output)
    monkeypatch.setattr(sys, "argv", ["libero_placement_gap.py", "--output", str(output)])
    load_benchmark("libero_placement_gap").main()
    got, committed = json.loads(output.read_text()), json.loads(COMMITTED.read_text())
    assert got == committed
    # The doc's reading: D's failures are not on the unusual placements (pooled over the 500 fixed states, 60
    # failed); every fixed state starts the arm off the default, and its offset ranks task 1's failures.
    pooled = got["pooled"]
    assert pooled["target"]["auroc_failure_nn_over_threshold"]["auroc"] == pytest.approx(0.511, abs=5e-4)
    assert pooled["robot_start_eef_offset"]["auroc_failure"]["auroc"] == pytest.approx(0.69, abs=5e-4)
    task1 = got["tasks"]["1"]["robot_start"]
    assert (
        task1["n_fixed_with_arm_off_default"] == 50
        and task1["sampled_arm_max_abs_diff_across_seeds_rad"] == 0
    )
    assert task1["auroc_failure_eef_offset"]["auroc"] == pytest.approx(0.757, abs=5e-4)
