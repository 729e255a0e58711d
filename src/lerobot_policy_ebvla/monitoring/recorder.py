"""Recording the energy of every chunk a policy refines during LeRobot rollouts: the `EnergyRecord`s.

`EnergyRecorder` needs nothing from the rollout loop but the policy and the vector env it steps:

    with EnergyRecorder(policy, restart_spread_chains=8, record_context_features=True) as recorder:
        env = recorder.watch(vec_env, task_group="metaworld", task_id=0)
        info = eval_policy(env, policy, ...)          # or LeRobot's `rollout`, or any loop calling
                                                       # `policy.select_action` and `env.step`
    records = recorder.records(info, n_episodes=10)    # successes from lerobot-eval's info dict
    write_energy_records("outputs/eval/energy_records.jsonl", records)

While active, the policy's `select_action` is shadowed on the instance (the rollout calls
`policy.select_action(observation)`); EB-VLA sets `policy.last_energy` to a new `EnergyReadout` each time
it refines a chunk, so a refinement is detected by object identity. The watched env reports its resets,
steps and which sub-envs are done: LeRobot's `rollout` keeps stepping finished sub-envs until the whole
batch is done, and only chunks of sub-envs still running belong to an episode.

Opt-in scores (`baselines.py`) are computed from the same observation right after each refinement,
without touching the executed chunk or the global random state (they draw from their own generator):
- `restart_spread_chains=N` (N >= 2): refines N more chunks from independent a^(0) with
  `policy.model.generate_actions` on the observation repeated N times, and records the std over the N
  chains, averaged over the chunk's H x d_a normalized actions. It costs N extra refinements per chunk.
- `normalized_energy_samples=N` (N >= 1): scores N chunks drawn from the MCMC prior N(0, sigma_init^2 I)
  under the same context (`policy.score_action_chunks`, one batched energy evaluation) and records
  E(a^(K_inf), C) + log mean_j exp(-E(a_j, C)).
- `record_context_features=True`: records the pooled context, the mean over tokens of the last block's
  context of `policy.model.backbone(batch)`, a (D,) vector per chunk.
"""

import logging
import math
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
    context_feature: np.ndarray | None = None


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

    def __getattr__(self, name: str) -> Any:
        if name == "_env":  # not set yet (e.g. while unpickling): avoid recursing
            raise AttributeError(name)
        return getattr(self._env, name)

    def reset(self, **kwargs: Any) -> Any:
        result = self._env.reset(**kwargs)
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
        _, _, terminated, truncated, _ = result
        self.done |= np.asarray(terminated, dtype=bool) | np.asarray(truncated, dtype=bool)
        self.step_index += 1
        return result

    def close(self) -> None:
        self._env.close()


def _task_name(env: Any, default: str) -> str:
    for attribute in ("task", "task_description"):
        try:
            return str(env.call(attribute)[0])
        except (AttributeError, NotImplementedError):
            continue
    return default


def repeat_batch(batch: dict[str, Any], batch_size: int, n: int) -> dict[str, Any]:
    """Each observation of a batch repeated n times in a row: (B, ...) -> (B * n, ...); lists likewise.

    Tensors made under `torch.inference_mode` (lerobot-eval) come back as normal tensors autograd can use.
    """

    def repeat(value: Any) -> Any:
        if isinstance(value, Tensor) and value.ndim > 0 and value.shape[0] == batch_size:
            return value.clone().repeat_interleave(n, dim=0)
        if isinstance(value, list | tuple) and len(value) == batch_size:
            return [item for item in value for _ in range(n)]
        return value.clone() if isinstance(value, Tensor) else value

    return {key: repeat(value) for key, value in batch.items()}


def restart_spread(policy: Any, batch: dict[str, Any], n_chains: int, generator: torch.Generator) -> Tensor:
    """(B,) spread of `n_chains` chunks refined for each observation: std over chains, mean over (H, d_a)."""
    batch_size = next(v.shape[0] for v in batch.values() if isinstance(v, Tensor) and v.ndim > 0)
    with torch.inference_mode(False):
        actions, _ = policy.model.generate_actions(
            repeat_batch(batch, batch_size, n_chains), generator=generator
        )
    actions = actions.float().view(batch_size, n_chains, *actions.shape[1:])  # (B, N, H, d_a)
    return actions.std(dim=1, unbiased=False).mean(dim=(1, 2))


def log_partition(policy: Any, batch: dict[str, Any], n_samples: int, generator: torch.Generator) -> Tensor:
    """(B,) log mean_j exp(-E(a_j, C)) over `n_samples` chunks a_j ~ N(0, sigma_init^2 I), the MCMC prior."""
    config = policy.config
    batch_size = next(v.shape[0] for v in batch.values() if isinstance(v, Tensor) and v.ndim > 0)
    shape = (batch_size, n_samples, config.chunk_size, config.action_dim)
    device = next(policy.parameters()).device
    samples = config.init_action_std * torch.randn(shape, device=device, generator=generator)
    energies = policy.score_action_chunks(batch, samples).float()  # (B, N)
    return torch.logsumexp(-energies, dim=1) - math.log(n_samples)


def pooled_context(policy: Any, batch: dict[str, Any]) -> Tensor:
    """(B, D) mean over tokens of the last block's backbone context C_L."""
    batch_size = next(v.shape[0] for v in batch.values() if isinstance(v, Tensor) and v.ndim > 0)
    with torch.inference_mode(False), torch.no_grad():
        contexts = policy.model.backbone(repeat_batch(batch, batch_size, 1))
    return contexts[-1].float().mean(dim=1)


class EnergyRecorder:
    """Records each refined chunk's energies (and opt-in baselines) during rollouts; see the module docstring.

    Args:
        policy: An `EBVLAPolicy` (anything exposing `select_action` and `last_energy`; the baselines also
            need `policy.model.generate_actions` and `policy.model.backbone`).
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
        self._last_readout: Any = None
        self._n_select_action_calls = 0

    def __enter__(self) -> "EnergyRecorder":
        select_action = self.policy.select_action

        def select_action_and_record(batch: dict[str, Any], *args: Any, **kwargs: Any) -> Any:
            action = select_action(batch, *args, **kwargs)
            self._n_select_action_calls += 1
            readout = getattr(self.policy, "last_energy", None)
            if readout is not None and readout is not self._last_readout:
                self._last_readout = readout
                self._record(readout, batch)
            return action

        # An instance attribute shadows the method: `rollout` calls `policy.select_action(observation)`.
        self.policy.select_action = select_action_and_record
        return self

    def __exit__(self, *exc: Any) -> None:
        del self.policy.select_action
        if self._n_select_action_calls and not self.chunks:
            logger.warning("The policy exposes no `last_energy`: no energy was recorded.")

    def watch(self, env: Any, task_group: str, task_id: int) -> WatchedVecEnv:
        """Wraps a vector env so the recorder knows each chunk's episode, step and seed."""
        return WatchedVecEnv(env, self, task_group, task_id)

    def _generator_for_baselines(self) -> torch.Generator:
        if self._generator is None:
            device = next(self.policy.parameters()).device
            self._generator = torch.Generator(device).manual_seed(self.seed)
        return self._generator

    def _baselines(self, batch: dict[str, Any]) -> tuple[list | None, list | None, list | None]:
        spread = features = partition = None
        if self.restart_spread_chains:
            n = self.restart_spread_chains
            spread = restart_spread(self.policy, batch, n, self._generator_for_baselines()).cpu().tolist()
        if self.normalized_energy_samples:
            n = self.normalized_energy_samples
            partition = log_partition(self.policy, batch, n, self._generator_for_baselines()).cpu().tolist()
        if self.record_context_features:
            features = list(pooled_context(self.policy, batch).cpu().numpy())
        return spread, features, partition

    def _record(self, readout: Any, batch: dict[str, Any]) -> None:
        env = self.watching
        if env is None:
            raise RuntimeError("Energies were produced for an env that `EnergyRecorder.watch` did not wrap.")
        initial = readout.initial_energy.detach().float().cpu().reshape(-1).tolist()
        final = readout.final_energy.detach().float().cpu().reshape(-1).tolist()
        if len(initial) != env.num_envs or len(final) != env.num_envs:
            raise ValueError(
                f"Expected energies of shape ({env.num_envs},), got {len(initial)} and {len(final)}."
            )
        spread, features, partition = self._baselines(batch)
        # Set with `last_energy` by an EB-VLA policy that has an OOD response (`ood_response.py`).
        decision = getattr(self.policy, "last_ood_decision", None)
        held = None if decision is None else decision.held.reshape(-1).tolist()
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
                    normalized_energy=None if partition is None else final[i] + partition[i],
                    held=None if held is None else bool(held[i]),
                    context_feature=None if features is None else features[i],
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
                context_feature=chunk.context_feature,
            )
            for chunk in chunks
            if chunk.episode_index < n_episodes
        ]
