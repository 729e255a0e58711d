"""Speed-ups of the refinement must not change its result.

Each test runs the default inference path and a faster way to compute the same thing (frozen or detached
parameters, another attention kernel, a compiled energy, a batch of environments instead of one at a time)
from the same seed, and asserts that the actions and energies agree to float tolerance. The policy's own
compiled chunk (`compile_mode`) is tested in tests/test_compile_mode.py.
"""

import os

import pytest
import torch
from torch.func import functional_call
from torch.nn.attention import SDPBackend, sdpa_kernel

from lerobot_policy_ebvla import EBVLAPolicy
from lerobot_policy_ebvla.mcmc import refine_actions

from .conftest import tiny_batch, tiny_config

TOL = {"atol": 1e-5, "rtol": 1e-5}


@pytest.fixture(scope="module")
def policy() -> EBVLAPolicy:
    torch.manual_seed(0)
    return EBVLAPolicy(tiny_config()).eval()


def refine(policy: EBVLAPolicy, batch: dict, seed: int = 0):
    actions, readout = policy.predict_action_chunk(
        batch, generator=torch.Generator().manual_seed(seed), return_energy=True
    )
    return actions, readout.initial_energy, readout.final_energy


def refine_with_energy(policy: EBVLAPolicy, kv, energy_fn, initial: torch.Tensor, seed: int = 0, **overrides):
    """`refine_actions` with the policy's inference settings and a given energy function of (actions, kv)."""
    cfg = policy.config
    settings = {
        "temperature": cfg.energy_temperature,
        "langevin_std": cfg.langevin_noise_std,
        "grad_clip": cfg.grad_clip,
        "action_clamp": cfg.action_clamp,
        **overrides,
    }
    return refine_actions(
        lambda a: energy_fn(a, kv),
        initial,
        [cfg.inference_step_size] * cfg.inference_mcmc_steps,
        generator=torch.Generator().manual_seed(seed),
        **settings,
    )


def detached_energy(head: torch.nn.Module):
    """The head evaluated with detached parameters: autograd records the path from the actions only."""
    params = {name: p.detach() for name, p in head.named_parameters()}
    params.update(head.named_buffers())
    return lambda actions, kv: functional_call(head, params, (actions, kv))


def assert_same_refinement(reference, other, exact: bool = False):
    for ref, got in zip(reference, other, strict=True):
        if exact:
            assert torch.equal(ref, got)
        else:
            torch.testing.assert_close(got, ref, **TOL)


def context_and_initial(policy: EBVLAPolicy, batch_size: int = 3):
    batch = tiny_batch(policy.config, batch_size=batch_size, with_action=False)
    with torch.no_grad():
        kv = policy.model.encode_context(batch)
    cfg = policy.config
    initial = torch.randn(
        batch_size, cfg.chunk_size, cfg.action_dim, generator=torch.Generator().manual_seed(1)
    )
    return batch, kv, initial


def test_inference_leaves_no_parameter_gradients(policy):
    """Refinement differentiates w.r.t. the actions only: no parameter accumulates a .grad."""
    policy.predict_action_chunk(tiny_batch(policy.config, with_action=False))
    assert all(p.grad is None for p in policy.parameters())


def test_frozen_parameters_give_the_same_refinement(policy):
    batch = tiny_batch(policy.config, with_action=False)
    reference = refine(policy, batch)
    policy.requires_grad_(False)
    try:
        assert_same_refinement(reference, refine(policy, batch), exact=True)
    finally:
        policy.requires_grad_(True)


def test_detached_parameter_energy_gives_the_same_refinement(policy):
    _, kv, initial = context_and_initial(policy)
    reference = refine_with_energy(policy, kv, policy.model.head, initial)
    detached = refine_with_energy(policy, kv, detached_energy(policy.model.head), initial)
    assert_same_refinement(
        (reference.actions, reference.step_energies), (detached.actions, detached.step_energies), exact=True
    )


def test_action_gradient_by_vjp_equals_autograd(policy):
    """torch.func.grad w.r.t. the actions alone gives the gradient that refinement uses."""
    _, kv, actions = context_and_initial(policy)
    head = policy.model.head
    a = actions.clone().requires_grad_(True)
    (expected,) = torch.autograd.grad(head(a, kv).mean(dim=-1).sum(), a)
    energy = detached_energy(head)
    got = torch.func.grad(lambda x: energy(x, kv).mean(dim=-1).sum())(actions)
    torch.testing.assert_close(got, expected, **TOL)


@pytest.mark.parametrize("backend", [SDPBackend.MATH, SDPBackend.FLASH_ATTENTION])
def test_attention_backend_does_not_change_the_refinement(policy, backend):
    batch = tiny_batch(policy.config, with_action=False)
    reference = refine(policy, batch)
    with sdpa_kernel(backend):
        assert_same_refinement(reference, refine(policy, batch))


def test_compiled_energy_gives_the_same_refinement(policy):
    """The graph torch.compile captures (AOTAutograd, detached parameters) refines like eager mode.

    `aot_eager` traces exactly what inductor would compile but skips code generation, so the test stays fast;
    `test_inductor_compiled_energy_gives_the_same_refinement` covers the generated kernels.
    """
    _, kv, initial = context_and_initial(policy)
    reference = refine_with_energy(policy, kv, policy.model.head, initial)
    compiled = torch.compile(detached_energy(policy.model.head), backend="aot_eager", dynamic=False)
    got = refine_with_energy(policy, kv, compiled, initial)
    assert_same_refinement((reference.actions, reference.step_energies), (got.actions, got.step_energies))


@pytest.mark.slow
@pytest.mark.skipif(
    os.environ.get("EBVLA_TEST_INDUCTOR") != "1", reason="inductor compiles C++ for minutes on CPU; opt in"
)
def test_inductor_compiled_energy_gives_the_same_refinement(policy):
    _, kv, initial = context_and_initial(policy)
    reference = refine_with_energy(policy, kv, policy.model.head, initial)
    compiled = torch.compile(detached_energy(policy.model.head), dynamic=False)
    got = refine_with_energy(policy, kv, compiled, initial)
    assert_same_refinement((reference.actions, reference.step_energies), (got.actions, got.step_energies))


def test_batched_environments_refine_like_one_environment_at_a_time(policy):
    """A batch of B environments gives each the chunk it would get alone (same context, a^(0), no noise).

    The Langevin noise is drawn for the whole batch at once, so it is switched off to give both runs the same
    draws; everything else (context encoding, attention, energy-scaled steps, clamps) is the real path.
    """
    batch, kv, initial = context_and_initial(policy, batch_size=3)
    batched = refine_with_energy(policy, kv, policy.model.head, initial, langevin_std=0.0)
    for i in range(3):
        single = {k: v[i : i + 1] for k, v in batch.items()}
        with torch.no_grad():
            kv_i = policy.model.encode_context(single)
        alone = refine_with_energy(policy, kv_i, policy.model.head, initial[i : i + 1], langevin_std=0.0)
        torch.testing.assert_close(alone.actions[0], batched.actions[i], **TOL)
        torch.testing.assert_close(alone.step_energies[:, 0], batched.step_energies[:, i], **TOL)


def test_final_energy_is_the_energy_of_the_returned_chunk(policy):
    """The confidence score is E(a^(K_inf), C) of the returned actions, not the last step's perturbed energy:
    fusing the final forward into the last MCMC step would change it."""
    batch = tiny_batch(policy.config, with_action=False)
    actions, _, final_energy = refine(policy, batch)
    scored = policy.score_action_chunks(batch, actions.unsqueeze(1)).squeeze(1)
    torch.testing.assert_close(scored, final_energy, **TOL)
