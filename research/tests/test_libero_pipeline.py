"""The LIBERO-Object pipeline (`research/benchmarks/libero_pipeline.py`) and the library options it added.

Its queue, commands and packing are checked on temporary folders, without the simulator; one slow test runs
every stage at a tiny size on CPU (it needs LIBERO set up, as the simulator tests of tests/test_libero.py).
"""

import json
import math
import tarfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from research.tests.conftest import load_benchmark
from tests.test_libero import requires_libero

pipeline = load_benchmark("libero_pipeline")


def write_json(path: Path, content: dict) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(content))
    return path


def fake_checkpoint(work: Path, run: str) -> Path:
    """A `last` checkpoint folder of `run`, as lerobot-train leaves it (only the files the pipeline looks at)."""
    checkpoint = work / "train" / run / "checkpoints" / "last" / "pretrained_model"
    write_json(checkpoint / "train_config.json", {})
    (checkpoint / "model.safetensors").write_bytes(b"weights")
    return checkpoint


@pytest.fixture
def work(tmp_path):
    """A pipeline folder whose recording stage has run, at 64 px."""
    write_json(tmp_path / "recording_summary.json", {"image_size": 64, "episodes_per_task": 2, "tasks": {}})
    return tmp_path


# The evaluation queue.


def test_eval_queue_puts_ebvla_vanilla_then_two_camera_conditions_before_the_other_policies():
    conditions = (("pose", 5), ("fov", 5), ("pose", 3))
    jobs = pipeline.eval_jobs(["ebvla_paper", "diffusion"], [0, 1], 10, 3, conditions)
    vanilla = ["vanilla_calib", "vanilla_heldout"]
    expected = (
        [("ebvla_paper", c, t) for t in (0, 1) for c in vanilla]
        + [("ebvla_paper", c, t) for c in ("pose5", "fov5") for t in (0, 1)]
        + [("diffusion", "vanilla_heldout", t) for t in (0, 1)]  # no energy to calibrate on
        + [("ebvla_paper", "pose3", t) for t in (0, 1)]
    )
    assert [(job.run, job.condition, job.task) for job in jobs] == expected
    assert len({job.name for job in jobs}) == len(jobs)


@pytest.mark.parametrize("vanilla", [10, 5])
def test_calibration_and_held_out_split_the_initial_states_and_perturbed_rollouts_start_at_zero(vanilla):
    jobs = {
        job.condition: job for job in pipeline.eval_jobs(["ebvla_paper"], [0], vanilla, 3, (("pose", 5),))
    }
    calibration, heldout, perturbed = jobs["vanilla_calib"], jobs["vanilla_heldout"], jobs["pose5"]
    assert (calibration.first, calibration.n) == (0, vanilla // 2)
    assert (heldout.first, heldout.first + heldout.n) == (vanilla // 2, vanilla)
    assert (perturbed.first, perturbed.n) == (0, 3)
    assert (perturbed.perturbation, perturbed.severity) == ("pose", 5)
    assert (calibration.perturbation, calibration.severity) == ("none", 0)
    assert len({calibration.seed, heldout.seed, perturbed.seed}) == 3


# The commands.


def test_ebvla_is_evaluated_by_ebvla_eval_with_context_features_from_its_initial_state(work):
    checkpoint = fake_checkpoint(work, "ebvla_paper")
    job = pipeline.EvalJob("ebvla_paper", "pose5", 3, 5, 4, 3000, "pose", 5)
    cmd = pipeline.eval_command(work, job, "cpu", episode_length=16)
    assert Path(cmd[0]).name == "ebvla-eval"
    for arg in (
        f"--policy.path={checkpoint}",
        "--env.task_ids=[3]",
        "--env.first_init_state=5",
        "--env.perturbation=pose",
        "--env.perturbation_severity=5",
        "--eval.n_episodes=4",
        "--seed=3000",
        "--env.episode_length=16",
        "--record_context_features=true",
        f"--output_dir={work / 'eval' / 'ebvla_paper' / 'pose5' / 'task3'}",
    ):
        assert arg in cmd
    # Rendered at the recorded size, as the policy saw its data.
    assert {"--env.observation_height=64", "--env.observation_width=64"} <= set(cmd)
    # Only the frames the policy reads, once it names its chunk cadence.
    assert not [arg for arg in cmd if arg.startswith("--env.render_every")]
    write_json(checkpoint / "config.json", {"type": "ebvla", "n_action_steps": 8})
    assert "--env.render_every=8" in pipeline.eval_command(work, job, "cpu")


def test_other_policies_are_evaluated_by_lerobot_eval_without_context_features(work):
    fake_checkpoint(work, "diffusion")
    cmd = pipeline.eval_command(
        work, pipeline.EvalJob("diffusion", "vanilla_heldout", 0, 10, 10, 2000), "cpu"
    )
    assert Path(cmd[0]).name == "lerobot-eval"
    assert "--env.first_init_state=10" in cmd and "--env.perturbation=none" in cmd
    assert not [
        arg
        for arg in cmd
        if arg.startswith(("--record_context_features", "--env.episode_length", "--env.render_every"))
    ]


def test_diffusion_policy_crops_ninety_percent_of_the_frame_and_ebvla_runs_are_unchanged():
    assert pipeline.run_args("diffusion", 128)[-1] == "--policy.crop_shape=[115,115]"
    assert pipeline.run_args("diffusion", 64)[-1] == "--policy.crop_shape=[57,57]"
    assert pipeline.run_args("diffusion", 64)[:-1] == pipeline.RUNS["diffusion"]
    for run in ("ebvla_paper", "ebvla_variant"):
        assert pipeline.run_args(run, 64) == pipeline.RUNS[run]
        assert not [arg for arg in pipeline.RUNS[run] if "crop_shape" in arg]


def test_training_starts_on_the_merged_dataset_then_resumes_from_the_last_checkpoint(work):
    fresh = pipeline.train_command(work, "diffusion", 100, 8, "cpu", 0)
    assert Path(fresh[0]).name == "ebvla-train"
    for arg in (
        f"--dataset.root={work / 'data' / 'all'}",
        f"--output_dir={work / 'train' / 'diffusion'}",
        "--steps=100",
        "--batch_size=8",
        "--policy.device=cpu",
        "--policy.crop_shape=[57,57]",
    ):
        assert arg in fresh
    assert "--resume=true" not in fresh

    checkpoint = fake_checkpoint(work, "diffusion")
    resumed = pipeline.train_command(work, "diffusion", 200, 8, "cpu", 0)
    assert resumed[1:] == [
        f"--config_path={checkpoint / 'train_config.json'}",
        "--resume=true",
        "--steps=200",
    ]


# Success and packing.


def eval_info(*successes: list[bool]) -> dict:
    """lerobot-eval's `eval_info.json`: one `per_task` entry per task id, each with its episodes' successes."""
    return {
        "per_task": [
            {
                "task_group": "libero_object",
                "task_id": i,
                "metrics": {"sum_rewards": [float(s) for s in ok], "successes": ok, "video_paths": []},
            }
            for i, ok in enumerate(successes)
        ],
        "overall": {"n_episodes": sum(len(ok) for ok in successes)},
    }


def test_success_table_counts_successes_per_run_condition_and_task(tmp_path):
    write_json(
        tmp_path / "eval/ebvla_paper/vanilla_calib/task0/eval_info.json", eval_info([True, False, True])
    )
    write_json(tmp_path / "eval/ebvla_paper/vanilla_calib/task3/eval_info.json", eval_info([False, False]))
    write_json(tmp_path / "eval/ebvla_paper/pose5/task0/eval_info.json", eval_info([True], [False, True]))
    write_json(tmp_path / "eval/diffusion/vanilla_heldout/task0/eval_info.json", eval_info([]))
    (tmp_path / "eval/ebvla_paper/fov5/task0").mkdir(parents=True)  # a job cut short: no eval_info.json
    assert pipeline.success_table(tmp_path) == {
        "ebvla_paper": {"vanilla_calib": {"task0": [2, 3], "task3": [0, 2]}, "pose5": {"task0": [2, 3]}},
        "diffusion": {"vanilla_heldout": {"task0": [0, 0]}},
    }


def test_table_iv_chooses_its_alarm_on_some_shifts_and_reports_it_on_the_others(tmp_path, monkeypatch):
    for condition in ("vanilla_calib", "vanilla_heldout", "pose5", "pose3", "rotation5", "light_dim5"):
        write_json(tmp_path / f"eval/ebvla_cpu/{condition}/task2/eval_info.json", eval_info([True, False]))
    commands = []
    monkeypatch.setattr(pipeline.subprocess, "run", lambda command, check: commands.append(command))

    def failure_sides() -> tuple[str, str]:
        failure = next(c for c in commands if c[0].endswith("ebvla-failure-report"))
        calibration = next(a for a in failure if a.startswith("--calibration="))
        return calibration, next(a for a in failure if a.startswith("--records="))

    pipeline.report(tmp_path, ["ebvla_cpu"], failure_calibration_shifts=("pose",))
    calibration, heldout = failure_sides()
    assert all(f"/{c}/task*" in calibration for c in ("vanilla_calib", "pose5", "pose3"))
    assert all(f"/{c}/task*" in heldout for c in ("vanilla_heldout", "rotation5", "light_dim5"))
    assert "pose" not in heldout and "rotation" not in calibration and "vanilla_heldout" not in calibration
    # Table III is unchanged: vanilla calibration, held-out vanilla, every shift.
    ood = next(c for c in commands if c[0].endswith("ebvla-ood-report"))
    assert "vanilla_calib" in ood[1] and "vanilla_heldout" in ood[2] and ood[3].count("task*") == 4

    commands.clear()
    pipeline.report(tmp_path, ["ebvla_cpu"])  # without shifts: vanilla on both sides, as before
    calibration, heldout = failure_sides()
    assert calibration.count("task*") == 1 and heldout.count("task*") == 1


def test_the_chosen_failure_check_reaches_the_monitor_and_fresh_placements_are_held_out(
    tmp_path, monkeypatch
):
    for condition in ("vanilla_calib", "vanilla_heldout", "vanilla_fresh", "vanilla_confirm", "pose5"):
        write_json(tmp_path / f"eval/ebvla_cpu/{condition}/task2/eval_info.json", eval_info([True, False]))
    fake_checkpoint(tmp_path, "ebvla_cpu")
    options = ["--failure_score=final_energy", "--failure_chunks=12", "--failure_reference=successful"]
    choice = write_json(tmp_path / "failure_check_choice.json", {"chunks": 12, "report_options": options})
    commands = []
    monkeypatch.setattr(pipeline.subprocess, "run", lambda command, check: commands.append(command))

    pipeline.report(tmp_path, ["ebvla_cpu"], failure_choice=choice, threshold_rule="conformal")
    ood = next(c for c in commands if c[0].endswith("ebvla-ood-report"))
    assert ood[-5:-2] == options and any(a.startswith("--calibrate_to=") for a in ood)
    # The OOD threshold ships the conformal quantile; the failure check keeps the rule it was chosen at.
    assert ood[-2:] == ["--threshold_rule=conformal", "--failure_threshold_rule=mean_std"]
    vanilla = next(a for a in ood if a.startswith("--vanilla="))
    calibration = next(a for a in ood if a.startswith("--calibration="))
    assert all(f"/{c}/task*" in vanilla for c in ("vanilla_heldout", "vanilla_fresh", "vanilla_confirm"))
    assert "fresh" not in calibration and "confirm" not in calibration
    assert "vanilla" not in next(a for a in ood if a.startswith("--ood="))
    failure = next(c for c in commands if c[0].endswith("ebvla-failure-report"))
    assert "/vanilla_fresh/task*" in next(a for a in failure if a.startswith("--records="))

    commands.clear()
    pipeline.report(tmp_path, ["ebvla_cpu"])  # without a choice: the checkpoint's own failure check
    ood = next(c for c in commands if c[0].endswith("ebvla-ood-report"))
    assert not any(a.startswith(("--failure_score", "--failure_chunks", "--failure_reference")) for a in ood)
    assert "--threshold_rule=mean_std" in ood


def test_a_checkpoint_monitored_by_e_c_is_calibrated_with_libero_s_score(tmp_path, monkeypatch):
    # LIBERO's rule (research/docs/libero_runs.md, "The starting sample's energy beside E_c"): where the checkpoint's
    # config would calibrate `context_phase_energy`, its report calibrates `context_start_energy`.
    from lerobot_policy_ebvla.presets import light_policy_config

    for condition in ("vanilla_calib", "vanilla_heldout", "pose5"):
        write_json(tmp_path / f"eval/ebvla_cpu/{condition}/task2/eval_info.json", eval_info([True, False]))
    light_policy_config().save_pretrained(fake_checkpoint(tmp_path, "ebvla_cpu"))
    commands = []
    monkeypatch.setattr(pipeline.subprocess, "run", lambda command, check: commands.append(command))
    pipeline.report(tmp_path, ["ebvla_cpu"])
    ood = next(c for c in commands if c[0].endswith("ebvla-ood-report"))
    assert "--score=context_start_energy" in ood and any(a.startswith("--calibrate_to=") for a in ood)


def test_pack_keeps_records_logs_and_ebvla_checkpoints_and_leaves_out_data_frames(work):
    kept = [
        "recording_summary.json",
        "data/task0_from0/meta/recording_report.json",
        "eval/ebvla_paper/camera_check.json",
        "eval/ebvla_paper/vanilla_calib/task0/eval_info.json",
        "eval/ebvla_paper/vanilla_calib/task0/energy_records.jsonl",
        "eval/ebvla_paper/vanilla_calib/task0/energy_records.features.npy",
        "logs/record_task0_from0.log",
        "logs/eval/ebvla_paper_vanilla_calib_task0.log",
        "reports/ebvla_paper/failure/failure_report.md",
    ]
    left_out = [
        "data/all/data/chunk-000/file-000.parquet",
        "data/all/meta/info.json",
        "data/task0_from0/data/chunk-000/file-000.parquet",
        # Frames an interrupted recording leaves before LeRobot embeds them in its parquet files.
        "data/task1_from0/images/observation.images.image/episode-000000/frame-000000.png",
        "train/ebvla_paper/checkpoints/000002/pretrained_model/model.safetensors",
    ]
    for name in kept + left_out:
        (work / name).parent.mkdir(parents=True, exist_ok=True)
        (work / name).write_text(name)
    fake_checkpoint(work, "ebvla_paper")
    fake_checkpoint(work, "diffusion")  # Diffusion Policy's checkpoint is too large to bring back

    archive = work / "out" / "results.tar.gz"
    pipeline.pack(work, archive)
    with tarfile.open(archive) as tar:
        names = {member.name for member in tar.getmembers() if member.isfile()}
    checkpoint = {"train/ebvla_paper/pretrained_model/model.safetensors"}
    checkpoint.add("train/ebvla_paper/pretrained_model/train_config.json")
    assert names == set(kept) | checkpoint


def test_with_a_calibration_count_held_out_and_perturbed_rollouts_share_the_states_after_it():
    jobs = {
        job.condition: job
        for job in pipeline.eval_jobs(["ebvla_cpu"], [2], 20, 5, (("pose", 5),), calibration=10)
    }
    assert (jobs["vanilla_calib"].first, jobs["vanilla_calib"].n) == (0, 10)
    assert (jobs["vanilla_heldout"].first, jobs["vanilla_heldout"].n) == (10, 20)
    assert (jobs["pose5"].first, jobs["pose5"].n) == (10, 5)


def test_a_queue_without_vanilla_and_one_without_conditions_split_the_whole_queue_between_two_machines():
    conditions = (("pose", 5), ("noise", 5))
    args = (["ebvla_cpu", "diffusion"], [2, 3], 20, 5)
    whole = pipeline.eval_jobs(*args, conditions, calibration=10, fresh=10)
    elsewhere = pipeline.eval_jobs(*args, conditions, calibration=10, fresh=10, vanilla_conditions=())
    here = pipeline.eval_jobs(*args, (), calibration=10)
    assert not {job.condition for job in elsewhere} & {"vanilla_calib", "vanilla_heldout"}
    assert {job.condition for job in here} == {"vanilla_calib", "vanilla_heldout"}
    # The same jobs, with the same initial states and seeds, whichever machine runs them.
    assert sorted(elsewhere + here, key=lambda job: job.name) == sorted(whole, key=lambda job: job.name)
    assert all(job.first == 10 for job in elsewhere if job.perturbation != "none")
    # A control on the other machine: its calibration rollouts again, first in its queue.
    control = pipeline.eval_jobs(*args, conditions, calibration=10, vanilla_conditions=("vanilla_calib",))
    assert [job.condition for job in control[:2]] == ["vanilla_calib"] * 2
    assert "vanilla_heldout" not in {job.condition for job in control}


def test_the_camera_check_waits_for_a_machine_with_the_dataset(work, capsys):
    fake_checkpoint(work, "ebvla_cpu")
    pipeline.camera_check(work, "ebvla_cpu")
    assert not (work / "eval" / "ebvla_cpu" / "camera_check.json").exists()
    assert "no dataset" in capsys.readouterr().out


def test_fresh_placement_rollouts_come_last_from_seeds_no_recording_or_initial_state_uses(work):
    jobs = pipeline.eval_jobs(
        ["ebvla_cpu", "diffusion"], [2, 3], 20, 5, (("pose", 5),), calibration=10, fresh=10
    )
    fresh = [job for job in jobs if job.condition == pipeline.FRESH_CONDITION]
    assert jobs[-2:] == fresh and [(j.run, j.task, j.n) for j in fresh] == [
        ("ebvla_cpu", 2, 10),
        ("ebvla_cpu", 3, 10),
    ]
    assert not [
        job
        for job in pipeline.eval_jobs(["ebvla_cpu"], [2], 20, 5, calibration=10)
        if job.condition == pipeline.FRESH_CONDITION
    ]
    fake_checkpoint(work, "ebvla_cpu")
    cmd = pipeline.eval_command(work, fresh[0], "cpu")
    # LeRobot's eval resets episode i with seed --seed + i; LIBERO samples the placements from it.
    assert "--env.init_states=false" in cmd and f"--seed={pipeline.FRESH_PLACEMENT_SEED}" in cmd
    assert pipeline.FRESH_PLACEMENT_SEED >= 100000 + 1000  # beyond any recording's seeds (100000 + attempt)
    held_out = pipeline.eval_command(work, jobs[1], "cpu")
    assert "--env.init_states=false" not in held_out


def test_fresh_arm_rollouts_repeat_the_fresh_placements_with_the_fixed_states_arm_noise(work):
    jobs = pipeline.eval_jobs(["ebvla_cpu"], [2, 3], 20, 5, (), calibration=10, fresh=10, fresh_arm=4)
    fresh = [job for job in jobs if job.condition == pipeline.FRESH_CONDITION]
    arm = [job for job in jobs if job.condition == pipeline.FRESH_ARM_CONDITION]
    assert jobs[-2:] == arm and [(j.task, j.first, j.n) for j in arm] == [(2, 0, 4), (3, 0, 4)]
    assert {j.seed for j in arm} == {j.seed for j in fresh} == {pipeline.FRESH_PLACEMENT_SEED}
    fake_checkpoint(work, "ebvla_cpu")
    cmd = pipeline.eval_command(work, arm[0], "cpu")
    assert "--env.init_states=false" in cmd and "--env.robot_init_noise=0.02" in cmd
    assert not any("robot_init_noise" in arg for arg in pipeline.eval_command(work, fresh[0], "cpu"))


def test_confirmation_rollouts_come_last_from_the_fixed_states_after_the_held_out_ones():
    jobs = pipeline.eval_jobs(
        ["ebvla_cpu", "diffusion"], [2, 3], 20, 5, (("pose", 5),), calibration=10, confirm=20
    )
    confirm = [job for job in jobs if job.condition == pipeline.CONFIRM_CONDITION]
    assert jobs[-2:] == confirm
    assert [(j.run, j.task, j.first, j.n) for j in confirm] == [
        ("ebvla_cpu", 2, 30, 20),
        ("ebvla_cpu", 3, 30, 20),
    ]
    assert len({job.seed for job in jobs if job.condition.startswith("vanilla")}) == 3
    with pytest.raises(ValueError, match="give `calibration`"):
        pipeline.eval_jobs(["ebvla_cpu"], [2], 20, 5, confirm=20)


def test_cpu_runs_resize_their_cameras_and_diffusion_crops_by_ratio():
    assert "--policy.resnet.resize_shape=[96,96]" in pipeline.run_args("ebvla_cpu", 128)
    assert "--policy.resize_shape=[96,96]" in pipeline.run_args("diffusion_cpu", 128)
    assert pipeline.run_args("diffusion_cpu", 128) == pipeline.RUNS["diffusion_cpu"]
    # The paper's MCMC: ebvla_cpu leaves Table V's K_train 8-15 and K_inf 15 at their defaults.
    assert not [arg for arg in pipeline.RUNS["ebvla_cpu"] if "mcmc_steps" in arg]


def test_training_cut_at_its_deadline_is_not_marked_done(work, monkeypatch):
    monkeypatch.setattr(pipeline, "train_command", lambda *args: ["sleep", "60"])
    pipeline.train(work, ["ebvla_cpu"], 100, 8, "cpu", 0, detach=False, until_s=1.0)
    assert not (work / "train" / "ebvla_cpu" / "DONE").exists()
    # A training that finishes (lerobot-train makes its output folder) is.
    output_dir = work / "train" / "ebvla_cpu"
    monkeypatch.setattr(pipeline, "train_command", lambda *args: ["mkdir", "-p", str(output_dir)])
    pipeline.train(work, ["ebvla_cpu"], 100, 8, "cpu", 0, detach=False, until_s=30.0)
    assert (output_dir / "DONE").exists()


def test_detached_training_stops_at_its_deadline(work, monkeypatch):
    # The slices of a long training are detached: nothing but the training's own script is left to stop it.
    monkeypatch.setattr(pipeline, "train_command", lambda *args: ["sleep", "60"])
    (process,) = pipeline.train(work, ["ebvla_cpu"], 100, 8, "cpu", 0, detach=True, until_s=1.0)
    assert process.wait(timeout=30) == 124
    assert not (work / "train" / "ebvla_cpu" / "DONE").exists()


def saved_run(work: Path, step: int) -> Path:
    """A work folder with a checkpoint at `step` (LeRobot's layout) and one finished evaluation job."""
    from lerobot_policy_ebvla.monitoring.records import EnergyRecord, write_energy_records

    checkpoints = work / "train" / "ebvla_cpu" / "checkpoints"
    model = checkpoints / f"{step:06d}" / "pretrained_model"
    write_json(
        model / "train_config.json",
        {"output_dir": "/elsewhere", "dataset": {"root": "/elsewhere/data"}, "steps": step},
    )
    (model / "model.safetensors").write_bytes(b"weights")
    write_json(checkpoints / f"{step:06d}" / "training_state" / "training_step.json", {"step": step})
    (checkpoints / "last").symlink_to(f"{step:06d}")
    job = work / "eval" / "ebvla_cpu" / "vanilla_heldout" / "task2"
    write_json(job / "eval_info.json", {"per_task": []})
    records = [
        EnergyRecord(
            episode_index=0,
            chunk_index=i,
            env_step=8 * i,
            initial_energy=1.0,
            final_energy=0.5,
            success=True,
            task="pick up the salad dressing and place it in the basket",
            seed=2000,
        )
        for i in range(3)
    ]
    write_energy_records(job / "energy_records.jsonl", records)
    return work


def test_saved_results_restore_a_resumable_training_and_skip_finished_jobs(tmp_path):
    from lerobot_policy_ebvla.monitoring.records import read_energy_records

    first = saved_run(tmp_path / "first", 1500)
    write_json(first / "recording_summary.json", {"image_size": 128, "episodes_per_task": 44, "tasks": {}})
    write_json(first / "data" / "task2_from0" / "meta" / "recording_report.json", {"n_kept": 22})
    fake_checkpoint(first, "diffusion_cpu")
    (first / "train" / "diffusion_cpu" / "DONE").write_text("")
    results = tmp_path / "results"
    pipeline.save_results(first, results)
    assert json.loads((results / "recording_reports" / "task2_from0.json").read_text()) == {"n_kept": 22}
    # Diffusion Policy's checkpoint is too large to commit; that it finished is kept.
    assert (results / "train/diffusion_cpu/DONE").exists()
    assert not (results / "train/diffusion_cpu/last").exists()
    # Records go in compressed; the frames and the full checkpoint tree do not.
    assert (results / "eval/ebvla_cpu/vanilla_heldout/task2/energy_records.jsonl.gz").exists()
    assert not (results / "eval/ebvla_cpu/vanilla_heldout/task2/energy_records.jsonl").exists()
    assert (results / "train/ebvla_cpu/last/pretrained_model/model.safetensors").exists()
    assert (results / "train/ebvla_cpu/last/training_state/training_step.json").exists()  # to resume from
    # Once the run is done, nothing resumes it: its optimizer state is not committed.
    (first / "train" / "ebvla_cpu" / "DONE").write_text("")
    finished = tmp_path / "finished"
    pipeline.save_results(first, finished)
    assert (finished / "train/ebvla_cpu/last/pretrained_model/model.safetensors").exists()
    assert not (finished / "train/ebvla_cpu/last/training_state").exists()
    pipeline.restore_results(finished, tmp_path / "evaluate_only")
    assert (tmp_path / "evaluate_only/train/ebvla_cpu/checkpoints/last").resolve().name == "001500"
    (first / "train" / "ebvla_cpu" / "DONE").unlink()

    # Restored into the folder that saved them, the compressed records do not join the uncompressed ones (a
    # folder with both is refused), and saving again works.
    pipeline.restore_results(results, first)
    assert not (first / "eval/ebvla_cpu/vanilla_heldout/task2/energy_records.jsonl.gz").exists()
    pipeline.save_results(first, results)

    second = tmp_path / "second"
    pipeline.restore_results(results, second)
    config = second / "train/ebvla_cpu/checkpoints/last/pretrained_model/train_config.json"
    assert json.loads(config.read_text())["output_dir"] == str(second / "train" / "ebvla_cpu")
    assert json.loads(config.read_text())["dataset"]["root"] == str(second / "data" / "all")
    assert (second / "train/ebvla_cpu/checkpoints/last").resolve().name == "001500"
    assert pipeline.train_command(second, "ebvla_cpu", 3000, 16, "cpu", 0)[1:] == [
        f"--config_path={config}",
        "--resume=true",
        "--steps=3000",
    ]
    # The frames are not restored, so neither is what would mark their piece recorded.
    assert not (second / "data").exists()
    job = second / "eval/ebvla_cpu/vanilla_heldout/task2"
    assert (job / "eval_info.json").exists()
    assert [r.chunk_index for r in read_energy_records(job / "energy_records.jsonl.gz")] == [0, 1, 2]
    statuses = pipeline.evaluate(
        second, [pipeline.EvalJob("ebvla_cpu", "vanilla_heldout", 2, 10, 20, 2000)], "cpu", 1, 60
    )
    assert statuses == {"ebvla_cpu/vanilla_heldout/task2": "done before"}


def test_pieces_recorded_as_video_are_saved_whole_and_restored_as_recorded(tmp_path, monkeypatch):
    first = tmp_path / "first"
    # No kept episode, so that `record` below stops before aggregating the stand-in pieces.
    write_json(first / "data" / "task0_from0" / "meta" / "recording_report.json", {"n_kept": 0})
    video = (
        first / "data" / "task0_from0" / "videos" / "observation.images.image" / "chunk-000" / "file-000.mp4"
    )
    video.parent.mkdir(parents=True)
    video.write_bytes(b"frames")
    write_json(first / "data" / "task1_from0" / "meta" / "recording_report.json", {"n_kept": 11})  # images
    results = tmp_path / "results"
    pipeline.save_results(first, results)
    assert (results / "data" / "task0_from0" / video.relative_to(first / "data" / "task0_from0")).exists()
    assert not (results / "data" / "task1_from0").exists()

    second = tmp_path / "second"
    pipeline.restore_results(results, second)
    assert (second / video.relative_to(first)).read_bytes() == b"frames"
    # Restored with its report, the piece counts as recorded: `record` runs only the other one.
    commands = []
    monkeypatch.setattr(pipeline, "run_logged", lambda cmd, log: commands.append(cmd) or 0)
    with pytest.raises(RuntimeError, match="No task recorded"):
        pipeline.record(second, [0, 1], 11, 128, jobs=1, use_videos=True)
    assert [c for c in commands if "--env.task_ids=[0]" in c] == []
    assert len([c for c in commands if "--env.task_ids=[1]" in c]) == 1


def test_record_asks_every_piece_for_video_frames_when_told(tmp_path, monkeypatch):
    """`--use_videos` reaches each recorder process (a dataset that travels in a GPU bundle, research/docs/libero_runs.md)."""
    commands = []
    monkeypatch.setattr(pipeline, "run_logged", lambda cmd, log: commands.append(cmd) or 0)
    with pytest.raises(RuntimeError, match="No task recorded"):
        pipeline.record(tmp_path, [0, 1], 2, 128, jobs=1, use_videos=True)
    assert len(commands) == 2 and all("--use_videos=true" in cmd for cmd in commands)
    commands.clear()
    with pytest.raises(RuntimeError, match="No task recorded"):
        pipeline.record(tmp_path, [0], 2, 128, jobs=1)
    assert "--use_videos=false" in commands[0]


# Every stage, at a tiny size.


def first_frame_features(checkpoint: Path, dataset_root: Path) -> np.ndarray:
    """(episodes, D) the checkpoint's context features of each dataset episode's first frame."""
    from lerobot.datasets import LeRobotDataset
    from lerobot.policies.factory import make_pre_post_processors
    from torch.utils.data import default_collate

    from lerobot_policy_ebvla import EBVLAPolicy

    policy = EBVLAPolicy.from_pretrained(checkpoint)
    preprocessor, _ = make_pre_post_processors(policy.config, pretrained_path=str(checkpoint))
    dataset = LeRobotDataset(pipeline.REPO_ID, root=dataset_root)
    keys = [*policy.config.input_features, "task"]
    starts = dataset.meta.episodes["dataset_from_index"]
    frames = [{key: dataset[int(i)][key] for key in keys} for i in starts]
    return policy.context_features(preprocessor(default_collate(frames))).numpy()


@requires_libero
@pytest.mark.slow
def test_pipeline_records_trains_evaluates_and_packs_a_tiny_libero_object_run(tmp_path, monkeypatch):
    from lerobot.datasets import LeRobotDataset

    from lerobot_policy_ebvla.monitoring.records import read_energy_records

    monkeypatch.setenv("MUJOCO_GL", "egl")
    work = tmp_path / "work"
    stages = {
        "record": "--tasks 0 --episodes_per_task=2 --parts=2 --image_size=64 --max_steps=12 --keep_failed --jobs=2",
        "train": "--runs ebvla_paper --steps=2 --batch_size=4 --workers=0 --device=cpu",
        "eval": "--runs ebvla_paper --tasks 0 --vanilla=2 --perturbed=1 --conditions pose:5 --episode_length=16 "
        "--jobs=2 --device=cpu --deadline_s=400",
        "pack": "",
    }
    for stage, args in stages.items():
        pipeline.main([stage, f"--work={work}", *args.split()])

    # Two pieces, from initial states 0 and 1, merged into one dataset of 64 px frames.
    reports = [
        json.loads((work / "data" / f"task0_from{first}" / "meta" / "recording_report.json").read_text())
        for first in (0, 1)
    ]
    assert [r["env"]["first_init_state"] for r in reports] == [0, 1]
    assert [ep["initial_state"] for r in reports for ep in r["episodes"]] == [0, 1]
    dataset = LeRobotDataset(pipeline.REPO_ID, root=work / "data" / "all")
    assert dataset.meta.total_episodes == 2
    assert dataset[0]["observation.images.image"].shape == dataset[0]["observation.images.image2"].shape
    assert dataset[0]["observation.images.image"].shape == (3, 64, 64)

    assert json.loads((work / "eval_status.json").read_text()) == {
        f"ebvla_paper/{condition}/task0": "done"
        for condition in ("vanilla_calib", "vanilla_heldout", "pose5")
    }
    records = {
        condition: read_energy_records(work / "eval" / "ebvla_paper" / condition / "task0")
        for condition in ("vanilla_calib", "vanilla_heldout", "pose5")
    }
    for condition, chunks in records.items():
        assert {r.episode_index for r in chunks} == {0}  # one episode each
        assert all(math.isfinite(r.initial_energy) and math.isfinite(r.final_energy) for r in chunks)
        assert all(r.context_feature is not None for r in chunks)
        info = json.loads(
            (work / "eval" / "ebvla_paper" / condition / "task0" / "eval_info.json").read_text()
        )
        assert info["overall"]["n_episodes"] == 1
    assert {(r.perturbation, r.severity) for r in records["pose5"]} == {("pose", 5.0)}
    assert len({chunks[0].seed for chunks in records.values()}) == 3
    # No record names its initial state: the first observation of each job is the recorded first frame of
    # the state it starts from (same simulator state, same 64 px rendering), so its context is nearest that.
    checkpoint = work / "train" / "ebvla_paper" / "checkpoints" / "last" / "pretrained_model"
    recorded = first_frame_features(checkpoint, work / "data" / "all")
    for condition, state in (("vanilla_calib", 0), ("vanilla_heldout", 1)):
        distances = np.linalg.norm(recorded - records[condition][0].context_feature, axis=1)
        assert distances.argmin() == state, (condition, distances)

    assert (work / "eval" / "ebvla_paper" / "camera_check.json").exists()
    with tarfile.open(work / "libero_results.tar.gz") as tar:
        names = set(tar.getnames())
    for condition in records:
        assert f"eval/ebvla_paper/{condition}/task0/energy_records.jsonl" in names
    assert "train/ebvla_paper/pretrained_model/model.safetensors" in names
    assert not [name for name in names if name.endswith(".parquet")]


def test_aggregating_restored_pieces_keeps_the_recordings_own_time(tmp_path, monkeypatch):
    """A session that restores the recorded pieces aggregates them again: the summary keeps the recording's time,
    which `save` would otherwise overwrite in the committed results."""
    import lerobot.datasets.aggregate

    work = tmp_path / "work"
    report = {
        "n_kept": 1,
        "n_attempted": 2,
        "success_rate_per_task": {"pick up the salad dressing": 0.5},
        "episodes": [{"n_steps": 120, "kept": True}, {"n_steps": 300, "kept": False}],
    }
    write_json(work / "data" / "task2_from0" / "meta" / "recording_report.json", report)
    write_json(work / "recording_summary.json", {"image_size": 128, "seconds": 8431.7})
    monkeypatch.setattr(pipeline, "run_logged", lambda cmd, log: pytest.fail(f"recorded again: {cmd}"))
    monkeypatch.setattr(lerobot.datasets.aggregate, "aggregate_datasets", lambda **kwargs: None)
    pipeline.record(work, [2], 1, 128, jobs=1)
    summary = json.loads((work / "recording_summary.json").read_text())
    assert summary["seconds"] == 8431.7 and summary["tasks"]["2"]["kept"] == 1


def test_more_episodes_add_pieces_of_the_same_size_to_their_tasks_only():
    assert pipeline.record_pieces([0, 1, 5], 44, 4, {1: 44, 5: 20}) == [
        *[(0, first, 11) for first in (0, 11, 22, 33)],
        *[(1, first, 11) for first in (0, 11, 22, 33, 44, 55, 66, 77)],
        *[(5, first, 11) for first in (0, 11, 22, 33, 44)],
        (5, 55, 9),
    ]


def piece_recording_report(n: int, task: str = "pick up the cream cheese") -> dict:
    """A recorder's report of a piece whose n attempts all succeeded."""
    return {
        "n_kept": n,
        "n_attempted": n,
        "success_rate_per_task": {task: 1.0},
        "episodes": [{"n_steps": 150, "kept": True}] * n,
    }


def fake_recorder(commands: list) -> Callable:
    """Stands in for `run_logged` when recording: keeps each piece's command and writes the report the recorder
    would, at the piece's `--root`, with its `--episodes_per_task` attempts kept."""

    def record_piece(cmd, log):
        commands.append(cmd)
        root = next(arg.split("=")[1] for arg in cmd if arg.startswith("--root="))
        n = int(next(arg.split("=")[1] for arg in cmd if arg.startswith("--episodes_per_task=")))
        write_json(Path(root) / "meta" / "recording_report.json", piece_recording_report(n))
        return 0

    return record_piece


def test_pieces_a_results_folder_holds_are_linked_and_only_the_extra_ones_are_recorded(tmp_path, monkeypatch):
    """A fine-tune's dataset: the saved video pieces of the first run, linked (never copied into the new results),
    and the extra demonstrations recorded from the placement seeds after them."""
    import lerobot.datasets.aggregate

    saved = tmp_path / "results"
    for first in (0, 11):
        write_json(
            saved / "data" / f"task1_from{first}" / "meta" / "recording_report.json",
            piece_recording_report(11),
        )
        video = saved / "data" / f"task1_from{first}" / "videos" / "observation.images.image" / "file-000.mp4"
        video.parent.mkdir(parents=True)
        video.write_bytes(b"frames")
    work, commands, aggregated = tmp_path / "work", [], []
    monkeypatch.setattr(pipeline, "run_logged", fake_recorder(commands))
    monkeypatch.setattr(
        lerobot.datasets.aggregate, "aggregate_datasets", lambda **kwargs: aggregated.append(kwargs["roots"])
    )
    more = {"more_episodes": {1: 11}, "pieces_from": [tmp_path / "other_results", saved]}
    pipeline.record(work, [1], 22, 128, jobs=1, parts=2, placement_seed=100000, use_videos=True, **more)
    # Attempt i of the extra piece starts from the placements of seed 100000 + 22 + i: none of the saved pieces'.
    assert len(commands) == 1 and "--env.first_init_state=22" in commands[0]
    assert "--placement_seed=100000" in commands[0]
    assert [root.name for root in aggregated[0]] == ["task1_from0", "task1_from11", "task1_from22"]
    assert (work / "data" / "task1_from0").resolve() == (saved / "data" / "task1_from0").resolve()
    summary = json.loads((work / "recording_summary.json").read_text())
    assert summary["more_episodes"] == {"1": 11} and summary["tasks"]["1"]["kept"] == 33

    results = tmp_path / "fine_tune_results"
    pipeline.save_results(work, results)
    assert sorted(p.name for p in (results / "recording_reports").iterdir()) == ["task1_from22.json"]
    assert not (results / "data" / "task1_from0").exists()


def test_arm_pieces_start_the_arm_as_the_fixed_states_do_on_placements_of_their_own(tmp_path, monkeypatch):
    import lerobot.datasets.aggregate

    work, commands, aggregated = tmp_path / "work", [], []
    monkeypatch.setattr(pipeline, "run_logged", fake_recorder(commands))
    monkeypatch.setattr(
        lerobot.datasets.aggregate, "aggregate_datasets", lambda **kwargs: aggregated.append(kwargs["roots"])
    )
    pipeline.record(work, [7], 3, 128, jobs=1, placement_seed=100000, arm_episodes=3)
    plain, arm = commands
    assert "--placement_seed=100000" in plain and not any("robot_init_noise" in arg for arg in plain)
    assert f"--placement_seed={pipeline.ARM_PLACEMENT_SEED}" in arm and "--env.robot_init_noise=0.02" in arm
    assert [root.name for root in aggregated[0]] == ["task7_from0", "task7_arm_from0"]
    summary = json.loads((work / "recording_summary.json").read_text())
    assert summary["tasks"]["7"]["kept"] == 6 and summary["tasks"]["7"]["arm_kept"] == 3


def test_more_arm_pieces_continue_their_tasks_placements_in_pieces_of_the_arm_size(tmp_path, monkeypatch):
    import lerobot.datasets.aggregate

    work, commands = tmp_path / "work", []
    monkeypatch.setattr(pipeline, "run_logged", fake_recorder(commands))
    monkeypatch.setattr(lerobot.datasets.aggregate, "aggregate_datasets", lambda **kwargs: None)
    pipeline.record(
        work, [1, 2], 2, 128, jobs=1, placement_seed=100000, arm_episodes=2, more_arm_episodes={1: 4}
    )
    arm = [cmd for cmd in commands if any("robot_init_noise" in arg for arg in cmd)]
    roots = [Path(next(arg.split("=")[1] for arg in cmd if arg.startswith("--root="))).name for cmd in arm]
    assert roots == ["task1_arm_from0", "task1_arm_from2", "task1_arm_from4", "task2_arm_from0"]
    # attempt i of a piece starts from placement seed ARM_PLACEMENT_SEED + first + i: no two pieces share one
    assert [next(a for a in cmd if a.startswith("--env.first_init_state=")) for cmd in arm[:3]] == [
        "--env.first_init_state=0",
        "--env.first_init_state=2",
        "--env.first_init_state=4",
    ]
    summary = json.loads((work / "recording_summary.json").read_text())
    assert summary["more_arm_episodes"] == {"1": 4}
    assert summary["tasks"]["1"]["arm_kept"] == 6 and summary["tasks"]["2"]["arm_kept"] == 2

    with pytest.raises(ValueError, match="arm_episodes"):
        pipeline.record(tmp_path / "other", [1], 2, 128, jobs=1, more_arm_episodes={1: 4})


def test_recovery_pieces_miss_their_first_grasp_with_the_arm_started_as_the_fixed_states(
    tmp_path, monkeypatch
):
    import lerobot.datasets.aggregate

    work, commands, aggregated = tmp_path / "work", [], []
    monkeypatch.setattr(pipeline, "run_logged", fake_recorder(commands))
    monkeypatch.setattr(
        lerobot.datasets.aggregate, "aggregate_datasets", lambda **kwargs: aggregated.append(kwargs["roots"])
    )
    pipeline.record(work, [1, 2], 2, 128, jobs=1, placement_seed=100000, recovery_episodes={1: 3})
    recover = [cmd for cmd in commands if "--regrasp=true" in cmd]
    assert len(recover) == 1 and "--episodes_per_task=3" in recover[0]
    assert f"--placement_seed={pipeline.RECOVERY_PLACEMENT_SEED}" in recover[0]
    assert (
        "--env.robot_init_noise=0.02" in recover[0]
        and f"--miss_first_grasp={pipeline.RECOVERY_MISS}" in recover[0]
    )
    assert not any("--regrasp=true" in cmd for cmd in commands if cmd is not recover[0])
    assert [root.name for root in aggregated[0]] == ["task1_from0", "task2_from0", "task1_recover_from0"]
    summary = json.loads((work / "recording_summary.json").read_text())
    assert summary["recovery_episodes"] == {"1": 3} and summary["tasks"]["1"]["recover_kept"] == 3
    assert "recover_kept" not in summary["tasks"]["2"]
    assert "--store_missed_grasp=true" in recover[0] and not summary["recovery_from_rise"]


def test_recovery_pieces_from_the_rise_are_stored_without_their_miss(tmp_path, monkeypatch):
    """J's pieces: the same attempts as I's, recorded with `--store_missed_grasp=false` under a name of their own."""
    import lerobot.datasets.aggregate

    work, commands, aggregated = tmp_path / "work", [], []
    monkeypatch.setattr(pipeline, "run_logged", fake_recorder(commands))
    monkeypatch.setattr(
        lerobot.datasets.aggregate, "aggregate_datasets", lambda **kwargs: aggregated.append(kwargs["roots"])
    )
    pipeline.record(work, [5], 2, 128, jobs=1, recovery_episodes={5: 2}, recovery_from_rise=True)
    recover = [cmd for cmd in commands if "--regrasp=true" in cmd]
    assert len(recover) == 1 and "--store_missed_grasp=false" in recover[0]
    assert f"--placement_seed={pipeline.RECOVERY_PLACEMENT_SEED}" in recover[0]
    assert [root.name for root in aggregated[0]] == ["task5_from0", "task5_recoverrise_from0"]
    summary = json.loads((work / "recording_summary.json").read_text())
    assert summary["recovery_from_rise"] and summary["tasks"]["5"]["recoverrise_kept"] == 2


def test_task_counts_read_task_equals_n_and_name_a_malformed_item():
    assert pipeline.task_counts(["1=20", "5=20"]) == {1: 20, 5: 20}
    with pytest.raises(ValueError, match="'1:20'"):
        pipeline.task_counts(["1:20"])


def test_a_fine_tune_starts_from_its_saved_weights_with_its_own_rate_then_resumes_itself(work):
    run = "ebvla_joint_fast_cpu_more"
    fine_tune = pipeline.FINE_TUNES[run]
    start = pipeline.REPOSITORY / fine_tune.start
    assert (start / "model.safetensors").exists() and (start / "config.json").exists()
    command = pipeline.train_command(work, run, 5000, 16, "cpu", 1)
    assert command[1:3] == [f"--policy.path={start}", "--policy.optimizer_lr=1e-4"]
    assert f"--dataset.root={work / 'data' / 'all'}" in command and "--steps=5000" in command
    assert not any(arg.startswith("--policy.type") for arg in command)  # the saved config's, not new flags

    checkpoint = fake_checkpoint(work, run)
    assert pipeline.train_command(work, run, 5000, 16, "cpu", 1)[1:] == [
        f"--config_path={checkpoint / 'train_config.json'}",
        "--resume=true",
        "--steps=5000",
    ]


@pytest.mark.parametrize("run", sorted(pipeline.FINE_TUNES))
def test_every_fine_tune_starts_from_committed_weights_trained_with_cs_flags(run):
    """Each fine-tune's start is a committed checkpoint, and it trains with C's flags (its ancestors' own)."""
    start = pipeline.REPOSITORY / pipeline.FINE_TUNES[run].start
    assert (start / "model.safetensors").exists() and (start / "config.json").exists()
    assert pipeline.RUNS[run] == pipeline.RUNS["ebvla_joint_fast_cpu"]


def test_first_moves_the_named_conditions_jobs_to_the_front_in_that_order():
    args = (["ebvla_cpu"], [2, 3], 20, 5, ())
    whole = pipeline.eval_jobs(*args, calibration=10, fresh=10, confirm=20, fresh_arm=10)
    ordered = pipeline.eval_jobs(
        *args, calibration=10, fresh=10, confirm=20, fresh_arm=10, first=("vanilla_confirm", "vanilla_fresh")
    )
    assert sorted(ordered, key=lambda job: job.name) == sorted(whole, key=lambda job: job.name)
    assert [job.condition for job in ordered[:4]] == ["vanilla_confirm"] * 2 + ["vanilla_fresh"] * 2
    rest = [job for job in whole if job.condition not in ("vanilla_confirm", "vanilla_fresh")]
    assert ordered[4:] == rest


def test_first_can_name_one_runs_condition_and_only_first_drops_the_rest():
    jobs = pipeline.eval_jobs(
        ["ebvla_a", "ebvla_b"],
        [2, 3],
        20,
        5,
        (),
        calibration=10,
        confirm=20,
        first=("ebvla_a/vanilla_confirm", "ebvla_b/vanilla_calib"),
        only_first=True,
    )
    assert [job.name for job in jobs] == [
        "ebvla_a/vanilla_confirm/task2",
        "ebvla_a/vanilla_confirm/task3",
        "ebvla_b/vanilla_calib/task2",
        "ebvla_b/vanilla_calib/task3",
    ]


def test_an_inference_variant_evaluates_its_base_runs_checkpoint_with_its_flags_and_is_never_trained(work):
    variant = "ebvla_joint_fast_cpu_more_best8"
    base = pipeline.INFERENCE_VARIANTS[variant].base
    assert pipeline.last_checkpoint(work, variant) is None
    checkpoint = fake_checkpoint(work, base)
    assert pipeline.last_checkpoint(work, variant) == checkpoint
    job = pipeline.EvalJob(variant, "vanilla_confirm", 1, 30, 20, 4000)
    cmd = pipeline.eval_command(work, job, "cpu")
    assert f"--policy.path={checkpoint}" in cmd and "--policy.num_restarts=8" in cmd
    # Its records sit apart from the base run's.
    assert f"--output_dir={work / 'eval' / variant / 'vanilla_confirm' / 'task1'}" in cmd
    base_cmd = pipeline.eval_command(work, pipeline.EvalJob(base, "vanilla_confirm", 1, 30, 20, 4000), "cpu")
    assert "--policy.num_restarts=8" not in base_cmd
    with pytest.raises(ValueError, match="evaluate another run's checkpoint and are not trained"):
        pipeline.train(work, [variant], 10, 2, "cpu", 0, detach=True)


def test_a_variant_executing_fewer_actions_per_chunk_renders_every_frame_its_policy_reads(work):
    """The env renders only the frames the policy reads; a variant that re-plans every 4 steps of the checkpoint's
    8 must have every 4th frame drawn, or `ebvla-eval` would refine chunks from frames never rendered."""
    variant = "ebvla_joint_fast_cpu_arm_more_act4"
    base = pipeline.INFERENCE_VARIANTS[variant].base
    checkpoint = fake_checkpoint(work, base)
    write_json(checkpoint / "config.json", {"type": "ebvla", "n_action_steps": 8})
    cmd = pipeline.eval_command(work, pipeline.EvalJob(variant, "vanilla_confirm", 1, 30, 20, 4000), "cpu")
    assert "--policy.n_action_steps=4" in cmd and "--env.render_every=4" in cmd
    assert "--env.render_every=8" not in cmd
    base_cmd = pipeline.eval_command(work, pipeline.EvalJob(base, "vanilla_confirm", 1, 30, 20, 4000), "cpu")
    assert "--env.render_every=8" in base_cmd and not any("n_action_steps" in arg for arg in base_cmd)
