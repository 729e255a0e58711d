"""The success energy E_s(C, t): how far the pooled context C at chunk index t is from what the policy's own
successful rollouts showed at t (beyond the paper; the `success_energy` failure check of `scores.py`).

    E_s(C, t) = g(W C~ + e_t),   C~ the context standardized by the successful rollouts' mean and std,

g an MLP to a scalar and e_t a learned embedding of the chunk index (t >= `BINS - 1` shares the last). The phase energy
E_tau asks *when* a context belongs and is normalized over t; E_s asks whether the context belongs *at* t, an energy
over contexts at a fixed t. It is fitted on the successful vanilla calibration rollouts, contrastively (InfoNCE): the
context a rollout holds at t is the positive, against `NEGATIVES` contexts of those rollouts drawn at any chunk (most
of another phase: a stalled rollout's context at t is one of an earlier t) and `NEGATIVES // 2` copies of it with
Gaussian noise (std `NOISE` in standardized units: a context unlike any). A small penalty on the positives' squared
energy (`ANCHOR`) holds success at 0, since InfoNCE alone leaves each t's offset free and energies of E_s fitted on
different folds must be read on one scale. It stores no context: the MLP and the standardization.

research/docs/libero_runs.md, "A success energy fitted on the policy's own successful rollouts", chose these
settings on three sets of K's rollouts and tested them on a fourth fixed before it was read; "Narrower noisy copies,
and a sixth set" chose the noise std, 0.5 (1.0 before), on five read sets and met the Table IV rule on a sixth.
"""

from collections.abc import Sequence

import numpy as np
import torch
from safetensors.torch import load as load_safetensors
from safetensors.torch import save as save_safetensors
from torch import Tensor, nn

BINS = 40
HIDDEN = 256
EPOCHS = 30
BATCH_SIZE = 128
LR = 1e-3
WEIGHT_DECAY = 1e-4
NEGATIVES = 32
NOISE = 0.5
ANCHOR = 0.1
# Cross-fitting: a calibration rollout is read by the E_s of the fold that left it out (`cross_fit`).
FOLDS = 5

# One rollout as E_s reads it: its pooled contexts (T, D) and their chunk indices (T,).
Rollout = tuple[np.ndarray, np.ndarray]


class SuccessEnergy(nn.Module):
    """E_s(C, t) of pooled contexts C (B, D) at chunk indices t (B,); the standardization is a buffer."""

    def __init__(self, dim: int, hidden: int = HIDDEN, bins: int = BINS):
        super().__init__()
        self.bins = bins
        self.register_buffer("feature_mean", torch.zeros(dim))
        self.register_buffer("feature_std", torch.ones(dim))
        self.context = nn.Linear(dim, hidden)
        self.time = nn.Embedding(bins, hidden)
        self.net = nn.Sequential(nn.SiLU(), nn.Linear(hidden, hidden), nn.SiLU(), nn.Linear(hidden, 1))

    @property
    def dim(self) -> int:
        return self.feature_mean.numel()

    def standardize(self, features: Tensor) -> Tensor:
        return (features - self.feature_mean) / self.feature_std

    def energy(self, standardized: Tensor, chunk_index: Tensor) -> Tensor:
        """(B,) E_s of contexts already standardized."""
        embedded = self.context(standardized) + self.time(chunk_index.clamp(0, self.bins - 1))
        return self.net(embedded).squeeze(-1)

    def forward(self, features: Tensor, chunk_index: Tensor) -> Tensor:
        return self.energy(self.standardize(features.float()), chunk_index.long())

    def series(self, features: np.ndarray, chunk_index: np.ndarray) -> np.ndarray:
        """(T,) E_s of one rollout's contexts (T, D) at their chunk indices, as float64."""
        with torch.no_grad():
            values = self(
                torch.as_tensor(np.asarray(features, dtype=np.float32)), torch.as_tensor(chunk_index)
            )
        return values.double().numpy()

    # A side file of a calibration (`runtime.checkpoint_files.SideFile`) reads and writes bytes.

    def to_bytes(self) -> bytes:
        state = {key: value.contiguous() for key, value in self.state_dict().items()}
        return save_safetensors(state, metadata={"bins": str(self.bins)})

    @classmethod
    def from_state(cls, state: dict[str, Tensor]) -> "SuccessEnergy":
        """The module of a saved state dict; its dimensions are read from the weights."""
        try:
            model = cls(
                state["feature_mean"].numel(), state["context.weight"].shape[0], state["time.weight"].shape[0]
            )
            model.load_state_dict(state)
        except (KeyError, RuntimeError) as e:
            raise ValueError(f"Not the weights of a success energy E_s: {e}") from e
        return model.eval()

    @classmethod
    def from_bytes(cls, data: bytes) -> "SuccessEnergy":
        return cls.from_state(load_safetensors(data))


def _check_rollouts(rollouts: Sequence[Rollout], minimum: int) -> None:
    if len(rollouts) < minimum:
        raise ValueError(
            f"Fitting a success energy needs at least {minimum} successful rollouts; got {len(rollouts)}."
        )
    dims = {features.shape[1] if features.ndim == 2 else None for features, _ in rollouts}
    if len(dims) != 1 or None in dims:
        raise ValueError(
            f"Every rollout's contexts must be (T, D) with one D; got dimensions {sorted(map(str, dims))}."
        )
    for number, (features, index) in enumerate(rollouts):
        if index.shape != (features.shape[0],):
            raise ValueError(
                f"Rollout {number}: `chunk_index` must be ({features.shape[0]},), one per context; got {index.shape}."
            )
        if not np.isfinite(features).all():
            raise ValueError(f"Rollout {number}: its contexts hold a non-finite value.")


def fit_success_energy(
    rollouts: Sequence[Rollout],
    seed: int = 0,
    epochs: int = EPOCHS,
    other_contexts: int = NEGATIVES,
    noisy_copies: int = NEGATIVES // 2,
    noise: float = NOISE,
) -> SuccessEnergy:
    """E_s trained on successful rollouts (each its contexts (T, D) and chunk indices (T,)) by InfoNCE against
    `other_contexts` contexts drawn from them and `noisy_copies` copies of the positive with Gaussian noise of std
    `noise` (standardized units), with the anchor at 0 (0 of a kind leaves that kind out). Deterministic for a seed on
    a given CPU.

    Raises:
        ValueError: No rollout, no negatives, a noise std not > 0, contexts of different widths, or a non-finite
            context.
    """
    _check_rollouts(rollouts, 1)
    if other_contexts < 0 or noisy_copies < 0 or other_contexts + noisy_copies == 0:
        raise ValueError(
            f"`other_contexts` and `noisy_copies` must be >= 0, one of them > 0; got {other_contexts}, {noisy_copies}."
        )
    if not noise > 0:
        raise ValueError(f"`noise`, the noisy copies' std in standardized units, must be > 0; got {noise}.")
    generator = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    features = torch.as_tensor(np.concatenate([np.asarray(f, dtype=np.float32) for f, _ in rollouts]))
    index = torch.as_tensor(np.concatenate([t for _, t in rollouts])).long()
    model = SuccessEnergy(features.shape[1])
    model.feature_mean.copy_(features.mean(0))
    model.feature_std.copy_(features.std(0) + 1e-6)
    standardized = model.standardize(features)
    optimizer = torch.optim.AdamW(model.parameters(), lr=LR, weight_decay=WEIGHT_DECAY)
    n = len(index)
    for _ in range(epochs):
        for batch in torch.randperm(n, generator=generator).split(BATCH_SIZE):
            positive, t = standardized[batch], index[batch]
            candidates = [positive[:, None]]
            if other_contexts:
                drawn = torch.randint(0, n, (len(batch), other_contexts), generator=generator)
                candidates.append(standardized[drawn])
            if noisy_copies:
                standard_normal = torch.randn(
                    (len(batch), noisy_copies, positive.shape[1]), generator=generator
                )
                candidates.append(positive[:, None] + noise * standard_normal)
            candidates = torch.cat(candidates, 1)
            times = t[:, None].expand(-1, candidates.shape[1])
            logits = -model.energy(candidates.flatten(0, 1), times.flatten()).view(candidates.shape[:2])
            loss = nn.functional.cross_entropy(logits, torch.zeros(len(batch), dtype=torch.long))
            loss = loss + ANCHOR * logits[:, 0].pow(2).mean()
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
    return model.eval()


def fold_order(n: int, seed: int = 0) -> list[np.ndarray]:
    """The `FOLDS` folds of n rollouts (their positions), from a permutation drawn with `seed`."""
    return np.array_split(np.random.default_rng(seed).permutation(n), FOLDS)


def fold_readers(rollouts: Sequence[Rollout], seed: int = 0, **fit_kwargs) -> list[SuccessEnergy]:
    """For each of `rollouts`, the E_s that reads it in a calibration: fitted on the other folds' rollouts (fold f
    with seed `seed + 1 + f`), so that no rollout is read by an E_s that saw it. The E_s a checkpoint ships is
    `fit_success_energy(rollouts, seed)`, on all of them.

    `fit_kwargs`: `fit_success_energy`'s epochs and negatives.

    Raises:
        ValueError: Fewer rollouts than folds, or as `fit_success_energy`.
    """
    _check_rollouts(rollouts, FOLDS)
    folds = fold_order(len(rollouts), seed)
    # The complement in the permuted order: a fit depends on the order its rows come in.
    order = np.concatenate(folds)
    readers: list[SuccessEnergy | None] = [None] * len(rollouts)
    for number, fold in enumerate(folds):
        left_out = set(fold.tolist())
        kept = [rollouts[i] for i in order if i not in left_out]
        model = fit_success_energy(kept, seed + 1 + number, **fit_kwargs)
        for i in fold:
            readers[i] = model
    return readers
