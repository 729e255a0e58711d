"""New held-out rollouts of K with its fitted phase energy: the second test of `joint_phase_time_energy` (issue 52,
Table IV; research/docs/libero_runs.md, "The phase energy on new rollouts", fixed before they ran).

K's checkpoint fitted by `ebvla-fit-phase-energy` records E_tau with every chunk as it runs, and with K's seeds it runs
K's rollouts chunk for chunk; new seeds give new rollouts of the same fixed states: states 10-29 with seeds 6000 + i,
states 30-49 with 7000 + i (`--test=second`; `third`: 8000 + i and 9000 + i; `fourth`: 10000 + i and 11000 + i; `fifth`: 12000 + i and
13000 + i; `sixth`: 14000 + i and 15000 + i), 20
a task and set, through the LIBERO pipeline's evaluation (`libero_pipeline.evaluate`: two jobs side by side, one torch
thread each, resumable: a job whose `eval_info.json` exists is skipped).

`--test=seventh --run=<its name>` runs another checkpoint the same way (G's confirmation of the success energy: 16000 + i
and 17000 + i; research/docs/libero_runs.md, "The success energy on another checkpoint").

Without K's fitted checkpoint (its demonstrations are not committed), `assemble` rebuilds it from what is: the
committed b18 checkpoint and the E_tau that `phase_energy_failure_check.py check` saved beside its report.

    python research/benchmarks/phase_energy_rollouts.py --checkpoint=outputs/k_phase/pretrained_model \\
        --recording_summary=research/results/libero_object10_b18/recording_summary.json \\
        --work=outputs/libero10_b18_phase --deadline_s=4800
    python research/benchmarks/phase_energy_rollouts.py --test=fourth --assemble \
        --checkpoint=research/results/libero_object10_b18/train/ebvla_joint_fast_cpu_b18/last/pretrained_model \
        --phase_energy=research/results/libero_object10_b18/reports/ebvla_joint_fast_cpu_b18/phase_energy/check.safetensors \
        --recording_summary=research/results/libero_object10_b18/recording_summary.json --work=outputs/libero10_b18_phase
"""

import argparse
import shutil
from pathlib import Path

from libero_pipeline import EvalJob, evaluate
from phase_energy_failure_check import load_phase_energy

from lerobot_policy_ebvla import EBVLAPolicy
from lerobot_policy_ebvla.pipelines.phase_energy import save_with_phase_energy

RUN = "ebvla_joint_fast_cpu_b18_phase"
# (condition, first fixed state, seed of its first episode) per test: seeds no earlier evaluation of K used
# (calibration 1000, held out 2000, shifts 3000, confirmation 4000, fresh placements 200000; the second test 6000 and
# 7000, the third 8000 and 9000, the fourth 10000 and 11000, the fifth 12000 and 13000 for the sixth's).
TESTS = {
    "second": (("vanilla_heldout_new", 10, 6000), ("vanilla_confirm_new", 30, 7000)),
    "third": (("vanilla_heldout_third", 10, 8000), ("vanilla_confirm_third", 30, 9000)),
    "fourth": (("vanilla_heldout_fourth", 10, 10000), ("vanilla_confirm_fourth", 30, 11000)),
    "fifth": (("vanilla_heldout_fifth", 10, 12000), ("vanilla_confirm_fifth", 30, 13000)),
    "sixth": (("vanilla_heldout_sixth", 10, 14000), ("vanilla_confirm_sixth", 30, 15000)),
    # G's: seeds neither G (1000, 2000, 4000) nor K ever ran.
    "seventh": (("vanilla_heldout_seventh", 10, 16000), ("vanilla_confirm_seventh", 30, 17000)),
}
TASKS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 9)


def jobs(test: str = "second", per_task: int = 20, run: str = RUN) -> list[EvalJob]:
    return [
        EvalJob(run, condition, task, first, per_task, seed)
        for condition, first, seed in TESTS[test]
        for task in TASKS
    ]


def assemble(checkpoint: Path, phase_energy: Path, output: Path) -> Path:
    """K's fitted checkpoint from the unfitted one and a saved E_tau, written as `ebvla-fit-phase-energy` writes it
    (`save_with_phase_energy`). Kept if present."""
    if not (output / "model.safetensors").exists():
        policy = EBVLAPolicy.from_pretrained(checkpoint)
        save_with_phase_energy(policy, load_phase_energy(phase_energy), checkpoint, output)
    return output


def prepare(work: Path, checkpoint: Path, recording_summary: Path, run: str = RUN) -> None:
    """The work folder as the pipeline reads it: the checkpoint as the run's last, and the recording's image size."""
    last = work / "train" / run / "checkpoints" / "last"
    last.mkdir(parents=True, exist_ok=True)
    link = last / "pretrained_model"
    if not link.exists():
        link.symlink_to(checkpoint.resolve())
    shutil.copy2(recording_summary, work / "recording_summary.json")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--checkpoint", type=Path, required=True, help="K's checkpoint with its phase energy")
    parser.add_argument(
        "--phase_energy", type=Path, default=None, help="with --assemble: the E_tau to fit into --checkpoint"
    )
    parser.add_argument(
        "--assemble", action="store_true", help="--checkpoint is unfitted: fit --phase_energy in"
    )
    parser.add_argument("--recording_summary", type=Path, required=True)
    parser.add_argument("--work", type=Path, required=True)
    parser.add_argument("--test", choices=sorted(TESTS), default="second", help="which set of new seeds")
    parser.add_argument(
        "--run",
        default=RUN,
        help="the run name the rollouts are filed under (another checkpoint than K's: its own name)",
    )
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--deadline_s", type=float, default=4800)
    args = parser.parse_args(argv)
    checkpoint = args.checkpoint
    if args.assemble:
        if args.phase_energy is None:
            parser.error("--assemble needs --phase_energy")
        checkpoint = assemble(checkpoint, args.phase_energy, args.work / "k_phase" / "pretrained_model")
    prepare(args.work, checkpoint, args.recording_summary, args.run)
    evaluate(args.work, jobs(args.test, run=args.run), "cpu", args.jobs, args.deadline_s)


if __name__ == "__main__":
    main()
