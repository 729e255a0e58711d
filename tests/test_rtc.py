"""Real-time chunking (RTC): the next chunk inpaints the previous chunk's leftover on the energy landscape."""

import numpy as np
import pytest
import torch
from lerobot.configs import RTCAttentionSchedule
from lerobot.policies.rtc.configuration_rtc import RTCConfig

from lerobot_policy_ebvla import EBVLAPolicy
from lerobot_policy_ebvla import modeling_ebvla as modeling
from lerobot_policy_ebvla.mcmc import RTCPrefix, refine_actions, sample_initial_actions
from tests.conftest import tiny_batch, tiny_config
from tests.test_mcmc import TARGET, quadratic

CHUNK, HORIZON = 8, 6
MCMC = {"temperature": 9.0, "langevin_std": 0.0, "grad_clip": 1.0, "action_clamp": 10.0}


def rtc_policy(**rtc) -> EBVLAPolicy:
    torch.manual_seed(0)
    config = tiny_config(
        chunk_size=CHUNK, n_action_steps=CHUNK, rtc_config=RTCConfig(execution_horizon=HORIZON, **rtc)
    )
    return EBVLAPolicy(config).eval()


def chunk(policy, batch, seed=1, **rtc):
    generator = torch.Generator().manual_seed(seed)
    return policy.predict_action_chunk(batch, generator=generator, return_energy=True, **rtc)


@pytest.fixture
def leftover() -> torch.Tensor:
    return torch.randn(2, HORIZON, 3, generator=torch.Generator().manual_seed(7))


def test_one_step_holds_the_first_d_actions_and_pulls_the_overlap_by_min_1_alpha_lambda_w():
    a0, prefix = torch.randn(2, 4, 2), torch.randn(2, 4, 2)
    weights = torch.tensor([1.0, 0.5, 0.25, 0.0])
    result = refine_actions(
        quadratic,
        a0,
        [0.2],
        **MCMC,
        prefix=RTCPrefix(prefix, held_steps=1, weights=weights, guidance_weight=5.0),
    )
    start = torch.cat([prefix[:, :1], a0[:, 1:]], dim=1)  # a^(0) already holds the prefix
    e = quadratic(start)
    stepped = start - 0.2 * torch.exp(e / 9.0).unsqueeze(-1) * ((start - TARGET) / 4).clamp(-1, 1)
    pull = (0.2 * 5.0 * weights).clamp(max=1.0).unsqueeze(-1)  # min(1, alpha lambda w_t)
    expected = stepped - pull * (stepped - prefix)
    expected[:, :1] = prefix[:, :1]
    torch.testing.assert_close(result.actions, expected)
    torch.testing.assert_close(result.step_energies[0], e.mean(-1))


def test_without_rtc_arguments_the_chunk_is_plain_refinement_bit_for_bit():
    policy = rtc_policy()
    batch = tiny_batch(policy.config, with_action=False)
    actions, readout = chunk(policy, batch)
    cfg, model = policy.config, policy.model
    generator = torch.Generator().manual_seed(1)
    with torch.no_grad():
        kv = model.encode_context(batch)
    initial = sample_initial_actions((2, CHUNK, 3), cfg.init_action_std, device="cpu", generator=generator)
    plain = refine_actions(
        lambda a: model.head(a, kv),
        initial,
        [cfg.inference_step_size] * cfg.inference_mcmc_steps,
        temperature=cfg.energy_temperature,
        langevin_std=cfg.langevin_noise_std,
        grad_clip=cfg.grad_clip,
        action_clamp=cfg.action_clamp,
        generator=generator,
    )
    assert torch.equal(actions, plain.actions)
    assert torch.equal(readout.initial_energy, plain.step_energies[0])


def test_rtc_disabled_ignores_the_leftover_as_lerobot_does(leftover):
    policy = rtc_policy(enabled=False)
    batch = tiny_batch(policy.config, with_action=False)
    plain, _ = chunk(policy, batch)
    ignored, _ = chunk(policy, batch, inference_delay=2, prev_chunk_left_over=leftover)
    assert torch.equal(plain, ignored)


# (num_restarts, restart_energy_threshold): the paper, best-of-3, and adaptive restarts that restart every chunk.
@pytest.mark.parametrize(("restarts", "threshold"), [(1, None), (3, None), (3, -1e9)])
@pytest.mark.parametrize("delay", [1, 3])
def test_the_first_d_actions_are_the_leftover_exactly(leftover, delay, restarts, threshold):
    policy = rtc_policy()
    policy.config.num_restarts = restarts
    policy.config.restart_energy_threshold = threshold
    batch = tiny_batch(policy.config, with_action=False)
    actions, _ = chunk(policy, batch, inference_delay=delay, prev_chunk_left_over=leftover)
    assert torch.equal(actions[:, :delay], leftover[:, :delay])


def test_the_guided_overlap_is_closer_to_the_leftover_than_a_hold_alone(leftover):
    batch = tiny_batch(rtc_policy().config, with_action=False)
    guided, _ = chunk(rtc_policy(), batch, inference_delay=2, prev_chunk_left_over=leftover)
    held_only, _ = chunk(
        rtc_policy(prefix_attention_schedule=RTCAttentionSchedule.ZEROS),
        batch,
        inference_delay=2,
        prev_chunk_left_over=leftover,
    )
    overlap = slice(2, HORIZON)
    distance = (guided[:, overlap] - leftover[:, overlap]).abs().mean()
    assert distance < 0.5 * (held_only[:, overlap] - leftover[:, overlap]).abs().mean()
    # Past the execution horizon the weights are 0: only the energy, in the prefix's context, shapes the chunk.
    assert not torch.allclose(guided[:, HORIZON:], torch.zeros_like(guided[:, HORIZON:]))


def test_the_energy_returned_is_the_energy_of_the_returned_chunk(leftover):
    policy = rtc_policy()
    batch = tiny_batch(policy.config, with_action=False)
    actions, readout = chunk(policy, batch, inference_delay=2, prev_chunk_left_over=leftover)
    torch.testing.assert_close(
        readout.final_energy, policy.score_action_chunks(batch, actions[:, None])[:, 0]
    )
    assert policy.last_energy is readout


def test_an_unbatched_leftover_longer_than_the_chunk_is_taken_as_lerobot_pads_it():
    policy = rtc_policy()
    policy.config.rtc_config.execution_horizon = 10  # LeRobot's default, above chunk_size
    batch = tiny_batch(policy.config, batch_size=1, with_action=False)
    leftover = torch.randn(10, 3)
    actions, _ = chunk(policy, batch, inference_delay=3, prev_chunk_left_over=leftover)
    assert actions.shape == (1, CHUNK, 3)
    assert torch.equal(actions[0, :3], leftover[:3])


def test_the_rtc_config_survives_save_and_load(tmp_path):
    policy = rtc_policy(prefix_attention_schedule=RTCAttentionSchedule.EXP, max_guidance_weight=3.0)
    policy.save_pretrained(tmp_path)
    loaded = EBVLAPolicy.from_pretrained(tmp_path)
    assert loaded.config.rtc_config == policy.config.rtc_config
    assert loaded.supports_rtc()


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (
            {"prev_chunk_left_over": torch.randn(2, 4, 5)},
            r"`prev_chunk_left_over` must be \(B=2, n, action_dim=3\)",
        ),
        ({"prev_chunk_left_over": torch.randn(3, 4, 3)}, r"`prev_chunk_left_over` must be \(B=2"),
        (
            {"prev_chunk_left_over": torch.full((2, 4, 3), float("nan"))},
            "`prev_chunk_left_over` contains NaN",
        ),
        ({"inference_delay": CHUNK + 1}, r"`inference_delay` must be in \[0, chunk_size=8\]"),
        ({"inference_delay": -1}, "`inference_delay`"),
        ({"execution_horizon": 0}, "`execution_horizon` must be >= 1"),
    ],
)
def test_a_leftover_that_does_not_fit_is_refused_naming_the_argument(kwargs, message):
    policy = rtc_policy()
    batch = tiny_batch(policy.config, with_action=False)
    kwargs = {"prev_chunk_left_over": torch.randn(2, 4, 3), "inference_delay": 1, **kwargs}
    with pytest.raises(ValueError, match=message):
        policy.predict_action_chunk(batch, **kwargs)


def test_a_leftover_without_rtc_config_is_refused():
    torch.manual_seed(0)
    policy = EBVLAPolicy(tiny_config()).eval()
    batch = tiny_batch(policy.config, with_action=False)
    with pytest.raises(ValueError, match="`prev_chunk_left_over` was given but `rtc_config` is None"):
        policy.predict_action_chunk(batch, inference_delay=1, prev_chunk_left_over=torch.randn(2, 4, 3))


def test_config_rejects_an_empty_execution_horizon():
    with pytest.raises(ValueError, match=r"`rtc_config.execution_horizon` must be >= 1"):
        tiny_config(rtc_config=RTCConfig(execution_horizon=0))


def test_lerobot_rollout_with_rtc_inference_drives_ebvla_and_inpaints_each_next_chunk(monkeypatch, tmp_path):
    from tests.test_rollout import run_lerobot_rollout

    prefixes = []
    rtc_prefix = modeling.rtc_prefix
    monkeypatch.setattr(
        modeling, "rtc_prefix", lambda *args: prefixes.append(rtc_prefix(*args)) or prefixes[-1]
    )
    robot, policy = run_lerobot_rollout(
        monkeypatch, tmp_path, "--inference.type=rtc", "--inference.rtc.execution_horizon=4"
    )
    assert policy.config.rtc_config.execution_horizon == 4
    assert policy.chunk_index >= 2
    inpainted = [p for p in prefixes if p is not None]
    assert inpainted, "no chunk after the first was given the previous chunk's leftover"
    assert all(p.actions.shape == (1, 4, 3) for p in inpainted)
    assert len(robot.sent_actions) >= 4
    assert all(np.isfinite(list(action.values())).all() for action in robot.sent_actions)


def test_zero_rows_lerobot_pads_the_leftover_with_are_not_guided(leftover):
    policy = rtc_policy()
    batch = tiny_batch(policy.config, with_action=False)
    padded = torch.cat([leftover[:, :3], torch.zeros(2, HORIZON - 3, 3)], dim=1)
    actions, _ = chunk(policy, batch, inference_delay=1, prev_chunk_left_over=padded)
    unpadded, _ = chunk(policy, batch, inference_delay=1, prev_chunk_left_over=leftover[:, :3])
    assert torch.equal(actions, unpadded)


def test_a_leftover_made_under_inference_mode_is_inpainted_as_in_lerobot_eval(leftover):
    policy = rtc_policy()
    batch = tiny_batch(policy.config, with_action=False)
    with torch.inference_mode():
        inference_leftover = leftover.clone()
        actions, _ = chunk(policy, batch, inference_delay=2, prev_chunk_left_over=inference_leftover)
    assert torch.equal(actions[:, :2], leftover[:, :2])
