"""Energy-based monitoring: OOD detection (Sec. III-C), failure prediction (Sec. III-D), landscapes (Fig. 2).

- `records`: the per-chunk energy records `ebvla-eval` writes and every tool here reads.
- `ood`: the threshold T = mu_v + k * sigma_v (Eq. 5), its run-time monitor and Table III's metrics.
- `failure`: energy-slope failure prediction and Table IV's sweep.
- `landscape`: the energy around a refined action chunk (Fig. 2).
"""

from .failure import (
    FailurePredictionResult,
    episode_slopes,
    evaluate_failure_predictor,
    failure_prediction_sweep,
    format_failure_table,
    linear_slope,
)
from .landscape import (
    EnergyLandscape,
    energy_landscape,
    make_policy_score_fn,
    plot_energy_landscape,
    policy_energy_landscape,
)
from .ood import (
    OOD_CALIBRATION_FILENAME,
    DetectionRow,
    EnergyOODMonitor,
    OODCalibration,
    OODDecision,
    auroc,
    format_detection_table,
    ood_detection_table,
    roc_curve,
    rollout_score,
    rollout_scores,
)
from .records import (
    ENERGY_RECORDS_FILENAME,
    EnergyRecord,
    EpisodeKey,
    group_by_episode,
    read_energy_records,
    write_energy_records,
)

__all__ = [
    "ENERGY_RECORDS_FILENAME",
    "OOD_CALIBRATION_FILENAME",
    "DetectionRow",
    "EnergyLandscape",
    "EnergyOODMonitor",
    "EnergyRecord",
    "EpisodeKey",
    "FailurePredictionResult",
    "OODCalibration",
    "OODDecision",
    "auroc",
    "energy_landscape",
    "episode_slopes",
    "evaluate_failure_predictor",
    "failure_prediction_sweep",
    "format_detection_table",
    "format_failure_table",
    "group_by_episode",
    "linear_slope",
    "make_policy_score_fn",
    "ood_detection_table",
    "plot_energy_landscape",
    "policy_energy_landscape",
    "read_energy_records",
    "roc_curve",
    "rollout_score",
    "rollout_scores",
    "write_energy_records",
]
