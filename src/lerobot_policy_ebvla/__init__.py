"""EB-VLA: the Energy-Based VLA policy for LeRobot (`--policy.type=ebvla`).

The policy (`EBVLAConfig`, `EBVLAPolicy`, `make_ebvla_pre_post_processors`, the CPU-sized `LIGHT_POLICY`
preset) and what acts on its energy at
run time (`EnergyMonitor`, the checkpoint's monitor; `OODCalibration`, `EnergyOODError`) are importable from here; the offline
analysis lives in `lerobot_policy_ebvla.monitoring` and is not imported by the policy.
"""

import importlib.metadata
import warnings

from .configuration_ebvla import EBVLAConfig
from .modeling_ebvla import EBVLAPolicy
from .presets import LIGHT_POLICY, light_policy_config
from .processor_ebvla import make_ebvla_pre_post_processors
from .runtime import (
    OOD_CALIBRATION_FILENAME,
    EnergyMonitor,
    EnergyOODError,
    EnergyOODMonitor,
    EnergyOODResponse,
    EnergyReadout,
    FailureCalibration,
    MonitorDecision,
    OODCalibration,
    OODDecision,
)

# The env types register after the policy, and apart from it: a LeRobot release that moved a name they import
# loses the envs only, with this warning, while `--policy.type=ebvla` stays registered (LeRobot's plugin loader
# would only log the error). The private LeRobot names they use are looked up when an env is built.
try:
    from . import envs  # noqa: F401  (registers `--env.type=metaworld_ebvla` and `libero_ebvla`; imports no simulator)
except ImportError as error:
    warnings.warn(
        f"lerobot_policy_ebvla: the env types metaworld_ebvla and libero_ebvla are not registered, as LeRobot "
        f"{importlib.metadata.version('lerobot')} fails to import them: {error}",
        stacklevel=2,
    )

__all__ = [
    "LIGHT_POLICY",
    "OOD_CALIBRATION_FILENAME",
    "EBVLAConfig",
    "EBVLAPolicy",
    "EnergyMonitor",
    "EnergyOODError",
    "EnergyOODMonitor",
    "EnergyOODResponse",
    "EnergyReadout",
    "FailureCalibration",
    "MonitorDecision",
    "OODCalibration",
    "OODDecision",
    "light_policy_config",
    "make_ebvla_pre_post_processors",
]
