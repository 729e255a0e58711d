"""The chunk scores a run-time OOD calibration can apply, one class each, and the registry that names them.

A `ChunkScore` turns the policy's `EnergyReadout` of B chunks (as `ChunkInputs`: the final energy, the chunk's
index in its episode, its pooled context, the context term of a joint energy) into components; a rollout's score
aggregates each component over its chunks (`rollout_score`: mean, max, last or median) and combines the
aggregates (`score_rollout`). The threshold T = mu_v + k sigma_v (Eq. 5) or the conformal one is then set on the
vanilla rollouts' scores (`OODCalibration`). A score is fitted on vanilla rollouts (`VanillaRollouts`) and saved
in `ood_calibration.json` (its JSON fields) and in safetensors files beside it (its side files).

The package ships seven scores (`SCORES`); a checkpoint is monitored with the one its config names
(`EBVLAConfig.monitor.score`: "context_phase_energy" for a policy with E_c on its own encoder, "final_energy"
otherwise, unless the config names another):

- "final_energy" (`FinalEnergy`, the paper's): E(a^(K_inf), C).
- "context_phase_energy" (`ContextPhaseEnergy`): a joint energy's context term E_c(C) against the vanilla E_c at
  the same chunk index, z_t = (E_c,t - mu_v[t]) / sigma_v[t] (`PhaseStatistics`), one-sided: the energy monitor
  for an E_c trained on its own encoder and flat at the data (the light preset), which every shift of the
  MetaWorld sweep raises.
- "head_energy_two_sided" (`HeadEnergyTwoSided`): |z| of the head's part of the joint energy, E - E_c, against
  the vanilla E - E_c at the same chunk index: a failure score, not an OOD one.
- "joint_phase_energy" (`JointPhaseEnergy`): both terms, E_c and E - E_c, each against its vanilla value at the
  same chunk index, averaged (one-sided): the failure check for a policy trained with the joint energy on LIBERO.
- "context_start_energy" (`ContextStartEnergy`): E_c against its vanilla value at each chunk index, and the head's
  energy of the MCMC's starting sample, E(a^(0), C) - E_c(C), below its vanilla value there, averaged: the OOD
  score of the LIBERO checkpoints, which also knows a dimmed light and mild sensor noise.
- "joint_phase_time_energy" (`JointPhaseTimeEnergy`): E_c, E - E_c and the phase energy E_tau(C, t), each against
  its vanilla value at the chunk index, averaged: the failure check of a LIBERO checkpoint with a fitted phase energy.
- "context_knn" (`ContextKNN`): the feature baseline, the Euclidean distance of the chunk's pooled context,
  standardized per dimension, to its k-th nearest standardized vanilla context (`ContextNeighbours`, every
  calibration context saved in `ood_calibration_neighbours.safetensors`).

The scores the research compared them with live beside the research code and join `SCORES` through
`register_score` when their module is imported.
"""

from collections.abc import Sequence
from dataclasses import dataclass, field, fields
from typing import Any, ClassVar, Protocol, Self

import numpy as np
from torch import Tensor

from .checkpoint_files import SideFile
from .readout import EnergyReadout
from .statistics import (
    DEFAULT_KNN_K,
    ContextNeighbours,
    PhaseStatistics,
    energies_by_index,
    float64,
)
from .threshold import ArrayLike, as_array

SCORE_AGGREGATIONS = ("mean", "max", "last", "median")

# The context neighbours, beside `ood_calibration.json`: N x D numbers are no JSON.
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
        "with a joint energy (`joint_energy.target`) reports"
    ),
}
INPUT_SOURCES["initial_energy"] = (
    "each chunk's E(a^(0), C) (`EnergyReadout.initial_energy`, (B,)), which the policy reports with every chunk; in "
    "records, the `initial_energy` column"
)
INPUT_SOURCES["phase_energy"] = (
    "each chunk's phase energy E_tau(C, t) (`EnergyReadout.phase_energy`, (B,)), which only a checkpoint fitted with "
    "`ebvla-fit-phase-energy` reports; in records, the `phase_energy` column"
)
# The head's energy is the final energy less E_c (`ChunkInputs.head_energy`): missing exactly where E_c is.
INPUT_SOURCES["head_energy"] = INPUT_SOURCES["context_energy"]
INPUT_SOURCES["start_head_energy"] = (
    f"{INPUT_SOURCES['initial_energy']}; and {INPUT_SOURCES['context_energy']}"
)


@dataclass(frozen=True)
class ChunkInputs:
    """An `EnergyReadout` of B chunks as the scores read it, in float64 arrays. Build it with `of`.

    Args:
        final_energy: E(a^(K_inf), C) of each chunk, (B,).
        chunk_index: Each chunk's 0-based index t in its episode, (B,).
        context_features: Each chunk's pooled last-block context c, (B, D); None when not computed.
        context_energy: E_c(C) of each chunk's observation, the joint energy's context term, (B,); None for a
            policy without one.
        initial_energy: E(a^(0), C) of each chunk, the energy of the MCMC's starting sample, (B,); None where a
            readout did not keep it.
        phase_energy: E_tau(C, t) of each chunk, the phase energy, (B,); None for a policy without a fitted one.
    """

    final_energy: np.ndarray
    chunk_index: np.ndarray
    context_features: np.ndarray | None = None
    context_energy: np.ndarray | None = None
    initial_energy: np.ndarray | None = None
    phase_energy: np.ndarray | None = None

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
        initial = None if readout.initial_energy is None else as_array(readout.initial_energy)
        phase = None if readout.phase_energy is None else as_array(readout.phase_energy)
        for name, rows in (
            ("chunk_index", index.size),
            ("context_features", None if features is None else features.shape[0]),
            ("context_energy", None if context is None else context.size),
            ("initial_energy", None if initial is None else initial.size),
            ("phase_energy", None if phase is None else phase.size),
        ):
            if rows is not None and rows != n:
                raise ValueError(
                    f"`{name}` has {rows} row(s) and `final_energy` {n} entries: give one per chunk."
                )
        return cls(energies, index, features, context, initial, phase)

    def first(self, n: int) -> "ChunkInputs":
        """The first n chunks (all of them when there are fewer): a rollout's opening, in chunk order."""
        columns = (getattr(self, f.name) for f in fields(self))
        return ChunkInputs(*(None if values is None else values[:n] for values in columns))

    @property
    def head_energy(self) -> np.ndarray | None:
        """E(a^(K_inf), C) - E_c(C), the head's part of a joint final energy, (B,); None without E_c."""
        return None if self.context_energy is None else self.final_energy - self.context_energy

    @property
    def start_head_energy(self) -> np.ndarray | None:
        """E(a^(0), C) - E_c(C), the head's energy of the MCMC's starting sample, (B,); None without E_c or
        without the initial energy."""
        if self.context_energy is None or self.initial_energy is None:
            return None
        return self.initial_energy - self.context_energy

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


def check_statistics(score: str, attribute: str, value: object, kind: type) -> None:
    """Checks that a score's statistics `attribute` is given and of `kind`, naming both if not."""
    if value is None:
        raise ValueError(f"`score={score!r}` needs `{attribute}` (`{kind.__name__}`).")
    if not isinstance(value, kind):
        raise ValueError(f"`{attribute}` must be `{kind.__name__}`, got {type(value).__name__}.")


def statistics_pair(fields: dict[str, Any], mean: str, std: str, score: str, kind: type) -> tuple:
    """The (mean, std) JSON fields of a statistics object, which come together."""
    values = fields.get(mean), fields.get(std)
    if (values[0] is None) != (values[1] is None):
        raise ValueError(f"`{mean}` and `{std}` come together: give both or neither.")
    if values[0] is None:
        raise ValueError(f"`score={score!r}` needs `{mean}` and `{std}` (`{kind.__name__}`).")
    return values


class AbsoluteOfAggregate:
    """A two-sided score |a|, a the rollout's one aggregated (signed) component."""

    def combine(self, aggregates: np.ndarray) -> np.ndarray:
        return np.abs(aggregates[:, 0])


@dataclass(frozen=True)
class FinalEnergy(ChunkScore):
    """E(a^(K_inf), C), the paper's score."""

    name = "final_energy"

    def components(self, chunks: ChunkInputs) -> np.ndarray:
        return chunks.final_energy[:, None]


def fit_phase(vanilla: VanillaRollouts, field_name: str, score: str) -> PhaseStatistics:
    """mu_v[t] and sigma_v[t] of the vanilla rollouts' input `field_name` (a `ChunkInputs` field) at each chunk
    index t, which the score `score` reads."""
    series = zip(vanilla.series(field_name, score), vanilla.series("chunk_index", score), strict=True)
    return PhaseStatistics.fit([energies_by_index(x, t) for x, t in series])


@dataclass(frozen=True)
class PhaseZScore(ChunkScore):
    """The base of the scores that standardize one per-chunk input (`input`, a `ChunkInputs` field) against
    the vanilla rollouts' at the same chunk index: z_t = (x_t - mu_v[t]) / sigma_v[t] (`PhaseStatistics`), t the
    chunk's 0-based index in its episode. A subclass names the input, its JSON fields and itself.
    """

    phase: PhaseStatistics

    input: ClassVar[str]
    reads = ("chunk_index",)

    def __post_init__(self):
        check_statistics(self.name, "phase", self.phase, PhaseStatistics)

    @classmethod
    def fit(cls, vanilla: VanillaRollouts) -> Self:
        return cls(fit_phase(vanilla, cls.input, cls.name))

    def components(self, chunks: ChunkInputs) -> np.ndarray:
        values = chunks.get(self.input, self.name)
        return self.phase.z(values, chunks.get("chunk_index", self.name))[:, None]

    def to_json(self) -> dict[str, Any]:
        return dict(zip(self.json_fields, (self.phase.mean, self.phase.std), strict=True))

    @classmethod
    def from_json(cls, fields: dict[str, Any]) -> Self:
        return cls(PhaseStatistics(*statistics_pair(fields, *cls.json_fields, cls.name, PhaseStatistics)))


@dataclass(frozen=True)
class ContextPhaseEnergy(PhaseZScore):
    """The joint energy's context term against the vanilla E_c at the same chunk index,
    z_t = (E_c,t - mu_v[t]) / sigma_v[t], aggregated over the rollout: one-sided, high above the vanilla band.

    The matched test for an E_c trained flat at the data (`joint_energy.gradient_penalty`), under which every shift
    of the sweep raises E_c in every scene; the two-sided form then reads the rollouts of low-E_c scenes that a
    mild shift lifts into the band's middle as typical (research/docs/energy_study.md, section 8.12).
    """

    name = "context_phase_energy"
    input = "context_energy"
    reads = ("chunk_index", "context_energy")
    json_fields = ("context_energy_phase_mean", "context_energy_phase_std")


@dataclass(frozen=True)
class HeadEnergyTwoSided(AbsoluteOfAggregate, PhaseZScore):
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


class PhaseTerms(ChunkScore):
    """The base of the scores that read several per-chunk inputs (`inputs`, `ChunkInputs` fields), each against the
    vanilla rollouts' at the same chunk index (`PhaseStatistics`, one dataclass field each, in `inputs`' order), each
    z turned by its sign (`signs`), each aggregated over the rollout before they are averaged. A subclass names
    its inputs, its signs, its JSON fields (mean and std of each term, in order), `n_components` and itself.
    """

    inputs: ClassVar[tuple[str, ...]]
    signs: ClassVar[tuple[float, ...]] = (1.0, 1.0)
    n_components = 2

    @property
    def phases(self) -> tuple[PhaseStatistics, ...]:
        return tuple(getattr(self, f.name) for f in fields(self))

    def __post_init__(self):
        for f in fields(self):
            check_statistics(self.name, f.name, getattr(self, f.name), PhaseStatistics)

    @classmethod
    def fit(cls, vanilla: VanillaRollouts) -> Self:
        return cls(*(fit_phase(vanilla, name, cls.name) for name in cls.inputs))

    def components(self, chunks: ChunkInputs) -> np.ndarray:
        index = chunks.get("chunk_index", self.name)
        terms = zip(self.phases, self.inputs, self.signs, strict=True)
        return np.stack(
            [sign * phase.z(chunks.get(name, self.name), index) for phase, name, sign in terms], axis=1
        )

    def combine(self, aggregates: np.ndarray) -> np.ndarray:
        return aggregates.mean(axis=1)

    def to_json(self) -> dict[str, Any]:
        values = [v for phase in self.phases for v in (phase.mean, phase.std)]
        return dict(zip(self.json_fields, values, strict=True))

    @classmethod
    def from_json(cls, fields: dict[str, Any]) -> Self:
        names = cls.json_fields
        return cls(
            *(
                PhaseStatistics(*statistics_pair(fields, *names[i : i + 2], cls.name, PhaseStatistics))
                for i in range(0, len(names), 2)
            )
        )


@dataclass(frozen=True)
class JointPhaseEnergy(PhaseTerms):
    """Both terms of the joint energy against their vanilla values at the same chunk index, averaged:
    s_t = (z_c,t + z_h,t) / 2, with z_c,t = (E_c,t - mu_c[t]) / sigma_c[t] for the context term and z_h,t likewise
    for the head's part E_t - E_c,t; one-sided, each term aggregated over the rollout before the two are averaged.

    A failure score: a rollout falling behind the task (on LIBERO, a grasp that misses and an arm that keeps
    reaching) shows in E_c, whose frames vanilla rollouts had left by that chunk, and in the head's energy of the
    chunk it refines there; together they tell failures apart better than either (research/docs/libero_runs.md,
    "A failure check on both terms of the joint energy").
    """

    context: PhaseStatistics
    head: PhaseStatistics

    name = "joint_phase_energy"
    reads = ("chunk_index", "context_energy")
    inputs = ("context_energy", "head_energy")
    json_fields = (
        "context_energy_phase_mean",
        "context_energy_phase_std",
        "head_energy_phase_mean",
        "head_energy_phase_std",
    )


@dataclass(frozen=True)
class ContextStartEnergy(PhaseTerms):
    """E_c against its vanilla value at each chunk index, and the head's energy of the MCMC's starting sample below
    its vanilla value there, averaged: s_t = (z_c,t - z_s,t) / 2, with z_c,t = (E_c,t - mu_c[t]) / sigma_c[t] and
    z_s,t likewise for E_head,t(a^(0)) = E(a^(0), C) - E_c(C); each term aggregated over the rollout before the two
    are averaged. One-sided, energies only.

    The LIBERO checkpoints' OOD score: the start's energy falls under every LIBERO shift, dim light and mild noise
    among them, where E_c barely moves (research/docs/libero_runs.md, "The starting sample's energy beside E_c").
    """

    context: PhaseStatistics
    start: PhaseStatistics

    name = "context_start_energy"
    reads = ("chunk_index", "context_energy", "initial_energy")
    inputs = ("context_energy", "start_head_energy")
    # The start term's sign turned: a shift lowers the head's energy of the Gaussian start.
    signs = (1.0, -1.0)
    json_fields = (
        "context_energy_phase_mean",
        "context_energy_phase_std",
        "start_head_energy_phase_mean",
        "start_head_energy_phase_std",
    )


@dataclass(frozen=True)
class JointPhaseTimeEnergy(PhaseTerms):
    """Both terms of the joint energy and the phase energy against their vanilla values at the same chunk index,
    averaged: s_t = (z_c,t + z_h,t + z_tau,t) / 3, z_tau,t = (E_tau,t - mu_tau[t]) / sigma_tau[t] for the phase
    energy E_tau(C, t) = -log p(t | C) (`phase_energy.py`), z_c and z_h as in `JointPhaseEnergy`; one-sided, each
    term aggregated over the rollout before the three are averaged.

    The failure check of a LIBERO checkpoint with a fitted phase energy: a rollout that never grasps keeps E_c and
    E - E_c at their vanilla level, and E_tau says its context belongs to an earlier chunk. On K's 400 held-out
    rollouts it caught 31 of 31 failures at 93.6 % balanced accuracy, where `joint_phase_energy` reached 81.3 %, and
    92.3 % on 400 new ones; the feature distance `chunk_context_nn` still reached 97 % on both, with half the false
    alarms (research/docs/libero_runs.md, "A phase energy for the failure check", "The phase energy on new rollouts").
    """

    context: PhaseStatistics
    head: PhaseStatistics
    phase: PhaseStatistics

    name = "joint_phase_time_energy"
    reads = ("chunk_index", "context_energy", "phase_energy")
    inputs = ("context_energy", "head_energy", "phase_energy")
    signs = (1.0, 1.0, 1.0)
    n_components = 3
    json_fields = (
        "context_energy_phase_mean",
        "context_energy_phase_std",
        "head_energy_phase_mean",
        "head_energy_phase_std",
        "phase_energy_phase_mean",
        "phase_energy_phase_std",
    )


@dataclass(frozen=True)
class ContextKNN(ChunkScore):
    """The distance of the chunk's standardized pooled context to its k-th nearest vanilla one."""

    # Saved beside the JSON, not compared by `==`.
    neighbours: ContextNeighbours = field(compare=False)

    name = "context_knn"
    reads = ("context_features",)
    side_files = (NEIGHBOURS_FILE,)

    def __post_init__(self):
        check_statistics(self.name, "neighbours", self.neighbours, ContextNeighbours)

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


# The registry: each score by its name. The package's seven; research code adds its own (`register_score`).
SCORES: dict[str, type[ChunkScore]] = {
    score.name: score
    for score in (
        FinalEnergy,
        ContextPhaseEnergy,
        HeadEnergyTwoSided,
        JointPhaseEnergy,
        ContextStartEnergy,
        JointPhaseTimeEnergy,
        ContextKNN,
    )
}
PACKAGE_SCORES = tuple(SCORES)


def register_score(score: type[ChunkScore]) -> type[ChunkScore]:
    """Adds a score class to `SCORES`, so that calibrations, reports and monitors find it by its name.

    Research code registers the scores it studies this way when its module is imported; the class is returned,
    so this can decorate it. Registering the same class again does nothing.

    Raises:
        ValueError: The class has no `name`, or its name is another class's.
    """
    name = getattr(score, "name", None)
    if not isinstance(name, str) or not name:
        raise ValueError(f"A score class needs a `name` to be registered, got {score!r}.")
    if SCORES.get(name, score) is not score:
        raise ValueError(f"The score name {name!r} is already registered for {SCORES[name].__qualname__}.")
    SCORES[name] = score
    return score


def set_score_order(names: Sequence[str]) -> None:
    """Puts `SCORES` in the order of `names`, which must name every registered score once: the order of the
    rows of the reports built from it (research code that recomputes committed tables restores theirs).

    Raises:
        ValueError: `names` is not the registered scores, each once.
    """
    if sorted(names) != sorted(SCORES):
        raise ValueError(
            f"The score order must name every registered score once: missing {sorted(set(SCORES) - set(names))}, "
            f"unknown {sorted(set(names) - set(SCORES))}, repeated {sorted({n for n in names if names.count(n) > 1})}."
        )
    ordered = {name: SCORES[name] for name in names}
    SCORES.clear()
    SCORES.update(ordered)
