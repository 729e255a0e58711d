"""A success energy for the failure check (issue 52, Table IV; research/docs/libero_runs.md, "A success energy fitted
on the policy's own successful rollouts", where the reading was chosen on K's three read sets and the test fixed
before the fourth set was read).

The phase energy E_tau(C, t) = -log p(t | C) asks *when* a context belongs and is normalized over t; the feature
distance `chunk_context_nn` asks whether the context at chunk t looks like any successful rollout's at chunk t, which
is a question over contexts at a fixed t. The success energy asks that one as an energy:

    E_s(C, t) = g(W C~ + e_t),   C~ the pooled context standardized by the successful calibration contexts,

g an MLP to a scalar, e_t a learned embedding of the chunk index (t >= 40 shares the last). It is trained on the
**successful calibration rollouts**, contrastively (InfoNCE): at each of their chunks the context it holds at t is
the positive, against `NEGATIVES` contexts drawn from those rollouts at any chunk (most of another phase: a stalled
rollout's context at t is one of an earlier t) and `NEGATIVES // 2` copies of it with Gaussian noise of std `NOISE`
in standardized units (a context unlike any); a small penalty on the positives' squared energy (`anchor`) holds
success at 0, since InfoNCE alone leaves each t's offset free. So E_s is about 0 where success is at chunk t and rises
off it, in every direction the noise takes. It stores no context: an MLP and the standardization.

No calibration rollout is scored by an E_s that saw it: the successful ones are cross-fitted in `FOLDS` folds (each
read by the fold's E_s that left it out); the failed ones and every held-out rollout are read by the E_s fitted on
all successful calibration rollouts, the one a checkpoint would ship. T = mu + 1 sigma of the successful calibration
rollouts' scores. The module, its fit and the cross-fitting are the package's (`lerobot_policy_ebvla.runtime.success_energy`,
the `success_energy` failure check); this script adds the trainings and readings the choice compared.

    # the development: every training and reading looked at, on K's three read sets (about 25 minutes, one thread)
    python research/benchmarks/success_energy_failure_check.py choose \\
        --output=research/results/libero_object10_b18/reports/ebvla_joint_fast_cpu_b18/success_energy/choice.json
    # the test: the chosen reading on a set never read, against `chunk_context_nn` (`--fitted`: with the E_s an
    # earlier test saved, as the fifth set is read)
    python research/benchmarks/success_energy_failure_check.py test --held_out '<eval>/vanilla_heldout_fourth/task*' \\
        '<eval>/vanilla_confirm_fourth/task*' --output=<...>/success_energy/fourth_rollouts.json
"""

import argparse
import json
import shutil
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from failure_check_test import (
    BASELINE,
    MIN_BALANCED_ACCURACY,
    leads,
    report_markdown,
    scores_at,
    write_report,
)
from failure_score_variants import difference_lines, rows_against_baseline
from phase_energy_failure_check import (
    CHOSEN,
    CHUNKS,
    K,
    first_chunks,
    joint_phase_time_scores,
    load_phase_energy,
    term_series,
)
from safetensors.torch import load_file, save_file

from lerobot_policy_ebvla.monitoring.baselines import episode_readout
from lerobot_policy_ebvla.monitoring.ood_report import OODReportConfig, write_ood_report
from lerobot_policy_ebvla.monitoring.records import Episode, load_episodes
from lerobot_policy_ebvla.runtime.calibration import FAILURE_CALIBRATION_FILENAME, FailureCalibration
from lerobot_policy_ebvla.runtime.statistics import PhaseStatistics, energies_by_index
from lerobot_policy_ebvla.runtime.success_energy import (
    FOLDS,
    NEGATIVES,
    SuccessEnergy,
    fit_success_energy,
    fold_order,
    fold_readers,
)

RESULTS = Path("research/results/libero_object10_b18")
K_EVAL = RESULTS / "eval/ebvla_joint_fast_cpu_b18"
K_NEW = RESULTS / "eval/ebvla_joint_fast_cpu_b18_phase"
K_PHASE = RESULTS / "reports/ebvla_joint_fast_cpu_b18/phase_energy/check.safetensors"
CALIBRATION = K_EVAL / "vanilla_calib"
# K's three sets of 400 held-out rollouts, every one read before this energy was thought of.
READ_SETS = {
    "K's first 400": (K_EVAL / "vanilla_heldout", K_EVAL / "vanilla_confirm"),
    "K's second 400": (K_NEW / "vanilla_heldout_new", K_NEW / "vanilla_confirm_new"),
    "K's third 400": (K_NEW / "vanilla_heldout_third", K_NEW / "vanilla_confirm_third"),
}
SHIPPED = CHOSEN  # the checkpoint's own failure check, `joint_phase_time_energy`
LATE = 4  # the last chunks of the window that the `late` readings average


@dataclass(frozen=True)
class Training:
    """How E_s is fitted (`fit_success_energy`: batch 128, AdamW at 1e-3, 30 epochs): which negatives."""

    negatives: str = "both"  # "both", "other contexts" or "noise"
    seed: int = 0
    # The noisy copies' std in standardized units: the first choice's 1.0 (the package's NOISE is 0.5 since the
    # sixth test).
    noise: float = 1.0

    @property
    def fit_kwargs(self) -> dict:
        """`fit_success_energy`'s negatives: 0 of a kind leaves it out."""
        return {
            "other_contexts": 0 if self.negatives == "noise" else NEGATIVES,
            "noisy_copies": 0 if self.negatives == "other contexts" else NEGATIVES // 2,
            "noise": self.noise,
        }


TRAININGS = {
    "other contexts and noise": Training(),
    "other contexts only": Training(negatives="other contexts"),
    "noise only": Training(negatives="noise"),
    # The sixth test's (libero_runs.md, "Narrower noisy copies, and a sixth set"), chosen on the five read sets.
    "other contexts and noise at 0.5": Training(noise=0.5),
}
# The trainings `choose` compared on K's three read sets.
FIRST_CHOICE = ("other contexts and noise", "other contexts only", "noise only")
# How a rollout's E_s (and, for the last, the three terms of `joint_phase_time_energy`) is read over its first
# `CHUNKS` chunks.
READINGS = {
    "E_s, mean": "mean",
    f"E_s, mean of the last {LATE}": "late",
    "E_s, z at each chunk index, mean": "z",
    "E_s's z beside the three terms": "four",
}


def contexts(episode: Episode) -> tuple[np.ndarray, np.ndarray]:
    """The episode's pooled contexts (T, D) and chunk indices (T,)."""
    if any(record.context_feature is None for record in episode):
        raise ValueError(
            "E_s reads each chunk's pooled context (`ebvla-eval --record_context_features=true`)."
        )
    return (
        np.stack([r.context_feature for r in episode]).astype(np.float32),
        np.array([r.chunk_index for r in episode]),
    )


def success_series(model: SuccessEnergy, episode: Episode) -> np.ndarray:
    """The episode's E_s, indexed by chunk index."""
    features, index = contexts(episode)
    return energies_by_index(model.series(features, index), index)


@dataclass
class Fitted:
    """E_s fitted on all successful calibration rollouts (`full`) and each calibration rollout's series, read by an
    E_s that never saw it."""

    full: SuccessEnergy
    folds: list[SuccessEnergy]
    calibration_series: dict


def read_calibration(calibration: dict, full: SuccessEnergy, folds: list[SuccessEnergy], seed: int) -> Fitted:
    """Each successful calibration rollout read by the E_s of the fold that left it out (`fold_order`), the rest by
    `full`."""
    successful = [key for key, e in calibration.items() if e[0].success]
    series = {}
    for fold, model in zip(fold_order(len(successful), seed), folds, strict=True):
        series.update({successful[i]: success_series(model, calibration[successful[i]]) for i in fold})
    series.update({key: success_series(full, e) for key, e in calibration.items() if key not in series})
    return Fitted(full, folds, series)


def cross_fit(calibration: dict, training: Training) -> Fitted:
    """The package's fit and cross-fitting (`fit_success_energy`, `fold_readers`) with `training`'s negatives."""
    successful = [contexts(e) for e in calibration.values() if e[0].success]
    readers = fold_readers(successful, training.seed, **training.fit_kwargs)
    folds = [readers[fold[0]] for fold in fold_order(len(successful), training.seed)]
    full = fit_success_energy(successful, training.seed, **training.fit_kwargs)
    return read_calibration(calibration, full, folds, training.seed)


def scores(fitted: Fitted, calibration: dict, held_out: dict, reading: str, phase=None, n: int = CHUNKS):
    """(every calibration rollout's score, a successful one against statistics without it; the held-out rollouts'
    scores), as `rows_against_baseline` reads them."""
    successful = [key for key, e in calibration.items() if e[0].success]
    held_series = {key: success_series(fitted.full, e) for key, e in held_out.items()}
    if reading in ("mean", "late"):

        def read(series: np.ndarray) -> float:
            values, _ = first_chunks(series, n)
            return float(np.mean(values[-LATE:] if reading == "late" else values))

        return (
            np.array([read(fitted.calibration_series[key]) for key in calibration]),
            np.array([read(s) for s in held_series.values()]),
        )
    episodes = {**calibration, **held_out}
    terms = {key: ([] if reading == "z" else term_series(e, phase)) for key, e in episodes.items()}
    series = {**fitted.calibration_series, **held_series}

    def statistics(leave_out=None) -> list[PhaseStatistics]:
        kept = [[*terms[key], series[key]] for key in successful if key != leave_out]
        return [PhaseStatistics.fit([r[i] for r in kept]) for i in range(len(kept[0]))]

    def read(key, stats) -> float:
        z = []
        for values, phase_statistics in zip([*terms[key], series[key]], stats, strict=True):
            kept, index = first_chunks(values, n)
            z.append(phase_statistics.z(kept, index).mean())
        return float(np.mean(z))

    everyone = statistics()
    return (
        np.array([read(key, statistics(key) if key in successful else everyone) for key in calibration]),
        np.array([read(key, everyone) for key in held_out]),
    )


def set_rows(values: dict, calibration: dict, held_out: dict) -> list[dict]:
    """`rows_against_baseline` of {name: (calibration scores, held-out scores)} with the baseline added."""
    successful = np.array([e[0].success for e in calibration.values()])
    failed = np.array([not e[0].success for e in held_out.values()])
    values = {**values, BASELINE: scores_at(BASELINE, calibration, held_out, CHUNKS)}
    return rows_against_baseline(values, successful, failed, K)


def load(paths) -> dict:
    return load_episodes([str(Path(p) / "task*") for p in paths])


def choose(threads: int = 1) -> dict:
    """Every training and reading on K's three read sets, and the choice: the reading whose worst set's AUROC minus
    the baseline's is highest, among those at a balanced accuracy of at least 80 % on each set."""
    torch.set_num_threads(threads)
    calibration = load([CALIBRATION])
    phase = load_phase_energy(K_PHASE)
    sets = {name: load(paths) for name, paths in READ_SETS.items()}
    rows = []
    for training_name in FIRST_CHOICE:
        fitted = cross_fit(calibration, TRAININGS[training_name])
        for reading_name, reading in READINGS.items():
            entry = {"training": training_name, "reading": reading_name, "sets": {}}
            for set_name, held in sets.items():
                found, baseline = set_rows(
                    {reading_name: scores(fitted, calibration, held, reading, phase)}, calibration, held
                )
                entry["sets"][set_name] = {**found, "baseline_auroc": baseline["auroc"]}
            entry["worst_difference"] = min(s["auroc_minus_baseline"] for s in entry["sets"].values())
            entry["eligible"] = all(s["balanced_accuracy"] >= 0.8 for s in entry["sets"].values())
            rows.append(entry)
            print(
                training_name,
                "|",
                reading_name,
                f"{entry['worst_difference']:+.4f}",
                entry["eligible"],
                flush=True,
            )
    eligible = [r for r in rows if r["eligible"]]
    chosen = max(eligible, key=lambda r: r["worst_difference"])
    return {
        "trainings": {name: asdict(TRAININGS[name]) for name in FIRST_CHOICE},
        "rows": rows,
        "chosen": {"training": chosen["training"], "reading": chosen["reading"]},
    }


def choice_markdown(result: dict) -> str:
    names = list(READ_SETS)
    lines = [
        "Development on K's three read sets (T = mu + 1 sigma of the successful calibration rollouts; first "
        f"{CHUNKS} chunks): AUROC [paired interval minus `{BASELINE}`], failed and successful alarmed.",
        "",
        "| training | reading | " + " | ".join(names) + " | worst minus baseline |",
        "|---|---|" + "---|" * len(names) + "---:|",
    ]
    for r in result["rows"]:
        cells = []
        for name in names:
            s = r["sets"][name]
            low, high = s["auroc_minus_baseline_interval"]
            cells.append(
                f"{s['auroc']:.3f} [{low:+.3f}, {high:+.3f}], {s['failed_alarmed']}/{s['failed']} and "
                f"{s['successful_alarmed']}/{s['successful']}, {s['balanced_accuracy']:.1%}"
            )
        mark = "" if r["eligible"] else " (under 80 % somewhere)"
        lines.append(
            f"| {r['training']} | {r['reading']}{mark} | "
            + " | ".join(cells)
            + f" | {r['worst_difference']:+.4f} |"
        )
    first = result["rows"][0]["sets"]
    lines.append(
        f"| `{BASELINE}` | | " + " | ".join(f"{first[n]['baseline_auroc']:.3f}" for n in names) + " | |"
    )
    chosen = result["chosen"]
    lines += ["", f"Chosen: **{chosen['training']}**, read as **{chosen['reading']}**.", ""]
    return "\n".join(lines)


def test(
    held_out_paths: list[str],
    training_name: str,
    reading_name: str,
    threads: int = 1,
    fitted: Fitted | None = None,
    calibration_path: Path = CALIBRATION,
    phase_path: Path | None = K_PHASE,
) -> tuple[dict, Fitted]:
    """The chosen reading on each held-out set and on all of them, with the checkpoint's shipped check
    (`joint_phase_time_energy`, when its E_tau is given), `joint_phase_energy` and the baseline beside it, and its
    caught failures' leads; E_s fitted on `calibration_path`'s rollouts as `training_name` says unless `fitted` is
    given."""
    torch.set_num_threads(threads)
    calibration = load([calibration_path])
    phase = None if phase_path is None else load_phase_energy(phase_path)
    if fitted is None:
        fitted = cross_fit(calibration, TRAININGS[training_name])
    held_sets = {Path(p).name: load([p]) for p in held_out_paths}
    held_sets["all held out"] = {key: e for s in held_sets.values() for key, e in s.items()}
    successful = np.array([e[0].success for e in calibration.values()])
    result = {"training": training_name, "reading": reading_name, "chunks": CHUNKS, "k": K, "sets": {}}
    result["calibration_rollouts"], result["calibration_failed"] = (
        int(successful.size),
        int((~successful).sum()),
    )
    for name, held in held_sets.items():
        values = {reading_name: scores(fitted, calibration, held, READINGS[reading_name], phase)}
        if phase is not None:
            values[SHIPPED] = joint_phase_time_scores(calibration, held, phase, CHUNKS)[:2]
        values["joint_phase_energy"] = scores_at("joint_phase_energy", calibration, held, CHUNKS)
        rows = set_rows(values, calibration, held)
        result["sets"][name] = {
            "rollouts": len(held),
            "failed": int(sum(not e[0].success for e in held.values())),
            "rows": rows,
            "leads": leads(list(held.values()), values[reading_name][1], rows[0]["threshold"], CHUNKS),
        }
    chosen = result["sets"]["all held out"]["rows"][0]
    result["met"] = bool(
        chosen["balanced_accuracy"] >= MIN_BALANCED_ACCURACY
        and chosen["auroc_minus_baseline_interval"][1] >= 0
    )
    return result, fitted


def test_markdown(result: dict) -> str:
    chosen = result["sets"]["all held out"]["rows"][0]
    low, high = chosen["auroc_minus_baseline_interval"]
    targets = [
        (
            f"balanced accuracy >= {MIN_BALANCED_ACCURACY:.0%}",
            chosen["balanced_accuracy"] >= MIN_BALANCED_ACCURACY,
            f"{chosen['balanced_accuracy']:.1%}",
        ),
        (
            f"not below {BASELINE} outside the paired interval",
            high >= 0,
            f"{chosen['auroc_minus_baseline']:+.3f} [{low:+.3f}, {high:+.3f}]",
        ),
    ]
    head = f"E_s trained as **{result['training']}**, read as **{result['reading']}**.\n\n"
    return head + report_markdown(
        result["reading"],
        result["chunks"],
        result["k"],
        result,
        targets,
        lambda found: difference_lines(found["rows"], lambda name: f"`{name}`"),
    )


def save_models(fitted: Fitted, path: Path) -> None:
    state = {f"full.{k}": v for k, v in fitted.full.state_dict().items()}
    for number, model in enumerate(fitted.folds):
        state.update({f"fold{number}.{k}": v for k, v in model.state_dict().items()})
    save_file(state, path)


def load_fitted(path: Path, calibration: dict, seed: int = 0) -> Fitted:
    """The E_s that `test` saved (on all, and one per fold), reading `calibration` as `cross_fit` did."""
    state = load_file(path)

    def model(name: str) -> SuccessEnergy:
        return SuccessEnergy.from_state(
            {k.removeprefix(f"{name}."): v for k, v in state.items() if k.startswith(f"{name}.")}
        )

    return read_calibration(calibration, model("full"), [model(f"fold{i}") for i in range(FOLDS)], seed)


def package_check(
    held_out_paths: list[str],
    fitted_path: Path,
    checkpoint: Path,
    ood_path: Path,
    work: Path,
    calibration_path: Path = CALIBRATION,
    threads: int = 1,
) -> dict:
    """The package's route on the same rollouts, a check of the code: `ebvla-ood-report --calibrate_to` with
    `--failure_score=success_energy` on a copy of `checkpoint` (its config's failure check set to it) and
    `calibration_path`'s rollouts; its E_s against the one `fitted_path` holds, its T against the research reading's,
    and every held-out rollout's score and decision against the research reading's."""
    torch.set_num_threads(threads)
    copy = work / "checkpoint"
    if not copy.exists():
        shutil.copytree(checkpoint, copy)
        config = json.loads((copy / "config.json").read_text())
        config["monitor"]["failure_score"] = "success_energy"
        (copy / "config.json").write_text(json.dumps(config, indent=4))
    if not (copy / FAILURE_CALIBRATION_FILENAME).exists():
        write_ood_report(
            OODReportConfig(
                calibration=[str(calibration_path / "task*")],
                vanilla=[f"{p}/task*" for p in held_out_paths],
                ood=[str(ood_path / "task*")],
                output_dir=work / "report",
                calibrate_to=copy,
                overwrite_calibration=True,
                failure_score="success_energy",
                failure_chunks=CHUNKS,
                failure_reference="successful",
                n_bootstrap=200,
            )
        )
    return compare_package(
        FailureCalibration.from_pretrained(copy), held_out_paths, fitted_path, calibration_path
    )


def compare_package(package, held_out_paths, fitted_path: Path, calibration_path: Path = CALIBRATION) -> dict:
    """The package's saved failure check against the research reading with the E_s of `fitted_path`."""
    calibration = load([calibration_path])
    fitted = load_fitted(fitted_path, calibration)
    ours = fitted.full.state_dict()
    theirs = package.score.energy.state_dict()
    difference = max(float((ours[k] - theirs[k]).abs().max()) for k in ours)
    held = load(held_out_paths)
    calibration_scores, research_scores = scores(fitted, calibration, held, "late")
    successful = np.array([e[0].success for e in calibration.values()])
    reference = calibration_scores[successful]
    research_threshold = float(reference.mean() + K * reference.std())
    package_scores = np.array(
        [package.score_rollout(package.chunk_components(episode_readout(e))[:CHUNKS]) for e in held.values()]
    )
    failed = np.array([not e[0].success for e in held.values()])
    alarms = {
        "package": package_scores > package.threshold,
        "research": research_scores > research_threshold,
    }
    return {
        "max_weight_difference": difference,
        "threshold": {"package": package.threshold, "research": research_threshold},
        "max_score_difference": float(np.abs(package_scores - research_scores).max()),
        "same_decisions": int((alarms["package"] == alarms["research"]).sum()),
        "rollouts": len(held),
        "alarmed": {
            name: {"failed": int(a[failed].sum()), "successful": int(a[~failed].sum())}
            for name, a in alarms.items()
        },
        "aggregation": package.aggregation,
        "chunks": package.chunks,
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    commands = parser.add_subparsers(dest="command", required=True)
    chooser = commands.add_parser("choose", help="every training and reading on K's three read sets")
    packaged = commands.add_parser(
        "package", help="the package's route (`ebvla-ood-report`) on the same rollouts"
    )
    packaged.add_argument("--held_out", nargs="+", required=True)
    packaged.add_argument("--fitted", type=Path, required=True, help="the E_s a `test` saved")
    packaged.add_argument(
        "--checkpoint", type=Path, required=True, help="K's fitted checkpoint (or another one: --calibration)"
    )
    packaged.add_argument(
        "--calibration", type=Path, default=CALIBRATION, help="the checkpoint's calibration records' folder"
    )
    packaged.add_argument(
        "--ood", type=Path, default=K_EVAL / "light_dim5", help="perturbed rollouts the report needs"
    )
    packaged.add_argument("--work", type=Path, required=True)
    tester = commands.add_parser("test", help="the chosen reading on new held-out sets")
    tester.add_argument("--held_out", nargs="+", required=True, help="held-out record folders, one per set")
    tester.add_argument("--training", default=None, help="default: the choice's (--choice)")
    tester.add_argument("--reading", default=None)
    tester.add_argument("--choice", type=Path, default=None, help="`choose`'s JSON")
    tester.add_argument(
        "--calibration", type=Path, default=CALIBRATION, help="the calibration records' folder"
    )
    tester.add_argument(
        "--fitted",
        type=Path,
        default=None,
        help="E_s saved by an earlier `test` (its .safetensors): read with it instead of refitting",
    )
    tester.add_argument(
        "--phase_energy",
        default=str(K_PHASE),
        help="the checkpoint's E_tau, or 'none' (no shipped check's row)",
    )
    for command in (chooser, tester, packaged):
        command.add_argument("--threads", type=int, default=1)
        command.add_argument("--output", type=Path, default=None)
    args = parser.parse_args(argv)
    if args.command == "choose":
        result = choose(args.threads)
        write_report(result, choice_markdown(result), args.output)
        return
    if args.command == "package":
        result = package_check(
            args.held_out,
            args.fitted,
            args.checkpoint,
            args.ood,
            args.work,
            args.calibration,
            threads=args.threads,
        )
        write_report(result, json.dumps(result, indent=1), args.output)
        return
    chosen = {} if args.choice is None else json.loads(args.choice.read_text())["chosen"]
    training, reading = args.training or chosen.get("training"), args.reading or chosen.get("reading")
    if training is None or reading is None:
        parser.error("give --choice, or --training and --reading")
    phase = None if args.phase_energy == "none" else Path(args.phase_energy)
    fitted = None
    if args.fitted is not None:
        fitted = load_fitted(args.fitted, load([args.calibration]), TRAININGS[training].seed)
    result, fitted = test(args.held_out, training, reading, args.threads, fitted, args.calibration, phase)
    write_report(result, test_markdown(result), args.output)
    if args.output is not None and args.fitted is None:  # E_s read from a file is not saved again
        save_models(fitted, args.output.with_suffix(".safetensors"))


if __name__ == "__main__":
    main()
