"""The energy recorder (`monitoring/recorder.py`) around LeRobot's rollout, with a scripted env and policy (no
simulator), its opt-in baselines on a tiny EB-VLA, and `pipelines.eval_energy`'s env perturbation and
MetaWorld config."""

import math
from collections import OrderedDict
from types import SimpleNamespace

import gymnasium as gym
import numpy as np
import pytest
import torch
from lerobot.scripts.lerobot_eval import rollout
from torch import nn
from torch.utils.hooks import RemovableHandle

from lerobot_policy_ebvla.envs import MetaworldEBVLAEnv
from lerobot_policy_ebvla.modeling_ebvla import EBVLAPolicy, EnergyReadout
from lerobot_policy_ebvla.monitoring.baselines import available_scores
from lerobot_policy_ebvla.monitoring.recorder import EnergyRecorder
from lerobot_policy_ebvla.monitoring.records import read_energy_records, write_energy_records
from lerobot_policy_ebvla.pipelines.eval_energy import (
    env_perturbation,
    frames_read_every,
    metaworld_eval_config,
)

from .conftest import tiny_batch, tiny_config

N_ACTION_STEPS = 3


class CountdownEnv(gym.Env):
    """Ends (successfully) after `length` steps; the rollout keeps stepping it until its batch is done."""

    def __init__(self, length: int, reports_goal_distance: bool = False):
        self.length = length
        self.reports_goal_distance = reports_goal_distance
        self.task = "countdown"
        self.task_description = "count down"
        self._max_episode_steps = 20
        self.observation_space = gym.spaces.Dict({"agent_pos": gym.spaces.Box(-1, 1, (2,))})
        self.action_space = gym.spaces.Box(-1, 1, (2,))

    def reset(self, seed=None, options=None):
        super().reset(seed=seed)
        self.t = 0
        return {"agent_pos": np.zeros(2, dtype=np.float32)}, self._info(done=False)

    def step(self, action):
        self.t += 1
        done = self.t >= self.length
        return {"agent_pos": np.zeros(2, dtype=np.float32)}, 0.0, done, False, self._info(done)

    def _info(self, done: bool) -> dict:
        # The steps left as the "distance" to the goal, as LIBERO's env reports its object's distance.
        return {"is_success": done} | (
            {"goal_distance": float(self.length - self.t)} if self.reports_goal_distance else {}
        )


class ChunkingPolicy(nn.Module):
    """Refines a chunk every `N_ACTION_STEPS` calls and hands its `EnergyReadout` to its chunk hooks."""

    def __init__(self):
        super().__init__()
        self.n_refinements = 0
        self.chunk_hooks = OrderedDict()

    def register_chunk_hook(self, hook):
        handle = RemovableHandle(self.chunk_hooks)
        self.chunk_hooks[handle.id] = hook
        return handle

    def reset(self):
        self.queue = 0

    def select_action(self, batch):
        batch_size = batch["observation.state"].shape[0]
        if self.queue == 0:
            self.n_refinements += 1
            energy = torch.full((batch_size,), float(self.n_refinements))
            readout = EnergyReadout(initial_energy=energy + 0.5, final_energy=energy)
            for hook in list(self.chunk_hooks.values()):
                hook(self, batch, readout, None)
            self.queue = N_ACTION_STEPS
        self.queue -= 1
        return torch.zeros(batch_size, 2)


def identity(x):
    return x


def run_recorded_rollout(lengths, seeds, reports_goal_distance=(False, False), render_every=None):
    policy = ChunkingPolicy()
    env = gym.vector.SyncVectorEnv(
        [lambda n=n, r=r: CountdownEnv(n, r) for n, r in zip(lengths, reports_goal_distance, strict=False)]
    )
    for sub_env in env.envs if render_every is not None else []:
        sub_env.render_every = render_every  # as LIBERO's env with `--env.render_every`
    with EnergyRecorder(policy) as recorder:
        watched = recorder.watch(env, "countdown", 0)
        rollout(watched, policy, identity, identity, identity, identity, seeds=seeds)
    return policy, recorder


def test_records_one_row_per_chunk_while_each_env_runs():
    lengths = [4, 9]
    _, recorder = run_recorded_rollout(lengths, seeds=[7, 8])
    for episode, length in enumerate(lengths):
        chunks = [c for c in recorder.chunks if c.episode_index == episode]
        assert len(chunks) == math.ceil(length / N_ACTION_STEPS)
        assert [c.chunk_index for c in chunks] == list(range(len(chunks)))
        assert [c.env_step for c in chunks] == [k * N_ACTION_STEPS for k in range(len(chunks))]
        assert {c.seed for c in chunks} == {7 + episode}
        assert {c.task for c in chunks} == {"countdown"}
        assert [c.final_energy for c in chunks] == [float(k + 1) for k in range(len(chunks))]
        assert [c.initial_energy for c in chunks] == [k + 1.5 for k in range(len(chunks))]


def test_an_env_rendering_every_n_th_step_must_render_each_step_a_chunk_is_refined_from():
    # The policy refines a chunk every N_ACTION_STEPS steps: an env rendering those steps is recorded as any.
    _, recorder = run_recorded_rollout([4, 9], seeds=[7, 8], render_every=N_ACTION_STEPS)
    assert [c.env_step for c in recorder.chunks if c.episode_index == 1] == [0, 3, 6]
    # One rendering every other step hands the policy a stale frame at step 3: refused, naming the option.
    with pytest.raises(RuntimeError, match="env step 3.*render_every=2"):
        run_recorded_rollout([4, 9], seeds=[7, 8], render_every=2)


def test_records_take_success_from_eval_info_and_drop_episodes_past_n_episodes():
    _, recorder = run_recorded_rollout([4, 9], seeds=None)
    eval_info = {"per_task": [{"task_group": "countdown", "task_id": 0, "metrics": {"successes": [True]}}]}
    records = recorder.records(eval_info, n_episodes=1, perturbation="pose", severity=2)
    assert {r.episode_index for r in records} == {0}
    assert all(
        r.success and r.seed is None and r.perturbation == "pose" and r.severity == 2.0 for r in records
    )


def test_records_keep_the_goal_distance_of_the_observation_each_chunk_was_refined_from(tmp_path):
    lengths = [4, 9]
    _, recorder = run_recorded_rollout(lengths, seeds=None, reports_goal_distance=(True, False))
    eval_info = {
        "per_task": [{"task_group": "countdown", "task_id": 0, "metrics": {"successes": [True, True]}}]
    }
    records = recorder.records(eval_info, n_episodes=2)
    reported = [r for r in records if r.episode_index == 0]
    assert (
        [r.goal_distance for r in reported]
        == [float(lengths[0] - r.env_step) for r in reported]
        == [4.0, 1.0]
    )
    # The sub-env that reports none (gymnasium's `_goal_distance` mask is False there) has None, not a 0.
    assert {r.goal_distance for r in records if r.episode_index == 1} == {None}
    path = tmp_path / "energy_records.jsonl"
    write_energy_records(path, records)
    assert [r.goal_distance for r in read_energy_records(path)] == [r.goal_distance for r in records]


def test_recorder_removes_its_chunk_hook_on_exit():
    policy, _ = run_recorded_rollout([2], seeds=None)
    assert not policy.chunk_hooks and "select_action" not in vars(policy)


def test_a_policy_without_energies_is_evaluated_with_no_records(caplog):
    class PlainPolicy(nn.Module):  # like LeRobot's diffusion policy: actions, no energies, no chunk hook
        def reset(self):
            pass

        def select_action(self, batch):
            return torch.zeros(batch["observation.state"].shape[0], 2)

    policy = PlainPolicy()
    env = gym.vector.SyncVectorEnv([lambda: CountdownEnv(3)])
    with EnergyRecorder(policy) as recorder:
        rollout(
            recorder.watch(env, "countdown", 0), policy, identity, identity, identity, identity, seeds=[0]
        )
    assert recorder.chunks == [] and "no energy to record" in caplog.text


def recorded_actions(policy, **recorder_options):
    """Two refinements for a batch of 2 envs; returns the executed actions and the recorder."""
    batch = tiny_batch(policy.config, batch_size=2, with_action=False)
    env = gym.vector.SyncVectorEnv([lambda: CountdownEnv(50)] * 2)
    policy.eval()
    policy.reset()
    torch.manual_seed(1)
    with EnergyRecorder(policy, **recorder_options) as recorder:
        recorder.watch(env, "g", 0).reset(seed=[0, 1])
        actions = [policy.select_action(batch) for _ in range(policy.config.n_action_steps + 1)]
    return torch.stack(actions), recorder, batch


def test_recorder_records_restart_spread_and_context_features(tiny_policy, tmp_path):
    _, recorder, batch = recorded_actions(tiny_policy, restart_spread_chains=3, record_context_features=True)
    records = recorder.records_from_successes({("g", 0): [True, False]}, n_episodes=2)
    assert [(r.episode_index, r.chunk_index) for r in records] == [(0, 0), (0, 1), (1, 0), (1, 1)]
    assert all(r.restart_spread > 0 for r in records)
    with torch.no_grad():
        pooled = tiny_policy.model.backbone(batch)[-1].mean(dim=1).numpy()
    np.testing.assert_allclose(records[0].context_feature, pooled[0], rtol=1e-5)
    np.testing.assert_allclose(records[3].context_feature, pooled[1], rtol=1e-5)
    read = read_energy_records(write_energy_records(tmp_path / "energy_records.jsonl", records))
    assert [r.restart_spread for r in read] == pytest.approx([r.restart_spread for r in records])
    assert read[2].context_feature.shape == (tiny_policy.config.dim_model,)
    # Each chunk's compute: the policy refines one chain (num_restarts = 1).
    assert [r.mcmc_chains for r in read] == [1, 1, 1, 1]


def test_recorder_records_the_final_energy_relative_to_prior_chunks(tiny_policy, tmp_path):
    _, recorder, batch = recorded_actions(tiny_policy, normalized_energy_samples=64)
    records = recorder.records_from_successes({("g", 0): [True, False]}, n_episodes=2)
    # A fresh estimate of log mean exp(-E) over 4096 prior chunks under the first observation's context.
    config = tiny_policy.config
    prior = config.init_action_std * torch.randn(1, 4096, config.chunk_size, config.action_dim)
    energies = tiny_policy.score_action_chunks({k: v[:1] for k, v in batch.items()}, prior)[0]
    partition = (torch.logsumexp(-energies, dim=0) - math.log(4096)).item()
    first = records[0]
    assert first.normalized_energy - first.final_energy == pytest.approx(
        partition, abs=0.1 + 0.2 * energies.std().item()
    )
    read = read_energy_records(write_energy_records(tmp_path / "energy_records.jsonl", records))
    assert [r.normalized_energy for r in read] == pytest.approx([r.normalized_energy for r in records])
    assert "normalized_energy" in available_scores([read])
    with pytest.raises(ValueError, match="normalized_energy_samples"):
        EnergyRecorder(tiny_policy, normalized_energy_samples=-1)


def test_recording_the_baselines_leaves_the_executed_actions_unchanged(tiny_policy):
    plain, _, _ = recorded_actions(tiny_policy)
    with_baselines, _, _ = recorded_actions(
        tiny_policy, restart_spread_chains=3, record_context_features=True, normalized_energy_samples=8
    )
    torch.testing.assert_close(plain, with_baselines)


def test_recorder_without_baselines_leaves_them_empty(tiny_policy):
    _, recorder, _ = recorded_actions(tiny_policy)
    records = recorder.records_from_successes({("g", 0): [True, True]}, n_episodes=2)
    assert all(r.restart_spread is None and r.context_feature is None for r in records)
    assert all(r.normalized_energy is None for r in records)


def test_restart_spread_needs_at_least_two_chains(tiny_policy):
    with pytest.raises(ValueError, match="restart_spread_chains"):
        EnergyRecorder(tiny_policy, restart_spread_chains=1)


def test_perturbation_of_an_env_config():
    assert env_perturbation(MetaworldEBVLAEnv(perturbation="fov", perturbation_severity=3)) == (
        "fov",
        3.0,
    )
    assert env_perturbation(MetaworldEBVLAEnv(perturbation="fov", perturbation_severity=0)) == (
        "none",
        0.0,
    )
    assert env_perturbation(SimpleNamespace(task="an env without perturbations")) == ("none", 0.0)


def test_metaworld_eval_config_applies_the_perturbation_and_the_extra_options(tmp_path):
    tiny_config().save_pretrained(tmp_path / "pretrained_model")

    cfg = metaworld_eval_config(
        tmp_path / "pretrained_model",
        tmp_path / "eval",
        task="push-v3",
        device="cpu",
        max_episode_steps=40,
        n_episodes=3,
        seed=2000,
        perturbation="light_dim",
        severity=4,
        normalized_energy_samples=8,
    )

    assert cfg.policy.pretrained_path == tmp_path / "pretrained_model" and cfg.policy.device == "cpu"
    assert cfg.normalized_energy_samples == 8
    assert (cfg.env.perturbation, cfg.env.perturbation_severity) == ("light_dim", 4)
    assert cfg.env.task == "push-v3" and cfg.env.fast_render and cfg.env.max_episode_steps == 40
    assert (cfg.eval.n_episodes, cfg.eval.batch_size, cfg.seed) == (3, 1, 2000)


def test_metaworld_eval_config_draws_only_the_frames_an_ebvla_policy_reads_unless_told(tmp_path):
    config = tiny_config()
    config.n_action_steps = 4
    config.save_pretrained(tmp_path / "pretrained_model")
    common = {"task": "push-v3", "device": "cpu", "max_episode_steps": 40, "n_episodes": 1, "seed": 0}

    assert (
        metaworld_eval_config(tmp_path / "pretrained_model", tmp_path / "a", **common).env.render_every == 4
    )
    told = metaworld_eval_config(tmp_path / "pretrained_model", tmp_path / "b", render_every=1, **common)
    assert told.env.render_every == 1
    # Diffusion Policy reads a history of frames: every one is drawn.
    assert frames_read_every(SimpleNamespace(type="diffusion", n_action_steps=8)) == 1


def test_recorder_records_the_joint_energys_context_term_apart(tmp_path):
    """A joint-energy policy's records carry E_c (`context_energy`), that of each chunk's own observation."""
    torch.manual_seed(0)
    policy = EBVLAPolicy(tiny_config(joint_energy={"weight": 1.0, "target": "observation"}))
    _, recorder, batch = recorded_actions(policy)
    records = recorder.records_from_successes({("g", 0): [True, False]}, n_episodes=2)
    with torch.no_grad():
        expected = policy.model.context_energy_of(batch, None).tolist()
    assert [r.context_energy for r in records] == pytest.approx(
        [expected[0]] * 2 + [expected[1]] * 2, abs=1e-5
    )
    read = read_energy_records(write_energy_records(tmp_path / "energy_records.jsonl", records))
    assert [r.context_energy for r in read] == pytest.approx([r.context_energy for r in records])


def test_records_of_a_policy_without_a_joint_energy_have_no_context_term(tiny_policy):
    _, recorder, _ = recorded_actions(tiny_policy)
    records = recorder.records_from_successes({("g", 0): [True, True]}, n_episodes=2)
    assert all(r.context_energy is None for r in records)
