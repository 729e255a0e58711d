"""Training signals beyond the paper's Eq. 4: outlier exposure for the energy (issue 32), and where the
contrastive term's head pass runs in bf16.

Outlier exposure: the expert chunk must cost more under a corrupted context.

The paper's loss (Eq. 4, the L1 of the refined chunk) and the contrastive ranking both leave the energy's level
per context free: adding any f(C) to E(a, C) changes neither the descent direction nor the ranking of chunks
under one context. Nothing then stops a context the policy never saw from sitting *lower* than the data, and
the final energy from flagging it as more familiar than vanilla (research/docs/energy_study.md, section "Why the energy
falls"). `energy_margin_loss` pins the level: for each observation, under a generically corrupted copy C~ of its
context (`corrupt_observation`, never the evaluation's perturbations), the expert chunk a* must cost at least
`margin` more than under the real context,

    L_margin = mean_i max(0, m - (E(a*_i, C~_i) - E(a*_i, C_i))).

The gradient flows through both energies: the hinge then sees only the part of the energy that depends on the
context, and cannot be met by raising every energy at once (a bias that also lengthens every MCMC step,
exp(e_t / tau)). With a stop-gradient on the real side, a tiny policy did exactly that: its energies climbed
by 5 in 8 steps while the gap stayed at 0.
"""

import functools

import torch
from torch import Tensor, nn

from .configuration_ebvla import OOD_CORRUPTIONS as CORRUPTIONS
from .configuration_ebvla import EBVLAConfig

# Range of |log g| of "channel_gain"'s per-channel gains g (the sign drawn per channel): g in [0.30, 0.67] or
# [1.5, 3.3]. Gains near 1 would look like the data, and a hinge on corruptions indistinguishable from the data is
# minimized by an energy that ignores the context (Jensen: E relu(m - gap) >= relu(m - E gap) = m at E gap = 0).
LOG_GAIN_RANGE = (0.4, 1.2)
# Range of the side of "patch_swap"'s rectangle and of "shift"'s translation, as fractions of the image side.
PATCH_RANGE = (0.3, 0.6)
SHIFT_RANGE = (0.1, 0.25)
# Std of "state_noise" in normalized state units.
STATE_NOISE_STD = 1.0
# Kernel sides of "random_conv" (RandConv, Xu et al., ICLR 2021): a random convolution of each image, its weights
# N(0, 1 / (C k^2)) so that the output keeps the input's scale before it is rescaled to [0, 1].
RANDOM_CONV_KERNELS = (3, 5)
# "shading": log g(y, x) = A (x cos(theta) + y sin(theta)) + B exp(-|(y, x) - c|^2 / (2 sigma^2)) on [-1, 1]^2,
# |A| and |B| in LOG_GAIN_RANGE (so that, as for "channel_gain", no image is left looking like the data) and
# sigma in SHADING_BLOB_RANGE: a brighter or darker side and one brighter or darker pool, alike on every channel.
SHADING_BLOB_RANGE = (0.2, 0.6)


def _uniform(
    low: float, high: float, shape: tuple[int, ...], generator: torch.Generator, ref: Tensor
) -> Tensor:
    return low + (high - low) * torch.rand(shape, generator=generator, device=ref.device, dtype=ref.dtype)


def channel_gain(images: Tensor, gains: Tensor) -> Tensor:
    """Each image's channels scaled by its own gains (B, C), clipped to [0, 1]."""
    return (images * gains[:, :, None, None]).clamp(0.0, 1.0)


def patch_swap(images: Tensor, sources: Tensor, boxes: list[tuple[int, int, int, int, int, int]]) -> Tensor:
    """Each image with a rectangle (h, w at y, x) replaced by the rectangle of another image at (y2, x2)."""
    out = images.clone()
    for i, (h, w, y, x, y2, x2) in enumerate(boxes):
        out[i, :, y : y + h, x : x + w] = sources[i, :, y2 : y2 + h, x2 : x2 + w]
    return out


def shift(images: Tensor, offsets: list[tuple[int, int]]) -> Tensor:
    """Each image translated by (dy, dx) pixels, the uncovered border black."""
    out = torch.zeros_like(images)
    height, width = images.shape[-2:]
    for i, (dy, dx) in enumerate(offsets):
        src_y, dst_y = slice(max(0, -dy), height - max(0, dy)), slice(max(0, dy), height - max(0, -dy))
        src_x, dst_x = slice(max(0, -dx), width - max(0, dx)), slice(max(0, dx), width - max(0, -dx))
        out[i, :, dst_y, dst_x] = images[i, :, src_y, src_x]
    return out


def random_conv(images: Tensor, kernels: Tensor) -> Tensor:
    """Each image (C, H, W) of (B, C, H, W) through its own (C, C, k, k) kernel of (B, C, C, k, k) (same padding,
    one grouped convolution), then min-max rescaled to [0, 1]: its colours remixed and its local texture
    filtered, its layout kept."""
    batch, channels, height, width = images.shape
    side = kernels.shape[-1]
    filtered = torch.nn.functional.conv2d(
        images.reshape(1, batch * channels, height, width),
        kernels.reshape(batch * channels, channels, side, side),
        padding=side // 2,
        groups=batch,
    ).view_as(images)
    low = filtered.amin(dim=(1, 2, 3), keepdim=True)
    high = filtered.amax(dim=(1, 2, 3), keepdim=True)
    return (filtered - low) / (high - low).clamp_min(1e-6)


def random_conv_kernels(batch_size: int, channels: int, generator: torch.Generator, ref: Tensor) -> Tensor:
    """One random kernel per observation, its side drawn from `RANDOM_CONV_KERNELS`, as (B, C, C, k_max, k_max):
    a smaller kernel sits zero-padded in the middle, which filters exactly as it would alone."""
    sides = torch.randint(len(RANDOM_CONV_KERNELS), (batch_size,), generator=generator, device=ref.device)
    largest = max(RANDOM_CONV_KERNELS)
    kernels = []
    for side in (RANDOM_CONV_KERNELS[i] for i in sides.tolist()):
        std = (channels * side * side) ** -0.5
        weight = torch.randn(
            (channels, channels, side, side), generator=generator, device=ref.device, dtype=ref.dtype
        )
        border = (largest - side) // 2
        kernels.append(torch.nn.functional.pad(std * weight, (border,) * 4))
    return torch.stack(kernels)


def shading(images: Tensor, log_gains: Tensor) -> Tensor:
    """Each image (C, H, W) times its own gain field exp(log_gains) (B, H, W), alike on every channel, clipped to
    [0, 1]."""
    return (images * log_gains.exp()[:, None]).clamp(0.0, 1.0)


def shading_log_gains(
    batch_size: int, height: int, width: int, generator: torch.Generator, ref: Tensor
) -> Tensor:
    """One smooth log-gain field (B, H, W) per observation: a linear ramp in a random direction plus one
    Gaussian blob, each of a random sign (the constants above)."""
    draws = torch.rand((batch_size, 8), generator=generator, device=ref.device, dtype=ref.dtype)
    theta, signs, magnitudes, sigma, centre = (
        draws[:, 0],
        draws[:, 1:3],
        draws[:, 3:5],
        draws[:, 5],
        draws[:, 6:],
    )
    signs = torch.where(signs < 0.5, -1.0, 1.0)
    low, high = LOG_GAIN_RANGE
    ramp, blob = (signs * (low + (high - low) * magnitudes)).unbind(1)
    sigma = SHADING_BLOB_RANGE[0] + (SHADING_BLOB_RANGE[1] - SHADING_BLOB_RANGE[0]) * sigma
    centre_y, centre_x = (2 * centre - 1).unbind(1)
    theta = 2 * torch.pi * theta
    y = torch.linspace(-1.0, 1.0, height, device=ref.device, dtype=ref.dtype)[None, :, None]
    x = torch.linspace(-1.0, 1.0, width, device=ref.device, dtype=ref.dtype)[None, None, :]
    along = x * theta.cos()[:, None, None] + y * theta.sin()[:, None, None]
    distance2 = (y - centre_y[:, None, None]) ** 2 + (x - centre_x[:, None, None]) ** 2
    pool = torch.exp(-distance2 / (2 * sigma[:, None, None] ** 2))
    return ramp[:, None, None] * along + blob[:, None, None] * pool


def corrupt_observation(
    batch: dict[str, Tensor],
    camera_keys: list[str],
    kinds: tuple[str, ...],
    generator: torch.Generator,
    state_key: str | None = None,
) -> dict[str, Tensor]:
    """A copy of `batch` in which each observation gets one corruption drawn uniformly from `kinds`.

    The image corruptions act on every camera of the observation alike; "state_noise" adds N(0, 1) to the
    normalized state (`state_key`). Other keys are shared with `batch`.
    """
    unknown = [kind for kind in kinds if kind not in CORRUPTIONS]
    if unknown or not kinds:
        raise ValueError(f"Corruptions must be a non-empty subset of {CORRUPTIONS}. Got {kinds}.")
    first = batch[camera_keys[0]]
    batch_size, (height, width) = first.shape[0], first.shape[-2:]
    device = first.device
    choice = torch.randint(len(kinds), (batch_size,), generator=generator, device=device).tolist()
    masks = {kind: torch.tensor([kinds[c] == kind for c in choice], device=device) for kind in kinds}
    # Every draw is made whether or not a kind is chosen, so that a batch's corruptions depend on the seed only.
    log_gains = _uniform(*LOG_GAIN_RANGE, (batch_size, first.shape[1]), generator, first)
    gain_signs = torch.randint(2, log_gains.shape, generator=generator, device=device) * 2 - 1
    gains = torch.exp(log_gains * gain_signs)
    sides = _uniform(*PATCH_RANGE, (batch_size, 2), generator, first)
    corners = torch.rand((batch_size, 4), generator=generator, device=device)
    boxes = []
    for (fh, fw), (a, b, c, d) in zip(sides.tolist(), corners.tolist(), strict=True):
        h, w = max(1, round(fh * height)), max(1, round(fw * width))
        boxes.append(
            (h, w, int(a * (height - h)), int(b * (width - w)), int(c * (height - h)), int(d * (width - w)))
        )
    magnitudes = _uniform(*SHIFT_RANGE, (batch_size, 2), generator, first)
    signs = torch.randint(2, (batch_size, 2), generator=generator, device=device) * 2 - 1
    offsets = [
        (round(my * sy * height), round(mx * sx * width))
        for (my, mx), (sy, sx) in zip(magnitudes.tolist(), signs.tolist(), strict=True)
    ]
    # Another observation of the batch for each one's patch: the batch is shuffled, so its neighbour is random.
    source_index = torch.roll(torch.arange(batch_size, device=device), 1)
    # Drawn last and only when asked for, so that the other kinds' draws stay those of the sets without it.
    kernels = (
        random_conv_kernels(batch_size, first.shape[1], generator, first) if "random_conv" in masks else None
    )
    fields = shading_log_gains(batch_size, height, width, generator, first) if "shading" in masks else None

    out = dict(batch)
    for key in camera_keys:
        images = batch[key]
        corrupted = images
        if "channel_gain" in masks:
            corrupted = torch.where(
                masks["channel_gain"][:, None, None, None], channel_gain(images, gains), corrupted
            )
        if "patch_swap" in masks:
            swapped = patch_swap(images, images[source_index], boxes)
            corrupted = torch.where(masks["patch_swap"][:, None, None, None], swapped, corrupted)
        if "shift" in masks:
            corrupted = torch.where(masks["shift"][:, None, None, None], shift(images, offsets), corrupted)
        if kernels is not None:
            convolved = random_conv(images, kernels)
            corrupted = torch.where(masks["random_conv"][:, None, None, None], convolved, corrupted)
        if fields is not None:
            shaded = shading(images, fields)
            corrupted = torch.where(masks["shading"][:, None, None, None], shaded, corrupted)
        out[key] = corrupted
    if "state_noise" in masks and state_key is not None and state_key in batch:
        state = batch[state_key]
        noise = STATE_NOISE_STD * torch.randn(
            state.shape, generator=generator, device=device, dtype=state.dtype
        )
        out[state_key] = torch.where(masks["state_noise"][:, None], state + noise, state)
    return out


def blend(clean: Tensor, corrupted: Tensor, strengths: Tensor) -> Tensor:
    """o + s (o~ - o) for each observation: its strength s of (B,) over all its other dimensions."""
    return torch.lerp(clean, corrupted, strengths.to(clean.dtype).view(-1, *([1] * (clean.dim() - 1))))


def graded_corruption(
    batch: dict[str, Tensor],
    camera_keys: list[str],
    kinds: tuple[str, ...],
    generator: torch.Generator,
    state_key: str | None = None,
    strength_range: tuple[float, float] = (1.0, 1.0),
) -> tuple[dict[str, Tensor], Tensor | None]:
    """`corrupt_observation`, each observation then moved only a fraction s of the way to its corrupted copy,

        o~_s = o + s (o~ - o),    s ~ U(strength_range) per observation,

    on its images and state alike, with the strengths s (B,) to scale its margin by (`energy_margin_loss`).

    Why (a hypothesis, research/docs/energy_study.md section 8.7): a hinge met on full corruptions, far from the data,
    asks nothing of the energy near the data, where mild shifts sit; a margin s m on an observation moved by s
    asks for an energy that rises with how far, not only whether. Measured there on three training seeds: it
    sees mild blur and noise on two and puts light direction confidently under the data on the third, so it is
    off by default. `strength_range=(1, 1)` returns the corruption itself and no strengths, its draws exactly
    those of `corrupt_observation`.
    """
    corrupted = corrupt_observation(batch, camera_keys, kinds, generator, state_key)
    if tuple(strength_range) == (1.0, 1.0):
        return corrupted, None
    ref = batch[camera_keys[0]]
    strengths = _uniform(*strength_range, (ref.shape[0],), generator, ref)
    blended = dict(corrupted)
    for key in [*camera_keys, state_key]:
        if key is not None and key in batch:
            blended[key] = blend(batch[key], corrupted[key], strengths)
    return blended, strengths


def energy_margin_loss(clean_energy: Tensor, corrupted_energy: Tensor, margin: float | Tensor) -> Tensor:
    """mean_i max(0, m_i - (E(a*_i, C~_i) - E(a*_i, C_i))): zero once every corrupted context costs its m_i
    more (`margin` one m for all, or (B,) margins)."""
    gap = corrupted_energy.float() - clean_energy.float()
    return torch.relu(margin - gap).mean()


def data_gradient_penalty(energy: Tensor, images: list[Tensor]) -> Tensor:
    """mean_i sum_x ||d E_i / d x||^2 over each observation's images (R1, Mescheder et al., ICML 2018), kept in
    the graph so that training flattens the energy at the data; `images` must be inputs of `energy`'s graph
    that require grad, one (B, ...) tensor per camera."""
    grads = torch.autograd.grad(energy.float().sum(), images, create_graph=True)
    return sum(g.float().pow(2).flatten(1).sum(dim=1) for g in grads).mean()


class EBVLAContextEnergy(nn.Module):
    """E_c(C): a scalar energy of the pooled context, added to the head's final energy (a joint energy
    E(a, C) + E_c(C), `energy_ood_margin_on="context"`, `"context_backbone"` or `"observation"`). It has no
    gradient in a, so the MCMC refinement and its energy-scaled steps are those of the head alone."""

    def __init__(self, dim: int):
        super().__init__()
        self.net = nn.Sequential(nn.LayerNorm(dim), nn.Linear(dim, dim), nn.SiLU(), nn.Linear(dim, 1))

    def forward(self, features: Tensor) -> Tensor:
        """(B, D) pooled contexts -> (B,) energies."""
        return self.net(features.float()).squeeze(-1)


def contrastive_in_bf16(config: EBVLAConfig, device_type: str) -> bool:
    """Whether the contrastive term's head pass runs under bf16 autocast (`energy_contrastive_dtype`)."""
    if config.energy_contrastive_dtype == "auto":
        return native_bf16(device_type)
    return config.energy_contrastive_dtype == "bfloat16"


@functools.cache
def native_bf16(device_type: str) -> bool:
    """Whether `device_type` multiplies bf16 matrices in hardware: a CUDA GPU that supports bf16, or a CPU
    with AVX512-BF16 or AMX tiles (elsewhere oneDNN emulates bf16, slower than fp32)."""
    if device_type == "cuda":
        return torch.cuda.is_available() and torch.cuda.is_bf16_supported()
    if device_type == "cpu":
        # Private torch names: getattr, so that a torch without them reads as "no native bf16".
        probes = ("_is_avx512_bf16_supported", "_is_amx_tile_supported")
        return any(getattr(torch.cpu, probe, lambda: False)() for probe in probes)
    return False
