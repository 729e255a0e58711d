"""Ways of reading the joint energy's two terms over a rollout's first N chunks, against the feature baseline
(issue 52, Table IV: the energy's failure check below `chunk_context_nn`).

Each variant aggregates the per-chunk components of `joint_phase_energy` (z_c,t of E_c and z_h,t of the head's part
E - E_c, each against the vanilla value at chunk index t, fitted on the checkpoint's calibration rollouts, each of
those scored against the fit without it) into one number per rollout; T = mu + k sigma of the successful calibration
rollouts, as the shipped check sets it. Beside them, `chunk_context_nn` (the pooled context at chunk N against the
successful calibration rollouts' at that chunk: no energy); each reading's AUROC also minus the baseline's on the
same rollouts, with a paired bootstrap interval (`metrics.bootstrap_auroc_difference_interval`): wholly below 0, the
reading is below the baseline beyond resampling noise. Every rollout of the held-out sets of each run (held-out
and confirmation fixed states, fresh placements) is judged together; failed rollouts are the positives.

Written on 2026-11-30 after the quick look of that morning (research/docs/libero_runs.md, "Left to do") to make its
figures reproducible. It chooses nothing: it reads the rollouts of D and E, on which `joint_phase_energy` was chosen
and tested, so no variant's figure here is held out.

    python research/benchmarks/failure_score_variants.py \\
        --run D=research/results/libero_object10_more/eval/ebvla_joint_fast_cpu_more \\
        --run E=research/results/libero_object10_arm/eval/ebvla_joint_fast_cpu_arm \\
        --output=research/results/libero_object10_arm/reports/failure_score_variants.json
"""

import argparse
from collections.abc import Callable
from pathlib import Path

import numpy as np
from failure_check_test import BASELINE, row, rows_table, write_report

from lerobot_policy_ebvla.monitoring.baselines import RegisteredScoreModel, chunk_context_nn
from lerobot_policy_ebvla.monitoring.metrics import auroc, bootstrap_auroc_difference_interval
from lerobot_policy_ebvla.monitoring.records import load_episodes
from lerobot_policy_ebvla.runtime.scores import SCORES

SCORE = "joint_phase_energy"
HELD_OUT = ("vanilla_heldout", "vanilla_confirm", "vanilla_fresh")
CHUNKS = 16
K = 1.0


def chunk_weighted(z: np.ndarray) -> float:
    """The two-term mean of each chunk, weighted by its 1-based index: later chunks count more."""
    weights = np.arange(1, len(z) + 1)
    return float((z.mean(axis=1) * weights).sum() / weights.sum())


# Each variant reads a rollout's (n, 2) components over its first n <= N chunks: columns z_c and z_h.
VARIANTS: dict[str, Callable[[np.ndarray], float]] = {
    "mean of both (shipped)": lambda z: float(z.mean()),
    "E_c term only": lambda z: float(z[:, 0].mean()),
    "head term only": lambda z: float(z[:, 1].mean()),
    "max over chunks": lambda z: float(z.mean(axis=1).max()),
    "mean of the later half": lambda z: float(z[len(z) // 2 :].mean()),
    "mean of the last 4": lambda z: float(z[-4:].mean()),
    "mean clipped at 0": lambda z: float(np.clip(z, 0, None).mean()),
    "chunk-weighted mean": chunk_weighted,
}


def components(calibration: list, held_out: list, n: int) -> tuple[list, list]:
    """Each rollout's (n, 2) components: a calibration rollout's from the fit without it, a held-out one's from the fit
    on all calibration rollouts."""
    model = RegisteredScoreModel(SCORES[SCORE], dict(enumerate(calibration)), "mean", knn_k=1)
    cal = [model.components(episode, key)[1][:n] for key, episode in enumerate(calibration)]
    return cal, [model.components(episode)[1][:n] for episode in held_out]


def run_rows(calibration: dict, held_out: dict, n: int = CHUNKS, k: float = K) -> dict:
    """Every variant's and the baseline's row on the held-out rollouts, at T of the successful calibration ones."""
    cal_episodes, held_episodes = list(calibration.values()), list(held_out.values())
    successful = np.array([episode[0].success for episode in cal_episodes])
    failed = np.array([not episode[0].success for episode in held_episodes])
    cal, held = components(cal_episodes, held_episodes, n)
    values = {
        name: (np.array([read(z) for z in cal]), np.array([read(z) for z in held]))
        for name, read in VARIANTS.items()
    }
    values[BASELINE] = (
        chunk_context_nn(calibration, calibration, n - 1),
        chunk_context_nn(calibration, held_out, n - 1),
    )
    return {
        "rollouts": int(failed.size),
        "failed": int(failed.sum()),
        "rows": rows_against_baseline(values, successful, failed, k),
    }


def rows_against_baseline(
    values: dict, successful: np.ndarray, failed: np.ndarray, k: float = K
) -> list[dict]:
    """Each score's row (`row`) at T = mu + k sigma of the successful calibration rollouts, from {name: (calibration
    values, held-out values)} that holds `BASELINE`; every other score's also with its AUROC minus the baseline's on
    the same held-out rollouts and that difference's paired bootstrap interval."""
    rows = []
    baseline = values[BASELINE][1]
    baseline_negatives, baseline_positives = baseline[~failed], baseline[failed]
    baseline_auroc = auroc(baseline_negatives, baseline_positives)
    for name, (cal_values, held_values) in values.items():
        reference = cal_values[successful]
        rows.append(row(name, held_values, float(reference.mean() + k * reference.std()), failed))
        if name != BASELINE:
            rows[-1]["auroc_minus_baseline"] = rows[-1]["auroc"] - baseline_auroc
            rows[-1]["auroc_minus_baseline_interval"] = list(
                bootstrap_auroc_difference_interval(
                    held_values[~failed], held_values[failed], baseline_negatives, baseline_positives
                )
            )
    return rows


def difference_lines(rows: list[dict], name=str) -> list[str]:
    """Each row's AUROC minus the baseline's with its paired interval (`rows_against_baseline`), as report lines."""
    return ["", f"AUROC minus `{BASELINE}`'s on the same rollouts [paired bootstrap 95 % CI]:"] + [
        f"- {name(r['score'])}: {r['auroc_minus_baseline']:+.3f} [{low:+.3f}, {high:+.3f}]"
        for r in rows
        if "auroc_minus_baseline" in r
        for low, high in [r["auroc_minus_baseline_interval"]]
    ]


def markdown(result: dict) -> str:
    lines = [
        f"`{SCORE}`'s components over the first {result['chunks']} chunks, read each way; T = mu + {result['k']:g} "
        "sigma of the successful calibration rollouts; all held-out rollouts of each run together."
    ]
    for run, found in result["runs"].items():
        lines += rows_table(run, found, name_column="Reading")
        lines += difference_lines(found["rows"])
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--run",
        action="append",
        required=True,
        help="NAME=<a run's eval folder> (vanilla_calib and held-out sets)",
    )
    parser.add_argument("--chunks", type=int, default=CHUNKS)
    parser.add_argument(
        "--output", type=Path, default=None, help="write the result here (JSON, and .md beside it)"
    )
    args = parser.parse_args(argv)
    result = {"score": SCORE, "chunks": args.chunks, "k": K, "runs": {}}
    for item in args.run:
        name, _, folder = item.partition("=")
        if not folder:
            raise ValueError(f"--run {item!r}: give NAME=<eval folder>.")
        calibration = load_episodes([f"{folder}/vanilla_calib/task*"])
        held = [
            f"{folder}/{condition}/task*"
            for condition in HELD_OUT
            if list(Path(folder).glob(f"{condition}/task*"))
        ]
        result["runs"][name] = run_rows(calibration, load_episodes(held), args.chunks)
    write_report(result, markdown(result), args.output)


if __name__ == "__main__":
    main()
