"""The chunk scores a run-time OOD calibration can apply, one class each, and the registry that names them.

A `ChunkScore` turns what the policy reports about a chunk (`ChunkInputs`: its final energy, its index in the
episode, its pooled context, the context term of a joint energy) into components; a rollout's score aggregates
each component over its chunks
(`rollout_score`: mean, max, last or median) and combines the aggregates (`score_rollout`). The threshold
T = mu_v + k sigma_v (Eq. 5) or the conformal one is then set on the vanilla rollouts' scores
(`OODCalibration`). A score is fitted on vanilla rollouts (`VanillaRollouts`) and saved in
`ood_calibration.json` (its JSON fields) and in safetensors files beside it (its side files).

- "final_energy" (`FinalEnergy`, the paper's): E(a^(K_inf), C).
- "phase_energy" (`PhaseEnergy`): the final energy against the vanilla energy at the same chunk index,
  z_t = (E_t - mu_v[t]) / sigma_v[t] (`PhaseStatistics`): the energy's level follows the task's phase.
- "context_distance" (`ContextDistance`): the Mahalanobis distance of the chunk's pooled last-block context
  c = mean over tokens of C_L (`EBVLAPolicy.context_features`) from the vanilla contexts,
  d(c) = sqrt((c - mu_c)^T P (c - mu_c)), P the inverse of the Ledoit-Wolf shrunk covariance
  (`ContextStatistics`, saved in `ood_calibration_context.safetensors`).
- "energy_and_context" (`EnergyAndContext`): the final energy and the context distance see different failures
  (how well the action chain converged, what the policy sees); each is aggregated over the rollout,
  standardized by the vanilla rollouts' mean and std (`CombinedStatistics`), and the larger counts,
  s = max((E - mu_E) / sigma_E, (d - mu_d) / sigma_d). A single chunk's score is the same on that chunk alone.
- "context_knn" (`ContextKNN`): the Euclidean distance of the chunk's pooled context, standardized per
  dimension, to its k-th nearest standardized vanilla context, d_k(c) = || z(c) - z(c_(k)) ||
  (`ContextNeighbours`, every calibration context saved in `ood_calibration_neighbours.safetensors`). Unlike
  the Mahalanobis distance it assumes no Gaussian shape.

Two-sided forms. A shift can lower the final energy below vanilla's (a dimmer light, another colour: the energy
is then confidently wrong, issue 32), so each energy score also has a form that flags a rollout on either side of
the vanilla band, |z| of the rollout's aggregated z (a typicality test, Nalisnick et al. 2019):

- "final_energy_two_sided" (`FinalEnergyTwoSided`): |E - mu_E| / sigma_E, mu_E and sigma_E of every vanilla
  chunk's final energy.
- "phase_energy_two_sided" (`PhaseEnergyTwoSided`): |z| of the phase energy's rollout aggregate.
- "phase_energy_deviation" (`PhaseEnergyDeviation`): |z_t| of each chunk, then aggregated. A rollout whose
  chunks leave the band on both sides (above vanilla early, below it later) has a mean z near 0 and so passes
  the aggregate's test; the mean of |z_t| does not (issue 32's joint-energy sweep: min over 26 conditions 0.51
  against 0.53, success-cutting 0.86 against 0.84).
- "energy_two_sided_and_context_knn" (`EnergyTwoSidedAndContextKNN`): the two-sided phase energy and the
  context k-NN distance, each standardized by the vanilla rollouts' mean and std, and the larger counts.

A policy trained with a joint energy (`energy_ood_margin_on`) reports its context term E_c(C) apart
(`EnergyReadout.context_energy`, already inside the final energy), and three scores read it alone:

- "context_energy" (`ContextEnergy`): E_c(C), high off the data by training.
- "context_phase_energy" (`ContextPhaseEnergy`): E_c against the vanilla E_c at the same chunk index, z_t
  as the phase energy's, one-sided: for an E_c trained flat at the data (`energy_ood_gradient_penalty`), which
  every shift of issue 32's sweep raises.
- "context_energy_two_sided" (`ContextEnergyTwoSided`): |z| of E_c against the vanilla E_c at the same chunk
  index, as the two-sided phase energy is of the final energy. Issue 32's sweeps put some shifts *under* the
  vanilla E_c (blur, a light from another side); this form is confidently wrong on one of eight training seeds'
  sweeps (first 3 chunks), the final energy on one too, E_c one-sided on three (docs/energy_study.md section 8.9).
- "head_energy_two_sided" (`HeadEnergyTwoSided`): |z| of the head's part of the joint energy, E - E_c, against the
  vanilla E - E_c at the same chunk index: a failure score, not an OOD one (E_c flags every shift, harmless ones
  too; the head's part leaves the band where the chain finds no chunk it trusts).

The window test (`window.py`) compares several rollouts' `window_values` at once: the rollout score, and for a
two-sided score |a| (`AbsoluteOfAggregate`) its signed aggregate a too.

A new score is one class here and one entry in `SCORES`: the calibration, its file, the monitors, the policy's
`ood_response` and `ebvla-ood-report --score=<name>` find it there. A new input is one field of `ChunkInputs`
(and its line in `INPUT_SOURCES`), a keyword of the methods that pass it on (`OODCalibration.chunk_score`, the
monitor's, the response's), filled where the policy or the records hold it.
"""

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar, Protocol, Self

import numpy as np
from torch import Tensor

from .checkpoint_files import SideFile
from .readout import EnergyReadout
from .statistics import (
    DEFAULT_KNN_K,
    MIN_SIGMA,
    CombinedStatistics,
    ContextNeighbours,
    ContextStatistics,
    PhaseStatistics,
    energies_by_index,
    float64,
)
from .threshold import ArrayLike, as_array

SCORE_AGGREGATIONS = ("mean", "max", "last", "median")

# The context statistics and neighbours, beside `ood_calibration.json`: D x D numbers are no JSON.
CONTEXT_FILE = SideFile(
    "context_statistics",
    "ood_calibration_context.safetensors",
    "context statistics",
    ContextStatistics.from_bytes,
    lambda s: {"dim": s.dim, "n_chunks": s.n_chunks},
)
NEIGHBOURS_FILE = SideFile(
    "context_neighbours",
    "ood_calibration_neighbours.safetensors",
    "context neighbours",
    ContextNeighbours.from_bytes,
    lambda s: {"dim": s.dim, "n_chunks": s.n_chunks, "k": s.k},
)


def rollout_score(chunk_energies: ArrayLike, aggregation: str = "mean") -> float:
    """Forms a rollout's anomaly score from the final energies (or other scores) of its chunks, in order.

    Args:
        chunk_energies: E(a^(K_inf), C) of each predicted chunk of the rollout.
        aggregation: "mean" (default, every chunk counts equally), "max" (the least confident chunk),
            "last" (the most recent chunk, what a streaming monitor sees) or "median" (robust to a few
            outlying chunks). With "mean" and "max" one +inf chunk makes the score +inf.

    Raises:
        ValueError: No energies, or an unknown aggregation.
    """
    if aggregation not in SCORE_AGGREGATIONS:
        raise ValueError(f"`aggregation` must be one of {SCORE_AGGREGATIONS}, got {aggregation!r}.")
    energies = as_array(chunk_energies)
    if energies.size == 0:
        raise ValueError("A rollout score needs at least one chunk energy.")
    reduce = {"mean": np.mean, "max": np.max, "last": lambda e: e[-1], "median": np.median}[aggregation]
    return float(reduce(energies))


# Where each input a score may read comes from: what a missing one's error tells the user to give.
INPUT_SOURCES = {
    "context_features": (
        "each chunk's pooled context (`EnergyReadout.context_features`, (B, D), which the policy fills when its "
        "calibration's score reads it; in records, `ebvla-eval --record_context_features=true`)"
    ),
    "context_energy": (
        "each chunk's context energy E_c(C) (`EnergyReadout.context_energy`, (B,)), which only a policy trained "
        "with a joint energy (`energy_ood_margin_on`) reports"
    ),
}
# The head's energy is the final energy less E_c (`ChunkInputs.head_energy`): missing exactly where E_c is.
INPUT_SOURCES["head_energy"] = INPUT_SOURCES["context_energy"]


@dataclass(frozen=True)
class ChunkInputs:
    """An `EnergyReadout` of B chunks as the scores read it, in float64 arrays. Build it with `of`.

    Args:
        final_energy: E(a^(K_inf), C) of each chunk, (B,).
        chunk_index: Each chunk's 0-based index t in its episode, (B,).
        context_features: Each chunk's pooled last-block context c, (B, D); None when not computed.
        context_energy: E_c(C) of each chunk's observation, the joint energy's context term, (B,); None for a
            policy without one.
    """

    final_energy: np.ndarray
    chunk_index: np.ndarray
    context_features: np.ndarray | None = None
    context_energy: np.ndarray | None = None

    @classmethod
    def of(cls, readout: EnergyReadout) -> "ChunkInputs":
        """The arrays of a readout: its one chunk index stands for all B chunks.

        Raises:
            ValueError: An input's rows are not one per final energy.
        """
        energies = as_array(readout.final_energy)
        n = energies.size
        index = readout.chunk_index
        index = index.detach().cpu().numpy() if isinstance(index, Tensor) else np.asarray(index)
        index = np.full(n, int(index)) if index.ndim == 0 else index.reshape(-1)
        features = readout.context_features
        features = None if features is None else np.atleast_2d(float64(features))
        context = None if readout.context_energy is None else as_array(readout.context_energy)
        for name, rows in (
            ("chunk_index", index.size),
            ("context_features", None if features is None else features.shape[0]),
            ("context_energy", None if context is None else context.size),
        ):
            if rows is not None and rows != n:
                raise ValueError(
                    f"`{name}` has {rows} row(s) and `final_energy` {n} entries: give one per chunk."
                )
        return cls(energies, index, features, context)

    @property
    def head_energy(self) -> np.ndarray | None:
        """E(a^(K_inf), C) - E_c(C), the head's part of a joint final energy, (B,); None without E_c."""
        return None if self.context_energy is None else self.final_energy - self.context_energy

    def require(self, names: Sequence[str], score: str) -> None:
        """Checks that the inputs `names` (fields), which the score `score` reads, were given.

        Raises:
            ValueError: Naming every missing one and where it comes from.
        """
        missing = [INPUT_SOURCES[name] for name in names if getattr(self, name) is None]
        if missing:
            raise ValueError(f"The {score} score needs {'; and '.join(missing)}.")

    def get(self, name: str, score: str) -> np.ndarray:
        """The input `name` (a field), which the score `score` reads.

        Raises:
            ValueError: It was not given, saying where it comes from.
        """
        self.require([name], score)
        return getattr(self, name)


@dataclass(frozen=True)
class VanillaRollouts:
    """What a score is fitted on: the chunks of vanilla calibration rollouts, one readout per rollout (its N_r
    chunks in order, `EnergyReadout.of_arrays`), kept as `ChunkInputs`.

    Args:
        rollouts: Each rollout's readout, in chunk order.
        aggregation: How the calibration aggregates a rollout's chunks (`rollout_score`).
        knn_k: Which nearest vanilla context the context k-NN distance measures to.
    """

    rollouts: Sequence[EnergyReadout | ChunkInputs]
    aggregation: str = "mean"
    knn_k: int = DEFAULT_KNN_K

    def __post_init__(self):
        chunks = [r if isinstance(r, ChunkInputs) else ChunkInputs.of(r) for r in self.rollouts]
        object.__setattr__(self, "rollouts", chunks)

    def __len__(self) -> int:
        return len(self.rollouts)

    @property
    def final_energies(self) -> list[np.ndarray]:
        """Each rollout's chunk final energies, (N_r,)."""
        return [r.final_energy for r in self.rollouts]

    def series(self, name: str, score: str) -> list[np.ndarray]:
        """Each rollout's input `name` (a `ChunkInputs` field), which `score` is fitted on.

        Raises:
            ValueError: A rollout lacks it, saying where it comes from.
        """
        return [r.get(name, score) for r in self.rollouts]

    def features(self, score: str) -> tuple[np.ndarray, np.ndarray]:
        """Every chunk's pooled context, (N, D), and the rollout of each, (N,)."""
        features = self.series("context_features", score)
        rollout = np.concatenate([np.full(len(f), i) for i, f in enumerate(features)])
        return np.concatenate([float64(f) for f in features]), rollout

    def without(self, rollout: int) -> "VanillaRollouts":
        """The same rollouts but one: what a calibration rollout is scored against (leave-one-out)."""
        others = [r for i, r in enumerate(self.rollouts) if i != rollout]
        return VanillaRollouts(others, self.aggregation, self.knn_k)


class ChunkScore(Protocol):
    """One OOD score: how a chunk becomes components, how a rollout's aggregated components combine, what it
    fits on vanilla rollouts, and how it is saved.

    The methods here are the defaults of a score with one component that fits and saves nothing; a score
    class may subclass this protocol to inherit them.
    """

    # The name in `SCORES`, in `ood_calibration.json`'s `score` and in every report.
    name: ClassVar[str]
    # The `ChunkInputs` fields beside the final energy that `components` reads.
    reads: ClassVar[tuple[str, ...]] = ()
    # Columns of `components`, each aggregated over a rollout before `combine`.
    n_components: ClassVar[int] = 1
    # Its plain JSON fields, and the statistics it saves beside the JSON (`to_json` gives them as objects).
    json_fields: ClassVar[tuple[str, ...]] = ()
    side_files: ClassVar[tuple[SideFile, ...]] = ()

    @classmethod
    def fit(cls, vanilla: VanillaRollouts) -> Self:
        """Fits the score's statistics on vanilla rollouts (here none, once they are checked to hold what the
        score reads)."""
        for name in cls.reads:
            vanilla.series(name, cls.name)
        return cls()

    def components(self, chunks: ChunkInputs) -> np.ndarray:
        """(B, n_components) from the inputs of B chunks; the inputs of `reads` are there (`ChunkInputs.get`)."""
        ...

    def combine(self, aggregates: np.ndarray) -> np.ndarray:
        """(R,) scores from (R, n_components) components, each aggregated over a rollout (or one chunk's)."""
        return aggregates[:, 0]

    def window_values(self, aggregates: np.ndarray) -> np.ndarray:
        """(R, m) what the window test (`window.py`) compares per rollout, from (R, n_components) aggregates: the
        score itself, (R, 1), unless the score says otherwise."""
        return self.combine(aggregates)[:, None]

    def to_json(self) -> dict[str, Any]:
        """The JSON fields (`json_fields`) and the statistics of each side file, by its JSON field."""
        return {}

    @classmethod
    def from_json(cls, fields: dict[str, Any]) -> Self:
        """The score from what `to_json` gave, its side files read back (missing fields are absent or None)."""
        return cls()


def score_rollout(score: ChunkScore, components: ArrayLike, aggregation: str) -> float:
    """The rollout score of (N, n_components) chunk components: each column aggregated, then combined.

    Raises:
        ValueError: `components` is not (N >= 1, n_components).
    """
    return float(score.combine(rollout_aggregates(score, components, aggregation))[0])


def rollout_aggregates(score: ChunkScore, components: ArrayLike, aggregation: str) -> np.ndarray:
    """(1, n_components): each column of a rollout's (N, n_components) chunk components aggregated over its chunks.

    Raises:
        ValueError: `components` is not (N >= 1, n_components).
    """
    components = float64(components)
    n = score.n_components
    if components.ndim != 2 or components.shape[1] != n:
        raise ValueError(
            f"`components` of a {score.name} rollout must be (N, {n}), one row of `chunk_components` per "
            f"chunk; got shape {components.shape}."
        )
    return np.array([[rollout_score(column, aggregation) for column in components.T]])


def _check_statistics(score: str, attribute: str, value: object, kind: type) -> None:
    if value is None:
        raise ValueError(f"`score={score!r}` needs `{attribute}` (`{kind.__name__}`).")
    if not isinstance(value, kind):
        raise ValueError(f"`{attribute}` must be `{kind.__name__}`, got {type(value).__name__}.")


def _pair(fields: dict[str, Any], mean: str, std: str, score: str, kind: type) -> tuple:
    """The (mean, std) JSON fields of a statistics object, which come together."""
    values = fields.get(mean), fields.get(std)
    if (values[0] is None) != (values[1] is None):
        raise ValueError(f"`{mean}` and `{std}` come together: give both or neither.")
    if values[0] is None:
        raise ValueError(f"`score={score!r}` needs `{mean}` and `{std}` (`{kind.__name__}`).")
    return values


class AbsoluteOfAggregate:
    """A two-sided score |a|, a the rollout's one aggregated (signed) component.

    The window test compares a as well as |a|: a small shift the same way on every rollout (issue 32's mild noise
    raises E_c a little on each) hides inside vanilla's spread of |a| but not of a.
    """

    def combine(self, aggregates: np.ndarray) -> np.ndarray:
        return np.abs(aggregates[:, 0])

    def window_values(self, aggregates: np.ndarray) -> np.ndarray:
        return np.stack([np.abs(aggregates[:, 0]), aggregates[:, 0]], axis=1)


@dataclass(frozen=True)
class FinalEnergy(ChunkScore):
    """E(a^(K_inf), C), the paper's score."""

    name = "final_energy"

    def components(self, chunks: ChunkInputs) -> np.ndarray:
        return chunks.final_energy[:, None]


@dataclass(frozen=True)
class PhaseEnergy(ChunkScore):
    """(E_t - mu_v[t]) / sigma_v[t] at the chunk's 0-based index t in its episode.

    A subclass may standardize another per-chunk input (`input`, a `ChunkInputs` field) the same way.
    """

    phase: PhaseStatistics

    name = "phase_energy"
    input: ClassVar[str] = "final_energy"
    reads = ("chunk_index",)
    json_fields = ("phase_mean", "phase_std")

    def __post_init__(self):
        _check_statistics(self.name, "phase", self.phase, PhaseStatistics)

    @classmethod
    def fit(cls, vanilla: VanillaRollouts) -> "PhaseEnergy":
        values = vanilla.series(cls.input, cls.name)
        series = zip(values, vanilla.series("chunk_index", cls.name), strict=True)
        return cls(PhaseStatistics.fit([energies_by_index(x, t) for x, t in series]))

    def components(self, chunks: ChunkInputs) -> np.ndarray:
        values = chunks.get(self.input, self.name)
        return self.phase.z(values, chunks.get("chunk_index", self.name))[:, None]

    def to_json(self) -> dict[str, Any]:
        return dict(zip(self.json_fields, (self.phase.mean, self.phase.std), strict=True))

    @classmethod
    def from_json(cls, fields: dict[str, Any]) -> Self:
        return cls(PhaseStatistics(*_pair(fields, *cls.json_fields, cls.name, PhaseStatistics)))


@dataclass(frozen=True)
class ContextDistance(ChunkScore):
    """The Mahalanobis distance d(c) of the chunk's pooled context from the vanilla contexts."""

    # Saved beside the JSON, not compared by `==`.
    context: ContextStatistics = field(compare=False)

    name = "context_distance"
    reads = ("context_features",)
    side_files = (CONTEXT_FILE,)

    def __post_init__(self):
        _check_statistics(self.name, "context", self.context, ContextStatistics)

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

    def __post_init__(self):
        _check_statistics(self.name, "context", self.context, ContextStatistics)
        _check_statistics(self.name, "combined", self.combined, CombinedStatistics)

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
        _check_statistics(cls.name, "context", context, ContextStatistics)
        pair = _pair(fields, "combined_mean", "combined_std", cls.name, CombinedStatistics)
        return cls(context, CombinedStatistics(*pair))


@dataclass(frozen=True)
class ContextKNN(ChunkScore):
    """The distance of the chunk's standardized pooled context to its k-th nearest vanilla one."""

    # Saved beside the JSON, not compared by `==`.
    neighbours: ContextNeighbours = field(compare=False)

    name = "context_knn"
    reads = ("context_features",)
    side_files = (NEIGHBOURS_FILE,)

    def __post_init__(self):
        _check_statistics(self.name, "neighbours", self.neighbours, ContextNeighbours)

    @classmethod
    def fit(cls, vanilla: VanillaRollouts) -> "ContextKNN":
        return cls(ContextNeighbours.fit(vanilla.features(cls.name)[0], vanilla.knn_k))

    def components(self, chunks: ChunkInputs) -> np.ndarray:
        return self.neighbours.distance(chunks.get("context_features", self.name))[:, None]

    def to_json(self) -> dict[str, Any]:
        return {NEIGHBOURS_FILE.field: self.neighbours}

    @classmethod
    def from_json(cls, fields: dict[str, Any]) -> "ContextKNN":
        return cls(fields.get(NEIGHBOURS_FILE.field))


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
        return cls(*_pair(fields, "energy_mean", "energy_std", cls.name, cls))


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
class ContextPhaseEnergy(PhaseEnergy):
    """The joint energy's context term against the vanilla E_c at the same chunk index,
    z_t = (E_c,t - mu_v[t]) / sigma_v[t], aggregated over the rollout: one-sided, high above the vanilla band.

    The matched test for an E_c trained flat at the data (`energy_ood_gradient_penalty`), under which every shift
    of the sweep raises E_c in every scene; the two-sided form then reads the rollouts of low-E_c scenes that a
    mild shift lifts into the band's middle as typical (docs/energy_study.md, section 8.12).
    """

    name = "context_phase_energy"
    input = "context_energy"
    reads = ("chunk_index", "context_energy")
    json_fields = ("context_energy_phase_mean", "context_energy_phase_std")


@dataclass(frozen=True)
class ContextEnergyTwoSided(PhaseEnergyTwoSided):
    """|z| of the joint energy's context term against the vanilla E_c at the same chunk indices,
    z_t = (E_c,t - mu_v[t]) / sigma_v[t], aggregated over the rollout: an observation the context term puts
    *under* the data (issue 32's blur, a light from another side) is flagged too.

    Per chunk index, not one band for every chunk: E_c follows the task's phase, and against one band the first
    chunks of a shifted rollout can land nearer its centre than vanilla's own (docs/energy_study.md section 8.9).
    """

    name = "context_energy_two_sided"
    input = "context_energy"
    reads = ("chunk_index", "context_energy")
    json_fields = ("context_energy_phase_mean", "context_energy_phase_std")


@dataclass(frozen=True)
class HeadEnergyTwoSided(PhaseEnergyTwoSided):
    """|z| of the head's part of the joint energy, E_head = E(a^(K_inf), C) - E_c(C), against the vanilla E_head
    at the same chunk indices, z_t = (E_head,t - mu_v[t]) / sigma_v[t], aggregated over the rollout.

    A failure score, not an OOD one: E_c rises on every shift, harmless ones too, while E_head leaves the vanilla
    band, on either side, under the shifts that cut success (how well the chain found a chunk the head trusts).
    Issue 32's stronger preset: failed vs successful 0.81-0.87 on four training seeds, two trained after the rule
    (E_c 0.65-0.68); under harmless appearance shifts it stays nearer the band's middle than held-out vanilla, so it
    flags trouble and not novelty (docs/monitoring.md, "Which rollouts will fail").
    """

    name = "head_energy_two_sided"
    input = "head_energy"
    reads = ("chunk_index", "context_energy")
    json_fields = ("head_energy_phase_mean", "head_energy_phase_std")


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

    def __post_init__(self):
        _check_statistics(self.name, "phase", self.phase, PhaseStatistics)
        _check_statistics(self.name, "neighbours", self.neighbours, ContextNeighbours)
        _check_statistics(self.name, "combined", self.combined, CombinedStatistics)

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
        phase = PhaseStatistics(*_pair(fields, "phase_mean", "phase_std", cls.name, PhaseStatistics))
        combined = CombinedStatistics(
            *_pair(fields, "combined_mean", "combined_std", cls.name, CombinedStatistics)
        )
        return cls(phase, fields.get(NEIGHBOURS_FILE.field), combined)


# The registry: each score by its name.
SCORES: dict[str, type[ChunkScore]] = {
    score.name: score
    for score in (
        FinalEnergy,
        PhaseEnergy,
        ContextDistance,
        EnergyAndContext,
        ContextKNN,
        FinalEnergyTwoSided,
        PhaseEnergyTwoSided,
        PhaseEnergyDeviation,
        EnergyTwoSidedAndContextKNN,
        ContextEnergy,
        ContextPhaseEnergy,
        ContextEnergyTwoSided,
        HeadEnergyTwoSided,
    )
}
