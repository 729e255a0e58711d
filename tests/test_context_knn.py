"""The context k-NN distance: the distance of a chunk's standardized pooled context to its k-th nearest vanilla one.

d_k(c) = ||z(c) - z(c_(k))||, z(c) = (c - mean) / std over the vanilla contexts (`ContextNeighbours`), the report's
`knn` baseline for a held-out chunk; stored beside `ood_calibration.json` so that the run-time response and monitor
can apply it. `ebvla-ood-report --score=context_knn` fits and saves it.
"""

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from lerobot_policy_ebvla import EBVLAPolicy
from lerobot_policy_ebvla.monitoring.baselines import ContextFeatureModel, fit_score_reference
from lerobot_policy_ebvla.monitoring.records import (
    load_episodes,
)
from lerobot_policy_ebvla.monitoring.scores import episode_chunk_scores, episode_scores
from lerobot_policy_ebvla.runtime import EnergyOODError
from lerobot_policy_ebvla.runtime.calibration import OOD_CALIBRATION_FILENAME, OODCalibration
from lerobot_policy_ebvla.runtime.monitor import EnergyOODMonitor
from lerobot_policy_ebvla.runtime.readout import EnergyReadout
from lerobot_policy_ebvla.runtime.scores import NEIGHBOURS_FILE, SCORES, ContextKNN
from lerobot_policy_ebvla.runtime.statistics import ChunkWindow, ContextNeighbours
from lerobot_policy_ebvla.scripts import ood_report

from .conftest import context_rollouts, tiny_batch, tiny_config, write_records

D = 4
K = 3


def vanilla_features(n: int = 40, seed: int = 0) -> np.ndarray:
    # float32, as the recorder stores them: the report's float64 features and the saved float32 ones then agree.
    return np.random.default_rng(seed).normal(size=(n, D)).astype(np.float32)


def knn_calibration(**kwargs) -> OODCalibration:
    neighbours = ContextNeighbours.fit(vanilla_features(), k=K)
    return OODCalibration.fit([1.0, 2.0], score=ContextKNN(neighbours), **kwargs)


# The neighbours.


def test_context_knn_distance_is_the_standardized_distance_to_the_kth_nearest_vanilla_context():
    features = vanilla_features().astype(np.float64)
    queries = np.random.default_rng(1).normal(size=(6, D)) * 2.0
    mean, std = features.mean(axis=0), features.std(axis=0)
    pairwise = np.linalg.norm(((queries - mean) / std)[:, None] - ((features - mean) / std)[None], axis=2)
    expected = np.sort(pairwise, axis=1)[:, K - 1]
    np.testing.assert_allclose(ContextNeighbours.fit(features, k=K).distance(queries), expected, rtol=1e-10)


def test_context_knn_distance_of_a_held_out_chunk_is_the_reports_knn_score():
    features = vanilla_features()
    episode_ids = [i // 5 for i in range(len(features))]
    queries = np.random.default_rng(2).normal(size=(7, D)).astype(np.float32) + 0.5
    report_knn = ContextFeatureModel.fit(features.astype(np.float64), episode_ids, k=K).context_knn(queries)
    run_time = ContextNeighbours.fit(features, k=K).distance(torch.from_numpy(queries))
    np.testing.assert_allclose(run_time, report_knn, rtol=1e-12)


def test_the_report_fits_the_neighbours_a_calibration_saves():
    features = vanilla_features()
    model = ContextFeatureModel.fit(features.astype(np.float64), [i // 5 for i in range(len(features))], k=K)
    fitted = ContextNeighbours.fit(features, k=K)
    np.testing.assert_array_equal(model.neighbours.features, fitted.features)
    np.testing.assert_array_equal(model.neighbours.mean, fitted.mean)
    np.testing.assert_array_equal(model.neighbours.std, fitted.std)
    assert model.neighbours.k == K


def test_context_neighbours_keep_the_features_in_float32():
    neighbours = ContextNeighbours.fit(vanilla_features().astype(np.float64), k=K)
    assert neighbours.features.dtype == np.float32 and neighbours.features.shape == (40, D)
    assert (neighbours.n_chunks, neighbours.dim) == (40, D)


def test_context_neighbours_with_fewer_features_than_k_use_the_farthest():
    neighbours = ContextNeighbours.fit(np.array([[0.0, 0.0], [2.0, 0.0]]), k=5)
    # Standardized: (-1, 0) and (1, 0); from (1, 0) the farthest is 2 away.
    assert neighbours.distance(np.array([2.0, 0.0]))[0] == pytest.approx(2.0)


def test_context_features_of_another_size_are_refused():
    with pytest.raises(ValueError, match=f"must be \\(N, {D}\\).*--score=context_knn"):
        ContextNeighbours.fit(vanilla_features(), k=K).distance(np.ones((2, D + 1)))


@pytest.mark.parametrize(
    ("features", "k", "match"),
    [
        (np.ones((1, D)), K, "N >= 2"),
        (np.array([[0.0, np.nan], [1.0, 2.0]]), K, "non-finite"),
        (None, 0, "`k`"),
    ],
)
def test_invalid_context_neighbours_are_refused(features, k, match):
    with pytest.raises(ValueError, match=match):
        ContextNeighbours.fit(vanilla_features() if features is None else features, k=k)


# The calibration that ships with a checkpoint.


def test_context_knn_is_a_calibrated_context_score():
    assert "context_features" in SCORES["context_knn"].reads and knn_calibration().needs_context_features


def test_a_context_knn_calibration_scores_a_chunk_by_its_knn_distance():
    calibration = knn_calibration()
    features = np.array([[0.0, 0.0, 0.0, 0.0], [5.0, 5.0, 5.0, 5.0]])
    np.testing.assert_allclose(
        calibration.chunk_score(
            EnergyReadout.of_arrays(torch.tensor([9.0, 9.0]), 0, torch.from_numpy(features))
        ),
        calibration.score.neighbours.distance(features),
    )


def test_a_context_knn_calibration_needs_the_context_features():
    with pytest.raises(ValueError, match="context_knn score needs each chunk's pooled context"):
        knn_calibration().chunk_score(EnergyReadout.of_arrays(1.0, 0))


def test_a_context_knn_calibration_needs_its_neighbours():
    with pytest.raises(ValueError, match="needs `neighbours`"):
        ContextKNN(None)


def test_a_context_knn_calibration_round_trips_through_json_and_safetensors(tmp_path):
    calibration = knn_calibration(k=0.5)
    calibration.save(tmp_path)
    entry = json.loads((tmp_path / OOD_CALIBRATION_FILENAME).read_text())[NEIGHBOURS_FILE.field]
    assert entry["file"] == NEIGHBOURS_FILE.filename and (entry["dim"], entry["n_chunks"], entry["k"]) == (
        D,
        40,
        K,
    )
    assert not (tmp_path / "ood_calibration_context.safetensors").exists()
    loaded = OODCalibration.load(tmp_path)
    assert loaded == calibration and loaded.score.name == "context_knn" and loaded.score.neighbours.k == K
    assert loaded.score.neighbours.features.dtype == np.float32
    np.testing.assert_array_equal(loaded.score.neighbours.features, calibration.score.neighbours.features)
    np.testing.assert_array_equal(loaded.score.neighbours.mean, calibration.score.neighbours.mean)
    np.testing.assert_array_equal(loaded.score.neighbours.std, calibration.score.neighbours.std)


def test_context_neighbours_of_another_calibration_are_refused(tmp_path):
    knn_calibration().save(tmp_path)
    other = ContextNeighbours.fit(vanilla_features(seed=1), k=K)
    (tmp_path / NEIGHBOURS_FILE.filename).write_bytes(other.to_bytes())
    with pytest.raises(ValueError, match="does not match `context_neighbours.sha256`"):
        OODCalibration.load(tmp_path)


def test_a_neighbours_entry_that_misstates_k_is_refused(tmp_path):
    knn_calibration().save(tmp_path)
    path = tmp_path / OOD_CALIBRATION_FILENAME
    payload = json.loads(path.read_text())
    payload[NEIGHBOURS_FILE.field]["k"] = K + 1
    path.write_text(json.dumps(payload))
    with pytest.raises(ValueError, match="but `context_neighbours` says"):
        OODCalibration.load(tmp_path)


# What the context k-NN saves beside the JSON: the context neighbours.
SIDE_FILES = [
    pytest.param(
        knn_calibration, NEIGHBOURS_FILE.filename, NEIGHBOURS_FILE.field, "neighbours", id="context_knn"
    ),
]


@pytest.mark.parametrize(("make_calibration", "filename", "field_name", "attribute"), SIDE_FILES)
def test_a_context_calibration_without_its_side_file_is_refused(
    tmp_path, make_calibration, filename, field_name, attribute
):
    make_calibration().save(tmp_path)
    (tmp_path / filename).unlink()
    with pytest.raises(ValueError, match=f"`{field_name}.file` names .* which does not exist"):
        OODCalibration.load(tmp_path)


@pytest.mark.parametrize(("make_calibration", "filename", "field_name", "attribute"), SIDE_FILES)
def test_saving_an_energy_calibration_removes_the_side_file_of_the_previous_one(
    tmp_path, make_calibration, filename, field_name, attribute
):
    make_calibration().save(tmp_path)
    OODCalibration(mu_v=1.0, sigma_v=1.0).save(tmp_path, overwrite=True)
    assert not (tmp_path / filename).exists()
    assert getattr(OODCalibration.load(tmp_path).score, attribute, None) is None


@pytest.mark.parametrize(("make_calibration", "filename", "field_name", "attribute"), SIDE_FILES)
def test_a_hub_calibration_downloads_its_side_file_beside_the_json(
    tmp_path, monkeypatch, make_calibration, filename, field_name, attribute
):
    import huggingface_hub

    snapshot = tmp_path / "snapshot"
    snapshot.mkdir()
    calibration = make_calibration()
    calibration.save(snapshot)
    downloaded = []

    def hf_hub_download(repo_id, filename):
        downloaded.append((repo_id, filename))
        return str(snapshot / filename)

    monkeypatch.setattr(huggingface_hub, "hf_hub_download", hf_hub_download)
    loaded = OODCalibration.from_pretrained("user/ebvla")
    assert downloaded == [("user/ebvla", OOD_CALIBRATION_FILENAME), ("user/ebvla", filename)]
    assert getattr(loaded.score, attribute).to_bytes() == getattr(calibration.score, attribute).to_bytes()


# The run-time monitor.


def calibrated_monitor() -> EnergyOODMonitor:
    """A monitor whose mu_v, sigma_v are the vanilla episodes' leave-one-episode-out k-NN scores (T at k = 1)."""
    features = vanilla_features(n=80)
    episode_ids = [i // 8 for i in range(len(features))]
    model = ContextFeatureModel.fit(features.astype(np.float64), episode_ids, k=K)
    scores = [model.context_knn(features[i : i + 8], episode_id=i // 8).mean() for i in range(0, 80, 8)]
    calibration = OODCalibration.fit(scores, k=1.0, score=ContextKNN(model.neighbours))
    return EnergyOODMonitor(calibration)


def test_the_monitor_passes_an_in_distribution_context_and_flags_a_shifted_one():
    monitor = calibrated_monitor()
    centre = monitor.calibration.score.neighbours.mean
    assert monitor.check(EnergyReadout.of_arrays(0.0, 0, centre))[0].in_distribution
    assert monitor.check(EnergyReadout.of_arrays(0.0, 0, centre + 4.0))[0].is_ood


def test_the_monitor_scores_each_environments_chunk_by_its_knn_distance():
    monitor = calibrated_monitor()
    features = np.array([[0.0, 0.0, 0.0, 0.0], [5.0, 5.0, 5.0, 5.0]])
    decisions = monitor.update(
        EnergyReadout(None, torch.tensor([9.0, 9.0]), context_features=torch.from_numpy(features))
    )
    expected = monitor.calibration.score.neighbours.distance(features)
    assert [d.energy for d in decisions] == pytest.approx(expected.tolist())
    assert [d.is_ood for d in decisions] == [False, True]


# ebvla-ood-report --score=context_knn.


@pytest.fixture(scope="module")
def record_dirs(tmp_path_factory):
    """Calibration and held-out vanilla rollouts, and rollouts whose contexts are shifted."""
    root = tmp_path_factory.mktemp("records")
    return (
        write_records(root / "calibration", context_rollouts(12, seed=10)),
        write_records(root / "vanilla", context_rollouts(12, seed=11)),
        write_records(root / "ood", context_rollouts(10, 1, "light", context=2.0)),
    )


def report_args(record_dirs, out: Path) -> list[str]:
    calibration, vanilla, ood = record_dirs
    return [
        f"--calibration=[{calibration}]",
        f"--vanilla=[{vanilla}]",
        f"--ood=[{ood}]",
        f"--output_dir={out}",
        "--n_bootstrap=50",
    ]


def test_ood_report_saves_a_context_knn_calibration_of_the_reports_knn_score(record_dirs, tmp_path, capsys):
    checkpoint = tmp_path / "pretrained_model"
    checkpoint.mkdir()
    args = [
        *report_args(record_dirs, tmp_path / "out"),
        f"--calibrate_to={checkpoint}",
        "--score=context_knn",
    ]
    ood_report.main([*args, f"--knn_k={K}"])
    out = capsys.readouterr().out
    assert "`--score=context_knn`" in out
    calibration = OODCalibration.load(checkpoint)
    assert calibration.score.name == "context_knn" and calibration.n_rollouts == 12
    assert calibration.score.neighbours.k == K and calibration.score.neighbours.n_chunks == 12 * 5
    calibration_set, vanilla = load_episodes([record_dirs[0]]), load_episodes([record_dirs[1]])
    reference = fit_score_reference(calibration_set, knn_k=K)
    features = np.stack([r.context_feature for episode in calibration_set.values() for r in episode])
    np.testing.assert_array_equal(calibration.score.neighbours.features, features)
    # The window is that of the report's knn score (the calibration rollouts leave-one-episode-out) over their
    # first 1, 2 and 3 chunks; mu_v and sigma_v are those of their window scores, each without its rollout.
    knn = np.stack(
        [
            episode_scores(calibration_set, "context_knn", reference=reference, first_chunks=n)
            for n in (1, 2, 3)
        ],
        axis=1,
    )
    window = calibration.window
    assert window.running.mean == pytest.approx(tuple(knn.mean(axis=0)))
    assert window.running.std == pytest.approx(tuple(knn.std(axis=0)))
    scores = ChunkWindow.leave_one_out_scores(knn)
    assert calibration.mu_v == pytest.approx(scores.mean()) and calibration.sigma_v == pytest.approx(
        scores.std()
    )
    # The report states the threshold it saved.
    assert "window score over their first 3 chunks" in out
    assert (
        f"mu_v = {calibration.mu_v:.4g}, sigma_v = {calibration.sigma_v:.4g}, T = {calibration.threshold:.4g}"
        in out
    )
    # A held-out rollout scores at run time what it scores in the report.
    monitor = EnergyOODMonitor(calibration)
    held_out = episode_chunk_scores(vanilla, "context_knn", reference)
    for key, episode in vanilla.items():
        energies = [r.final_energy for r in episode]
        features = np.stack([r.context_feature for r in episode])
        decision = monitor.check_rollout(EnergyReadout.of_arrays(energies, context_features=features))
        running = [held_out[key][:n].mean() for n in (1, 2, 3)]
        assert decision.energy == pytest.approx(window.score(running), rel=1e-12)


def test_ood_report_refuses_a_context_knn_calibration_without_context_features(record_dirs, tmp_path):
    no_features = [dataclasses.replace(r, context_feature=None) for r in context_rollouts(6, seed=20)]
    dirs = (write_records(tmp_path / "calibration", no_features), *record_dirs[1:])
    with pytest.raises(ValueError, match="record_context_features"):
        ood_report.main([*report_args(dirs, tmp_path / "out"), "--score=context_knn"])


# The policy's response.


def test_the_policy_scores_each_chunk_by_the_knn_distance_of_its_observation(tmp_path):
    torch.manual_seed(0)
    policy = EBVLAPolicy(tiny_config()).eval()
    contexts = [tiny_batch(policy.config, batch_size=4, seed=s, with_action=False) for s in range(3)]
    neighbours = ContextNeighbours.fit(torch.cat([policy.context_features(b) for b in contexts]), k=K)
    # A threshold below every distance: every chunk is flagged and raises with its highest distance.
    OODCalibration(mu_v=-1.0, sigma_v=0.0, score=ContextKNN(neighbours)).save(tmp_path)
    policy.configure_ood_response(tmp_path, response="raise")
    batch = tiny_batch(policy.config, batch_size=2, seed=7, with_action=False)
    with pytest.raises(EnergyOODError, match="context_knn") as raised:
        policy.predict_action_chunk(batch)
    expected = neighbours.distance(policy.context_features(batch)).max()
    assert raised.value.energy == pytest.approx(expected, rel=1e-5)
