"""What `bench_speed.py` reports: the machine, ratios and head-vs-floor rows, and the markdown tables."""

import contextlib
import datetime
import math
import os
import platform

import torch

from .timing import Cell


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
