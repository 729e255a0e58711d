"""The cells `bench_speed.py` times: each policy's new chunk and training step, and the energy head alone.

The head cells time `EBVLA.generate_actions` with the backbone's output cached (`CachedContext` stands in for
the backbone), against the floor the refinement math needs, and, with `--variants`, inference variants that
must not change the actions. The compiled variant is the policy's own `compile_mode` path (named
`compiled_detached` in runs before `compile_mode` replaced `compile_refinement`).
"""

import contextlib
from collections.abc import Callable

import torch
from lerobot.utils.constants import OBS_STATE
from torch import Tensor, nn
from torch.nn.attention import SDPBackend, sdpa_kernel

from lerobot_policy_ebvla import EBVLAPolicy
from lerobot_policy_ebvla.compile_ebvla import head_energy

from .inputs import Scene
from .timing import Cell


def policy_cells(name: str, policy: nn.Module, scene: Scene, args, device: torch.device) -> list[Cell]:
    """New-chunk cells for each batch size and one training-step cell."""
    cells = []
    for b in args.batch_sizes:
        obs = scene.observation(b, device)

        def new_chunk(obs=obs):
            with torch.inference_mode():
                return policy.select_action(dict(obs))

        cells.append(
            Cell(
                f"{name}/chunk_b{b}",
                new_chunk,
                setup=lambda: (policy.eval(), policy.reset()),
                group="chunk",
                meta={"policy": name, "batch": b},
            )
        )
    batch = scene.training_batch(args.train_batch_size, device)
    if name.startswith("diffusion"):
        batch[OBS_STATE] = batch[OBS_STATE].unsqueeze(1)  # (B, n_obs_steps = 1, state_dim)
    optimizer = policy.config.get_optimizer_preset().build(list(policy.get_optim_params()))
    clip = policy.config.get_optimizer_preset().grad_clip_norm
    seeds = iter(range(10**6))

    def setup_train():
        policy.train()
        # Diffusion's noise and timesteps come from the global RNG (EB-VLA's K ~ U[K_min, K_max] from its own
        # generator, seeded at construction): seeding each step keeps re-runs comparable.
        torch.manual_seed(next(seeds))

    def train_step():
        optimizer.zero_grad(set_to_none=True)
        loss, _ = policy.forward(dict(batch))
        loss.backward()
        torch.nn.utils.clip_grad_norm_(policy.parameters(), clip)
        optimizer.step()

    cells.append(
        Cell(
            f"{name}/train_b{args.train_batch_size}",
            train_step,
            setup=setup_train,
            group="train",
            meta={"policy": name, "batch": args.train_batch_size},
        )
    )
    return cells


class CachedContext(nn.Module):
    """Stands in for the backbone: returns fixed per-block contexts, so only the head's work is timed."""

    def __init__(self, contexts: list[Tensor]):
        super().__init__()
        self.contexts = contexts

    def forward(self, batch: dict[str, Tensor]) -> list[Tensor]:
        return self.contexts


@contextlib.contextmanager
def swapped(owner: object, **replacements):
    """Sets attributes of `owner` (a submodule, a config field) for the duration, then restores each."""
    originals = {name: getattr(owner, name) for name in replacements}
    for name, value in replacements.items():
        setattr(owner, name, value)
    try:
        yield
    finally:
        for name, value in originals.items():
            setattr(owner, name, value)


@contextlib.contextmanager
def frozen_parameters(module: nn.Module):
    """requires_grad_(False) on every parameter for the duration, then restores each flag."""
    flags = [(p, p.requires_grad) for p in module.parameters()]
    for p, _ in flags:
        p.requires_grad_(False)
    try:
        yield
    finally:
        for p, flag in flags:
            p.requires_grad_(flag)


class DetachedParamsHead(nn.Module):
    """The energy head evaluated with detached parameters in eager mode (`compile_ebvla.head_energy`).

    Autograd then records only the path from the actions. This is the energy `compile_mode` compiles, timed
    here uncompiled to tell the two effects apart.
    """

    def __init__(self, head: nn.Module):
        super().__init__()
        self.head = head

    def context_kv(self, contexts):
        return self.head.context_kv(contexts)

    def forward(self, actions: Tensor, kv) -> Tensor:
        if not torch.is_grad_enabled():
            return self.head(actions, kv)  # the final-energy forward: nothing to differentiate
        params = {k: v.detach() for k, v in self.head.named_parameters()}
        params.update(self.head.named_buffers())
        return head_energy(self.head, params, actions, kv)


def head_contexts(policy: EBVLAPolicy, scene: Scene, b: int, tokens: int | None, device) -> list[Tensor]:
    """The backbone's real output (tokens None) or random VLM-sized contexts of `tokens` tokens per block."""
    if tokens is None:
        with torch.no_grad():
            return [c.detach() for c in policy.model.backbone(scene.observation(b, device))]
    g = torch.Generator().manual_seed(b)
    dim = policy.model.head.blocks[0].cross_attn.kv.in_features
    return [torch.randn(b, tokens, dim, generator=g).to(device) for _ in policy.model.head.blocks]


def floor_fn(head: nn.Module, contexts: list[Tensor], chunk: int, action_dim: int, steps: int, alpha: float):
    """The minimum the refinement math needs: kv once, then K x (forward, grad w.r.t. the actions, update)."""
    b, device = contexts[0].shape[0], contexts[0].device

    def run():
        with torch.no_grad():
            kv = head.context_kv(contexts)
        a = torch.randn(b, chunk, action_dim, device=device)
        for _ in range(steps):
            a = a.detach().requires_grad_(True)
            (grad,) = torch.autograd.grad(head(a, kv).mean(dim=-1).sum(), a)
            a = a - alpha * grad
        return a.detach()

    return run


def head_cells(name: str, policy: EBVLAPolicy, scene: Scene, args, device) -> list[Cell]:
    """Floor and actual refinement per (context size, batch), plus the `--variants` cells.

    A variant cell carries the default refinement as its `reference`: after timing, both run once from the
    same seed and the largest differences of their actions and energies are recorded.
    """
    model, cfg = policy.model, policy.config
    policy.eval()
    token_options = [None] + (
        [args.vlm_context_tokens] if name == "ebvla-paper" and args.vlm_context_tokens else []
    )
    fused = SDPBackend.FLASH_ATTENTION if device.type == "cpu" else SDPBackend.EFFICIENT_ATTENTION
    wrappers: dict[str, Callable[[], contextlib.AbstractContextManager]] = {
        "frozen_params": lambda: frozen_parameters(model.head),
        "detached_params": lambda: swapped(model, head=DetachedParamsHead(model.head)),
        "sdpa_math": lambda: sdpa_kernel(SDPBackend.MATH),
        f"sdpa_{fused.name.lower()}": lambda: sdpa_kernel(fused),
    }
    if args.compile:
        # The policy's own compiled chunk; `--compile-mode` was checked against the config's modes. With the
        # backbone's output cached, what it compiles is the key/value projection and the MCMC steps' energy.
        wrappers["compiled_chunk"] = lambda: swapped(cfg, compile_mode=args.compile_mode)
    cells = []
    for tokens in token_options:
        for b in args.batch_sizes:
            contexts = head_contexts(policy, scene, b, tokens, device)
            stub, obs = CachedContext(contexts), scene.observation(b, device)
            meta = {"policy": name, "batch": b, "context_tokens": contexts[0].shape[1]}
            prefix = f"{name}/head_S{meta['context_tokens']}_b{b}"

            def refine(wrap=contextlib.nullcontext, stub=stub, obs=obs):
                with swapped(model, backbone=stub), wrap():
                    return model.generate_actions(obs)

            floor = floor_fn(
                model.head,
                contexts,
                cfg.chunk_size,
                cfg.action_dim,
                cfg.inference_mcmc_steps,
                cfg.inference_step_size,
            )
            for variant, fn in (("floor", floor), ("actual", refine)):
                variant_meta = {**meta, "variant": variant}
                cells.append(
                    Cell(f"{prefix}/{variant}", fn, setup=policy.eval, group="head", meta=variant_meta)
                )
            if not args.variants:
                continue
            with torch.no_grad():
                kv = model.head.context_kv(contexts)
            zeros = torch.zeros(b, cfg.chunk_size, cfg.action_dim, device=device)
            cells.append(
                Cell(
                    f"{prefix}/final_energy_forward_only",
                    lambda kv=kv, zeros=zeros: _no_grad_energy(model.head, zeros, kv),
                    setup=policy.eval,
                    group="head",
                    meta={**meta, "variant": "final_energy_forward_only"},
                )
            )
            for variant, wrap in wrappers.items():
                cells.append(
                    Cell(
                        f"{prefix}/{variant}",
                        lambda refine=refine, wrap=wrap: refine(wrap),
                        setup=policy.eval,
                        group="head",
                        meta={**meta, "variant": variant},
                        reference=refine,
                    )
                )
    return cells


def _no_grad_energy(head: nn.Module, actions: Tensor, kv) -> Tensor:
    with torch.no_grad():
        return head(actions, kv)
