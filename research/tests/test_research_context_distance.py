"""The context distance: the Mahalanobis distance of a chunk's pooled context from the vanilla contexts.

d(c) = sqrt((c - mu_c)^T P (c - mu_c)), mu_c and P (the inverse Ledoit-Wolf covariance) fitted on the pooled
contexts of vanilla chunks (`ContextStatistics`); stored beside `ood_calibration.json` so that the run-time
response and monitor can apply it. `ebvla-ood-report --score=context_distance` fits and saves it
(tests/test_monitoring_reports.py).
"""

import json

import numpy as np
import pytest
import torch

from lerobot_policy_ebvla import EBVLAPolicy
from lerobot_policy_ebvla.runtime import EnergyOODError
from lerobot_policy_ebvla.runtime.calibration import OOD_CALIBRATION_FILENAME, OODCalibration
from lerobot_policy_ebvla.runtime.monitor import EnergyOODMonitor
from lerobot_policy_ebvla.runtime.readout import EnergyReadout
from lerobot_policy_ebvla.runtime.statistics import ContextStatistics, ledoit_wolf_covariance
from research.tests.conftest import load_benchmark
from tests.conftest import tiny_batch, tiny_config

research_scores = load_benchmark("research_scores")
CONTEXT_FILE = research_scores.CONTEXT_FILE
ContextDistance = research_scores.ContextDistance

D = 4


def vanilla_features(n: int = 40, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(n, D))


def context_calibration(**kwargs) -> OODCalibration:
    statistics = ContextStatistics.fit(vanilla_features())
    return OODCalibration.fit([1.0, 2.0], score=ContextDistance(statistics), **kwargs)


# The statistics.


def test_context_distance_is_the_mahalanobis_distance_under_the_shrunk_covariance():
    features = vanilla_features()
    statistics = ContextStatistics.fit(features)
    query = np.array([[1.0, -2.0, 0.5, 3.0]])
    centered = query[0] - features.mean(axis=0)
    precision = np.linalg.inv(ledoit_wolf_covariance(features - features.mean(axis=0)))
    assert statistics.distance(query)[0] == pytest.approx(np.sqrt(centered @ precision @ centered))


def test_context_distance_of_the_vanilla_mean_is_zero():
    features = vanilla_features()
    assert ContextStatistics.fit(features).distance(features.mean(axis=0))[0] == pytest.approx(0.0, abs=1e-9)


def test_context_statistics_fit_where_features_outnumber_chunks():
    statistics = ContextStatistics.fit(np.random.default_rng(1).normal(size=(5, 32)))
    assert np.all(np.isfinite(statistics.distance(np.ones(32))))


def test_context_statistics_need_two_finite_chunks():
    with pytest.raises(ValueError, match="N >= 2"):
        ContextStatistics.fit(np.ones((1, D)))
    with pytest.raises(ValueError, match="non-finite"):
        ContextStatistics.fit(np.array([[0.0, 1.0], [np.nan, 2.0]]))


def test_context_features_of_another_size_are_refused():
    with pytest.raises(ValueError, match=f"must be \\(N, {D}\\)"):
        ContextStatistics.fit(vanilla_features()).distance(np.ones((2, D + 1)))


# The calibration that ships with a checkpoint.


def test_a_context_calibration_scores_a_chunk_by_its_context_distance():
    calibration = context_calibration()
    features = np.array([[0.0, 0.0, 0.0, 0.0], [5.0, 5.0, 5.0, 5.0]])
    np.testing.assert_allclose(
        calibration.chunk_score(
            EnergyReadout.of_arrays(torch.tensor([9.0, 9.0]), 0, torch.from_numpy(features))
        ),
        calibration.score.context.distance(features),
    )


def test_a_context_calibration_needs_the_context_features():
    with pytest.raises(ValueError, match="context_features"):
        context_calibration().chunk_score(EnergyReadout.of_arrays(1.0, 0))


def test_a_context_calibration_needs_one_context_per_chunk():
    with pytest.raises(ValueError, match="`context_features` has 2 row.*one per chunk"):
        context_calibration().chunk_score(EnergyReadout.of_arrays(torch.zeros(3), 0, np.zeros((2, D))))


def test_a_context_calibration_needs_its_statistics():
    with pytest.raises(ValueError, match="needs `context`"):
        ContextDistance(None)


def test_a_context_calibration_round_trips_through_json_and_safetensors(tmp_path):
    calibration = context_calibration(k=0.5)
    calibration.save(tmp_path)
    entry = json.loads((tmp_path / OOD_CALIBRATION_FILENAME).read_text())[CONTEXT_FILE.field]
    assert entry["file"] == CONTEXT_FILE.filename and entry["dim"] == D and entry["n_chunks"] == 40
    loaded = OODCalibration.load(tmp_path)
    assert loaded == calibration and loaded.score.name == "context_distance"
    np.testing.assert_array_equal(loaded.score.context.mean, calibration.score.context.mean)
    np.testing.assert_array_equal(loaded.score.context.precision, calibration.score.context.precision)


def test_context_statistics_of_another_calibration_are_refused(tmp_path):
    context_calibration().save(tmp_path)
    other = ContextStatistics.fit(vanilla_features(seed=1))
    (tmp_path / CONTEXT_FILE.filename).write_bytes(other.to_bytes())
    with pytest.raises(ValueError, match="does not match `context_statistics.sha256`"):
        OODCalibration.load(tmp_path)


# The run-time monitor.


def test_the_monitor_scores_each_environments_chunk_by_its_context_distance():
    monitor = EnergyOODMonitor(context_calibration())
    features = np.array([[0.0, 0.0, 0.0, 0.0], [5.0, 5.0, 5.0, 5.0]])
    decisions = monitor.update(
        EnergyReadout(None, torch.tensor([9.0, 9.0]), context_features=torch.from_numpy(features))
    )
    expected = monitor.calibration.score.context.distance(features)
    assert [d.energy for d in decisions] == pytest.approx(expected.tolist())


def test_the_monitor_checks_a_rollout_by_its_chunks_context_distances():
    monitor = EnergyOODMonitor(context_calibration(aggregation="max"))
    features = vanilla_features(n=3, seed=2)
    decision = monitor.check_rollout(EnergyReadout.of_arrays([0.0, 0.0, 0.0], context_features=features))
    assert decision.energy == pytest.approx(monitor.calibration.score.context.distance(features).max())


def test_the_monitor_checks_one_chunk_with_one_context_feature():
    monitor = EnergyOODMonitor(context_calibration())
    (decision,) = monitor.check(EnergyReadout.of_arrays(0.0, 0, np.full(D, 10.0)))
    assert decision.energy == pytest.approx(monitor.calibration.score.context.distance(np.full(D, 10.0))[0])


# The policy's response.


def test_the_policy_scores_each_chunk_by_the_context_distance_of_its_observation(tmp_path):
    torch.manual_seed(0)
    policy = EBVLAPolicy(tiny_config()).eval()
    contexts = [tiny_batch(policy.config, batch_size=4, seed=s, with_action=False) for s in range(3)]
    statistics = ContextStatistics.fit(torch.cat([policy.context_features(b) for b in contexts]))
    # A threshold below every distance: every chunk is flagged and raises with its highest distance.
    OODCalibration(mu_v=-1.0, sigma_v=0.0, score=ContextDistance(statistics)).save(tmp_path)
    policy.configure_ood_response(tmp_path, response="raise")
    batch = tiny_batch(policy.config, batch_size=2, seed=7, with_action=False)
    with pytest.raises(EnergyOODError, match="context_distance") as raised:
        policy.predict_action_chunk(batch)
    expected = statistics.distance(policy.context_features(batch)).max()
    assert raised.value.energy == pytest.approx(expected, rel=1e-5)
