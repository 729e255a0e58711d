"""How much of a rollout's outcome its first chunks carry at all (issue 32, "failed vs successful >= 0.75").

The energies score failed against successful rollouts at 0.43-0.64 over the first 3 chunks. Is that the energy, or
is the outcome simply not decided yet when the first chunks run? This asks a supervised probe: an L2-regularized
logistic regression on what the policy itself saw, the pooled backbone context C_L of each of the first chunks
(averaged) and their final energies, labelled by the rollout's success. It is an upper-bound style reading, not a
monitor: it is fitted on outcomes.

- **within vanilla**: stratified k-fold cross-validation over the sweep's vanilla and calibration rollouts;
- **all rollouts**: the same over every rollout of the sweep (vanilla, calibration, every condition): the probe
  also learns which conditions fail, so this is in-sample over the conditions;
- **vanilla -> perturbed**: fitted on the vanilla and calibration rollouts (the outcomes a user has after
  calibrating), scored on every perturbed rollout, as a deployed failure predictor would be.

Each figure is the AUROC of failed (positive) against successful rollouts, the probe's score being -logit
P(success); cross-validated figures are the mean over repeats of the pooled out-of-fold scores.

    python research/benchmarks/outcome_probe.py --runs s1000=RUN/records s2000=... --output=probe.md
"""

import argparse
from pathlib import Path

import numpy as np
import torch
from energy_margin_report import emit, episodes

from lerobot_policy_ebvla.monitoring.metrics import auroc, bootstrap_auroc_interval
from lerobot_policy_ebvla.monitoring.records import records_file_in

# The sweep's folders whose outcomes a user has before deployment.
VANILLA_FOLDERS = ("vanilla", "calibration")


def rollout_features(episode: list, chunks: int) -> np.ndarray:
    """The mean pooled context of the first `chunks` chunks, then their final energies."""
    first = episode[:chunks]
    context = np.stack([r.context_feature for r in first]).mean(axis=0)
    return np.concatenate([context, [r.final_energy for r in first]])


def sweep_rollouts(folder: Path, chunks: int) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """(features, succeeded) of the rollouts in each of a sweep's folders that recorded context features."""
    out = {}
    for sub in sorted(p for p in folder.iterdir() if p.is_dir() and records_file_in(p) is not None):
        eps = [ep for ep in episodes(sub) if len(ep) >= chunks and ep[0].context_feature is not None]
        if eps:
            out[sub.name] = (
                np.stack([rollout_features(ep, chunks) for ep in eps]),
                np.array([ep[0].success for ep in eps], dtype=bool),
            )
    return out


def failure_scores(train_x: np.ndarray, succeeded: np.ndarray, test_x: np.ndarray, l2: float) -> np.ndarray:
    """-logit P(success) of `test_x` under a logistic regression on standardized `train_x` (L2 weight `l2`,
    full-batch L-BFGS in float64: deterministic for given data)."""
    mean, std = train_x.mean(axis=0), train_x.std(axis=0) + 1e-6
    x = torch.tensor((train_x - mean) / std, dtype=torch.float64)
    y = torch.tensor(succeeded, dtype=torch.float64)
    weight = torch.zeros(x.shape[1], dtype=torch.float64, requires_grad=True)
    bias = torch.zeros(1, dtype=torch.float64, requires_grad=True)
    optimizer = torch.optim.LBFGS([weight, bias], max_iter=200, line_search_fn="strong_wolfe")

    def loss() -> torch.Tensor:
        optimizer.zero_grad()
        value = torch.nn.functional.binary_cross_entropy_with_logits(x @ weight + bias, y)
        value = value + l2 * weight.pow(2).sum()
        value.backward()
        return value

    optimizer.step(loss)
    test = torch.tensor((test_x - mean) / std, dtype=torch.float64)
    return -(test @ weight + bias).detach().numpy()


def failure_auroc(scores: np.ndarray, succeeded: np.ndarray) -> float:
    return auroc(scores[succeeded], scores[~succeeded])


def cross_validated(x: np.ndarray, succeeded: np.ndarray, l2: float, folds: int, repeats: int) -> float:
    """The mean over `repeats` shuffles of the AUROC of the out-of-fold scores of a stratified `folds`-fold split."""
    values = []
    for repeat in range(repeats):
        rng = np.random.default_rng(repeat)
        fold = np.empty(len(succeeded), dtype=int)
        for label in (False, True):
            members = rng.permutation(np.flatnonzero(succeeded == label))
            fold[members] = np.arange(len(members)) % folds
        scores = np.empty(len(succeeded))
        for k in range(folds):
            held = fold == k
            scores[held] = failure_scores(x[~held], succeeded[~held], x[held], l2)
        values.append(failure_auroc(scores, succeeded))
    return float(np.mean(values))


def vanilla_and_perturbed(folder: Path, chunks: int) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
    """(features, succeeded) of a sweep's vanilla and calibration rollouts, and of its perturbed ones."""
    rollouts = sweep_rollouts(folder, chunks)
    sides = (
        [rollouts[name] for name in VANILLA_FOLDERS if name in rollouts],
        [rollouts[name] for name in rollouts if name not in VANILLA_FOLDERS],
    )
    return tuple(
        (np.concatenate([x for x, _ in side]), np.concatenate([s for _, s in side])) for side in sides
    )


def transfer(vanilla: tuple, perturbed: tuple, l2: float) -> tuple[float, tuple[float, float]]:
    """The probe fitted on the vanilla rollouts, its AUROC on the perturbed ones, with a bootstrap interval."""
    scores = failure_scores(*vanilla, perturbed[0], l2)
    succeeded = perturbed[1]
    return failure_auroc(scores, succeeded), bootstrap_auroc_interval(scores[succeeded], scores[~succeeded])


def counts(side: tuple[np.ndarray, np.ndarray]) -> tuple[int, int]:
    """n rollouts and how many failed."""
    return len(side[1]), int((~side[1]).sum())


def probe_row(folder: Path, chunks: int, l2: float, folds: int = 5, repeats: int = 5) -> dict[str, tuple]:
    """A sweep's three probe readings (module docstring), each with n and failures."""
    vanilla, perturbed = vanilla_and_perturbed(folder, chunks)
    everything = tuple(np.concatenate([v, p]) for v, p in zip(vanilla, perturbed, strict=True))
    value, interval = transfer(vanilla, perturbed, l2)
    return {
        "within vanilla": (cross_validated(*vanilla, l2, folds, repeats), *counts(vanilla)),
        "all rollouts": (cross_validated(*everything, l2, folds, repeats), *counts(everything)),
        "vanilla -> perturbed": (value, *counts(perturbed), interval),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", nargs="+", required=True, help="name=folder of sweep records")
    parser.add_argument("--chunks", type=int, default=3)
    parser.add_argument("--l2", type=float, default=0.01)
    parser.add_argument("--output", type=Path)
    args = parser.parse_args()
    lines = [
        "| run | within vanilla, 5-fold CV (n, failed) | all rollouts, CV (n, failed) | "
        "fitted on vanilla, scored on perturbed [95%] (n, failed) |",
        "|---|---|---|---|",
    ]
    for name, folder in (item.split("=", 1) for item in args.runs):
        row = probe_row(Path(folder), args.chunks, args.l2)
        (wv, wn, wf), (av, an, af) = row["within vanilla"], row["all rollouts"]
        tv, tn, tf, (low, high) = row["vanilla -> perturbed"]
        lines.append(
            f"| {name} | {wv:.2f} ({wn}, {wf}) | {av:.2f} ({an}, {af}) | {tv:.2f} [{low:.2f}, {high:.2f}] ({tn}, {tf}) |"
        )
    emit(lines, args.output)


if __name__ == "__main__":
    main()
