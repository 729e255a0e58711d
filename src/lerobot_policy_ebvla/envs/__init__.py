"""Simulation environments for recording demonstrations and evaluating EB-VLA.

- `MetaworldEBVLAEnv` (`--env.type=metaworld_ebvla`): LeRobot's MetaWorld env with fast rendering and
  LIBERO-Plus-style perturbations; the simulator side lives in `envs.metaworld` (needs MetaWorld).
- `LiberoEBVLAEnv` (`--env.type=libero_ebvla`): LeRobot's LIBERO env with LIBERO-Plus-style camera and lighting
  perturbations; the simulator side lives in `envs.libero` (needs the `libero` extra and
  `ebvla-install-libero-assets`, whose library part is `envs.libero_assets`).
- `envs.perturbations`: the perturbation names of both envs and their check.
- `envs.frames`: `render_every`, both envs drawing only the frames a chunked policy reads.
"""

from .configs import MetaworldEBVLAEnv
from .libero_configs import LiberoEBVLAEnv
from .perturbations import CAMERA_PERTURBATIONS, MAX_SEVERITY

__all__ = ["CAMERA_PERTURBATIONS", "MAX_SEVERITY", "LiberoEBVLAEnv", "MetaworldEBVLAEnv"]
