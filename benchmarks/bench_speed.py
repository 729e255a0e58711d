"""Speed of EB-VLA (light backbone) against LeRobot's Diffusion Policy, and of the energy head against its floor.

Everything runs in one process, on the same machine and the same random, already pre-processed inputs:

* policies: a NEW action chunk (`reset()` then `select_action`, under `torch.inference_mode` as lerobot-eval
  runs it) for B = 1 and B = 8 observations, and one training step (`forward`, `backward`, gradient-norm clip,
  optimizer `step`, each policy with its own optimizer preset);
* the energy head: the policy's refinement (`EBVLA.generate_actions` with the backbone's output cached, i.e.
  key/value projection + K_inf MCMC steps + the final-energy forward) against its FLOOR, one key/value
  projection plus K_inf forward+backward passes w.r.t. the actions only;
* with `--variants` (and `--compile`): inference variants that must not change the actions (frozen
  parameters, SDPA backends, torch.compile), with their max deviation from the default path.

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

    python benchmarks/bench_speed.py --variants --compile --json benchmarks/results/bench_speed_cpu.json

It takes about half an hour on a 2-core CPU, most of it in the default Diffusion's 100-step chunks
(`--policies` picks fewer rows).

`--quick` is a smoke test (tiny head, CPU-sized diffusion only, 2 repeats).
"""

import argparse
import contextlib
import ctypes
import datetime
import gc
import json
import math
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.utils.constants import ACTION, OBS_STATE
from torch import Tensor, nn
from torch.nn.attention import SDPBackend, sdpa_kernel

from lerobot_policy_ebvla import EBVLAConfig, EBVLAPolicy

MIB = 1024**2
# Context tokens per head block of the paper's VLM: K_a latents + the state token + K_t = 2 x 256 vision tokens.
VLM_CONTEXT_TOKENS = 64 + 1 + 512

EBVLA_HEADS = {
    "ebvla-light": {"dim_model": 256, "n_heads": 8, "n_blocks": 4},
    "ebvla-paper": {"dim_model": 896, "n_heads": 8, "n_blocks": 4},
    "ebvla-tiny": {"dim_model": 32, "n_heads": 2, "n_blocks": 2},  # --quick only
}
DIFFUSION_VARIANTS = {
    "diffusion": {},  # LeRobot's defaults: down_dims (512, 1024, 2048), DDPM, 100 inference steps.
    "diffusion-cpu": {
        "down_dims": (128, 256, 512),
        "noise_scheduler_type": "DDIM",
        "num_inference_steps": 10,
    },
}


@dataclass
class Scene:
    """The inputs both policies see (RoboMimic-like: two 84 px cameras cropped to 76, 9-d state, 7-d action)."""

    cameras: int = 2
    image_size: int = 84
    crop: int = 76
    state_dim: int = 9
    action_dim: int = 7
    chunk: int = 8
    keypoints: int = 32

    def input_features(self) -> dict[str, PolicyFeature]:
        features = {
            f"observation.images.cam{i}": PolicyFeature(
                FeatureType.VISUAL, (3, self.image_size, self.image_size)
            )
            for i in range(self.cameras)
        }
        features[OBS_STATE] = PolicyFeature(FeatureType.STATE, (self.state_dim,))
        return features

    def encoder_fields(self) -> dict:
        """The image-encoder fields, spelled the same in `EBVLAConfig` and `DiffusionConfig`."""
        return {
            "vision_backbone": "resnet18",
            "pretrained_backbone_weights": None,
            "use_group_norm": True,
            "crop_shape": (self.crop, self.crop),
            "crop_is_random": True,
            "spatial_softmax_num_keypoints": self.keypoints,
            "use_separate_rgb_encoder_per_camera": True,
        }

    def observation(self, batch_size: int, device: torch.device, seed: int = 0) -> dict[str, Tensor]:
        g = torch.Generator().manual_seed(seed)
        batch = {
            key: torch.rand(batch_size, *ft.shape, generator=g)
            for key, ft in self.input_features().items()
            if ft.type is FeatureType.VISUAL
        }
        batch[OBS_STATE] = torch.randn(batch_size, self.state_dim, generator=g)
        return {k: v.to(device) for k, v in batch.items()}

    def training_batch(self, batch_size: int, device: torch.device, seed: int = 1) -> dict[str, Tensor]:
        batch = self.observation(batch_size, device, seed)
        g = torch.Generator().manual_seed(seed + 1)
        batch[ACTION] = torch.randn(batch_size, self.chunk, self.action_dim, generator=g).to(device)
        batch["action_is_pad"] = torch.zeros(batch_size, self.chunk, dtype=torch.bool, device=device)
        return batch


def make_ebvla(scene: Scene, head: dict, device: str) -> EBVLAPolicy:
    config = EBVLAConfig(
        backbone="resnet",
        device=device,
        input_features=scene.input_features(),
        output_features={ACTION: PolicyFeature(FeatureType.ACTION, (scene.action_dim,))},
        chunk_size=scene.chunk,
        n_action_steps=scene.chunk,
        **scene.encoder_fields(),
        **head,
    )
    return EBVLAPolicy(config).to(device)


def make_diffusion(scene: Scene, overrides: dict, device: str) -> nn.Module:
    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy

    config = DiffusionConfig(
        device=device,
        input_features=scene.input_features(),
        output_features={ACTION: PolicyFeature(FeatureType.ACTION, (scene.action_dim,))},
        n_obs_steps=1,
        horizon=scene.chunk,
        n_action_steps=scene.chunk,
        drop_n_last_frames=0,
        **scene.encoder_fields(),
        **overrides,
    )
    return DiffusionPolicy(config).to(device)


# --------------------------------------------------------------------------------------------- measurement


def synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _proc_status_kib(field_name: str) -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field_name + ":"):
                return int(line.split()[1])
    raise KeyError(field_name)


def _release_free_heap() -> None:
    """Returns glibc's free heap pages to the OS (malloc_trim); a no-op elsewhere."""
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6").malloc_trim(0)


def peak_memory_mib(fn: Callable[[], object], device: torch.device) -> float | None:
    """Runs `fn` once; returns its peak memory above the level before it (see the module docstring)."""
    if device.type == "cuda":
        synchronize(device)
        torch.cuda.reset_peak_memory_stats(device)
        base = torch.cuda.memory_allocated(device)
        fn()
        synchronize(device)
        return (torch.cuda.max_memory_allocated(device) - base) / MIB
    gc.collect()
    _release_free_heap()  # so that the call's allocations need new pages instead of reusing freed ones
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")  # resets VmHWM to the current VmRSS (Linux >= 4.0)
        base = _proc_status_kib("VmRSS")
    except OSError:
        fn()
        return None
    fn()
    return (_proc_status_kib("VmHWM") - base) / 1024


@dataclass
class Cell:
    """One thing to time. `fn` runs one call; `setup` (untimed) runs before each call."""

    name: str
    fn: Callable[[], object]
    setup: Callable[[], object] | None = None
    group: str = ""
    meta: dict = field(default_factory=dict)
    times: list[float] = field(default_factory=list)
    peak_mib: float | None = None
    first_call_s: float | None = None
    reference: Callable[[], object] | None = None
    check: dict = field(default_factory=dict)

    def run(self, device: torch.device) -> float:
        if self.setup is not None:
            self.setup()
        synchronize(device)
        start = time.perf_counter()
        self.fn()
        synchronize(device)
        return time.perf_counter() - start

    @property
    def median_ms(self) -> float:
        return 1e3 * statistics.median(self.times) if self.times else math.nan


def measure(cells: list[Cell], device: torch.device, args: argparse.Namespace) -> None:
    """Probes each cell once (first-call time and peak memory), warms it up, then times interleaved rounds.

    Rounds visit every cell in turn so that a load change on a shared machine hits all cells alike. A cell
    stops after `--repeats` calls, or earlier once it has `--min-repeats` calls and `--cell-budget-s` seconds.
    """
    for cell in cells:
        start = time.perf_counter()
        if cell.setup is not None:
            cell.setup()
        cell.peak_mib = peak_memory_mib(cell.fn, device)
        cell.first_call_s = time.perf_counter() - start
        for _ in range(args.warmup - 1):
            cell.run(device)
        print(f"  probed {cell.name}: first call {cell.first_call_s:.2f} s", flush=True)
    for _ in range(args.repeats):
        for cell in cells:
            spent = sum(cell.times)
            if len(cell.times) >= args.min_repeats and spent >= args.cell_budget_s:
                continue
            cell.times.append(cell.run(device))
    for cell in cells:
        print(f"  {cell.name}: median {cell.median_ms:.1f} ms over {len(cell.times)}", flush=True)
        if cell.reference is not None:
            if cell.setup is not None:
                cell.setup()
            cell.check = compare_outputs(cell.reference, cell.fn, device)


# ---------------------------------------------------------------------------------------- policy cells


def policy_cells(name: str, policy: nn.Module, scene: Scene, args, device: torch.device) -> list[Cell]:
    """New-chunk cells for each batch size and one training-step cell."""
    cells = []
    for b in args.batch_sizes:
        obs = scene.observation(b, device)

        def new_chunk(obs=obs):
            with torch.inference_mode():
                return policy.select_action(dict(obs))

        cells.append(
            Cell(
                f"{name}/chunk_b{b}",
                new_chunk,
                setup=lambda: (policy.eval(), policy.reset()),
                group="chunk",
                meta={"policy": name, "batch": b},
            )
        )
    batch = scene.training_batch(args.train_batch_size, device)
    if name.startswith("diffusion"):
        batch[OBS_STATE] = batch[OBS_STATE].unsqueeze(1)  # (B, n_obs_steps = 1, state_dim)
    optimizer = policy.config.get_optimizer_preset().build(list(policy.get_optim_params()))
    clip = policy.config.get_optimizer_preset().grad_clip_norm
    seeds = iter(range(10**6))

    def setup_train():
        policy.train()
        # Diffusion's noise and timesteps come from the global RNG (EB-VLA's K ~ U[K_min, K_max] from its own
        # generator, seeded at construction): seeding each step keeps re-runs comparable.
        torch.manual_seed(next(seeds))

    def train_step():
        optimizer.zero_grad(set_to_none=True)
        loss, _ = policy.forward(dict(batch))
        loss.backward()
        torch.nn.utils.clip_grad_norm_(policy.parameters(), clip)
        optimizer.step()

    cells.append(
        Cell(
            f"{name}/train_b{args.train_batch_size}",
            train_step,
            setup=setup_train,
            group="train",
            meta={"policy": name, "batch": args.train_batch_size},
        )
    )
    return cells


# ------------------------------------------------------------------------------------------ head cells


class CachedContext(nn.Module):
    """Stands in for the backbone: returns fixed per-block contexts, so only the head's work is timed."""

    def __init__(self, contexts: list[Tensor]):
        super().__init__()
        self.contexts = contexts

    def forward(self, batch: dict[str, Tensor]) -> list[Tensor]:
        return self.contexts


@contextlib.contextmanager
def swapped(module: nn.Module, name: str, replacement: nn.Module):
    original = getattr(module, name)
    setattr(module, name, replacement)
    try:
        yield
    finally:
        setattr(module, name, original)


@contextlib.contextmanager
def frozen_parameters(module: nn.Module):
    """requires_grad_(False) on every parameter for the duration, then restores each flag."""
    flags = [(p, p.requires_grad) for p in module.parameters()]
    for p, _ in flags:
        p.requires_grad_(False)
    try:
        yield
    finally:
        for p, flag in flags:
            p.requires_grad_(flag)


class DetachedParamsHead(nn.Module):
    """The energy head evaluated with detached parameters (optionally torch.compile'd).

    Autograd then records only the path from the actions, and a compiled graph's backward computes only
    grad_a: with parameters that require grad, AOTAutograd's backward also computes every weight gradient.
    """

    def __init__(self, head: nn.Module, compile_mode: str | None = None):
        super().__init__()
        self.head = head
        call = lambda params, actions, kv: torch.func.functional_call(head, params, (actions, kv))  # noqa: E731
        self.call = torch.compile(call, mode=compile_mode, dynamic=False) if compile_mode else call

    def context_kv(self, contexts):
        return self.head.context_kv(contexts)

    def forward(self, actions: Tensor, kv) -> Tensor:
        if not torch.is_grad_enabled():
            return self.head(actions, kv)  # the final-energy forward: nothing to differentiate, stay eager
        params = {k: v.detach() for k, v in self.head.named_parameters()}
        params.update(self.head.named_buffers())
        return self.call(params, actions, kv)


def head_contexts(policy: EBVLAPolicy, scene: Scene, b: int, tokens: int | None, device) -> list[Tensor]:
    """The backbone's real output (tokens None) or random VLM-sized contexts of `tokens` tokens per block."""
    if tokens is None:
        with torch.no_grad():
            return [c.detach() for c in policy.model.backbone(scene.observation(b, device))]
    g = torch.Generator().manual_seed(b)
    dim = policy.model.head.blocks[0].cross_attn.kv.in_features
    return [torch.randn(b, tokens, dim, generator=g).to(device) for _ in policy.model.head.blocks]


def floor_fn(head: nn.Module, contexts: list[Tensor], chunk: int, action_dim: int, steps: int, alpha: float):
    """The minimum the refinement math needs: kv once, then K x (forward, grad w.r.t. the actions, update)."""
    b, device = contexts[0].shape[0], contexts[0].device

    def run():
        with torch.no_grad():
            kv = head.context_kv(contexts)
        a = torch.randn(b, chunk, action_dim, device=device)
        for _ in range(steps):
            a = a.detach().requires_grad_(True)
            (grad,) = torch.autograd.grad(head(a, kv).mean(dim=-1).sum(), a)
            a = a - alpha * grad
        return a.detach()

    return run


def head_cells(name: str, policy: EBVLAPolicy, scene: Scene, args, device) -> list[Cell]:
    """Floor and actual refinement per (context size, batch), plus the `--variants` cells.

    A variant cell carries the default refinement as its `reference`: after timing, both run once from the
    same seed and the largest differences of their actions and energies are recorded.
    """
    model, cfg = policy.model, policy.config
    policy.eval()
    token_options = [None] + (
        [args.vlm_context_tokens] if name == "ebvla-paper" and args.vlm_context_tokens else []
    )
    compiled = DetachedParamsHead(model.head, compile_mode=args.compile_mode) if args.compile else None
    fused = SDPBackend.FLASH_ATTENTION if device.type == "cpu" else SDPBackend.EFFICIENT_ATTENTION
    wrappers: dict[str, Callable[[], contextlib.AbstractContextManager]] = {
        "frozen_params": lambda: frozen_parameters(model.head),
        "detached_params": lambda: swapped(model, "head", DetachedParamsHead(model.head)),
        "sdpa_math": lambda: sdpa_kernel(SDPBackend.MATH),
        f"sdpa_{fused.name.lower()}": lambda: sdpa_kernel(fused),
    }
    if compiled is not None:
        wrappers["compiled_detached"] = lambda: swapped(model, "head", compiled)
    cells = []
    for tokens in token_options:
        for b in args.batch_sizes:
            contexts = head_contexts(policy, scene, b, tokens, device)
            stub, obs = CachedContext(contexts), scene.observation(b, device)
            meta = {"policy": name, "batch": b, "context_tokens": contexts[0].shape[1]}
            prefix = f"{name}/head_S{meta['context_tokens']}_b{b}"

            def refine(wrap=contextlib.nullcontext, stub=stub, obs=obs):
                with swapped(model, "backbone", stub), wrap():
                    return model.generate_actions(obs)

            floor = floor_fn(
                model.head,
                contexts,
                cfg.chunk_size,
                cfg.action_dim,
                cfg.inference_mcmc_steps,
                cfg.inference_step_size,
            )
            cells.append(
                Cell(
                    f"{prefix}/floor",
                    floor,
                    setup=policy.eval,
                    group="head",
                    meta={**meta, "variant": "floor"},
                )
            )
            cells.append(
                Cell(
                    f"{prefix}/actual",
                    refine,
                    setup=policy.eval,
                    group="head",
                    meta={**meta, "variant": "actual"},
                )
            )
            if not args.variants:
                continue
            with torch.no_grad():
                kv = model.head.context_kv(contexts)
            zeros = torch.zeros(b, cfg.chunk_size, cfg.action_dim, device=device)
            cells.append(
                Cell(
                    f"{prefix}/final_energy_forward_only",
                    lambda kv=kv, zeros=zeros: _no_grad_energy(model.head, zeros, kv),
                    setup=policy.eval,
                    group="head",
                    meta={**meta, "variant": "final_energy_forward_only"},
                )
            )
            for variant, wrap in wrappers.items():
                cells.append(
                    Cell(
                        f"{prefix}/{variant}",
                        lambda refine=refine, wrap=wrap: refine(wrap),
                        setup=policy.eval,
                        group="head",
                        meta={**meta, "variant": variant},
                        reference=refine,
                    )
                )
    return cells


def _no_grad_energy(head: nn.Module, actions: Tensor, kv) -> Tensor:
    with torch.no_grad():
        return head(actions, kv)


def compare_outputs(reference: Callable, variant: Callable, device: torch.device, seed: int = 0) -> dict:
    """Max |difference| of actions and energies between two refinements seeded alike."""

    def seeded(fn):
        torch.manual_seed(seed)  # the refinement draws a^(0) and the Langevin noise from the global RNG
        if device.type == "cuda":
            torch.cuda.manual_seed(seed)
        actions, readout = fn()
        return actions, readout

    (a0, r0), (a1, r1) = seeded(reference), seeded(variant)
    return {
        "max_abs_action_diff": (a0 - a1).abs().max().item(),
        "max_abs_final_energy_diff": (r0.final_energy - r1.final_energy).abs().max().item(),
        "max_abs_initial_energy_diff": (r0.initial_energy - r1.initial_energy).abs().max().item(),
    }


# --------------------------------------------------------------------------------------------- report


def machine_info(device: torch.device) -> dict:
    cpu = platform.processor() or "unknown"
    with contextlib.suppress(OSError), open("/proc/cpuinfo") as f:
        for line in f:
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    info = {
        "date": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
        "cpu": cpu,
        "logical_cores": os.cpu_count(),
        "usable_cores": len(os.sched_getaffinity(0)),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "device": str(device),
        "load_average_start": os.getloadavg(),
    }
    with contextlib.suppress(Exception):
        import lerobot

        info["lerobot"] = lerobot.__version__
    with contextlib.suppress(Exception):
        import diffusers

        info["diffusers"] = diffusers.__version__
    if device.type == "cuda":
        info["gpu"] = torch.cuda.get_device_name(device)
    return info


def _fmt(x: float | None, digits: int = 1) -> str:
    return "n/a" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:,.{digits}f}"


def markdown_report(results: dict) -> str:
    cells = {c["name"]: c for c in results["cells"]}
    settings, info = results["settings"], results["machine"]
    batch_sizes, train_b = settings["batch_sizes"], settings["train_batch_size"]
    lines = [
        f"Date {info['date']}; {info['cpu']}, {info['usable_cores']} usable cores, torch {info['torch']} "
        f"({info['torch_threads']} threads), device {info['device']}; load average "
        f"{', '.join(f'{x:.1f}' for x in info['load_average_start'])} at start, "
        f"{', '.join(f'{x:.1f}' for x in info['load_average_end'])} at end.",
        "",
        f"Command: `{results['command']}`",
        "",
        "### New chunk and training step (median ms; peak memory MiB above the pre-call level)",
        "",
        "| policy | params (M) | "
        + " | ".join(f"chunk B={b}" for b in batch_sizes)
        + f" | train step B={train_b} | "
        + " | ".join(f"peak chunk B={b}" for b in batch_sizes)
        + " | peak train |",
        "|---" * (3 + 2 * len(batch_sizes) + 1) + "|",
    ]
    for policy, meta in results["policies"].items():
        chunk = [cells.get(f"{policy}/chunk_b{b}") for b in batch_sizes]
        train = cells.get(f"{policy}/train_b{train_b}")
        lines.append(
            f"| {policy} ({meta['label']}) | {meta['params_m']:.1f} | "
            + " | ".join(_fmt(c and c["median_ms"]) for c in chunk)
            + f" | {_fmt(train and train['median_ms'])} | "
            + " | ".join(_fmt(c and c["peak_mib"], 0) for c in chunk)
            + f" | {_fmt(train and train['peak_mib'], 0)} |"
        )
    ratios = results["ratios"]
    if ratios:
        lines += [
            "",
            "### Ratios ebvla / diffusion (median time; < 1 means EB-VLA is faster)",
            "",
            "| ebvla | diffusion | " + " | ".join(f"chunk B={b}" for b in batch_sizes) + " | train |",
            "|---" * (3 + len(batch_sizes)) + "|",
        ]
        for r in ratios:
            lines.append(
                f"| {r['ebvla']} | {r['diffusion']} | "
                + " | ".join(_fmt(r[f"chunk_b{b}"], 3) for b in batch_sizes)
                + f" | {_fmt(r['train'], 3)} |"
            )
    head = results["head"]
    if head:
        lines += [
            "",
            "### Energy head: policy refinement vs its floor (median ms, backbone output cached)",
            "",
            "Floor: one key/value projection + K_inf x (head forward + grad w.r.t. the actions). Actual: "
            "`generate_actions` (key/value projection, K_inf MCMC steps of Eq. 2-3, final-energy forward).",
            "",
            "| head | context tokens | B | floor | actual | actual / floor | per env at B | final-energy forward |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for h in head:
            lines.append(
                f"| {h['policy']} | {h['context_tokens']} | {h['batch']} | {_fmt(h['floor_ms'])} | "
                f"{_fmt(h['actual_ms'])} | {_fmt(h['ratio'], 2)} | {_fmt(h['actual_ms'] / h['batch'])} | "
                f"{_fmt(h['final_energy_forward_ms'])} |"
            )
    variants = results["variants"]
    if variants:
        lines += [
            "",
            "### Inference variants (median ms; same seed, max |difference| from the default path)",
            "",
            "| head | context tokens | B | variant | median | speed-up vs actual | max abs d(action) | "
            "max abs d(final E) | first call s |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for v in variants:
            lines.append(
                f"| {v['policy']} | {v['context_tokens']} | {v['batch']} | {v['variant']} | {_fmt(v['median_ms'])} "
                f"| {_fmt(v['speedup'], 2)}x | {_fmt(v.get('max_abs_action_diff'), 8)} | "
                f"{_fmt(v.get('max_abs_final_energy_diff'), 8)} | {_fmt(v['first_call_s'], 2)} |"
            )
    return "\n".join(lines) + "\n"


def summarize(cells: list[Cell], policies: dict, args) -> dict:
    by_name = {c.name: c for c in cells}
    ratios = []
    for e in (p for p in policies if p.startswith("ebvla")):
        for d in (p for p in policies if p.startswith("diffusion")):
            row = {"ebvla": e, "diffusion": d}
            for b in args.batch_sizes:
                row[f"chunk_b{b}"] = (
                    by_name[f"{e}/chunk_b{b}"].median_ms / by_name[f"{d}/chunk_b{b}"].median_ms
                )
            tb = args.train_batch_size
            row["train"] = by_name[f"{e}/train_b{tb}"].median_ms / by_name[f"{d}/train_b{tb}"].median_ms
            ratios.append(row)
    head, variants = [], []
    for c in cells:
        if c.group != "head" or c.meta["variant"] != "actual":
            continue
        prefix = c.name.rsplit("/", 1)[0]
        floor = by_name[f"{prefix}/floor"]
        row = {k: c.meta[k] for k in ("policy", "batch", "context_tokens")}
        row.update(floor_ms=floor.median_ms, actual_ms=c.median_ms, ratio=c.median_ms / floor.median_ms)
        final = by_name.get(f"{prefix}/final_energy_forward_only")
        row["final_energy_forward_ms"] = final.median_ms if final else None
        head.append(row)
        for other in cells:
            if other.reference is not None and other.name.startswith(prefix + "/"):
                variants.append(
                    {
                        **other.meta,
                        "median_ms": other.median_ms,
                        "speedup": c.median_ms / other.median_ms,
                        "first_call_s": other.first_call_s,
                        **other.check,
                    }
                )
    return {"ratios": ratios, "head": head, "variants": variants}


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
        "--compile", action="store_true", help="with --variants: add torch.compile (slow to build)"
    )
    parser.add_argument("--compile-mode", default="default", help="torch.compile mode of --compile")
    parser.add_argument(
        "--quick", action="store_true", help="smoke test: tiny head, diffusion-cpu, 2 repeats"
    )
    parser.add_argument("--json", type=Path, default=Path("benchmarks/results/bench_speed.json"))
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
        "command": "python benchmarks/bench_speed.py " + " ".join(argv if argv is not None else sys.argv[1:]),
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
