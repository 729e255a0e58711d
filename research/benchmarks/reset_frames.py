"""The frames two machines draw of the same LIBERO reset, and what the policy's E_c makes of each (issue 54).

On a lent H200, E_c of a CPU-trained policy at the first chunk of LIBERO's fixed states was 6.25 against 0.10 here,
and nothing done to frames here (TF32, noise, blur, gamma) came near it (`renderer_sensitivity.py`). The candidate
left is the frames NVIDIA's EGL draws. `dump` renders the reset observation of fixed initial states, both cameras, on
the machine it runs on (seconds a state; a GPU call brings the file back under $OUT); `compare` reads two dumps
here, pairs their frames, and gives the pixel differences per camera and E_c of both through one checkpoint on the
CPU: if the other machine's frames give E_c near its rollouts', the renderer alone moved it.

    MUJOCO_GL=egl python research/benchmarks/reset_frames.py dump --tasks 0 1 5 --states 30 31 32 \\
        --output=outputs/frames_here.npz
    python research/benchmarks/reset_frames.py compare --here=outputs/frames_here.npz --there=frames_gpu.npz \\
        --checkpoint=outputs/libero10_arm/train/ebvla_joint_fast_cpu_arm/checkpoints/last/pretrained_model \\
        --output=research/results/libero_object10_arm_gpu/reset_frames.json
"""

import argparse
import json
import platform
from pathlib import Path

import numpy as np

# The cameras of LeRobot's LIBERO env (`observation.images.image` and `.image2`), as its env writes them.
CAMERAS = ("image", "image2")


def flatten(observation: dict, prefix: str = "") -> dict[str, np.ndarray]:
    """A nested observation as "a/b" keys (what `unflatten` reads back)."""
    flat = {}
    for key, value in observation.items():
        if isinstance(value, dict):
            flat.update(flatten(value, f"{prefix}{key}/"))
        else:
            flat[f"{prefix}{key}"] = np.asarray(value)
    return flat


def unflatten(flat: dict[str, np.ndarray]) -> dict:
    observation = {}
    for key, value in flat.items():
        *parents, leaf = key.split("/")
        node = observation
        for parent in parents:
            node = node.setdefault(parent, {})
        node[leaf] = value
    return observation


def env_config(task: int, state: int, size: int):
    from lerobot_policy_ebvla.envs.libero_configs import LiberoEBVLAEnv

    return LiberoEBVLAEnv(
        task="libero_object",
        task_ids=[task],
        first_init_state=state,
        observation_height=size,
        observation_width=size,
    )


def dump(tasks: list[int], states: list[int], size: int) -> dict[str, np.ndarray]:
    """Each (task, fixed state)'s reset observation as the env returns it (both cameras' uint8 frames, the robot
    state), stacked over the resets as one batch, with each one's task, state and instruction."""
    from lerobot.envs.factory import make_env

    observations, keys = [], {"task": [], "state": [], "instruction": []}
    for task in tasks:
        for state in states:
            env = make_env(env_config(task, state, size), n_envs=1)["libero_object"][task]
            observation, _ = env.reset(seed=0)
            observations.append(flatten(observation))
            keys["task"].append(task)
            keys["state"].append(state)
            keys["instruction"].append(env.call("task_description")[0])
            env.close()
    stacked = {f"observation/{k}": np.concatenate([o[k] for o in observations]) for k in observations[0]}
    return {
        **stacked,
        **{key: np.array(values) for key, values in keys.items()},
        "machine": np.array(platform.node()),
    }


def frames_of(dumped: dict[str, np.ndarray], camera: str) -> np.ndarray:
    """(N, H, W, 3) uint8 frames of one camera of a dump."""
    return dumped[f"observation/pixels/{camera}"]


def pixel_differences(here: np.ndarray, there: np.ndarray) -> dict:
    """How two cameras' paired frames (N, H, W, 3) differ: mean |difference| in levels, the share of pixels more
    than 8 levels apart, and each machine's mean level per channel."""
    difference = np.abs(here.astype(np.int16) - there.astype(np.int16))
    return {
        "mean_abs_levels": float(difference.mean()),
        "share_over_8_levels": float((difference.max(axis=-1) > 8).mean()),
        "mean_level_here": here.reshape(-1, 3).mean(axis=0).round(2).tolist(),
        "mean_level_there": there.reshape(-1, 3).mean(axis=0).round(2).tolist(),
    }


def context_energies(checkpoint: Path, dumped: dict[str, np.ndarray], size: int) -> np.ndarray:
    """E_c of each dumped reset through the checkpoint on the CPU, the observation processed as `lerobot-eval`
    processes it (LeRobot's observation conversion, the env's and the policy's processors)."""
    import torch
    from lerobot.envs import make_env_pre_post_processors, preprocess_observation
    from lerobot.policies.factory import make_pre_post_processors

    from lerobot_policy_ebvla.modeling_ebvla import EBVLAPolicy

    policy = EBVLAPolicy.from_pretrained(str(checkpoint)).eval()
    preprocessor, _ = make_pre_post_processors(policy.config, pretrained_path=str(checkpoint))
    env_preprocessor, _ = make_env_pre_post_processors(
        env_cfg=env_config(0, 0, size), policy_cfg=policy.config
    )
    raw = unflatten(
        {k.removeprefix("observation/"): v for k, v in dumped.items() if k.startswith("observation/")}
    )
    observation = preprocess_observation(raw)
    observation["task"] = [str(t) for t in dumped["instruction"]]
    batch = preprocessor(env_preprocessor(observation))
    generator = torch.Generator().manual_seed(0)
    _, readout = policy.predict_action_chunk(batch, generator=generator, return_energy=True)
    return readout.context_energy.float().numpy()


def compare(here: dict, there: dict, checkpoint: Path | None) -> dict:
    """Pairs the two dumps by (task, state) and measures how their frames, and E_c of them, differ."""
    pairs = {(int(t), int(s)): i for i, (t, s) in enumerate(zip(there["task"], there["state"], strict=True))}
    wanted = [(int(t), int(s)) for t, s in zip(here["task"], here["state"], strict=True)]
    missing = [key for key in wanted if key not in pairs]
    if missing:
        raise ValueError(f"The other dump has no reset of these (task, state) pairs of this one: {missing}.")
    order = [pairs[key] for key in wanted]
    there = {k: (v[order] if v.ndim else v) for k, v in there.items()}
    size = frames_of(here, CAMERAS[0]).shape[1]
    result = {
        "pairs": len(order),
        "machines": [str(here["machine"]), str(there["machine"])],
        "cameras": {
            camera: pixel_differences(frames_of(here, camera), frames_of(there, camera)) for camera in CAMERAS
        },
    }
    if checkpoint is not None:
        energy_here, energy_there = (
            context_energies(checkpoint, here, size),
            context_energies(checkpoint, there, size),
        )
        result["context_energy"] = {
            "checkpoint": str(checkpoint),
            "here_mean": float(energy_here.mean()),
            "there_mean": float(energy_there.mean()),
            "paired_difference_min": float((energy_there - energy_here).min()),
            "paired_difference_max": float((energy_there - energy_here).max()),
        }
    return result


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("stage", choices=["dump", "compare"])
    parser.add_argument("--tasks", type=int, nargs="+", default=list(range(10)))
    parser.add_argument("--states", type=int, nargs="+", default=[30, 31])
    parser.add_argument(
        "--size", type=int, default=128, help="dump: frame height and width (the evaluation's)"
    )
    parser.add_argument("--here", type=Path, help="compare: this machine's dump")
    parser.add_argument("--there", type=Path, help="compare: the other machine's dump")
    parser.add_argument(
        "--checkpoint", type=Path, default=None, help="compare: E_c of both through this policy"
    )
    parser.add_argument("--output", type=Path, required=True)
    args = parser.parse_args(argv)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    if args.stage == "dump":
        np.savez_compressed(args.output, **dump(args.tasks, args.states, args.size))
        return
    load = lambda path: dict(np.load(path))  # noqa: E731
    result = compare(load(args.here), load(args.there), args.checkpoint)
    print(json.dumps(result, indent=1))
    args.output.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
