"""Does thinking more pay? Best-of-N by energy in closed loop, in vanilla and under every sweep shift (issue 32).

For one checkpoint, every variant is evaluated on the same seeds: `num_restarts` = N (N chains refined per chunk,
the lowest final energy kept), and adaptive restarts (`restart_energy_threshold`: one chain, and N only where its
final energy is above T). T is a quantile (`--adaptive_quantile`) of the chunk final energies of N = 1's
calibration rollouts (other seeds than the reported ones), so it is chosen before any reported rollout is seen.

    MUJOCO_GL=egl python research/benchmarks/best_of_n_closed_loop.py run --checkpoint=<pretrained_model> \\
        --output_dir=outputs/best_of_n --restarts 1 4 8 --adaptive 8
    python research/benchmarks/best_of_n_closed_loop.py table --output_dir=outputs/best_of_n   # the markdown table

`run` skips every folder that already holds its records, so an interrupted run resumes. Layout:
`<variant>/<condition>/energy_records.jsonl` (each chunk's `mcmc_chains` is its compute), `timings.jsonl` (the
wall time of each condition's process, start-up included: kept, not tabled, since other jobs share the cores),
`adaptive_<N>/threshold.json`, and `chunk_cost.json` from `cost` (CPU ms per chunk for each N, one thread).
"""

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
from compare_diffusion_metaworld import run_in_process

from lerobot_policy_ebvla.envs.perturbations import PERTURBATIONS
from lerobot_policy_ebvla.monitoring.metrics import markdown_table, wilson_interval
from lerobot_policy_ebvla.monitoring.records import group_by_episode, read_energy_records, records_file_in
from lerobot_policy_ebvla.pipelines.eval_energy import eval_metaworld_checkpoint

SWEPT = [p for p in PERTURBATIONS if p not in ("none", "pose_fov")]
VANILLA = "vanilla"


def variant_name(restarts: int, adaptive: bool) -> str:
    return f"adaptive_{restarts}" if adaptive else f"restarts_{restarts}"


def evaluate(
    args, variant: str, condition: str, seed: int, episodes: int, overrides: list[str], **env
) -> None:
    out = args.output_dir / variant / condition
    if out.is_dir() and records_file_in(out) is not None:
        return
    out.parent.mkdir(parents=True, exist_ok=True)
    seconds = run_in_process(
        eval_metaworld_checkpoint,
        args.output_dir / variant / f"{condition}.log",
        args.checkpoint,
        out,
        task=args.tasks,
        device="cpu",
        max_episode_steps=args.max_episode_steps,
        n_episodes=episodes,
        seed=seed,
        observation_size=args.observation_size,
        policy_overrides=overrides,
        **env,
    )
    row = {"variant": variant, "condition": condition, "seconds": round(seconds, 1), "episodes": episodes}
    with open(args.output_dir / "timings.jsonl", "a") as f:
        f.write(json.dumps(row) + "\n")


def adaptive_threshold(args) -> float:
    """T: the `--adaptive_quantile` of N = 1's calibration chunk energies."""
    calibration = args.output_dir / variant_name(1, False) / "calibration"
    energies = [r.final_energy for r in read_energy_records(records_file_in(calibration))]
    return float(np.quantile(energies, args.adaptive_quantile))


def saved_threshold(args, variant: str) -> float:
    """T of an adaptive variant, chosen once and kept in its `threshold.json`, so a resumed run reuses it."""
    saved = args.output_dir / variant / "threshold.json"
    if not saved.is_file():
        saved.parent.mkdir(parents=True, exist_ok=True)
        source = f"{variant_name(1, False)}/calibration"
        saved.write_text(
            json.dumps(
                {"threshold": adaptive_threshold(args), "quantile": args.adaptive_quantile, "from": source}
            )
        )
    return json.loads(saved.read_text())["threshold"]


def run(args) -> None:
    conditions = {f"{p}_s{s}": (p, s) for p in args.perturbations for s in args.severities}
    base = variant_name(1, False)
    evaluate(args, base, "calibration", args.calibration_seed, args.calibration_episodes, [])
    variants = [(n, False) for n in args.restarts] + [(n, True) for n in args.adaptive]
    for restarts, adaptive in variants:
        variant = variant_name(restarts, adaptive)
        overrides = [f"--num_restarts={restarts}"]
        if adaptive:
            overrides.append(f"--restart_energy_threshold={saved_threshold(args, variant)}")
        evaluate(args, variant, VANILLA, args.seed, args.vanilla_episodes, overrides)
        for condition, (perturbation, severity) in conditions.items():
            evaluate(
                args, variant, condition, args.seed, args.episodes, overrides,
                perturbation=perturbation, severity=severity,
            )  # fmt: skip


def episodes_of(folder: Path) -> list[list]:
    return list(group_by_episode(read_energy_records(records_file_in(folder))).values())


def success_cell(successes: int, n: int) -> str:
    low, high = wilson_interval(successes, n)
    return f"{successes}/{n} = {100 * successes / n:.0f}% [{100 * low:.0f}, {100 * high:.0f}]"


def variant_rows(folder: Path) -> dict[str, dict]:
    """Per condition of one variant: successes, n, chains per chunk, and each episode's outcome by seed."""
    rows = {}
    for condition_folder in sorted(p for p in folder.iterdir() if p.is_dir() and p.name != "calibration"):
        eps = episodes_of(condition_folder)
        rows[condition_folder.name] = {
            "successes": sum(ep[0].success for ep in eps),
            "n": len(eps),
            "chains_per_chunk": float(np.mean([r.mcmc_chains for ep in eps for r in ep])),
            "outcomes": {ep[0].seed: ep[0].success for ep in eps},
        }
    return rows


def paired_against(base: dict, other: dict, conditions: list[str]) -> tuple[int, int, float]:
    """Episodes (same condition and seed) that `other` won and `base` lost, the reverse, and the two-sided
    exact sign test's p-value over those discordant pairs."""
    wins = losses = 0
    for c in conditions:
        for seed, success in other[c]["outcomes"].items():
            before = base[c]["outcomes"][seed]
            wins += success and not before
            losses += before and not success
    n = wins + losses
    tail = sum(math.comb(n, k) for k in range(min(wins, losses) + 1)) / 2**n if n else 1.0
    return wins, losses, min(1.0, 2 * tail)


def cost_cell(output_dir: Path, variant: str, rows: dict, conditions: list[str]) -> str:
    """The measured CPU ms per chunk (`cost`) of N chains; for adaptive N, interpolated linearly in its mean
    chains per chunk between the measured N = 1 and N (marked "est.")."""
    path = output_dir / "chunk_cost.json"
    if not path.is_file():
        return "-"
    cost = {int(n): ms for n, ms in json.loads(path.read_text())["cpu_ms_per_chunk"].items()}
    n = int(variant.rsplit("_", 1)[1])
    if n not in cost:
        return "-"
    if variant.startswith("restarts_"):
        return f"{cost[n]:.0f}"
    chains = np.mean([rows[c]["chains_per_chunk"] for c in conditions])
    return f"{cost[1] + (chains - 1) / (n - 1) * (cost[n] - cost[1]):.0f} (est.)"


def variant_sort_key(name: str) -> tuple[int, int]:
    kind, n = name.rsplit("_", 1)
    return (kind == "adaptive", int(n))


def table(output_dir: Path) -> tuple[str, dict]:
    """The markdown table and {variant: rows}: success per condition, the shifts pooled, and the compute."""
    variants = sorted(
        (
            p.name
            for p in output_dir.iterdir()
            if p.is_dir() and p.name.startswith(("restarts_", "adaptive_"))
        ),
        key=variant_sort_key,
    )
    results = {v: variant_rows(output_dir / v) for v in variants}
    shifts = [c for c in results[variants[0]] if c != VANILLA and all(c in results[v] for v in variants)]
    conditions = [VANILLA] + shifts
    rows = [
        [c] + [success_cell(results[v][c]["successes"], results[v][c]["n"]) for v in variants]
        for c in conditions
    ]
    pooled = {
        v: (sum(results[v][c]["successes"] for c in shifts), sum(results[v][c]["n"] for c in shifts))
        for v in variants
    }
    rows.append(["all shifts pooled"] + [success_cell(*pooled[v]) for v in variants])
    base = results.get(variant_name(1, False))
    if base is not None:
        paired = []
        for v in variants:
            wins, losses, p = paired_against(base, results[v], conditions)
            paired.append("-" if results[v] is base else f"+{wins} / -{losses} (p = {p:.3f})")
        rows.append(["episodes won / lost against N = 1 (all conditions, same seeds)"] + paired)
    rows.append(
        ["MCMC chains per chunk"]
        + [f"{np.mean([results[v][c]['chains_per_chunk'] for c in conditions]):.2f}" for v in variants]
    )
    rows.append(
        ["CPU ms per chunk, one thread"]
        + [cost_cell(output_dir, v, results[v], conditions) for v in variants]
    )
    return markdown_table(["condition"] + variants, rows), results


def chunk_cost(checkpoint: Path, restarts: list[int], calls: int = 30) -> dict[int, float]:
    """CPU milliseconds per chunk (`predict_action_chunk` of one observation, one torch thread) for each N.

    Thread CPU time, not wall time: one torch thread runs on the calling thread, so its CPU time does not grow
    when other jobs share the cores, as wall time does. Inputs are random pre-processed observations.
    """
    import torch

    from lerobot_policy_ebvla import EBVLAPolicy

    torch.set_num_threads(1)
    policy = EBVLAPolicy.from_pretrained(checkpoint).eval()
    config = policy.config
    batch = {key: torch.rand(1, *ft.shape) for key, ft in config.image_features.items()}
    if config.robot_state_feature is not None:
        batch["observation.state"] = torch.randn(1, *config.robot_state_feature.shape)
    costs = {}
    for n in restarts:
        policy.config.num_restarts = n
        times = []
        with torch.inference_mode():
            for _ in range(calls + 3):
                start = time.thread_time()
                policy.predict_action_chunk(batch)
                times.append(time.thread_time() - start)
        costs[n] = 1000 * float(np.median(times[3:]))
    return costs


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="command", required=True)
    run_parser = sub.add_parser("run")
    run_parser.add_argument("--checkpoint", type=Path, required=True, help="A pretrained_model folder.")
    run_parser.add_argument("--output_dir", type=Path, default=Path("outputs/best_of_n"))
    run_parser.add_argument("--tasks", default="button-press-v3")
    run_parser.add_argument("--restarts", type=int, nargs="+", default=[1, 4, 8])
    run_parser.add_argument(
        "--adaptive", type=int, nargs="*", default=[8], help="N of the adaptive variants."
    )
    run_parser.add_argument("--adaptive_quantile", type=float, default=0.75)
    run_parser.add_argument("--episodes", type=int, default=8, help="Rollouts per shift.")
    run_parser.add_argument("--vanilla_episodes", type=int, default=16)
    run_parser.add_argument("--calibration_episodes", type=int, default=10)
    run_parser.add_argument("--perturbations", nargs="+", default=SWEPT, choices=SWEPT)
    run_parser.add_argument("--severities", type=int, nargs="+", default=[5])
    run_parser.add_argument("--seed", type=int, default=3000)
    run_parser.add_argument("--calibration_seed", type=int, default=4000)
    run_parser.add_argument("--max_episode_steps", type=int, default=150)
    run_parser.add_argument("--observation_size", type=int, default=128)
    cost_parser = sub.add_parser("cost", help="CPU ms per chunk for each N (one thread)")
    cost_parser.add_argument("--checkpoint", type=Path, required=True)
    cost_parser.add_argument("--restarts", type=int, nargs="+", default=[1, 4, 8])
    cost_parser.add_argument("--output_dir", type=Path, default=Path("outputs/best_of_n"))
    table_parser = sub.add_parser("table")
    table_parser.add_argument("--output_dir", type=Path, default=Path("outputs/best_of_n"))
    args = parser.parse_args()
    if args.command == "cost":
        costs = chunk_cost(args.checkpoint, args.restarts)
        (args.output_dir / "chunk_cost.json").write_text(json.dumps({"cpu_ms_per_chunk": costs}, indent=1))
        print(costs)
        return
    if args.command == "run":
        args.output_dir.mkdir(parents=True, exist_ok=True)
        run(args)
    print(table(args.output_dir)[0])


if __name__ == "__main__":
    sys.exit(main())
