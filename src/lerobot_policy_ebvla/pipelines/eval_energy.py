"""LeRobot's evaluation with the energy of every action chunk the policy refines (what `ebvla-eval` runs).

`eval_energy` runs LeRobot's own evaluation (`eval_policy_all` and its `rollout`) under
`monitoring.recorder.EnergyRecorder`. Alongside `eval_info.json` it writes `energy_records.jsonl`: one
`EnergyRecord` per episode and predicted chunk, with the env step of the prediction, the initial and final
energies, the episode's success and seed, and the perturbation of the env (`--env.type=metaworld_ebvla`;
"none" for other envs). The config's opt-in fields also record the baselines of the OOD report (see
`monitoring/baselines.py`).

`metaworld_eval_config` builds the config of a fast-render MetaWorld evaluation of a checkpoint, one env at a
time, and `eval_metaworld_checkpoint` runs it: the quickstart and the benchmarks evaluate this way.
"""

import json
import logging
from collections.abc import Sequence
from contextlib import nullcontext
from dataclasses import asdict, dataclass
from pathlib import Path
from pprint import pformat
from typing import Any

import torch
from lerobot.configs.default import EvalConfig
from lerobot.configs.eval import EvalPipelineConfig
from lerobot.configs.policies import PreTrainedConfig
from lerobot.envs import close_envs, make_env, make_env_pre_post_processors
from lerobot.policies import make_policy, make_pre_post_processors
from lerobot.scripts.lerobot_eval import eval_policy_all
from lerobot.utils.device_utils import get_safe_torch_device
from lerobot.utils.random_utils import set_seed

from ..envs import MetaworldEBVLAEnv
from ..monitoring.recorder import EnergyRecorder
from ..monitoring.records import ENERGY_RECORDS_FILENAME, VANILLA_PERTURBATION, write_energy_records

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


def eval_energy(cfg: EnergyEvalPipelineConfig) -> dict:
    """lerobot-eval's `eval_main`, with the policy's energies recorded and written beside `eval_info.json`.

    Returns:
        LeRobot's evaluation info (what `eval_info.json` holds).
    """
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
    return info


def metaworld_eval_env(
    task: str,
    max_episode_steps: int,
    perturbation: str = "none",
    severity: int = 0,
    observation_size: int | None = None,
    render_every: int = 1,
) -> MetaworldEBVLAEnv:
    """The fast-render MetaWorld env of an evaluation; raises a ValueError naming an invalid perturbation.

    `observation_size` renders smaller frames than MetaWorld's 480 px: evaluate at the size the training data
    was recorded at. `render_every` draws only the frames a policy acting in chunks of that many steps reads.
    """
    return MetaworldEBVLAEnv(
        task=task,
        fast_render=True,
        max_episode_steps=max_episode_steps,
        perturbation=perturbation,
        perturbation_severity=severity if perturbation != "none" else 0,
        observation_size=observation_size,
        render_every=render_every,
    )


def frames_read_every(policy: PreTrainedConfig) -> int:
    """Every how many env steps the policy reads a frame: an `ebvla` policy refines a chunk every
    `n_action_steps` from one observation; any other policy (Diffusion Policy's observation history) reads all."""
    return policy.n_action_steps if policy.type == "ebvla" else 1


def metaworld_eval_config(
    checkpoint: Path,
    output_dir: Path,
    *,
    task: str,
    max_episode_steps: int,
    n_episodes: int,
    seed: int,
    perturbation: str = "none",
    severity: int = 0,
    device: str | None = None,
    observation_size: int | None = None,
    render_every: int | None = None,
    policy_overrides: Sequence[str] = (),
    **options: Any,
) -> EnergyEvalPipelineConfig:
    """The `eval_energy` config of a fast-render MetaWorld evaluation of a checkpoint, one env at a time.

    Args:
        checkpoint: A `pretrained_model` folder (any LeRobot policy: the benchmarks evaluate Diffusion Policy
            this way too; energies are recorded for `ebvla`).
        output_dir: Where `eval_info.json` and `energy_records.jsonl` go.
        task: MetaWorld v3 task, or comma-separated tasks.
        max_episode_steps: Episodes end after this many env steps.
        n_episodes: Episodes per task, seeded from `seed`.
        seed: Seed of the first episode.
        perturbation: One of `metaworld_ebvla`'s perturbations (docs/metaworld.md); "none": the vanilla scene.
        severity: Its severity, 1 to 5 (ignored for "none").
        device: The policy's torch device; None keeps the checkpoint's.
        observation_size: Side of the rendered frames (`--env.observation_size`); None: MetaWorld's 480 px.
        render_every: Draw the frames of the reset and of every `render_every`-th step only
            (`--env.render_every`); None: those the policy reads (`frames_read_every`). Results do not change.
        policy_overrides: `--policy.<field>=<value>` arguments without `policy.`, e.g. `["--num_restarts=4"]`.
        **options: Other `EnergyEvalPipelineConfig` fields, e.g. `normalized_energy_samples=16` or
            `restart_spread_chains=4`.
    """
    # What `--policy.path=<checkpoint> --policy.device=<device>` loads on lerobot-eval's command line.
    overrides = ([] if device is None else [f"--device={device}"]) + list(policy_overrides)
    policy = PreTrainedConfig.from_pretrained(checkpoint, cli_overrides=overrides)
    policy.pretrained_path = Path(checkpoint)
    # EvalPipelineConfig looks for `--policy.path` on the command line and warns when it finds none; the
    # policy is given here instead.
    eval_logger = logging.getLogger("lerobot.configs.eval")
    level = eval_logger.level
    eval_logger.setLevel(logging.ERROR)
    try:
        return EnergyEvalPipelineConfig(
            env=metaworld_eval_env(
                task,
                max_episode_steps,
                perturbation,
                severity,
                observation_size,
                frames_read_every(policy) if render_every is None else render_every,
            ),
            eval=EvalConfig(n_episodes=n_episodes, batch_size=1, use_async_envs=False),
            policy=policy,
            output_dir=Path(output_dir),
            seed=seed,
            **options,
        )
    finally:
        eval_logger.setLevel(level)


def eval_metaworld_checkpoint(checkpoint: Path, output_dir: Path, **kwargs: Any) -> dict:
    """Evaluates a checkpoint on MetaWorld with energies: `eval_energy` of `metaworld_eval_config`.

    Takes `metaworld_eval_config`'s arguments and returns LeRobot's evaluation info.
    """
    return eval_energy(metaworld_eval_config(checkpoint, output_dir, **kwargs))
