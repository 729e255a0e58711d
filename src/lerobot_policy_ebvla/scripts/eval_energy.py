"""`ebvla-eval`: lerobot-eval that also records the energy of every action chunk the policy refines.

It takes lerobot-eval's arguments and runs LeRobot's own evaluation (`eval_policy_all` and its `rollout`).
Alongside `eval_info.json` it writes `energy_records.jsonl`: one `EnergyRecord` per episode and predicted
chunk, with the env step of the prediction, the initial and final energies, the episode's success and seed,
and the camera perturbation of the env (`--env.type=metaworld_ebvla`; "none" for other envs).

Example:

    MUJOCO_GL=egl ebvla-eval --policy.path=outputs/train/ebvla_reach/checkpoints/last/pretrained_model \\
        --env.type=metaworld_ebvla --env.task=reach-v3 --env.fast_render=true \\
        --env.camera_perturbation=pose --env.perturbation_severity=3 \\
        --eval.n_episodes=10 --eval.batch_size=1 --output_dir=outputs/eval/reach_pose3

Unlike lerobot-eval, which always renders videos of the first 10 episodes, videos are off unless
`--max_episodes_rendered` is set: rendering them doubles the cost of an env step.
"""

import json
import logging
import sys
from contextlib import nullcontext
from dataclasses import asdict, dataclass
from pathlib import Path
from pprint import pformat
from typing import Any

import numpy as np
import torch
from lerobot.configs import parser
from lerobot.configs.eval import EvalPipelineConfig
from lerobot.envs import close_envs, make_env, make_env_pre_post_processors
from lerobot.policies import make_policy, make_pre_post_processors
from lerobot.scripts.lerobot_eval import eval_policy_all
from lerobot.utils.device_utils import get_safe_torch_device
from lerobot.utils.import_utils import register_third_party_plugins
from lerobot.utils.random_utils import set_seed
from lerobot.utils.utils import init_logging

from lerobot_policy_ebvla.envs import MetaworldEBVLAEnv
from lerobot_policy_ebvla.monitoring.records import (
    ENERGY_RECORDS_FILENAME,
    VANILLA_PERTURBATION,
    EnergyRecord,
    write_energy_records,
)

logger = logging.getLogger(__name__)


@dataclass
class EnergyEvalPipelineConfig(EvalPipelineConfig):
    # Episodes rendered to videos in `<output_dir>/videos` (lerobot-eval renders 10).
    max_episodes_rendered: int = 0


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


class _WatchedVecEnv:
    """Forwards everything to a vector env, and tracks the step count and which sub-envs are done.

    LeRobot's `rollout` keeps stepping sub-envs whose episode ended until the whole batch is done; only
    chunks predicted for sub-envs that are still running belong to an episode.
    """

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


class EnergyRecorder:
    """Records `policy.last_energy` after each chunk refinement during LeRobot's rollout.

    EB-VLA's `select_action` sets `last_energy` to a new `EnergyReadout` each time it refines a chunk, so a
    refinement is detected by object identity. While active (`with EnergyRecorder(policy) as recorder`),
    the policy's `select_action` is wrapped; envs passed through `watch` report their steps and resets.
    """

    def __init__(self, policy: Any):
        self.policy = policy
        self.watching: _WatchedVecEnv | None = None
        self.chunks: list[_Chunk] = []
        self._last_readout: Any = None
        self._n_select_action_calls = 0

    def __enter__(self) -> "EnergyRecorder":
        select_action = self.policy.select_action

        def select_action_and_record(*args: Any, **kwargs: Any) -> Any:
            action = select_action(*args, **kwargs)
            self._n_select_action_calls += 1
            self._record(getattr(self.policy, "last_energy", None))
            return action

        # An instance attribute shadows the method: `rollout` calls `policy.select_action(observation)`.
        self.policy.select_action = select_action_and_record
        return self

    def __exit__(self, *exc: Any) -> None:
        del self.policy.select_action
        if self._n_select_action_calls and not self.chunks:
            logger.warning("The policy exposes no `last_energy`: no energy was recorded.")

    def watch(self, env: Any, task_group: str, task_id: int) -> _WatchedVecEnv:
        return _WatchedVecEnv(env, self, task_group, task_id)

    def _record(self, readout: Any) -> None:
        if readout is None or readout is self._last_readout:
            return
        self._last_readout = readout
        env = self.watching
        if env is None:
            raise RuntimeError("Energies were produced for an env that `EnergyRecorder.watch` did not wrap.")
        initial = readout.initial_energy.detach().float().cpu().reshape(-1).tolist()
        final = readout.final_energy.detach().float().cpu().reshape(-1).tolist()
        if len(initial) != env.num_envs or len(final) != env.num_envs:
            raise ValueError(
                f"Expected energies of shape ({env.num_envs},), got {len(initial)} and {len(final)}."
            )
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
        """The recorded chunks as `EnergyRecord`s, with each episode's success from lerobot's `eval_info`.

        Episodes past `n_episodes` (the unused rest of the last batch) are dropped, as lerobot-eval does.
        """
        successes = {
            (task["task_group"], task["task_id"]): task["metrics"]["successes"]
            for task in eval_info["per_task"]
        }
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
            )
            for chunk in chunks
            if chunk.episode_index < n_episodes
        ]


def env_perturbation(env_cfg: Any) -> tuple[str, float]:
    """(perturbation name, severity) of an env config: the camera perturbation of `metaworld_ebvla`."""
    if isinstance(env_cfg, MetaworldEBVLAEnv):
        return env_cfg.perturbation, float(env_cfg.perturbation_severity)
    return VANILLA_PERTURBATION, 0.0


@parser.wrap()
def eval_energy_main(cfg: EnergyEvalPipelineConfig) -> None:
    """lerobot-eval's `eval_main`, with the policy's energies recorded and written beside `eval_info.json`."""
    logging.info(pformat(asdict(cfg)))
    if cfg.env.max_parallel_tasks > 1:
        raise ValueError("ebvla-eval evaluates tasks one after the other: set `--env.max_parallel_tasks=1`.")

    device = get_safe_torch_device(cfg.policy.device, log=True)
    torch.backends.cudnn.benchmark = True
    torch.backends.cuda.matmul.allow_tf32 = True
    set_seed(cfg.seed)
    output_dir = Path(cfg.output_dir)
    logging.info(f"Output dir: {output_dir}")

    envs = make_env(
        cfg.env,
        n_envs=cfg.eval.batch_size,
        use_async_envs=cfg.eval.use_async_envs,
        trust_remote_code=cfg.trust_remote_code,
    )
    policy = make_policy(cfg=cfg.policy, env_cfg=cfg.env, rename_map=cfg.rename_map)
    policy.eval()
    preprocessor, postprocessor = make_pre_post_processors(
        policy_cfg=cfg.policy,
        pretrained_path=cfg.policy.pretrained_path,
        preprocessor_overrides={
            "device_processor": {"device": str(policy.config.device)},
            "rename_observations_processor": {"rename_map": cfg.rename_map},
        },
    )
    env_preprocessor, env_postprocessor = make_env_pre_post_processors(env_cfg=cfg.env, policy_cfg=cfg.policy)
    recording_dir = output_dir / "recordings" if cfg.eval.recording else None

    amp = torch.autocast(device_type=device.type) if cfg.policy.use_amp else nullcontext()
    with EnergyRecorder(policy) as recorder, torch.no_grad(), amp:
        watched = {
            group: {task_id: recorder.watch(env, group, task_id) for task_id, env in tasks.items()}
            for group, tasks in envs.items()
        }
        info = eval_policy_all(
            envs=watched,
            policy=policy,
            env_preprocessor=env_preprocessor,
            env_postprocessor=env_postprocessor,
            preprocessor=preprocessor,
            postprocessor=postprocessor,
            n_episodes=cfg.eval.n_episodes,
            max_episodes_rendered=cfg.max_episodes_rendered,
            videos_dir=output_dir / "videos" if cfg.max_episodes_rendered > 0 else None,
            return_episode_data=False,
            start_seed=cfg.seed,
            max_parallel_tasks=1,
            recording_dir=recording_dir,
            env_features=cfg.env.features if cfg.eval.recording else None,
            recording_repo_id=cfg.eval.recording_repo_id,
            recording_private=cfg.eval.recording_private,
        )
    close_envs(envs)
    logger.info("Overall aggregated metrics: %s", info["overall"])

    perturbation, severity = env_perturbation(cfg.env)
    records = recorder.records(info, cfg.eval.n_episodes, perturbation, severity)
    output_dir.mkdir(parents=True, exist_ok=True)
    with open(output_dir / "eval_info.json", "w") as f:
        json.dump(info, f, indent=2)
    # eval_info.json is overwritten by a new run in the same folder; the energies must follow it.
    path = write_energy_records(output_dir / ENERGY_RECORDS_FILENAME, records, overwrite=True)
    logging.info(f"Wrote {len(records)} energy records to {path}")


def main() -> None:
    init_logging()
    register_third_party_plugins()
    eval_energy_main()


def metaworld_eval_command(
    checkpoint: Path,
    output_dir: Path,
    *,
    task: str,
    device: str,
    max_episode_steps: int,
    n_episodes: int,
    seed: int,
    perturbation: str = "none",
    severity: int = 0,
) -> list[str]:
    """The `ebvla-eval` command line of a fast-render MetaWorld evaluation, one env at a time.

    The quickstart and the MetaWorld benchmark both evaluate this way, so they build the command here.
    """
    command = [
        sys.executable,
        "-m",
        "lerobot_policy_ebvla.scripts.eval_energy",
        f"--policy.path={checkpoint}",
        f"--policy.device={device}",
        "--env.type=metaworld_ebvla",
        f"--env.task={task}",
        "--env.fast_render=true",
        f"--env.max_episode_steps={max_episode_steps}",
        f"--eval.n_episodes={n_episodes}",
        "--eval.batch_size=1",
        f"--seed={seed}",
        f"--output_dir={output_dir}",
    ]
    if perturbation != "none":
        command += [f"--env.camera_perturbation={perturbation}", f"--env.perturbation_severity={severity}"]
    return command


if __name__ == "__main__":
    main()
