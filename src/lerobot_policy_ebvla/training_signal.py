"""The training loss: the paper's Eq. 4 (`compute_loss`) and the signals beyond it, the contrastive ranking
(`contrastive_energy_loss`) and outlier exposure for the energy (issue 32: `ood_margin_loss` on the head,
`context_margin_loss` on the joint energy's E_c).

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
from lerobot.utils.constants import ACTION, OBS_STATE
from torch import Tensor, nn
from torch.nn.attention import SDPBackend, sdpa_kernel

from .compile_ebvla import begin_compiled_training_step, compiled_context, compiled_energy_fn
from .configuration_ebvla import EBVLAConfig
from .configuration_groups import OOD_CORRUPTIONS as CORRUPTIONS
from .energy_head import ContextKV, pooled_context

ACTION_IS_PAD = "action_is_pad"

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
    E(a, C) + E_c(C), `joint_energy.target="context"`, `"context_backbone"` or `"observation"`). It has no
    gradient in a, so the MCMC refinement and its energy-scaled steps are those of the head alone."""

    def __init__(self, dim: int):
        super().__init__()
        self.net = nn.Sequential(nn.LayerNorm(dim), nn.Linear(dim, dim), nn.SiLU(), nn.Linear(dim, 1))

    def forward(self, features: Tensor) -> Tensor:
        """(B, D) pooled contexts -> (B,) energies."""
        return self.net(features.float()).squeeze(-1)


def contrastive_in_bf16(config: EBVLAConfig, device_type: str) -> bool:
    """Whether the contrastive term's head pass runs under bf16 autocast (`contrastive.dtype`)."""
    if config.contrastive.dtype == "auto":
        return native_bf16(device_type)
    return config.contrastive.dtype == "bfloat16"


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


# The training loss. `model` is the core `modeling_ebvla.EBVLA` (backbone, head, optional joint energy); these
# functions take it rather than living on it, so that the network's module holds the network and this one
# everything training adds to Eq. 4.


def training_generator(model: nn.Module, device: torch.device) -> torch.Generator:
    """A generator for one training step of `model`, seeded by its saved `mcmc_seed` and `train_steps` buffers (a
    resumed run draws what an uninterrupted one would); ranks of a multi-process run get different streams."""
    rank = torch.distributed.get_rank() if torch.distributed.is_initialized() else 0
    seed = (
        int(model.mcmc_seed) * 6364136223846793005 + int(model.train_steps) * 1442695040888963407 + rank
    ) % 2**63
    model.train_steps += 1
    return torch.Generator(device=device).manual_seed(seed)


def sample_training_step_sizes(config: EBVLAConfig, generator: torch.Generator) -> list[float]:
    """The step sizes alpha^(k) of one training chain: K ~ U{K_min..K_max} of them, alpha ~ U[alpha_min, alpha_max]
    drawn once for the chain ("per_chain") or for every step ("per_mcmc_step")."""
    k_min, k_max = config.train_mcmc_steps_range
    device = generator.device
    num_steps = int(torch.randint(k_min, k_max + 1, (1,), generator=generator, device=device).item())
    num_alphas = 1 if config.train_step_size_sampling == "per_chain" else num_steps
    alpha_min, alpha_max = config.train_step_size_range
    alphas = alpha_min + (alpha_max - alpha_min) * torch.rand(num_alphas, generator=generator, device=device)
    return alphas.expand(num_steps).tolist()


def compute_loss(
    model: nn.Module, batch: dict[str, Tensor], generator: torch.Generator | None = None
) -> tuple[Tensor, dict]:
    """Training: K ~ U[K_min, K_max] steps with alpha ~ U[alpha_min, alpha_max], L1 on a^(K) (Eq. 4), plus the
    opt-in terms of `model.config` (the contrastive ranking, the joint energy's margin).

    Without a `generator`, the randomness comes from `training_generator`. Only the last step is
    differentiated (second order, through grad_a E); the earlier ones see a detached context, so they build no
    graph into the backbone. With `train_compile_mode`, the backbone pass and those earlier steps run compiled
    (`compile_ebvla.py`) and draw the same numbers from `generator`.
    """
    cfg = model.config
    target = batch[ACTION]
    # The joint energy's margin reads the pooled context of this same backbone pass.
    return_features = model.context_energy is not None and model.observation_encoder is None
    if cfg.train_compile_mode == "off":
        encoded = model.encode_context(batch, return_features)
    else:
        begin_compiled_training_step(model)
        encoded = compiled_context(model, batch, return_features, cfg.train_compile_mode)
    kv, clean_features = encoded if return_features else (encoded, None)
    if generator is None:
        generator = training_generator(model, target.device)
    step_sizes = sample_training_step_sizes(cfg, generator)
    num_steps = len(step_sizes)

    # a^(0) and the refinement are fp32 even in a bf16 policy; the L1 loss is taken in float32.
    actions = model.initial_actions(target.shape[0], kv[0][0], generator)
    initial_energy = None
    if num_steps > 1:
        detached_kv = [(k.detach(), v.detach()) for k, v in kv]
        energy_fn = None
        if cfg.train_compile_mode != "off":
            energy_fn = compiled_energy_fn(model.head, detached_kv, cfg.train_compile_mode)
        warmup = model.refine(detached_kv, actions, step_sizes[:-1], generator, energy_fn=energy_fn)
        actions, initial_energy = warmup.actions, warmup.step_energies[0]
    # CPU (and fused GPU) attention kernels have no double backward; the math kernel does.
    with sdpa_kernel(SDPBackend.MATH):
        last = model.refine(
            kv,
            actions,
            step_sizes[-1:],
            generator,
            create_graph=True,
            straight_through_clip=cfg.train_straight_through_clip,
        )
    if initial_energy is None:
        initial_energy = last.step_energies[0]

    l1 = (last.actions.float() - target.float()).abs()  # (B, H, d_a)
    if ACTION_IS_PAD in batch:
        valid = (~batch[ACTION_IS_PAD]).unsqueeze(-1).to(l1.dtype)  # (B, H, 1)
        loss = (l1 * valid).sum() / (valid.sum() * l1.shape[-1]).clamp(min=1)
    else:
        loss = l1.mean()
    info = {
        "l1_loss": loss.item(),
        "mcmc_steps": num_steps,
        "initial_energy": initial_energy.mean().item(),
        "last_step_energy": last.step_energies[-1].mean().item(),
    }
    if cfg.contrastive.weight > 0:
        contrastive = contrastive_energy_loss(model, kv, target, generator)
        loss = loss + cfg.contrastive.weight * contrastive
        info["contrastive_loss"] = contrastive.item()
    if model.context_energy is not None:
        margin_loss, gap = context_margin_loss(model, batch, generator, clean_features)
        loss = loss + cfg.joint_energy.weight * margin_loss
        info["ood_margin_loss"], info["ood_energy_gap"] = margin_loss.item(), gap
    elif cfg.joint_energy.weight > 0:
        chunk = target if cfg.joint_energy.chunk == "expert" else last.actions.detach()
        margin_loss, gap = ood_margin_loss(model, batch, kv, chunk, generator, step_sizes)
        loss = loss + cfg.joint_energy.weight * margin_loss
        info["ood_margin_loss"], info["ood_energy_gap"] = margin_loss.item(), gap
    return loss, info


def context_margin_loss(
    model: nn.Module,
    batch: dict[str, Tensor],
    generator: torch.Generator,
    clean_features: Tensor | None = None,
) -> tuple[Tensor, float]:
    """The margin on the context energy E_c of the joint energy E(a, C) + E_c(C), on the pooled backbone
    contexts of the batch (`clean_features` where the caller's backbone pass has them) and of its corrupted
    copy, plus E_c(C)^2 on the data (the hinge leaves E_c's level free), plus the gradient penalty on E_c at
    the real images where `joint_energy.gradient_penalty` > 0, on the training steps whose count is a multiple of
    `joint_energy.gradient_penalty_every` (the training log's `ood_margin_loss` is the sum).

    `joint_energy.target="context"` detaches both contexts: the backbone and head train as without the
    term. "context_backbone" lets the margin's gradient into the backbone. "observation" reads the contexts
    of the observation encoder, which the margin alone trains.
    """
    cfg = model.config
    corrupted_batch, margin = _corrupted_copy(cfg, batch, generator)
    if model.observation_encoder is not None:
        every = cfg.joint_energy.gradient_penalty_every
        penalized = cfg.joint_energy.gradient_penalty > 0 and int(model.train_steps) % every == 0
        images = {key: batch[key].detach().requires_grad_(penalized) for key in cfg.image_features}
        clean_features = pooled_context(model.observation_encoder({**batch, **images}))
        corrupted_features = pooled_context(model.observation_encoder(corrupted_batch))
        loss, gap, clean = _context_margin(model.context_energy, clean_features, corrupted_features, margin)
        if penalized:
            # Lazy regularization: one step in `every` carries the penalty of all of them.
            penalty = data_gradient_penalty(clean, list(images.values()))
            loss = loss + every * cfg.joint_energy.gradient_penalty * penalty
        return loss, gap
    through_backbone = cfg.joint_energy.target == "context_backbone"
    with torch.set_grad_enabled(through_backbone):
        if clean_features is None:
            clean_features = pooled_context(model.backbone(batch))
        corrupted_features = pooled_context(model.backbone(corrupted_batch))
    if not through_backbone:
        clean_features = clean_features.detach()
    loss, gap, _ = _context_margin(model.context_energy, clean_features, corrupted_features, margin)
    return loss, gap


def _corrupted_copy(
    cfg: EBVLAConfig, batch: dict[str, Tensor], generator: torch.Generator
) -> tuple[dict[str, Tensor], float | Tensor]:
    """The batch's corrupted copy and the margin each corrupted observation must clear: m, or s m at
    strength s (`joint_energy.corruption_strength`)."""
    corrupted_batch, strengths = graded_corruption(
        batch,
        list(cfg.image_features),
        cfg.joint_energy.corruptions,
        generator,
        state_key=OBS_STATE,
        strength_range=cfg.joint_energy.corruption_strength,
    )
    margin = cfg.joint_energy.margin if strengths is None else cfg.joint_energy.margin * strengths.float()
    return corrupted_batch, margin


def _context_margin(
    context_energy: nn.Module, clean_features: Tensor, corrupted_features: Tensor, margin: float | Tensor
) -> tuple[Tensor, float, Tensor]:
    """The margin's loss, its mean gap and the clean observations' E_c(C), (B,)."""
    clean, shifted = context_energy(clean_features), context_energy(corrupted_features)
    loss = energy_margin_loss(clean, shifted, margin) + clean.float().pow(2).mean()
    return loss, (shifted - clean).mean().item(), clean


def ood_margin_loss(
    model: nn.Module,
    batch: dict[str, Tensor],
    kv: ContextKV,
    chunk: Tensor,
    generator: torch.Generator,
    step_sizes: list[float],
) -> tuple[Tensor, float]:
    """`energy_margin_loss` on the head's energy under corrupted copies of the batch's observations, and the mean
    energy gap it acts on.

    `joint_energy.chunk="expert"`: E(a*, C~) against E(a*, C), `chunk` being a*. "refined": the energy
    of the chunk refined under C~ (the same a^(0) and step sizes as the training chain, no graph) against
    that of the training chain's own refined chunk `chunk` under C, so that min_a E(a, C~) rises.
    """
    cfg = model.config
    corrupted_batch, margin = _corrupted_copy(cfg, batch, generator)
    corrupted_kv = model.encode_context(corrupted_batch)
    corrupted_chunk = chunk
    if cfg.joint_energy.chunk == "refined":
        initial = model.initial_actions(chunk.shape[0], kv[0][0], generator)
        detached_kv = [(k.detach(), v.detach()) for k, v in corrupted_kv]
        corrupted_chunk = model.refine(detached_kv, initial, step_sizes, generator).actions.detach()
    clean = model.head(chunk, kv).mean(dim=-1)
    shifted = model.head(corrupted_chunk, corrupted_kv).mean(dim=-1)
    loss = energy_margin_loss(clean, shifted, margin)
    return loss, (shifted - clean).mean().item()


def contrastive_energy_loss(
    model: nn.Module, kv: ContextKV, target: Tensor, generator: torch.Generator
) -> Tensor:
    """InfoNCE over chunks: under each context C_i, the expert chunk a*_i must have the lowest energy.

    Candidates for C_i are a*_i (the positive), other observations' expert chunks a*_j (a mismatched
    action for this context; `contrastive.mismatched` of them, all B - 1 by default) and noisy
    copies a*_i + sigma n (a nearby worse action), so that E(a, C) ranks how well a chunk fits its context
    rather than only shaping the descent direction.
    """
    cfg = model.config
    batch_size = target.shape[0]
    mismatched = batch_size - 1
    if cfg.contrastive.mismatched is not None:
        mismatched = min(mismatched, cfg.contrastive.mismatched)
    anchors = batch_size
    if cfg.contrastive.anchors is not None:
        anchors = min(anchors, cfg.contrastive.anchors)
    noise = torch.randn(
        (anchors, cfg.contrastive.negatives, *target.shape[1:]),
        generator=generator,
        device=target.device,
        dtype=target.dtype,
    )
    noisy = target[:anchors].unsqueeze(1) + cfg.contrastive.noise_std * noise  # (A, N_noisy, H, d_a)
    # Row i: a*_i first (the positive), then a*_{i+1}, ..., a*_{i+M} (mismatched; the batch is shuffled, so
    # these are random other observations), then the noisy copies.
    rows = torch.arange(batch_size, device=target.device)
    order = (rows[:anchors, None] + rows[None, : 1 + mismatched]) % batch_size  # (A, 1 + M)
    candidates = torch.cat([target[order], noisy], dim=1)  # (A, 1 + M + N_noisy, H, d_a)
    num_candidates = candidates.shape[1]
    anchor_kv = kv if anchors == batch_size else [(k[:anchors], v[:anchors]) for k, v in kv]
    device_type = target.device.type
    with torch.autocast(device_type, torch.bfloat16, enabled=contrastive_in_bf16(cfg, device_type)):
        energies = model.head(candidates.flatten(0, 1), anchor_kv).mean(dim=-1)
    logits = -energies.view(anchors, num_candidates).float() / cfg.contrastive.temperature
    return nn.functional.cross_entropy(logits, torch.zeros(anchors, dtype=torch.long, device=target.device))
