"""Energy landscape around a refined action chunk (paper Fig. 2).

Two action dimensions of one timestep of the refined chunk a^(K_inf) are swept over a grid while every other
dimension and timestep stays fixed; each grid point's chunk is scored by the energy head, E(a, C), with the
context C encoded once. A well-shaped head shows a basin at the refined action.
"""

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

# (N, H, d_a) candidate chunks in normalized action space -> (N,) energies.
ScoreFn = Callable[[Tensor], Tensor]


@dataclass(frozen=True)
class EnergyLandscape:
    """Energies over a 2-D grid of one timestep's action values.

    Args:
        x: (G,) values of action dimension `dims[0]` along the grid.
        y: (G,) values of action dimension `dims[1]` along the grid.
        energies: (G, G) energies, `energies[i, j]` at (x[j], y[i]) (matplotlib's meshgrid layout).
        center: (2,) the refined chunk's values of the two swept dimensions.
        center_energy: Energy of the refined chunk itself.
        dims: The two swept action dimensions.
        timestep: The swept timestep of the chunk.
    """

    x: np.ndarray
    y: np.ndarray
    energies: np.ndarray
    center: np.ndarray
    center_energy: float
    dims: tuple[int, int]
    timestep: int


def _grid_axis(center: float, span: float | tuple[float, float], grid_size: int) -> np.ndarray:
    low, high = (center - span, center + span) if isinstance(span, int | float) else span
    return np.linspace(low, high, grid_size)


@torch.no_grad()
def energy_landscape(
    score_fn: ScoreFn,
    refined_chunk: Tensor,
    dims: tuple[int, int] = (0, 1),
    timestep: int = 0,
    grid_size: int = 50,
    span: float | tuple[float, float] = 1.0,
    batch_size: int = 1024,
) -> EnergyLandscape:
    """Sweeps two action dimensions of one timestep of a refined chunk and scores every grid point.

    Args:
        score_fn: Maps (N, H, d_a) normalized chunks to (N,) energies, e.g. `make_policy_score_fn`.
        refined_chunk: (H, d_a) the refined chunk a^(K_inf), in normalized action space.
        dims: The two action dimensions to sweep (Fig. 2 sweeps Δx and Δy, dims 0 and 1).
        timestep: The chunk timestep to sweep (Fig. 2: the first action, 0).
        grid_size: Points per axis; the grid has grid_size**2 points (Fig. 2: 50).
        span: A float s sweeps each dimension over [value - s, value + s] around the refined value; a
            (low, high) pair sweeps both over that absolute range.
        batch_size: Candidate chunks scored per `score_fn` call, to bound memory.

    Returns:
        The grid and its energies.
    """
    if refined_chunk.ndim != 2:
        raise ValueError(f"`refined_chunk` must be (H, d_a), got shape {tuple(refined_chunk.shape)}.")
    horizon, action_dim = refined_chunk.shape
    if not 0 <= timestep < horizon:
        raise ValueError(f"`timestep` must be in [0, {horizon}), got {timestep}.")
    if dims[0] == dims[1] or not all(0 <= d < action_dim for d in dims):
        raise ValueError(f"`dims` must be two different action dimensions in [0, {action_dim}), got {dims}.")

    center = refined_chunk[timestep, list(dims)].double().cpu().numpy()
    x = _grid_axis(float(center[0]), span, grid_size)
    y = _grid_axis(float(center[1]), span, grid_size)
    grid_x, grid_y = np.meshgrid(x, y)  # (G, G) each, row i <-> y[i]
    # The refined point itself rides along as the last point: a policy encodes the context once per call.
    points = np.concatenate([np.stack([grid_x.ravel(), grid_y.ravel()], axis=-1), center[None]])
    points = torch.from_numpy(points).to(refined_chunk)  # (G * G + 1, 2)

    energies = []
    for batch_points in points.split(batch_size):
        candidates = refined_chunk.expand(len(batch_points), horizon, action_dim).clone()  # (n, H, d_a)
        candidates[:, timestep, dims[0]] = batch_points[:, 0]
        candidates[:, timestep, dims[1]] = batch_points[:, 1]
        energies.append(score_fn(candidates).reshape(-1).double().cpu())
    energies = torch.cat(energies).numpy()
    return EnergyLandscape(
        x=x,
        y=y,
        energies=energies[:-1].reshape(grid_size, grid_size),
        center=center,
        center_energy=float(energies[-1]),
        dims=(int(dims[0]), int(dims[1])),
        timestep=int(timestep),
    )


def select_sample(batch: dict[str, Any], index: int) -> dict[str, Any]:
    """Keeps sample `index` of a preprocessed batch (tensors and per-sample lists), with a batch dim of 1."""
    batch_size = next(v.shape[0] for v in batch.values() if isinstance(v, Tensor) and v.ndim > 0)

    def is_per_sample(value: Any) -> bool:
        if isinstance(value, Tensor):
            return value.ndim > 0 and value.shape[0] == batch_size
        return isinstance(value, list | tuple) and len(value) == batch_size

    return {key: value[index : index + 1] if is_per_sample(value) else value for key, value in batch.items()}


def make_policy_score_fn(policy: Any, batch: dict[str, Any]) -> ScoreFn:
    """Wraps `policy.score_action_chunks` into a `ScoreFn` for one observation.

    Args:
        policy: An `EBVLAPolicy` (anything with `score_action_chunks(batch, candidates) -> (B, N)`).
        batch: A preprocessed batch of one observation (see `select_sample`).
    """

    def score_fn(candidates: Tensor) -> Tensor:
        return policy.score_action_chunks(batch, candidates[None])[0]  # (1, N, H, d_a) -> (N,)

    return score_fn


def policy_energy_landscape(
    policy: Any,
    batch: dict[str, Any],
    sample_index: int = 0,
    generator: torch.Generator | None = None,
    **landscape_kwargs: Any,
) -> EnergyLandscape:
    """Refines a chunk for one observation with the policy's MCMC, then maps the energy around it.

    Args:
        policy: An `EBVLAPolicy` in eval mode.
        batch: A preprocessed batch (the output of the policy's pre-processor).
        sample_index: Which observation of the batch to use.
        generator: Seeds the initial sample a^(0) of the refinement, for a reproducible figure.
        **landscape_kwargs: `dims`, `timestep`, `grid_size`, `span`, `batch_size` of `energy_landscape`.
    """
    sample = select_sample(batch, sample_index)
    # No `torch.no_grad()` here: MCMC refinement differentiates the energy with respect to the actions.
    actions, _ = policy.predict_action_chunk(sample, return_energy=True, generator=generator)
    return energy_landscape(make_policy_score_fn(policy, sample), actions[0].detach(), **landscape_kwargs)
