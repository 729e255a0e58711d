"""The energy of the successful plans: a failure score read from the policy's own energy head (issue 52, Table IV).

`joint_phase_energy` reads two scalars per chunk (E_c and E - E_c against their vanilla level at that chunk
index) and stays below `chunk_context_nn`, the distance of the pooled context to the successful calibration
contexts at the same chunk (research/docs/libero_runs.md, "Left to do"): a scalar per chunk does not know where
in the task the rollout is. This asks the energy head that question instead. At chunk k the successful
calibration rollouts executed chunks a_j^(k); a rollout on their track should find one of them almost as
plausible as its own refined chunk a^(K) under its context C_k, and a rollout that is behind (a missed grasp, an
object dropped) should find all of them implausible:

    s_k = min_j E_head(a_j^(k'), C_k) - E_head(a^(K), C_k),   k' in [k - w, k + w]

It stores the calibration's successful action chunks (H x d_a numbers each), no features.

Stages (every stage skips what its folder holds, so a cut run resumes):

    W=outputs/plan_energy_D; C=research/results/libero_object10_more; P=research/benchmarks/plan_energy.py
    MUJOCO_GL=egl python $P capture --work=$W --results=$C --run=ebvla_joint_fast_cpu_more \
        --conditions vanilla_calib vanilla_heldout vanilla_confirm --jobs=2
    OMP_NUM_THREADS=1 python $P score --work=$W --run=ebvla_joint_fast_cpu_more --results=$C \
        --held_out=vanilla_heldout --output=$C/reports/plan_energy_choice.json

`score` runs one head pass per chunk (about 1 s a rollout on one thread); beside a training run it slows that
run several-fold (the training's threads wait on each other), so run it alone or beside single-threaded rollouts.

`capture` re-runs the pipeline's jobs (same initial states and seeds) under `ebvla-eval` with two hooks that keep,
for the first `MAX_CHUNKS` chunks of every episode, the head's per-block keys and values and the refined chunk
(`plan_capture.pt` beside the energy records). The rollouts are the pipeline's: `score` checks each capture's
head energy against the records' final energy, and the records' successes against the committed ones.
"""

import argparse
import json
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import libero_pipeline as lp  # noqa: E402

CAPTURE_FILE = "plan_capture.pt"
# Chunks 0..19 of an episode: the failure checks read the first 16 (Table IV at chunk 16), and a window of a few
# chunks around each.
MAX_CHUNKS = 20
# fp16 keys and values move the head energy by at most 0.009 over D's first 400 calibration chunks.
CAPTURE_TOLERANCE = 0.05


def eval_one(argv: list[str]) -> None:
    """`ebvla-eval` with the capture hooks: runs in the job's own process."""
    from lerobot.configs import parser
    from lerobot.utils.import_utils import register_third_party_plugins
    from lerobot.utils.utils import init_logging

    from lerobot_policy_ebvla import modeling_ebvla
    from lerobot_policy_ebvla.pipelines.eval_energy import EnergyEvalPipelineConfig, eval_energy

    rows: list[dict] = []
    last_kv: dict = {}
    encode_context = modeling_ebvla.EBVLA.encode_context
    predict_action_chunk = modeling_ebvla.EBVLAPolicy.predict_action_chunk

    def encode_and_keep(self, batch, return_features=False):
        out = encode_context(self, batch, return_features)
        last_kv["kv"] = out[0] if return_features else out
        return out

    def predict_and_keep(self, batch, *args, **kwargs):
        index = self.chunk_index
        out = predict_action_chunk(self, batch, *args, **kwargs)
        actions = out[0] if isinstance(out, tuple) else out
        row = {"chunk_index": index}
        if index < MAX_CHUNKS:
            row["kv"] = [(k.detach().half().cpu(), v.detach().half().cpu()) for k, v in last_kv["kv"]]
            row["actions"] = actions.detach().float().cpu()
        rows.append(row)
        return out

    modeling_ebvla.EBVLA.encode_context = encode_and_keep
    modeling_ebvla.EBVLAPolicy.predict_action_chunk = predict_and_keep
    output_dir = next(a.split("=", 1)[1] for a in argv if a.startswith("--output_dir="))

    # What `ebvla-eval` runs, with the hooks above in place.
    @parser.wrap()
    def run(cfg: EnergyEvalPipelineConfig) -> None:
        eval_energy(cfg)

    init_logging()
    register_third_party_plugins()
    sys.argv = ["ebvla-eval", *argv]
    run()
    torch.save(rows, Path(output_dir) / CAPTURE_FILE)


def prepare_work(work: Path, results: Path, run: str) -> None:
    """A work folder whose `train/<run>/checkpoints/last` is the committed checkpoint, for `eval_command`."""
    work.mkdir(parents=True, exist_ok=True)
    (work / "recording_summary.json").write_text((results / "recording_summary.json").read_text())
    last = work / "train" / run / "checkpoints" / "last"
    if not last.exists():
        last.parent.mkdir(parents=True, exist_ok=True)
        last.symlink_to((results / "train" / run / "last").resolve())


def capture(args: argparse.Namespace) -> None:
    prepare_work(args.work, args.results, args.run)
    jobs = lp.eval_jobs(
        [args.run],
        args.tasks,
        vanilla=20,
        perturbed=0,
        conditions=(),
        calibration=10,
        confirm=20,
        vanilla_conditions=("vanilla_calib", "vanilla_heldout"),
    )
    jobs = [job for job in jobs if job.condition in args.conditions]
    jobs.sort(key=lambda job: args.conditions.index(job.condition))

    def run(job: lp.EvalJob) -> str:
        folder = args.work / "eval" / job.name
        if (folder / CAPTURE_FILE).exists():
            return "done before"
        command = lp.eval_command(args.work, job, "cpu")
        command = [sys.executable, __file__, "eval-one", *command[1:]]
        log = args.work / "logs" / f"{job.name.replace('/', '_')}.log"
        status = lp.run_logged(command, log)
        print(f"{job.name}: exit {status}", flush=True)
        return "done" if status == 0 else f"exit {status}"

    with ThreadPoolExecutor(args.jobs) as pool:
        statuses = list(pool.map(run, jobs))
    print({s: statuses.count(s) for s in set(statuses)})


# Scoring -----------------------------------------------------------------------------------------------------------

CHUNKS = 16  # Table IV's chunk: the shipped `joint_phase_energy` and `chunk_context_nn` read 16 chunks
K = 1.0  # T = mu + K sigma of the successful calibration rollouts, as the shipped check sets it
DEV, TEST = "vanilla_heldout", "vanilla_confirm"


def captured_episodes(folder: Path) -> list[dict]:
    """A job's episodes, in the records' order: success, the records (with the pooled context the baseline reads),
    and the first `MAX_CHUNKS` chunks' keys/values and refined chunk. Each capture row is checked against the records
    it belongs to (the same number of chunks, in order)."""
    from lerobot_policy_ebvla.monitoring.records import group_by_episode, read_energy_records, records_file_in

    episodes = list(group_by_episode(read_energy_records(records_file_in(folder))).values())
    rows = torch.load(folder / CAPTURE_FILE)
    starts = [i for i, r in enumerate(rows) if r["chunk_index"] == 0] + [len(rows)]
    if len(starts) - 1 != len(episodes):
        raise ValueError(f"{folder}: {len(starts) - 1} captured episodes, {len(episodes)} in the records.")
    found = []
    for records, first, end in zip(episodes, starts, starts[1:], strict=False):
        captured = rows[first:end]
        if [r["chunk_index"] for r in captured] != [r.chunk_index for r in records]:
            raise ValueError(
                f"{folder}: episode {records[0].episode_index}'s chunks differ from its records."
            )
        chunks = [r for r in captured if "kv" in r]
        found.append({"success": records[0].success, "records": records, "chunks": chunks})
    return found


def check_same_rollouts(folder: Path, committed: Path) -> None:
    """Raises unless a captured job's records are the committed job's: every chunk's final energy and success."""
    from lerobot_policy_ebvla.monitoring.records import read_energy_records, records_file_in

    ours, theirs = (read_energy_records(records_file_in(f)) for f in (folder, committed))
    same = len(ours) == len(theirs) and all(
        abs(a.final_energy - b.final_energy) < 1e-4 and a.success == b.success
        for a, b in zip(ours, theirs, strict=True)
    )
    if not same:
        raise ValueError(f"{folder}: the re-run rollouts differ from the committed ones in {committed}.")


@torch.no_grad()
def head_energies(head, kv: list, candidates: torch.Tensor) -> torch.Tensor:
    """E_head(a, C) of N candidate chunks (N, H, d_a) under one chunk's keys/values: (N,)."""
    kv = [(k.float(), v.float()) for k, v in kv]
    return head(candidates, kv).mean(dim=-1)


def plan_gaps(
    head, episode: dict, bank: dict[int, list[tuple[int, torch.Tensor]]], own_id, windows=(0, 1, 2)
) -> dict[int, np.ndarray]:
    """{w: s_k for k < CHUNKS} (fewer chunks when the episode ends sooner): the minimum over the bank's chunks of
    indices k - w..k + w (none of the episode's own: `own_id`) of E_head under C_k, minus E_head of the episode's own
    refined chunk. One head pass per chunk scores the widest window's plans and the own chunk together."""
    widest = max(windows)
    gaps = {w: [] for w in windows}
    for chunk, record in zip(episode["chunks"][:CHUNKS], episode["records"], strict=False):
        k = chunk["chunk_index"]
        plans = [
            (i, a) for i in range(k - widest, k + widest + 1) for rid, a in bank.get(i, []) if rid != own_id
        ]
        if not any(i == k for i, _ in plans):
            raise ValueError(
                f"No successful calibration rollout (but this one) has a chunk {k} to compare with."
            )
        candidates = torch.cat([torch.stack([a for _, a in plans]), chunk["actions"]])
        energies = head_energies(head, chunk["kv"], candidates)
        # The captured keys/values are fp16: the own chunk's head energy must still be the recorded E - E_c.
        recorded = record.final_energy - record.context_energy
        if abs(float(energies[-1]) - recorded) > CAPTURE_TOLERANCE:
            raise ValueError(
                f"Episode {record.episode_index}, chunk {k}: captured head energy {float(energies[-1]):.4f}, "
                f"recorded E - E_c {recorded:.4f}."
            )
        offsets = torch.tensor([abs(i - k) for i, _ in plans])
        for w in windows:
            gaps[w].append(float(energies[:-1][offsets <= w].min() - energies[-1]))
    return {w: np.array(values) for w, values in gaps.items()}


def success_bank(calibration: list[dict]) -> dict[int, list[tuple[int, torch.Tensor]]]:
    """The successful calibration rollouts' refined chunks by chunk index: {k: [(rollout id, (H, d_a))]}."""
    bank: dict[int, list] = {}
    for rid, episode in enumerate(calibration):
        if episode["success"]:
            for chunk in episode["chunks"]:
                bank.setdefault(chunk["chunk_index"], []).append((rid, chunk["actions"][0]))
    return bank


WINDOWS = (0, 1, 2)


def phase_z(gaps: np.ndarray, mu: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    return (gaps - mu[: len(gaps)]) / sigma[: len(gaps)]


def readings(gaps: dict, terms: list[np.ndarray], mu: np.ndarray, sigma: np.ndarray) -> dict:
    """The candidate readings of one rollout (fixed before any plan gap was seen; research/docs/libero_runs.md, "The
    energy of the successful plans"): `gaps[w]` its s_k, `terms` its (n, 2) z_c, z_h of `joint_phase_energy`."""
    z = phase_z(gaps[1], mu, sigma)
    n = min(len(z), len(terms))
    return {
        "plan gap, w=0": float(gaps[0].mean()),
        "plan gap, w=1": float(gaps[1].mean()),
        "plan gap, w=2": float(gaps[2].mean()),
        "plan gap against vanilla, w=1": float(z.mean()),
        "plan gap against vanilla and both terms, w=1": float(np.column_stack([z[:n], terms[:n]]).mean()),
        "plan gap, w=1, last 4 chunks": float(gaps[1][-4:].mean()),
    }


def task_episodes(root: Path, condition: str) -> list[list]:
    """A condition's episodes (each its records), tasks 0-9 in order, each task's in its records' order."""
    from lerobot_policy_ebvla.monitoring.records import group_by_episode, read_energy_records, records_file_in

    return [
        records
        for task in range(10)
        for records in group_by_episode(
            read_energy_records(records_file_in(root / condition / f"task{task}"))
        ).values()
    ]


def capture_gaps(args: argparse.Namespace, held_condition: str) -> dict:
    """Every calibration and held-out rollout's s_k for each window (`plan_gaps`), from the captures: the expensive
    part, written to the result so that `rows_of` (and the test) can recompute the table from it."""
    from lerobot_policy_ebvla import EBVLAPolicy

    policy = EBVLAPolicy.from_pretrained(
        args.work / "train" / args.run / "checkpoints" / "last" / "pretrained_model"
    )
    head = policy.eval().model.head
    root = args.work / "eval" / args.run

    def load(condition: str) -> list[dict]:
        folders = [root / condition / f"task{task}" for task in range(10)]
        if args.results is not None:
            for folder in folders:
                check_same_rollouts(folder, args.results / "eval" / args.run / condition / folder.name)
        return [e for folder in folders for e in captured_episodes(folder)]

    calibration, held = load("vanilla_calib"), load(held_condition)
    bank = success_bank(calibration)

    def listed(gaps: dict[int, np.ndarray]) -> dict[str, list[float]]:
        return {str(w): [round(float(v), 6) for v in values] for w, values in gaps.items()}

    return {
        "calibration": [listed(plan_gaps(head, e, bank, rid, WINDOWS)) for rid, e in enumerate(calibration)],
        "held_out": [listed(plan_gaps(head, e, bank, None, WINDOWS)) for e in held],
    }


def rows_of(calibration: list[list], held: list[list], gaps: dict) -> dict:
    """Each reading's and `chunk_context_nn`'s row on the held-out rollouts (their records), at T = mu + K sigma of the
    successful calibration rollouts, with the AUROC minus the baseline's and its paired interval."""
    from failure_check_test import BASELINE, row
    from failure_score_variants import components, rows_against_baseline

    from lerobot_policy_ebvla.monitoring.baselines import chunk_context_nn

    def arrays(listed: dict) -> dict[int, np.ndarray]:
        return {int(w): np.array(values) for w, values in listed.items()}

    cal_gaps, held_gaps = [arrays(g) for g in gaps["calibration"]], [arrays(g) for g in gaps["held_out"]]
    successful = np.array([episode[0].success for episode in calibration])
    failed = np.array([not episode[0].success for episode in held])
    # Per-chunk vanilla level of s_k (w = 1): the successful calibration rollouts', each scored without itself.
    stacked = [g[1] for g, ok in zip(cal_gaps, successful, strict=True) if ok]
    mu = np.array([np.mean([g[k] for g in stacked if len(g) > k]) for k in range(CHUNKS)])
    sigma = np.array([np.std([g[k] for g in stacked if len(g) > k]) for k in range(CHUNKS)])
    cal_terms, held_terms = components(calibration, held, CHUNKS)
    cal_values = [readings(g, t, mu, sigma) for g, t in zip(cal_gaps, cal_terms, strict=True)]
    held_values = [readings(g, t, mu, sigma) for g, t in zip(held_gaps, held_terms, strict=True)]
    values = {
        name: (np.array([v[name] for v in cal_values]), np.array([v[name] for v in held_values]))
        for name in cal_values[0]
    }
    cal_map, held_map = dict(enumerate(calibration)), dict(enumerate(held))
    values[BASELINE] = (
        chunk_context_nn(cal_map, cal_map, CHUNKS - 1),
        chunk_context_nn(cal_map, held_map, CHUNKS - 1),
    )
    rows = rows_against_baseline(values, successful, failed, K)
    # The shipped check (the mean of both terms) at its own T, from the terms above: the test compares the chosen
    # reading with it on the same rollouts.
    cal_shipped = np.array([t.mean() for t in cal_terms])[successful]
    shipped = row(
        "mean of both (shipped)",  # failure_score_variants' name for it
        np.array([t.mean() for t in held_terms]),
        float(cal_shipped.mean() + K * cal_shipped.std()),
        failed,
    )
    return {
        "shipped": shipped,
        "calibration_rollouts": int(successful.size),
        "calibration_successful": int(successful.sum()),
        "rollouts": int(failed.size),
        "failed": int(failed.sum()),
        "rows": rows,
    }


def markdown(result: dict) -> str:
    """The rows as a table, each reading's AUROC minus the baseline's, and the choice."""
    from failure_check_test import rows_table

    lines = [
        f"Plan gaps of `{result['run']}` over the first {result['chunks']} chunks, T = mu + {result['k']:g} sigma of "
        f"the {result['calibration_successful']} successful of {result['calibration_rollouts']} calibration rollouts."
    ]
    lines += rows_table(result["held_out"], result, name_column="Reading")
    lines += ["", "AUROC minus `chunk_context_nn`'s on the same rollouts [paired bootstrap 95 % CI]:"]
    lines += [
        f"- {r['score']}: {r['auroc_minus_baseline']:+.3f} [{low:+.3f}, {high:+.3f}]"
        for r in result["rows"]
        if "auroc_minus_baseline" in r
        for low, high in [r["auroc_minus_baseline_interval"]]
    ]
    if "chosen" in result:
        lines += ["", f"Chosen (the highest AUROC): {result['chosen']}"]
    if result["held_out"] == TEST:
        shipped = result["shipped"]
        lines += [
            "",
            f"`joint_phase_energy` (shipped) on the same rollouts at its own T: balanced accuracy "
            f"{shipped['balanced_accuracy']:.1%}, AUROC {shipped['auroc']:.3f}",
        ]
    return "\n".join(lines) + "\n"


def chosen(result: dict) -> dict:
    """The rule's choice among the readings: the highest AUROC, a tie broken by the balanced accuracy at T."""
    from failure_check_test import BASELINE

    readings_rows = [r for r in result["rows"] if r["score"] != BASELINE]
    return max(readings_rows, key=lambda r: (r["auroc"], r["balanced_accuracy"]))


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "eval-one":
        eval_one(argv[1:])
        return
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="stage", required=True)
    cap = sub.add_parser("capture")
    cap.add_argument("--work", type=Path, required=True)
    cap.add_argument("--results", type=Path, required=True)
    cap.add_argument("--run", required=True)
    cap.add_argument("--conditions", nargs="+", required=True)
    cap.add_argument("--tasks", type=int, nargs="+", default=list(range(10)))
    cap.add_argument("--jobs", type=int, default=2)
    sco = sub.add_parser("score")
    sco.add_argument("--work", type=Path, required=True)
    sco.add_argument("--run", required=True)
    sco.add_argument(
        "--results", type=Path, default=None, help="check the rollouts against this results folder's"
    )
    sco.add_argument("--held_out", default=DEV, choices=(DEV, TEST))
    sco.add_argument("--output", type=Path, default=None)
    args = parser.parse_args(argv)
    if args.stage == "capture":
        capture(args)
    else:
        gaps = capture_gaps(args, args.held_out)
        root = args.work / "eval" / args.run
        result = {"run": args.run, "held_out": args.held_out, "chunks": CHUNKS, "k": K}
        result |= rows_of(task_episodes(root, "vanilla_calib"), task_episodes(root, args.held_out), gaps)
        if args.held_out == DEV:
            result["chosen"] = chosen(result)["score"]
        print(markdown(result))
        if args.output is not None:
            args.output.parent.mkdir(parents=True, exist_ok=True)
            args.output.write_text(json.dumps(result | {"gaps": gaps}) + "\n")
            args.output.with_suffix(".md").write_text(markdown(result))


if __name__ == "__main__":
    main()
