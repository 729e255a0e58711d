"""The chunk scores a run-time OOD calibration can apply, one class each, and the registry that names them.

A `ChunkScore` turns the policy's `EnergyReadout` of B chunks (as `ChunkInputs`: the final energy, the chunk's
index in its episode, its pooled context, the context term of a joint energy) into components; a rollout's score
aggregates each component over its chunks (`rollout_score`: mean, max, last or median) and combines the
aggregates (`score_rollout`). The threshold T = mu_v + k sigma_v (Eq. 5) or the conformal one is then set on the
vanilla rollouts' scores (`OODCalibration`). A score is fitted on vanilla rollouts (`VanillaRollouts`) and saved
in `ood_calibration.json` (its JSON fields) and in safetensors files beside it (its side files).

The package ships eight scores (`SCORES`); a checkpoint is monitored with the one its config names
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
- "success_energy" (`SuccessEnergyScore`): the success energy E_s(C, t), an energy of the pooled context at
  chunk index t fitted on the successful calibration rollouts (`success_energy.py`), read over a window's last
  chunks: the failure check of a checkpoint calibrated on about 100 rollouts with their pooled contexts.
- "context_knn" (`ContextKNN`): the feature baseline, the Euclidean distance of the chunk's pooled context,
  standardized per dimension, to its k-th nearest standardized vanilla context (`ContextNeighbours`, every
  calibration context saved in `ood_calibration_neighbours.safetensors`).

The scores the research compared them with live beside the research code and join `SCORES` through
`register_score` when their module is imported.

The pieces live in three modules: the base every score builds on (`ChunkInputs`, `VanillaRollouts`, the
`ChunkScore` protocol, `rollout_score`, `score_rollout`) in `chunk_scores.py`; the scores that read an input
against the vanilla rollouts' value at the same chunk index (`PhaseZScore`, `PhaseTerms` and the five built on
them) in `phase_scores.py`; the paper's `FinalEnergy`, the success energy's `SuccessEnergyScore`, the feature
baseline `ContextKNN` and the registry here.
This module re-exports the other two's names, so a score and its base are still imported from `runtime.scores`.
"""

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .checkpoint_files import SideFile
from .chunk_scores import (
    INPUT_SOURCES,
    SCORE_AGGREGATIONS,
    AbsoluteOfAggregate,
    ChunkInputs,
    ChunkScore,
    VanillaRollouts,
    check_statistics,
    reading_of,
    rollout_aggregates,
    rollout_score,
    score_rollout,
    statistics_pair,
)
from .phase_scores import (
    ContextPhaseEnergy,
    ContextStartEnergy,
    HeadEnergyTwoSided,
    JointPhaseEnergy,
    JointPhaseTimeEnergy,
    PhaseTerms,
    PhaseZScore,
    fit_phase,
)
from .statistics import ContextNeighbours
from .success_energy import SuccessEnergy, fit_success_energy, fold_readers

logger = logging.getLogger(__name__)

__all__ = [
    "INPUT_SOURCES",
    "NEIGHBOURS_FILE",
    "PACKAGE_SCORES",
    "SCORES",
    "SCORE_AGGREGATIONS",
    "AbsoluteOfAggregate",
    "ChunkInputs",
    "ChunkScore",
    "ContextKNN",
    "ContextPhaseEnergy",
    "ContextStartEnergy",
    "FinalEnergy",
    "HeadEnergyTwoSided",
    "JointPhaseEnergy",
    "JointPhaseTimeEnergy",
    "PhaseTerms",
    "PhaseZScore",
    "SuccessEnergyScore",
    "VanillaRollouts",
    "check_statistics",
    "fit_phase",
    "reading_of",
    "register_score",
    "rollout_aggregates",
    "rollout_score",
    "score_rollout",
    "set_score_order",
    "statistics_pair",
]


@dataclass(frozen=True)
class FinalEnergy(ChunkScore):
    """E(a^(K_inf), C), the paper's score."""

    name = "final_energy"

    def components(self, chunks: ChunkInputs) -> np.ndarray:
        return chunks.final_energy[:, None]


# The context neighbours, beside `ood_calibration.json`: N x D numbers are no JSON.
NEIGHBOURS_FILE = SideFile(
    "context_neighbours",
    "ood_calibration_neighbours.safetensors",
    "context neighbours",
    ContextNeighbours.from_bytes,
    lambda s: {"dim": s.dim, "n_chunks": s.n_chunks, "k": s.k},
)


@dataclass(frozen=True)
class ContextKNN(ChunkScore):
    """The distance of the chunk's standardized pooled context to its k-th nearest vanilla one."""

    # Saved beside the JSON, not compared by `==`.
    neighbours: ContextNeighbours = field(compare=False)

    name = "context_knn"
    reads = ("context_features",)
    side_files = (NEIGHBOURS_FILE,)
    feature_baseline = True

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


# Fewer successful calibration rollouts than this, and the success energy's fit warns.
FEW_SUCCESSFUL_ROLLOUTS = 50
# E_s's weights and standardization, beside the calibration that reads it (a model, not the contexts it saw).
SUCCESS_ENERGY_FILE = SideFile(
    "success_energy",
    "success_energy.safetensors",
    "success energy E_s",
    SuccessEnergy.from_bytes,
    lambda s: {"dim": s.dim, "bins": s.bins},
)


@dataclass(frozen=True)
class SuccessEnergyScore(ChunkScore):
    """The success energy E_s(C, t) of the chunk's pooled context at its chunk index (`success_energy.py`), fitted
    on the successful vanilla rollouts and read as the mean of a window's last `LATE_CHUNKS` chunks ("late").

    A failure score, and the LIBERO checkpoints' (`ebvla-fit-phase-energy` sets it): a rollout whose context at
    chunk t is unlike any successful rollout's at t is heading for failure. On a sixth set of 400 new LIBERO rollouts
    of K, fixed before they were read, over the first 16 chunks it caught 29/32 failures with 22/368 successful
    rollouts alarmed (92.3 %), AUROC 0.973 against the feature distance `chunk_context_nn`'s 0.979 (paired -0.007
    [-0.023, +0.005]: not below it beyond noise) and `joint_phase_time_energy`'s 0.957; on the two sets before, with
    noisy copies twice as wide, it was level at the threshold but 0.012 and 0.006 below in AUROC
    (research/docs/libero_runs.md, "Narrower noisy copies, and a sixth set"). A calibration
    reads each successful rollout with the E_s of the fold that left it out. It was chosen with 95 successful
    calibration rollouts and needs about that many, with their pooled contexts; the fit warns below
    `FEW_SUCCESSFUL_ROLLOUTS`.
    """

    energy: SuccessEnergy = field(compare=False)

    name = "success_energy"
    reads = ("context_features", "chunk_index")
    side_files = (SUCCESS_ENERGY_FILE,)
    rollout_aggregation = "late"
    trains_model = True

    def __post_init__(self):
        check_statistics(self.name, "energy", self.energy, SuccessEnergy)

    @classmethod
    def _rollouts(cls, vanilla: VanillaRollouts, positions: list[int]) -> list:
        chunks = [vanilla.rollouts[i] for i in positions]
        return [(c.get("context_features", cls.name), c.get("chunk_index", cls.name)) for c in chunks]

    @classmethod
    def fit(cls, vanilla: VanillaRollouts) -> "SuccessEnergyScore":
        successful = vanilla.successful(cls.name)
        if len(successful) < FEW_SUCCESSFUL_ROLLOUTS:
            logger.warning(
                "The success energy is fitted on %d successful calibration rollouts; it was chosen and tested with 95 "
                "(LIBERO), and with fewer its threshold rests on few, noisy reads.",
                len(successful),
            )
        return cls(fit_success_energy(cls._rollouts(vanilla, successful)))

    @classmethod
    def held_out_fits(cls, vanilla: VanillaRollouts) -> list["SuccessEnergyScore | None"]:
        successful = vanilla.successful(cls.name)
        readers: list[SuccessEnergyScore | None] = [None] * len(vanilla)
        for position, model in zip(successful, fold_readers(cls._rollouts(vanilla, successful)), strict=True):
            readers[position] = cls(model)
        return readers

    def components(self, chunks: ChunkInputs) -> np.ndarray:
        features = chunks.get("context_features", self.name)
        return self.energy.series(features, chunks.get("chunk_index", self.name))[:, None]

    def to_json(self) -> dict[str, Any]:
        return {SUCCESS_ENERGY_FILE.field: self.energy}

    @classmethod
    def from_json(cls, fields: dict[str, Any]) -> "SuccessEnergyScore":
        return cls(fields.get(SUCCESS_ENERGY_FILE.field))


# The registry: each score by its name. The package's eight; research code adds its own (`register_score`).
SCORES: dict[str, type[ChunkScore]] = {
    score.name: score
    for score in (
        FinalEnergy,
        ContextPhaseEnergy,
        HeadEnergyTwoSided,
        JointPhaseEnergy,
        ContextStartEnergy,
        JointPhaseTimeEnergy,
        SuccessEnergyScore,
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
