"""Training-step time and `select_action` latency of the full-size EB-VLA (random weights, bf16) on a GPU, for each
`compile_mode`.

The policy is built directly on the device with the paper's sizes (two 224 px cameras, Qwen2.5-0.5B, LoRA 64,
K_a = 64, L = 4, D = 896, K_inf = 15) and the built-in Qwen2.5-0.5B config of `vlm_size_table.py` (no Hub).
Inputs are random, already pre-processed batches (random instruction token ids, 20 of 48 real). Run:

    python research/benchmarks/vlm_gpu_bench.py --batch-sizes 1 8 32 --compile-modes off default reduce-overhead \\
        max-autotune --out-dir research/results/gpu_h100_DATE --skip-existing --budget-s 420

A configuration is one training step size (`train_b{B}.json`, eager; `--train-steps 0` skips them) or one
(compile mode, batch size) pair (`chunk_{mode}_b{B}.json`: a new chunk per `select_action` with the policy's
`compile_mode` set to that mode). Each writes its JSON into `--out-dir` as soon as it is measured. A chunk
configuration records the start-up (the first chunk, which compiles and, in the CUDA-graph modes, captures),
the median and min of `--chunks` timed chunks, the context encoding alone (compiled as the chunk runs it), the
peak memory and, for a compiled mode, the largest differences of the actions and final energies from the eager
chunk refined from the same a^(0) and noise, split into the context's difference and the chain's alone (run in
the mode and eagerly on the eager context). `--skip-existing` skips a configuration whose JSON exists and
`--budget-s` starts no new one after that many seconds, so the same command, run again in slices of device time
(`timeout 480 python ...`), goes on where the last slice stopped; a slice killed mid-configuration leaves no
JSON for it. Modes share the process's memory (CUDA-graph pools stay allocated), so for clean peak memories
run one compile mode per process. `--profile` adds one profiled chunk per configuration and one profiled
training step: the costliest ops, the number of GPU kernels and the GPU busy fraction. `--tiny` swaps in a tiny
model for a CPU smoke test of the script (inductor then compiles C++, about a minute per mode and batch size
on a 2-core CPU).
"""

import argparse
import json
import os
import statistics
import time
import traceback
from pathlib import Path

import torch
from lerobot.utils.constants import ACTION, OBS_LANGUAGE_ATTENTION_MASK, OBS_LANGUAGE_TOKENS, OBS_STATE
from vlm_size_table import full_size_config

from lerobot_policy_ebvla import EBVLAConfig, EBVLAPolicy
from lerobot_policy_ebvla.compile_ebvla import CHUNK_GRAPH_MODE, refinement_graphs
from lerobot_policy_ebvla.configuration_ebvla import COMPILE_MODES, TRAIN_COMPILE_MODES
from lerobot_policy_ebvla.energy_head import ContextKV

# Fields of the `vlm` group, then top-level fields, of the tiny VLM.
TINY_VLM = {
    "model_config": {
        "model_type": "qwen2",
        "vocab_size": 256,
        "hidden_size": 64,
        "intermediate_size": 128,
        "num_hidden_layers": 2,
        "num_attention_heads": 4,
        "num_key_value_heads": 2,
    },
    "vision_model_overrides": {"depth": 2, "embed_dim": 32, "num_heads": 2},
    "vision_image_size": 28,
    "num_context_layers": 3,
}
TINY = {"dim_model": 32, "n_heads": 2}


def make_batch(
    config: EBVLAConfig, batch_size: int, device: torch.device, dtype: torch.dtype, text_tokens: int = 20
) -> dict:
    """A pre-processed batch; floats in `dtype`, as LeRobot's device step with `float_dtype` would give."""
    vocab = config.vlm.model_config["vocab_size"]
    batch = {
        key: torch.rand(batch_size, *ft.shape, device=device) for key, ft in config.image_features.items()
    }
    batch[OBS_STATE] = torch.randn(batch_size, config.state_dim, device=device)
    batch[OBS_LANGUAGE_TOKENS] = torch.randint(
        0, min(vocab, 151643), (batch_size, config.vlm.tokenizer_max_length), device=device
    )
    mask = torch.zeros(batch_size, config.vlm.tokenizer_max_length, dtype=torch.bool, device=device)
    mask[:, :text_tokens] = True
    batch[OBS_LANGUAGE_ATTENTION_MASK] = mask
    batch[ACTION] = torch.randn(batch_size, config.chunk_size, config.action_dim, device=device)
    batch["action_is_pad"] = torch.zeros(batch_size, config.chunk_size, dtype=torch.bool, device=device)
    return {k: v.to(dtype) if v.is_floating_point() else v for k, v in batch.items()}


def timed(fn, device: torch.device) -> float:
    if device.type == "cuda":
        torch.cuda.synchronize()
    start = time.perf_counter()
    fn()
    if device.type == "cuda":
        torch.cuda.synchronize()
    return time.perf_counter() - start


def profile_summary(fn, device: torch.device, rows: int = 12) -> dict:
    """One call of `fn` under torch.profiler: wall time, GPU kernel time and count, and the costliest ops.

    A GPU busy fraction far under 1 means the step is bound by kernel launches and Python, not arithmetic.
    """
    from torch.profiler import ProfilerActivity, profile

    cuda = device.type == "cuda"
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    with profile(activities=activities) as prof:
        wall = timed(fn, device)
    kernels = [e for e in prof.events() if e.device_type == torch.autograd.DeviceType.CUDA]
    kernel_ms = sum(e.device_time_total for e in kernels) / 1e3
    sort_by = "self_device_time_total" if cuda else "self_cpu_time_total"
    print(prof.key_averages().table(sort_by=sort_by, row_limit=rows), flush=True)
    return {
        "wall_ms": round(1e3 * wall, 1),
        "gpu_kernel_ms": round(kernel_ms, 1),
        "gpu_kernels": len(kernels),
        "gpu_busy_fraction": round(kernel_ms / (1e3 * wall), 3) if cuda else None,
    }


def peak_gib(device: torch.device) -> float:
    return torch.cuda.max_memory_allocated() / 1024**3 if device.type == "cuda" else float("nan")


def reset_peak(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats()


def seeded_chunk(
    policy: EBVLAPolicy, observation: dict, device: torch.device
) -> tuple[torch.Tensor, torch.Tensor]:
    """One chunk (normalized actions) and its final energies, refined from a fixed a^(0) and noise."""
    generator = torch.Generator(device=device).manual_seed(0)
    with torch.no_grad():
        actions, readout = policy.predict_action_chunk(observation, generator=generator, return_energy=True)
    return actions.float(), readout.final_energy.float()


def max_abs_diff(a: torch.Tensor, b: torch.Tensor) -> float:
    return (a.float() - b.float()).abs().max().item()


def compiled_vs_eager(policy: EBVLAPolicy, observation: dict, device: torch.device) -> dict:
    """Largest |compiled - eager| of the actions and final energies of one chunk, same a^(0) and noise."""
    mode = policy.config.compile_mode
    compiled = seeded_chunk(policy, observation, device)
    policy.config.compile_mode = "off"
    try:
        eager = seeded_chunk(policy, observation, device)
    finally:
        policy.config.compile_mode = mode
    return {
        "compiled_vs_eager_max_abs_action_diff": max_abs_diff(compiled[0], eager[0]),
        "compiled_vs_eager_max_abs_final_energy_diff": max_abs_diff(compiled[1], eager[1]),
        **context_and_chain_diffs(policy, observation, device),
    }


def context_and_chain_diffs(policy: EBVLAPolicy, observation: dict, device: torch.device) -> dict:
    """Where a compiled chunk parts from the eager one: the context C (largest |compiled - eager| over its
    per-layer keys and values, and relative to their largest |eager| entry), and the refinement chain alone, run
    in the compiled mode and eagerly on the same eager context, a^(0) and noise. In bf16 a small context
    difference is amplified by K_inf energy-scaled steps; a chain that agrees on one context says the compiled
    chain itself is faithful."""
    model, mode = policy.model, policy.config.compile_mode

    def context_in(run_mode: str) -> ContextKV:
        policy.config.compile_mode = run_mode
        with torch.no_grad():  # a CUDA-graph output is overwritten by the next replay: cloned at once
            return [(k.clone(), v.clone()) for k, v in model._inference_context(observation)]

    def chain_in(run_mode: str, kv: ContextKV) -> tuple[torch.Tensor, torch.Tensor]:
        policy.config.compile_mode = run_mode
        generator = torch.Generator(device=device).manual_seed(0)
        initial = model.initial_actions(kv[0][0].shape[0], kv[0][0], generator)
        result, final_energy = model._inference_chain(kv, initial, generator, None)
        return result.actions.detach(), final_energy.detach()

    try:
        eager_kv, compiled_kv = context_in("off"), context_in(mode)
        compiled_chain, eager_chain = chain_in(mode, eager_kv), chain_in("off", eager_kv)
    finally:
        policy.config.compile_mode = mode
    eager_tensors = [t for pair in eager_kv for t in pair]
    compiled_tensors = [t for pair in compiled_kv for t in pair]
    context_diff = max(max_abs_diff(c, e) for c, e in zip(compiled_tensors, eager_tensors, strict=True))
    return {
        "context_max_abs_diff": context_diff,
        "context_max_rel_diff": context_diff / max(e.float().abs().max().item() for e in eager_tensors),
        "chain_on_eager_context_max_abs_action_diff": max_abs_diff(compiled_chain[0], eager_chain[0]),
        "chain_on_eager_context_max_abs_final_energy_diff": max_abs_diff(compiled_chain[1], eager_chain[1]),
    }


def train_configuration(policy, optimizer, batch: dict, args, device: torch.device) -> dict:
    """Eager training steps (`compile_mode` applies to inference only) after 2 warm-ups."""
    policy.train()

    def train_step():
        optimizer.zero_grad(set_to_none=True)
        loss, _ = policy.forward(batch)
        loss.backward()
        optimizer.step()

    reset_peak(device)
    for _ in range(2):
        train_step()
    step_times = [timed(train_step, device) for _ in range(args.train_steps)]
    row = {
        "train_step_ms_mean": round(1e3 * statistics.mean(step_times), 1),
        "train_step_ms_min": round(1e3 * min(step_times), 1),
        "train_step_ms_max": round(1e3 * max(step_times), 1),
        "train_peak_GiB": round(peak_gib(device), 2),
    }
    if args.profile:
        row["profile_train_step"] = profile_summary(train_step, device)
    optimizer.zero_grad(set_to_none=True)
    return row


def train_curve_configuration(
    policy, start_state: dict, batch: dict, mode: str, args, device: torch.device, eager_losses: dict
) -> dict:
    """`--curve-steps` training steps in `train_compile_mode=mode` from `start_state` (weights and the training
    draws' seed: every mode sees the same K, alpha, a^(0) and noise) on one fixed batch, with a fresh AdamW. Each
    step is timed; the first (which compiles) is reported apart. Against the eager curve of the same batch size
    (measured first), the largest absolute and relative loss differences over the steps."""
    policy.load_state_dict(start_state)
    policy.config.train_compile_mode = mode
    policy.train()
    optimizer = torch.optim.AdamW(policy.get_optim_params(), lr=1e-4)

    def train_step():
        optimizer.zero_grad(set_to_none=True)
        loss, _ = policy.forward(batch)
        loss.backward()
        optimizer.step()
        losses.append(loss.item())

    losses: list[float] = []
    reset_peak(device)
    step_times = [timed(train_step, device) for _ in range(args.curve_steps)]
    optimizer.zero_grad(set_to_none=True)
    steady = step_times[min(5, len(step_times) - 1) :]  # the first steps compile (and capture)
    row = {
        "train_compile_mode": mode,
        "curve_steps": args.curve_steps,
        "first_step_s": round(step_times[0], 1),
        "train_step_ms_median_after_5": round(1e3 * statistics.median(steady), 1),
        "train_step_ms_min": round(1e3 * min(steady), 1),
        "train_peak_GiB": round(peak_gib(device), 2),
        "losses": [round(value, 5) for value in losses],
    }
    batch_size = batch[ACTION].shape[0]
    if mode == "off":
        eager_losses[batch_size] = losses
    elif batch_size in eager_losses:
        reference = eager_losses[batch_size]
        diffs = [abs(a - b) for a, b in zip(losses, reference, strict=True)]
        row["max_abs_loss_diff_vs_eager"] = round(max(diffs), 5)
        row["max_rel_loss_diff_vs_eager"] = round(
            max(d / abs(b) for d, b in zip(diffs, reference, strict=True)), 5
        )
        row["loss_first_last_eager"] = [round(reference[0], 4), round(reference[-1], 4)]
    policy.config.train_compile_mode = "off"
    return row


def chunk_configuration(policy: EBVLAPolicy, observation: dict, args, device: torch.device) -> dict:
    """`select_action` on a new chunk in `policy.config.compile_mode`: start-up, timed chunks, comparison."""
    policy.eval()

    def refine_chunk():
        policy.reset()  # every call refines a new chunk
        policy.select_action(observation)

    def encode_context():
        with torch.no_grad():
            policy.model._inference_context(
                observation
            )  # the context encoding the chunk runs, compiled or not

    reset_peak(device)
    startup_s = timed(refine_chunk, device)
    for _ in range(2):
        refine_chunk()
    chunk_times = [timed(refine_chunk, device) for _ in range(args.chunks)]
    encode_times = [timed(encode_context, device) for _ in range(args.chunks)]
    row = {
        "startup_first_chunk_s": round(startup_s, 1),
        "select_action_chunk_ms_median": round(1e3 * statistics.median(chunk_times), 1),
        "select_action_chunk_ms_min": round(1e3 * min(chunk_times), 1),
        "of_which_context_encoding_ms_median": round(1e3 * statistics.median(encode_times), 1),
        "inference_peak_GiB": round(peak_gib(device), 2),
    }
    if policy.config.compile_mode == CHUNK_GRAPH_MODE:  # were the chains replayed, or refined eagerly?
        graphs = refinement_graphs(policy.model.head)
        row["chunk_graphs_captured"] = len(graphs.graphs)
        row["chunk_graph_failures"] = list(graphs.failures.values())
    if policy.config.compile_mode != "off":
        row.update(compiled_vs_eager(policy, observation, device))
    if args.profile:
        row["profile_select_action_chunk"] = profile_summary(refine_chunk, device)
    return row


def train_head(
    policy, optimizer, config, steps: int, device, dtype, batch_size: int = 8
) -> list[float] | None:
    """`steps` eager training steps on one fixed random batch (seed 1): the energy learns a bowl around its
    actions, as a trained head has, before compiled and eager refinements are compared. Returns the first and
    last losses."""
    if steps <= 0:
        return None
    torch.manual_seed(1)
    batch = make_batch(config, batch_size, device, dtype)
    policy.train()
    losses = []
    for _ in range(steps):
        optimizer.zero_grad(set_to_none=True)
        loss, _ = policy.forward(batch)
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    optimizer.zero_grad(set_to_none=True)
    torch.manual_seed(0)
    return [round(losses[0], 4), round(losses[-1], 4)]


TABLE_COLUMNS = {
    "configuration": "configuration",
    "dtype": "dtype",
    "batch_size": "B",
    "select_action_chunk_ms_median": "chunk ms (median)",
    "select_action_chunk_ms_min": "chunk ms (min)",
    "of_which_context_encoding_ms_median": "context ms",
    "startup_first_chunk_s": "first chunk s",
    "inference_peak_GiB": "inference peak GiB",
    "train_step_ms_mean": "train step ms",
    "train_compile_mode": "train_compile_mode",
    "first_step_s": "first step s",
    "train_step_ms_median_after_5": "train step ms (median after 5)",
    "max_abs_loss_diff_vs_eager": "max |loss diff|",
    "max_rel_loss_diff_vs_eager": "max rel. loss diff",
    "train_peak_GiB": "train peak GiB",
    "gpu_busy_fraction": "GPU busy",
    "compiled_vs_eager_max_abs_action_diff": "max |action diff|",
    "compiled_vs_eager_max_abs_final_energy_diff": "max |energy diff|",
    "context_max_rel_diff": "context rel. diff",
    "chain_on_eager_context_max_abs_action_diff": "chain alone: max |action diff|",
    "chain_on_eager_context_max_abs_final_energy_diff": "chain alone: max |energy diff|",
    "head_trained_steps": "head steps",
    "error": "error",
}


def markdown_table(folder: Path) -> str:
    """One row per configuration JSON of `folder` (and its subfolders): the latency, memory, GPU-busy and
    compiled-vs-eager tolerance tables of research/docs/vlm_gpu.md in one."""
    rows = []
    for path in sorted(folder.rglob("*.json")):
        row = json.loads(path.read_text())
        profile = row.get("profile_select_action_chunk") or row.get("profile_train_step") or {}
        row["gpu_busy_fraction"] = profile.get("gpu_busy_fraction")
        rows.append(row)
    columns = [c for c in TABLE_COLUMNS if any(row.get(c) is not None for row in rows)]
    lines = ["| " + " | ".join(TABLE_COLUMNS[c] for c in columns) + " |", "|" + "---|" * len(columns)]
    for row in rows:
        cells = [row.get(c) for c in columns]
        lines.append(
            "| "
            + " | ".join(
                "" if v is None else f"{v:.2e}" if "diff" in c else str(v)
                for c, v in zip(columns, cells, strict=True)
            )
            + " |"
        )
    return "\n".join(lines)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[1, 8, 32])
    parser.add_argument(
        "--train-batch-sizes",
        type=int,
        nargs="+",
        default=None,
        help="batch sizes of the timed training steps (default: --batch-sizes)",
    )
    parser.add_argument(
        "--order",
        choices=["mode", "batch"],
        default="mode",
        help="chunk configurations mode by mode (each mode at every batch size), or batch size by batch size "
        "(every mode at the first batch size first: the B=1 target before the rest in a short device call)",
    )
    parser.add_argument(
        "--compile-modes",
        nargs="+",
        choices=COMPILE_MODES,
        default=["off"],
        help="the policy's `compile_mode` of each chunk configuration; reduce-overhead and max-autotune "
        "replay CUDA graphs on a GPU",
    )
    parser.add_argument(
        "--train-steps",
        type=int,
        default=6,
        help="Timed training steps (after 2 warm-ups); 0 skips training.",
    )
    parser.add_argument(
        "--chunks", type=int, default=10, help="Timed chunks (after the start-up and 2 more)."
    )
    parser.add_argument(
        "--train-compile-modes",
        nargs="+",
        choices=TRAIN_COMPILE_MODES,
        default=[],
        help="loss-curve configurations, before every other: `--curve-steps` steps at each training batch size "
        "in each `train_compile_mode` (eager 'off' always first), from the same weights and draws",
    )
    parser.add_argument("--curve-steps", type=int, default=50, help="training steps of each loss curve")
    parser.add_argument(
        "--train-head-steps",
        type=int,
        default=0,
        help="Eager training steps on one fixed batch before any configuration, so that the compiled-vs-eager "
        "differences are measured on a trained head (the issue asks for a few hundred), not random weights.",
    )
    parser.add_argument(
        "--table",
        type=Path,
        default=None,
        help="Print the markdown table of the JSONs in this folder and exit (no model is built).",
    )
    parser.add_argument("--tiny", action="store_true", help="Tiny model, for a CPU smoke test.")
    parser.add_argument("--dtype", choices=["bfloat16", "float32"], default="bfloat16")
    parser.add_argument("--out-dir", type=Path, default=None, help="One JSON per configuration goes here.")
    parser.add_argument(
        "--skip-existing", action="store_true", help="Skip configurations whose JSON is in --out-dir."
    )
    parser.add_argument(
        "--budget-s", type=float, default=None, help="Start no new configuration after this many seconds."
    )
    parser.add_argument(
        "--gradient-checkpointing",
        action="store_true",
        help="Recompute the language model's layer activations in the backward pass (less memory, more time).",
    )
    parser.add_argument(
        "--profile",
        action="store_true",
        help="Profile one chunk per configuration and one training step (top ops, GPU busy fraction).",
    )
    args = parser.parse_args(argv)
    if args.skip_existing and args.out_dir is None:
        parser.error("--skip-existing needs --out-dir")
    return args


def configurations(args) -> list[tuple[str, str | None, int]]:
    """(JSON name, compile mode, "train:<mode>" for a loss curve or None for eager training steps, batch size):
    the loss curves first, then eager training, then the chunks in `args.order`."""
    train_sizes = args.train_batch_sizes or args.batch_sizes
    curve_modes = (
        ["off"] + [m for m in args.train_compile_modes if m != "off"] if args.train_compile_modes else []
    )
    curves = [(f"traincurve_{mode}_b{b}", f"train:{mode}", b) for b in train_sizes for mode in curve_modes]
    train = [(f"train_b{b}", None, b) for b in train_sizes] if args.train_steps > 0 else []
    pairs = [(mode, b) for mode in args.compile_modes for b in args.batch_sizes]
    if args.order == "batch":
        pairs.sort(key=lambda pair: args.batch_sizes.index(pair[1]))  # stable: modes keep their order
    return curves + train + [(f"chunk_{mode}_b{b}", mode, b) for mode, b in pairs]


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    if args.table is not None:
        print(markdown_table(args.table))
        return
    started = time.perf_counter()
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dtype = getattr(torch, args.dtype)
    # One compiled graph per (mode, batch size) of each compiled function: more than dynamo's default of 8.
    torch._dynamo.config.recompile_limit = 64
    todo = [
        c
        for c in configurations(args)
        if not (args.skip_existing and (args.out_dir / f"{c[0]}.json").exists())
    ]
    if not todo:
        print("Every configuration has its JSON in", args.out_dir, flush=True)
        return
    config = full_size_config(offline=True)
    config.device = device.type
    if args.tiny:
        for name, value in TINY.items():
            setattr(config, name, value)
        for name, value in TINY_VLM.items():
            setattr(config.vlm, name, value)
    torch.manual_seed(0)
    start = time.perf_counter()
    with torch.device(device):
        policy = EBVLAPolicy(config)
    policy.to(dtype)
    if args.gradient_checkpointing:
        policy.model.backbone.lm.gradient_checkpointing_enable()
    build_s = time.perf_counter() - start
    optimizer = torch.optim.AdamW(policy.get_optim_params(), lr=1e-4)
    head_loss = train_head(policy, optimizer, config, args.train_head_steps, device, dtype)
    # Every loss curve starts here; the chunk configurations then run on the last curve's weights.
    start_state = {k: v.clone() for k, v in policy.state_dict().items()} if args.train_compile_modes else None
    eager_losses: dict[int, list[float]] = {}
    common = {
        "device": torch.cuda.get_device_name() if device.type == "cuda" else "cpu",
        "dtype": str(dtype),
        "torch": torch.__version__,
        "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
        "build_s": round(build_s, 1),
        "trainable_params_M": round(sum(p.numel() for p in policy.get_optim_params()) / 1e6, 2),
        "total_params_M": round(sum(p.numel() for p in policy.parameters()) / 1e6, 2),
        "gradient_checkpointing": args.gradient_checkpointing,
        "head_trained_steps": args.train_head_steps,
        "head_loss_first_last": head_loss,
        "tiny": args.tiny,
    }
    print(json.dumps(common), flush=True)
    if args.out_dir is not None:
        args.out_dir.mkdir(parents=True, exist_ok=True)

    for name, mode, batch_size in todo:
        if args.budget_s is not None and time.perf_counter() - started > args.budget_s:
            print(f"Budget of {args.budget_s:.0f} s spent; not started: {name} and later.", flush=True)
            break
        torch.manual_seed(2)  # the same batch for every mode of a batch size
        batch = make_batch(config, batch_size, device, dtype)
        try:
            if mode is not None and mode.startswith("train:"):
                curve_mode = mode.removeprefix("train:")
                row = train_curve_configuration(
                    policy, start_state, batch, curve_mode, args, device, eager_losses
                )
            elif mode is None:
                row = train_configuration(policy, optimizer, batch, args, device)
            else:
                policy.config.compile_mode = mode
                observation = {k: v for k, v in batch.items() if k not in (ACTION, "action_is_pad")}
                row = chunk_configuration(policy, observation, args, device)
        except Exception as error:  # noqa: BLE001 -- one failing mode must not cost a device call the others
            traceback.print_exc()
            row = {"error": f"{type(error).__name__}: {error}"[:2000]}
            policy.config.compile_mode = policy.config.train_compile_mode = "off"
        row = {"configuration": name, "compile_mode": mode, "batch_size": batch_size, **row, **common}
        print(json.dumps(row), flush=True)
        if args.out_dir is not None:
            # Written whole or not at all: a slice killed while writing must not leave a JSON to skip.
            partial = args.out_dir / f".{name}.json.partial"
            partial.write_text(json.dumps(row, indent=2))
            os.replace(partial, args.out_dir / f"{name}.json")


if __name__ == "__main__":
    main()
