"""The test of a failure check `failure_check_choice.py` chose, on another checkpoint's rollouts (issue 52, Table IV).

The (score, N) comes fixed from the choice's JSON. T = mu + k sigma of the tested checkpoint's own *successful*
calibration rollouts, each scored against the others as the choice scores them, and its held-out vanilla rollouts
are judged at T: failed ones are the positives. Beside the chosen check, at the same N and rule: the energy scores of
`--beside` (the check the checkpoint ships otherwise first) and `chunk_context_nn`, the pooled context at chunk N
against the successful calibration rollouts' at that chunk (no energy). Each row gives the failed and successful
rollouts alarmed (n per side), the balanced accuracy and the AUROC with its bootstrap 95 % interval; the chosen check
also each caught failure's lead to its onset (`lead_time.failure_onset`) and to the episode's end, in chunks. Each
`--held_out` set is reported apart and all together.

Written on 2026-11-30, before E's calibration and held-out energies were read (research/docs/libero_runs.md, "A
failure check on both terms of the joint energy"), whose reading of the targets it prints.

    python research/benchmarks/failure_check_test.py \\
        --choice=research/results/libero_object10_more/reports/ebvla_joint_fast_cpu_more/failure_check_choice_joint.json \\
        --calibration='outputs/libero10_arm/eval/ebvla_joint_fast_cpu_arm/vanilla_calib/task*' \\
        --held_out 'outputs/libero10_arm/eval/ebvla_joint_fast_cpu_arm/vanilla_heldout/task*' \\
        'outputs/libero10_arm/eval/ebvla_joint_fast_cpu_arm/vanilla_confirm/task*' \\
        --output=research/results/libero_object10_arm/reports/ebvla_joint_fast_cpu_arm/failure_check_test.json
"""

import argparse
import json
from pathlib import Path

import numpy as np
from failure_check_choice import calibration_scores

from lerobot_policy_ebvla.monitoring.baselines import chunk_context_nn
from lerobot_policy_ebvla.monitoring.lead_time import failure_onset
from lerobot_policy_ebvla.monitoring.metrics import BinaryRates, auroc, bootstrap_auroc_interval
from lerobot_policy_ebvla.monitoring.records import load_episodes

BASELINE = "chunk_context_nn"
# The Table IV target for the failure check's balanced accuracy, held out.
MIN_BALANCED_ACCURACY = 0.80


def scores_at(score: str, calibration: dict, held_out: dict, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The calibration rollouts' scores over their first n chunks (each against the others) and the held-out ones'."""
    if score == BASELINE:
        return chunk_context_nn(calibration, calibration, n - 1), chunk_context_nn(
            calibration, held_out, n - 1
        )
    values = calibration_scores(list(calibration.values()), score, (n,), list(held_out.values()))[n]
    return values[: len(calibration)], values[len(calibration) :]


def row(name: str, held_scores: np.ndarray, threshold: float, failed: np.ndarray) -> dict:
    """One score's decision at T on held-out rollouts: counts per side, balanced accuracy, AUROC [95 % CI]."""
    flags = held_scores > threshold
    rates = BinaryRates.from_flags(flags[~failed], flags[failed])
    negatives, positives = held_scores[~failed], held_scores[failed]
    return {
        "score": name,
        "threshold": threshold,
        "failed_alarmed": rates.tp,
        "failed": rates.n_positive,
        "successful_alarmed": rates.fp,
        "successful": rates.fp + rates.tn,
        "balanced_accuracy": rates.balanced_accuracy,
        "auroc": auroc(negatives, positives),
        "auroc_interval": list(bootstrap_auroc_interval(negatives, positives)),
    }


def leads(episodes: list, scores: np.ndarray, threshold: float, n: int) -> dict:
    """The caught failures' lead to their onset and to the episode's end, in chunks (median, and how many caught at
    or before the onset); the alarm is decided at the end of chunk n."""
    caught = [e for e, s in zip(episodes, scores, strict=True) if not e[0].success and s > threshold]
    onset = [failure_onset(e) - n for e in caught if failure_onset(e) is not None]
    end = [len(e) - n for e in caught]
    return {
        "caught": len(caught),
        "at_or_before_onset": int(sum(lead >= 0 for lead in onset)),
        "median_lead_to_onset": float(np.median(onset)) if onset else None,
        "median_lead_to_end": float(np.median(end)) if end else None,
    }


def test_choice(choice: dict, calibration: dict, held_out_sets: dict[str, dict], beside: list[str]) -> dict:
    """Every row of every held-out set (and of all of them together), at T of the successful calibration rollouts."""
    n, k, chosen = choice["chunks"], choice["k"], choice["score"]
    successful = np.array([episode[0].success for episode in calibration.values()])
    if successful.all() or successful.sum() < 2:
        raise ValueError(
            f"The test needs failed and at least 2 successful calibration rollouts; got {successful.sum()} successful "
            f"of {successful.size}."
        )
    sets = {**held_out_sets, "all held out": {k_: e for s in held_out_sets.values() for k_, e in s.items()}}
    result = {"choice": {"score": chosen, "chunks": n, "k": k}, "calibration_rollouts": int(successful.size)}
    result["calibration_failed"] = int((~successful).sum())
    result["sets"] = {}
    for title, held_out in sets.items():
        failed = np.array([not episode[0].success for episode in held_out.values()])
        rows = []
        for name in dict.fromkeys([chosen, *beside, BASELINE]):
            calibration_values, held_values = scores_at(name, calibration, held_out, n)
            reference = calibration_values[successful]
            threshold = float(reference.mean() + k * reference.std())
            rows.append(row(name, held_values, threshold, failed))
            if name == chosen:
                lead = leads(list(held_out.values()), held_values, threshold, n)
        result["sets"][title] = {
            "rollouts": int(failed.size),
            "failed": int(failed.sum()),
            "rows": rows,
            "leads": lead,
        }
    return result


def targets(result: dict) -> list[tuple[str, bool, str]]:
    """The pre-registered reading on all held-out rollouts together: (target, met, figures)."""
    rows = {r["score"]: r for r in result["sets"]["all held out"]["rows"]}
    chosen, baseline = rows[result["choice"]["score"]], rows[BASELINE]
    others = [r for name, r in rows.items() if name not in (result["choice"]["score"], BASELINE)]
    low, high = chosen["auroc_interval"]
    found = [
        (
            f"balanced accuracy >= {MIN_BALANCED_ACCURACY:.0%}",
            chosen["balanced_accuracy"] >= MIN_BALANCED_ACCURACY,
            f"{chosen['balanced_accuracy']:.1%}",
        )
    ]
    found += [
        (
            f"at least {other['score']}'s balanced accuracy",
            chosen["balanced_accuracy"] >= other["balanced_accuracy"],
            f"{chosen['balanced_accuracy']:.1%} against {other['balanced_accuracy']:.1%}",
        )
        for other in others
    ]
    found.append(
        (
            f"not below {BASELINE} outside its interval",
            baseline["auroc"] <= high,
            f"{chosen['auroc']:.3f} [{low:.3f}, {high:.3f}] against {baseline['auroc']:.3f}",
        )
    )
    return found


def rows_table(title: str, found: dict, name=str, name_column: str = "Score") -> list[str]:
    """A held-out set's rows (`row`) as a markdown table under its title: counts per side, balanced accuracy, AUROC."""
    lines = [
        "",
        f"### {title}: {found['failed']} of {found['rollouts']} failed",
        "",
        f"| {name_column} | Failed alarmed | Successful alarmed | Bal. acc. | AUROC [95 % CI] |",
        "|---|---:|---:|---:|---|",
    ]
    for r in found["rows"]:
        low, high = r["auroc_interval"]
        lines.append(
            f"| {name(r['score'])} | {r['failed_alarmed']}/{r['failed']} | {r['successful_alarmed']}/{r['successful']} "
            f"| {r['balanced_accuracy']:.1%} | {r['auroc']:.3f} [{low:.3f}, {high:.3f}] |"
        )
    return lines


def lead_line(lead: dict) -> str:
    """The caught failures' leads (`leads`) as a sentence of the report."""
    return (
        f"\nCaught {lead['caught']}: {lead['at_or_before_onset']} at or before the onset; median lead to the onset "
        f"{lead['median_lead_to_onset']} chunks, to the episode's end {lead['median_lead_to_end']}."
    )


def report_markdown(score: str, chunks: int, k: float, result: dict, targets, beside_rows=None) -> str:
    """A failure check's report: its T, each held-out set's rows (then `beside_rows(found)`, if given) and lead line,
    and the fixed targets as (target, met, figures)."""
    lines = [
        f"Failure check `{score}` over the first {chunks} chunks, T = mu + {k:g} sigma "
        f"of the {result['calibration_rollouts'] - result['calibration_failed']} successful calibration rollouts "
        f"(of {result['calibration_rollouts']})."
    ]
    for title, found in result["sets"].items():
        lines += rows_table(title, found, lambda name: f"`{name}`")
        lines += beside_rows(found) if beside_rows else []
        lines.append(lead_line(found["leads"]))
    lines += ["", "Targets (all held out):"]
    lines += [f"- {name}: {'met' if met else 'missed'} ({figures})" for name, met, figures in targets]
    return "\n".join(lines) + "\n"


def markdown(result: dict) -> str:
    choice = result["choice"]
    return report_markdown(choice["score"], choice["chunks"], choice["k"], result, targets(result))


def write_report(result: dict, text: str, output: Path | None) -> None:
    """Prints the report; with `output`, writes the result there as JSON and the text beside it (.md)."""
    print(text)
    if output is not None:
        output.parent.mkdir(parents=True, exist_ok=True)
        output.write_text(json.dumps(result, indent=1) + "\n")
        output.with_suffix(".md").write_text(text)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--choice", type=Path, required=True, help="failure_check_choice.py's JSON")
    parser.add_argument(
        "--calibration", required=True, help="the tested checkpoint's calibration records (a glob)"
    )
    parser.add_argument("--held_out", nargs="+", required=True, help="held-out records, one glob per set")
    parser.add_argument(
        "--beside", nargs="*", default=["context_phase_energy"], help="energy scores beside it"
    )
    parser.add_argument(
        "--output", type=Path, default=None, help="write the result here (JSON, and .md beside it)"
    )
    args = parser.parse_args(argv)
    calibration = load_episodes([args.calibration])
    held_out = {Path(pattern).parent.name: load_episodes([pattern]) for pattern in args.held_out}
    result = test_choice(json.loads(args.choice.read_text()), calibration, held_out, args.beside)
    result["targets"] = [{"target": t, "met": met, "figures": f} for t, met, f in targets(result)]
    write_report(result, markdown(result), args.output)


if __name__ == "__main__":
    main()
