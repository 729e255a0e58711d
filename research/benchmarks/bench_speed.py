"""Speed of EB-VLA (light backbone) against LeRobot's Diffusion Policy, and of the energy head against its floor.

Everything runs in one process, on the same machine and the same random, already pre-processed inputs:

* policies: a NEW action chunk (`reset()` then `select_action`, under `torch.inference_mode` as lerobot-eval
  runs it) for B = 1 and B = 8 observations, and one training step (`forward`, `backward`, gradient-norm clip,
  optimizer `step`, each policy with its own optimizer preset);
* the energy head: the policy's refinement (`EBVLA.generate_actions` with the backbone's output cached, i.e.
  key/value projection + K_inf MCMC steps + the final-energy forward) against its FLOOR, one key/value
  projection plus K_inf forward+backward passes w.r.t. the actions only;
* with `--variants` (and `--compile`): inference variants that must not change the actions (frozen
  parameters, SDPA backends, the policy's `compile_mode` set to `--compile-mode`: with the backbone's output
  cached, it compiles the key/value projection and every MCMC step's energy), with their max deviation from
  the default path.

Policies (`--policies`), all with the image encoder of LeRobot's Diffusion Policy built from the same fields
(`vision_backbone`, image size, `crop_shape`, `spatial_softmax_num_keypoints`, group norm, no pretrained
weights, one encoder per camera) and the same chunk length H:

    ebvla-light    EB-VLA, D = 256, L = 4, 8 heads, K_inf = 15 (the light CPU head)
    ebvla-paper    EB-VLA, the paper's head: D = 896, L = 4, 8 heads, K_inf = 15
    diffusion      LeRobot `diffusion` at its defaults: U-Net down_dims (512, 1024, 2048), 100 DDPM steps
    diffusion-cpu  a CPU-sized `diffusion`: down_dims (128, 256, 512), 10 DDIM steps

Chunk length: EB-VLA refines `chunk_size` = H actions; Diffusion Policy denoises `horizon` actions and needs
horizon % 2**len(down_dims) == 0. With `n_obs_steps` = 1 (EB-VLA sees one observation, so Diffusion Policy is
given one too) and horizon = n_action_steps = H, both produce and execute the same H actions per chunk. H = 8 (the
paper's) is a multiple of 2**3 = 8, so no padding is needed; another H must be a multiple of 8 for both U-Nets.

Peak memory is the rise over the level just before the FIRST call of that cell: on CUDA
`torch.cuda.max_memory_allocated`; on CPU the process's resident-set high-water mark (VmHWM, reset through
/proc/self/clear_refs), since tracemalloc does not see torch's allocations. CPU numbers count every page the
call touched (allocator included); glibc's free heap pages are returned to the OS (malloc_trim) before the
call, so that earlier cells' freed memory does not hide its allocations.

Run (a quiet machine; `--threads 1` on a shared one, where oversubscribed threads distort everything):

    python research/benchmarks/bench_speed.py --variants --compile --json research/results/bench_speed_cpu.json

It takes about half an hour on a 2-core CPU, most of it in the default Diffusion's 100-step chunks
(`--policies` picks fewer rows).

`--quick` is a smoke test (tiny head, CPU-sized diffusion only, 2 repeats).

The pieces live in `research/benchmarks/speed/`: `inputs` (scene and policies), `memory` (peak memory), `timing` (the
cells' timing), `cells` (what is timed) and `report` (the tables).
"""

import argparse
import json
import os
import sys
from pathlib import Path

import torch
from speed.cells import head_cells, policy_cells
from speed.inputs import (
    DIFFUSION_VARIANTS,
    EBVLA_HEADS,
    VLM_CONTEXT_TOKENS,
    Scene,
    make_diffusion,
    make_ebvla,
)
from speed.report import machine_info, markdown_report, summarize
from speed.timing import measure

from lerobot_policy_ebvla.configuration_ebvla import COMPILE_MODES


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--policies",
        nargs="+",
        default=["ebvla-light", "ebvla-paper", "diffusion", "diffusion-cpu"],
        choices=[*EBVLA_HEADS, *DIFFUSION_VARIANTS],
    )
    parser.add_argument("--device", default="cpu", help="cpu or cuda")
    parser.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's)")
    parser.add_argument(
        "--batch-sizes", type=int, nargs="+", default=[1, 8], help="observations per new chunk"
    )
    parser.add_argument("--train-batch-size", type=int, default=8)
    parser.add_argument("--chunk", type=int, default=8, help="H: ebvla chunk_size = diffusion horizon")
    parser.add_argument(
        "--warmup", type=int, default=2, help="untimed calls per cell, the memory probe included"
    )
    parser.add_argument("--repeats", type=int, default=7, help="timed calls per cell (at most)")
    parser.add_argument("--min-repeats", type=int, default=3)
    parser.add_argument(
        "--cell-budget-s",
        type=float,
        default=120.0,
        help="stop timing a cell once it has --min-repeats calls and this many seconds",
    )
    parser.add_argument(
        "--vlm-context-tokens",
        type=int,
        default=VLM_CONTEXT_TOKENS,
        help="also time the paper head on contexts this long, as the VLM gives (0: skip)",
    )
    parser.add_argument("--no-head", action="store_true", help="skip the head-vs-floor cells")
    parser.add_argument("--no-policies", action="store_true", help="only the head cells")
    parser.add_argument(
        "--variants", action="store_true", help="time inference variants (frozen params, SDPA)"
    )
    parser.add_argument(
        "--compile",
        action="store_true",
        help="with --variants: add the policy's compile_mode (torch.compile, slow to build)",
    )
    parser.add_argument(
        "--compile-mode",
        default="default",
        choices=[mode for mode in COMPILE_MODES if mode != "off"],
        help="with --compile: the policy's `compile_mode`",
    )
    parser.add_argument(
        "--quick", action="store_true", help="smoke test: tiny head, diffusion-cpu, 2 repeats"
    )
    parser.add_argument("--json", type=Path, default=Path("research/results/bench_speed.json"))
    parser.add_argument("--markdown", type=Path, default=None, help="also write the tables here")
    args = parser.parse_args(argv)
    if args.quick:
        args.policies, args.batch_sizes, args.train_batch_size = ["ebvla-tiny", "diffusion-cpu"], [1, 2], 2
        args.warmup, args.repeats, args.min_repeats, args.vlm_context_tokens = 1, 2, 1, 0
    if args.warmup < 1:
        parser.error("--warmup must be >= 1 (the first call is the memory probe)")
    return args


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(argv)
    device = torch.device(args.device)
    # One compiled graph per (head, batch size, context length): more than dynamo's default of 8.
    torch._dynamo.config.recompile_limit = 64
    if args.threads:
        torch.set_num_threads(args.threads)
    scene = Scene(chunk=args.chunk)
    info = machine_info(device)
    print(json.dumps(info, indent=1), flush=True)

    policies, cells = {}, []
    for name in args.policies:
        torch.manual_seed(0)
        if name in EBVLA_HEADS:
            policy = make_ebvla(scene, EBVLA_HEADS[name], args.device)
            h = EBVLA_HEADS[name]
            label = (
                f"D={h['dim_model']}, L={h['n_blocks']}, {h['n_heads']} heads, "
                f"K_inf={policy.config.inference_mcmc_steps}"
            )
        else:
            policy = make_diffusion(scene, DIFFUSION_VARIANTS[name], args.device)
            c = policy.config
            steps = c.num_inference_steps or c.num_train_timesteps
            label = f"down_dims={tuple(c.down_dims)}, {steps} {c.noise_scheduler_type} steps"
        policies[name] = {"label": label, "params_m": sum(p.numel() for p in policy.parameters()) / 1e6}
        if not args.no_policies:
            cells += policy_cells(name, policy, scene, args, device)
        if name in EBVLA_HEADS and not args.no_head:
            cells += head_cells(name, policy, scene, args, device)
    if args.no_policies:
        policies = {k: v for k, v in policies.items() if k in EBVLA_HEADS}

    measure(cells, device, args)
    info["load_average_end"] = os.getloadavg()
    results = {
        "command": "python research/benchmarks/bench_speed.py "
        + " ".join(argv if argv is not None else sys.argv[1:]),
        "machine": info,
        "settings": {
            **{k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
            "scene": vars(scene),
        },
        "policies": policies,
        "cells": [
            {
                "name": c.name,
                "group": c.group,
                **c.meta,
                "median_ms": c.median_ms,
                "times_ms": [1e3 * t for t in c.times],
                "peak_mib": c.peak_mib,
                "first_call_s": c.first_call_s,
                **c.check,
            }
            for c in cells
        ],
    }
    results.update(summarize(cells, {} if args.no_policies else policies, args))
    report = markdown_report(results)
    print(report)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(results, indent=1))
    if args.markdown:
        args.markdown.parent.mkdir(parents=True, exist_ok=True)
        args.markdown.write_text(report)
    return results


if __name__ == "__main__":
    main()
