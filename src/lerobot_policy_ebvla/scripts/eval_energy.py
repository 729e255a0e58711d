"""`ebvla-eval`: lerobot-eval that also records the energy of every action chunk the policy refines.

It takes lerobot-eval's arguments and runs LeRobot's own evaluation (`eval_policy_all` and its `rollout`)
under `monitoring.recorder.EnergyRecorder`. Alongside `eval_info.json` it writes `energy_records.jsonl`: one
`EnergyRecord` per episode and predicted chunk, with the env step of the prediction, the initial and final
energies, the episode's success and seed, and the perturbation of the env (`--env.type=metaworld_ebvla`;
"none" for other envs). `--restart_spread_chains=N` and `--record_context_features=true` also record the
baselines of the OOD report (see `monitoring/baselines.py`).

Example:

    MUJOCO_GL=egl ebvla-eval --policy.path=outputs/train/ebvla_reach/checkpoints/last/pretrained_model \\
        --env.type=metaworld_ebvla --env.task=reach-v3 --env.fast_render=true \\
        --env.perturbation=pose --env.perturbation_severity=3 \\
        --eval.n_episodes=10 --eval.batch_size=1 --output_dir=outputs/eval/reach_pose3 \\
        --restart_spread_chains=8 --record_context_features=true

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

from lerobot_policy_ebvla.monitoring.recorder import EnergyRecorder
from lerobot_policy_ebvla.monitoring.records import (
    ENERGY_RECORDS_FILENAME,
    VANILLA_PERTURBATION,
    write_energy_records,
)

logger = logging.getLogger(__name__)


@dataclass
class EnergyEvalPipelineConfig(EvalPipelineConfig):
    # Episodes rendered to videos in `<output_dir>/videos` (lerobot-eval renders 10).
    max_episodes_rendered: int = 0
    # Baseline for the OOD report: also refine N independent chunks per observation and record their
    # spread (`restart_spread`). 0 = off; N >= 2 costs N extra refinements per chunk.
    restart_spread_chains: int = 0
    # Score for the OOD report: the final energy relative to the energies of N chunks drawn from the MCMC
    # prior under the same context (`normalized_energy`). 0 = off; N >= 1 costs one batched energy per chunk.
    normalized_energy_samples: int = 0
    # Baseline for the OOD report: record each chunk's pooled backbone context (energy_records.features.npy).
    record_context_features: bool = False


def env_perturbation(env_cfg: Any) -> tuple[str, float]:
    """(perturbation name, severity) of an env config with `perturbation` and `perturbation_severity` fields
    (`metaworld_ebvla`, `libero_ebvla`); ("none", 0) for envs without perturbations."""
    perturbation = getattr(env_cfg, "perturbation", VANILLA_PERTURBATION)
    return perturbation, float(getattr(env_cfg, "perturbation_severity", 0))


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
    recorder = EnergyRecorder(
        policy,
        restart_spread_chains=cfg.restart_spread_chains,
        record_context_features=cfg.record_context_features,
        seed=cfg.seed or 0,
        normalized_energy_samples=cfg.normalized_energy_samples,
    )
    with recorder, torch.no_grad(), amp:
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
    extra_args: tuple[str, ...] = (),
) -> list[str]:
    """The `ebvla-eval` command line of a fast-render MetaWorld evaluation, one env at a time.

    `benchmarks/compare_diffusion_metaworld.py` evaluates every method this way. `extra_args` are appended as
    given (for example `--normalized_energy_samples=16`).
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
        command += [f"--env.perturbation={perturbation}", f"--env.perturbation_severity={severity}"]
    return command + list(extra_args)


if __name__ == "__main__":
    main()
