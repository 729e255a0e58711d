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
from pathlib import Path

import numpy as np
import torch
from failure_check_test import BASELINE, MIN_BALANCED_ACCURACY, leads, report_markdown, scores_at, write_report
from failure_score_variants import difference_lines, rows_against_baseline
from safetensors.torch import load_file, save_file
from torch import nn

from lerobot_policy_ebvla.monitoring.records import Episode, load_episodes
from lerobot_policy_ebvla.runtime.statistics import PhaseStatistics, energies_by_index

CHOSEN = "joint_phase_time_energy"
SHIPPED = "joint_phase_energy"
CHUNKS = 16
K = 1.0
# Chunk bins of p(t | C): the demonstrations end within 40 chunks (320 steps); later chunks share the last bin.
PHASE_BINS = 40
FRAME_STRIDE = 8
HIDDEN = 256
MAX_EPOCHS = 40
VALIDATION_FRACTION = 0.1


def demonstration_contexts(checkpoint: str, dataset_root: str, batch_size: int = 64) -> dict[str, np.ndarray]:
    """The pooled context of every demonstration frame at a multiple of `FRAME_STRIDE`, with its chunk index,
    episode and task, computed as the policy computes it in a rollout (its preprocessor, then `context_features`)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.policies.factory import make_pre_post_processors

    from lerobot_policy_ebvla import EBVLAPolicy

    policy = EBVLAPolicy.from_pretrained(checkpoint).eval()
    preprocessor, _ = make_pre_post_processors(policy.config, pretrained_path=checkpoint)
    dataset = LeRobotDataset("local/demonstrations", root=dataset_root)
    frame = np.asarray(dataset.hf_dataset["frame_index"])
    rows = np.nonzero(frame % FRAME_STRIDE == 0)[0]
    keys = list(policy.config.input_features)
    features = []
    for start in range(0, len(rows), batch_size):
        items = [dataset[int(i)] for i in rows[start : start + batch_size]]
        batch = {key: torch.stack([item[key] for item in items]) for key in keys}
        batch["task"] = [item["task"] for item in items]
        with torch.no_grad():
            features.append(policy.context_features(preprocessor(batch)).float().numpy())
    return {
        "features": np.concatenate(features),
        "chunk": frame[rows] // FRAME_STRIDE,
        "episode": np.asarray(dataset.hf_dataset["episode_index"])[rows],
        "task": np.asarray(dataset.hf_dataset["task_index"])[rows],
    }


class PhaseEnergy(nn.Module):
    """E_tau(C, t) = -log softmax_t(-f(C)): how unlikely chunk index t is for a demonstration with pooled context C."""

    def __init__(self, dim: int, mean: np.ndarray, std: np.ndarray):
        super().__init__()
        self.register_buffer("mean", torch.as_tensor(mean, dtype=torch.float32))
        self.register_buffer("std", torch.as_tensor(std, dtype=torch.float32))
        self.f = nn.Sequential(
            nn.Linear(dim, HIDDEN), nn.GELU(), nn.Linear(HIDDEN, HIDDEN), nn.GELU(), nn.Linear(HIDDEN, PHASE_BINS)
        )

    def logits(self, features: torch.Tensor) -> torch.Tensor:
        return -self.f((features - self.mean) / self.std)

    def forward(self, features: np.ndarray, chunks: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            log_p = torch.log_softmax(self.logits(torch.as_tensor(features, dtype=torch.float32)), -1).numpy()
        return -log_p[np.arange(len(chunks)), np.minimum(chunks, PHASE_BINS - 1)]


def _fit(contexts: dict, rows: np.ndarray, epochs: int, held: np.ndarray | None) -> tuple[PhaseEnergy, list]:
    torch.manual_seed(0)
    x = contexts["features"]
    model = PhaseEnergy(x.shape[1], x.mean(0), x.std(0) + 1e-6)
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-3, weight_decay=1e-2)
    labels = torch.as_tensor(np.minimum(contexts["chunk"], PHASE_BINS - 1))
    inputs = torch.as_tensor(x, dtype=torch.float32)
    train = torch.as_tensor(rows)
    validation_nll = []
    for _ in range(epochs):
        for batch in train[torch.randperm(len(train))].split(256):
            loss = nn.functional.cross_entropy(model.logits(inputs[batch]), labels[batch])
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
        if held is not None:
            with torch.no_grad():
                validation_nll.append(
                    nn.functional.cross_entropy(model.logits(inputs[held]), labels[held]).item()
                )
    return model, validation_nll


def train_phase_energy(contexts: dict) -> tuple[PhaseEnergy, dict]:
    """E_tau trained on all demonstrations for the number of epochs at which a held-out tenth of the
    demonstrations (whole episodes) had its lowest negative log-likelihood."""
    episodes = np.unique(contexts["episode"])
    rng = np.random.default_rng(0)
    validation = rng.choice(episodes, max(1, int(len(episodes) * VALIDATION_FRACTION)), replace=False)
    held = np.isin(contexts["episode"], validation)
    _, curve = _fit(contexts, np.nonzero(~held)[0], MAX_EPOCHS, np.nonzero(held)[0])
    epochs = int(np.argmin(curve)) + 1
    model, _ = _fit(contexts, np.arange(len(held)), epochs, None)
    return model.eval(), {"validation_nll": curve, "epochs": epochs, "frames": int(len(held))}


def phase_series(episode: Episode, model: PhaseEnergy) -> np.ndarray:
    """The episode's E_tau, indexed by chunk index."""
    index = np.array([record.chunk_index for record in episode])
    if any(record.context_feature is None for record in episode):
        raise ValueError("The phase energy reads each chunk's pooled context (`--record_context_features=true`).")
    return energies_by_index(model(np.stack([r.context_feature for r in episode]), index), index)


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


def test(calibration: dict, held_out_sets: dict, model: PhaseEnergy, n: int = CHUNKS, k: float = K) -> dict:
    """Every row of every held-out set and of all of them together, at T of the successful calibration rollouts."""
    successful = np.array([episode[0].success for episode in calibration.values()])
    sets = {**held_out_sets, "all held out": {key: e for s in held_out_sets.values() for key, e in s.items()}}
    result = {"chosen": CHOSEN, "chunks": n, "k": k, "calibration_rollouts": int(successful.size)}
    result["calibration_failed"] = int((~successful).sum())
    result["sets"] = {}
    for title, held_out in sets.items():
        failed = np.array([not episode[0].success for episode in held_out.values()])
        calibration_scores, held_scores, _ = joint_phase_time_scores(calibration, held_out, model, n)
        values = {
            CHOSEN: (calibration_scores, held_scores),
            SHIPPED: scores_at(SHIPPED, calibration, held_out, n),
            BASELINE: scores_at(BASELINE, calibration, held_out, n),
        }
        rows = rows_against_baseline(values, successful, failed, k)
        chosen = next(r for r in rows if r["score"] == CHOSEN)
        result["sets"][title] = {
            "rollouts": int(failed.size),
            "failed": int(failed.sum()),
            "rows": rows,
            "leads": leads(list(held_out.values()), held_scores, chosen["threshold"], n),
        }
    return result


def targets(result: dict) -> list[tuple[str, bool, str]]:
    """The fixed reading on all held-out rollouts together: (target, met, figures)."""
    rows = {r["score"]: r for r in result["sets"]["all held out"]["rows"]}
    chosen, shipped = rows[CHOSEN], rows[SHIPPED]
    low, high = chosen["auroc_minus_baseline_interval"]
    return [
        (
            f"balanced accuracy >= {MIN_BALANCED_ACCURACY:.0%}",
            chosen["balanced_accuracy"] >= MIN_BALANCED_ACCURACY,
            f"{chosen['balanced_accuracy']:.1%}",
        ),
        (
            f"AUROC above {SHIPPED}'s",
            chosen["auroc"] > shipped["auroc"],
            f"{chosen['auroc']:.3f} against {shipped['auroc']:.3f}",
        ),
        (
            f"not below {BASELINE} outside the paired interval",
            high >= 0,
            f"{chosen['auroc_minus_baseline']:+.3f} [{low:+.3f}, {high:+.3f}]",
        ),
    ]


def markdown(result: dict) -> str:
    training = result["phase_energy"]
    head = (
        f"E_tau trained {training['epochs']} epochs on {training['frames']} demonstration frames "
        f"(held-out demonstrations' lowest NLL {min(training['validation_nll']):.4f}).\n\n"
    )
    return head + report_markdown(
        CHOSEN,
        result["chunks"],
        result["k"],
        result,
        targets(result),
        lambda found: difference_lines(found["rows"], lambda name: f"`{name}`"),
    )


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)
    contexts = commands.add_parser("contexts", help="the demonstrations' pooled contexts under a checkpoint")
    contexts.add_argument("--checkpoint", required=True)
    contexts.add_argument("--dataset", required=True, help="the LeRobot dataset's root folder")
    contexts.add_argument("--output", type=Path, required=True)
    check = commands.add_parser("check", help="train E_tau on the contexts and test the reading")
    check.add_argument("--contexts", type=Path, required=True)
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
    model, training = train_phase_energy(dict(np.load(args.contexts)))
    calibration = load_episodes([args.calibration])
    held_out_sets = {Path(pattern).parent.name: load_episodes([pattern]) for pattern in args.held_out}
    result = test(calibration, held_out_sets, model, args.chunks)
    result["phase_energy"] = training
    write_report(result, markdown(result), args.output)
    if args.output is not None:
        save_file(model.state_dict(), args.output.with_suffix(".safetensors"))


def load_phase_energy(path: Path) -> PhaseEnergy:
    """E_tau as `check` saved it beside its report."""
    state = load_file(path)
    model = PhaseEnergy(state["mean"].numel(), state["mean"].numpy(), state["std"].numpy())
    model.load_state_dict(state)
    return model.eval()


if __name__ == "__main__":
    main()
