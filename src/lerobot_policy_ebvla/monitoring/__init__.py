"""Energy-based monitoring: OOD detection (Sec. III-C), failure prediction (Sec. III-D), landscapes (Fig. 2).

- `records`: the per-chunk energy records every tool here reads (`energy_records.jsonl`).
- `recorder`: writes them during LeRobot rollouts (`ebvla-eval`, examples, any rollout loop).
- `threshold`: where a score becomes a decision: "flag when score > T", T = mu + k sigma (Eq. 5) or the
  conformal quantile of a stated false-alarm rate.
- `metrics`: accuracy, balanced accuracy, TPR, FPR, F1, AUROC with bootstrap intervals, ROC curves.
- `ood`: the vanilla calibration, its run-time monitor and Table III.
- `baselines`: the post-hoc scores the energy is compared with (initial energy, restart spread,
  Mahalanobis and k-NN distances of the context).
- `failure`: energy-slope failure prediction and Table IV, in-sample or held out.
- `landscape`: the energy around a refined action chunk (Fig. 2).
- `plots`: every figure.
- `vision`: does the policy see? Its chunk and energy with real against blanked cameras.
"""

from .baselines import SCORE_NAMES, ContextFeatureModel, available_scores, episode_scores, fit_feature_model
from .failure import (
    FailurePredictionResult,
    episode_slopes,
    evaluate_configurations,
    evaluate_failure_predictor,
    failure_prediction_sweep,
    format_failure_table,
    linear_slope,
    select_configurations,
)
from .landscape import EnergyLandscape, energy_landscape, make_policy_score_fn, policy_energy_landscape
from .metrics import BinaryRates, auroc, bootstrap_auroc_interval, roc_curve
from .ood import (
    OOD_CALIBRATION_FILENAME,
    DetectionRow,
    EnergyOODMonitor,
    OODCalibration,
    OODDecision,
    format_detection_table,
    ood_detection_table,
    rollout_score,
    rollout_scores,
)
from .plots import plot_energy_landscape, plot_energy_over_time, plot_roc, plot_score_histograms
from .recorder import EnergyRecorder
from .records import (
    ENERGY_RECORDS_FILENAME,
    EnergyRecord,
    EpisodeKey,
    group_by_episode,
    load_episodes,
    read_energy_records,
    write_energy_records,
)
from .threshold import conformal_threshold, exceeds, mean_std_threshold
from .vision import CameraDependence, blank_cameras, camera_dependence

__all__ = [
    "CameraDependence",
    "blank_cameras",
    "camera_dependence",
    "ENERGY_RECORDS_FILENAME",
    "OOD_CALIBRATION_FILENAME",
    "SCORE_NAMES",
    "BinaryRates",
    "ContextFeatureModel",
    "DetectionRow",
    "EnergyLandscape",
    "EnergyOODMonitor",
    "EnergyRecord",
    "EnergyRecorder",
    "EpisodeKey",
    "FailurePredictionResult",
    "OODCalibration",
    "OODDecision",
    "auroc",
    "available_scores",
    "bootstrap_auroc_interval",
    "conformal_threshold",
    "energy_landscape",
    "episode_scores",
    "episode_slopes",
    "evaluate_configurations",
    "evaluate_failure_predictor",
    "exceeds",
    "failure_prediction_sweep",
    "fit_feature_model",
    "format_detection_table",
    "format_failure_table",
    "group_by_episode",
    "linear_slope",
    "load_episodes",
    "make_policy_score_fn",
    "mean_std_threshold",
    "ood_detection_table",
    "plot_energy_landscape",
    "plot_energy_over_time",
    "plot_roc",
    "plot_score_histograms",
    "policy_energy_landscape",
    "read_energy_records",
    "roc_curve",
    "rollout_score",
    "rollout_scores",
    "select_configurations",
    "write_energy_records",
]
