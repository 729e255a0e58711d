"""What a user of a checkpoint's shipped monitor gets: `EnergyMonitor` replayed on recorded rollouts, chunk by chunk.

The reports judge the OOD check as one decision on each rollout's first 3 chunks, T fitted on the calibration
rollouts' first 3 chunks. At run time `EnergyMonitor` (and `EnergyOODMonitor`) compares the running score of the
rollout so far, after every chunk, to the T saved in `ood_calibration.json` (`ebvla-ood-report --calibrate_to`
fitted it on whole calibration episodes until 2026-11-29, C's saved T; since then on the first 3 chunks, as the
reports do; since the window score, `ChunkWindow`, on the window score of the first 3 chunks, so that T bounds
the alarms of chunks 1-3 together). Here each recorded rollout is fed to the checkpoint's monitor as the policy
would feed it, and per condition this counts the rollouts flagged unfamiliar at chunk 3, at any of chunks 1-3, and
at any chunk of the episode, beside the failure check's alarms (decided at its chunk N). `balanced_accuracy`: for
each vanilla set, the mean of its rollouts not flagged by chunk 3 and of all perturbed rollouts flagged by then.

`--refit_first_chunks=3` replays the same monitor with its OOD threshold refitted without a window, on the
calibration rollouts' (`vanilla_calib`) scores over their first 3 chunks, at the monitor's rule: the check C
shipped after the first fix, and D before the window.

    python research/benchmarks/runtime_alarm_rates.py \\
        --checkpoint=research/results/libero_object10/train/ebvla_joint_fast_cpu/last/pretrained_model \\
        --records=outputs/libero10/eval/ebvla_joint_fast_cpu \\
        --output=research/results/libero_object10/reports/ebvla_joint_fast_cpu/runtime_alarms.json
"""

import argparse
import dataclasses
import json
from pathlib import Path

from lerobot_policy_ebvla import EnergyMonitor
from lerobot_policy_ebvla.monitoring.baselines import episode_readout
from lerobot_policy_ebvla.monitoring.metrics import wilson_interval
from lerobot_policy_ebvla.monitoring.ood_report import OODReportConfig, score_ood_report
from lerobot_policy_ebvla.monitoring.records import load_episodes


def refit_on_first_chunks(monitor: EnergyMonitor, records: Path, chunks: int) -> EnergyMonitor:
    """The monitor with its OOD check's mu_v and sigma_v those of the calibration rollouts' first `chunks` chunks."""
    conditions = [p for p in records.iterdir() if p.is_dir() and not p.name.startswith("vanilla")]
    cfg = OODReportConfig(
        calibration=[str(records / "vanilla_calib" / "task*")],
        vanilla=[str(records / "vanilla_heldout" / "task*")],
        ood=[str(p / "task*") for p in conditions],
        k=monitor.ood.k,
        false_alarm_rate=monitor.ood.false_alarm_rate,
    )
    fit = score_ood_report(cfg).fit(monitor.ood.score.name, chunks)
    ood = dataclasses.replace(
        monitor.ood,
        mu_v=fit.mu_v,
        sigma_v=fit.sigma_v,
        n_rollouts=fit.n_rollouts,
        conformal_threshold=fit.conformal_threshold
        if monitor.ood.rule == "conformal"
        else monitor.ood.conformal_threshold,
        window=None,
    )
    return EnergyMonitor(ood, monitor.failure)


def replay(monitor: EnergyMonitor, episode: list) -> dict:
    """The monitor's decisions on one recorded rollout, chunk by chunk."""
    monitor.reset()
    readout = episode_readout(episode)
    unfamiliar, failing = [], None
    for chunk in range(len(episode)):
        (decision,) = monitor.update(readout.row(chunk))
        unfamiliar.append(decision.unfamiliar.is_ood)
        failing = decision.failing if decision.failing is not None else failing
    return {
        "at_chunk_3": unfamiliar[min(2, len(unfamiliar) - 1)],
        "by_chunk_3": any(unfamiliar[:3]),
        "ever": any(unfamiliar),
        "failing": bool(failing),
        "success": bool(episode[0].success),
    }


def rates(decisions: list[dict]) -> dict:
    n = len(decisions)
    row = {"rollouts": n, "successes": sum(d["success"] for d in decisions)}
    for key in ("at_chunk_3", "by_chunk_3", "ever", "failing"):
        k = sum(d[key] for d in decisions)
        row[key] = {"alarmed": k, "rate": k / n, "wilson_95": list(wilson_interval(k, n))}
    return row


def balanced_accuracies(conditions: dict[str, dict]) -> dict:
    """For each vanilla set: (1 - its rate flagged by chunk 3 + the perturbed rollouts' rate flagged by then) / 2."""
    perturbed = [row for name, row in conditions.items() if not name.startswith("vanilla")]
    if not perturbed:
        return {}
    caught = sum(row["by_chunk_3"]["alarmed"] for row in perturbed) / sum(
        row["rollouts"] for row in perturbed
    )
    return {
        name: (1.0 - row["by_chunk_3"]["rate"] + caught) / 2
        for name, row in conditions.items()
        if name.startswith("vanilla")
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--checkpoint", type=Path, required=True, help="a pretrained_model folder with its monitor"
    )
    parser.add_argument(
        "--records", type=Path, required=True, help="eval/<run>: one folder per condition and task"
    )
    parser.add_argument("--output", type=Path, default=None)
    parser.add_argument(
        "--refit_first_chunks",
        type=int,
        default=None,
        help="refit the OOD threshold on this many first chunks",
    )
    args = parser.parse_args(argv)
    monitor = EnergyMonitor.from_pretrained(args.checkpoint)
    if args.refit_first_chunks is not None:
        monitor = refit_on_first_chunks(monitor, args.records, args.refit_first_chunks)
    result = {
        "refit_first_chunks": args.refit_first_chunks,
        "ood_score": monitor.ood.score.name,
        "ood_threshold": monitor.ood.threshold,
        "failure_check": None
        if monitor.failure is None
        else {"score": monitor.failure.score.name, "chunks": monitor.failure.chunks},
        "conditions": {},
    }
    for folder in sorted(p for p in args.records.iterdir() if p.is_dir()):
        episodes = load_episodes([str(folder / "task*")])
        if episodes:
            result["conditions"][folder.name] = rates([replay(monitor, e) for e in episodes.values()])
    result["balanced_accuracy_by_chunk_3"] = balanced_accuracies(result["conditions"])
    print(f"{'condition':18} {'n':>4} {'at chunk 3':>11} {'by chunk 3':>11} {'any chunk':>10} {'failing':>8}")
    for name, row in result["conditions"].items():
        cells = " ".join(
            f"{row[key]['rate']:>10.0%}" for key in ("at_chunk_3", "by_chunk_3", "ever", "failing")
        )
        print(f"{name:18} {row['rollouts']:>4} {cells}")
    for name, accuracy in result["balanced_accuracy_by_chunk_3"].items():
        print(f"balanced accuracy by chunk 3, {name} against every perturbed rollout: {accuracy:.1%}")
    if args.output is not None:
        args.output.parent.mkdir(parents=True, exist_ok=True)
        args.output.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
