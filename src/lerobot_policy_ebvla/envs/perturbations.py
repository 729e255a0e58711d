"""The perturbations each env offers, by name, and the check of a (perturbation, severity) pair.

Both the env configs (`configs.py`, `libero_configs.py`) and the simulators (`metaworld.py`, `libero.py`) need
them; they live here so that a simulator never imports its config. Every perturbation is graded by a severity
level from 0 (no change) to `MAX_SEVERITY`, LIBERO-Plus's five levels; the magnitudes per level are the
constants of each simulator module, tabulated in docs/metaworld.md and docs/libero.md.
"""

import math

MAX_SEVERITY = 5
LIGHTING_PERTURBATIONS = ("light_dim", "light_bright", "light_color", "light_direction")

# The perturbation dimensions of LIBERO-Plus that MetaWorld allows (magnitudes: envs/metaworld.py).
CAMERA_PERTURBATIONS = ("pose", "fov", "pose_fov")
SENSOR_PERTURBATIONS = ("noise", "blur", "blank")
SCENE_PERTURBATIONS = ("table_color", "table_texture", "distractor")
ROBOT_PERTURBATIONS = ("robot_init",)
PERTURBATIONS = (
    "none",
    *CAMERA_PERTURBATIONS,
    *LIGHTING_PERTURBATIONS,
    *SENSOR_PERTURBATIONS,
    *SCENE_PERTURBATIONS,
    *ROBOT_PERTURBATIONS,
)

# LIBERO-Plus's camera dimension, whose variants change one of three things: "pose" orbits the agent-view
# camera (horizontally about the world's vertical axis, vertically about LIBERO-Plus's pivot), "distance" moves
# it away from the pivot, "rotation" turns it in place. "fov" widens its field of view (a focal change, which
# LIBERO-Plus's released variants do not include). Magnitudes per severity: envs/libero.py, docs/libero.md.
LIBERO_CAMERA_PERTURBATIONS = ("pose", "distance", "rotation", "fov")
# Beyond the camera and the light, two kinds that no training corruption of the LIBERO recipe produces (issue 52):
# LIBERO-Plus's sensor noise (and a blur) on every camera's frames, and its background dimension as a recolouring
# of the table, floor and walls ("table_color", as MetaWorld's).
LIBERO_SENSOR_PERTURBATIONS = ("noise", "blur")
LIBERO_SCENE_PERTURBATIONS = ("table_color",)
LIBERO_PERTURBATIONS = (
    "none",
    *LIBERO_CAMERA_PERTURBATIONS,
    *LIGHTING_PERTURBATIONS,
    *LIBERO_SENSOR_PERTURBATIONS,
    *LIBERO_SCENE_PERTURBATIONS,
)


def _check(perturbation: str, severity: int, names: tuple[str, ...]) -> None:
    if perturbation not in names:
        raise ValueError(f"`perturbation` must be one of {names}, got {perturbation!r}.")
    if isinstance(severity, bool) or not isinstance(severity, int) or not 0 <= severity <= MAX_SEVERITY:
        raise ValueError(f"`perturbation_severity` must be an int in [0, {MAX_SEVERITY}], got {severity!r}.")
    if perturbation == "none" and severity != 0:
        raise ValueError(
            f"`perturbation_severity` > 0 needs a `perturbation` other than 'none' (one of {names[1:]})."
        )


def check_perturbation(perturbation: str, severity: int) -> None:
    """Raises a ValueError naming the field and its allowed values if a MetaWorld perturbation is invalid."""
    _check(perturbation, severity, PERTURBATIONS)


def check_libero_perturbation(perturbation: str, severity: int) -> None:
    """Raises a ValueError naming the field and its allowed values if a LIBERO perturbation is invalid."""
    _check(perturbation, severity, LIBERO_PERTURBATIONS)


def check_robot_init_noise(robot_init_noise: float) -> None:
    if not (math.isfinite(robot_init_noise) and robot_init_noise >= 0):
        raise ValueError(
            f"`robot_init_noise` (radians, the std of each arm joint's starting noise) must be finite and >= 0, "
            f"got {robot_init_noise}."
        )
