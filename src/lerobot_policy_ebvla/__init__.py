"""EB-VLA: the Energy-Based VLA policy for LeRobot (`--policy.type=ebvla`)."""

from . import envs  # noqa: F401  (registers `--env.type=metaworld_ebvla`; imports no simulator)
from .configuration_ebvla import EBVLAConfig
from .modeling_ebvla import EBVLAPolicy, EnergyReadout
from .processor_ebvla import make_ebvla_pre_post_processors

__all__ = ["EBVLAConfig", "EBVLAPolicy", "EnergyReadout", "make_ebvla_pre_post_processors"]
