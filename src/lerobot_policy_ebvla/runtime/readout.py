"""`EnergyReadout`: what the policy reports about a refined chunk, and the one input of every run-time tool.

The policy makes one per chunk (`EBVLAPolicy.last_energy`); the scores, the calibration, the two monitors and
the policy's OOD response all take it. Offline, recorded chunks become the same object with `of_arrays`.
"""

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor


def _tensor(values, dtype: torch.dtype = torch.float64) -> Tensor:
    """A 1-D tensor of `values` (a scalar, a sequence, an array or a tensor)."""
    if isinstance(values, Tensor):
        return values.detach().reshape(-1)
    return torch.as_tensor(np.asarray(values), dtype=dtype).reshape(-1)


@dataclass
class EnergyReadout:
    """The energies of one refined chunk per batch element, with where the chunk is in its episode.

    Attributes:
        initial_energy: E(a^(0), C), (B,): the energy of the initial noise, read at the first MCMC step; None
            in a readout built from records that did not keep it.
        final_energy: E(a^(K_inf), C), (B,): the confidence score of the returned chunk; +inf where the
            refinement hit a non-finite energy or gradient.
        chains: (B,) how many MCMC chains were refined for each observation: `num_restarts`, or with
            `restart_energy_threshold` 1, and `num_restarts` where the first chunk's energy was above it.
        context_energy: E_c(C), (B,), the joint energy's context term, already inside `final_energy`; None
            without a joint energy (it has one with `joint_energy.target` "context", "context_backbone" or
            "observation"). Recorded apart because its rise under a shift can be small beside the spread of
            the head's part (docs/energy_study.md, section 8.8).
        chunk_index: The chunk's 0-based index in its episode: the policy counts the chunks it refined since
            `reset()`, every environment of the batch at the same index. In a readout of recorded chunks
            (`of_arrays`), one index per row, (B,).
        context_features: (B, D) the pooled last-block context of each observation (`EBVLAPolicy.context_features`),
            filled by the policy when its calibration's score reads it; None otherwise.
        phase_energy: E_tau(C, t), (B,), the phase energy of each context at the chunk's index (`phase_energy.py`);
            None for a policy without a fitted one.
    """

    initial_energy: Tensor | None
    final_energy: Tensor
    chains: Tensor | None = None
    context_energy: Tensor | None = None
    chunk_index: int | Tensor = 0
    context_features: Tensor | None = None
    phase_energy: Tensor | None = None

    @classmethod
    def of_arrays(
        cls,
        final_energy,
        chunk_index=None,
        context_features=None,
        context_energy=None,
        initial_energy=None,
        phase_energy=None,
    ) -> "EnergyReadout":
        """A readout of recorded chunks, one per row: what the policy's readouts of those chunks held.

        Args:
            final_energy: Each chunk's final energy: a float, or (N,) numbers.
            chunk_index: Each chunk's index in its episode: an int for all, or (N,). None: the rows are one
                rollout's chunks in order, 0 .. N-1.
            context_features: Each chunk's pooled context, (N, D), or (D,) for one chunk.
            context_energy: Each chunk's E_c(C), (N,).
            initial_energy: Each chunk's E(a^(0), C), (N,).
            phase_energy: Each chunk's E_tau(C, t), (N,).

        Raises:
            ValueError: An input has not one row per final energy.
        """
        final = _tensor(final_energy)
        n = final.numel()
        index = torch.arange(n) if chunk_index is None else _tensor(chunk_index, torch.int64)
        if index.numel() == 1 and n != 1:
            index = index.expand(n)
        features = None
        if context_features is not None:
            if isinstance(context_features, Tensor):
                features = context_features.detach().to("cpu", torch.float64)
            else:
                features = torch.as_tensor(np.asarray(context_features, dtype=np.float64))
            features = features.reshape(1, -1) if features.ndim == 1 else features
        optional = {
            "chunk_index": index,
            "context_features": features,
            "context_energy": None if context_energy is None else _tensor(context_energy),
            "initial_energy": None if initial_energy is None else _tensor(initial_energy),
            "phase_energy": None if phase_energy is None else _tensor(phase_energy),
        }
        for name, values in optional.items():
            if values is not None and values.shape[0] != n:
                raise ValueError(
                    f"`{name}` has {values.shape[0]} row(s) and `final_energy` {n} entries: give one per chunk."
                )
        return cls(
            optional["initial_energy"],
            final,
            context_energy=optional["context_energy"],
            chunk_index=index,
            context_features=features,
            phase_energy=optional["phase_energy"],
        )

    def row(self, i: int) -> "EnergyReadout":
        """The readout of row i alone: replays a recorded rollout (`of_arrays`) through a monitor chunk by chunk,
        as the policy reported it."""

        def one(values: Tensor | None) -> Tensor | None:
            return None if values is None else values[i : i + 1]

        index = self.chunk_index
        return EnergyReadout(
            one(self.initial_energy),
            one(self.final_energy),
            one(self.chains),
            one(self.context_energy),
            index[i : i + 1] if isinstance(index, Tensor) and index.ndim else index,
            one(self.context_features),
            one(self.phase_energy),
        )
