"""refine_actions: each line of Eq. 2-3, on energies whose gradients are known in closed form."""

import math

import pytest
import torch

from lerobot_policy_ebvla.mcmc import refine_actions, sample_initial_actions

H, D_A = 4, 2
TARGET = torch.tensor([0.5, -0.25])


def quadratic(a):
    """e_t = 1/2 ||a_t - target||^2, so grad_a E = (a - target) / H."""
    return 0.5 * ((a - TARGET) ** 2).sum(-1)


def refine(a0, steps, **overrides):
    kwargs = {"temperature": 9.0, "langevin_std": 0.0, "grad_clip": 1.0, "action_clamp": 10.0}
    kwargs.update(overrides)
    return refine_actions(quadratic, a0, steps, **kwargs)


def test_one_step_is_the_energy_scaled_update_of_eq3():
    a0 = torch.randn(3, H, D_A)
    result = refine(a0, [0.22])
    e = quadratic(a0)
    expected = a0 - 0.22 * torch.exp(e / 9.0).unsqueeze(-1) * ((a0 - TARGET) / H).clamp(-1, 1)
    torch.testing.assert_close(result.actions, expected)
    torch.testing.assert_close(result.step_energies[0], e.mean(-1))


def test_gradient_is_clipped_elementwise_to_c():
    a0 = torch.full((1, H, D_A), 100.0)
    result = refine(a0, [1.0], temperature=1e9, grad_clip=0.5, action_clamp=1000.0)
    torch.testing.assert_close(result.actions, a0 - 0.5, atol=1e-4, rtol=0)


def test_actions_are_clamped_to_a_max():
    a0 = torch.full((1, H, D_A), 9.9)
    result = refine_actions(
        lambda a: -a.sum(-1) * 100,
        a0,
        [5.0],
        temperature=1e9,
        langevin_std=0.0,
        grad_clip=1.0,
        action_clamp=10.0,
    )
    assert result.actions.max().item() == pytest.approx(10.0)


def test_gradient_is_taken_at_the_langevin_perturbed_point():
    a0 = torch.zeros(1, H, D_A)
    g = torch.Generator().manual_seed(3)
    result = refine(a0, [1.0], langevin_std=0.1, temperature=1e9, generator=g)
    noise = torch.randn(a0.shape, generator=torch.Generator().manual_seed(3))
    expected = a0 - ((a0 + 0.1 * noise - TARGET) / H)
    torch.testing.assert_close(result.actions, expected)


def test_descends_to_the_energy_minimum():
    a0 = sample_initial_actions((2, H, D_A), 1.0, device="cpu", generator=torch.Generator().manual_seed(0))
    result = refine(a0, [0.5 * H] * 30)
    torch.testing.assert_close(result.actions, TARGET.expand(2, H, D_A), atol=1e-3, rtol=0)
    assert (result.step_energies[1:] <= result.step_energies[:-1] + 1e-6).all()


def test_without_create_graph_no_gradient_reaches_parameters():
    weight = torch.nn.Parameter(torch.tensor(2.0))
    result = refine_actions(
        lambda a: weight * (a**2).sum(-1),
        torch.ones(1, H, D_A),
        [0.1, 0.1],
        temperature=9.0,
        langevin_std=0.0,
        grad_clip=1.0,
        action_clamp=10.0,
    )
    assert not result.actions.requires_grad
    assert weight.grad is None


def test_create_graph_differentiates_the_update_with_respect_to_parameters():
    weight = torch.nn.Parameter(torch.tensor(2.0))
    result = refine_actions(
        lambda a: weight * (a**2).sum(-1),
        torch.ones(1, H, D_A),
        [0.1],
        temperature=1e9,
        langevin_std=0.0,
        grad_clip=10.0,
        action_clamp=10.0,
        create_graph=True,
    )
    # a1 = a0 - 0.1 * 2 w a0 / H, so d(sum a1)/dw = -0.2 * sum(a0) / H.
    result.actions.sum().backward()
    assert weight.grad.item() == pytest.approx(-0.2 * H * D_A / H, rel=1e-4)


def test_non_finite_energy_freezes_that_chunk_and_marks_it_diverged():
    def energy(a):
        e = quadratic(a)
        return torch.cat([e[:1], torch.full_like(e[1:], math.nan)])

    a0 = torch.randn(2, H, D_A)
    result = refine_actions(
        energy, a0, [0.2, 0.2], temperature=9.0, langevin_std=0.0, grad_clip=1.0, action_clamp=10.0
    )
    assert result.diverged.tolist() == [False, True]
    torch.testing.assert_close(result.actions[1], a0[1])
    assert torch.isfinite(result.actions).all()


def test_early_stop_ends_once_actions_stop_moving():
    a0 = TARGET.expand(1, H, D_A).clone()
    result = refine(a0, [0.2] * 15, early_stop_tol=1e-6)
    assert result.num_steps == 1
    assert refine(a0, [0.2] * 15).num_steps == 15


def test_same_generator_seed_gives_the_same_chain():
    a0 = torch.randn(2, H, D_A)
    r1 = refine(a0, [0.2] * 5, langevin_std=0.01, generator=torch.Generator().manual_seed(7))
    r2 = refine(a0, [0.2] * 5, langevin_std=0.01, generator=torch.Generator().manual_seed(7))
    torch.testing.assert_close(r1.actions, r2.actions, rtol=0, atol=0)


def _scaled_quadratic(scale):
    """e_t = scale / 2 ||a_t - target||^2: a large `scale` pushes every gradient entry past the clip."""
    return lambda a: 0.5 * scale * ((a - TARGET) ** 2).sum(-1)


@pytest.mark.parametrize("straight_through", [False, True])
def test_straight_through_clip_keeps_the_forward_values(straight_through):
    a0 = torch.full((2, H, D_A), 3.0)
    scale = torch.tensor(100.0, requires_grad=True)
    kwargs = {"temperature": 1e9, "langevin_std": 0.0, "grad_clip": 1.0, "action_clamp": 10.0}
    result = refine_actions(
        _scaled_quadratic(scale),
        a0,
        [0.1],
        create_graph=True,
        straight_through_clip=straight_through,
        **kwargs,
    )
    torch.testing.assert_close(result.actions, a0 - 0.1)


def test_hard_clip_passes_no_gradient_where_it_clips_and_straight_through_does():
    a0 = torch.full((2, H, D_A), 3.0)
    kwargs = {"temperature": 1e9, "langevin_std": 0.0, "grad_clip": 1.0, "action_clamp": 10.0}
    grads = {}
    for straight_through in (False, True):
        scale = torch.tensor(100.0, requires_grad=True)
        result = refine_actions(
            _scaled_quadratic(scale),
            a0,
            [0.1],
            create_graph=True,
            straight_through_clip=straight_through,
            **kwargs,
        )
        (grads[straight_through],) = torch.autograd.grad(result.actions.sum(), scale)
    # Only exp(e_t / tau)'s path is left, and tau = 1e9 makes it vanish.
    assert abs(grads[False].item()) < 1e-6
    # d/dscale of -alpha * grad_a E with grad_a E = scale (a - target) / H, summed over every entry.
    expected = -0.1 * ((a0 - TARGET) / H).sum()
    torch.testing.assert_close(grads[True], expected)
