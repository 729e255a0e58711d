"""A bf16 policy refines in fp32: a, eps, the updates and the energy readout never take the head's dtype.

In bf16 the spacing of numbers near 1.0 is 2^-7 = 0.0078, so an MCMC run in bf16 would round away the Langevin
noise (sigma_L = 0.001) and any step smaller than half that spacing.
"""

import copy

import pytest
import torch

from lerobot_policy_ebvla import EBVLAPolicy
from lerobot_policy_ebvla.energy_head import EBVLARotaryEmbedding
from lerobot_policy_ebvla.mcmc import refine_actions

from .conftest import tiny_batch, tiny_config

# bf16 has an 8-bit mantissa (relative rounding 2^-9 = 0.002 per op); through a 2-block head, 15 MCMC steps of
# alpha = 0.22 and the exp(e / tau) step scaling, the refined actions (normalized units, clamped to a_max = 10)
# stay within this of the fp32 policy's on this tiny model.
BF16_ACTION_ATOL = 0.05
BF16_ENERGY_ATOL = 0.05


@pytest.fixture(scope="module")
def policies() -> tuple[EBVLAPolicy, EBVLAPolicy]:
    torch.manual_seed(0)
    fp32 = EBVLAPolicy(tiny_config()).eval()
    return fp32, copy.deepcopy(fp32).to(torch.bfloat16)


def observation(policy: EBVLAPolicy) -> dict[str, torch.Tensor]:
    """Inputs in the policy's dtype, as LeRobot's device step gives them to a bf16 policy."""
    batch = tiny_batch(policy.config, with_action=False)
    return {k: v.to(next(policy.parameters()).dtype) for k, v in batch.items()}


def refine(policy: EBVLAPolicy, seed: int = 1):
    return policy.predict_action_chunk(
        observation(policy), generator=torch.Generator().manual_seed(seed), return_energy=True
    )


def test_bf16_policy_returns_fp32_actions_and_energies(policies):
    _, bf16 = policies
    actions, readout = refine(bf16)
    assert bf16.model.head.action_in.weight.dtype == torch.bfloat16
    assert actions.dtype == torch.float32
    assert readout.initial_energy.dtype == readout.final_energy.dtype == torch.float32


def test_bf16_refinement_matches_fp32_within_tolerance(policies):
    fp32, bf16 = policies
    actions, readout = refine(fp32)
    bf16_actions, bf16_readout = refine(bf16)
    assert actions.abs().max() > 0.1  # refined, not trivially zero
    torch.testing.assert_close(bf16_actions, actions, atol=BF16_ACTION_ATOL, rtol=0)
    torch.testing.assert_close(bf16_readout.final_energy, readout.final_energy, atol=BF16_ENERGY_ATOL, rtol=0)


def test_initial_actions_are_fp32_in_a_bf16_policy(policies):
    _, bf16 = policies
    reference = torch.zeros(1, dtype=torch.bfloat16)
    assert bf16.model.initial_actions(2, reference, None).dtype == torch.float32


def test_langevin_noise_of_sigma_0001_is_not_rounded_away_in_a_bf16_policy(policies):
    _, bf16 = policies
    with torch.no_grad():
        kv = bf16.model.encode_context(observation(bf16))
    initial = bf16.model.initial_actions(2, kv[0][0], torch.Generator().manual_seed(0))

    def run(sigma_l: float) -> torch.Tensor:
        return refine_actions(
            lambda a: bf16.model.head(a, kv),
            initial,
            [1e-3],  # one step small enough that only the noise at which grad E is taken can differ
            temperature=9.0,
            langevin_std=sigma_l,
            grad_clip=1.0,
            action_clamp=10.0,
            generator=torch.Generator().manual_seed(2),
        ).actions

    quiet, noisy = run(0.0), run(1e-3)
    assert quiet.dtype == noisy.dtype == torch.float32
    # Where |a| >= 1 the step is below half of bf16's spacing there (2^-7): a bf16 iterate would not move.
    moved, large = (quiet - initial).abs(), initial.abs() >= 1
    assert large.any()
    assert (moved[large] > 0).all()
    assert (moved[large] < 2**-8).all()
    # The noise moves the point where the gradient is taken, so it changes the step.
    assert not torch.equal(quiet, noisy)


def test_rotary_frequencies_stay_fp32_under_a_bf16_cast(policies):
    fp32, bf16 = policies
    rotary, rotary_bf16 = fp32.model.head.rotary, bf16.model.head.rotary
    assert rotary_bf16.inv_freq.dtype == torch.float32
    assert torch.equal(rotary_bf16.inv_freq, rotary.inv_freq)


def test_rotary_frequencies_are_made_on_the_device_the_head_is_built_on():
    """A head built under `with torch.device("cuda")` and then cast (`policy.to(torch.bfloat16)`) kept its
    frequencies on the CPU: every energy evaluation copied them to the GPU, a host sync that also kept the
    refinement out of CUDA graphs (research/docs/vlm_gpu.md, 2026-11-27). Here the meta device stands in for CUDA."""
    with torch.device("meta"):
        rotary = EBVLARotaryEmbedding(head_dim=16, base=10000.0)
    rotary.to(torch.bfloat16)
    assert rotary.inv_freq.device.type == "meta" and rotary.inv_freq.dtype == torch.float32
