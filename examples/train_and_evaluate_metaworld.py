"""Train `ebvla` on MetaWorld expert demonstrations and evaluate it with the energy of every chunk.

Three library calls, all in this process:
1. `record_metaworld`: MetaWorld's scripted expert, recorded as a LeRobotDataset (offline, no Hub).
2. LeRobot's `train` (what `lerobot-train` runs) with a `TrainPipelineConfig` built here: the dataset and
   the light `EBVLAConfig` (LeRobot's Diffusion Policy ResNet-18 encoder and a CPU-sized energy head).
3. LeRobot's `eval_policy_all` (what `lerobot-eval` runs) under an `EnergyRecorder`, which keeps the initial
   and final energy E(a^(K), C) of every refined chunk; they are written to `energy_records.jsonl`, the file
   every tool of `lerobot_policy_ebvla.monitoring` reads.

    MUJOCO_GL=egl python examples/train_and_evaluate_metaworld.py                 # ~5 min on a 2-core CPU
    MUJOCO_GL=egl python examples/train_and_evaluate_metaworld.py --steps=3000 --device=cuda

The checkpoint lands in `<output_dir>/train/checkpoints/last/pretrained_model`; the other examples read it.
"""

import os
from dataclasses import dataclass
from pathlib import Path

import draccus
import torch
from lerobot.configs.default import DatasetConfig, WandBConfig
from lerobot.configs.train import TrainPipelineConfig
from lerobot.envs import close_envs, make_env, make_env_pre_post_processors
from lerobot.policies import make_pre_post_processors
from lerobot.scripts.lerobot_eval import eval_policy_all
from lerobot.scripts.lerobot_train import train

from lerobot_policy_ebvla import EBVLAPolicy
from lerobot_policy_ebvla.envs import MetaworldEBVLAEnv
from lerobot_policy_ebvla.monitoring import (
    EnergyRecorder,
    episode_scores,
    group_by_episode,
    write_energy_records,
)
from lerobot_policy_ebvla.pipelines.column_queries import single_column_delta_queries
from lerobot_policy_ebvla.presets import light_policy_config
from lerobot_policy_ebvla.recording.metaworld import RecordMetaworldConfig, record_metaworld


@dataclass
class ExampleConfig:
    # MetaWorld v3 task (its goal should be visible in the camera: not reach-v3).
    task: str = "button-press-v3"
    # Where the dataset, the training run and the energy records go.
    output_dir: Path = Path("outputs/example_metaworld")
    # Expert episodes to record.
    episodes: int = 10
    # Training steps.
    steps: int = 1500
    # Training batch size.
    batch_size: int = 16
    # Evaluation episodes.
    eval_episodes: int = 5
    # Evaluation episodes end after this many env steps.
    max_episode_steps: int = 100
    # Torch device ("cpu", "cuda", "mps").
    device: str = "cpu"


def main(cfg: ExampleConfig) -> None:
    # 1. Demonstrations. `fast_render` drops shadows and reflections (3x faster): evaluate the same way.
    data_root = cfg.output_dir / "data"
    repo_id = f"local/metaworld_{cfg.task}"
    if not (data_root / "meta" / "info.json").is_file():
        record_metaworld(
            RecordMetaworldConfig(
                env=MetaworldEBVLAEnv(task=cfg.task, fast_render=True),
                repo_id=repo_id,
                root=data_root,
                episodes_per_task=cfg.episodes,
            )
        )

    # 2. Training. The quickstart's light policy (`presets.LIGHT_POLICY`: LeRobot's Diffusion Policy encoder
    # from scratch and a CPU-sized energy head; its docstring gives its sizes and how its training recipe
    # differs from the paper's). Print it to see it all.
    policy_cfg = light_policy_config(
        scheduler_warmup_steps=cfg.steps // 10,
        scheduler_decay_steps=cfg.steps,
        device=cfg.device,
    )
    train_dir = cfg.output_dir / "train"
    # LeRobot 0.6.1 decodes the frames of all 8 rows of an action chunk to read the actions; this context reads
    # the action column alone (pipelines/column_queries.py), a training step ~45 ms faster on two cores.
    with single_column_delta_queries():
        train(
            TrainPipelineConfig(
                dataset=DatasetConfig(repo_id=repo_id, root=str(data_root)),
                policy=policy_cfg,
                output_dir=train_dir,
                steps=cfg.steps,
                batch_size=cfg.batch_size,
                save_freq=cfg.steps,
                log_freq=max(1, cfg.steps // 10),
                num_workers=0,
                wandb=WandBConfig(enable=False),
            )
        )
    checkpoint = train_dir / "checkpoints" / "last" / "pretrained_model"

    # 3. Evaluation with energies: LeRobot's rollout, the recorder watching the policy and the env.
    policy = EBVLAPolicy.from_pretrained(checkpoint)
    preprocessor, postprocessor = make_pre_post_processors(policy.config, pretrained_path=checkpoint)
    env_cfg = MetaworldEBVLAEnv(task=cfg.task, fast_render=True, max_episode_steps=cfg.max_episode_steps)
    env_preprocessor, env_postprocessor = make_env_pre_post_processors(env_cfg, policy.config)
    envs = make_env(env_cfg, n_envs=1)
    with EnergyRecorder(policy) as recorder, torch.no_grad():
        watched = {
            group: {task_id: recorder.watch(env, group, task_id) for task_id, env in tasks.items()}
            for group, tasks in envs.items()
        }
        info = eval_policy_all(
            watched,
            policy,
            env_preprocessor,
            env_postprocessor,
            preprocessor,
            postprocessor,
            n_episodes=cfg.eval_episodes,
            start_seed=1000,  # the demonstrations used seeds 0..episodes-1
            max_parallel_tasks=1,
        )
    close_envs(envs)
    records = recorder.records(info, cfg.eval_episodes)
    path = write_energy_records(cfg.output_dir / "eval" / "energy_records.jsonl", records, overwrite=True)

    print(f"\nSuccess rate: {info['overall']['pc_success']:.0f}% over {cfg.eval_episodes} episodes")
    episodes = dict(sorted(group_by_episode(records).items()))
    for (key, chunks), energy in zip(episodes.items(), episode_scores(episodes, "final_energy"), strict=True):
        print(
            f"episode {key.episode_index}: success={chunks[0].success}, {len(chunks)} chunks, "
            f"mean final energy {energy:.3f}"
        )
    print(f"Checkpoint: {checkpoint}\nEnergy records: {path}")


if __name__ == "__main__":
    os.environ.setdefault("MUJOCO_GL", "egl")  # MuJoCo renders off-screen, with no display
    main(draccus.parse(ExampleConfig))
