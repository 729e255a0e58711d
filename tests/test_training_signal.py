"""The training-signal options: how alpha is drawn along a chain, the straight-through clip, the contrastive term."""

import pytest
import torch

from lerobot_policy_ebvla import EBVLAPolicy
from lerobot_policy_ebvla.training_signal import (
    compute_loss,
    contrastive_energy_loss,
    sample_training_step_sizes,
)

from .conftest import tiny_batch, tiny_config


@pytest.mark.parametrize("seed", range(5))
def test_per_chain_sampling_keeps_alpha_constant_along_the_chain(seed):
    config = tiny_config(train_step_size_sampling="per_chain", train_mcmc_steps_range=(4, 9))
    steps = sample_training_step_sizes(config, torch.Generator().manual_seed(seed))
    assert 4 <= len(steps) <= 9
    assert len(set(steps)) == 1
    assert config.train_step_size_range[0] <= steps[0] <= config.train_step_size_range[1]


def test_per_mcmc_step_sampling_draws_a_new_alpha_at_every_step():
    config = tiny_config(train_step_size_sampling="per_mcmc_step", train_mcmc_steps_range=(6, 6))
    steps = sample_training_step_sizes(config, torch.Generator().manual_seed(0))
    alpha_min, alpha_max = config.train_step_size_range
    assert len(set(steps)) == 6
    assert all(alpha_min <= alpha <= alpha_max for alpha in steps)


def test_unknown_step_size_sampling_is_rejected_by_name():
    with pytest.raises(ValueError, match="train_step_size_sampling"):
        tiny_config(train_step_size_sampling="per_episode")


def test_straight_through_clip_does_not_change_inference():
    batch = tiny_batch(tiny_config(), with_action=False)
    chunks = []
    for straight_through in (False, True):
        torch.manual_seed(0)
        policy = EBVLAPolicy(tiny_config(train_straight_through_clip=straight_through)).eval()
        chunks.append(policy.predict_action_chunk(batch, generator=torch.Generator().manual_seed(1)))
    torch.testing.assert_close(chunks[0], chunks[1])


def test_straight_through_clip_gives_the_backbone_a_larger_gradient_when_clips_are_active():
    """With a tiny clip c every gradient entry is clipped: the hard clip leaves only exp(e_t / tau)'s path."""
    norms = {}
    for straight_through in (False, True):
        torch.manual_seed(0)
        policy = EBVLAPolicy(tiny_config(grad_clip=1e-6, train_straight_through_clip=straight_through))
        loss, _ = compute_loss(
            policy.model, tiny_batch(policy.config), generator=torch.Generator().manual_seed(0)
        )
        loss.backward()
        grads = [p.grad.norm() for p in policy.model.backbone.parameters() if p.grad is not None]
        norms[straight_through] = torch.stack(grads).norm().item()
    assert norms[True] > 10 * norms[False]


def test_contrastive_term_is_added_and_reported():
    batch = tiny_batch(tiny_config(), batch_size=4)
    losses = {}
    for weight in (0.0, 1.0):
        torch.manual_seed(0)
        policy = EBVLAPolicy(tiny_config(contrastive={"weight": weight}))
        losses[weight] = compute_loss(policy.model, batch, generator=torch.Generator().manual_seed(0))
    (plain, plain_info), (with_term, info) = losses[0.0], losses[1.0]
    assert "contrastive_loss" not in plain_info
    assert with_term.item() == pytest.approx(plain.item() + info["contrastive_loss"], rel=1e-5)
    # Chance level of the InfoNCE over B in-batch chunks plus the noisy copies is log(B + N_noisy).
    assert 0 < info["contrastive_loss"] < 3 * torch.log(torch.tensor(4.0 + 8.0)).item()


def test_contrastive_candidates_follow_the_mismatched_and_noisy_counts():
    batch = tiny_batch(tiny_config(), batch_size=6)
    seen = []
    for mismatched, noisy in ((None, 3), (2, 1), (0, 0)):
        torch.manual_seed(0)
        policy = EBVLAPolicy(
            tiny_config(
                contrastive={"weight": 1.0, "mismatched": mismatched, "negatives": noisy},
            )
        )
        kv = policy.model.encode_context(batch)
        sizes = []
        handle = policy.model.head.register_forward_hook(
            lambda m, args, out, sizes=sizes: sizes.append(args[0].shape[0])
        )
        loss = contrastive_energy_loss(policy.model, kv, batch["action"], torch.Generator().manual_seed(0))
        handle.remove()
        seen.append((sizes, loss.item()))
    # All B - 1 = 5 other chunks by default; 6 contexts x (1 + M + N) candidates in one head call.
    assert seen[0][0] == [6 * (1 + 5 + 3)]
    assert seen[1][0] == [6 * (1 + 2 + 1)]
    # The positive alone: nothing to rank against, so the InfoNCE is exactly 0.
    assert seen[2][0] == [6] and seen[2][1] == pytest.approx(0.0, abs=1e-6)


def test_contrastive_anchors_rank_their_candidates_against_the_whole_batch():
    """With A anchors, only the first A observations rank candidates, each against every other chunk of the
    batch; the loss is the mean of the full loss's first A rows."""
    batch = tiny_batch(tiny_config(), batch_size=6)
    torch.manual_seed(0)
    policy = EBVLAPolicy(tiny_config(contrastive={"weight": 1.0, "negatives": 0}))
    kv = policy.model.encode_context(batch)
    energies = []
    handle = policy.model.head.register_forward_hook(lambda m, args, out: energies.append(out.mean(dim=-1)))
    full = contrastive_energy_loss(policy.model, kv, batch["action"], torch.Generator().manual_seed(0))
    policy.config.contrastive.anchors = 2
    two = contrastive_energy_loss(policy.model, kv, batch["action"], torch.Generator().manual_seed(0))
    handle.remove()
    assert [e.shape[0] for e in energies] == [6 * 6, 2 * 6]
    # Without noisy copies both calls score the same (context, chunk) pairs for the first two anchors.
    logits = -energies[0].view(6, 6) / policy.config.contrastive.temperature
    per_row = torch.nn.functional.cross_entropy(logits, torch.zeros(6, dtype=torch.long), reduction="none")
    torch.testing.assert_close(full, per_row.mean(), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(two, per_row[:2].mean(), rtol=1e-5, atol=1e-6)
    # More anchors than the batch holds: every observation.
    policy.config.contrastive.anchors = 50
    torch.testing.assert_close(
        contrastive_energy_loss(policy.model, kv, batch["action"], torch.Generator().manual_seed(0)), full
    )
    with pytest.raises(ValueError, match="`contrastive.anchors`"):
        tiny_config(contrastive={"anchors": 0})


def test_contrastive_mismatched_must_not_be_negative():
    with pytest.raises(ValueError, match="`contrastive.mismatched`"):
        tiny_config(contrastive={"mismatched": -1})


def test_training_with_the_contrastive_term_lowers_it_on_a_fixed_batch():
    torch.manual_seed(0)
    policy = EBVLAPolicy(tiny_config(contrastive={"weight": 1.0}))
    batch = tiny_batch(policy.config, batch_size=4)
    optimizer = torch.optim.Adam(policy.parameters(), lr=3e-3)
    contrastive = []
    for step in range(30):
        loss, info = compute_loss(policy.model, batch, generator=torch.Generator().manual_seed(step))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        contrastive.append(info["contrastive_loss"])
    assert sum(contrastive[-5:]) / 5 < 0.5 * sum(contrastive[:5]) / 5


def test_state_dropout_hides_the_state_token_in_training_only():
    torch.manual_seed(0)
    policy = EBVLAPolicy(tiny_config(resnet={"state_dropout": 0.5}))
    batch = tiny_batch(policy.config, batch_size=64, with_action=False)
    backbone = policy.model.backbone.train()
    state_tokens = backbone(batch)[0][:, -1]  # p is the last context token, (B, D)
    hidden = (state_tokens == 0).all(dim=1)
    assert 0.2 < hidden.float().mean().item() < 0.8
    backbone.eval()
    assert not (backbone(batch)[0][:, -1] == 0).all(dim=1).any()


def test_state_dropout_outside_zero_one_is_rejected_by_name():
    with pytest.raises(ValueError, match="`resnet.state_dropout`"):
        tiny_config(resnet={"state_dropout": 1.0})


def test_contrastive_term_in_bf16_runs_its_head_pass_in_bf16_and_stays_close_to_fp32():
    """`energy_contrastive_dtype="bfloat16"`: the head's matrix products in bf16, the energies and the loss in
    fp32, close to the fp32 loss, with gradients reaching the head and the image encoder."""
    batch = tiny_batch(tiny_config(), batch_size=6)
    torch.manual_seed(0)
    policy = EBVLAPolicy(tiny_config(contrastive={"weight": 1.0}))
    kv = policy.model.encode_context(batch)
    fp32 = contrastive_energy_loss(policy.model, kv, batch["action"], torch.Generator().manual_seed(0))
    dtypes = []
    handle = policy.model.head.blocks[0].ffn.down.register_forward_hook(
        lambda m, args, out: dtypes.append(out.dtype)
    )
    policy.config.contrastive.dtype = "bfloat16"
    bf16 = contrastive_energy_loss(policy.model, kv, batch["action"], torch.Generator().manual_seed(0))
    handle.remove()
    assert dtypes == [torch.bfloat16]
    assert bf16.dtype == torch.float32 and torch.isfinite(bf16)
    torch.testing.assert_close(bf16, fp32, rtol=0.05, atol=0.05)
    bf16.backward()
    for name, module in (("head", policy.model.head), ("backbone", policy.model.backbone)):
        grads = [p.grad for p in module.parameters() if p.requires_grad]
        assert any(g is not None and g.abs().sum() > 0 for g in grads), name
        assert all(g is None or (g.dtype == torch.float32 and torch.isfinite(g).all()) for g in grads), name


@pytest.mark.parametrize(("native", "expected"), [(True, torch.bfloat16), (False, torch.float32)])
def test_contrastive_dtype_auto_uses_bf16_only_where_the_device_has_it(monkeypatch, native, expected):
    from lerobot_policy_ebvla import training_signal

    monkeypatch.setattr(training_signal, "native_bf16", lambda device_type: native)
    batch = tiny_batch(tiny_config(), batch_size=3)
    policy = EBVLAPolicy(tiny_config(contrastive={"weight": 1.0, "dtype": "auto"}))
    dtypes = []
    policy.model.head.blocks[0].ffn.down.register_forward_hook(lambda m, args, out: dtypes.append(out.dtype))
    kv = policy.model.encode_context(batch)
    contrastive_energy_loss(policy.model, kv, batch["action"], torch.Generator().manual_seed(0))
    assert dtypes == [expected]


def test_contrastive_dtype_must_be_a_known_precision():
    with pytest.raises(ValueError, match="`contrastive.dtype`.*'float16'"):
        tiny_config(contrastive={"dtype": "float16"})
