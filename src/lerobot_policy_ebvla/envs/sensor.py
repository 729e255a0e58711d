"""The sensor perturbations, applied to every rendered frame while an env runs: the same in MetaWorld and LIBERO.

"noise" adds Gaussian pixel noise, "blur" a Gaussian blur, "blank" replaces the frame by a black one (the camera
check's condition). Each is graded by a severity 1..5 (0: none); the per-level magnitudes are the constants below,
tabulated in docs/metaworld.md and docs/libero.md.
"""

import cv2
import numpy as np

from .perturbations import SENSOR_PERTURBATIONS

# Standard deviation of the Gaussian pixel noise (uint8 levels) and of the Gaussian blur (pixels of a 480x480
# frame, scaled with the frame's size) per level.
NOISE_STD_PER_LEVEL = 8.0
BLUR_SIGMA_PX_PER_LEVEL = 1.5
BLUR_REFERENCE_SIZE = 480


def perturb_image(
    image: np.ndarray, perturbation: str, severity: int, rng: np.random.Generator
) -> np.ndarray:
    """Applies the sensor perturbations ("noise", "blur", "blank") to an (H, W, 3) uint8 frame.

    Other perturbations return `image` unchanged. "blank" (a black frame) is the same at every severity >= 1.
    """
    if severity == 0 or perturbation not in SENSOR_PERTURBATIONS:
        return image
    if perturbation == "blank":
        return np.zeros_like(image)
    if perturbation == "blur":
        # The same blur relative to the frame whatever size it was rendered at.
        sigma = BLUR_SIGMA_PX_PER_LEVEL * severity * image.shape[1] / BLUR_REFERENCE_SIZE
        return cv2.GaussianBlur(image, (0, 0), sigmaX=sigma)
    noisy = image + rng.normal(0.0, NOISE_STD_PER_LEVEL * severity, image.shape)
    return np.clip(np.round(noisy), 0, 255).astype(np.uint8)
