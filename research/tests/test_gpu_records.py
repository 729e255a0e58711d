"""The GPU figures of BENCHMARKS.md and research/docs/vlm_gpu.md ("`compile_mode` on a GPU", "`compile_mode=
"chunk-graph"`") are those of the committed JSONs of the H200 sessions of 2026-11-26 and 2026-11-27
(`research/benchmarks/vlm_gpu_bench.py`, one JSON per configuration)."""

import json
from pathlib import Path

import pytest
import torch

from research.tests.conftest import RESULTS, load_benchmark
from tests.conftest import tiny_batch
from tests.test_compile_mode import BATCH_SIZE, aot_eager_compiles, clear_compiled, make_policy

RECORDS = RESULTS / "gpu_h200_2026-11-26"
CHUNK_GRAPH_RECORDS = RESULTS / "gpu_h200_2026-11-27"
vlm_gpu_bench = load_benchmark("vlm_gpu_bench")


def rows(records: Path = RECORDS) -> dict[str, dict]:
    return {f"{p.parent.name}/{p.stem}": json.loads(p.read_text()) for p in sorted(records.rglob("*.json"))}


def test_every_configuration_ran_on_the_h200_at_full_size():
    records = rows()
    assert len(records) == 8
    for name, row in records.items():
        assert row["device"] == "NVIDIA H200" and not row["tiny"], name
        assert row["total_params_M"] > 1000, name  # the full VLA, not the tiny smoke model
        assert "error" not in row, name


@pytest.mark.parametrize(
    ("record", "figures"),
    [
        ("bf16/chunk_off_b1", ["277.5 (200.4)", "72.6"]),
        ("bf16/chunk_default_b1", ["123.6 (119.9)", "28.5"]),
        ("bf16/chunk_reduce-overhead_b1", ["57.0 (52.1)", "10.6"]),
        ("bf16_untrained_head/chunk_reduce-overhead_b8", ["73.1 (71.6)", "28.8"]),
        ("fp32/chunk_off_b1", ["170.1 (158.8)", "62.2"]),
        ("fp32/chunk_reduce-overhead_b1", ["83.5 (81.6)", "45.6"]),
    ],
)
def test_the_latency_tables_are_the_records(record, figures):
    row = rows()[record]
    assert (
        figures[0] == f"{row['select_action_chunk_ms_median']:.1f} ({row['select_action_chunk_ms_min']:.1f})"
    )
    assert figures[1] == f"{row['of_which_context_encoding_ms_median']:.1f}"


def test_compiled_and_eager_agree_as_reported():
    records = rows()
    fp32 = records["fp32/chunk_reduce-overhead_b1"]
    assert f"{fp32['compiled_vs_eager_max_abs_action_diff']:.1e}" == "7.6e-06"
    assert f"{fp32['compiled_vs_eager_max_abs_final_energy_diff']:.1e}" == "1.2e-05"
    bf16 = records["bf16/chunk_reduce-overhead_b1"]
    assert f"{bf16['compiled_vs_eager_max_abs_action_diff']:.1e}" == "2.8e-03"
    assert bf16["compiled_vs_eager_max_abs_final_energy_diff"] == 0.0
    profile = bf16["profile_select_action_chunk"]
    assert round(100 * profile["gpu_busy_fraction"], 1) == 19.8


def test_the_training_steps_are_the_records():
    records = rows()
    assert round(records["bf16/train_b8"]["train_step_ms_mean"]) == 331
    assert round(records["bf16/train_b32"]["train_step_ms_mean"]) == 503
    assert records["bf16/train_b32"]["train_peak_GiB"] == 30.71


def test_the_benchmark_prints_the_records_as_one_table():
    table = vlm_gpu_bench.markdown_table(RECORDS)
    assert table.count("\n") == len(rows()) + 1  # a header, a rule, one row per configuration
    assert "chunk_reduce-overhead_b1" in table


def test_a_short_device_call_measures_every_mode_at_batch_1_first():
    args = vlm_gpu_bench.parse_args(
        [
            "--batch-sizes",
            "1",
            "8",
            "--train-batch-sizes",
            "8",
            "--order",
            "batch",
            "--compile-modes",
            "off",
            "reduce-overhead",
        ]
    )
    assert [name for name, _, _ in vlm_gpu_bench.configurations(args)] == [
        "train_b8",
        "chunk_off_b1",
        "chunk_reduce-overhead_b1",
        "chunk_off_b8",
        "chunk_reduce-overhead_b8",
    ]
    by_mode = vlm_gpu_bench.parse_args(
        ["--batch-sizes", "1", "8", "--compile-modes", "off", "reduce-overhead"]
    )
    assert [name for name, _, _ in vlm_gpu_bench.configurations(by_mode)][3:5] == [
        "chunk_off_b8",
        "chunk_reduce-overhead_b1",
    ]


def test_the_chunk_graph_rows_are_the_records_and_their_graphs_were_replayed():
    records = rows(CHUNK_GRAPH_RECORDS)
    for name, figures in {
        "bf16/chunk_chunk-graph_b1": ["26.6 (26.1)", "10.7", "65.7 %", "2.3e-2", "3.9e-2"],
        "bf16/chunk_chunk-graph_b8": ["50.6 (49.2)", "31.9", "79.4 %", "5.8e-3", "1.6e-2"],
    }.items():
        row = records[name]
        assert row["device"] == "NVIDIA H200" and not row["tiny"] and row["total_params_M"] > 1000
        assert row["chunk_graphs_captured"] >= 1 and row["chunk_graph_failures"] == []
        measured = [
            f"{row['select_action_chunk_ms_median']:.1f} ({row['select_action_chunk_ms_min']:.1f})",
            f"{row['of_which_context_encoding_ms_median']:.1f}",
            f"{100 * row['profile_select_action_chunk']['gpu_busy_fraction']:.1f} %",
            f"{row['compiled_vs_eager_max_abs_action_diff']:.1e}".replace("e-0", "e-"),
            f"{row['compiled_vs_eager_max_abs_final_energy_diff']:.1e}".replace("e-0", "e-"),
        ]
        assert measured == figures, name


def test_the_first_call_of_2026_11_27_failed_its_capture_on_the_host_copy_as_reported():
    records = rows(CHUNK_GRAPH_RECORDS)
    for batch_size in (1, 8, 32):
        row = records[f"bf16_rotary_on_cpu/chunk_chunk-graph_b{batch_size}"]
        assert row["chunk_graphs_captured"] == 0
        assert all("Cannot copy between CPU and CUDA tensors" in f for f in row["chunk_graph_failures"])
    for mode, reported in (
        ("off", "eager 308.2 / 363.9 / 360.5 ms"),
        ("chunk-graph", "221.4 / 230.9 / 315.2 ms"),
    ):
        medians = [
            records[f"bf16_rotary_on_cpu/chunk_{mode}_b{b}"]["select_action_chunk_ms_median"]
            for b in (1, 8, 32)
        ]
        assert " / ".join(f"{ms:.1f}" for ms in medians) in reported


def diff(value: float) -> str:
    """A difference as the tables print it: 1.1e-3, or 0 for an exact match."""
    return "0" if value == 0 else f"{value:.1e}".replace("e-0", "e-")


@pytest.mark.parametrize(
    ("record", "figures"),
    [
        ("bf16_head300/chunk_chunk-graph_b1", ["27.6 (26.9)", "13.3", "60.0 %", "1.1e-3", "2.8e-3", "0 / 0"]),
        (
            "bf16_head300/chunk_reduce-overhead_b1",
            ["67.2 (60.2)", "12.6", "15.9 %", "2.6e-3", "3.9e-3", "1.2e-3 / 0"],
        ),
        ("bf16_head300/chunk_off_b1", ["382.3 (347.0)", "118.6", "4.3 %"]),
        (
            "bf16_head300/chunk_chunk-graph_b8",
            ["51.8 (51.2)", "32.9", "74.5 %", "2.9e-3", "7.8e-3", "1.2e-3 / 7.8e-3"],
        ),
        (
            "bf16_head300/chunk_reduce-overhead_b8",
            ["65.0 (62.9)", "32.5", "42.9 %", "2.4e-3", "9.0e-3", "3.9e-3 / 5.9e-3"],
        ),
        ("bf16_head300/chunk_off_b8", ["376.7 (335.2)", "90.3", "9.8 %"]),
        (
            "fp32_head150/chunk_chunk-graph_b1",
            ["76.3 (76.2)", "46.4", None, "5.8e-6", "2.6e-5", "5.4e-6 / 2.6e-5"],
        ),
    ],
)
def test_the_trained_head_rows_are_the_records(record, figures):
    """The 300-step head's table of BENCHMARKS.md and research/docs/vlm_gpu.md, with the difference split
    into the context's and the chain's alone."""
    row = rows(CHUNK_GRAPH_RECORDS)[record]
    assert row["device"] == "NVIDIA H200" and not row["tiny"] and row["total_params_M"] > 1000
    assert row["head_trained_steps"] == (300 if record.startswith("bf16") else 150)
    if row["compile_mode"] == "chunk-graph":
        assert row["chunk_graphs_captured"] >= 1 and row["chunk_graph_failures"] == []
    profile = row.get("profile_select_action_chunk")
    measured = [
        f"{row['select_action_chunk_ms_median']:.1f} ({row['select_action_chunk_ms_min']:.1f})",
        f"{row['of_which_context_encoding_ms_median']:.1f}",
        None if profile is None else f"{100 * profile['gpu_busy_fraction']:.1f} %",
    ]
    if row["compile_mode"] != "off":
        measured += [
            diff(row["compiled_vs_eager_max_abs_action_diff"]),
            diff(row["compiled_vs_eager_max_abs_final_energy_diff"]),
            f"{diff(row['chain_on_eager_context_max_abs_action_diff'])} / "
            f"{diff(row['chain_on_eager_context_max_abs_final_energy_diff'])}",
        ]
    assert measured == figures


def test_the_trained_head_training_steps_and_context_differences_are_the_records():
    records = rows(CHUNK_GRAPH_RECORDS)
    assert round(records["bf16_head300/train_b8"]["train_step_ms_mean"], 1) == 445.1
    assert round(records["bf16_head300/train_b32"]["train_step_ms_mean"], 1) == 507.4
    assert records["bf16_head300/train_b32"]["train_peak_GiB"] == 30.71
    bf16_context = [
        records[f"bf16_head300/chunk_{mode}_b{b}"]["context_max_rel_diff"]
        for mode in ("chunk-graph", "reduce-overhead")
        for b in (1, 8)
    ]
    assert f"{min(bf16_context):.1%}-{max(bf16_context):.1%}" == "1.2%-1.5%"


def test_the_difference_split_puts_a_context_difference_in_the_context_not_the_chain(monkeypatch):
    """`context_and_chain_diffs` runs the chain of both modes on the eager context: a compiled context that differs
    shows in the context's figures alone, and the policy keeps its mode."""
    aot_eager_compiles(monkeypatch)
    clear_compiled()
    policy = make_policy(compile_mode="chunk-graph")
    batch = tiny_batch(policy.config, batch_size=BATCH_SIZE, seed=17, with_action=False)
    encode = policy.model._inference_context

    def context_off_by_half_when_compiled(observation, return_features=False):
        kv = encode(observation, return_features)
        return kv if policy.config.compile_mode == "off" else [(k + 0.5, v) for k, v in kv]

    monkeypatch.setattr(policy.model, "_inference_context", context_off_by_half_when_compiled)
    try:
        diffs = vlm_gpu_bench.context_and_chain_diffs(policy, batch, torch.device("cpu"))
    finally:
        clear_compiled()
    assert policy.config.compile_mode == "chunk-graph"
    assert diffs["context_max_abs_diff"] == pytest.approx(0.5, abs=1e-3)
    policy.config.compile_mode = "off"
    with torch.no_grad():
        largest = max(t.abs().max().item() for pair in encode(batch) for t in pair)
    policy.config.compile_mode = "chunk-graph"
    assert diffs["context_max_rel_diff"] == pytest.approx(diffs["context_max_abs_diff"] / largest)
    assert diffs["chain_on_eager_context_max_abs_action_diff"] == 0.0  # off CUDA the chain is the eager chain
    assert diffs["chain_on_eager_context_max_abs_final_energy_diff"] == 0.0
