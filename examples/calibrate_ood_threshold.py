"""Calibrate a checkpoint's monitor from vanilla rollouts (its OOD threshold, and its failure check where it has
one), and save it beside the checkpoint.

The paper's Eq. 5: roll the policy out in the scene it was trained for, score each rollout by the mean of its
chunks' scores, and set T = mu_v + k * sigma_v over those scores. The score is the checkpoint's own,
`policy.config.monitor.score` (decided when it was trained: "final_energy" by default, "context_phase_energy" for
the light preset), the one `ebvla-ood-report --calibrate_to` saves. `OODCalibration.save` writes
`ood_calibration.json` into the checkpoint folder, where `EnergyMonitor.from_pretrained` and the policy's own
OOD response (`--policy.monitor.response=hold|raise`, examples/rollout_with_ood_response.py) find it. A policy with
the joint energy's E_c on its own encoder also gets its failure check (`policy.config.monitor.failure_score`, the
head's energy over the first 3 chunks, fitted on the same rollouts): `failure_calibration.json`.

    MUJOCO_GL=egl python examples/calibrate_ood_threshold.py \\
        --checkpoint=outputs/example_metaworld/train/checkpoints/last/pretrained_model --episodes=20

Calibrate on other seeds than the ones you report on: this script starts at seed 2000, evaluations at 1000.
"""

import os
from dataclasses import dataclass
from pathlib import Path

import draccus
import torch
from lerobot.envs import close_envs, make_env, make_env_pre_post_processors
from lerobot.policies import make_pre_post_processors
from lerobot.scripts.lerobot_eval import eval_policy_all

from lerobot_policy_ebvla import EBVLAPolicy, EnergyMonitor, FailureCalibration, OODCalibration
from lerobot_policy_ebvla.envs import MetaworldEBVLAEnv
from lerobot_policy_ebvla.monitoring import EnergyRecorder, group_by_episode
from lerobot_policy_ebvla.monitoring.baselines import episode_readout, vanilla_rollouts
from lerobot_policy_ebvla.runtime.scores import SCORES


@dataclass
class CalibrateConfig:
    # The `pretrained_model` folder of the checkpoint; the calibration is written into it.
    checkpoint: Path = Path("outputs/example_metaworld/train/checkpoints/last/pretrained_model")
    # The MetaWorld task the policy was trained on.
    task: str = "button-press-v3"
    # Vanilla rollouts to calibrate on.
    episodes: int = 10
    # Rollouts end after this many env steps.
    max_episode_steps: int = 100
    # Seed of the first calibration rollout.
    seed: int = 2000
    # k of T = mu_v + k * sigma_v (Eq. 5): lower flags more OOD rollouts, and more vanilla ones too.
    k: float = 1.0
    # Also store the conformal threshold of this false-alarm rate (`--threshold_rule=conformal` elsewhere).
    false_alarm_rate: float = 0.1
    # Replace an existing ood_calibration.json (and failure_calibration.json).
    overwrite: bool = True


def main(cfg: CalibrateConfig) -> None:
    policy = EBVLAPolicy.from_pretrained(cfg.checkpoint)
    preprocessor, postprocessor = make_pre_post_processors(policy.config, pretrained_path=cfg.checkpoint)
    env_cfg = MetaworldEBVLAEnv(task=cfg.task, fast_render=True, max_episode_steps=cfg.max_episode_steps)
    env_preprocessor, env_postprocessor = make_env_pre_post_processors(env_cfg, policy.config)

    # Vanilla rollouts with LeRobot's evaluation loop; the recorder keeps every chunk's energies (and its pooled
    # context, for a score that reads it).
    score = policy.config.monitor.score
    envs = make_env(env_cfg, n_envs=1)
    features = "context_features" in SCORES[score].reads
    with EnergyRecorder(policy, record_context_features=features) as recorder, torch.no_grad():
        watched = {g: {i: recorder.watch(env, g, i) for i, env in tasks.items()} for g, tasks in envs.items()}
        info = eval_policy_all(
            watched,
            policy,
            env_preprocessor,
            env_postprocessor,
            preprocessor,
            postprocessor,
            n_episodes=cfg.episodes,
            start_seed=cfg.seed,
        )
    close_envs(envs)
    records = recorder.records(info, cfg.episodes)

    # The checkpoint's score fitted on the rollouts, one score per rollout (the mean of its chunks'), then Eq. 5.
    episodes = group_by_episode(records)
    calibration = OODCalibration.calibrate(
        score, vanilla_rollouts(episodes), k=cfg.k, false_alarm_rate=cfg.false_alarm_rate
    )
    path = calibration.save(cfg.checkpoint, overwrite=cfg.overwrite)
    print(
        f"\n{score}: mu_v = {calibration.mu_v:.3f}, sigma_v = {calibration.sigma_v:.3f} over {calibration.n_rollouts} "
        f"vanilla rollouts: T = {calibration.threshold:.3f} (k = {cfg.k}); conformal threshold at "
        f"{cfg.false_alarm_rate:.0%} false alarms: {calibration.conformal_threshold:.3f}"
    )
    print(f"Saved {path}")
    monitor_config = policy.config.monitor
    if monitor_config.failure_score != "none":
        failure = FailureCalibration.calibrate(
            monitor_config.failure_score,
            vanilla_rollouts(episodes),
            chunks=monitor_config.failure_chunks,
            k=cfg.k,
            false_alarm_rate=cfg.false_alarm_rate,
        )
        path = failure.save(cfg.checkpoint, overwrite=cfg.overwrite)
        print(
            f"{failure.score.name} over the first {failure.chunks} chunks: T = {failure.threshold:.3f}; saved {path}"
        )

    # What a control loop does with it: the monitor reads the files back from the checkpoint folder and takes the
    # policy's readout of each chunk (`monitor.update(policy.last_energy)`); here, each recorded chunk in turn.
    monitor = EnergyMonitor.from_pretrained(cfg.checkpoint)
    for key, episode in episodes.items():
        monitor.reset()
        readout = episode_readout(episode)
        for chunk in range(len(episode)):
            (decision,) = monitor.update(readout.row(chunk))
        verdict = "OOD" if decision.unfamiliar.is_ood else "in distribution"
        failing = {None: "", True: ", failing", False: ", not failing"}[decision.failing]
        print(f"rollout {key.episode_index}: score {decision.unfamiliar.energy:.3f} -> {verdict}{failing}")


if __name__ == "__main__":
    os.environ.setdefault("MUJOCO_GL", "egl")
    main(draccus.parse(CalibrateConfig))
