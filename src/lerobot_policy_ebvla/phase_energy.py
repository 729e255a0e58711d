"""The phase energy E_tau(C, t) = -log p(t | C): how unlikely it is that a demonstration shows the pooled context C at
chunk index t of its episode (beyond the paper; `PhaseEnergyConfig`).

    p(t | C) = softmax_t(-f(C))_t,   f: an MLP from the standardized pooled context to one energy per chunk bin.

It is an energy over elapsed time, normalized per context, as E_c is one over contexts. On LIBERO a failing
rollout often never grasps: its E_c and E - E_c stay where a successful rollout's were at the start, but at chunk 16
its context is one the demonstrations left behind by chunk 5, so E_tau at t = 16 is high. The monitor's
`joint_phase_time_energy` reads it beside E_c and E - E_c (`runtime/phase_scores.py`); research/docs/libero_runs.md,
"A phase energy for the failure check", measured it on two ten-task checkpoints.

It is fitted once the policy is trained (`fit_phase_energy`, on the training demonstrations' contexts under the
frozen backbone; `ebvla-fit-phase-energy` does it for a checkpoint), never on a rollout.
"""

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor, nn

# The fit's defaults (research/docs/libero_runs.md, "A phase energy for the failure check").
FIT_MAX_EPOCHS = 40
FIT_VALIDATION_FRACTION = 0.1
FIT_BATCH_SIZE = 256
FIT_LR = 1e-3
FIT_WEIGHT_DECAY = 1e-2


class PhaseEnergy(nn.Module):
    """E_tau(C, t) of pooled contexts C (B, D) at chunk indices t; t >= bins reads the last bin.

    The standardization of C (the demonstrations' mean and std) and how many frames it was fitted on are buffers,
    saved with the policy's weights: a module that was never fitted has `fitted_frames` 0 and no energy to give.
    """

    def __init__(self, dim: int, bins: int, hidden: int):
        super().__init__()
        self.bins, self.hidden = bins, hidden
        self.register_buffer("feature_mean", torch.zeros(dim))
        self.register_buffer("feature_std", torch.ones(dim))
        self.register_buffer("fitted_frames", torch.zeros((), dtype=torch.long))
        self.net = nn.Sequential(
            nn.Linear(dim, hidden), nn.GELU(), nn.Linear(hidden, hidden), nn.GELU(), nn.Linear(hidden, bins)
        )

    @property
    def fitted(self) -> bool:
        return bool(self.fitted_frames > 0)

    def log_probabilities(self, features: Tensor) -> Tensor:
        """(B, bins) log p(t | C) of every chunk bin t."""
        energies = self.net((features.float() - self.feature_mean) / self.feature_std)
        return torch.log_softmax(-energies, dim=-1)

    def forward(self, features: Tensor, chunk_index: int | Tensor) -> Tensor:
        """(B,) E_tau(C, t) = -log p(t | C) of each context at its chunk index (one int for all, or (B,))."""
        index = torch.as_tensor(chunk_index, device=features.device).long().clamp(0, self.bins - 1)
        index = index.expand(features.shape[0]) if index.ndim == 0 else index.reshape(-1)
        return -self.log_probabilities(features).gather(-1, index[:, None]).squeeze(-1)


@dataclass(frozen=True)
class PhaseEnergyFit:
    """How a phase energy was fitted: the epochs kept, the held-out demonstrations' NLL after each epoch of the
    trial run, and how many frames (from how many episodes) it saw."""

    epochs: int
    validation_nll: tuple[float, ...]
    frames: int
    episodes: int


def _check_fit_inputs(features: np.ndarray, chunk_index: np.ndarray, episode: np.ndarray, dim: int) -> None:
    if features.ndim != 2 or features.shape[1] != dim:
        raise ValueError(f"`features` must be (N, {dim}), the pooled contexts; got shape {features.shape}.")
    for name, values in (("chunk_index", chunk_index), ("episode", episode)):
        if values.shape != (features.shape[0],):
            raise ValueError(
                f"`{name}` must be ({features.shape[0]},), one per row of `features`; got shape {values.shape}."
            )
    if (chunk_index < 0).any():
        raise ValueError("`chunk_index` must be >= 0 (a frame's 0-based chunk index in its episode).")
    if np.unique(episode).size < 2:
        raise ValueError("Fitting a phase energy needs frames of at least 2 episodes (one is held out).")
    if not np.isfinite(features).all():
        raise ValueError("`features` holds a non-finite value.")


def _train(
    template: PhaseEnergy,
    features: Tensor,
    labels: Tensor,
    rows: Tensor,
    epochs: int,
    held: Tensor | None,
    seed: int,
) -> tuple[PhaseEnergy, list[float]]:
    """A fresh copy of `template` (its standardization, new weights from `seed`) trained with cross-entropy on
    `rows`; with `held`, the held-out rows' NLL after each epoch."""
    torch.manual_seed(seed)
    model = PhaseEnergy(features.shape[1], template.bins, template.hidden)
    model.feature_mean.copy_(template.feature_mean)
    model.feature_std.copy_(template.feature_std)
    optimizer = torch.optim.AdamW(model.parameters(), lr=FIT_LR, weight_decay=FIT_WEIGHT_DECAY)
    curve = []
    for _ in range(epochs):
        for batch in rows[torch.randperm(len(rows))].split(FIT_BATCH_SIZE):
            loss = nn.functional.nll_loss(model.log_probabilities(features[batch]), labels[batch])
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
        if held is not None:
            with torch.no_grad():
                curve.append(
                    nn.functional.nll_loss(model.log_probabilities(features[held]), labels[held]).item()
                )
    return model, curve


def fit_phase_energy(
    phase_energy: PhaseEnergy,
    features: np.ndarray,
    chunk_index: np.ndarray,
    episode: np.ndarray,
    max_epochs: int = FIT_MAX_EPOCHS,
    seed: int = 0,
) -> PhaseEnergyFit:
    """Fits `phase_energy` in place on demonstration frames: their pooled contexts (N, D), chunk indices and
    episodes.

    A trial run holds out a tenth of the episodes (whole ones) and records their NLL after each of `max_epochs`
    epochs; the module is then trained on every frame for the number of epochs with the lowest held-out NLL. The
    contexts are standardized by their own mean and std. Deterministic for a given seed on a given CPU.

    Raises:
        ValueError: Inputs of the wrong shape, a negative chunk index, a non-finite context, or fewer than two
            episodes.
    """
    features = np.asarray(features, dtype=np.float32)
    chunk_index, episode = np.asarray(chunk_index), np.asarray(episode)
    dim = phase_energy.feature_mean.numel()
    _check_fit_inputs(features, chunk_index, episode, dim)
    episodes = np.unique(episode)
    rng = np.random.default_rng(seed)
    held_episodes = rng.choice(episodes, max(1, int(len(episodes) * FIT_VALIDATION_FRACTION)), replace=False)
    held = np.isin(episode, held_episodes)

    with torch.no_grad():
        phase_energy.feature_mean.copy_(torch.as_tensor(features.mean(0)))
        phase_energy.feature_std.copy_(torch.as_tensor(features.std(0) + 1e-6))
    inputs = torch.as_tensor(features)
    labels = torch.as_tensor(np.minimum(chunk_index, phase_energy.bins - 1)).long()
    _, curve = _train(
        phase_energy,
        inputs,
        labels,
        torch.as_tensor(np.flatnonzero(~held)),
        max_epochs,
        torch.as_tensor(np.flatnonzero(held)),
        seed,
    )
    epochs = int(np.argmin(curve)) + 1
    trained, _ = _train(phase_energy, inputs, labels, torch.arange(len(held)), epochs, None, seed)
    with torch.no_grad():
        phase_energy.net.load_state_dict(trained.net.state_dict())
        phase_energy.fitted_frames.fill_(len(held))
    return PhaseEnergyFit(epochs, tuple(curve), len(held), len(episodes))
