"""What ships with a checkpoint and acts on the energy at run time; the policy imports it, analysis builds on it.

- `readout`: `EnergyReadout`, what the policy reports about each chunk (its energies, its index in the episode,
  its pooled context when needed): the one input of the scores, the calibration, the monitors and the response.
- `threshold`: the one decision rule, "flag when score > T", with T = mu + k sigma (Eq. 5) or the conformal
  quantile of a stated false-alarm rate, and `OODDecision`, its verdict on a batch of scores.
- `statistics`: what the chunk scores measure against, fitted on vanilla rollouts (`PhaseStatistics`,
  `ContextStatistics`, `ContextNeighbours`, `CombinedStatistics`), and `ChunkWindow`, the one score of a rollout's
  first N running scores that lets one T bound a run-time monitor's N decisions.
- `scores`: `ChunkInputs` (a readout as the scores read it), the `ChunkScore` protocol, the package's eight scores
  (final energy, context phase energy, two-sided head energy, joint phase energy, context start energy, joint phase
  time energy, success energy, context k-NN), and `SCORES`, the registry that names them, with `register_score`,
  its hook for research scores.
- `success_energy`: `SuccessEnergy`, E_s(C, t), an energy of the pooled context at chunk index t fitted on the
  successful calibration rollouts, its fit and its cross-fitting (the `success_energy` failure check).
- `calibration`: `OODCalibration`, the threshold statistics of one chunk score (`ood_calibration.json` beside
  the weights, the score's statistics in safetensors files beside it), and `FailureCalibration`, the failure
  check's: an energy score over the first N chunks, set on the same vanilla rollouts (`failure_calibration.json`;
  the success energy's weights beside it).
- `monitor`: `EnergyMonitor`, the checkpoint's monitor: both thresholds applied to the policy's readouts as they
  come (`from_pretrained`, `update(policy.last_energy)`, `reset`), and `EnergyOODMonitor`, one calibration alone.
- `failure_alarm`: `FailureAlarm`, the paper's energy-slope failure predictor as one check at a step chosen on
  calibration rollouts that include failures (`failure_alarm.json` beside the weights), and
  `EnergyFailureMonitor`, which feeds it each chunk.
- `history`: the per-environment history both monitors keep, and `ReadoutMonitor`, their one shape.
- `checkpoint_files`: the one way a calibration is saved beside a checkpoint and loaded back (local or Hub).
- `response`: what the policy does with a flagged chunk (`EBVLAConfig.monitor.response`: continue, hold, or raise
  `EnergyOODError`).

Nothing here imports the analysis (`monitoring/`), matplotlib or a simulator.
"""

from .calibration import (
    FAILURE_CALIBRATION_FILENAME,
    OOD_CALIBRATION_FILENAME,
    FailureCalibration,
    OODCalibration,
)
from .failure_alarm import FAILURE_ALARM_FILENAME, EnergyFailureMonitor, FailureAlarm, FailureDecision
from .monitor import EnergyMonitor, EnergyOODMonitor, MonitorDecision
from .readout import EnergyReadout
from .response import EnergyOODError, EnergyOODResponse, HoldAction, respond_to_energy
from .scores import SCORES, ChunkInputs, ChunkScore, VanillaRollouts, rollout_score
from .statistics import ChunkWindow, PhaseStatistics
from .threshold import MeanStd, OODDecision, conformal_threshold, exceeds, mean_std_threshold

__all__ = [
    "FAILURE_ALARM_FILENAME",
    "FAILURE_CALIBRATION_FILENAME",
    "SCORES",
    "ChunkInputs",
    "ChunkScore",
    "ChunkWindow",
    "EnergyFailureMonitor",
    "EnergyMonitor",
    "FailureAlarm",
    "FailureCalibration",
    "FailureDecision",
    "OOD_CALIBRATION_FILENAME",
    "EnergyOODError",
    "EnergyOODMonitor",
    "EnergyOODResponse",
    "EnergyReadout",
    "HoldAction",
    "MeanStd",
    "MonitorDecision",
    "OODCalibration",
    "OODDecision",
    "PhaseStatistics",
    "VanillaRollouts",
    "conformal_threshold",
    "exceeds",
    "mean_std_threshold",
    "respond_to_energy",
    "rollout_score",
]
