"""The noisy copies' std for the success energy E_s, looked at on K's five read sets (issue 52, Table IV;
research/docs/libero_runs.md, "Narrower noisy copies, and a sixth set", where the choice and the sixth test are
fixed).

Every one of K's five sets of 400 held-out rollouts has been read by E_s at the package's noise (std 1.0 in
standardized units), so this is development: E_s fitted on all successful calibration rollouts at each noise and seed,
each set's rollouts read over their first 16 chunks three ways (the package's `late`, the mean of chunks 12-15; the
last chunk, 15, where `chunk_context_nn` reads; the maximum of chunks 12-15), and the AUROC minus the feature distance
`chunk_context_nn`'s on the same rollouts with its paired bootstrap interval, per set and over all 2000. AUROC needs
no threshold, so the calibration rollouts are read with that E_s too (nothing here is a balanced accuracy). The fitted
E_s are saved beside the report (.safetensors) and read from there when it exists.

    python research/benchmarks/success_energy_noise_choice.py --noises 1.0 0.5 --seeds 0 1 2 \\
        --output=research/results/libero_object10_b18/reports/ebvla_joint_fast_cpu_b18/success_energy/noise_choice.json
"""

import argparse
from pathlib import Path

import numpy as np
import torch
from failure_check_test import BASELINE, scores_at, write_report
from failure_score_variants import rows_against_baseline
from phase_energy_failure_check import first_chunks
from safetensors.torch import load_file, save_file
from success_energy_failure_check import (
    CALIBRATION,
    CHUNKS,
    K_EVAL,
    K_NEW,
    contexts,
    load,
    success_series,
)

from lerobot_policy_ebvla.runtime.chunk_scores import LATE_CHUNKS, rollout_score
from lerobot_policy_ebvla.runtime.success_energy import SuccessEnergy, fit_success_energy

FIVE_READ_SETS = {
    "first": (K_EVAL / "vanilla_heldout", K_EVAL / "vanilla_confirm"),
    "second": (K_NEW / "vanilla_heldout_new", K_NEW / "vanilla_confirm_new"),
    "third": (K_NEW / "vanilla_heldout_third", K_NEW / "vanilla_confirm_third"),
    "fourth": (K_NEW / "vanilla_heldout_fourth", K_NEW / "vanilla_confirm_fourth"),
    "fifth": (K_NEW / "vanilla_heldout_fifth", K_NEW / "vanilla_confirm_fifth"),
}
READINGS = {
    "late": lambda values: rollout_score(values, "late"),
    "last": lambda values: rollout_score(values, "last"),
    "max of the last 4": lambda values: float(np.max(values[-LATE_CHUNKS:])),
}


def windows(model, episodes: dict) -> list[np.ndarray]:
    """Each episode's E_s over its first `CHUNKS` chunks."""
    return [first_chunks(success_series(model, e), CHUNKS)[0] for e in episodes.values()]


def difference(values, baseline, successful, failed) -> dict:
    row = rows_against_baseline({"E_s": values, BASELINE: baseline}, successful, failed)[0]
    return {
        "auroc": row["auroc"],
        "difference": row["auroc_minus_baseline"],
        "interval": row["auroc_minus_baseline_interval"],
    }


def weights_key(noise: float, seed: int) -> str:
    return f"noise{noise:g}_seed{seed}"


def look(noises: list[float], seeds: list[int], threads: int = 1, weights: Path | None = None) -> dict:
    """Every noise, seed and reading over the five read sets. With `weights`: E_s read from that file where it holds
    them (a committed look recomputes without refitting, whose last digits differ between CPUs), else fitted and
    saved there."""
    torch.set_num_threads(threads)
    saved = load_file(weights) if weights is not None and weights.exists() else {}
    fitted = {}
    calibration = load([CALIBRATION])
    sets = {name: load(paths) for name, paths in FIVE_READ_SETS.items()}
    successful = np.array([e[0].success for e in calibration.values()])
    failed = {name: np.array([not e[0].success for e in held.values()]) for name, held in sets.items()}
    baseline = {name: scores_at(BASELINE, calibration, held, CHUNKS) for name, held in sets.items()}
    # The calibration rollouts' distances are each against the others, the same whichever set is read.
    pooled_baseline = (baseline["first"][0], np.concatenate([baseline[name][1] for name in sets]))
    pooled_failed = np.concatenate([failed[name] for name in sets])
    training = [contexts(e) for e in calibration.values() if e[0].success]
    rows = []
    for noise in noises:
        for seed in seeds:
            key = weights_key(noise, seed)
            state = {k.removeprefix(f"{key}."): v for k, v in saved.items() if k.startswith(f"{key}.")}
            model = (
                SuccessEnergy.from_state(state) if state else fit_success_energy(training, seed, noise=noise)
            )
            fitted.update({f"{key}.{k}": v.contiguous() for k, v in model.state_dict().items()})
            cal_windows = windows(model, calibration)
            held_windows = {name: windows(model, episodes) for name, episodes in sets.items()}
            for reading, how in READINGS.items():
                cal = np.array([how(w) for w in cal_windows])
                held = {name: np.array([how(w) for w in found]) for name, found in held_windows.items()}
                entry = {"noise": noise, "seed": seed, "reading": reading, "sets": {}}
                for name in sets:
                    entry["sets"][name] = difference(
                        (cal, held[name]), baseline[name], successful, failed[name]
                    )
                entry["pooled"] = difference(
                    (cal, np.concatenate(list(held.values()))), pooled_baseline, successful, pooled_failed
                )
                rows.append(entry)
                print(noise, seed, reading, f"{entry['pooled']['difference']:+.4f}", flush=True)
    if weights is not None and not saved:
        save_file(fitted, weights)
    return {"chunks": CHUNKS, "sets": list(sets), "rows": rows}


def markdown(result: dict) -> str:
    lines = [
        f"E_s on K's five read sets, first {result['chunks']} chunks: AUROC minus `{BASELINE}`'s on the same rollouts "
        "[paired bootstrap 95 % CI], per set and over all 2000.",
        "",
        "| noise | seed | reading | " + " | ".join(result["sets"]) + " | all 2000 |",
        "|---:|---:|---|" + "---|" * (len(result["sets"]) + 1),
    ]
    for r in result["rows"]:
        cells = [
            f"{c['difference']:+.4f} [{c['interval'][0]:+.4f}, {c['interval'][1]:+.4f}]"
            for c in [*r["sets"].values(), r["pooled"]]
        ]
        lines.append(f"| {r['noise']:g} | {r['seed']} | {r['reading']} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--noises", type=float, nargs="+", default=[1.0, 0.5])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--output", type=Path, default=None)
    args = parser.parse_args(argv)
    weights = None if args.output is None else args.output.with_suffix(".safetensors")
    result = look(args.noises, args.seeds, args.threads, weights)
    write_report(result, markdown(result), args.output)


if __name__ == "__main__":
    main()
