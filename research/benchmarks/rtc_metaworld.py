"""Chunk-boundary jump and success on MetaWorld with and without real-time chunking (RTC), at injected latencies.

The simulated robot keeps moving while a chunk is refined. A chunk is refined from the observation at step t
and arrives at step t + d (the injected latency, in control steps); LeRobot's RTC `ActionQueue` (what
`lerobot-rollout --inference.type=rtc` uses) then replaces the queue with the new chunk minus its first d
actions, which the robot executed from the old chunk meanwhile. The next chunk is asked for when
`queue_threshold` actions or fewer remain, as in LeRobot's RTC engine, so a new chunk takes over every
chunk_size - queue_threshold steps at every latency. Only the first chunk of an episode is waited for.

Two arms share that schedule: "rtc" passes `inference_delay=d` and the queue's leftover to
`predict_action_chunk` (the policy holds the first d actions and guides the overlap, `mcmc.py`); "naive"
refines every chunk from scratch. The latency is counted in env steps, so the numbers do not depend on the
speed of the machine. Episodes run in LeRobot's own `lerobot_eval.rollout`, which also says success.

Jump: at each switch, mean over action dimensions of |a(new chunk, first executed) - a(old chunk, planned for
the same step)|, in raw action units (MetaWorld: end-effector deltas in [-1, 1]). RTC holds the first d actions
and pulls the start of the overlap onto the leftover, so its jump there is about 0 by construction; the step
change (mean and 95th percentile over all executed steps of |a_{t+1} - a_t|, same units) says whether the
difference moved further into the chunk instead.

    MUJOCO_GL=egl python research/benchmarks/rtc_metaworld.py \\
        --checkpoint=outputs/ebvla_quickstart/train/checkpoints/last/pretrained_model \\
        --task=button-press-v3 --episodes=10 --max_episode_steps=100 --latencies 1 2 3 --observation_size=128 \\
        --output=outputs/rtc_metaworld.json
"""

import argparse
import json
import math
from pathlib import Path

import torch
from lerobot.configs import RTCAttentionSchedule
from lerobot.envs import close_envs, make_env, make_env_pre_post_processors
from lerobot.policies import make_pre_post_processors
from lerobot.policies.rtc import ActionQueue, RTCConfig
from lerobot.scripts.lerobot_eval import rollout
from torch import Tensor, nn

from lerobot_policy_ebvla import EBVLAPolicy
from lerobot_policy_ebvla.pipelines.eval_energy import metaworld_eval_env

ARMS = ("naive", "rtc")


class DelayedChunking(nn.Module):
    """`select_action` of a robot that keeps executing while the next chunk is refined, `latency` steps late.

    LeRobot's `lerobot_eval.rollout` drives it like a policy (batch of one env). It keeps each switch's
    (new first action, old planned action) pair, normalized, in `switches`.
    """

    def __init__(self, policy: EBVLAPolicy, latency: int, queue_threshold: int, rtc: bool):
        super().__init__()
        self.policy, self.latency, self.queue_threshold, self.rtc = policy, latency, queue_threshold, rtc
        self.reset()

    def reset(self) -> None:
        self.policy.reset()
        # The replacing queue of RTC for both arms: they differ only in what the policy is given.
        self.queue = ActionQueue(RTCConfig(enabled=True))
        self.pending: tuple[Tensor, int, Tensor | None] | None = None  # chunk, its delay, the leftover
        self.step = self.arrival = 0
        self.switches: list[tuple[Tensor, Tensor]] = []
        self.executed: list[Tensor] = []  # every action sent to the robot, normalized

    def select_action(self, batch: dict[str, Tensor]) -> Tensor:
        if self.pending is None and self.queue.qsize() <= self.queue_threshold:
            leftover = self.queue.get_left_over()  # (n, d_a), normalized; None before the first chunk
            delay = 0 if leftover is None else self.latency  # the first chunk is waited for
            rtc = {"inference_delay": delay, "prev_chunk_left_over": leftover} if self.rtc else {}
            chunk = self.policy.predict_action_chunk(batch, **rtc)[0]
            self.pending = (chunk, delay, leftover)
            self.arrival = self.step + delay
        if self.pending is not None and self.step == self.arrival:
            chunk, delay, leftover = self.pending
            if leftover is not None:
                self.switches.append((chunk[delay], leftover[delay]))
            self.queue.merge(chunk, chunk, delay)
            self.pending = None
        self.step += 1
        action = self.queue.get()
        self.executed.append(action)
        return action.unsqueeze(0)


def run_arm(robot: DelayedChunking, env, processors: tuple, episodes: int, seed: int) -> dict:
    """Success rate, jumps at the switches (raw units) and final energies of `episodes` seeded episodes."""
    env_preprocessor, env_postprocessor, preprocessor, postprocessor = processors
    energies = []
    handle = robot.policy.register_chunk_hook(
        lambda _p, _b, readout, _d: energies.append(readout.final_energy)
    )
    successes, jumps, changes = [], [], []
    try:
        for episode in range(episodes):
            torch.manual_seed(seed + episode)
            data = rollout(
                env,
                robot,
                env_preprocessor,
                env_postprocessor,
                preprocessor,
                postprocessor,
                seeds=[seed + episode],
            )
            successes.append(bool(data["success"][0].any()))
            if robot.switches:
                new, old = (postprocessor(torch.stack(side)) for side in zip(*robot.switches, strict=True))
                jumps += (new - old).abs().mean(dim=1).tolist()
            # The jump at a switch can be 0 by construction (RTC holds and pulls the overlap onto the leftover):
            # the change between consecutive executed actions says where the new chunk's difference went.
            executed = postprocessor(torch.stack(robot.executed))
            changes += executed.diff(dim=0).abs().mean(dim=1).tolist()
    finally:
        handle.remove()
    return {
        "episodes": episodes,
        "success_rate": sum(successes) / episodes,
        "switches": len(jumps),
        "mean_jump": sum(jumps) / len(jumps) if jumps else math.nan,
        "mean_step_change": sum(changes) / len(changes) if changes else math.nan,
        "p95_step_change": torch.tensor(changes).quantile(0.95).item() if changes else math.nan,
        "mean_final_energy": torch.cat(energies).mean().item(),
    }


def run(
    checkpoint: Path,
    *,
    task: str = "button-press-v3",
    episodes: int = 10,
    max_episode_steps: int = 100,
    latencies: tuple[int, ...] = (1, 2, 3),
    queue_threshold: int | None = None,
    execution_horizon: int | None = None,
    schedule: str = "LINEAR",
    max_guidance_weight: float = 10.0,
    seed: int = 1000,
    device: str = "cpu",
    observation_size: int | None = None,
) -> list[dict]:
    """One row per latency and arm: success rate, mean jump at the switches and mean final energy.

    Args:
        checkpoint: An ebvla `pretrained_model` folder (with its processors).
        queue_threshold: Ask for the next chunk when this many actions or fewer remain; None: chunk_size // 2.
        execution_horizon: End of RTC's guided overlap (`RTCConfig.execution_horizon`); None: queue_threshold,
            the length of the leftover.
        schedule: LeRobot's `RTCAttentionSchedule` name of the guidance weights (LINEAR, EXP, ONES, ZEROS).
        max_guidance_weight: RTC's lambda.
        observation_size: Side of the rendered frames (`--env.observation_size`): the size the checkpoint's data
            was recorded at (the quickstart's: 128); None: MetaWorld's 480.
    """
    policy = EBVLAPolicy.from_pretrained(checkpoint)
    policy.config.device = device
    policy.to(device).eval()
    chunk_size = policy.config.chunk_size
    threshold = chunk_size // 2 if queue_threshold is None else queue_threshold
    # The leftover when a chunk is asked for, min(threshold, chunk_size - d - 1), must outlast the latency d.
    if not all(0 <= d < min(threshold, chunk_size - d - 1) for d in latencies):
        raise ValueError(
            f"Latencies must be >= 0 and below both `queue_threshold` ({threshold}) and chunk_size - d - 1 "
            f"(chunk_size={chunk_size}): the robot would run out of actions first. Got {latencies}."
        )
    policy.config.rtc_config = RTCConfig(
        prefix_attention_schedule=RTCAttentionSchedule[schedule],
        max_guidance_weight=max_guidance_weight,
        execution_horizon=execution_horizon or threshold,
    )
    preprocessor, postprocessor = make_pre_post_processors(
        policy.config,
        pretrained_path=str(checkpoint),
        preprocessor_overrides={"device_processor": {"device": device}},
    )
    env_cfg = metaworld_eval_env(task, max_episode_steps, observation_size=observation_size)
    envs = make_env(env_cfg, n_envs=1)
    env = next(iter(next(iter(envs.values())).values()))
    processors = (*make_env_pre_post_processors(env_cfg, policy.config), preprocessor, postprocessor)
    try:
        return [
            {
                "latency": latency,
                "arm": arm,
                **run_arm(
                    DelayedChunking(policy, latency, threshold, arm == "rtc"), env, processors, episodes, seed
                ),
            }
            for latency in latencies
            for arm in ARMS
        ]
    finally:
        close_envs(envs)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--checkpoint", type=Path, required=True, help="An ebvla pretrained_model folder.")
    parser.add_argument("--task", default="button-press-v3")
    parser.add_argument("--episodes", type=int, default=10, help="Episodes per latency and arm.")
    parser.add_argument("--max_episode_steps", type=int, default=100)
    parser.add_argument("--latencies", type=int, nargs="+", default=[1, 2, 3], help="In control steps.")
    parser.add_argument("--queue_threshold", type=int, default=None, help="Default: chunk_size // 2.")
    parser.add_argument("--execution_horizon", type=int, default=None, help="Default: queue_threshold.")
    parser.add_argument("--schedule", default="LINEAR", choices=[s.name for s in RTCAttentionSchedule])
    parser.add_argument("--max_guidance_weight", type=float, default=10.0)
    parser.add_argument("--seed", type=int, default=1000, help="Seed of the first episode.")
    parser.add_argument("--device", default="cpu")
    parser.add_argument(
        "--observation_size",
        type=int,
        default=None,
        help="Rendered frame side; that of the checkpoint's data.",
    )
    parser.add_argument("--output", type=Path, default=None, help="Also write the rows to this JSON file.")
    args = parser.parse_args()
    options = {k: v for k, v in vars(args).items() if k not in ("checkpoint", "output")}
    rows = run(args.checkpoint, **{**options, "latencies": tuple(args.latencies)})
    print(
        f"{'latency':>7} {'arm':<6} {'success':>8} {'switches':>8} {'mean jump':>10} {'step change':>11} "
        f"{'p95':>7} {'final energy':>12}"
    )
    for r in rows:
        print(
            f"{r['latency']:>7} {r['arm']:<6} {r['success_rate']:>8.2f} {r['switches']:>8} "
            f"{r['mean_jump']:>10.4f} {r['mean_step_change']:>11.4f} {r['p95_step_change']:>7.4f} "
            f"{r['mean_final_energy']:>12.4f}"
        )
    if args.output is not None:
        args.output.parent.mkdir(parents=True, exist_ok=True)
        args.output.write_text(json.dumps({**vars(args), "rows": rows}, default=str, indent=2))


if __name__ == "__main__":
    main()
