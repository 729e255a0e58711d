"""`ebvla-ood-report --calibrate_to --score=<research score>`: the research scores, registered by their module,
are calibrated by the package's report like its own."""

import numpy as np
import pytest

from lerobot_policy_ebvla.monitoring.baselines import fit_score_reference
from lerobot_policy_ebvla.monitoring.records import load_episodes
from lerobot_policy_ebvla.monitoring.scores import episode_scores
from lerobot_policy_ebvla.runtime.calibration import OODCalibration
from lerobot_policy_ebvla.scripts import ood_report
from research.tests.conftest import load_benchmark
from tests import test_monitoring_reports as package_reports
from tests.test_monitoring_reports import ood_args, rollouts, write


@pytest.fixture
def record_dirs(tmp_path):
    """The records of tests/test_monitoring_reports.py's fixture of that name."""
    return package_reports.record_dirs.__wrapped__(tmp_path)


def test_ood_report_saves_a_phase_energy_calibration_when_asked(record_dirs, tmp_path):
    load_benchmark("research_scores")  # a research score, registered by its module
    checkpoint = tmp_path / "pretrained_model"
    checkpoint.mkdir()
    ood_report.main(
        [*ood_args(*record_dirs, tmp_path / "out"), f"--calibrate_to={checkpoint}", "--score=phase_energy"]
    )
    calibration = OODCalibration.load(checkpoint)
    expected = fit_score_reference(load_episodes([record_dirs[0]]), features=False).phase.statistics
    assert calibration.score.name == "phase_energy" and calibration.score.phase == expected
    assert calibration.n_rollouts == 12 and abs(calibration.mu_v) < 1.0  # z-scores of vanilla rollouts


def calibrated(record_dirs, tmp_path, score: str) -> OODCalibration:
    """The calibration `ebvla-ood-report --calibrate_to --score=<score>` saves from the fixture's records."""
    checkpoint = tmp_path / "pretrained_model"
    checkpoint.mkdir()
    ood_report.main(
        [*ood_args(*record_dirs, tmp_path / "out"), f"--calibrate_to={checkpoint}", f"--score={score}"]
    )
    return OODCalibration.load(checkpoint)


def test_ood_report_saves_a_context_distance_calibration_when_asked(record_dirs, tmp_path):
    load_benchmark("research_scores")  # a research score, registered by its module
    calibration = calibrated(record_dirs, tmp_path, "context_distance")
    episodes = load_episodes([record_dirs[0]])
    reference = fit_score_reference(episodes)
    assert calibration.score.name == "context_distance" and calibration.n_rollouts == 12
    np.testing.assert_allclose(calibration.score.context.mean, reference.features.statistics.mean)
    np.testing.assert_allclose(calibration.score.context.precision, reference.features.statistics.precision)
    # The window's mu_n is that of the report's context_distance score after n chunks: the calibration rollouts
    # leave-one-episode-out (mu_3: the first-chunk Table III's fit).
    assert calibration.window is not None and calibration.window.chunks == 3
    for n in (1, 3):
        context_distance = episode_scores(episodes, "context_distance", reference=reference, first_chunks=n)
        assert calibration.window.running.mean[n - 1] == pytest.approx(context_distance.mean())


def test_ood_report_refuses_a_context_distance_calibration_without_context_features(tmp_path):
    load_benchmark("research_scores")  # a research score, registered by its module
    dirs = (
        write(tmp_path, "vanilla_a", rollouts(6, 5.0, seed=10)),
        write(tmp_path, "vanilla_b", rollouts(6, 5.0, seed=11)),
        write(tmp_path, "camera", rollouts(6, 6.0, "camera", 1.0, seed=1)),
    )
    with pytest.raises(ValueError, match="record_context_features"):
        ood_report.main([*ood_args(*dirs, tmp_path / "out"), "--score=context_distance"])
