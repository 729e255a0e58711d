"""Training-step time and `select_action` latency of the full-size EB-VLA (random weights, bf16) on a GPU.

The policy is built directly on the device with the paper's sizes (two 224 px cameras, Qwen2.5-0.5B, LoRA 64,
K_a = 64, L = 4, D = 896, K_inf = 15) and the built-in Qwen2.5-0.5B config of `vlm_size_table.py` (no Hub).
Inputs are random, already pre-processed batches (random instruction token ids, 20 of 48 real). Run:

    python benchmarks/vlm_gpu_bench.py --batch-sizes 1 8

`--compile-refinement reduce-overhead` sets the policy's `compile_refinement=True` and
`compile_refinement_mode="reduce-overhead"`: the inference MCMC steps run the energy's forward and grad_a
backward in CUDA graphs. It also times the eager refinement in the same run and reports the largest difference
between the two paths' actions for the same generator. `--tiny` swaps in a tiny model for a CPU smoke test of
the script itself (a compiled refinement then compiles C++ through inductor, minutes on a CPU). `--profile`
profiles one training step and one chunk at the first batch size: the costliest ops, the number of GPU kernels
and the GPU busy fraction.
"""

import argparse
import json
import statistics
import time

import torch
from lerobot.utils.constants import ACTION, OBS_LANGUAGE_ATTENTION_MASK, OBS_LANGUAGE_TOKENS, OBS_STATE
from vlm_size_table import full_size_config

from lerobot_policy_ebvla import EBVLAConfig, EBVLAPolicy
from lerobot_policy_ebvla.configuration_ebvla import COMPILE_MODES

TINY = {
    "vlm_config": {
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
    "dim_model": 32,
    "n_heads": 2,
}


def make_batch(
    config: EBVLAConfig, batch_size: int, device: torch.device, dtype: torch.dtype, text_tokens: int = 20
) -> dict:
    """A pre-processed batch; floats in `dtype`, as LeRobot's device step with `float_dtype` would give."""
    vocab = config.vlm_config["vocab_size"]
    batch = {
        key: torch.rand(batch_size, *ft.shape, device=device) for key, ft in config.image_features.items()
    }
    batch[OBS_STATE] = torch.randn(batch_size, config.state_dim, device=device)
    batch[OBS_LANGUAGE_TOKENS] = torch.randint(
        0, min(vocab, 151643), (batch_size, config.tokenizer_max_length), device=device
    )
    mask = torch.zeros(batch_size, config.tokenizer_max_length, dtype=torch.bool, device=device)
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


def compiled_vs_eager(policy: EBVLAPolicy, observation: dict, device: torch.device) -> float:
    """Largest |a_compiled - a_eager| of one chunk (normalized actions) refined from the same a^(0) and noise."""
    chunks = []
    for compile_refinement in (True, False):
        policy.config.compile_refinement = compile_refinement
        generator = torch.Generator(device=device).manual_seed(0)
        with torch.no_grad():
            chunks.append(policy.predict_action_chunk(observation, generator=generator).float())
    return (chunks[0] - chunks[1]).abs().max().item()


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[1, 8])
    parser.add_argument("--train-steps", type=int, default=6, help="Timed training steps (after 2 warm-ups).")
    parser.add_argument("--chunks", type=int, default=10, help="Timed chunk refinements (after 3 warm-ups).")
    parser.add_argument("--tiny", action="store_true", help="Tiny model, for a CPU smoke test.")
    parser.add_argument("--dtype", choices=["bfloat16", "float32"], default="bfloat16")
    parser.add_argument("--json", default=None, help="Also write the results to this file.")
    parser.add_argument(
        "--compile-refinement",
        choices=["off", *COMPILE_MODES],
        default="off",
        help="`compile_refinement_mode` of a compiled inference MCMC energy (`compile_refinement`); "
        "reduce-overhead and max-autotune capture CUDA graphs. The eager path is timed and compared in the "
        "same run.",
    )
    parser.add_argument(
        "--gradient-checkpointing",
        action="store_true",
        help="Recompute the language model's layer activations in the backward pass (less memory, more time).",
    )
    parser.add_argument(
        "--profile",
        action="store_true",
        help="Profile one training step and one chunk at the first batch size (top ops, GPU busy fraction).",
    )
    args = parser.parse_args()

    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dtype = getattr(torch, args.dtype)
    config = full_size_config(offline=True)
    config.device = device.type
    if args.tiny:
        for name, value in TINY.items():
            setattr(config, name, value)
    compiled = args.compile_refinement != "off"
    if compiled:
        config.compile_refinement = True
        config.compile_refinement_mode = args.compile_refinement
    torch.manual_seed(0)
    start = time.perf_counter()
    with torch.device(device):
        policy = EBVLAPolicy(config)
    policy.to(dtype)
    if args.gradient_checkpointing:
        policy.model.backbone.lm.gradient_checkpointing_enable()
    build_s = time.perf_counter() - start
    optimizer = torch.optim.AdamW(policy.get_optim_params(), lr=1e-4)
    results = {
        "device": torch.cuda.get_device_name() if device.type == "cuda" else "cpu",
        "dtype": str(dtype),
        "torch": torch.__version__,
        "build_s": round(build_s, 1),
        "trainable_params_M": round(sum(p.numel() for p in policy.get_optim_params()) / 1e6, 2),
        "total_params_M": round(sum(p.numel() for p in policy.parameters()) / 1e6, 2),
        "compile_refinement": args.compile_refinement,
        "gradient_checkpointing": args.gradient_checkpointing,
    }
    print(json.dumps(results), flush=True)

    for batch_size in args.batch_sizes:
        batch = make_batch(config, batch_size, device, dtype)
        policy.train()

        def train_step(batch=batch):
            optimizer.zero_grad(set_to_none=True)
            loss, info = policy.forward(batch)
            loss.backward()
            optimizer.step()
            return info

        if device.type == "cuda":
            torch.cuda.reset_peak_memory_stats()
        for _ in range(2):
            train_step()
        step_times = [timed(train_step, device) for _ in range(args.train_steps)]
        train_peak = peak_gib(device)

        policy.eval()
        observation = {k: v for k, v in batch.items() if k not in (ACTION, "action_is_pad")}

        def refine_chunk(observation=observation):
            policy.reset()  # every call refines a new chunk
            policy.select_action(observation)

        optimizer.zero_grad(set_to_none=True)
        if device.type == "cuda":
            torch.cuda.empty_cache()
            torch.cuda.reset_peak_memory_stats()
        for _ in range(3):
            refine_chunk()
        chunk_times = [timed(refine_chunk, device) for _ in range(args.chunks)]

        def encode_context(observation=observation):
            with torch.no_grad():
                policy.model.encode_context(observation)

        encode_times = [timed(encode_context, device) for _ in range(args.chunks)]
        extra = {}
        if compiled:
            policy.config.compile_refinement = False
            for _ in range(3):
                refine_chunk()
            eager_times = [timed(refine_chunk, device) for _ in range(args.chunks)]
            extra["eager_select_action_chunk_ms_median"] = round(1e3 * statistics.median(eager_times), 1)
            extra["compiled_vs_eager_max_abs_action_diff"] = compiled_vs_eager(policy, observation, device)
            policy.config.compile_refinement = True
        if args.profile and batch_size == args.batch_sizes[0]:
            policy.train()
            extra["profile_train_step"] = profile_summary(train_step, device)
            optimizer.zero_grad(set_to_none=True)
            policy.eval()
            extra["profile_select_action_chunk"] = profile_summary(refine_chunk, device)
        row = {
            "batch_size": batch_size,
            "train_step_ms_mean": round(1e3 * statistics.mean(step_times), 1),
            "train_step_ms_min": round(1e3 * min(step_times), 1),
            "train_step_ms_max": round(1e3 * max(step_times), 1),
            "train_peak_GiB": round(train_peak, 2),
            "select_action_chunk_ms_median": round(1e3 * statistics.median(chunk_times), 1),
            "select_action_chunk_ms_min": round(1e3 * min(chunk_times), 1),
            "of_which_context_encoding_ms_median": round(1e3 * statistics.median(encode_times), 1),
            "inference_peak_GiB": round(peak_gib(device), 2),
            **extra,
        }
        results[f"batch_{batch_size}"] = row
        print(json.dumps(row), flush=True)

    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=2)


if __name__ == "__main__":
    main()
