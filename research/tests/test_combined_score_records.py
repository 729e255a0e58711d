"""The combined score's figures of research/results/metaworld_sweep_context_distance/combined_score.md, recomputed
from the sweep's committed records."""

from lerobot_policy_ebvla.monitoring.baselines import fit_score_reference
from lerobot_policy_ebvla.monitoring.metrics import auroc
from lerobot_policy_ebvla.monitoring.ood import ood_detection_table
from lerobot_policy_ebvla.monitoring.records import load_episodes
from lerobot_policy_ebvla.monitoring.scores import episode_scores
from lerobot_policy_ebvla.runtime.calibration import OODCalibration
from lerobot_policy_ebvla.runtime.statistics import CombinedStatistics
from research.tests.conftest import RESULTS

SWEEP = RESULTS / "metaworld_sweep_context_distance" / "records"


def test_the_combined_score_of_the_committed_sweep_catches_pose_3_which_neither_score_alone_does():
    """combined_score.md, pose 3 (success 100% -> 60%): whole-episode AUROC final energy 0.800, mahalanobis
    0.720, energy_and_context 0.960; Table III balanced accuracy at k = 1.0: 70.0%."""
    calibration, vanilla, pose = (
        load_episodes([SWEEP / name]) for name in ("calibration", "vanilla", "pose_s3")
    )
    reference = fit_score_reference(calibration)

    def scores(episodes):
        return [
            episode_scores(episodes, n, reference=reference) for n in ("final_energy", "context_distance")
        ]

    statistics = CombinedStatistics.fit(*scores(calibration))
    negatives, positives = statistics.combine(*scores(vanilla)), statistics.combine(*scores(pose))
    assert [f"{auroc(a, b):.3f}" for a, b in zip(scores(vanilla), scores(pose), strict=True)] == [
        "0.800",
        "0.720",
    ]
    assert f"{auroc(negatives, positives):.3f}" == "0.960"
    fit = OODCalibration.fit(statistics.combine(*scores(calibration)))
    row = {r.multiplier: r for r in ood_detection_table(negatives, positives, calibration=fit)}[1.0]
    assert f"{row.balanced_accuracy:.1%}" == "70.0%"
