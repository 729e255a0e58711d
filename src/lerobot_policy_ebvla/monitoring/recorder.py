"""Recording the energy of every chunk a policy refines during LeRobot rollouts: the `EnergyRecord`s.

`EnergyRecorder` needs nothing from the rollout loop but the policy and the vector env it steps:

    with EnergyRecorder(policy, restart_spread_chains=8, record_context_features=True) as recorder:
        env = recorder.watch(vec_env, task_group="metaworld", task_id=0)
        info = eval_policy(env, policy, ...)          # or LeRobot's `rollout`, or any loop calling
                                                       # `policy.select_action` and `env.step`
    records = recorder.records(info, n_episodes=10)    # successes from lerobot-eval's info dict
    write_energy_records("outputs/eval/energy_records.jsonl", records)

While active, the recorder is registered with `policy.register_chunk_hook`: after every chunk the policy
refines (whichever loop calls `select_action`) it receives the observation batch, the chunk's `EnergyReadout`
and the OOD decision. The watched env reports its resets, steps and which sub-envs are done: LeRobot's
`rollout` keeps stepping finished sub-envs until the whole batch is done, and only chunks of sub-envs still
running belong to an episode. Where the env's info has a `goal_distance` (our LIBERO env's: how far the task's
object is from its container), each chunk keeps the one of the observation it was refined from.

Opt-in scores (`baselines.py`) are the policy's own quantities, computed from the same observation right after
each refinement, without touching the executed chunk or the global random state (they draw from the
recorder's own generator):
- `restart_spread_chains=N` (N >= 2): `policy.restart_spread`, the std over N more chains refined from
  independent a^(0), averaged over the chunk's H x d_a normalized actions. It costs N refinements per chunk.
- `normalized_energy_samples=N` (N >= 1): `policy.normalized_energy`, E(a^(K_inf), C) + log mean_j
  exp(-E(a_j, C)) over N chunks drawn from the MCMC prior under the same context (one batched evaluation).
- `record_context_features=True`: `policy.context_features`, the pooled last-block context, a (D,) vector.
"""

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from .records import VANILLA_PERTURBATION, EnergyRecord

logger = logging.getLogger(__name__)


@dataclass
class _Chunk:
    task_group: str
    task_id: int
    task: str
    episode_index: int
    chunk_index: int
    env_step: int
    initial_energy: float
    final_energy: float
    seed: int | None
    restart_spread: float | None = None
    normalized_energy: float | None = None
    held: bool | None = None
    mcmc_chains: int | None = None
    context_energy: float | None = None
    context_feature: np.ndarray | None = None
    goal_distance: float | None = None
    phase_energy: float | None = None


class WatchedVecEnv:
    """Forwards everything to a vector env, and tracks the step count and which sub-envs are done."""

    def __init__(self, env: Any, recorder: "EnergyRecorder", task_group: str, task_id: int):
        self._env = env
        self._recorder = recorder
        self.task_group = task_group
        self.task_id = task_id
        self.batch_index = -1
        self.step_index = 0
        self.done = np.zeros(env.num_envs, dtype=bool)
        self.seeds: list[int | None] = [None] * env.num_envs
        self.chunk_counts = np.zeros(env.num_envs, dtype=int)
        self.task = ""
        # Each sub-env's `info["goal_distance"]` of its last reset or step: the observation a chunk is refined from.
        self.goal_distances: list[float | None] = [None] * env.num_envs
        # An env that renders only every N-th step's frames (our LIBERO env's `render_every`): 1 renders all.
        # Asked at the first reset, when an async env's workers run.
        self.render_every = 1

    def __getattr__(self, name: str) -> Any:
        if name == "_env":  # not set yet (e.g. while unpickling): avoid recursing
            raise AttributeError(name)
        return getattr(self._env, name)

    def reset(self, **kwargs: Any) -> Any:
        result = self._env.reset(**kwargs)
        self.goal_distances = _goal_distances(result[1], self.num_envs)
        self.render_every = _render_every(self._env)
        seeds = kwargs.get("seed")
        self.batch_index += 1
        self.step_index = 0
        self.done[:] = False
        self.chunk_counts[:] = 0
        self.seeds = list(seeds) if isinstance(seeds, list | tuple | range) else [seeds] * self.num_envs
        self.task = _task_name(self._env, default=f"{self.task_group}_{self.task_id}")
        self._recorder.watching = self
        return result

    def step(self, actions: Any) -> Any:
        result = self._env.step(actions)
        _, _, terminated, truncated, info = result
        self.goal_distances = _goal_distances(info, self.num_envs)
        self.done |= np.asarray(terminated, dtype=bool) | np.asarray(truncated, dtype=bool)
        self.step_index += 1
        return result

    def close(self) -> None:
        self._env.close()


def _render_every(env: Any) -> int:
    """The sub-envs' `render_every` (1 where they have none, or where an async env cannot be asked)."""
    try:
        values = env.get_attr("render_every")
    except (AttributeError, NotImplementedError):
        return 1
    return max(int(value) for value in values)


def _goal_distances(info: Any, num_envs: int) -> list[float | None]:
    """Each sub-env's `goal_distance` from a vector env's info (gymnasium's `_goal_distance` marks the sub-envs
    that reported one); None where it is absent or NaN."""
    values = info.get("goal_distance") if isinstance(info, dict) else None
    if values is None:
        return [None] * num_envs
    reported = info.get("_goal_distance", np.ones(num_envs, dtype=bool))
    return [
        float(value) if has and np.isfinite(value) else None
        for value, has in zip(np.asarray(values, dtype=np.float64), reported, strict=True)
    ]


def _per_env(values: Any) -> list[float] | None:
    """A (B,) energy tensor as one float per environment; None stays None."""
    return None if values is None else values.detach().float().cpu().reshape(-1).tolist()


def _task_name(env: Any, default: str) -> str:
    for attribute in ("task", "task_description"):
        try:
            return str(env.call(attribute)[0])
        except (AttributeError, NotImplementedError):
            continue
    return default


class EnergyRecorder:
    """Records each refined chunk's energies (and opt-in baselines) during rollouts; see the module docstring.

    Args:
        policy: An `EBVLAPolicy` (anything with `register_chunk_hook`; the opt-in scores also need its
            `restart_spread`, `normalized_energy` and `context_features`).
        restart_spread_chains: N >= 2 records the restart spread over N chains; 0 (default) does not.
        normalized_energy_samples: N >= 1 records the normalized energy with N prior chunks; 0 (default) does not.
        record_context_features: Record the pooled backbone context of every chunk's observation.
        seed: Seed of the generator of the restart-spread chains and the prior chunks.
    """

    def __init__(
        self,
        policy: Any,
        restart_spread_chains: int = 0,
        record_context_features: bool = False,
        seed: int = 0,
        normalized_energy_samples: int = 0,
    ):
        if restart_spread_chains == 1 or restart_spread_chains < 0:
            raise ValueError(
                f"`restart_spread_chains` must be 0 (off) or >= 2 chains, got {restart_spread_chains}."
            )
        if normalized_energy_samples < 0:
            raise ValueError(
                f"`normalized_energy_samples` must be 0 (off) or >= 1, got {normalized_energy_samples}."
            )
        self.normalized_energy_samples = normalized_energy_samples
        self.policy = policy
        self.restart_spread_chains = restart_spread_chains
        self.record_context_features = record_context_features
        self.seed = seed
        self.watching: WatchedVecEnv | None = None
        self.chunks: list[_Chunk] = []
        self._generator: torch.Generator | None = None
        self._hook: Any = None

    def __enter__(self) -> "EnergyRecorder":
        if hasattr(self.policy, "register_chunk_hook"):
            self._hook = self.policy.register_chunk_hook(self._on_chunk)
        else:  # another LeRobot policy (the diffusion baseline) is evaluated the same way, without energies
            logger.warning("%s has no energy to record: no records are written.", type(self.policy).__name__)
        return self

    def __exit__(self, *exc: Any) -> None:
        if self._hook is not None:
            self._hook.remove()
            self._hook = None

    def _on_chunk(self, policy: Any, batch: dict[str, Any], readout: Any, decision: Any) -> None:
        self._record(readout, batch, decision)

    def watch(self, env: Any, task_group: str, task_id: int) -> WatchedVecEnv:
        """Wraps a vector env so the recorder knows each chunk's episode, step and seed."""
        return WatchedVecEnv(env, self, task_group, task_id)

    def _generator_for_baselines(self) -> torch.Generator:
        if self._generator is None:
            device = next(self.policy.parameters()).device
            self._generator = torch.Generator(device).manual_seed(self.seed)
        return self._generator

    def _baselines(self, batch: dict[str, Any], final_energy: Tensor) -> tuple[list | None, ...]:
        spread = features = normalized = None
        if self.restart_spread_chains:
            n = self.restart_spread_chains
            spread = self.policy.restart_spread(batch, n, self._generator_for_baselines()).cpu().tolist()
        if self.normalized_energy_samples:
            n = self.normalized_energy_samples
            normalized = self.policy.normalized_energy(
                batch, final_energy, n, self._generator_for_baselines()
            )
            normalized = normalized.cpu().tolist()
        if self.record_context_features:
            features = list(self.policy.context_features(batch).cpu().numpy())
        return spread, features, normalized

    def _record(self, readout: Any, batch: dict[str, Any], decision: Any) -> None:
        env = self.watching
        if env is None:
            raise RuntimeError("Energies were produced for an env that `EnergyRecorder.watch` did not wrap.")
        if env.step_index % env.render_every:
            # The frames between rendered steps are the last rendered ones: this chunk would be refined from a
            # stale observation, and its rollout would not be the one an env rendering every step gives.
            raise RuntimeError(
                f"A chunk was refined from the observation of env step {env.step_index}, which the env did not "
                f"render (`render_every={env.render_every}`): set `--env.render_every` to the policy's "
                "n_action_steps, or to 1."
            )
        initial, final = _per_env(readout.initial_energy), _per_env(readout.final_energy)
        if len(initial) != env.num_envs or len(final) != env.num_envs:
            raise ValueError(
                f"Expected energies of shape ({env.num_envs},), got {len(initial)} and {len(final)}."
            )
        spread, features, normalized = self._baselines(batch, readout.final_energy.detach())
        held = None if decision is None else decision.held.reshape(-1).tolist()
        chains = getattr(readout, "chains", None)
        chains = None if chains is None else chains.reshape(-1).tolist()
        context_energy = _per_env(getattr(readout, "context_energy", None))
        phase_energy = _per_env(getattr(readout, "phase_energy", None))
        for i in np.flatnonzero(~env.done):
            self.chunks.append(
                _Chunk(
                    task_group=env.task_group,
                    task_id=env.task_id,
                    task=env.task,
                    episode_index=env.batch_index * env.num_envs + int(i),
                    chunk_index=int(env.chunk_counts[i]),
                    env_step=env.step_index,
                    initial_energy=initial[i],
                    final_energy=final[i],
                    seed=None if env.seeds[i] is None else int(env.seeds[i]),
                    restart_spread=None if spread is None else spread[i],
                    normalized_energy=None if normalized is None else normalized[i],
                    held=None if held is None else bool(held[i]),
                    mcmc_chains=None if chains is None else int(chains[i]),
                    context_energy=None if context_energy is None else context_energy[i],
                    context_feature=None if features is None else features[i],
                    goal_distance=env.goal_distances[i],
                    phase_energy=None if phase_energy is None else phase_energy[i],
                )
            )
            env.chunk_counts[i] += 1

    def records(
        self,
        eval_info: dict,
        n_episodes: int,
        perturbation: str = VANILLA_PERTURBATION,
        severity: float = 0.0,
    ) -> list[EnergyRecord]:
        """The recorded chunks as `EnergyRecord`s, each episode's success from lerobot-eval's `eval_info`.

        Episodes past `n_episodes` (the unused rest of the last batch) are dropped, as lerobot-eval does.
        """
        successes = {
            (task["task_group"], task["task_id"]): task["metrics"]["successes"]
            for task in eval_info["per_task"]
        }
        return self.records_from_successes(successes, n_episodes, perturbation, severity)

    def records_from_successes(
        self,
        successes: dict[tuple[str, int], list[bool]],
        n_episodes: int,
        perturbation: str = VANILLA_PERTURBATION,
        severity: float = 0.0,
    ) -> list[EnergyRecord]:
        """The recorded chunks as `EnergyRecord`s, given {(task_group, task_id): success of each episode}."""
        # Chunks were recorded step by step, interleaving the envs of a batch: list them episode by episode.
        task_order = {
            key: i for i, key in enumerate(dict.fromkeys((c.task_group, c.task_id) for c in self.chunks))
        }
        chunks = sorted(
            self.chunks, key=lambda c: (task_order[c.task_group, c.task_id], c.episode_index, c.chunk_index)
        )
        return [
            EnergyRecord(
                episode_index=chunk.episode_index,
                chunk_index=chunk.chunk_index,
                env_step=chunk.env_step,
                initial_energy=chunk.initial_energy,
                final_energy=chunk.final_energy,
                success=bool(successes[(chunk.task_group, chunk.task_id)][chunk.episode_index]),
                task=chunk.task,
                seed=chunk.seed,
                perturbation=perturbation,
                severity=float(severity),
                restart_spread=chunk.restart_spread,
                normalized_energy=chunk.normalized_energy,
                held=chunk.held,
                mcmc_chains=chunk.mcmc_chains,
                context_energy=chunk.context_energy,
                context_feature=chunk.context_feature,
                goal_distance=chunk.goal_distance,
                phase_energy=chunk.phase_energy,
            )
            for chunk in chunks
            if chunk.episode_index < n_episodes
        ]
