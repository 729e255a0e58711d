"""What ships with a checkpoint and acts on the energy at run time; the policy imports it, analysis builds on it.

- `threshold`: the one decision rule, "flag when score > T", with T = mu + k sigma (Eq. 5) or the conformal
  quantile of a stated false-alarm rate.
- `calibration`: `OODCalibration` (mu_v, sigma_v, k, the rule, and the chunk score it applies to: the final
  energy, the phase energy of `PhaseStatistics`, the context distance of `ContextStatistics`, the energy and
  context score of `CombinedStatistics`, or the context k-NN distance of `ContextNeighbours`;
  `ood_calibration.json` beside the weights, context statistics and neighbours in safetensors files beside it),
  the rollout score it is defined on, and `EnergyOODMonitor`, which applies it to energies as they come.
- `failure_alarm`: `FailureAlarm`, the energy-slope failure predictor as one check at a step chosen on
  calibration (`failure_alarm.json` beside the weights), and `EnergyFailureMonitor`, which feeds it each chunk.
- `response`: what the policy does with a flagged chunk (`EBVLAConfig.ood_response`: continue, hold, or raise
  `EnergyOODError`).

Nothing here imports the analysis (`monitoring/`), matplotlib or a simulator.
"""

from .calibration import (
    OOD_CALIBRATION_FILENAME,
    EnergyOODMonitor,
    OODCalibration,
    OODDecision,
    PhaseStatistics,
    rollout_score,
)
from .failure_alarm import FAILURE_ALARM_FILENAME, EnergyFailureMonitor, FailureAlarm, FailureDecision
from .response import EnergyOODError, EnergyOODResponse, HoldAction, OODResponseDecision, respond_to_energy
from .threshold import MeanStd, conformal_threshold, exceeds, mean_std_threshold

__all__ = [
    "FAILURE_ALARM_FILENAME",
    "EnergyFailureMonitor",
    "FailureAlarm",
    "FailureDecision",
    "OOD_CALIBRATION_FILENAME",
    "EnergyOODError",
    "EnergyOODMonitor",
    "EnergyOODResponse",
    "HoldAction",
    "MeanStd",
    "OODCalibration",
    "OODDecision",
    "OODResponseDecision",
    "PhaseStatistics",
    "conformal_threshold",
    "exceeds",
    "mean_std_threshold",
    "respond_to_energy",
    "rollout_score",
]
