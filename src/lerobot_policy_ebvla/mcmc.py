"""MCMC refinement of action chunks by gradient descent on the learned energy (paper Sec. II-C, Eq. 2-3).

One step k, for a chunk a^(k) in R^{H x d_a}:

    eps^(k) ~ N(0, sigma_L^2 I)
    e^(k)   = E_theta(a^(k) + eps^(k), C)              per-timestep energies, (B, H)
    g^(k)   = clip(grad_a mean_t e_t^(k), -c, c)       Eq. 2: gradient at the perturbed point, element-wise clip
    a_t^(k+1) = clamp(a_t^(k) - alpha^(k) exp(e_t^(k) / tau) g_t^(k), -a_max, a_max)     Eq. 3

Every step starts from a detached a^(k), so gradients only ever flow within one step: at inference this keeps
memory flat in K, and in training it is the paper's "detach the graph at every step except the last"
(the caller asks for `create_graph=True` on the last step only).

In training the loss reaches the energy's parameters (and through them the backbone) only through that last
step's update alpha exp(e_t / tau) clip(g, -c, c). Where the clip is active its derivative is zero, so the
direction g carries no learning signal there and only the step length exp(e_t / tau) does. `straight_through_clip`
keeps the clipped value in the forward pass and lets the backward pass treat the clip as the identity.

Real-time chunking (RTC) refines the next chunk as inpainting on the same landscape. The robot keeps executing
the previous chunk while this one is refined; its unexecuted actions are the prefix abar, (B, H, d_a). The
first d of them run before this chunk can arrive, so they are held; the rest of the overlap is pulled towards
abar with weights w_t in [0, 1] (LeRobot's prefix-attention schedule: 1 before d, decaying to 0 at the
execution horizon) and a guidance weight lambda. After every update of Eq. 3:

    a_t^(k+1) <- a_t^(k+1) - min(1, alpha^(k) lambda w_t) (a_t^(k+1) - abar_t)     guidance
    a_t^(k+1) <- abar_t  for t < d, and likewise in a^(0)                          hold

The guidance is a gradient step of size alpha^(k) on (lambda / 2) w_t ||a_t - abar_t||^2, taken apart from
the energy's step so that neither the clip c nor the scale exp(e_t / tau) bends it, and capped so that it never
overshoots abar. The held actions take part in every energy evaluation (the head attends over the whole chunk,
so the continuation is refined in their context) but no update moves them. The energies are those of
E_theta, never of the guidance term.
"""

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

# Maps action chunks (B, H, d_a) to per-timestep energies e_t (B, H); the context is bound inside.
EnergyFn = Callable[[Tensor], Tensor]


@dataclass
class RTCPrefix:
    """The previous chunk's leftover that real-time chunking inpaints (the `prefix` of `refine_actions`).

    Attributes:
        actions: abar, (B, H, d_a): the leftover aligned with this chunk's timesteps (entries where the weights
            are 0 and t >= d are not read).
        held_steps: d: the first d actions are abar's in a^(0) and after every step.
        weights: w_t, (H,) or (B, H), in [0, 1]: LeRobot's prefix-attention schedule, 0 past the guided overlap;
            None holds only.
        guidance_weight: lambda of the pull towards abar.
    """

    actions: Tensor
    held_steps: int
    weights: Tensor | None = None
    guidance_weight: float = 0.0


@dataclass
class RefinementResult:
    """What `refine_actions` returns.

    Attributes:
        actions: The refined chunk a^(K), (B, H, d_a).
        step_energies: E(a^(k) + eps^(k), C) at every step k that ran, (K, B). Row 0 is the initial energy.
        diverged: (B,) True where a non-finite energy or gradient appeared; such a chunk kept its last
            finite iterate from then on.
    """

    actions: Tensor
    step_energies: Tensor
    diverged: Tensor

    @property
    def num_steps(self) -> int:
        return self.step_energies.shape[0]


def sample_initial_actions(
    shape: tuple[int, ...],
    init_std: float,
    *,
    device: torch.device | str,
    dtype: torch.dtype = torch.float32,
    generator: torch.Generator | None = None,
) -> Tensor:
    """Draws a^(0) ~ N(0, sigma_init^2 I)."""
    return init_std * torch.randn(shape, device=device, dtype=dtype, generator=generator)


def draw_langevin_noise(num_steps: int, actions: Tensor, generator: torch.Generator | None = None) -> Tensor:
    """Draws the standard normal noise of `num_steps` steps for chunks shaped like `actions`: (K, B, H, d_a).

    One draw per step, in step order: the same numbers `refine_actions` draws itself from the same generator,
    so a chain given them (its `noise`) is the chain that drew its own.
    """
    return torch.stack(
        [
            torch.randn(actions.shape, device=actions.device, dtype=actions.dtype, generator=generator)
            for _ in range(num_steps)
        ]
    )


def refine_actions(
    energy_fn: EnergyFn,
    initial_actions: Tensor,
    step_sizes: Sequence[float],
    *,
    temperature: float,
    langevin_std: float,
    grad_clip: float,
    action_clamp: float,
    generator: torch.Generator | None = None,
    create_graph: bool = False,
    early_stop_tol: float | None = None,
    straight_through_clip: bool = False,
    prefix: RTCPrefix | None = None,
    noise: Tensor | None = None,
) -> RefinementResult:
    """Runs len(step_sizes) energy-scaled gradient steps (Eq. 2-3) from `initial_actions`.

    Args:
        energy_fn: Per-timestep energies e_t of a chunk under a fixed context.
        initial_actions: a^(0), (B, H, d_a). Used detached.
        step_sizes: The base step size alpha^(k) of each step; its length is the number of steps K.
        temperature: tau of the energy scaling exp(e_t / tau).
        langevin_std: sigma_L of the perturbation at which the gradient is taken.
        grad_clip: c of the element-wise gradient clip.
        action_clamp: a_max of the clamp applied after every update.
        generator: Seeds the Langevin noise.
        create_graph: Keep each step's update differentiable with respect to the energy's parameters
            (second-order training). Gradients never flow from one step into the previous one.
        early_stop_tol: Stop once no action entry moved more than this in a step. None runs every step.
        straight_through_clip: With `create_graph`, differentiate the clip as the identity (same forward
            values); without it the clip passes no gradient wherever |g| > c.
        prefix: RTC's previous chunk to inpaint: abar, d, w_t and lambda (`RTCPrefix`). None refines from
            scratch.
        noise: The standard normal draws of every step, (K, B, H, d_a) (`draw_langevin_noise`), scaled by
            sigma_L here; None draws them from `generator` step by step. Given, and without `early_stop_tol`
            (a stop decided on the host), nothing in the loop reads the generator or waits for the device, so a
            CUDA graph can capture the whole chain (`compile_ebvla.RefinementGraphs`).

    Returns:
        The refined chunk, the energy seen at every step and which chunks diverged.
    """
    a = initial_actions.detach()
    abar = None
    if prefix is not None:
        if prefix.actions.shape != a.shape or not 0 <= prefix.held_steps <= a.shape[1]:
            raise ValueError(
                f"`prefix.actions` must have the chunk's shape {tuple(a.shape)} and `prefix.held_steps` be in "
                f"[0, {a.shape[1]}]. Got {tuple(prefix.actions.shape)} and {prefix.held_steps}."
            )
        abar, guidance_weight = prefix.actions.detach().to(a.dtype), prefix.guidance_weight
        held = (torch.arange(a.shape[1], device=a.device) < prefix.held_steps).unsqueeze(-1)  # (H, 1)
        weights = torch.zeros(a.shape[1], device=a.device) if prefix.weights is None else prefix.weights
        weights = weights.to(a.device, a.dtype).unsqueeze(-1)  # w_t, (H, 1) or (B, H, 1)
        a = torch.where(held, abar, a)
    if noise is not None and noise.shape != (len(step_sizes), *a.shape):
        raise ValueError(
            f"`noise` must hold one draw per step, shaped {(len(step_sizes), *a.shape)}; got {tuple(noise.shape)}."
        )
    diverged = torch.zeros(a.shape[0], dtype=torch.bool, device=a.device)
    step_energies = []
    for k, alpha in enumerate(step_sizes):
        with torch.enable_grad():
            a = a.detach().requires_grad_(True)
            if noise is None:
                eps = torch.randn(a.shape, device=a.device, dtype=a.dtype, generator=generator)
            else:
                eps = noise[k]
            e = energy_fn(a + langevin_std * eps)  # (B, H)
            energy = e.mean(dim=-1)  # E(a, C), (B,)
            # Chunks are independent, so the gradient of the batch sum is each chunk's own gradient.
            (grad,) = torch.autograd.grad(energy.sum(), a, create_graph=create_graph)
        with torch.set_grad_enabled(create_graph):
            if not create_graph:
                e, grad = e.detach(), grad.detach()
            clipped = grad.clamp(-grad_clip, grad_clip)
            if straight_through_clip:
                clipped = grad + (clipped - grad).detach()
            step = alpha * torch.exp(e / temperature).unsqueeze(-1) * clipped
            updated = (a - step).clamp(-action_clamp, action_clamp)
            if abar is not None:
                pull = (alpha * guidance_weight * weights).clamp(max=1.0)
                updated = torch.where(held, abar, updated - pull * (updated - abar))
            finite = torch.isfinite(energy) & torch.isfinite(grad).flatten(1).all(dim=1)
            finite &= torch.isfinite(updated).flatten(1).all(dim=1)
            # A chunk whose energy or gradient went non-finite keeps its last finite iterate.
            updated = torch.where(finite[:, None, None], updated, a.detach())
        diverged |= ~finite
        step_energies.append(energy.detach())
        moved = (updated - a).detach().abs().amax() if early_stop_tol is not None else None
        a = updated
        if moved is not None and moved < early_stop_tol:
            break
    if not create_graph:
        a = a.detach()
    return RefinementResult(actions=a, step_energies=torch.stack(step_energies), diverged=diverged)
