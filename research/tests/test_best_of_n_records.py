"""The closed-loop best-of-N table (research/results/metaworld_best_of_n/summary.md, issue 32 part 5),
recomputed from its committed records by the script that printed it."""

import json

import pytest

from research.tests.conftest import RESULTS, load_benchmark

BEST_OF_N = RESULTS / "metaworld_best_of_n"


@pytest.fixture(scope="module")
def script():
    return load_benchmark("best_of_n_closed_loop")


@pytest.fixture(scope="module")
def results(script):
    return script.table(BEST_OF_N)[1]


def pooled(rows: dict) -> tuple[int, int]:
    shifts = [c for c in rows if c != "vanilla"]
    return sum(rows[c]["successes"] for c in shifts), sum(rows[c]["n"] for c in shifts)


def test_every_variant_ran_the_same_episodes(results):
    seeds = {v: {c: sorted(r["outcomes"]) for c, r in rows.items()} for v, rows in results.items()}
    assert len({json.dumps(s, sort_keys=True) for s in seeds.values()}) == 1
    assert len(results["restarts_1"]) == 14  # vanilla and the 13 perturbations at severity 5
    assert results["restarts_1"]["vanilla"]["n"] == 16


def test_best_of_8_raises_success_and_best_of_4_and_adaptive_restarts_at_the_75th_percentile_do_not(
    script, results
):
    base = results["restarts_1"]
    assert pooled(base) == (49, 104)
    assert pooled(results["restarts_8"]) == (60, 104)
    assert pooled(results["restarts_4"]) == (50, 104)
    assert pooled(results["adaptive_8"]) == (48, 104)
    conditions = list(base)
    wins, losses, p = script.paired_against(base, results["restarts_8"], conditions)
    assert (wins, losses) == (14, 1) and p < 0.01
    assert script.paired_against(base, results["restarts_4"], conditions)[:2] == (7, 6)
    wins, losses, p = script.paired_against(base, results["adaptive_8"], conditions)
    assert (wins, losses) == (6, 7) and p > 0.5


def test_the_chunks_compute_is_what_each_variant_asked_for(results):
    assert all(rows["chains_per_chunk"] == 1 for rows in results["restarts_1"].values())
    assert all(rows["chains_per_chunk"] == 8 for rows in results["restarts_8"].values())
    # Adaptive: one chain, or 8 where the first chunk's energy was above the calibration's 75th percentile.
    chains = [rows["chains_per_chunk"] for rows in results["adaptive_8"].values()]
    assert min(chains) > 1 and max(chains) < 8
    threshold = json.loads((BEST_OF_N / "adaptive_8" / "threshold.json").read_text())
    assert threshold["quantile"] == 0.75 and threshold["from"] == "restarts_1/calibration"


def test_the_threshold_is_the_calibrations_quantile(script):
    class Args:
        output_dir = BEST_OF_N
        adaptive_quantile = 0.75

    saved = json.loads((BEST_OF_N / "adaptive_8" / "threshold.json").read_text())["threshold"]
    assert script.adaptive_threshold(Args) == pytest.approx(saved, rel=1e-6)


def test_paired_sign_test_counts_discordant_episodes_only(script):
    base = {"c": {"outcomes": {1: True, 2: False, 3: False, 4: True}}}
    other = {"c": {"outcomes": {1: True, 2: True, 3: True, 4: False}}}
    wins, losses, p = script.paired_against(base, other, ["c"])
    assert (wins, losses) == (2, 1)
    assert p == pytest.approx(1.0)  # 2 of 3 discordant pairs: no evidence either way
    assert script.paired_against(base, base, ["c"]) == (0, 0, 1.0)
