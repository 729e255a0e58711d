"""The outlier-exposure margin (issue 32): E(a*, corrupted C) is pushed above E(a*, C), off by default."""

import numpy as np
import pytest
import torch

from lerobot_policy_ebvla import EBVLAPolicy
from lerobot_policy_ebvla.energy_head import pooled_context
from lerobot_policy_ebvla.runtime import EnergyOODResponse, OODCalibration, PhaseStatistics
from lerobot_policy_ebvla.runtime.scores import ContextPhaseEnergy
from lerobot_policy_ebvla.training_signal import (
    CORRUPTIONS,
    channel_gain,
    compute_loss,
    context_margin_loss,
    corrupt_observation,
    data_gradient_penalty,
    energy_margin_loss,
    graded_corruption,
    ood_margin_loss,
    random_conv,
    shading,
    shading_log_gains,
    shift,
)

from .conftest import tiny_batch, tiny_config


def test_margin_term_is_off_by_default_and_adds_nothing():
    config = tiny_config()
    assert config.joint_energy.weight == 0.0
    batch = tiny_batch(config, batch_size=4)
    torch.manual_seed(0)
    policy = EBVLAPolicy(config)
    _, info = compute_loss(policy.model, batch, generator=torch.Generator().manual_seed(0))
    assert "ood_margin_loss" not in info


def test_margin_term_is_added_with_its_weight_and_reported():
    batch = tiny_batch(tiny_config(), batch_size=4)
    losses = {}
    for weight in (0.0, 0.5):
        torch.manual_seed(0)
        policy = EBVLAPolicy(tiny_config(joint_energy={"weight": weight, "margin": 100.0}))
        losses[weight] = compute_loss(policy.model, batch, generator=torch.Generator().manual_seed(0))
    (plain, _), (with_term, info) = losses[0.0], losses[0.5]
    # A margin far above any gap of an untrained head: the hinge is active, 100 - gap.
    assert info["ood_margin_loss"] == pytest.approx(100.0 - info["ood_energy_gap"], rel=1e-4)
    assert with_term.item() == pytest.approx(plain.item() + 0.5 * info["ood_margin_loss"], rel=1e-4)


@pytest.mark.parametrize("chunk", ["expert", "refined"])
def test_margin_term_runs_on_either_chunk_and_reaches_the_backbone(chunk):
    torch.manual_seed(0)
    policy = EBVLAPolicy(tiny_config(joint_energy={"weight": 1.0, "margin": 100.0, "chunk": chunk}))
    margin, _ = ood_margin_loss(
        policy.model,
        tiny_batch(policy.config, batch_size=3),
        policy.model.encode_context(tiny_batch(policy.config, batch_size=3)),
        tiny_batch(policy.config, batch_size=3)["action"],
        torch.Generator().manual_seed(0),
        [0.1, 0.1],
    )
    margin.backward()
    assert policy.model.backbone.state_proj.weight.grad.abs().sum() > 0


def test_margin_loss_is_zero_once_the_corrupted_energy_is_a_margin_above():
    clean = torch.tensor([0.0, 1.0])
    assert energy_margin_loss(clean, clean + 2.0, margin=1.0).item() == 0.0
    assert energy_margin_loss(clean, clean + 0.25, margin=1.0).item() == pytest.approx(0.75)


def test_margin_loss_raises_the_corrupted_energy_and_lowers_the_clean_one_alike():
    clean = torch.tensor([0.5, -0.5], requires_grad=True)
    corrupted = torch.tensor([0.0, 0.0], requires_grad=True)
    energy_margin_loss(clean, corrupted, margin=1.0).backward()
    # Descending the loss moves the corrupted energies up and the real ones down, by the same amount: a shift
    # of every energy (a bias) has no gradient.
    assert (corrupted.grad < 0).all() and (clean.grad > 0).all()
    torch.testing.assert_close(clean.grad, -corrupted.grad)


def test_training_with_the_margin_opens_the_gap_on_a_fixed_batch():
    """The tiny policy's GroupNorm ResNet and keypoints barely see its random images, whatever their corruption
    (its context moves by 0.004 of 8 under them): the state's corruption is the one it can learn to tell."""
    torch.manual_seed(0)
    policy = EBVLAPolicy(
        tiny_config(joint_energy={"weight": 1.0, "margin": 1.0, "corruptions": ("state_noise",)})
    )
    batch = tiny_batch(policy.config, batch_size=4)
    optimizer = torch.optim.Adam(policy.parameters(), lr=3e-3)
    gaps = []
    for step in range(30):
        loss, info = compute_loss(policy.model, batch, generator=torch.Generator().manual_seed(step))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        gaps.append(info["ood_energy_gap"])
    assert sum(gaps[-5:]) / 5 > sum(gaps[:5]) / 5 + 0.5


@pytest.mark.parametrize("kind", CORRUPTIONS)
def test_each_corruption_changes_the_observation_and_keeps_images_in_range(kind):
    config = tiny_config()
    batch = tiny_batch(config, batch_size=4)
    cameras = list(config.image_features)
    out = corrupt_observation(batch, cameras, (kind,), torch.Generator().manual_seed(0), "observation.state")
    changed_key = "observation.state" if kind == "state_noise" else cameras[0]
    assert not torch.equal(out[changed_key], batch[changed_key])
    for key in cameras:
        assert out[key].shape == batch[key].shape
        assert out[key].min() >= 0.0 and out[key].max() <= 1.0
    torch.testing.assert_close(out["action"], batch["action"])


def test_corruptions_depend_on_the_seed_only():
    config = tiny_config()
    batch = tiny_batch(config, batch_size=4)
    cameras = list(config.image_features)
    outs = [
        corrupt_observation(
            batch, cameras, CORRUPTIONS, torch.Generator().manual_seed(3), "observation.state"
        )
        for _ in range(2)
    ]
    for key in outs[0]:
        torch.testing.assert_close(outs[0][key], outs[1][key])


def test_random_conv_filters_each_image_with_its_own_kernel_and_rescales_it():
    images = torch.rand(2, 3, 8, 8, generator=torch.Generator().manual_seed(0))
    identity = torch.zeros(3, 3, 3, 3)
    identity[range(3), range(3), 1, 1] = 1.0
    swap = torch.zeros(3, 3, 3, 3)
    swap[[0, 1, 2], [2, 1, 0], 1, 1] = 1.0  # red <- blue, blue <- red
    out = random_conv(images, torch.stack([identity, swap]))
    low, high = images[0].min(), images[0].max()
    torch.testing.assert_close(out[0], (images[0] - low) / (high - low))
    torch.testing.assert_close(
        out[1, 0], ((images[1] - images[1].min()) / (images[1].max() - images[1].min()))[2]
    )


def test_full_strength_is_the_corruption_itself_with_the_same_draws():
    config = tiny_config()
    batch = tiny_batch(config, batch_size=4)
    cameras = list(config.image_features)
    full, strengths = graded_corruption(
        batch, cameras, CORRUPTIONS, torch.Generator().manual_seed(5), "observation.state"
    )
    plain = corrupt_observation(
        batch, cameras, CORRUPTIONS, torch.Generator().manual_seed(5), "observation.state"
    )
    assert strengths is None
    for key in plain:
        torch.testing.assert_close(full[key], plain[key])


def test_graded_corruption_moves_each_observation_its_strength_of_the_way():
    config = tiny_config()
    batch = tiny_batch(config, batch_size=6)
    cameras = list(config.image_features)
    graded, strengths = graded_corruption(
        batch, cameras, CORRUPTIONS, torch.Generator().manual_seed(1), "observation.state", (0.2, 0.6)
    )
    # The corruption's own draws come first, so the same seed gives the full corruption it interpolates to.
    full = corrupt_observation(
        batch, cameras, CORRUPTIONS, torch.Generator().manual_seed(1), "observation.state"
    )
    assert strengths.shape == (6,) and (strengths >= 0.2).all() and (strengths <= 0.6).all()
    for key in [*cameras, "observation.state"]:
        s = strengths.view(-1, *([1] * (batch[key].dim() - 1)))
        torch.testing.assert_close(graded[key], batch[key] + s * (full[key] - batch[key]))
    for key in cameras:
        assert graded[key].min() >= 0.0 and graded[key].max() <= 1.0
    torch.testing.assert_close(graded["action"], batch["action"])


def test_margin_loss_takes_one_margin_per_observation():
    clean = torch.zeros(3)
    corrupted = torch.tensor([0.1, 0.5, 2.0])
    loss = energy_margin_loss(clean, corrupted, margin=torch.tensor([0.2, 0.4, 1.0]))
    assert loss.item() == pytest.approx(0.1 / 3)


@pytest.mark.parametrize("target", ["observation", "head"])
def test_graded_corruption_asks_each_observation_for_its_strength_of_the_margin(target):
    """At strength s the hinge compares the gap with s m, on the copy moved s of the way (here s = 0.3 for
    all, so the loss is computed from the same draws by hand)."""
    torch.manual_seed(0)
    config = tiny_config(
        joint_energy={
            "weight": 1.0,
            "margin": 2.0,
            "target": target,
            "corruptions": ("state_noise", "channel_gain"),
            "corruption_strength": (0.3, 0.3),
        },
    )
    policy = EBVLAPolicy(config).eval()
    model = policy.model
    batch = tiny_batch(config, batch_size=4)
    shifted_batch, strengths = graded_corruption(
        batch,
        list(config.image_features),
        config.joint_energy.corruptions,
        torch.Generator().manual_seed(7),
        "observation.state",
        config.joint_energy.corruption_strength,
    )
    torch.testing.assert_close(strengths, torch.full((4,), 0.3))
    with torch.no_grad():
        if target == "observation":
            loss, _ = context_margin_loss(model, batch, torch.Generator().manual_seed(7))
            energy = model.context_energy
            clean = energy(pooled_context(model.observation_encoder(batch)))
            shifted = energy(pooled_context(model.observation_encoder(shifted_batch)))
            expected = torch.relu(0.6 - (shifted - clean)).mean() + clean.pow(2).mean()
        else:
            kv = model.encode_context(batch)
            loss, _ = ood_margin_loss(model, batch, kv, batch["action"], torch.Generator().manual_seed(7), [])
            clean = model.head(batch["action"], kv).mean(dim=-1)
            shifted = model.head(batch["action"], model.encode_context(shifted_batch)).mean(dim=-1)
            expected = torch.relu(0.6 - (shifted - clean)).mean()
    torch.testing.assert_close(loss, expected)


def test_channel_gain_and_shift_do_what_they_say():
    images = torch.full((1, 3, 4, 4), 0.5)
    torch.testing.assert_close(
        channel_gain(images, torch.tensor([[2.0, 1.0, 0.0]]))[0, :, 0, 0], torch.tensor([1.0, 0.5, 0.0])
    )
    moved = shift(torch.arange(16.0).view(1, 1, 4, 4), [(1, 0)])
    assert moved[0, 0, 0].eq(0).all() and torch.equal(moved[0, 0, 1], torch.arange(4.0))


def test_shading_scales_every_channel_by_one_smooth_field_of_both_signs():
    images = torch.full((16, 3, 32, 32), 0.4)
    fields = shading_log_gains(16, 32, 32, torch.Generator().manual_seed(0), images)
    out = shading(images, fields)
    # Achromatic: where nothing clips, every channel is the image times the same gain.
    torch.testing.assert_close(out[:, 0], out[:, 1])
    unclipped = out[:, 0] < 1.0
    torch.testing.assert_close(out[:, 0][unclipped], (0.4 * fields.exp())[unclipped])
    # Smooth: a field changes little from one pixel to the next and much across the image.
    assert (fields[:, 1:] - fields[:, :-1]).abs().max() < 0.3
    spread = fields.amax(dim=(1, 2)) - fields.amin(dim=(1, 2))
    assert spread.min() > 0.3
    # Brighter and darker sides alike.
    assert (fields.mean(dim=(1, 2)) > 0).any() and (fields.mean(dim=(1, 2)) < 0).any()


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("weight", -0.1),
        ("margin", 0.0),
        ("corruptions", ("fog",)),
        ("chunk", "prior"),
        ("target", "action"),
        ("corruption_strength", (0.0, 1.0)),
        ("corruption_strength", (0.6, 0.3)),
        ("corruption_strength", (0.5, 1.5)),
        ("gradient_penalty", -1.0),
        ("gradient_penalty_every", 0),
        ("encoder_resize_shape", (32,)),
    ],
)
def test_margin_fields_are_validated_by_name(field, value):
    with pytest.raises(ValueError, match=f"`joint_energy.{field}`"):
        tiny_config(joint_energy={field: value})


@pytest.mark.parametrize("target", ["head", "context", "context_backbone"])
def test_gradient_penalty_needs_the_observation_encoder(target):
    with pytest.raises(
        ValueError, match="`joint_energy.gradient_penalty`.*`joint_energy.target='observation'`"
    ):
        tiny_config(joint_energy={"weight": 0.01, "target": target, "gradient_penalty": 0.1})
    with pytest.raises(ValueError, match="`joint_energy.weight` > 0"):
        tiny_config(joint_energy={"target": "observation", "gradient_penalty": 0.1})


def test_gradient_penalty_is_the_squared_image_gradient_per_observation_summed_over_cameras():
    images = [torch.rand(2, 3, 4, 4, requires_grad=True), torch.rand(2, 1, 2, 2, requires_grad=True)]
    weights = [torch.randn(3, 4, 4), torch.randn(1, 2, 2)]
    # E_i = sum_x w x + (sum_x x)^2 / 2 on the first camera: gradient w + sum_x x, a different one per observation.
    energy = sum((w * x).flatten(1).sum(1) for w, x in zip(weights, images, strict=True))
    energy = energy + images[0].flatten(1).sum(1).pow(2) / 2
    penalty = data_gradient_penalty(energy, images)
    expected = [(weights[0] + images[0][i].sum()).pow(2).sum() + weights[1].pow(2).sum() for i in range(2)]
    torch.testing.assert_close(penalty, torch.stack(expected).mean())
    # Kept in the graph: training can lower it (here through the first camera's second-order term).
    penalty.backward()
    assert images[0].grad.abs().sum() > 0


def policy_with_gradient_penalty(penalty: float, **fields) -> EBVLAPolicy:
    torch.manual_seed(0)
    return EBVLAPolicy(
        tiny_config(
            joint_energy={"weight": 1.0, "target": "observation", "gradient_penalty": penalty},
            **fields,
        )
    )


def image_gradient_penalty(policy: EBVLAPolicy, batch: dict) -> float:
    """The penalty's value at `batch`'s images, whatever the policy's own weight on it."""
    model = policy.model
    images = {key: batch[key].clone().requires_grad_(True) for key in policy.config.image_features}
    energy = model.context_energy(pooled_context(model.observation_encoder({**batch, **images})))
    return data_gradient_penalty(energy, list(images.values())).item()


def test_gradient_penalty_is_added_to_the_margin_and_trains_the_observation_encoder_only():
    batch = tiny_batch(tiny_config(), batch_size=3)
    losses = {}
    for penalty in (0.0, 50.0):
        policy = policy_with_gradient_penalty(penalty)
        losses[penalty], _ = context_margin_loss(policy.model, batch, torch.Generator().manual_seed(0))
    value = image_gradient_penalty(policy_with_gradient_penalty(0.0), batch)
    assert value > 0
    assert losses[50.0].item() == pytest.approx(losses[0.0].item() + 50.0 * value, rel=1e-4)
    losses[50.0].backward()
    assert all(p.grad is None for p in policy.model.backbone.parameters())
    assert all(p.grad is None for p in policy.model.head.parameters())
    assert policy.model.observation_encoder.state_proj.weight.grad.abs().sum() > 0


def test_a_lazy_gradient_penalty_is_taken_one_step_in_k_at_k_times_its_weight():
    """`gradient_penalty_every=k`: the steps whose count is a multiple of k carry k gamma times the penalty, the
    others none, so that the penalty's expected gradient is the eager one's."""
    batch = tiny_batch(tiny_config(), batch_size=3)
    value = image_gradient_penalty(policy_with_gradient_penalty(0.0), batch)
    eager = policy_with_gradient_penalty(0.0).model
    torch.manual_seed(0)
    lazy_fields = {
        "weight": 1.0,
        "target": "observation",
        "gradient_penalty": 2.0,
        "gradient_penalty_every": 3,
    }
    lazy = EBVLAPolicy(tiny_config(joint_energy=lazy_fields)).model
    for steps, weight in ((0, 3 * 2.0), (1, 0.0), (2, 0.0), (3, 3 * 2.0)):
        eager.train_steps.fill_(steps)
        lazy.train_steps.fill_(steps)
        without, _ = context_margin_loss(eager, batch, torch.Generator().manual_seed(0))
        with_lazy, _ = context_margin_loss(lazy, batch, torch.Generator().manual_seed(0))
        assert with_lazy.item() == pytest.approx(without.item() + weight * value, rel=1e-4), steps


def test_the_observation_encoder_reads_frames_at_its_own_size():
    """`encoder_resize_shape`: E_c's encoder resizes the frames to its own side (its spatial softmax fitted to
    that map) while the policy's backbone reads them at their stored size."""
    torch.manual_seed(0)
    fields = {"weight": 0.01, "target": "observation", "encoder_resize_shape": (40, 40)}
    policy = EBVLAPolicy(tiny_config(joint_energy=fields))
    encoder = policy.model.observation_encoder.rgb_encoders[0]
    assert tuple(encoder.resize.size) == (40, 40)
    assert policy.model.backbone.rgb_encoders[0].resize is None  # the policy's frames at their stored size
    batch = tiny_batch(policy.config, batch_size=2)
    energy = policy.model.context_energy_of(batch, None)
    assert energy.shape == (2,) and torch.isfinite(energy).all()
    with pytest.raises(ValueError, match="`joint_energy.encoder_resize_shape`.*target='observation'"):
        tiny_config(joint_energy={"weight": 0.01, "target": "context", "encoder_resize_shape": (40, 40)})
    with pytest.raises(ValueError, match="larger than 32 px.*after `joint_energy.encoder_resize_shape`"):
        EBVLAPolicy(tiny_config(joint_energy={**fields, "encoder_resize_shape": (24, 24)}))


def test_descending_the_gradient_penalty_flattens_the_context_energy_at_the_images():
    """The penalty reaches the observation encoder's image weights through the second derivative (the feature
    map's tokens, which see the tiny policy's random images more than its keypoints do): steps on it alone make
    E_c flatter at the images."""
    policy = policy_with_gradient_penalty(1.0, resnet={"camera_tokens": "feature_map"})
    model = policy.model
    batch = tiny_batch(policy.config, batch_size=4)
    optimizer = torch.optim.SGD(model.observation_encoder.parameters(), lr=0.5)
    values = []
    for _ in range(5):
        images = {key: batch[key].clone().requires_grad_(True) for key in policy.config.image_features}
        energy = model.context_energy(pooled_context(model.observation_encoder({**batch, **images})))
        penalty = data_gradient_penalty(energy, list(images.values()))
        optimizer.zero_grad()
        penalty.backward()
        values.append(penalty.item())
        optimizer.step()
    image_weights = [p for name, p in model.observation_encoder.named_parameters() if "rgb_encoder" in name]
    assert image_weights and any(p.grad.abs().sum() > 0 for p in image_weights)
    assert values[-1] < 0.5 * values[0]


def policy_after_the_context_margin(target: str) -> EBVLAPolicy:
    """A tiny policy with the joint energy's margin on `target`, after one backward pass of that margin alone."""
    torch.manual_seed(0)
    policy = EBVLAPolicy(tiny_config(joint_energy={"weight": 1.0, "target": target}))
    margin, _ = context_margin_loss(policy.model, tiny_batch(policy.config, batch_size=3), torch.Generator())
    margin.backward()
    return policy


def test_context_margin_trains_only_the_context_energy():
    policy = policy_after_the_context_margin("context")
    assert all(p.grad is None for p in policy.model.backbone.parameters())
    assert all(p.grad is None for p in policy.model.head.parameters())
    assert any(
        p.grad is not None and p.grad.abs().sum() > 0 for p in policy.model.context_energy.parameters()
    )


def test_context_margin_through_the_backbone_trains_the_backbone_and_the_context_energy_not_the_head():
    policy = policy_after_the_context_margin("context_backbone")
    config = policy.config
    assert policy.model.backbone.state_proj.weight.grad.abs().sum() > 0
    assert all(p.grad is None for p in policy.model.head.parameters())
    # In a training step the margin reads the context of the step's own backbone pass.
    policy.zero_grad(set_to_none=True)
    loss, info = compute_loss(
        policy.model, tiny_batch(config, batch_size=3), torch.Generator().manual_seed(0)
    )
    assert "ood_margin_loss" in info and torch.isfinite(loss)


def test_observation_margin_trains_the_observation_encoder_and_the_context_energy_only():
    policy = policy_after_the_context_margin("observation")
    assert all(p.grad is None for p in policy.model.backbone.parameters())
    assert all(p.grad is None for p in policy.model.head.parameters())
    assert policy.model.observation_encoder.state_proj.weight.grad.abs().sum() > 0
    assert policy.model.context_energy.net[-1].weight.grad.abs().sum() > 0


def test_with_the_observation_energy_the_policy_starts_and_trains_exactly_as_without_the_term():
    """Same seed: the backbone and head start from the same weights and get the same gradients, so the actions
    differ from a policy without the term only through what they share with nothing (the observation encoder
    and E_c are built last and the corruptions drawn after the action losses)."""
    policies = {}
    for name, fields in (("without", {}), ("observation", {"target": "observation"})):
        torch.manual_seed(0)
        config = tiny_config(joint_energy={"weight": 1.0 if fields else 0.0, **fields})
        policies[name] = EBVLAPolicy(config)
        loss, _ = compute_loss(
            policies[name].model, tiny_batch(config, batch_size=3), torch.Generator().manual_seed(0)
        )
        loss.backward()
    without, observation = policies["without"].model, policies["observation"].model
    for part in ("backbone", "head"):
        ours = dict(getattr(observation, part).named_parameters())
        for name, param in getattr(without, part).named_parameters():
            torch.testing.assert_close(ours[name], param)
            if param.grad is not None:
                torch.testing.assert_close(ours[name].grad, param.grad)


@pytest.mark.parametrize("target", ["context", "context_backbone", "observation"])
def test_joint_final_energy_is_the_head_energy_plus_the_context_energy(target):
    torch.manual_seed(0)
    policy = EBVLAPolicy(tiny_config(joint_energy={"weight": 1.0, "target": target})).eval()
    batch = tiny_batch(policy.config, batch_size=3, with_action=False)
    chunk, readout = policy.predict_action_chunk(
        batch, generator=torch.Generator().manual_seed(0), return_energy=True
    )
    head = policy.score_action_chunks(batch, chunk[:, None])[:, 0]
    context = policy.model.context_energy_of(batch, policy.context_features(batch))
    torch.testing.assert_close(readout.final_energy, head + context, rtol=1e-4, atol=1e-4)
    # The readout carries E_c apart, so that records can split the joint energy.
    torch.testing.assert_close(readout.context_energy, context, rtol=1e-5, atol=1e-5)
    if target == "observation":  # E_c reads the observation encoder's context, not the policy's
        other = policy.model.context_energy(policy.context_features(batch))
        assert not torch.allclose(context, other)


def test_without_the_context_variant_the_policy_has_no_context_energy():
    assert EBVLAPolicy(tiny_config(joint_energy={"weight": 1.0})).model.context_energy is None
    policy = EBVLAPolicy(tiny_config(joint_energy={"target": "context"})).eval()
    assert policy.model.context_energy is None
    batch = tiny_batch(policy.config, batch_size=2, with_action=False)
    _, readout = policy.predict_action_chunk(batch, return_energy=True)
    assert readout.context_energy is None


def test_adaptive_restarts_keep_the_observations_context_energy():
    """E_c depends on the observation only: a restarted chunk keeps it, and the readout still splits."""
    torch.manual_seed(0)
    config = tiny_config(
        joint_energy={"weight": 1.0, "target": "observation"},
        num_restarts=3,
        restart_energy_threshold=-1e9,
    )
    policy = EBVLAPolicy(config).eval()
    batch = tiny_batch(config, batch_size=2, with_action=False)
    chunk, readout = policy.predict_action_chunk(
        batch, generator=torch.Generator().manual_seed(0), return_energy=True
    )
    assert readout.chains.tolist() == [3, 3]
    context = policy.model.context_energy_of(batch, None)
    torch.testing.assert_close(readout.context_energy, context)
    head = policy.score_action_chunks(batch, chunk[:, None])[:, 0]
    torch.testing.assert_close(readout.final_energy, head + context, rtol=1e-4, atol=1e-4)


def test_the_policy_monitors_its_context_energy_against_the_vanilla_band_at_its_chunk_index():
    """A context-energy calibration reads the readout's E_c: a chunk whose E_c lies far above the vanilla band at
    its chunk index is flagged, with z = (E_c - mu_v[0]) / sigma_v[0]."""
    torch.manual_seed(0)
    policy = EBVLAPolicy(tiny_config(joint_energy={"weight": 1.0, "target": "observation"})).eval()
    batch = tiny_batch(policy.config, batch_size=2, with_action=False)
    context = policy.model.context_energy_of(batch, None).detach().double().numpy()
    # The vanilla band at chunk index 0 sits one unit below this batch's E_c, 0.1 wide.
    band = PhaseStatistics(mean=(float(context.mean()) - 1.0,), std=(0.1,))
    calibration = OODCalibration(mu_v=0.0, sigma_v=1.0, score=ContextPhaseEnergy(band))
    policy.ood_response = EnergyOODResponse(policy.config, calibration)
    policy.predict_action_chunk(batch)
    decision = policy.last_ood_decision
    np.testing.assert_allclose(decision.scores.numpy(), (context - band.mean[0]) / 0.1, rtol=1e-4)
    assert decision.flagged.all()
