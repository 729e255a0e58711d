"""A rollout in which the policy acts on its own energy: it holds (or stops) when a chunk looks OOD.

With `ood_calibration.json` in the checkpoint (examples/calibrate_ood_threshold.py), every refined chunk's
score (the checkpoint's `monitor.score`) is compared to the calibrated T; `monitor.response` says what happens
to a chunk above it:
"continue" (execute it, log a warning), "hold" (execute `hold_action` instead: "zero_delta" for
end-effector delta actions such as MetaWorld's and LIBERO's, "current_state" for absolute joint targets) or
"raise" (`EnergyOODError`). These are `EBVLAConfig.monitor` fields, so `lerobot-eval` and `lerobot-rollout` take
them as `--policy.monitor.response=hold --policy.monitor.hold_action=zero_delta`; here they are set
in Python and the episodes run in LeRobot's own `rollout`, in the vanilla scene and under a perturbation.

    MUJOCO_GL=egl python examples/rollout_with_ood_response.py \\
        --checkpoint=outputs/example_metaworld/train/checkpoints/last/pretrained_model --perturbation=blank
"""

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path

import draccus
import torch
from lerobot.configs import PreTrainedConfig
from lerobot.envs import close_envs, make_env, make_env_pre_post_processors
from lerobot.policies import make_pre_post_processors
from lerobot.scripts.lerobot_eval import rollout

from lerobot_policy_ebvla import EBVLAPolicy, EnergyOODError
from lerobot_policy_ebvla.envs import MetaworldEBVLAEnv


@dataclass
class RolloutConfig:
    # A calibrated checkpoint (its folder holds ood_calibration.json).
    checkpoint: Path = Path("outputs/example_metaworld/train/checkpoints/last/pretrained_model")
    # The MetaWorld task the policy was trained on.
    task: str = "button-press-v3"
    # The perturbed scene (`--env.perturbation` of `metaworld_ebvla`, docs/metaworld.md).
    perturbation: str = "blank"
    # Its severity, 1 to 5.
    perturbation_severity: int = 1
    # Episodes per scene.
    episodes: int = 3
    # Episodes end after this many env steps.
    max_episode_steps: int = 100
    # What the policy does with a chunk above T: "continue", "hold" or "raise".
    response: str = "hold"
    # The hold action (MetaWorld's actions are end-effector deltas).
    hold_action: str = "zero_delta"
    # k of T = mu_v + k * sigma_v; None keeps the calibration's.
    threshold_k: float | None = None


def run_episodes(cfg: RolloutConfig, policy, perturbation: str, severity: int) -> None:
    preprocessor, postprocessor = make_pre_post_processors(policy.config, pretrained_path=cfg.checkpoint)
    env_cfg = MetaworldEBVLAEnv(
        task=cfg.task,
        fast_render=True,
        max_episode_steps=cfg.max_episode_steps,
        perturbation=perturbation,
        perturbation_severity=severity,
    )
    env_preprocessor, env_postprocessor = make_env_pre_post_processors(env_cfg, policy.config)
    envs = make_env(env_cfg, n_envs=1)
    env = next(iter(next(iter(envs.values())).values()))

    # The policy leaves its decision on each refined chunk in `last_ood_decision`: keep them to count.
    decisions = []
    predict_action_chunk = policy.predict_action_chunk

    def predict_and_keep_decision(*args, **kwargs):
        actions = predict_action_chunk(*args, **kwargs)
        decisions.append(policy.last_ood_decision)
        return actions

    policy.predict_action_chunk = predict_and_keep_decision
    try:
        for seed in range(1000, 1000 + cfg.episodes):
            decisions.clear()
            try:
                data = rollout(
                    env,
                    policy,
                    env_preprocessor,
                    env_postprocessor,
                    preprocessor,
                    postprocessor,
                    seeds=[seed],
                )
                outcome = f"success={bool(data['success'][0].any())}"
            except EnergyOODError as error:  # response "raise": the robot would stop here
                decisions.append(error.decision)  # raised before the policy could leave it
                outcome = f"stopped: energy {error.energy:.3f} > T = {error.threshold:.3f}"
            held = sum(bool(d.held.any()) for d in decisions if d is not None)
            flagged = sum(bool(d.flagged.any()) for d in decisions if d is not None)
            print(
                f"{perturbation:>8} s{severity} seed {seed}: {len(decisions)} chunks, {flagged} above T, "
                f"{held} held; {outcome}"
            )
    finally:
        del policy.predict_action_chunk
        close_envs(envs)


def main(cfg: RolloutConfig) -> None:
    # `--policy.monitor.<field>` overrides, as lerobot-eval applies them to the saved config.
    config = PreTrainedConfig.from_pretrained(cfg.checkpoint)
    monitor = dataclasses.replace(
        config.monitor, response=cfg.response, hold_action=cfg.hold_action, threshold_k=cfg.threshold_k
    )
    config = dataclasses.replace(config, monitor=monitor)
    policy = EBVLAPolicy.from_pretrained(cfg.checkpoint, config=config)
    print(f"OOD threshold T = {policy.ood_response.threshold:.3f}, response {cfg.response!r}")
    with torch.no_grad():
        run_episodes(cfg, policy, "none", 0)
        run_episodes(cfg, policy, cfg.perturbation, cfg.perturbation_severity)


if __name__ == "__main__":
    os.environ.setdefault("MUJOCO_GL", "egl")
    main(draccus.parse(RolloutConfig))
