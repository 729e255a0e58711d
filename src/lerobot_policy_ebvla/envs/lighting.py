"""The lighting perturbations MetaWorld and LIBERO share: intensity and colour of every light of a MuJoCo scene.

Per severity level s: intensity factor 1 - 0.16 s for "light_dim" (0.2 at severity 5) and 1 + 0.3 s for
"light_bright" (2.5 at severity 5); "light_color" moves the lights' colour from white to `LIGHT_TINT_RGB`,
reached at the highest severity. The direction perturbations depend on each scene's lights and stay with the env.
"""

from collections.abc import Sequence

import mujoco
import numpy as np

LIGHT_DIM_PER_LEVEL = 0.16
LIGHT_BRIGHT_PER_LEVEL = 0.30
LIGHT_TINT_RGB = (1.0, 0.6, 0.25)
LIGHT_INTENSITY_PERTURBATIONS = ("light_dim", "light_bright", "light_color")


def scale_lights(model: mujoco.MjModel, rgb_factor: Sequence[float]) -> None:
    """Multiplies the ambient, diffuse and specular colour of every light, the headlight included."""
    factor = np.asarray(rgb_factor, dtype=float)
    for colour in (model.light_ambient, model.light_diffuse, model.light_specular):
        colour *= factor
    headlight = model.vis.headlight
    headlight.ambient = headlight.ambient * factor
    headlight.diffuse = headlight.diffuse * factor
    headlight.specular = headlight.specular * factor


def perturb_light_intensity(
    model: mujoco.MjModel, perturbation: str, severity: int, max_severity: int
) -> None:
    """Applies one of `LIGHT_INTENSITY_PERTURBATIONS` at `severity` (0 to `max_severity`) to `model`, in place."""
    if perturbation == "light_dim":
        scale_lights(model, [1.0 - LIGHT_DIM_PER_LEVEL * severity] * 3)
    elif perturbation == "light_bright":
        scale_lights(model, [1.0 + LIGHT_BRIGHT_PER_LEVEL * severity] * 3)
    elif perturbation == "light_color":
        scale_lights(model, 1.0 + severity / max_severity * (np.asarray(LIGHT_TINT_RGB) - 1.0))
    else:
        raise ValueError(
            f"`perturbation` must be one of {LIGHT_INTENSITY_PERTURBATIONS}, got {perturbation!r}."
        )
