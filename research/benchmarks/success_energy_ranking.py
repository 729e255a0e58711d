"""Which rollouts the success energy ranks wrongly (issue 52, Table IV; research/docs/libero_runs.md, "E_s in the
package, and a fifth set"): every held-out rollout's E_s (the chosen reading, with the E_s a test saved) beside the
feature distance `chunk_context_nn`, its success, its length in chunks and its task, highest E_s first, and the
successful rollouts' scores by length. Descriptive: it chooses nothing.

    python research/benchmarks/success_energy_ranking.py \\
        --fitted=research/results/libero_object10_b18/reports/ebvla_joint_fast_cpu_b18/success_energy/fourth_rollouts.safetensors \\
        --held_out <eval>/vanilla_heldout_fourth <eval>/vanilla_confirm_fourth --output=<...>/fourth_ranking.json
"""

import argparse
from pathlib import Path

import numpy as np
import torch
from failure_check_test import BASELINE, scores_at, write_report
from success_energy_failure_check import CALIBRATION, CHUNKS, load, load_fitted, scores

# Successful rollouts by how many chunks they took: the window ends at chunk 16, the step cap at 35.
LENGTHS = ((0, 20), (20, 25), (25, 30), (30, 36))


def ranking(fitted_path: Path, held_out_paths: list[str], calibration_path: Path = CALIBRATION) -> dict:
    calibration = load([calibration_path])
    fitted = load_fitted(fitted_path, calibration)
    held = load(held_out_paths)
    _, energy = scores(fitted, calibration, held, "late")
    _, distance = scores_at(BASELINE, calibration, held, CHUNKS)
    rows = [
        {
            "rollout": f"{Path(key[0]).parent.parent.name}/{Path(key[0]).parent.name}/{key[1].episode_index}",
            "task": episode[0].task,
            "succeeded": bool(episode[0].success),
            "chunks": len(episode),
            "success_energy": float(e),
            BASELINE: float(d),
        }
        for (key, episode), e, d in zip(held.items(), energy, distance, strict=True)
    ]
    rows.sort(key=lambda r: -r["success_energy"])
    successful = [r for r in rows if r["succeeded"]]
    by_length = []
    for low, high in LENGTHS:
        kept = [r for r in successful if low <= r["chunks"] < high]
        by_length.append(
            {
                "chunks": [low, high - 1],
                "rollouts": len(kept),
                "success_energy_mean": float(np.mean([r["success_energy"] for r in kept])) if kept else None,
                f"{BASELINE}_mean": float(np.mean([r[BASELINE] for r in kept])) if kept else None,
            }
        )
    lengths = np.array([r["chunks"] for r in successful])
    return {
        "rows": rows,
        "successful_by_length": by_length,
        "correlation_with_length": {
            name: float(np.corrcoef([r[name] for r in successful], lengths)[0, 1])
            for name in ("success_energy", BASELINE)
        },
    }


def markdown(result: dict, top: int = 45) -> str:
    lines = [
        f"Held-out rollouts by E_s (mean of chunks 12-15), highest first (the first {top}), beside `{BASELINE}`:",
        "",
        f"| E_s | `{BASELINE}` | succeeded | chunks | task |",
        "|---:|---:|---|---:|---|",
    ]
    for r in result["rows"][:top]:
        lines.append(
            f"| {r['success_energy']:.2f} | {r[BASELINE]:.2f} | {r['succeeded']} | {r['chunks']} | {r['task']} |"
        )
    lines += [
        "",
        "Successful rollouts by length:",
        "",
        "| chunks | rollouts | E_s mean | distance mean |",
        "|---|---:|---:|---:|",
    ]
    for b in result["successful_by_length"]:
        values = [b["success_energy_mean"], b[f"{BASELINE}_mean"]]
        cells = " | ".join("-" if v is None else f"{v:.2f}" for v in values)
        lines.append(f"| {b['chunks'][0]}-{b['chunks'][1]} | {b['rollouts']} | {cells} |")
    correlation = result["correlation_with_length"]
    lines += [
        "",
        "Correlation with the length over the successful rollouts: "
        + ", ".join(f"{name} {value:.2f}" for name, value in correlation.items()),
        "",
    ]
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--fitted", type=Path, required=True)
    parser.add_argument("--held_out", nargs="+", required=True)
    parser.add_argument("--calibration", type=Path, default=CALIBRATION)
    parser.add_argument("--output", type=Path, default=None)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    result = ranking(args.fitted, args.held_out, args.calibration)
    write_report(result, markdown(result), args.output)


if __name__ == "__main__":
    main()
