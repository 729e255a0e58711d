"""The checkpoint's energy monitor: the OOD threshold and the failure check, both set on vanilla rollouts, on one
readout; calibrated and reported by `ebvla-ood-report`, applied at run time by `EnergyMonitor`."""

import json

import numpy as np
import pytest

from lerobot_policy_ebvla import EnergyMonitor, EnergyReadout, FailureCalibration, OODCalibration
from lerobot_policy_ebvla.monitoring.baselines import chunk_context_nn, episode_readout
from lerobot_policy_ebvla.monitoring.records import (
    ENERGY_RECORDS_FILENAME,
    EnergyRecord,
    load_episodes,
    write_energy_records,
)
from lerobot_policy_ebvla.runtime.calibration import FAILURE_CALIBRATION_FILENAME, OOD_CALIBRATION_FILENAME
from lerobot_policy_ebvla.runtime.scores import VanillaRollouts
from lerobot_policy_ebvla.scripts import ood_report

from .conftest import tiny_config

N_CHUNKS = 6


def joint_rollouts(
    n, seed, perturbation="none", severity=0.0, context_shift=0.0, fail_every=4, features=False
):
    """Rollouts of a joint-energy policy: E_c around 1 (+ `context_shift`), the head's part E - E_c around a level
    that falls with the chunk index; every `fail_every`-th rollout fails, its head energy 1.5 above vanilla's in
    its first chunks."""
    rng = np.random.default_rng(seed)
    records = []
    for episode in range(n):
        failed = (episode + 1) % fail_every == 0
        for chunk in range(N_CHUNKS):
            context = 1.0 + context_shift + rng.normal(0, 0.1)
            head = 3.0 - 0.2 * chunk + (1.5 if failed else 0.0) + rng.normal(0, 0.1)
            records.append(
                EnergyRecord(
                    episode_index=episode,
                    chunk_index=chunk,
                    env_step=8 * chunk,
                    initial_energy=head + context + 2.0,
                    final_energy=head + context,
                    success=not failed,
                    task="reach",
                    seed=1000 * seed + episode,
                    perturbation=perturbation,
                    severity=severity,
                    context_energy=context,
                    context_feature=(
                        rng.normal(context_shift + (1.0 if failed else 0.0), 0.3, size=4).astype(np.float32)
                        if features
                        else None
                    ),
                )
            )
    return records


def write(folder, records):
    return write_energy_records(folder / ENERGY_RECORDS_FILENAME, records).parent


@pytest.fixture(scope="module")
def record_dirs(tmp_path_factory):
    root = tmp_path_factory.mktemp("joint_records")
    return (
        write(root / "calibration", joint_rollouts(16, seed=10, fail_every=100, features=True)),
        write(root / "vanilla", joint_rollouts(16, seed=11, features=True)),
        write(
            root / "camera",
            joint_rollouts(
                12,
                seed=1,
                perturbation="camera",
                severity=1.0,
                context_shift=1.0,
                fail_every=2,
                features=True,
            ),
        ),
    )


@pytest.fixture
def checkpoint(tmp_path):
    """A pretrained_model folder of a policy trained with E_c on its own encoder."""
    folder = tmp_path / "pretrained_model"
    tiny_config(joint_energy={"target": "observation", "weight": 0.01}).save_pretrained(folder)
    return folder


def report(record_dirs, out, *extra):
    calibration, vanilla, camera = record_dirs
    ood_report.main(
        [
            f"--calibration=[{calibration}]",
            f"--vanilla=[{vanilla}]",
            f"--ood=[{camera}]",
            f"--output_dir={out}",
            "--n_bootstrap=50",
            *extra,
        ]
    )
    return (out / "ood_report.md").read_text()


def test_the_report_calibrates_both_checks_and_the_run_time_monitor_repeats_its_decisions(
    record_dirs, checkpoint, tmp_path
):
    text = report(record_dirs, tmp_path / "out", f"--calibrate_to={checkpoint}")
    monitor = EnergyMonitor.from_pretrained(checkpoint)
    assert monitor.ood.score.name == "context_phase_energy"
    assert monitor.failure.score.name == "head_energy_two_sided" and monitor.failure.chunks == 3
    assert monitor.failure.n_rollouts == 16  # the calibration rollouts, vanilla only
    section = text.split("## The monitor's failure check")[1].split("\n## ")[0]
    together = section.split("### held-out vanilla and perturbed rollouts together: ")[1]
    assert together.startswith("10 of 28 failed")  # 4 of 16 vanilla, 6 of 12 shifted
    rows = {line.split("|")[1].strip(): line for line in together.splitlines() if line.startswith("| ")}
    for baseline in ("head_energy_two_sided", "context_phase_energy", "context_knn", "chunk_context_nn"):
        assert baseline in rows
    # The head's energy 1.5 above vanilla's in the first chunks: every failure caught, a few false alarms at k = 1.
    assert "| 10/10 (100.0%) |" in rows["head_energy_two_sided"]
    assert rows["head_energy_two_sided"].endswith("| 1.000 [1.000, 1.000] |")

    # Run time: the monitor decides each held-out rollout as the report's rows count it.
    failing, alarmed = {True: 0, False: 0}, {True: 0, False: 0}
    for folder in record_dirs[1:]:
        for episode in load_episodes([folder]).values():
            monitor.reset()
            readout = episode_readout(episode)
            for chunk in range(3):
                (decision,) = monitor.update(readout.row(chunk))
                assert (decision.failing is None) == (chunk < 2)
            failed = not episode[0].success
            failing[failed] += decision.failing
            alarmed[failed] += decision.alarm
    assert f"| 10/10 (100.0%) | {failing[False]}/18 " in rows["head_energy_two_sided"]
    assert f"| {alarmed[True]}/10 " in rows["monitor (either check)"]
    assert f"| {alarmed[False]}/18 " in rows["monitor (either check)"]
    assert alarmed[False] >= 6 > failing[False]  # the shifted successful rollouts: unfamiliar, not failing


def test_the_failure_decision_is_kept_for_the_episode_and_forgotten_on_reset():
    vanilla = VanillaRollouts(
        [
            EnergyReadout.of_arrays(
                3.0 + 0.1 * np.sin(np.arange(4) + r), np.arange(4), context_energy=np.ones(4)
            )
            for r in range(10)
        ]
    )
    monitor = EnergyMonitor(
        OODCalibration.calibrate("context_phase_energy", vanilla),
        FailureCalibration.calibrate("head_energy_two_sided", vanilla, chunks=2),
    )
    energies = [9.0, 9.0, 3.0, 3.0]  # a head energy far above vanilla's in the first two chunks, then normal
    decisions = [
        monitor.update(EnergyReadout.of_arrays([e], t, context_energy=[1.0]))[0]
        for t, e in enumerate(energies)
    ]
    assert [d.failing for d in decisions] == [None, True, True, True]
    assert decisions[1].failure_score > decisions[1].failure_threshold and decisions[3].chunks == 4
    assert all(d.alarm for d in decisions[1:]) and not decisions[0].unfamiliar.is_ood
    monitor.reset()
    (decision,) = monitor.update(EnergyReadout.of_arrays([3.0], 0, context_energy=[1.0]))
    assert decision.failing is None and not decision.alarm


def test_a_checkpoint_without_a_failure_check_is_monitored_for_novelty_alone(tmp_path):
    OODCalibration.fit([1.0, 2.0, 3.0]).save(tmp_path)
    monitor = EnergyMonitor.from_pretrained(tmp_path)
    (decision,) = monitor.update(EnergyReadout.of_arrays([10.0], 0))
    assert monitor.failure is None and decision.failing is None and decision.failure_threshold is None
    assert decision.unfamiliar.is_ood and decision.alarm


def test_a_broken_failure_calibration_is_an_error_not_a_missing_check(tmp_path):
    OODCalibration.fit([1.0, 2.0, 3.0]).save(tmp_path)
    (tmp_path / FAILURE_CALIBRATION_FILENAME).write_text(json.dumps({"mu_v": 1.0}))
    with pytest.raises(ValueError, match="is not a valid failure calibration"):
        EnergyMonitor.from_pretrained(tmp_path)


def test_the_failure_check_stores_no_features_and_leaves_the_ood_calibrations_side_file(tmp_path):
    features = np.random.default_rng(0).normal(size=(12, 4))
    vanilla = VanillaRollouts(
        [
            EnergyReadout.of_arrays(np.ones(3), np.arange(3), context_features=features[3 * r : 3 * r + 3])
            for r in range(4)
        ]
    )
    OODCalibration.calibrate("context_knn", vanilla).save(tmp_path)
    with pytest.raises(ValueError, match="stores no features; `context_knn` is a feature baseline"):
        FailureCalibration.calibrate("context_knn", vanilla)
    saved = FailureCalibration.calibrate("final_energy", vanilla, chunks=2)
    saved.save(tmp_path)
    assert FailureCalibration.load(tmp_path) == saved and saved.chunks == 2
    assert OODCalibration.load(tmp_path).score.name == "context_knn"  # its neighbours file is still there


def test_the_report_refuses_to_overwrite_a_failure_check_and_can_leave_it_out(
    record_dirs, checkpoint, tmp_path
):
    (checkpoint / FAILURE_CALIBRATION_FILENAME).write_text("kept")
    with pytest.raises(FileExistsError, match=FAILURE_CALIBRATION_FILENAME):
        report(record_dirs, tmp_path / "out", f"--calibrate_to={checkpoint}")
    assert (checkpoint / FAILURE_CALIBRATION_FILENAME).read_text() == "kept"
    assert not (checkpoint / OOD_CALIBRATION_FILENAME).exists()
    (checkpoint / FAILURE_CALIBRATION_FILENAME).unlink()
    text = report(record_dirs, tmp_path / "out", f"--calibrate_to={checkpoint}", "--failure_score=none")
    assert "failure check" not in text and not (checkpoint / FAILURE_CALIBRATION_FILENAME).exists()


def test_a_failure_check_fitted_on_the_successful_calibration_rollouts_leaves_the_failed_ones_out(
    record_dirs, checkpoint, tmp_path
):
    # A calibration with 4 failed rollouts of 16, their final energies 1.5 above the others' from the first chunk.
    calibration = write(tmp_path / "calibration", joint_rollouts(16, seed=10, fail_every=4, features=True))
    dirs = (calibration, *record_dirs[1:])
    check = ("--failure_score=final_energy", "--failure_chunks=3", f"--calibrate_to={checkpoint}")
    text = report(dirs, tmp_path / "out", *check, "--failure_reference=successful")
    successful = [e for e in load_episodes([calibration]).values() if e[0].success]
    first_means = [np.mean([r.final_energy for r in episode[:3]]) for episode in successful]
    saved = FailureCalibration.load(checkpoint)
    assert saved.n_rollouts == 12 and saved.chunks == 3
    assert saved.threshold == pytest.approx(np.mean(first_means) + np.std(first_means), rel=1e-5)
    assert OODCalibration.load(checkpoint).n_rollouts == 16  # the OOD check still calibrates on every rollout
    assert "first 3 chunks of the calibration rollouts that succeeded" in text

    # Fitted on every calibration rollout, the failed ones raise mu_v and sigma_v: a higher threshold.
    report(dirs, tmp_path / "vanilla", *check, "--overwrite_calibration=true")
    assert FailureCalibration.load(checkpoint).threshold > saved.threshold + 0.5
    with pytest.raises(ValueError, match="`failure_reference` must be one of"):
        report(dirs, tmp_path / "bad", "--failure_reference=failed")


def test_the_failure_check_keeps_eq_5_while_the_ood_threshold_is_conformal(record_dirs, checkpoint, tmp_path):
    calibration = write(tmp_path / "calibration", joint_rollouts(24, seed=10, features=True))
    dirs = (calibration, *record_dirs[1:])
    rules = ("--threshold_rule=conformal", "--failure_threshold_rule=mean_std", "--false_alarm_rate=0.1")
    text = report(
        dirs, tmp_path / "out", "--failure_score=final_energy", f"--calibrate_to={checkpoint}", *rules
    )
    ood, failure = OODCalibration.load(checkpoint), FailureCalibration.load(checkpoint)
    assert ood.rule == "conformal" and ood.threshold == ood.conformal_threshold
    assert failure.rule == "mean_std" and failure.threshold == pytest.approx(failure.mu_v + failure.sigma_v)
    assert "(the conformal quantile at alpha = 10.0%)" in text
    with pytest.raises(ValueError, match="`failure_threshold_rule` must be one of"):
        report(dirs, tmp_path / "bad", "--failure_threshold_rule=quantile")


def test_the_chunk_context_baseline_measures_to_the_nearest_successful_calibration_rollout():
    def episode(seed, feature_at_chunk_1, success=True):
        return [
            EnergyRecord(
                0, chunk, 8 * chunk, 1.0, 1.0, success, "t", seed, context_feature=np.array(f, np.float32)
            )
            for chunk, f in enumerate([[0.0, 0.0], feature_at_chunk_1])
        ]

    calibration = {
        "a": episode(1, [0.0, 0.0]),
        "b": episode(2, [2.0, 0.0]),
        "c": episode(3, [0.0, 2.0]),
        "failed": episode(4, [50.0, 50.0], success=False),  # never a reference
    }
    # Standardized by the successful contexts at chunk 1: mean (2/3, 2/3), std 0.943 per dimension.
    held_out = {"x": episode(5, [2.0, 0.0]), "short": episode(6, [0.0, 0.0])[:1]}
    distances = chunk_context_nn(calibration, {**calibration, **held_out}, chunk=1)
    std = np.std([0.0, 2.0, 0.0])
    assert distances[4] == pytest.approx(0.0, abs=1e-6)  # "x" sits on "b"
    assert distances[0] == pytest.approx(2.0 / std)  # "a" does not find itself: "b" or "c" at 2 / std
    assert distances[5] == pytest.approx(
        0.0, abs=1e-6
    )  # "short" ends before chunk 1: its last chunk, against "a"
    with pytest.raises(ValueError, match="at least 2 successful calibration rollouts"):
        chunk_context_nn({"a": calibration["a"], "failed": calibration["failed"]}, held_out, chunk=1)


def test_the_failure_check_gives_each_caught_failures_lead_to_its_onset():
    from types import SimpleNamespace

    from lerobot_policy_ebvla.monitoring.failure_check import format_failure_check

    labels = np.array([True, True, True, False, False])
    flags = np.array([True, True, False, True, False])  # two failures caught, one success alarmed
    onsets = np.array([5.0, 3.0, 4.0, np.nan, np.nan])  # 1-based steps of the failures' last progress
    cfg = SimpleNamespace(n_bootstrap=20, seed=0, failure_reference="vanilla")
    rows = {"head_energy_two_sided": {"all": (np.arange(5.0), flags)}}
    text = format_failure_check(rows, {"all": labels}, 3, "head_energy_two_sided", cfg, onsets)
    # Decided at chunk 3: leads 5 - 3 = +2 and 3 - 3 = 0, both at or before the onset.
    assert "| 2/3 (66.7%) | 1/2 (50.0%) |" in text and text.split("\n")[-3].endswith("| 2/2, median +1 |")
    # Records without goal distances: no such column.
    assert "onset" not in format_failure_check(rows, {"all": labels}, 3, "head_energy_two_sided", cfg)


def test_the_libero_score_flags_a_start_energy_below_vanillas_and_needs_the_initial_energy(tmp_path):
    # `context_start_energy`: E_c at vanilla's level but the head's energy of the Gaussian start far below it.
    rng = np.random.default_rng(0)
    vanilla = VanillaRollouts(
        [
            EnergyReadout.of_arrays(
                3.0 + rng.normal(0, 0.1, 4),
                np.arange(4),
                context_energy=1.0 + rng.normal(0, 0.1, 4),
                initial_energy=20.0 + rng.normal(0, 0.5, 4),
            )
            for _ in range(10)
        ]
    )
    calibration = OODCalibration.calibrate("context_start_energy", vanilla)
    calibration.save(tmp_path)
    monitor = EnergyMonitor(OODCalibration.load(tmp_path))
    assert monitor.ood.score.name == "context_start_energy"
    # At vanilla's chunk-0 levels of both terms, then with the start's energy 8 lower (16 of its sigmas).
    context, start = monitor.ood.score.context.mean[0], monitor.ood.score.start.mean[0]
    (typical,) = monitor.update(
        EnergyReadout.of_arrays([3.0], 0, context_energy=[context], initial_energy=[context + start])
    )
    monitor.reset()
    (low_start,) = monitor.update(
        EnergyReadout.of_arrays([3.0], 0, context_energy=[context], initial_energy=[context + start - 8.0])
    )
    assert not typical.unfamiliar.is_ood and low_start.unfamiliar.is_ood
    monitor.reset()
    with pytest.raises(ValueError, match=r"needs each chunk's E\(a\^\(0\), C\)"):
        monitor.update(EnergyReadout.of_arrays([3.0], 0, context_energy=[1.0]))
