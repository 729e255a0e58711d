"""Offline analysis of the energy: records, reports (Table III/IV), baselines, landscapes, plots.

Everything here studies rollouts; it imports the policy and `runtime/`, and neither imports it back.

- `records`: the per-chunk energy records every tool here reads (`energy_records.jsonl`).
- `recorder`: writes them during LeRobot rollouts through the policy's chunk hook.
- `scores`: the one way to turn an episode's chunk records into a score (the energy or a baseline).
- `metrics`: accuracy, balanced accuracy, TPR, FPR, F1, AUROC with bootstrap intervals, ROC curves.
- `protocol`: the held-out check: calibration and report sets share no record file and no seed.
- `ood`: Table III, the energy threshold of Eq. 5 evaluated on vanilla and perturbed rollouts;
  `ood_report` builds `ebvla-ood-report`'s report from it (`score_ood_report`, then `write_scored_report`).
- `baselines`: the post-hoc scores the energy is compared with (initial energy, restart spread,
  Mahalanobis and k-NN distances of the context).
- `failure`: energy-slope failure prediction and Table IV, in-sample or held out, and the one-check alarm
  chosen on calibration (`select_check_step`, `failure_alarm`); `failure_report` builds
  `ebvla-failure-report`'s report and saves that alarm with `--calibrate_to`.
- `landscape`: the energy around a refined action chunk (Fig. 2).
- `plots`: every figure (the only module that imports matplotlib).
- `vision`: does the policy see? Its chunk and energy with real against blanked cameras.

The threshold rule, the calibration and the failure alarm that ship with a checkpoint live in `runtime/`.
"""

from .metrics import (
    BinaryRates,
    auroc,
    bootstrap_auroc_difference_interval,
    bootstrap_auroc_interval,
    roc_curve,
)
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
from .scores import episode_scores

__all__ = [
    "ENERGY_RECORDS_FILENAME",
    "BinaryRates",
    "EnergyRecord",
    "EnergyRecorder",
    "EpisodeKey",
    "auroc",
    "bootstrap_auroc_difference_interval",
    "bootstrap_auroc_interval",
    "episode_scores",
    "group_by_episode",
    "load_episodes",
    "read_energy_records",
    "roc_curve",
    "write_energy_records",
]
