"""`--env.render_every` on MetaWorld: the same rollouts, energies and successes, in less time (issue 55).

Evaluates one checkpoint twice on the same seeds, with the env drawing every step's frame (`render_every=1`,
LeRobot's) and only the frames the policy reads (`render_every` = its `n_action_steps`, the default of
`metaworld_eval_config` since 2026-11-28), checks that every chunk's energies and every episode's success are
identical, and prints both wall times. On the quickstart's checkpoint and settings:

    MUJOCO_GL=egl python research/benchmarks/metaworld_render_every.py --checkpoint=<quickstart>/train/checkpoints/last/pretrained_model \
        --task=button-press-v3 --episodes=10 --max_episode_steps=100 --observation_size=128 --perturbation=pose --severity=3
"""

import argparse
import json
import tempfile
import time
from pathlib import Path

from lerobot_policy_ebvla.monitoring.records import read_energy_records, records_file_in
from lerobot_policy_ebvla.pipelines.eval_energy import eval_metaworld_checkpoint


def evaluate(args: argparse.Namespace, render_every: int | None, output_dir: Path) -> tuple[float, list]:
    start = time.perf_counter()
    eval_metaworld_checkpoint(
        args.checkpoint,
        output_dir,
        task=args.task,
        max_episode_steps=args.max_episode_steps,
        n_episodes=args.episodes,
        seed=args.seed,
        perturbation=args.perturbation,
        severity=args.severity,
        observation_size=args.observation_size,
        device="cpu",
        render_every=render_every,
    )
    return time.perf_counter() - start, read_energy_records(records_file_in(output_dir))


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--checkpoint", type=Path, required=True)
    parser.add_argument("--task", default="button-press-v3")
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--max_episode_steps", type=int, default=100)
    parser.add_argument("--observation_size", type=int, default=128)
    parser.add_argument("--perturbation", default="none")
    parser.add_argument("--severity", type=int, default=0)
    parser.add_argument("--seed", type=int, default=1000)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        every_s, every = evaluate(args, 1, Path(tmp) / "every")
        read_s, read = evaluate(args, None, Path(tmp) / "read")
    fields = (
        "episode_index",
        "chunk_index",
        "env_step",
        "success",
        "initial_energy",
        "final_energy",
        "context_energy",
    )
    same = len(every) == len(read) and all(
        all(getattr(a, f) == getattr(b, f) for f in fields) for a, b in zip(every, read, strict=True)
    )
    result = {
        "chunks": len(every),
        "episodes": args.episodes,
        "successes": int(sum(r.success for r in every if r.chunk_index == 0)),
        "identical_energies_and_successes": bool(same),
        "render_every_1_s": round(every_s, 1),
        "render_every_read_s": round(read_s, 1),
        "speedup": round(every_s / read_s, 2),
        "args": {k: str(v) for k, v in vars(args).items()},
    }
    print(json.dumps(result, indent=1))
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
