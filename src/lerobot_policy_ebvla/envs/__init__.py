"""Simulation environments for recording demonstrations and evaluating EB-VLA.

- `MetaworldEBVLAEnv` (`--env.type=metaworld_ebvla`): LeRobot's MetaWorld env with fast rendering and
  LIBERO-Plus-style camera perturbations; the simulator side lives in `envs.metaworld` (needs MetaWorld).
"""

from .configs import CAMERA_PERTURBATIONS, MAX_SEVERITY, MetaworldEBVLAEnv
from .libero_configs import LiberoEBVLAEnv  # noqa: F401  (registers `--env.type=libero_ebvla`)

__all__ = ["CAMERA_PERTURBATIONS", "MAX_SEVERITY", "MetaworldEBVLAEnv"]
