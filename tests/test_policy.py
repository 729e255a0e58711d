"""EBVLAPolicy on the light backbone: training loss, inference, energies, save/load, input checks."""

import math
import re

import pytest
import torch
from lerobot.configs.types import FeatureType, PolicyFeature

from lerobot_policy_ebvla import EBVLAPolicy, EnergyReadout
from lerobot_policy_ebvla.mcmc import refine_actions
from lerobot_policy_ebvla.training_signal import compute_loss

from .conftest import IMAGE_SHAPE, tiny_batch, tiny_config


def seeded(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def test_head_scores_n_candidates_per_context_as_against_copies_of_it(tiny_policy):
    """The contrastive candidates and the restarts share their context's keys and values (one attention call
    for the N * H queries) instead of copying them: energies and gradients must be those of the copies."""
    head = tiny_policy.model.head
    batch = tiny_batch(tiny_policy.config, batch_size=3)
    kv = tiny_policy.model.encode_context(batch)
    candidates = 5
    actions = torch.randn(3 * candidates, tiny_policy.config.chunk_size, tiny_policy.config.action_dim)
    copies = [(k.repeat_interleave(candidates, dim=0), v.repeat_interleave(candidates, dim=0)) for k, v in kv]
    shared = head(actions, kv)
    copied = head(actions, copies)
    torch.testing.assert_close(shared, copied, rtol=1e-5, atol=1e-5)
    key = kv[0][0]
    (grad_shared,) = torch.autograd.grad(shared.square().sum(), key, retain_graph=True)
    (grad_copied,) = torch.autograd.grad(copied.square().sum(), key)
    torch.testing.assert_close(grad_shared, grad_copied, rtol=1e-4, atol=1e-5)
    # Candidate i * N + j belongs to context i: moving context 0 changes only its own N candidates.
    moved = [(k.clone(), v.clone()) for k, v in kv]
    moved[0][1][0] += 1.0
    changed = (head(actions, moved) - shared).abs().amax(dim=1) > 1e-6
    assert changed.tolist() == [True] * candidates + [False] * (2 * candidates)


def test_energy_bias_init_raises_every_energy_by_b_and_each_first_step_by_exp_b_over_tau():
    """The readout's initial bias is the only weight it changes: every e_t rises by b, and Eq. 3's first step
    from the same a^(0) is exp(b / tau) times longer where the gradient is not clipped."""
    b = 4.5
    policies = {}
    for bias in (0.0, b):
        torch.manual_seed(0)
        policies[bias] = EBVLAPolicy(tiny_config(energy_bias_init=bias, grad_clip=1e6)).eval()
    plain, raised = policies[0.0].state_dict(), policies[b].state_dict()
    assert [k for k in plain if not torch.equal(plain[k], raised[k])] == ["model.head.energy_out.bias"]
    config = policies[0.0].config
    batch = tiny_batch(config, batch_size=3)
    start = torch.randn(3, config.chunk_size, config.action_dim, generator=seeded())
    energies, steps = {}, {}
    for bias, policy in policies.items():
        kv = policy.model.encode_context(batch)
        energies[bias] = policy.model.head(start, kv)
        moved = refine_actions(
            lambda a, kv=kv, policy=policy: policy.model.head(a, kv),
            start,
            step_sizes=[0.1],
            temperature=policy.config.energy_temperature,
            grad_clip=policy.config.grad_clip,
            action_clamp=policy.config.action_clamp,
            langevin_std=0.0,
        ).actions
        steps[bias] = moved - start
    torch.testing.assert_close(energies[b], energies[0.0] + b, rtol=0, atol=1e-4)
    torch.testing.assert_close(
        steps[b], steps[0.0] * math.exp(b / config.energy_temperature), rtol=1e-4, atol=1e-6
    )


def test_head_rejects_a_candidate_count_that_does_not_divide_by_the_contexts(tiny_policy):
    kv = tiny_policy.model.encode_context(tiny_batch(tiny_policy.config, batch_size=2))
    actions = torch.zeros(3, tiny_policy.config.chunk_size, tiny_policy.config.action_dim)
    with pytest.raises(ValueError, match="3 chunks for 2 contexts"):
        tiny_policy.model.head(actions, kv)


def test_forward_returns_l1_loss_and_energy_metrics(tiny_policy):
    loss, info = tiny_policy.forward(tiny_batch(tiny_policy.config))
    assert loss.ndim == 0 and torch.isfinite(loss)
    assert info["l1_loss"] == pytest.approx(loss.item())
    assert 8 <= info["mcmc_steps"] <= 15
    assert math.isfinite(info["initial_energy"]) and math.isfinite(info["last_step_energy"])


def test_padded_action_steps_do_not_count_in_the_loss(tiny_policy):
    batch = tiny_batch(tiny_policy.config)
    batch["action_is_pad"][:, -3:] = True
    loss, _ = compute_loss(tiny_policy.model, batch, generator=seeded(1))
    batch["action"][:, -3:] += 100.0
    loss_changed_padding, _ = compute_loss(tiny_policy.model, batch, generator=seeded(1))
    torch.testing.assert_close(loss, loss_changed_padding)


def test_second_order_gradient_reaches_head_and_backbone(tiny_policy):
    loss, _ = tiny_policy.forward(tiny_batch(tiny_policy.config))
    loss.backward()
    without_grad = [
        n for n, p in tiny_policy.named_parameters() if p.grad is None or not p.grad.abs().sum() > 0
    ]
    assert without_grad == []


def test_inference_builds_no_parameter_gradients(tiny_policy):
    actions = tiny_policy.predict_action_chunk(tiny_batch(tiny_policy.config, with_action=False))
    assert not actions.requires_grad
    assert all(p.grad is None for p in tiny_policy.parameters())


def test_predict_action_chunk_works_under_inference_mode(tiny_policy):
    batch = tiny_batch(tiny_policy.config, batch_size=3, with_action=False)
    with torch.inference_mode():
        actions, energy = tiny_policy.predict_action_chunk(batch, return_energy=True)
    assert actions.shape == (3, tiny_policy.config.chunk_size, tiny_policy.config.action_dim)
    assert energy.initial_energy.shape == energy.final_energy.shape == (3,)
    assert torch.isfinite(actions).all() and torch.isfinite(energy.final_energy).all()
    assert actions.abs().max() <= tiny_policy.config.action_clamp


def test_select_action_refills_every_n_action_steps_with_a_new_energy_readout():
    policy = EBVLAPolicy(tiny_config(n_action_steps=3)).eval()
    batch = tiny_batch(policy.config, with_action=False)
    readouts = []
    for _ in range(7):
        assert policy.select_action(batch).shape == (2, policy.config.action_dim)
        readouts.append(policy.last_energy)
    assert isinstance(readouts[0], EnergyReadout)
    assert len({id(r) for r in readouts}) == 3  # refills at calls 1, 4 and 7
    assert readouts[0] is readouts[2] and readouts[2] is not readouts[3]
    policy.reset()
    assert policy.last_energy is None


def test_same_generator_seed_gives_the_same_actions(tiny_policy):
    batch = tiny_batch(tiny_policy.config, with_action=False)
    tiny_policy.eval()
    a1 = tiny_policy.predict_action_chunk(batch, generator=seeded(5))
    a2 = tiny_policy.predict_action_chunk(batch, generator=seeded(5))
    a3 = tiny_policy.predict_action_chunk(batch, generator=seeded(6))
    torch.testing.assert_close(a1, a2, rtol=0, atol=0)
    assert not torch.allclose(a1, a3)


def test_save_and_load_give_the_same_actions(tiny_policy, tmp_path):
    tiny_policy.eval()
    batch = tiny_batch(tiny_policy.config, with_action=False)
    before = tiny_policy.predict_action_chunk(batch, generator=seeded(1))
    tiny_policy.save_pretrained(tmp_path)
    loaded = EBVLAPolicy.from_pretrained(tmp_path)
    after = loaded.predict_action_chunk(batch, generator=seeded(1))
    torch.testing.assert_close(before, after, rtol=0, atol=0)


def test_context_cache_changes_nothing(tiny_policy):
    """Refining with the context's keys/values computed once equals recomputing them at every step."""
    model, cfg = tiny_policy.eval().model, tiny_policy.config
    batch = tiny_batch(cfg, with_action=False)
    a0 = torch.randn(2, cfg.chunk_size, cfg.action_dim)
    kwargs = {
        "temperature": cfg.energy_temperature,
        "langevin_std": cfg.langevin_noise_std,
        "grad_clip": cfg.grad_clip,
        "action_clamp": cfg.action_clamp,
    }
    steps = [cfg.inference_step_size] * cfg.inference_mcmc_steps
    kv = model.encode_context(batch)
    cached = refine_actions(lambda a: model.head(a, kv), a0, steps, generator=seeded(2), **kwargs)
    uncached = refine_actions(
        lambda a: model.head(a, model.encode_context(batch)), a0, steps, generator=seeded(2), **kwargs
    )
    torch.testing.assert_close(cached.actions, uncached.actions)
    torch.testing.assert_close(cached.step_energies, uncached.step_energies)


def test_final_energy_is_the_energy_of_the_returned_chunk(tiny_policy):
    tiny_policy.eval()
    batch = tiny_batch(tiny_policy.config, with_action=False)
    actions, energy = tiny_policy.predict_action_chunk(batch, return_energy=True)
    scored = tiny_policy.score_action_chunks(batch, actions.unsqueeze(1))
    torch.testing.assert_close(scored[:, 0], energy.final_energy)


def test_restarts_keep_the_lowest_energy_chain():
    torch.manual_seed(0)
    policy = EBVLAPolicy(tiny_config(num_restarts=4)).eval()
    batch = tiny_batch(policy.config, batch_size=2, with_action=False)
    _, best = policy.predict_action_chunk(batch, generator=seeded(3), return_energy=True)
    # The same chains, run as a batch of 2 x 4 independent observations without restarts.
    policy.config.num_restarts = 1
    repeated = {k: v.repeat_interleave(4, dim=0) for k, v in batch.items()}
    _, every = policy.predict_action_chunk(repeated, generator=seeded(3), return_energy=True)
    torch.testing.assert_close(best.final_energy, every.final_energy.view(2, 4).min(dim=1).values)


def test_adaptive_restarts_refine_more_chains_only_where_the_first_energy_is_above_the_threshold():
    torch.manual_seed(0)
    policy = EBVLAPolicy(tiny_config(num_restarts=1)).eval()
    batch = tiny_batch(policy.config, batch_size=2, with_action=False)
    first_actions, first = policy.predict_action_chunk(batch, generator=seeded(3), return_energy=True)
    assert first.chains.tolist() == [1, 1]
    low, high = first.final_energy.sort().values.tolist()
    unsure = int(first.final_energy.argmax())

    policy.config.num_restarts = 4
    policy.config.restart_energy_threshold = (low + high) / 2
    actions, adaptive = policy.predict_action_chunk(batch, generator=seeded(3), return_energy=True)
    sure = 1 - unsure
    # The sure observation keeps its one chain; the unsure one gets 3 more and keeps the lowest of all 4.
    assert adaptive.chains.tolist()[sure] == 1 and adaptive.chains.tolist()[unsure] == 4
    torch.testing.assert_close(actions[sure], first_actions[sure])
    torch.testing.assert_close(adaptive.final_energy[sure], first.final_energy[sure])
    assert adaptive.final_energy[unsure] <= first.final_energy[unsure]
    scored = policy.score_action_chunks(batch, actions.unsqueeze(1))[:, 0]
    torch.testing.assert_close(scored, adaptive.final_energy)

    # Above every energy nothing restarts: the paper's single chain, drawn identically.
    policy.config.restart_energy_threshold = high + 1.0
    same, energy = policy.predict_action_chunk(batch, generator=seeded(3), return_energy=True)
    torch.testing.assert_close(same, first_actions)
    assert energy.chains.tolist() == [1, 1]


def test_non_finite_energy_never_reaches_the_actions(tiny_policy, monkeypatch, caplog):
    tiny_policy.eval()
    head_forward = tiny_policy.model.head.forward
    monkeypatch.setattr(tiny_policy.model.head, "forward", lambda a, kv: head_forward(a, kv) * math.nan)
    actions, energy = tiny_policy.predict_action_chunk(
        tiny_batch(tiny_policy.config, with_action=False), return_energy=True
    )
    assert torch.isfinite(actions).all()
    assert torch.isinf(energy.final_energy).all()
    assert "non-finite" in caplog.text


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda b: b.pop("observation.images.top"), "Missing camera `observation.images.top`"),
        (
            lambda b: b.update({"observation.images.top": torch.rand(2, 3, 48, 48)}),
            "`observation.images.top` must be",
        ),
        (
            lambda b: b.update({"observation.state": torch.randn(2, 5)}),
            "`observation.state` must be \\(B, 4\\)",
        ),
        (lambda b: b.pop("observation.state"), "Missing `observation.state`"),
        (lambda b: b["observation.state"].__setitem__((0, 0), math.nan), "`observation.state` contains NaN"),
        (lambda b: b.update({"action": torch.randn(2, 5, 3)}), "`action` must be \\(B, 8, 3\\)"),
    ],
)
def test_bad_input_gets_an_error_naming_the_key(tiny_policy, mutate, message):
    batch = tiny_batch(tiny_policy.config)
    mutate(batch)
    with pytest.raises(ValueError, match=message):
        tiny_policy.forward(batch)


@pytest.mark.parametrize("entry", ["select_action", "forward"])
def test_a_uint8_image_gets_an_error_naming_the_key_the_dtype_and_what_is_expected(tiny_policy, entry):
    batch = tiny_batch(tiny_policy.config, with_action=entry == "forward")
    batch["observation.images.top"] = (255 * batch["observation.images.top"]).to(torch.uint8)
    message = (
        r"Camera `observation.images.top` has dtype torch.uint8; the policy expects float images in \[0, 1\]"
    )
    with pytest.raises(ValueError, match=message):
        getattr(tiny_policy, entry)(batch)


@pytest.mark.parametrize("entry", ["select_action", "forward"])
def test_a_state_of_another_batch_size_than_the_image_gets_an_error_naming_both(tiny_policy, entry):
    batch = tiny_batch(tiny_policy.config, with_action=entry == "forward")
    batch["observation.state"] = torch.randn(3, 4)
    message = "same batch size B. Got `observation.images.top` 2, `observation.state` 3."
    with pytest.raises(ValueError, match=re.escape(message)):
        getattr(tiny_policy, entry)(batch)


def test_training_randomness_is_restored_with_the_weights(tiny_policy, tmp_path):
    """The MCMC draws of the next training step depend on the saved state, not on the global RNG."""
    batch = tiny_batch(tiny_policy.config)
    tiny_policy.forward(batch)
    tiny_policy.save_pretrained(tmp_path)
    expected, _ = tiny_policy.forward(batch)
    loaded = EBVLAPolicy.from_pretrained(tmp_path).train()
    torch.manual_seed(123)  # whatever happened to the global RNG in between
    resumed, _ = loaded.forward(batch)
    torch.testing.assert_close(resumed, expected)


def test_task_tokens_tell_instructions_apart_and_reject_unknown_ones():
    torch.manual_seed(0)
    policy = EBVLAPolicy(tiny_config(resnet={"task_instructions": ["open the drawer", "close the drawer"]}))
    policy.eval()
    batch = tiny_batch(policy.config, batch_size=1, with_action=False)
    chunks = [
        policy.predict_action_chunk(batch | {"task": [task]}, generator=seeded(1))
        for task in ("open the drawer", "close the drawer")
    ]
    assert not torch.allclose(chunks[0], chunks[1])
    with pytest.raises(ValueError, match="Unknown task instruction.*'push the block'"):
        policy.predict_action_chunk(batch | {"task": ["push the block"]})
    with pytest.raises(ValueError, match="has no `task`"):
        policy.predict_action_chunk(batch)


def test_task_instructions_are_filled_from_the_training_dataset_and_saved(tmp_path):
    from lerobot.datasets import LeRobotDatasetMetadata
    from lerobot.policies.factory import make_policy

    from .conftest import write_tiny_dataset

    root = write_tiny_dataset(tmp_path / "data")
    config = tiny_config(resnet={"task_instructions": []}, input_features={}, output_features={})
    # LeRobot's factory, as lerobot-train calls it: it hands the dataset's metadata to the policy.
    policy = make_policy(config, ds_meta=LeRobotDatasetMetadata("local/ebvla_tiny", root=root))
    assert policy.config.resnet.task_instructions == ["reach the goal"]
    policy.save_pretrained(tmp_path / "ckpt")
    assert EBVLAPolicy.from_pretrained(tmp_path / "ckpt").config.resnet.task_instructions == [
        "reach the goal"
    ]
    with pytest.raises(ValueError, match="no `dataset_meta`"):
        EBVLAPolicy(tiny_config(resnet={"task_instructions": []}))


@pytest.mark.parametrize("stages, map_side", [(4, 2), (3, 4), (2, 8)])
def test_fewer_resnet_stages_keep_a_finer_keypoint_map(stages, map_side):
    policy = EBVLAPolicy(tiny_config(resnet={"vision_backbone_stages": stages}))
    encoder = policy.model.backbone.rgb_encoders[0]
    features = encoder.backbone(torch.rand(1, *IMAGE_SHAPE))
    assert features.shape[-2:] == (map_side, map_side)
    assert policy.predict_action_chunk(tiny_batch(policy.config, with_action=False)).isfinite().all()


def test_feature_map_tokens_give_one_context_token_per_cell_and_camera():
    cameras = {f"observation.images.{name}": PolicyFeature(FeatureType.VISUAL, IMAGE_SHAPE) for name in "ab"}
    state = {"observation.state": PolicyFeature(FeatureType.STATE, (4,))}
    config = tiny_config(
        resnet={"camera_tokens": "feature_map", "vision_backbone_stages": 3}, input_features=cameras | state
    )
    policy = EBVLAPolicy(config)
    batch = tiny_batch(config)
    context = policy.model.backbone(batch)[0]
    assert context.shape == (2, 2 * 4 * 4 + 1, config.dim_model)  # 4x4 cells per 64 px camera, then p
    # Each camera's tokens come from its own image: changing camera b leaves camera a's 16 tokens alone.
    changed = policy.model.backbone(
        batch | {"observation.images.b": torch.zeros_like(batch["observation.images.b"])}
    )
    torch.testing.assert_close(changed[0][:, :16], context[:, :16])
    assert not torch.allclose(changed[0][:, 16:32], context[:, 16:32])
    loss, _ = policy.forward(batch)
    loss.backward()
    assert policy.model.backbone.rgb_encoders[0].backbone[0].weight.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="`resnet.camera_tokens` must be one of"):
        tiny_config(resnet={"camera_tokens": "patches"})


def test_too_small_images_for_the_kept_stages_are_refused():
    small = {"observation.images.top": PolicyFeature(FeatureType.VISUAL, (3, 24, 24))}
    with pytest.raises(ValueError, match="`resnet.vision_backbone_stages=2`.*larger than 8 px"):
        EBVLAPolicy(
            tiny_config(resnet={"vision_backbone_stages": 2, "resize_shape": (8, 8)}, input_features=small)
        )
    with pytest.raises(ValueError, match="`resnet.vision_backbone_stages` must be 1, 2, 3 or 4"):
        tiny_config(resnet={"vision_backbone_stages": 5})


def test_chunk_hooks_see_every_refined_chunk_until_removed(tiny_policy):
    seen = []
    handle = tiny_policy.register_chunk_hook(
        lambda policy, batch, readout, decision: seen.append((policy, readout, decision))
    )
    batch = tiny_batch(tiny_policy.config, with_action=False)
    tiny_policy.reset()
    for _ in range(tiny_policy.config.n_action_steps + 1):
        tiny_policy.select_action(batch)
    assert len(seen) == 2
    assert all(p is tiny_policy and d is None for p, _, d in seen)
    assert seen[-1][1] is tiny_policy.last_energy
    handle.remove()
    tiny_policy.predict_action_chunk(batch)
    assert len(seen) == 2


def test_restart_spread_is_zero_only_without_noise(tiny_policy):
    batch = tiny_batch(tiny_policy.config, with_action=False)
    spread = tiny_policy.restart_spread(batch, 4, torch.Generator().manual_seed(0))
    assert spread.shape == (batch["observation.state"].shape[0],)
    assert (spread > 0).all()
    with pytest.raises(ValueError, match="n_chains"):
        tiny_policy.restart_spread(batch, 1, torch.Generator())


def test_normalized_energy_is_the_final_energy_plus_the_log_partition_of_prior_chunks(tiny_policy):
    batch = tiny_batch(tiny_policy.config, with_action=False)
    cfg = tiny_policy.config
    final = torch.tensor([1.0, -2.0])[: batch["observation.state"].shape[0]]
    normalized = tiny_policy.normalized_energy(batch, final, 8, torch.Generator().manual_seed(3))
    samples = cfg.init_action_std * torch.randn(
        (final.shape[0], 8, cfg.chunk_size, cfg.action_dim), generator=torch.Generator().manual_seed(3)
    )
    energies = tiny_policy.score_action_chunks(batch, samples)
    expected = final + torch.logsumexp(-energies, dim=1) - math.log(8)
    torch.testing.assert_close(normalized, expected)


def test_context_features_are_the_pooled_last_block_context(tiny_policy):
    batch = tiny_batch(tiny_policy.config, with_action=False)
    features = tiny_policy.context_features(batch)
    with torch.no_grad():
        expected = tiny_policy.model.backbone(batch)[-1].mean(dim=1)
    torch.testing.assert_close(features, expected)
