"""The success energy E_s(C, t): the module and its fit, the cross-fitting that reads calibration rollouts, the
`success_energy` failure check saved beside `failure_calibration.json`, the policy's readout for it, and
`ebvla-ood-report --calibrate_to` fitting it."""

import json

import numpy as np
import pytest
import torch

from lerobot_policy_ebvla import EBVLAPolicy, EnergyMonitor, EnergyReadout, FailureCalibration
from lerobot_policy_ebvla.monitoring.metrics import auroc
from lerobot_policy_ebvla.monitoring.records import (
    ENERGY_RECORDS_FILENAME,
    EnergyRecord,
    write_energy_records,
)
from lerobot_policy_ebvla.runtime.calibration import FAILURE_CALIBRATION_FILENAME
from lerobot_policy_ebvla.runtime.chunk_scores import LATE_CHUNKS, rollout_score
from lerobot_policy_ebvla.runtime.scores import SuccessEnergyScore, VanillaRollouts
from lerobot_policy_ebvla.runtime.success_energy import (
    FOLDS,
    SuccessEnergy,
    fit_success_energy,
    fold_order,
    fold_readers,
)
from lerobot_policy_ebvla.scripts import ood_report

from .conftest import tiny_batch, tiny_config

N_CHUNKS, DIM = 8, 6


def contexts(rng, stall_at=None):
    """(T, D) pooled contexts whose first dimension tracks the task's progress; a failing rollout stalls at chunk
    `stall_at` (its context stays where it was, as a missed grasp's does)."""
    progress = np.arange(N_CHUNKS, dtype=float)
    if stall_at is not None:
        progress = np.minimum(progress, stall_at)
    features = rng.normal(scale=0.3, size=(N_CHUNKS, DIM))
    features[:, 0] += progress
    features[:, 1] += 0.5 * progress
    return features.astype(np.float32), np.arange(N_CHUNKS)


def rollouts(n, seed, stall_at=None):
    rng = np.random.default_rng(seed)
    return [contexts(rng, stall_at) for _ in range(n)]


def late(model, rollout):
    return rollout_score(model.series(*rollout), "late")


def test_e_s_learns_what_success_looks_like_at_each_chunk_and_is_deterministic():
    torch.set_num_threads(1)
    model = fit_success_energy(rollouts(30, seed=0))
    successful = [late(model, r) for r in rollouts(20, seed=1)]
    stalled = [late(model, r) for r in rollouts(20, seed=2, stall_at=2)]
    assert auroc(successful, stalled) > 0.95
    # The anchor holds success near 0.
    assert abs(np.median(successful)) < 1.0 < np.median(stalled)

    again = fit_success_energy(rollouts(30, seed=0))
    assert all(
        torch.equal(a, b)
        for a, b in zip(model.state_dict().values(), again.state_dict().values(), strict=True)
    )


def test_a_saved_e_s_reads_as_it_was_fitted_and_a_wrong_file_is_named():
    model = fit_success_energy(rollouts(6, seed=0), epochs=1)
    loaded = SuccessEnergy.from_bytes(model.to_bytes())
    rollout = rollouts(1, seed=3)[0]
    assert np.array_equal(loaded.series(*rollout), model.series(*rollout))
    assert loaded.series(rollout[0], np.full(N_CHUNKS, 99)).shape == (
        N_CHUNKS,
    )  # late chunks share the last bin
    from safetensors.torch import save

    with pytest.raises(ValueError, match="success energy"):
        SuccessEnergy.from_bytes(save({"weight": torch.zeros(2)}))


def test_cross_fitting_reads_each_rollout_with_an_e_s_that_never_saw_it(monkeypatch):
    import lerobot_policy_ebvla.runtime.success_energy as module

    class Fit:
        def __init__(self, fitted_on, seed=0, epochs=module.EPOCHS):
            self.ids, self.seed = {id(features) for features, _ in fitted_on}, seed

    monkeypatch.setattr(module, "fit_success_energy", Fit)
    data = rollouts(12, seed=0)
    readers = fold_readers(data, seed=0)
    models = {id(r): r for r in readers}.values()
    assert sorted(m.seed for m in models) == [1, 2, 3, 4, 5]
    for (features, _), reader in zip(data, readers, strict=True):
        assert id(features) not in reader.ids
    # Each fold's E_s saw every rollout but its fold.
    assert sorted(len(m.ids) for m in models) == sorted(12 - len(f) for f in fold_order(12))
    with pytest.raises(ValueError, match=f"at least {FOLDS} successful rollouts"):
        fold_readers(data[:3])


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda r: [(r[0][0][:, :3], r[0][1]), *r[1:]], "one D"),
        (lambda r: [(r[0][0], r[0][1][:3]), *r[1:]], "`chunk_index` must be"),
        (lambda r: [(np.full_like(r[0][0], np.nan), r[0][1]), *r[1:]], "non-finite"),
    ],
)
def test_the_fit_names_what_is_wrong_with_its_inputs(change, message):
    with pytest.raises(ValueError, match=message):
        fit_success_energy(change(rollouts(6, seed=0)), epochs=1)


def test_the_noisy_copies_std_is_the_fits_to_choose_and_must_be_positive():
    data = rollouts(6, seed=0)
    wide, narrow = (
        fit_success_energy(data, epochs=1, noise=1.0),
        fit_success_energy(data, epochs=1, noise=0.5),
    )
    assert not torch.equal(wide.net[-1].weight, narrow.net[-1].weight)
    for noise in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="`noise`.*must be > 0"):
            fit_success_energy(data, epochs=1, noise=noise)


def readout(rollout):
    features, index = rollout
    return EnergyReadout.of_arrays(np.zeros(len(index)), index, features)


def vanilla(n_successful=25, n_failed=5, seed=0, **kwargs):
    data = [*rollouts(n_successful, seed), *rollouts(n_failed, seed + 100, stall_at=2)]
    return VanillaRollouts(
        [readout(r) for r in data], succeeded=[True] * n_successful + [False] * n_failed, **kwargs
    )


@pytest.fixture(scope="module")
def failure_check():
    torch.set_num_threads(1)
    return FailureCalibration.calibrate("success_energy", vanilla(), chunks=N_CHUNKS)


def test_the_failure_check_of_e_s_is_read_late_and_saved_beside_its_json(failure_check, tmp_path):
    assert failure_check.aggregation == "late" and failure_check.n_rollouts == 30
    stalled = [
        failure_check.score_rollout(failure_check.chunk_components(readout(r))) for r in rollouts(5, 7, 2)
    ]
    successful = [
        failure_check.score_rollout(failure_check.chunk_components(readout(r))) for r in rollouts(5, 8)
    ]
    assert min(stalled) > failure_check.threshold > np.median(successful)

    failure_check.save(tmp_path)
    payload = json.loads((tmp_path / FAILURE_CALIBRATION_FILENAME).read_text())
    assert (
        payload["score"] == "success_energy"
        and payload["success_energy"]["file"] == "success_energy.safetensors"
    )
    loaded = FailureCalibration.from_pretrained(tmp_path)
    rollout = readout(rollouts(1, seed=9)[0])
    assert np.array_equal(loaded.chunk_components(rollout), failure_check.chunk_components(rollout))
    # Another aggregation than the one E_s was chosen with is refused.
    import dataclasses

    with pytest.raises(ValueError, match="'late' aggregation"):
        dataclasses.replace(failure_check, aggregation="mean")


def test_the_failure_check_names_what_e_s_needs():
    with pytest.raises(ValueError, match="`succeeded`"):
        SuccessEnergyScore.fit(VanillaRollouts([readout(r) for r in rollouts(6, 0)]))
    without_features = VanillaRollouts(
        [EnergyReadout.of_arrays(np.zeros(N_CHUNKS), np.arange(N_CHUNKS)) for _ in range(6)],
        succeeded=[True] * 6,
    )
    with pytest.raises(ValueError, match="pooled context"):
        SuccessEnergyScore.fit(without_features)
    # E_s keeps a model beside the calibration; the feature baselines stay out of the failure check.
    assert not SuccessEnergyScore.feature_baseline


def test_the_policy_passes_the_pooled_context_when_its_failure_check_reads_it():
    torch.manual_seed(0)
    own = {"weight": 0.1, "target": "observation"}
    reads = EBVLAPolicy(tiny_config(joint_energy=own, monitor={"failure_score": "success_energy"})).eval()
    energies_only = EBVLAPolicy(tiny_config(joint_energy=own)).eval()
    batch = tiny_batch(reads.config, batch_size=2)
    reads.select_action(dict(batch))
    energies_only.select_action(dict(batch))
    assert reads.last_energy.context_features.shape[0] == 2
    assert energies_only.last_energy.context_features is None


def write_rollouts(folder, data, success, first_seed, perturbation="none"):
    records = [
        EnergyRecord(
            episode_index=episode,
            chunk_index=int(t),
            env_step=8 * int(t),
            initial_energy=2.0,
            final_energy=1.0 + 0.1 * (episode % 3),
            success=ok,
            task="reach",
            seed=first_seed + episode,
            perturbation=perturbation,
            severity=1.0 if perturbation != "none" else 0.0,
            context_feature=features[i],
        )
        for episode, ((features, index), ok) in enumerate(zip(data, success, strict=True))
        for i, t in enumerate(index)
    ]
    return write_energy_records(folder / ENERGY_RECORDS_FILENAME, records).parent


def test_ood_report_fits_e_s_at_calibrate_to_and_the_monitor_applies_it(tmp_path):
    torch.set_num_threads(1)
    checkpoint = tmp_path / "checkpoint"
    config = tiny_config(monitor={"failure_score": "success_energy", "failure_chunks": N_CHUNKS})
    config.save_pretrained(checkpoint)
    calibration = write_rollouts(
        tmp_path / "calibration", [*rollouts(24, 0), *rollouts(2, 50, 2)], [True] * 24 + [False] * 2, 0
    )
    held = write_rollouts(
        tmp_path / "vanilla", [*rollouts(8, 1), *rollouts(4, 51, 2)], [True] * 8 + [False] * 4, 100
    )
    shifted = write_rollouts(tmp_path / "shift", rollouts(6, 2, 3), [False] * 6, 200, perturbation="camera")
    ood_report.main(
        [
            f"--calibration=[{calibration}]",
            f"--vanilla=[{held}]",
            f"--ood=[{shifted}]",
            "--n_bootstrap=50",
            f"--output_dir={tmp_path / 'report'}",
            f"--calibrate_to={checkpoint}",
            "--failure_reference=successful",
        ]
    )
    saved = json.loads((checkpoint / FAILURE_CALIBRATION_FILENAME).read_text())
    assert (
        saved["score"] == "success_energy" and saved["aggregation"] == "late" and saved["chunks"] == N_CHUNKS
    )
    assert saved["n_rollouts"] == 24  # T from the successful calibration rollouts
    assert (checkpoint / "success_energy.safetensors").is_file()

    monitor = EnergyMonitor.from_pretrained(checkpoint)
    decided = []
    for rollout in [*rollouts(3, 5), *rollouts(3, 6, 2)]:
        monitor.reset()
        for t in range(N_CHUNKS):
            features, index = rollout
            decision = monitor.update(
                EnergyReadout.of_arrays(np.ones(1), index[t : t + 1], features[t : t + 1])
            )[0]
        decided.append(decision.failing)
    assert decided == [False] * 3 + [True] * 3
    assert LATE_CHUNKS == 4


def test_ood_report_refuses_e_s_for_a_checkpoint_whose_policy_would_not_pass_the_pooled_context(tmp_path):
    checkpoint = tmp_path / "checkpoint"
    tiny_config().save_pretrained(checkpoint)  # its failure check: "none"
    calibration = write_rollouts(tmp_path / "calibration", rollouts(6, 0), [True] * 6, 0)
    held = write_rollouts(tmp_path / "vanilla", rollouts(3, 1), [True] * 3, 100)
    shifted = write_rollouts(tmp_path / "shift", rollouts(3, 2, 3), [False] * 3, 200, perturbation="camera")
    options = [f"--calibration=[{calibration}]", f"--vanilla=[{held}]", f"--ood=[{shifted}]"]
    with pytest.raises(ValueError, match="monitor.failure_score='success_energy'"):
        ood_report.main(
            [
                *options,
                f"--output_dir={tmp_path / 'report'}",
                f"--calibrate_to={checkpoint}",
                "--failure_score=success_energy",
            ]
        )
    assert not (checkpoint / FAILURE_CALIBRATION_FILENAME).exists()


def test_a_fit_on_few_successful_rollouts_warns(caplog):
    with caplog.at_level("WARNING"):
        SuccessEnergyScore.fit(vanilla(6, 0, seed=3))
    assert "fitted on 6 successful calibration rollouts" in caplog.text
