"""Readings of the phase energy looked at before its third test (issue 52, Table IV; research/docs/libero_runs.md,
"Readings of the phase energy looked at, and a third test"). Development: every set here had been read.

Each reading is the shipped `joint_phase_time_energy` (the z of E_c, E - E_c and E_tau at each chunk index against
the successful calibration rollouts, averaged over the first 16 chunks and the three terms) with one thing changed:
- how the phase term is read from p(k | C): within one chunk of t, -log sum_{|k - t| <= 1} p(k | C); two or more
  chunks behind, -log sum_{k >= t - 2} p(k | C); the expected lag, max(0, t - sum_k k p(k | C));
- how the z are aggregated over the chunks: their median, or each clipped at 3;
- whose mean they are taken against: the rollout's task's (`task_phase_failure_check.fit_task_phase`);
- what E_tau was fitted on: the demonstrations with the successful calibration rollouts, or those rollouts alone,
  cross-fitted in five folds so that no calibration rollout is scored by an E_tau that saw it;
- the phase term alone.
T = mu + 1 sigma of the successful calibration rollouts' scores, each scored without itself, as in the tests.

    python research/benchmarks/phase_energy_variants.py --g_contexts=<G's demonstration contexts .npz> \\
        --k_contexts=<K's demonstration contexts .npz> \\
        --output=research/results/libero_object10_b18/reports/ebvla_joint_fast_cpu_b18/phase_energy/variants.json

The contexts are `phase_energy_failure_check.py contexts` of each checkpoint on F's demonstrations (not committed:
13,802 frames each); K's E_tau is the one its test trained (`check.safetensors`), G's is trained here as that test
trained it.
"""

import argparse
import json
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
from failure_check_test import BASELINE, row, scores_at
from phase_energy_failure_check import CHUNKS, HIDDEN, PHASE_BINS, load_phase_energy, train_phase_energy
from task_phase_failure_check import fit_task_phase

from lerobot_policy_ebvla.monitoring.metrics import auroc, bootstrap_auroc_difference_interval
from lerobot_policy_ebvla.monitoring.records import load_episodes
from lerobot_policy_ebvla.phase_energy import PhaseEnergy, fit_phase_energy
from lerobot_policy_ebvla.runtime.statistics import PhaseStatistics, energies_by_index

RESULTS = Path("research/results")
K_EVAL = RESULTS / "libero_object10_b18/eval/ebvla_joint_fast_cpu_b18"
K_NEW = RESULTS / "libero_object10_b18/eval/ebvla_joint_fast_cpu_b18_phase"
G_EVAL = RESULTS / "libero_object10_arm_more/eval/ebvla_joint_fast_cpu_arm_more_longer"
K_PHASE = RESULTS / "libero_object10_b18/reports/ebvla_joint_fast_cpu_b18/phase_energy/check.safetensors"
# (name, run, calibration records, held-out records)
SETS = (
    ("G's 400", "G", G_EVAL / "vanilla_calib", (G_EVAL / "vanilla_heldout", G_EVAL / "vanilla_confirm")),
    (
        "K's first 400",
        "K",
        K_EVAL / "vanilla_calib",
        (K_EVAL / "vanilla_heldout", K_EVAL / "vanilla_confirm"),
    ),
    (
        "K's second 400",
        "K",
        K_EVAL / "vanilla_calib",
        (K_NEW / "vanilla_heldout_new", K_NEW / "vanilla_confirm_new"),
    ),
)
FOLDS = 5
CHUNK_BINS = np.arange(PHASE_BINS)


@dataclass(frozen=True)
class Rollout:
    """What the readings need of one rollout: per chunk its index, E_c, E - E_c, log p(k | C) and pooled context."""

    index: np.ndarray
    context_energy: np.ndarray
    head_energy: np.ndarray
    log_p: np.ndarray
    features: np.ndarray
    success: bool
    task: str


def rollouts(episodes: dict, model: PhaseEnergy) -> list[Rollout]:
    out = []
    for episode in episodes.values():
        features = np.stack([r.context_feature for r in episode]).astype(np.float32)
        context = np.array([r.context_energy for r in episode], dtype=float)
        out.append(
            Rollout(
                np.array([r.chunk_index for r in episode]),
                context,
                np.array([r.final_energy for r in episode], dtype=float) - context,
                log_probabilities(model, features),
                features,
                episode[0].success,
                episode[0].task,
            )
        )
    return out


def log_probabilities(model: PhaseEnergy, features: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        return model.log_probabilities(torch.as_tensor(features)).numpy()


def _mass(r: Rollout, keep: np.ndarray) -> np.ndarray:
    return -np.log(np.clip((np.exp(r.log_p) * keep).sum(1), 1e-30, None))


def _bins(r: Rollout) -> np.ndarray:
    return np.minimum(r.index, PHASE_BINS - 1)


READOUTS: dict[str, Callable[[Rollout], np.ndarray]] = {
    "E_tau": lambda r: -r.log_p[np.arange(len(r.index)), _bins(r)],
    "within one chunk": lambda r: _mass(r, np.abs(CHUNK_BINS[None] - _bins(r)[:, None]) <= 1),
    "two or more behind": lambda r: _mass(r, CHUNK_BINS[None] >= _bins(r)[:, None] - 2),
    "expected lag": lambda r: np.maximum(0.0, _bins(r) - np.exp(r.log_p) @ CHUNK_BINS),
}
AGGREGATES: dict[str, Callable[[np.ndarray], float]] = {
    "mean": np.mean,
    "median": np.median,
    "clipped at 3": lambda z: float(np.clip(z, None, 3.0).mean()),
}


@dataclass(frozen=True)
class Reading:
    name: str
    readout: str = "E_tau"
    aggregate: str = "mean"
    task_keyed: bool = False
    phase_only: bool = False
    fitted_on: str = "demonstrations"  # or "demonstrations and rollouts", "rollouts"


READINGS = (
    Reading("shipped (`joint_phase_time_energy`)"),
    Reading("E_tau within one chunk of t", readout="within one chunk"),
    Reading("E_tau two or more chunks behind", readout="two or more behind"),
    Reading("expected lag, clipped at 0", readout="expected lag"),
    Reading("median over the chunks", aggregate="median"),
    Reading("each z clipped at 3", aggregate="clipped at 3"),
    Reading("the task's mean", task_keyed=True),
    Reading("E_tau fitted on demonstrations and rollouts", fitted_on="demonstrations and rollouts"),
    Reading("E_tau fitted on rollouts only", fitted_on="rollouts"),
    Reading("the phase term alone", phase_only=True),
)


def terms(r: Rollout, reading: Reading) -> list[np.ndarray]:
    """The reading's terms of one rollout, each indexed by chunk index."""
    phase = energies_by_index(READOUTS[reading.readout](r), r.index)
    if reading.phase_only:
        return [phase]
    return [energies_by_index(r.context_energy, r.index), energies_by_index(r.head_energy, r.index), phase]


def statistics(kept: list[tuple[list[np.ndarray], str]], keyed: bool, task: str) -> list[PhaseStatistics]:
    n_terms = len(kept[0][0])
    if not keyed:
        return [PhaseStatistics.fit([t[i] for t, _ in kept]) for i in range(n_terms)]
    tasks = [task_name for _, task_name in kept]
    return [fit_task_phase([t[i] for t, _ in kept], tasks)[task] for i in range(n_terms)]


def score(series: list[np.ndarray], stats: list[PhaseStatistics], aggregate: str) -> float:
    z = []
    for values, phase in zip(series, stats, strict=True):
        index = np.arange(min(CHUNKS, len(values)))
        index = index[~np.isnan(values[index])]
        z.append(AGGREGATES[aggregate](phase.z(values[index], index)))
    return float(np.mean(z))


def reading_scores(calibration: list[Rollout], held: list[Rollout], reading: Reading):
    """(the successful calibration rollouts' scores, each without itself; the held-out rollouts' scores)."""
    reference = [(terms(r, reading), r.task) for r in calibration if r.success]

    def fitted(task: str, leave_out: int | None = None):
        kept = [x for i, x in enumerate(reference) if i != leave_out]
        return statistics(kept, reading.task_keyed, task)

    calibration_scores = [
        score(t, fitted(task, i), reading.aggregate) for i, (t, task) in enumerate(reference)
    ]
    everyone = {task: fitted(task) for task in {r.task for r in held}}
    held_scores = [score(terms(r, reading), everyone[r.task], reading.aggregate) for r in held]
    return np.array(calibration_scores), np.array(held_scores)


def refit_phase(calibration: list[Rollout], demonstrations: dict | None) -> tuple[list[Rollout], PhaseEnergy]:
    """E_tau fitted on the successful calibration rollouts (with the demonstrations' frames when given): the
    calibration rollouts, each successful one read by the fold's E_tau that left it out and the rest by the one
    fitted on all, and that one (for the held-out rollouts)."""
    successful = [i for i, r in enumerate(calibration) if r.success]
    fold = {i: k % FOLDS for k, i in enumerate(np.random.default_rng(0).permutation(successful))}

    def fit(indices: list[int]) -> PhaseEnergy:
        # (contexts, chunk indices, episode ids) of each source; a rollout's id cannot be a demonstration's.
        sources = (
            []
            if demonstrations is None
            else [tuple(demonstrations[k] for k in ("features", "chunk_index", "episode"))]
        )
        sources += [
            (calibration[i].features, calibration[i].index, np.full(len(calibration[i].index), 10**6 + j))
            for j, i in enumerate(indices)
        ]
        features, index, episode = (np.concatenate(column) for column in zip(*sources, strict=True))
        model = PhaseEnergy(features.shape[1], PHASE_BINS, HIDDEN)
        fit_phase_energy(model, features, index, episode)
        return model.eval()

    log_p = {}
    for k in range(FOLDS):
        model = fit([i for i in successful if fold[i] != k])
        log_p.update(
            {i: log_probabilities(model, calibration[i].features) for i in successful if fold[i] == k}
        )
    everyone = fit(successful)
    new_calibration = [
        replace(r, log_p=log_p[i] if i in log_p else log_probabilities(everyone, r.features))
        for i, r in enumerate(calibration)
    ]
    return new_calibration, everyone


def result_row(name: str, calibration_scores, held_scores, baseline, failed) -> dict:
    """The reading's decisions at T = mu + 1 sigma of the calibration scores (`failure_check_test.row`) and the
    paired interval of its AUROC minus the feature distance's."""
    found = row(name, held_scores, calibration_scores.mean() + calibration_scores.std(), failed)
    paired = bootstrap_auroc_difference_interval(
        held_scores[~failed], held_scores[failed], baseline[~failed], baseline[failed]
    )
    return {
        "reading": name,
        "auroc": found["auroc"],
        "paired_interval": list(paired),
        "failed_alarmed": found["failed_alarmed"],
        "successful_alarmed": found["successful_alarmed"],
    }


def misordered_pairs(scores: np.ndarray, failed: np.ndarray) -> int:
    """(failed, successful) pairs whose successful rollout scores at least as high as the failed one."""
    return int(sum((scores[~failed] >= s).sum() for s in scores[failed]))


def evaluate_set(
    calibration: list[Rollout], held: list[Rollout], baseline: np.ndarray, demonstrations, refits: dict
) -> dict:
    """Every reading's row on one held-out set; `refits` keeps the E_tau fitted on this calibration for the next set
    that shares it."""
    failed = np.array([not r.success for r in held])
    rows, held_scores_of = [], {}
    for reading in READINGS:
        cal, out = calibration, held
        if reading.fitted_on != "demonstrations":
            if reading.fitted_on not in refits:
                with_demonstrations = (
                    demonstrations if reading.fitted_on == "demonstrations and rollouts" else None
                )
                refits[reading.fitted_on] = refit_phase(calibration, with_demonstrations)
            cal, model = refits[reading.fitted_on]
            out = [replace(r, log_p=log_probabilities(model, r.features)) for r in held]
        calibration_scores, held_scores_of[reading] = reading_scores(cal, out, reading)
        rows.append(result_row(reading.name, calibration_scores, held_scores_of[reading], baseline, failed))
        print(f"  {reading.name}: AUROC {rows[-1]['auroc']:.3f}", flush=True)
    rows.append(
        {
            "reading": f"`{BASELINE}` (feature distance)",
            "auroc": auroc(baseline[~failed], baseline[failed]),
            "paired_interval": None,
            "failed_alarmed": None,
            "successful_alarmed": None,
        }
    )
    return {
        "failed": int(failed.sum()),
        "successful": int((~failed).sum()),
        "rows": rows,
        "misordered_pairs": {
            "shipped": misordered_pairs(held_scores_of[READINGS[0]], failed),
            BASELINE: misordered_pairs(baseline, failed),
        },
        "first_task": held[0].task,
        "first_task_term_auroc": first_task_term_auroc(calibration, held, failed),
    }


def first_task_term_auroc(calibration: list[Rollout], held: list[Rollout], failed: np.ndarray) -> dict:
    """Each term of the shipped reading alone, its z averaged over the first chunks: AUROC of the failed against the
    successful held-out rollouts of the first task (None without a failure there)."""
    first = np.array([r.task == held[0].task for r in held])
    shipped = READINGS[0]
    found = {}
    for i, term in enumerate(("E_c", "E - E_c", "E_tau")):
        series = [terms(r, shipped)[i] for r in held]
        stats = PhaseStatistics.fit([terms(r, shipped)[i] for r in calibration if r.success])
        scores = np.array([score([s], [stats], "mean") for s in series])
        found[term] = (
            auroc(scores[first & ~failed], scores[first & failed]) if (first & failed).any() else None
        )
    return found


def markdown(result: dict) -> str:
    names = list(result["sets"])
    lines = [
        "| reading | " + " | ".join(f"{n} ({s['failed']} failed)" for n, s in result["sets"].items()) + " |",
        "|---|" + "---|" * len(names),
    ]
    for i, first in enumerate(result["sets"][names[0]]["rows"]):
        cells = []
        for name in names:
            row = result["sets"][name]["rows"][i]
            if row["paired_interval"] is None:
                cells.append(f"{row['auroc']:.3f}")
            else:
                low, high = row["paired_interval"]
                cells.append(
                    f"{row['auroc']:.3f} [{low:+.3f}, {high:+.3f}], {row['failed_alarmed']} and "
                    f"{row['successful_alarmed']} alarmed"
                )
        lines.append(f"| {first['reading']} | " + " | ".join(cells) + " |")
    lines.append("")
    lines.append(
        "AUROC [paired 95 % interval of its difference to the feature distance's], failed and successful rollouts "
        f"alarmed at T = mu + 1 sigma; first {result['chunks']} chunks."
    )
    for name, found in result["sets"].items():
        pairs = found["misordered_pairs"]
        terms_line = ", ".join(
            f"{term} {value:.3f}"
            for term, value in found["first_task_term_auroc"].items()
            if value is not None
        )
        lines.append(
            f"- {name}: (failed, successful) pairs ordered wrongly: shipped {pairs['shipped']}, `{BASELINE}` "
            f"{pairs[BASELINE]}; each term alone on the first task ({found['first_task']}): {terms_line or 'no failure'}."
        )
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--g_contexts", type=Path, required=True, help="G's demonstration contexts (.npz)")
    parser.add_argument("--k_contexts", type=Path, required=True, help="K's demonstration contexts (.npz)")
    parser.add_argument("--output", type=Path, default=None, help="the result (JSON, and .md beside it)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    demonstrations = {}
    for run, path in (("G", args.g_contexts), ("K", args.k_contexts)):
        contexts = dict(np.load(path))
        # Contexts saved before the package's fit named the chunk index `chunk`.
        contexts.setdefault("chunk_index", contexts.get("chunk"))
        demonstrations[run] = contexts
    models = {"G": train_phase_energy(demonstrations["G"])[0], "K": load_phase_energy(K_PHASE)}
    result, refits = {"chunks": CHUNKS, "sets": {}}, {"G": {}, "K": {}}
    for name, run, calibration_dir, held_dirs in SETS:
        calibration = load_episodes([str(calibration_dir / "task*")])
        held = {}
        for folder in held_dirs:
            held.update(load_episodes([str(folder / "task*")]))
        _, baseline = scores_at(BASELINE, calibration, held, CHUNKS)
        result["sets"][name] = evaluate_set(
            rollouts(calibration, models[run]),
            rollouts(held, models[run]),
            baseline,
            demonstrations[run],
            refits[run],
        )
        print(f"{name} done", flush=True)
    text = markdown(result)
    print(text)
    if args.output is not None:
        args.output.parent.mkdir(parents=True, exist_ok=True)
        args.output.write_text(json.dumps(result, indent=1) + "\n")
        args.output.with_suffix(".md").write_text(text)


if __name__ == "__main__":
    main()
