"""research/benchmarks/rtc_metaworld.py: real-time chunking against naive chunk switching on MetaWorld."""

import math

import pytest

from research.tests.conftest import load_benchmark


def test_the_metaworld_benchmark_measures_both_arms_at_each_latency(tmp_path):
    pytest.importorskip("metaworld")
    from tests.test_ood_response import metaworld_config, save_checkpoint

    benchmark = load_benchmark("rtc_metaworld")
    checkpoint = save_checkpoint(tmp_path, metaworld_config(), None, action_dim=4, state_dim=4)
    rows = benchmark.run(checkpoint, task="reach-v3", episodes=1, max_episode_steps=8, latencies=(1,))
    assert [(r["latency"], r["arm"]) for r in rows] == [(1, "naive"), (1, "rtc")]
    for row in rows:
        # chunk_size 4, the next chunk asked for at 2 actions left: a switch every 2 steps after the first chunk.
        assert row["switches"] == 3
        assert math.isfinite(row["mean_jump"]) and math.isfinite(row["mean_final_energy"])
    naive, rtc = rows
    assert rtc["mean_jump"] < naive["mean_jump"]
    with pytest.raises(ValueError, match="Latencies must be"):
        benchmark.run(checkpoint, task="reach-v3", episodes=1, max_episode_steps=8, latencies=(2,))
