"""The chunk scores the research compared the package's four with, registered into the package's `SCORES`.

Importing this module (`import research_scores` from a script beside it; `load_benchmark("research_scores")` in
a test) registers each class below with `lerobot_policy_ebvla.runtime.scores.register_score`, so that
`ebvla-ood-report --score=<name>`, `OODCalibration.load` and the monitors find them; without the import a saved
calibration of one of them is refused with an error that says so.

- "phase_energy" (`PhaseEnergy`): the final energy against the vanilla energy at the same chunk index,
  z_t = (E_t - mu_v[t]) / sigma_v[t] (`PhaseStatistics`): the energy's level follows the task's phase.
- "context_distance" (`ContextDistance`): the Mahalanobis distance of the chunk's pooled last-block context
  from the vanilla contexts, d(c) = sqrt((c - mu_c)^T P (c - mu_c)), P the inverse of the Ledoit-Wolf shrunk
  covariance (`ContextStatistics`, saved in `ood_calibration_context.safetensors`).
- "energy_and_context" (`EnergyAndContext`): the final energy and the context distance, each aggregated over the
  rollout and standardized by the vanilla rollouts' mean and std (`CombinedStatistics`); the larger counts.
- "context_energy" (`ContextEnergy`): E_c(C) of a joint energy, high off the data by training.
- Two-sided forms, |z| of the rollout's aggregated z (a typicality test, Nalisnick et al. 2019): a shift can
  lower the energy below vanilla's (issue 32): "final_energy_two_sided", "phase_energy_two_sided",
  "context_energy_two_sided" (E_c against the vanilla E_c at each chunk index); "phase_energy_deviation" (the mean
  of |z_t|, not |mean z_t|); "energy_two_sided_and_context_knn" (the two-sided phase energy and the context k-NN
  distance, standardized, the larger counting).
"""

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lerobot_policy_ebvla.runtime.checkpoint_files import SideFile
from lerobot_policy_ebvla.runtime.scores import (
    NEIGHBOURS_FILE,
    AbsoluteOfAggregate,
    ChunkInputs,
    ChunkScore,
    PhaseZScore,
    VanillaRollouts,
    check_statistics,
    register_score,
    rollout_score,
    set_score_order,
    statistics_pair,
)
from lerobot_policy_ebvla.runtime.statistics import (
    MIN_SIGMA,
    CombinedStatistics,
    ContextNeighbours,
    ContextStatistics,
    PhaseStatistics,
    energies_by_index,
    float64,
)

# The context statistics, beside `ood_calibration.json`: D x D numbers are no JSON.
CONTEXT_FILE = SideFile(
    "context_statistics",
    "ood_calibration_context.safetensors",
    "context statistics",
    ContextStatistics.from_bytes,
    lambda s: {"dim": s.dim, "n_chunks": s.n_chunks},
)


@dataclass(frozen=True)
class PhaseEnergy(PhaseZScore):
    """(E_t - mu_v[t]) / sigma_v[t]: the final energy against the vanilla final energy at the same chunk index."""

    name = "phase_energy"
    input = "final_energy"
    json_fields = ("phase_mean", "phase_std")


@dataclass(frozen=True)
class ContextDistance(ChunkScore):
    """The Mahalanobis distance d(c) of the chunk's pooled context from the vanilla contexts."""

    # Saved beside the JSON, not compared by `==`.
    context: ContextStatistics = field(compare=False)

    name = "context_distance"
    reads = ("context_features",)
    side_files = (CONTEXT_FILE,)
    feature_baseline = True

    def __post_init__(self):
        check_statistics(self.name, "context", self.context, ContextStatistics)

    @classmethod
    def fit(cls, vanilla: VanillaRollouts) -> "ContextDistance":
        return cls(ContextStatistics.fit(vanilla.features(cls.name)[0]))

    def components(self, chunks: ChunkInputs) -> np.ndarray:
        return self.context.distance(chunks.get("context_features", self.name))[:, None]

    def to_json(self) -> dict[str, Any]:
        return {CONTEXT_FILE.field: self.context}

    @classmethod
    def from_json(cls, fields: dict[str, Any]) -> "ContextDistance":
        return cls(fields.get(CONTEXT_FILE.field))


@dataclass(frozen=True)
class EnergyAndContext(ChunkScore):
    """max(z_E, z_d): the final energy and the context distance, each standardized by the vanilla rollouts'.

    Its two components, E and d, are aggregated over a rollout apart and combined after.
    """

    context: ContextStatistics = field(compare=False)
    combined: CombinedStatistics

    name = "energy_and_context"
    reads = ("context_features",)
    n_components = 2
    json_fields = ("combined_mean", "combined_std")
    side_files = (CONTEXT_FILE,)
    feature_baseline = True

    def __post_init__(self):
        check_statistics(self.name, "context", self.context, ContextStatistics)
        check_statistics(self.name, "combined", self.combined, CombinedStatistics)

    @classmethod
    def fit(cls, vanilla: VanillaRollouts) -> "EnergyAndContext":
        """The context statistics of every vanilla chunk, and the standardization of the vanilla rollouts'
        final energy and context distance, each rollout's distance measured without its own chunks (as the
        report scores a calibration rollout)."""
        features, rollout_of = vanilla.features(cls.name)
        energies, distances = [], []
        for i, chunk_energies in enumerate(vanilla.final_energies):
            own = rollout_of == i
            left_out = ContextStatistics.fit_without(features, own)
            energies.append(rollout_score(chunk_energies, vanilla.aggregation))
            distances.append(rollout_score(left_out.distance(features[own]), vanilla.aggregation))
        return cls(ContextStatistics.fit(features), CombinedStatistics.fit(energies, distances))

    def components(self, chunks: ChunkInputs) -> np.ndarray:
        distance = self.context.distance(chunks.get("context_features", self.name))
        return np.stack([chunks.final_energy, distance], axis=1)

    def combine(self, aggregates: np.ndarray) -> np.ndarray:
        return self.combined.combine(aggregates[:, 0], aggregates[:, 1])

    def to_json(self) -> dict[str, Any]:
        return {
            CONTEXT_FILE.field: self.context,
            "combined_mean": self.combined.mean,
            "combined_std": self.combined.std,
        }

    @classmethod
    def from_json(cls, fields: dict[str, Any]) -> "EnergyAndContext":
        context = fields.get(CONTEXT_FILE.field)
        check_statistics(cls.name, "context", context, ContextStatistics)
        pair = statistics_pair(fields, "combined_mean", "combined_std", cls.name, CombinedStatistics)
        return cls(context, CombinedStatistics(*pair))


@dataclass(frozen=True)
class ContextEnergy(ChunkScore):
    """E_c(C), the joint energy's context term alone: trained to rise off the data, without the head's part."""

    name = "context_energy"
    reads = ("context_energy",)

    def components(self, chunks: ChunkInputs) -> np.ndarray:
        return chunks.get("context_energy", self.name)[:, None]


@dataclass(frozen=True)
class FinalEnergyTwoSided(AbsoluteOfAggregate, ChunkScore):
    """|E - mu_E| / sigma_E of a rollout's aggregated final energy, mu_E and sigma_E of every vanilla chunk's:
    high when the energy leaves the vanilla band on either side."""

    mean: float
    std: float

    name = "final_energy_two_sided"
    json_fields = ("energy_mean", "energy_std")

    def __post_init__(self):
        if not (np.isfinite(self.mean) and np.isfinite(self.std) and self.std > 0):
            raise ValueError(
                f"`energy_mean` and `energy_std` must be finite, std > 0; got {self.mean}, {self.std}."
            )

    @classmethod
    def fit(cls, vanilla: VanillaRollouts) -> "FinalEnergyTwoSided":
        energies = np.concatenate([float64(e) for e in vanilla.final_energies])
        energies = energies[np.isfinite(energies)]
        if energies.size == 0:
            raise ValueError(f"The {cls.name} score needs a finite vanilla final energy.")
        return cls(float(energies.mean()), max(float(energies.std()), MIN_SIGMA))

    def components(self, chunks: ChunkInputs) -> np.ndarray:
        return ((chunks.final_energy - self.mean) / self.std)[:, None]

    def to_json(self) -> dict[str, Any]:
        return {"energy_mean": self.mean, "energy_std": self.std}

    @classmethod
    def from_json(cls, fields: dict[str, Any]) -> "FinalEnergyTwoSided":
        return cls(*statistics_pair(fields, "energy_mean", "energy_std", cls.name, cls))


@dataclass(frozen=True)
class PhaseEnergyTwoSided(AbsoluteOfAggregate, PhaseEnergy):
    """|z_t| of the phase energy: the rollout's aggregated z against the vanilla energy at the same chunk
    indices, on either side."""

    name = "phase_energy_two_sided"


@dataclass(frozen=True)
class PhaseEnergyDeviation(PhaseEnergy):
    """|z_t| of each chunk's phase energy: how far its final energy lies from the vanilla energy at the same
    chunk index, on either side, aggregated over the rollout (mean |z_t| by default)."""

    name = "phase_energy_deviation"

    def components(self, chunks: ChunkInputs) -> np.ndarray:
        return np.abs(super().components(chunks))


@dataclass(frozen=True)
class ContextEnergyTwoSided(PhaseEnergyTwoSided):
    """|z| of the joint energy's context term against the vanilla E_c at the same chunk indices,
    z_t = (E_c,t - mu_v[t]) / sigma_v[t], aggregated over the rollout: an observation the context term puts
    *under* the data (issue 32's blur, a light from another side) is flagged too.

    Per chunk index, not one band for every chunk: E_c follows the task's phase, and against one band the first
    chunks of a shifted rollout can land nearer its centre than vanilla's own (research/docs/energy_study.md section 8.9).
    """

    name = "context_energy_two_sided"
    input = "context_energy"
    reads = ("chunk_index", "context_energy")
    json_fields = ("context_energy_phase_mean", "context_energy_phase_std")


@dataclass(frozen=True)
class EnergyTwoSidedAndContextKNN(ChunkScore):
    """max(z_|phase|, z_knn): the two-sided phase energy and the context k-NN distance, each standardized by
    the vanilla rollouts' mean and std (`CombinedStatistics`, in that order).

    Its two components, the phase energy's signed z_t and the k-NN distance, are aggregated over a rollout
    apart; the first is then made two-sided, both are standardized and the larger counts.
    """

    phase: PhaseStatistics
    neighbours: ContextNeighbours = field(compare=False)
    combined: CombinedStatistics

    name = "energy_two_sided_and_context_knn"
    reads = ("chunk_index", "context_features")
    n_components = 2
    json_fields = ("phase_mean", "phase_std", "combined_mean", "combined_std")
    side_files = (NEIGHBOURS_FILE,)
    feature_baseline = True

    def __post_init__(self):
        check_statistics(self.name, "phase", self.phase, PhaseStatistics)
        check_statistics(self.name, "neighbours", self.neighbours, ContextNeighbours)
        check_statistics(self.name, "combined", self.combined, CombinedStatistics)

    @classmethod
    def fit(cls, vanilla: VanillaRollouts) -> "EnergyTwoSidedAndContextKNN":
        """The phase statistics and neighbours of every vanilla rollout, and the standardization of the vanilla
        rollouts' two scores, each rollout scored against the others (as the report scores a calibration
        rollout)."""
        features, rollout_of = vanilla.features(cls.name)
        neighbours = ContextNeighbours.fit(features, vanilla.knn_k)
        indices_of = vanilla.series("chunk_index", cls.name)
        series = [energies_by_index(e, t) for e, t in zip(vanilla.final_energies, indices_of, strict=True)]
        energies, distances = [], []
        for i, (chunk_energies, indices) in enumerate(zip(vanilla.final_energies, indices_of, strict=True)):
            others = [s for j, s in enumerate(series) if j != i] or series
            z = PhaseStatistics.fit(others).z(chunk_energies, indices)
            energies.append(abs(rollout_score(z, vanilla.aggregation)))
            own = rollout_of == i
            distances.append(
                rollout_score(neighbours.distance(features[own], excluded=own), vanilla.aggregation)
            )
        return cls(PhaseStatistics.fit(series), neighbours, CombinedStatistics.fit(energies, distances))

    def components(self, chunks: ChunkInputs) -> np.ndarray:
        z = self.phase.z(chunks.final_energy, chunks.get("chunk_index", self.name))
        distance = self.neighbours.distance(chunks.get("context_features", self.name))
        return np.stack([z, distance], axis=1)

    def combine(self, aggregates: np.ndarray) -> np.ndarray:
        return self.combined.combine(np.abs(aggregates[:, 0]), aggregates[:, 1])

    def to_json(self) -> dict[str, Any]:
        return {
            "phase_mean": self.phase.mean,
            "phase_std": self.phase.std,
            NEIGHBOURS_FILE.field: self.neighbours,
            "combined_mean": self.combined.mean,
            "combined_std": self.combined.std,
        }

    @classmethod
    def from_json(cls, fields: dict[str, Any]) -> "EnergyTwoSidedAndContextKNN":
        phase = PhaseStatistics(
            *statistics_pair(fields, "phase_mean", "phase_std", cls.name, PhaseStatistics)
        )
        combined = CombinedStatistics(
            *statistics_pair(fields, "combined_mean", "combined_std", cls.name, CombinedStatistics)
        )
        return cls(phase, fields.get(NEIGHBOURS_FILE.field), combined)


RESEARCH_SCORES = (
    PhaseEnergy,
    ContextDistance,
    EnergyAndContext,
    FinalEnergyTwoSided,
    PhaseEnergyTwoSided,
    PhaseEnergyDeviation,
    EnergyTwoSidedAndContextKNN,
    ContextEnergy,
    ContextEnergyTwoSided,
)
RESEARCH_NAMES = tuple(score.name for score in RESEARCH_SCORES)
# The order of the rows of every committed score table: the registry's before the package kept four scores.
TABLE_ORDER = (
    "final_energy",
    "phase_energy",
    "context_distance",
    "energy_and_context",
    "context_knn",
    "final_energy_two_sided",
    "phase_energy_two_sided",
    "phase_energy_deviation",
    "energy_two_sided_and_context_knn",
    "context_energy",
    "context_phase_energy",
    "context_energy_two_sided",
    "head_energy_two_sided",
    "joint_phase_energy",
    "context_start_energy",
    "joint_phase_time_energy",
    "success_energy",  # computed only where named (it trains a model): in no committed table
)
for _score in RESEARCH_SCORES:
    register_score(_score)
# The committed reports list their scores in this order (the registry's, before the package kept four): the
# registry is put back in it, so that a report recomputed from the records is the committed one line for line.
set_score_order(TABLE_ORDER)
