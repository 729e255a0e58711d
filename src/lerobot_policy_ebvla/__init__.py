"""EB-VLA: the Energy-Based VLA policy for LeRobot (`--policy.type=ebvla`).

The policy (`EBVLAConfig`, `EBVLAPolicy`, `make_ebvla_pre_post_processors`, the CPU-sized `LIGHT_POLICY`
preset) and what acts on its energy at
run time (`OODCalibration`, `EnergyOODMonitor`, `EnergyOODError`) are importable from here; the offline
analysis lives in `lerobot_policy_ebvla.monitoring` and is not imported by the policy.
"""

from . import envs  # noqa: F401  (registers `--env.type=metaworld_ebvla` and `libero_ebvla`; imports no simulator)
from .configuration_ebvla import EBVLAConfig
from .modeling_ebvla import EBVLAPolicy, EnergyReadout
from .presets import LIGHT_POLICY, light_policy_config
from .processor_ebvla import make_ebvla_pre_post_processors
from .runtime import (
    OOD_CALIBRATION_FILENAME,
    EnergyOODError,
    EnergyOODMonitor,
    EnergyOODResponse,
    OODCalibration,
    OODResponseDecision,
)

__all__ = [
    "LIGHT_POLICY",
    "OOD_CALIBRATION_FILENAME",
    "EBVLAConfig",
    "EBVLAPolicy",
    "EnergyOODError",
    "EnergyOODMonitor",
    "EnergyOODResponse",
    "EnergyReadout",
    "OODCalibration",
    "OODResponseDecision",
    "light_policy_config",
    "make_ebvla_pre_post_processors",
]
