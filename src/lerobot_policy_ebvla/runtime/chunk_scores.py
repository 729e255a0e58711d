"""The base every chunk score builds on: its inputs, what it is fitted on, how a rollout's score is formed.

`ChunkInputs` is an `EnergyReadout` of B chunks as a score reads it (`INPUT_SOURCES`: where each input comes
from), `VanillaRollouts` the calibration rollouts a score is fitted on, and `ChunkScore` the protocol of one
score. A rollout aggregates each component over its chunks (`rollout_score`, `rollout_aggregates`) and the score
combines the aggregates (`score_rollout`). `check_statistics`, `statistics_pair` and `AbsoluteOfAggregate` are the small
pieces the scores share. The scores are in `phase_scores.py` and `scores.py`, which also
holds the registry.
"""

from collections.abc import Sequence
from dataclasses import dataclass, fields
from typing import Any, ClassVar, Protocol, Self

import numpy as np
from torch import Tensor

from .checkpoint_files import SideFile
from .readout import EnergyReadout
from .statistics import DEFAULT_KNN_K, float64
from .threshold import ArrayLike, as_array

SCORE_AGGREGATIONS = ("mean", "max", "last", "median", "late")
# "late": the mean of a rollout's last chunks, this many, where a score tells failures apart once the rollouts
# have had time to diverge (`SuccessEnergyScore`).
LATE_CHUNKS = 4


def rollout_score(chunk_energies: ArrayLike, aggregation: str = "mean") -> float:
    """Forms a rollout's anomaly score from the final energies (or other scores) of its chunks, in order.

    Args:
        chunk_energies: E(a^(K_inf), C) of each predicted chunk of the rollout.
        aggregation: "mean" (default, every chunk counts equally), "max" (the least confident chunk),
            "last" (the most recent chunk, what a streaming monitor sees), "median" (robust to a few
            outlying chunks) or "late" (the mean of the last `LATE_CHUNKS`). With "mean", "max" and "late" one
            +inf chunk makes the score +inf.

    Raises:
        ValueError: No energies, or an unknown aggregation.
    """
    if aggregation not in SCORE_AGGREGATIONS:
        raise ValueError(f"`aggregation` must be one of {SCORE_AGGREGATIONS}, got {aggregation!r}.")
    energies = as_array(chunk_energies)
    if energies.size == 0:
        raise ValueError("A rollout score needs at least one chunk energy.")
    reduce = {
        "mean": np.mean,
        "max": np.max,
        "last": lambda e: e[-1],
        "median": np.median,
        "late": lambda e: np.mean(e[-LATE_CHUNKS:]),
    }[aggregation]
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
        succeeded: Whether each rollout succeeded, where known: a score fitted on successful rollouts only
            (`SuccessEnergyScore`) reads it.
    """

    rollouts: Sequence[EnergyReadout | ChunkInputs]
    aggregation: str = "mean"
    knn_k: int = DEFAULT_KNN_K
    succeeded: Sequence[bool] | None = None

    def __post_init__(self):
        chunks = [r if isinstance(r, ChunkInputs) else ChunkInputs.of(r) for r in self.rollouts]
        object.__setattr__(self, "rollouts", chunks)
        if self.succeeded is not None:
            if len(self.succeeded) != len(chunks):
                raise ValueError(
                    f"`succeeded` has {len(self.succeeded)} entries and `rollouts` {len(chunks)}: give one per rollout."
                )
            object.__setattr__(self, "succeeded", tuple(bool(s) for s in self.succeeded))

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
        succeeded = (
            None if self.succeeded is None else [s for i, s in enumerate(self.succeeded) if i != rollout]
        )
        return VanillaRollouts(others, self.aggregation, self.knn_k, succeeded)

    def first(self, n: int) -> "VanillaRollouts":
        """Each rollout's first n chunks (`ChunkInputs.first`)."""
        return VanillaRollouts(
            [r.first(n) for r in self.rollouts], self.aggregation, self.knn_k, self.succeeded
        )

    def successful(self, score: str) -> list[int]:
        """The positions of the rollouts that succeeded, which `score` is fitted on.

        Raises:
            ValueError: Whether they succeeded is not known.
        """
        if self.succeeded is None:
            raise ValueError(
                f"The {score} score is fitted on the successful calibration rollouts: give `succeeded`, whether "
                "each rollout succeeded (the records' `success`)."
            )
        return [i for i, s in enumerate(self.succeeded) if s]


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
    # A feature baseline keeps the calibration's contexts or their statistics: reported beside the energies, never
    # the failure check.
    feature_baseline: ClassVar[bool] = False
    # The aggregation the score's rollout reading was chosen with, which a calibration of it must use; None: any.
    rollout_aggregation: ClassVar[str | None] = None
    # Whether fitting trains a model (minutes, not milliseconds): a report computes it only where it is asked for.
    trains_model: ClassVar[bool] = False

    @classmethod
    def fit(cls, vanilla: VanillaRollouts) -> Self:
        """Fits the score's statistics on vanilla rollouts (here none, once they are checked to hold what the
        score reads)."""
        for name in cls.reads:
            vanilla.series(name, cls.name)
        return cls()

    @classmethod
    def held_out_fits(cls, vanilla: VanillaRollouts) -> list[Self | None] | None:
        """For each vanilla rollout, the fitted score that reads it in a calibration, one that never saw it (None
        for a rollout the fit on all never saw either). None (the default): each is refitted without it
        (`VanillaRollouts.without`), which a score that trains a model replaces by cross-fitting."""
        return None

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


def reading_of(score: ChunkScore | type[ChunkScore], aggregation: str) -> str:
    """The aggregation `score` is read with: its own (`rollout_aggregation`) where it has one, else `aggregation`."""
    return score.rollout_aggregation or aggregation


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
