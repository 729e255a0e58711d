"""The head can learn: the loss falls on a fixed batch, and on a bimodal toy problem both expert modes get
lower energy than perturbed chunks."""

import torch

from lerobot_policy_ebvla import EBVLAPolicy

from .conftest import tiny_config

IMAGE = (3, 40, 40)


def toy_config(**overrides):
    from lerobot.configs.types import FeatureType, PolicyFeature

    features = {
        "observation.images.top": PolicyFeature(FeatureType.VISUAL, IMAGE),
        "observation.state": PolicyFeature(FeatureType.STATE, (4,)),
    }
    return tiny_config(
        input_features=features, train_mcmc_steps_range=(3, 5), inference_mcmc_steps=10, **overrides
    )


def train(policy, batch, steps, lr=3e-3):
    optimizer = torch.optim.Adam(policy.parameters(), lr=lr)
    losses = []
    for _ in range(steps):
        loss, _ = policy.forward(batch)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    return losses


def bimodal_batch(batch_size=16, seed=0):
    """One observation, two expert modes: the chunk ramps up (+) or down (-) with equal probability."""
    g = torch.Generator().manual_seed(seed)
    config = toy_config()
    ramp = torch.linspace(0.8, 1.3, config.chunk_size)[None, :, None].expand(1, -1, config.action_dim)
    sign = torch.tensor([1.0, -1.0]).repeat(batch_size // 2)[:, None, None]
    return {
        "observation.images.top": torch.rand(1, *IMAGE, generator=g).expand(batch_size, -1, -1, -1).clone(),
        "observation.state": torch.randn(1, 4, generator=g).expand(batch_size, -1).clone(),
        "action": sign * ramp,
        "action_is_pad": torch.zeros(batch_size, config.chunk_size, dtype=torch.bool),
    }


def test_loss_goes_down_on_a_fixed_batch():
    torch.manual_seed(0)
    policy = EBVLAPolicy(toy_config())
    g = torch.Generator().manual_seed(1)
    batch = bimodal_batch()
    state = torch.randn(batch["observation.state"].shape, generator=g)
    batch["observation.state"] = state
    batch["action"] = torch.tanh(state[:, None, :3] * torch.linspace(0.5, 1.5, 8)[None, :, None])
    losses = train(policy, batch, steps=60)
    assert sum(losses[-10:]) / 10 < 0.7 * sum(losses[:10]) / 10


def test_bimodal_experts_sit_at_lower_energy_than_perturbed_chunks():
    torch.manual_seed(0)
    policy = EBVLAPolicy(toy_config())
    batch = bimodal_batch()
    train(policy, batch, steps=100)
    policy.eval()
    observation = {k: v for k, v in batch.items() if k.startswith("observation.")}
    experts = batch["action"]  # both modes, for the same observation
    g = torch.Generator().manual_seed(2)
    perturbed = experts + 0.5 * torch.randn(experts.shape, generator=g)
    expert_energy = policy.score_action_chunks(observation, experts.unsqueeze(1))
    perturbed_energy = policy.score_action_chunks(observation, perturbed.unsqueeze(1))
    assert (expert_energy < perturbed_energy).float().mean() >= 0.9
    # Neither mode is favoured by more than the perturbation costs: both are minima.
    assert (
        expert_energy[0::2].mean() < perturbed_energy.mean()
        and expert_energy[1::2].mean() < perturbed_energy.mean()
    )
