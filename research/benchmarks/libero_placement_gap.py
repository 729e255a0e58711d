"""Are LIBERO-Object's 50 fixed initial states unlike the sampled placements policy D was trained on?

D (`ebvla_joint_fast_cpu_more`, research/results/libero_object10_more) learned from scripted demonstrations that start
from placements LIBERO's sampler draws with seeds 100000 + i (`libero_pipeline.py record --placement_seed=100000`),
and is evaluated on the task's fixed initial states 0-49 (`vanilla_calib` 0-9, `vanilla_heldout` 10-29,
`vanilla_confirm` 30-49) and on fresh placements from seeds 200000 + i (`vanilla_fresh`). For each task this script
resets the scene (a) on every fixed initial state, (b) on every training placement (the seeds of the kept
demonstrations, read from the recording reports) and (c) on fresh placements, and reads, after the reset's settling
steps, the goal object's pose (x, y, z, yaw: the heading of its body x axis in the table plane) and its container's
position (`envs.libero.goal_object_and_container`), their offset, and the distance from the object to the nearest
other object on the table.

Resets repeat LeRobot's `LiberoEnv.reset` (seed, LIBERO reset, the fixed state if any, `num_steps_wait` no-op
steps) on LIBERO's `ControlEnv` built without cameras or renderer (about 1 s a reset instead of 4 on two cores;
rendering changes no physics). Every evaluated episode is checked against its energy record: the goal distance
measured here must equal the one the rollout recorded at its first chunk (`goal_distance`), which ties each episode
to its fixed state (first state of its condition + `episode_index`) or its seed.

Then, per task: each fixed state's distance to the training placements (nearest neighbour in (x, y, yaw) of the
goal object, each coordinate divided by its spread over the training placements, yaw difference wrapped), and the
fraction of training placements within 1 cm and 15 degrees; "far" means farther than the 95th percentile of the
training placements' own leave-one-out nearest-neighbour distances (a rule set before outcomes are joined). The
distances are joined with D's outcome on each fixed state, giving success near vs far (n per side) and the AUROC of
the distance for predicting failure. The same is done in two wider spaces (with the container's position; every
object's x, y, yaw).

The robot's start (`measure_robot_start`, added after the placement results were seen): a fixed state also stores
the arm's joint angles, which a sampled reset sets to robosuite's default every time; per fixed state, the arm's
joint distance to that default and the end-effector's offset before the settling steps, with their AUROC for D's
failures.

Measurements are cached in the output JSON (`raw`): a task whose cache exists is not measured again (unless
`--remeasure`), so after `--deadline_min` stops a run the same command finishes the remaining tasks. On the 2-core
machine a reset took 1.0-1.5 s (all ten tasks: about 27 min of resets, and 80 s for the robot starts):

    MUJOCO_GL=egl nice -n 19 .venv/bin/python research/benchmarks/libero_placement_gap.py \
        --tasks 1 5 0 2 3 4 6 7 8 9 --fresh 20 --deadline_min 24
"""

import argparse
import glob
import json
import math
import time
from pathlib import Path

import numpy as np
from libero_pipeline import FRESH_PLACEMENT_SEED, eval_jobs
from scipy.stats import ks_2samp

REPO = Path(__file__).resolve().parents[2]
RESULTS = REPO / "research" / "results"
WORK = RESULTS / "libero_object10_more"
RUN = "ebvla_joint_fast_cpu_more"
# The recordings D's data aggregates: its own pieces and those linked from the first ten-task run.
RECORDING_REPORTS = [WORK / "recording_reports", RESULTS / "libero_object10" / "recording_reports"]
N_FIXED = 50
# D's evaluation (research/docs/libero_runs.md): calibration on states 0-9, 20 held out, 10 fresh, 20 confirmation.
EVAL_SIZES = {"calibration": 10, "vanilla": 20, "fresh": 10, "confirm": 20}
NN_COORDS = ("x", "y", "yaw")  # the goal object's placement: what the distance compares
FAR_QUANTILE = 95  # "far": beyond this percentile of the training placements' leave-one-out NN distances
CLOSE_XY_M, CLOSE_YAW_DEG = 0.01, 15.0
# Floors of the per-coordinate spreads used to standardize (an object whose yaw never varies has a spread of 0).
MIN_SPREAD = {"x": 1e-3, "y": 1e-3, "yaw": 1.0}


# Measuring -----------------------------------------------------------------------------------------------------


def training_seeds(task: int) -> list[int]:
    """The placement seeds of the kept demonstrations of `task`, from every recording report D's data uses."""
    seeds = set()
    for folder in RECORDING_REPORTS:
        for path in glob.glob(str(folder / f"task{task}_from*.json")):
            report = json.loads(Path(path).read_text())
            seeds |= {
                ep["placement_seed"] for ep in report["episodes"] if ep["kept"] and ep["task_id"] == task
            }
    summary = json.loads((WORK / "recording_summary.json").read_text())["tasks"][str(task)]
    if len(seeds) != summary["kept"]:
        raise RuntimeError(
            f"task {task}: {len(seeds)} kept seeds in the reports, {summary['kept']} in the summary"
        )
    return sorted(seeds)


def scene_pose(scene, target: str, container: str) -> dict:
    """The goal object's pose, its container's position and the nearest other object, in the world frame."""
    data = scene.sim.data

    def position(name):
        return np.asarray(data.body_xpos[scene.obj_body_id[name]], dtype=float)

    def yaw(name):  # heading of the body's x axis in the table plane, degrees
        rotation = np.asarray(data.body_xmat[scene.obj_body_id[name]], dtype=float).reshape(3, 3)
        return math.degrees(math.atan2(rotation[1, 0], rotation[0, 0]))

    obj, box = position(target), position(container)
    others = [position(name) for name in scene.obj_body_id if name not in (target, container)]
    every = {}
    for name in scene.obj_body_id:  # every object's (x, y, yaw): the whole layout
        every.update(
            {
                f"obj:{name}_x": position(name)[0],
                f"obj:{name}_y": position(name)[1],
                f"obj:{name}_yaw": yaw(name),
            }
        )
    return {
        "x": obj[0],
        "y": obj[1],
        "z": obj[2],
        "yaw": yaw(target),
        "container_x": box[0],
        "container_y": box[1],
        "container_z": box[2],
        "dx": obj[0] - box[0],
        "dy": obj[1] - box[1],
        "goal_distance": float(np.linalg.norm(obj - box)),
        "nearest_other_xy": float(min(np.linalg.norm(o[:2] - obj[:2]) for o in others))
        if others
        else math.nan,
        **{k: round(float(v), 6) for k, v in every.items()},
    }


def scene_env(task: int):
    """LeRobot's env as the evaluation builds it (not started: its BDDL file, fixed states and settling steps), and
    LIBERO's `ControlEnv` of the same task without cameras or renderer, reset once as LeRobot's `_ensure_env` does."""
    from lerobot_policy_ebvla.envs.libero_assets import require_libero_ready

    require_libero_ready()
    import gymnasium as gym
    from libero.libero.envs.env_wrapper import ControlEnv

    from lerobot_policy_ebvla.envs.libero import create_libero_ebvla_envs

    spec = create_libero_ebvla_envs(
        "libero_object", 1, {"task_ids": [task]}, "agentview_image", True, gym.vector.SyncVectorEnv
    )["libero_object"][task].envs[0]
    env = ControlEnv(
        bddl_file_name=spec._task_bddl_file,
        control_freq=spec.control_freq,
        hard_reset=spec.hard_reset,
        use_camera_obs=False,
        has_offscreen_renderer=False,
    )
    env.reset()
    return spec, env


def measure_task(task: int, n_fresh: int, n_fixed: int = N_FIXED, max_train: int | None = None) -> dict:
    """Resets the task's scene on its fixed states, training placements and fresh placements; returns the poses."""
    from lerobot.envs.libero import get_libero_dummy_action

    from lerobot_policy_ebvla.envs.libero import goal_object_and_container

    spec, env = scene_env(task)
    target, container = goal_object_and_container(env.env)

    def reset(seed, state=None):
        env.seed(seed)
        env.reset()
        if state is not None:
            env.set_init_state(state)
        for _ in range(spec.num_steps_wait):
            env.step(get_libero_dummy_action())
        return scene_pose(env.env, target, container)

    start = time.time()
    # Each fixed state with the seed its evaluation reset with (the seed only draws placements the state replaces).
    fixed = [reset(state_seeds(task).get(s), spec._init_states[s]) for s in range(n_fixed)]
    train_seeds = training_seeds(task)[:max_train]
    train = [{"seed": s, **reset(s)} for s in train_seeds]
    fresh = [{"seed": FRESH_PLACEMENT_SEED + i, **reset(FRESH_PLACEMENT_SEED + i)} for i in range(n_fresh)]
    n_resets = len(fixed) + len(train) + len(fresh)
    seconds = time.time() - start
    env.close()
    spec.close()
    return {
        "task_name": spec.task,
        "target": target,
        "container": container,
        "fixed": [{"state": s, **pose} for s, pose in enumerate(fixed)],
        "train": train,
        "fresh": fresh,
        "n_resets": n_resets,
        "seconds": round(seconds, 1),
        "seconds_per_reset": round(seconds / n_resets, 3),
    }


def measure_robot_start(task: int, n_fixed: int = N_FIXED) -> dict:
    """The robot's starting arm configuration: LIBERO's fixed states store one (in the state vector) that a sampled
    placement's reset does not draw. Per fixed state, its arm joints' distance to the configuration every sampled
    reset starts from (checked on three training seeds and one fresh seed), and the hand's (end-effector site's)
    offset, before the settling steps. No settling resets: the state is set and forwarded once."""
    spec, env = scene_env(task)
    robot = env.env.robots[0]
    arm, gripper = np.array(robot._ref_joint_pos_indexes), np.array(robot._ref_gripper_joint_pos_indexes)

    def start():
        data = env.env.sim.data
        return (
            np.array(data.qpos[arm]),
            np.array(data.qpos[gripper]),
            np.array(data.site_xpos[robot.eef_site_id]),
        )

    sampled = []
    for seed in (100000, 100001, 100002, FRESH_PLACEMENT_SEED):
        env.seed(seed)
        env.reset()
        sampled.append(start())
    q0, g0, eef0 = sampled[0]
    spread = max(float(np.abs(q - q0).max()) for q, _, _ in sampled)
    rows = []
    for state in range(n_fixed):
        env.set_init_state(spec._init_states[state])
        q, g, eef = start()
        rows.append(
            {
                "state": state,
                "arm_dq_norm_rad": float(np.linalg.norm(q - q0)),
                "arm_dq_max_rad": float(np.abs(q - q0).max()),
                "gripper_dq_max": float(np.abs(g - g0).max()),
                "eef_offset_m": float(np.linalg.norm(eef - eef0)),
                "eef_dx": float(eef[0] - eef0[0]),
                "eef_dy": float(eef[1] - eef0[1]),
                "eef_dz": float(eef[2] - eef0[2]),
            }
        )
    env.close()
    return {
        "sampled_arm_qpos": q0.round(6).tolist(),
        "sampled_eef": eef0.round(6).tolist(),
        "sampled_arm_max_abs_diff_across_seeds_rad": spread,
        "fixed": rows,
    }


# D's outcomes ---------------------------------------------------------------------------------------------------


def d_jobs(task: int):
    """D's evaluation jobs of `task`, as `libero_pipeline eval` queued them."""
    return eval_jobs(
        [RUN],
        [task],
        EVAL_SIZES["vanilla"],
        0,
        conditions=(),
        calibration=EVAL_SIZES["calibration"],
        fresh=EVAL_SIZES["fresh"],
        confirm=EVAL_SIZES["confirm"],
    )


def state_seeds(task: int) -> dict[int, int]:
    """{fixed state: the seed its evaluation episode reset with}."""
    return {
        job.first + k: job.seed + k
        for job in d_jobs(task)
        if job.condition != "vanilla_fresh"
        for k in range(job.n)
    }


def outcomes(task: int) -> dict:
    """D's rollouts of `task` per condition: {condition: [{episode, state or seed, success, goal_distance}]}.

    The condition's env comes from `libero_pipeline.eval_jobs` with D's sizes: episode k starts from fixed state
    `first + k` (LeRobot steps the state by one per reset with one env) and is seeded `seed + k`; fresh episodes
    keep the placements of that seed."""
    from lerobot_policy_ebvla.monitoring.records import load_episodes

    found = {}
    for job in d_jobs(task):
        folder = WORK / "eval" / job.name
        info = json.loads((folder / "eval_info.json").read_text())["per_task"][0]["metrics"]["successes"]
        rows = []
        for (_, key), chunks in load_episodes([str(folder)]).items():
            first = chunks[0]
            if first.seed != job.seed + key.episode_index:
                raise RuntimeError(f"{job.name} episode {key.episode_index}: seed {first.seed}")
            rows.append(
                {
                    "episode": key.episode_index,
                    "success": bool(first.success),
                    "recorded_seed": first.seed,
                    "first_chunk_step": first.env_step,
                    "goal_distance": first.goal_distance,
                    **(
                        {"seed": first.seed}
                        if job.condition == "vanilla_fresh"
                        else {"state": job.first + key.episode_index}
                    ),
                }
            )
        rows.sort(key=lambda r: r["episode"])
        if [r["success"] for r in rows] != info or len(rows) != job.n:
            raise RuntimeError(f"{job.name}: records disagree with eval_info.json")
        found[job.condition] = rows
    return found


# Analysis ------------------------------------------------------------------------------------------------------

# The spaces distances are measured in: the goal object's placement (the primary one), with its container's
# position, and the whole layout (every object's x, y and yaw). Columns ending in "yaw" are angles (degrees).
SPACES = {
    "target": ["x", "y", "yaw"],
    "target_container": ["x", "y", "yaw", "container_x", "container_y"],
    "layout": None,  # every "obj:<name>_{x,y,yaw}" column
}
RANGE_COORDS = ("x", "y", "z", "yaw", "container_x", "container_y", "dx", "dy", "nearest_other_xy")


def space_columns(space: str, row: dict) -> list[str]:
    return SPACES[space] or sorted(k for k in row if k.startswith("obj:"))


def wrap_deg(d):
    return (np.asarray(d) + 180.0) % 360.0 - 180.0


def matrix(rows, columns) -> np.ndarray:
    return np.array([[r[c] for c in columns] for r in rows], dtype=float)


def spreads(train: np.ndarray, columns) -> np.ndarray:
    """Each column's spread over the training placements (angles about their circular mean), floored."""
    out = []
    for i, c in enumerate(columns):
        if c.endswith("yaw"):
            mean = math.degrees(np.angle(np.exp(1j * np.radians(train[:, i])).mean()))
            out.append(max(float(np.sqrt((wrap_deg(train[:, i] - mean) ** 2).mean())), 1.0))
        else:
            out.append(max(float(train[:, i].std()), 1e-3))
    return np.array(out)


def standardized_nn(queries, reference, scale, angular, leave_one_out=False) -> np.ndarray:
    """Nearest-neighbour distance of each query row to the `reference` rows, columns divided by `scale`."""
    diff = queries[:, None, :] - reference[None, :, :]
    diff[..., angular] = wrap_deg(diff[..., angular])
    dist = np.sqrt(((diff / scale) ** 2).sum(-1))
    if leave_one_out:
        np.fill_diagonal(dist, np.inf)
    return dist.min(1)


def close_fraction(queries, reference) -> np.ndarray:
    """Fraction of `reference` (x, y, yaw) placements within CLOSE_XY_M in (x, y) and CLOSE_YAW_DEG in yaw."""
    xy = np.linalg.norm(queries[:, None, :2] - reference[None, :, :2], axis=-1)
    yaw = np.abs(wrap_deg(queries[:, None, 2] - reference[None, :, 2]))
    return ((xy <= CLOSE_XY_M) & (yaw <= CLOSE_YAW_DEG)).mean(1)


def auroc_block(negatives, positives) -> dict:
    """AUROC (positives scoring higher) with its stratified bootstrap 95 % interval and the n of each side."""
    from lerobot_policy_ebvla.monitoring.metrics import auroc, bootstrap_auroc_interval

    neg, pos = np.asarray(negatives, float), np.asarray(positives, float)
    value = auroc(neg, pos)
    low, high = bootstrap_auroc_interval(neg, pos)
    return {
        "auroc": None if math.isnan(value) else round(value, 3),
        "ci95": None if math.isnan(low) else [round(low, 3), round(high, 3)],
        "n_positive": int(pos.size),
        "n_negative": int(neg.size),
    }


def success_split(success, far) -> dict:
    success, far = np.asarray(success, bool), np.asarray(far, bool)

    def side(mask):
        return {
            "n": int(mask.sum()),
            "successes": int(success[mask].sum()),
            "rate": None if not mask.any() else round(float(success[mask].mean()), 3),
        }

    return {"near": side(~far), "far": side(far)}


def summarize(values) -> dict:
    values = np.asarray(values, float)
    return {
        "min": round(float(values.min()), 4),
        "max": round(float(values.max()), 4),
        "median": round(float(np.median(values)), 4),
        "std": round(float(values.std()), 4),
    }


def join_outcomes(raw: dict, runs: dict) -> tuple[dict, dict, float]:
    """({fixed state: (condition, success)}, {fresh seed: success}, the largest |goal distance measured here -
    goal distance the episode recorded at its first chunk| over the evaluated episodes that were measured)."""
    fixed, fresh = raw["fixed"], {r["seed"]: r for r in raw["fresh"]}
    by_state, by_seed, mismatch = {}, {}, 0.0
    for condition, rows in runs.items():
        for row in rows:
            if "state" in row:
                if row["state"] >= len(fixed):
                    continue
                measured = fixed[row["state"]]
                by_state[row["state"]] = (condition, row["success"])
            else:
                if row["seed"] not in fresh:
                    continue
                measured = fresh[row["seed"]]
                by_seed[row["seed"]] = row["success"]
            mismatch = max(mismatch, abs(measured["goal_distance"] - row["goal_distance"]))
    return by_state, by_seed, mismatch


def space_gap(space, raw, by_state, by_seed) -> dict:
    """Distances of the fixed and fresh placements to the training ones in one space, and D's success by them."""
    fixed, train, fresh = raw["fixed"], raw["train"], raw["fresh"]
    columns = space_columns(space, train[0])
    angular = np.array([c.endswith("yaw") for c in columns])
    t = matrix(train, columns)
    scale = spreads(t, columns)
    train_nn = standardized_nn(t, t, scale, angular, leave_one_out=True)
    threshold = float(np.percentile(train_nn, FAR_QUANTILE))
    fixed_nn = standardized_nn(matrix(fixed, columns), t, scale, angular)
    fresh_nn = standardized_nn(matrix(fresh, columns), t, scale, angular)
    states = sorted(by_state)
    success = np.array([by_state[s][1] for s in states], bool)
    seeds = sorted(by_seed)
    fresh_index = {r["seed"]: i for i, r in enumerate(fresh)}
    fresh_success = np.array([by_seed[s] for s in seeds], bool)
    fresh_far = np.array([fresh_nn[fresh_index[s]] > threshold for s in seeds], bool)
    dist = fixed_nn[states]
    return {
        "n_columns": len(columns),
        "far_threshold": round(threshold, 3),
        "nn_train_leave_one_out": summarize(train_nn),
        "nn_fixed": summarize(fixed_nn),
        "nn_fresh": summarize(fresh_nn),
        "n_far": {
            "fixed": int((fixed_nn > threshold).sum()),
            "n_fixed": len(fixed),
            "fresh": int((fresh_nn > threshold).sum()),
            "n_fresh": len(fresh),
        },
        # Are the fixed states farther from the training placements than fresh samples of the same sampler are?
        "auroc_fixed_vs_fresh_nn": auroc_block(fresh_nn, fixed_nn),
        "fixed_success_near_vs_far": success_split(success, dist > threshold),
        "fresh_success_near_vs_far": success_split(fresh_success, fresh_far),
        "auroc_failure_fixed": auroc_block(dist[success], dist[~success]),
        "_fixed_nn": fixed_nn.tolist(),
        "_threshold": threshold,
    }


def analyze_task(raw: dict, runs: dict) -> dict:
    fixed, train, fresh = raw["fixed"], raw["train"], raw["fresh"]
    by_state, by_seed, mismatch = join_outcomes(raw, runs)
    ranges = {}
    for c in RANGE_COORDS:
        f, t, r = (np.array([row[c] for row in rows]) for rows in (fixed, train, fresh))
        ranges[c] = {
            "fixed": summarize(f),
            "train": summarize(t),
            "fresh": summarize(r),
            "n_fixed_outside_train_range": int(((f < t.min()) | (f > t.max())).sum()),
            "n_fresh_outside_train_range": int(((r < t.min()) | (r > t.max())).sum()),
            "ks_p_fixed_vs_train": float(ks_2samp(f, t).pvalue),
            "ks_p_fresh_vs_train": float(ks_2samp(r, t).pvalue),
        }

    def outside(rows, columns):
        t = {c: np.array([row[c] for row in train]) for c in columns}
        return sum(any(not t[c].min() <= row[c] <= t[c].max() for c in columns) for row in rows)

    robot = raw.get("robot")
    if robot is not None:
        rows = {r["state"]: r for r in robot["fixed"]}
        ok = [s for s in sorted(by_state) if s in rows]
        won = np.array([by_state[s][1] for s in ok], bool)
        offset = np.array([rows[s]["eef_offset_m"] for s in ok])
        dq = np.array([rows[s]["arm_dq_norm_rad"] for s in ok])
        median = float(np.median(offset))
        robot_gap = {
            "sampled_arm_max_abs_diff_across_seeds_rad": robot["sampled_arm_max_abs_diff_across_seeds_rad"],
            "fixed_arm_dq_norm_rad": summarize([r["arm_dq_norm_rad"] for r in robot["fixed"]]),
            "fixed_eef_offset_m": summarize([r["eef_offset_m"] for r in robot["fixed"]]),
            "n_fixed_with_arm_off_default": int(sum(r["arm_dq_max_rad"] > 1e-6 for r in robot["fixed"])),
            "auroc_failure_eef_offset": auroc_block(offset[won], offset[~won]),
            "auroc_failure_arm_dq_norm": auroc_block(dq[won], dq[~won]),
            "success_by_eef_offset_vs_task_median": {
                "median_m": round(median, 4),
                **dict(
                    zip(("below_or_at", "above"), success_split(won, offset > median).values(), strict=True)
                ),
            },
            "_offset": offset.tolist(),
            "_success": won.tolist(),
        }
    else:
        robot_gap = None
    layout_columns = space_columns("layout", train[0])
    states = sorted(by_state)
    success = np.array([by_state[s][1] for s in states], bool)
    t_target = matrix(train, SPACES["target"])
    fixed_close = close_fraction(matrix(fixed, SPACES["target"]), t_target)
    fresh_close = close_fraction(matrix(fresh, SPACES["target"]), t_target)
    spaces = {space: space_gap(space, raw, by_state, by_seed) for space in SPACES}
    per_state = [
        {
            "state": s,
            "condition": by_state[s][0],
            "success": by_state[s][1],
            **{f"nn_{space}": round(spaces[space]["_fixed_nn"][s], 3) for space in SPACES},
            **{
                f"far_{space}": spaces[space]["_fixed_nn"][s] > spaces[space]["_threshold"]
                for space in SPACES
            },
            "close_fraction": round(float(fixed_close[s]), 3),
            **{
                c: round(fixed[s][c], 4)
                for c in ("x", "y", "yaw", "container_x", "container_y", "nearest_other_xy")
            },
            **({} if robot is None else {"eef_offset_m": round(rows[s]["eef_offset_m"], 4)}),
        }
        for s in states
    ]

    def over_threshold(space, s):  # pooled across tasks as distance / the task's "far" threshold (> 1: far)
        distance, threshold = spaces[space]["_fixed_nn"][s], spaces[space]["_threshold"]
        return distance / threshold if threshold > 0 else (math.inf if distance > 0 else 0.0)

    pooled = {
        space: {"nn_over_threshold": [over_threshold(space, s) for s in states], "success": success.tolist()}
        for space in SPACES
    }
    for gap in spaces.values():
        del gap["_fixed_nn"], gap["_threshold"]
    return {
        "task_name": raw["task_name"],
        "target": raw["target"],
        "container": raw["container"],
        "n": {
            "fixed": len(fixed),
            "train": len(train),
            "fresh": len(fresh),
            "fixed_with_outcome": len(states),
            "fresh_with_outcome": len(by_seed),
        },
        "seconds_per_reset": raw["seconds_per_reset"],
        "record_check_max_abs_goal_distance_diff_m": mismatch,
        "success": {
            "fixed": int(success.sum()),
            "fresh": int(sum(by_seed.values())),
            "by_condition": {
                c: [int(sum(r["success"] for r in rows)), len(rows)] for c, rows in runs.items()
            },
        },
        "ranges": ranges,
        "n_fixed_outside_train_range": {
            "target_x_y_yaw": outside(fixed, SPACES["target"]),
            "container_x_y": outside(fixed, ["container_x", "container_y"]),
            "layout_any": outside(fixed, layout_columns),
        },
        "n_fresh_outside_train_range": {
            "target_x_y_yaw": outside(fresh, SPACES["target"]),
            "container_x_y": outside(fresh, ["container_x", "container_y"]),
            "layout_any": outside(fresh, layout_columns),
        },
        "close_fraction_1cm_15deg": {
            "fixed": summarize(fixed_close),
            "fresh": summarize(fresh_close),
            "auroc_failure_fixed_minus_fraction": auroc_block(
                -fixed_close[states][success], -fixed_close[states][~success]
            ),
        },
        "spaces": spaces,
        # Every object's coordinates, fixed states against training placements: (KS p-value, n fixed outside the
        # training range), a check for a systematic shift of any single object.
        "layout_ks_p_and_n_outside": {
            c: [
                float(ks_2samp([r[c] for r in fixed], [r[c] for r in train]).pvalue),
                int(sum(not min(r[c] for r in train) <= f[c] <= max(r[c] for r in train) for f in fixed)),
            ]
            for c in layout_columns
            if not c.endswith("yaw")
        },
        "auroc_failure_fixed_minus_nearest_other_xy": auroc_block(
            [-fixed[s]["nearest_other_xy"] for s in np.array(states)[success]],
            [-fixed[s]["nearest_other_xy"] for s in np.array(states)[~success]],
        ),
        "robot_start": robot_gap,
        "per_state": per_state,
        "_pooled": pooled,
    }


def dump(result: dict, raw: dict, path: Path) -> None:
    """The results indented, the raw poses one placement a line."""
    head = json.dumps(result, indent=1)
    rows = ",\n".join(
        f' "{task}": {{'
        + ", ".join(
            f'"{k}": '
            + (
                json.dumps(v)
                if not isinstance(v, list)
                else "[\n  " + ",\n  ".join(json.dumps(r, separators=(",", ":")) for r in v) + "]"
            )
            for k, v in entry.items()
        )
        + "}"
        for task, entry in raw.items()
    )
    head = head[:-2] + ",\n" if result else "{\n"
    path.write_text(head + ' "raw": {\n' + rows + "\n }\n}\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--tasks", type=int, nargs="+", default=[1, 5, 0, 2, 3, 4, 6, 7, 8, 9])
    parser.add_argument("--fresh", type=int, default=20, help="fresh placements per task, seeds 200000 + i")
    parser.add_argument("--deadline_min", type=float, default=25.0, help="start no new task after this long")
    parser.add_argument(
        "--n_fixed", type=int, default=N_FIXED, help="fixed states 0..n-1 (fewer: a quick test)"
    )
    parser.add_argument(
        "--max_train", type=int, default=None, help="first training placements only (a quick test)"
    )
    parser.add_argument("--remeasure", action="store_true")
    parser.add_argument("--output", type=Path, default=WORK / "placement_gap.json")
    args = parser.parse_args()

    saved = json.loads(args.output.read_text()) if args.output.exists() else {}
    raw = {} if args.remeasure else saved.get("raw", {})
    start = time.time()
    for task in args.tasks:
        key = str(task)
        if key in raw and len(raw[key]["fresh"]) >= args.fresh:
            continue
        if (time.time() - start) / 60 > args.deadline_min:
            print(f"deadline: task {task} not measured")
            continue
        raw[key] = measure_task(task, args.fresh, args.n_fixed, args.max_train)
        print(
            f"task {task}: {raw[key]['n_resets']} resets, {raw[key]['seconds_per_reset']} s each", flush=True
        )
        dump({}, raw, args.output)  # keep what is measured so far

    for task in args.tasks:
        key = str(task)
        if key in raw and "robot" not in raw[key]:
            raw[key]["robot"] = measure_robot_start(task, len(raw[key]["fixed"]))
            print(f"task {task}: robot start measured", flush=True)
            dump({}, raw, args.output)

    tasks = {
        str(task): analyze_task(raw[str(task)], outcomes(task)) for task in args.tasks if str(task) in raw
    }
    pooled = {}
    for space in SPACES:
        ratio = np.array(sum((t["_pooled"][space]["nn_over_threshold"] for t in tasks.values()), []))
        success = np.array(sum((t["_pooled"][space]["success"] for t in tasks.values()), []), bool)
        pooled[space] = {
            "fixed_success_near_vs_far": success_split(success, ratio > 1),
            "auroc_failure_nn_over_threshold": auroc_block(ratio[success], ratio[~success]),
        }
    robot = [t["robot_start"] for t in tasks.values() if t["robot_start"]]
    if robot:
        offset = np.array(sum((r["_offset"] for r in robot), []))
        success = np.array(sum((r["_success"] for r in robot), []), bool)
        pooled["robot_start_eef_offset"] = {
            "auroc_failure": auroc_block(offset[success], offset[~success]),
            "note": "pooled over tasks without per-task normalization (every task's arm starts from one default)",
        }
        for r in robot:
            del r["_offset"], r["_success"]
    for t in tasks.values():
        del t["_pooled"]
    result = {
        "question": "Do LIBERO-Object's fixed initial states differ from the sampled placements D was trained on, "
        "and do D's failures sit on the unusual ones?",
        "run": RUN,
        "command": "MUJOCO_GL=egl nice -n 19 .venv/bin/python research/benchmarks/libero_placement_gap.py "
        f"--tasks {' '.join(map(str, args.tasks))} --fresh {args.fresh}",
        "machine": "2-core AMD EPYC without AVX512",
        "distance": "nearest-neighbour distance to the task's training placements, each column divided by its "
        "spread over them (std; yaw about its circular mean, wrapped; floors 1 mm and 1 deg); spaces: "
        "target = goal object (x, y, yaw), target_container = + container (x, y), layout = every "
        "object's (x, y, yaw)",
        "far_rule": f"distance > the {FAR_QUANTILE}th percentile of the training placements' own leave-one-out "
        "nearest-neighbour distances (per task and space; set before outcomes were joined)",
        "auroc_note": "auroc_failure: the distance ranking failed over successful rollouts (0.5: no relation); "
        "auroc_fixed_vs_fresh_nn: fixed states' distances over fresh placements' (0.5: fixed states "
        "as close to training as new samples of the training sampler); 95 % stratified bootstrap",
        "tasks_measured": [int(k) for k in tasks],
        "tasks_not_measured": [t for t in args.tasks if str(t) not in raw],
        "pooled": pooled,
        "tasks": tasks,
    }
    dump(result, {k: raw[k] for k in tasks}, args.output)
    for key, t in tasks.items():
        gap = t["spaces"]["target"]
        print(
            f"task {key} ({t['target']}): fixed {t['success']['fixed']}/{t['n']['fixed_with_outcome']}, "
            f"fresh {t['success']['fresh']}/{t['n']['fresh_with_outcome']}, record check "
            f"{t['record_check_max_abs_goal_distance_diff_m']:.1e} m"
        )
        for space, gap in t["spaces"].items():
            split = gap["fixed_success_near_vs_far"]
            print(
                f"  {space}: NN median train/fixed/fresh {gap['nn_train_leave_one_out']['median']}/"
                f"{gap['nn_fixed']['median']}/{gap['nn_fresh']['median']}, far {gap['n_far']}, "
                f"fixed-vs-fresh {gap['auroc_fixed_vs_fresh_nn']['auroc']}, near {split['near']}, "
                f"far {split['far']}, failure AUROC {gap['auroc_failure_fixed']['auroc']} "
                f"{gap['auroc_failure_fixed']['ci95']}"
            )
    for key, t in tasks.items():
        if t["robot_start"]:
            r = t["robot_start"]
            print(
                f"task {key} robot: eef offset {r['fixed_eef_offset_m']}, failure AUROC "
                f"{r['auroc_failure_eef_offset']}, split {r['success_by_eef_offset_vs_task_median']}"
            )
    for space, p in pooled.items():
        print("pooled", space, p)


if __name__ == "__main__":
    main()
