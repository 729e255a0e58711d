"""A phase energy beside the joint energy's two terms: the test of `joint_phase_time_energy` (issue 52, Table IV;
research/docs/libero_runs.md, "A phase energy for the failure check", where the reading was chosen on G's rollouts
and this test fixed before K's were read by it).

The feature distance `chunk_context_nn` knows where in the task a rollout is: at chunk 16 it compares the context with
the successful rollouts' contexts *at chunk 16*. A per-chunk scalar of E_c or E - E_c does not: a rollout that never
grasps looks familiar to both at every chunk. The phase energy asks the backbone's context itself when in an episode
it belongs:

    E_tau(C, t) = -log p(t | C),   p(t | C) = softmax_t(-f(C))_t,

f an MLP on the pooled last-block context C (`EBVLAPolicy.context_features`), trained with cross-entropy on the
policy's **training demonstrations** (each frame every 8 steps, t = its chunk index, frame_index // 8), never on a
rollout. A stalled rollout at chunk t holds a context the demonstrations show at an earlier t, so its E_tau rises.

The reading: at each chunk index the z of E_c, of E - E_c and of E_tau against the successful calibration rollouts
(`PhaseStatistics`), one-sided, averaged over the first 16 chunks and the three terms; a calibration rollout is
scored against statistics fitted without it; T = mu + 1 sigma of the successful calibration rollouts' scores.

    # once per checkpoint: the demonstrations' pooled contexts (about 5 minutes on two cores)
    python research/benchmarks/phase_energy_failure_check.py contexts --checkpoint=<pretrained_model> \\
        --dataset=outputs/libero10_b18/data/all --output=<run's reports>/phase_energy/demonstration_contexts.npz
    # train E_tau on them and test it (seconds)
    python research/benchmarks/phase_energy_failure_check.py check \\
        --contexts=<...>/demonstration_contexts.npz --calibration='<eval>/vanilla_calib/task*' \\
        --held_out '<eval>/vanilla_heldout/task*' '<eval>/vanilla_confirm/task*' --output=<...>/phase_energy/check.json
"""

import argparse
import dataclasses
from pathlib import Path

import numpy as np
import torch
from failure_check_test import (
    report_markdown,
    row,
    write_report,
)
from failure_score_variants import difference_lines
from safetensors.torch import load_file, save_file
from task_phase_failure_check import reading_targets, test_reading

from lerobot_policy_ebvla.monitoring.baselines import episode_readout, vanilla_rollouts
from lerobot_policy_ebvla.monitoring.records import Episode, load_episodes
from lerobot_policy_ebvla.phase_energy import PhaseEnergy, fit_phase_energy
from lerobot_policy_ebvla.pipelines.phase_energy import demonstration_contexts as package_contexts
from lerobot_policy_ebvla.runtime.calibration import FailureCalibration
from lerobot_policy_ebvla.runtime.statistics import PhaseStatistics, energies_by_index

CHOSEN = "joint_phase_time_energy"
CHUNKS = 16
K = 1.0
# Chunk bins of p(t | C): the demonstrations end within 40 chunks (320 steps); later chunks share the last bin.
PHASE_BINS = 40
HIDDEN = 256


def demonstration_contexts(checkpoint: str, dataset_root: str, batch_size: int = 64) -> dict[str, np.ndarray]:
    """The pooled context of every demonstration frame at a multiple of the policy's `n_action_steps`, with its chunk
    index and episode, as `ebvla-fit-phase-energy` reads them."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.policies.factory import make_pre_post_processors

    from lerobot_policy_ebvla import EBVLAPolicy

    policy = EBVLAPolicy.from_pretrained(checkpoint).eval()
    preprocessor, _ = make_pre_post_processors(policy.config, pretrained_path=checkpoint)
    dataset = LeRobotDataset("local/demonstrations", root=dataset_root)
    return package_contexts(policy, preprocessor, dataset, batch_size)


def train_phase_energy(contexts: dict) -> tuple[PhaseEnergy, dict]:
    """E_tau fitted on the demonstrations' contexts as the package fits it (`fit_phase_energy`)."""
    model = PhaseEnergy(contexts["features"].shape[1], PHASE_BINS, HIDDEN)
    fit = fit_phase_energy(model, contexts["features"], contexts["chunk_index"], contexts["episode"])
    return model.eval(), {
        "validation_nll": list(fit.validation_nll),
        "epochs": fit.epochs,
        "frames": fit.frames,
    }


def phase_series(episode: Episode, model: PhaseEnergy) -> np.ndarray:
    """The episode's E_tau, indexed by chunk index."""
    index = np.array([record.chunk_index for record in episode])
    if any(record.context_feature is None for record in episode):
        raise ValueError(
            "The phase energy reads each chunk's pooled context (`--record_context_features=true`)."
        )
    features = torch.as_tensor(np.stack([r.context_feature for r in episode]), dtype=torch.float32)
    with torch.no_grad():
        values = model(features, torch.as_tensor(index)).numpy()
    return energies_by_index(values, index)


def term_series(episode: Episode, model: PhaseEnergy) -> list[np.ndarray]:
    """E_c, E - E_c and E_tau of the episode, each indexed by chunk index."""
    index = [record.chunk_index for record in episode]
    context = np.array([record.context_energy for record in episode], dtype=float)
    final = np.array([record.final_energy for record in episode], dtype=float)
    return [
        energies_by_index(context, index),
        energies_by_index(final - context, index),
        phase_series(episode, model),
    ]


def first_chunks(series: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    index = np.arange(min(n, len(series)))
    kept = index[~np.isnan(series[index])]
    return series[kept], kept


def joint_phase_time_scores(calibration: dict, episodes: dict, model: PhaseEnergy, n: int):
    """The reading over the first n chunks of the calibration rollouts (each successful one against the statistics
    fitted without it) and of `episodes`: (calibration scores, held-out scores, held-out phase-term scores)."""
    cal_terms = {key: term_series(e, model) for key, e in calibration.items()}
    successful = [key for key, e in calibration.items() if e[0].success]

    def fitted(leave_out=None) -> list[PhaseStatistics]:
        kept = [cal_terms[key] for key in successful if key != leave_out]
        return [PhaseStatistics.fit([terms[i] for terms in kept]) for i in range(3)]

    def score(terms: list[np.ndarray], statistics: list[PhaseStatistics]) -> tuple[float, float]:
        z = []
        for series, phase in zip(terms, statistics, strict=True):
            values, index = first_chunks(series, n)
            z.append(phase.z(values, index).mean())
        return float(np.mean(z)), float(z[2])

    everyone = fitted()
    calibration_scores = np.array(
        [score(cal_terms[key], fitted(key) if key in successful else everyone)[0] for key in calibration]
    )
    held = [score(term_series(e, model), everyone) for e in episodes.values()]
    return calibration_scores, np.array([s for s, _ in held]), np.array([p for _, p in held])


def with_phase_energy(episodes: dict, model: PhaseEnergy) -> dict:
    """The episodes' records with E_tau filled in from their pooled contexts, as a checkpoint with this phase energy
    reports it with each chunk."""
    filled = {}
    for key, episode in episodes.items():
        phase = phase_series(episode, model)
        filled[key] = [dataclasses.replace(r, phase_energy=float(phase[r.chunk_index])) for r in episode]
    return filled


def package_check(calibration: dict, held_out: dict, model: PhaseEnergy, n: int, reading: tuple) -> dict:
    """The package's failure check on the same rollouts: `FailureCalibration.calibrate` of `joint_phase_time_energy`
    on the successful calibration rollouts' first n chunks (E_tau filled in), each held-out rollout's first n chunks
    scored by it; against the reading's (T, held-out scores), how far its threshold and scores are."""
    successful = {key: e for key, e in with_phase_energy(calibration, model).items() if e[0].success}
    failure_check = FailureCalibration.calibrate(CHOSEN, vanilla_rollouts(successful), chunks=n)
    scores = []
    for episode in with_phase_energy(held_out, model).values():
        readout = episode_readout([r for r in episode if r.chunk_index < n] or episode[:1])
        scores.append(failure_check.score_rollout(failure_check.chunk_components(readout)))
    threshold, held_scores = reading
    failed = np.array([not episode[0].success for episode in held_out.values()])
    recorded = [
        abs(r.phase_energy - f.phase_energy)
        for e, filled in zip(held_out.values(), with_phase_energy(held_out, model).values(), strict=True)
        for r, f in zip(e, filled, strict=True)
        if r.phase_energy is not None
    ]
    return {
        "recorded_phase_energy_difference": max(recorded) if recorded else None,
        "threshold": failure_check.threshold,
        "threshold_difference": abs(failure_check.threshold - threshold),
        "max_score_difference": float(np.max(np.abs(np.array(scores) - held_scores))),
        "row": row(CHOSEN, np.array(scores), failure_check.threshold, failed),
    }


def test(calibration: dict, held_out_sets: dict, model: PhaseEnergy, n: int = CHUNKS, k: float = K) -> dict:
    """Every row of every held-out set and of all of them together, at T of the successful calibration rollouts
    (`test_reading`), and the package's failure check on all of them (`package_check`)."""

    def reading(held_out: dict) -> tuple[np.ndarray, np.ndarray]:
        return joint_phase_time_scores(calibration, held_out, model, n)[:2]

    result = test_reading(calibration, held_out_sets, CHOSEN, reading, n, k)
    everyone = {key: e for s in held_out_sets.values() for key, e in s.items()}
    threshold = next(r for r in result["sets"]["all held out"]["rows"] if r["score"] == CHOSEN)["threshold"]
    result["package"] = package_check(calibration, everyone, model, n, (threshold, reading(everyone)[1]))
    return result


def markdown(result: dict) -> str:
    training = result["phase_energy"]
    head = (
        "E_tau loaded as trained.\n\n"
        if training is None
        else f"E_tau trained {training['epochs']} epochs on {training['frames']} demonstration frames "
        f"(held-out demonstrations' lowest NLL {min(training['validation_nll']):.4f}).\n\n"
    )
    package = result["package"]
    shipped = package["row"]
    difference = package["recorded_phase_energy_difference"]
    recorded = (
        ""
        if difference is None
        else f" The held-out records' own `phase_energy` (the policy's, as it ran) is E_tau of their contexts within "
        f"{difference:.1e}."
    )
    tail = (
        f"\nThe package's `FailureCalibration` of `{CHOSEN}` on the same rollouts (its statistics fitted on the first "
        f"{result['chunks']} chunks only, so its sigma floor differs): T = {package['threshold']:.4f} (the reading's "
        f"within {package['threshold_difference']:.1e}), held-out scores within "
        f"{package['max_score_difference']:.1e}; {shipped['failed_alarmed']}/{shipped['failed']} failed and "
        f"{shipped['successful_alarmed']}/{shipped['successful']} successful alarmed, balanced accuracy "
        f"{shipped['balanced_accuracy']:.1%}, AUROC {shipped['auroc']:.3f}.{recorded}\n"
    )
    return (
        head
        + report_markdown(
            CHOSEN,
            result["chunks"],
            result["k"],
            result,
            reading_targets(result, at_least=False),
            lambda found: difference_lines(found["rows"], lambda name: f"`{name}`"),
        )
        + tail
    )


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    commands = parser.add_subparsers(dest="command", required=True)
    contexts = commands.add_parser("contexts", help="the demonstrations' pooled contexts under a checkpoint")
    contexts.add_argument("--checkpoint", required=True)
    contexts.add_argument("--dataset", required=True, help="the LeRobot dataset's root folder")
    contexts.add_argument("--output", type=Path, required=True)
    check = commands.add_parser("check", help="train E_tau on the contexts and test the reading")
    check.add_argument("--contexts", type=Path, default=None, help="demonstration contexts to train E_tau on")
    check.add_argument(
        "--phase_energy",
        type=Path,
        default=None,
        help="a trained E_tau: check.safetensors or a checkpoint's weights",
    )
    check.add_argument("--calibration", required=True, help="the checkpoint's calibration records (a glob)")
    check.add_argument("--held_out", nargs="+", required=True, help="held-out records, one glob per set")
    check.add_argument("--chunks", type=int, default=CHUNKS)
    check.add_argument("--output", type=Path, default=None, help="the result (JSON, .md and E_tau beside it)")
    args = parser.parse_args(argv)
    torch.set_num_threads(2)
    if args.command == "contexts":
        args.output.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(args.output, **demonstration_contexts(args.checkpoint, args.dataset))
        return
    if (args.contexts is None) == (args.phase_energy is None):
        parser.error("give --contexts (to train E_tau) or --phase_energy (a trained one), not both")
    if args.phase_energy is not None:
        model, training = load_phase_energy(args.phase_energy), None
    else:
        contexts = dict(np.load(args.contexts))
        # Contexts saved before the package's fit named the chunk index `chunk`.
        contexts.setdefault("chunk_index", contexts.get("chunk"))
        model, training = train_phase_energy(contexts)
    calibration = load_episodes([args.calibration])
    held_out_sets = {Path(pattern).parent.name: load_episodes([pattern]) for pattern in args.held_out}
    result = test(calibration, held_out_sets, model, args.chunks)
    result["phase_energy"] = training
    write_report(result, markdown(result), args.output)
    if args.output is not None:
        save_file(model.state_dict(), args.output.with_suffix(".safetensors"))


def load_phase_energy(path: Path) -> PhaseEnergy:
    """E_tau as `check` saved it beside its report, or a fitted checkpoint's (its `model.safetensors`)."""
    state = load_file(path)
    prefix = "model.phase_energy."
    if any(key.startswith(prefix) for key in state):
        # The checkpoint stores in bf16 every weight bf16 holds exactly: fp32 again, at no loss.
        state = {
            key.removeprefix(prefix): value.float() if value.is_floating_point() else value
            for key, value in state.items()
            if key.startswith(prefix)
        }
    model = PhaseEnergy(state["feature_mean"].numel(), PHASE_BINS, HIDDEN)
    model.load_state_dict(state)
    return model.eval()


if __name__ == "__main__":
    main()
