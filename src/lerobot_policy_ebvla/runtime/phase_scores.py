"""The chunk scores that read their inputs against the vanilla rollouts' values at the same chunk index.

`PhaseZScore` standardizes one per-chunk input, z_t = (x_t - mu_v[t]) / sigma_v[t] (`PhaseStatistics`, t the
chunk's index in its episode), and `PhaseTerms` several, each z aggregated over the rollout before they are
averaged. The package's scores built on them: `ContextPhaseEnergy`, `HeadEnergyTwoSided`, `JointPhaseEnergy`,
`ContextStartEnergy` and `JointPhaseTimeEnergy`; `scores.py` registers them in `SCORES`.
"""

from dataclasses import dataclass, fields
from typing import Any, ClassVar, Self

import numpy as np

from .chunk_scores import (
    AbsoluteOfAggregate,
    ChunkInputs,
    ChunkScore,
    VanillaRollouts,
    check_statistics,
    statistics_pair,
)
from .statistics import PhaseStatistics, energies_by_index


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
    92.3 % and 92.9 % on two sets of 400 new ones; the feature distance `chunk_context_nn` still reached 95.8-97.0 %,
    with about half the false alarms (research/docs/libero_runs.md, "A phase energy for the failure check" and the
    two sections after it).
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
