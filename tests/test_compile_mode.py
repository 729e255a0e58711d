"""`compile_mode`: a compiled chunk (context encoding and every MCMC step's energy) is the eager chunk.

The inductor tests compile the light backbone's smallest policy once per module (about 25 s on a 2-core CPU with
an empty inductor cache). The other tests build their graphs with `aot_eager`, which traces what inductor would
compile but generates no code, or with a stand-in for a CUDA-graph replay, so they run in seconds.
"""

import json
import logging
import os

import pytest
import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.utils.constants import OBS_LANGUAGE_ATTENTION_MASK, OBS_LANGUAGE_TOKENS
from torch.utils._pytree import tree_flatten, tree_unflatten

from lerobot_policy_ebvla import EBVLAConfig, EBVLAPolicy, compile_ebvla
from lerobot_policy_ebvla.compile_ebvla import compile_static
from lerobot_policy_ebvla.modeling_ebvla import EBVLA
from lerobot_policy_ebvla.presets import light_policy_config

from .conftest import tiny_batch, tiny_config
from .test_backbone_vlm import vlm_config, write_tiny_language_model

# fp32, the same seed: inductor's fused kernels reassociate sums (measured: up to 2e-7 in the actions of the
# light head, 2e-5 over 15 steps of the paper's head; research/docs/benchmarks_speed.md).
TOL = {"atol": 1e-5, "rtol": 1e-5}
# One ResNet stage: the smallest light backbone, so inductor compiles it quickly.
SMALL = {"resnet": {"vision_backbone_stages": 1}}
BATCH_SIZE = 2


def make_policy(**overrides) -> EBVLAPolicy:
    torch.manual_seed(0)
    return EBVLAPolicy(tiny_config(**SMALL, **overrides)).eval()


def chunk(policy: EBVLAPolicy, batch: dict, seed: int = 0):
    actions, readout = policy.predict_action_chunk(
        batch, generator=torch.Generator().manual_seed(seed), return_energy=True
    )
    return actions, readout.initial_energy, readout.final_energy


def refinement(model: EBVLA, batch: dict, seed: int = 0):
    """Context and MCMC chain of `generate_actions` (its inference path), with every step's energy."""
    with torch.no_grad():
        kv = model._inference_context(batch)
    cfg = model.config
    initial = torch.randn(
        BATCH_SIZE, cfg.chunk_size, cfg.action_dim, generator=torch.Generator().manual_seed(1)
    )
    result = model.refine(
        kv,
        initial,
        [cfg.inference_step_size] * cfg.inference_mcmc_steps,
        torch.Generator().manual_seed(seed),
        energy_fn=model._inference_energy_fn(kv),
    )
    return kv, result


def clear_compiled():
    compile_ebvla.compiled_head_energy.cache_clear()
    compile_ebvla.compiled_context_encoder.cache_clear()
    compile_ebvla.effective_compile_mode.cache_clear()


@pytest.fixture(scope="module")
def eager() -> EBVLAPolicy:
    return make_policy()


@pytest.fixture(scope="module")
def compiled() -> tuple[EBVLAPolicy, int]:
    """The eager policy's weights with `compile_mode="default"` (inductor), and the graphs its first chunk built."""
    policy = make_policy(compile_mode="default")
    torch._dynamo.reset()  # graphs an earlier test built for the same shapes would be reused, not counted
    graphs = torch._dynamo.utils.counters["stats"]["unique_graphs"]
    chunk(policy, tiny_batch(policy.config, batch_size=BATCH_SIZE, with_action=False))
    return policy, torch._dynamo.utils.counters["stats"]["unique_graphs"] - graphs


def test_a_compiled_chunk_runs_compiled_graphs(compiled):
    policy, graphs = compiled
    # One for the context encoding, one for the energy's forward and backward (more where dynamo breaks a graph).
    assert graphs >= 2, f"the first compiled chunk built {graphs} graphs"
    assert all(p.requires_grad and p.grad is None for p in policy.parameters())


def test_compiled_chunk_gives_the_eager_actions_and_energies(eager, compiled):
    batch = tiny_batch(eager.config, batch_size=BATCH_SIZE, seed=3, with_action=False)
    for got, expected in zip(chunk(compiled[0], batch), chunk(eager, batch), strict=True):
        torch.testing.assert_close(got, expected, **TOL)


def test_compiled_context_and_step_energies_equal_eager(eager, compiled):
    batch = tiny_batch(eager.config, batch_size=BATCH_SIZE, seed=4, with_action=False)
    kv, result = refinement(compiled[0].model, batch)
    eager_kv, expected = refinement(eager.model, batch)
    torch.testing.assert_close(kv, eager_kv, **TOL)
    assert result.step_energies.shape == (eager.config.inference_mcmc_steps, BATCH_SIZE)
    torch.testing.assert_close(result.step_energies, expected.step_energies, **TOL)
    torch.testing.assert_close(result.actions, expected.actions, **TOL)


def test_two_compiled_chunks_keep_their_own_energies(eager, compiled):
    policy = compiled[0]
    first, second = (
        tiny_batch(policy.config, batch_size=BATCH_SIZE, seed=s, with_action=False) for s in (5, 6)
    )
    policy.reset()
    policy.select_action(first, generator=torch.Generator().manual_seed(0))
    readout = policy.last_energy
    kept = (readout.initial_energy.clone(), readout.final_energy.clone())
    policy.reset()
    policy.select_action(second, generator=torch.Generator().manual_seed(0))
    assert policy.last_energy is not readout
    assert not torch.equal(policy.last_energy.final_energy, readout.final_energy)
    assert torch.equal(readout.initial_energy, kept[0]) and torch.equal(readout.final_energy, kept[1])
    torch.testing.assert_close(kept, chunk(eager, first)[1:], **TOL)


def replaying(fn):
    """Runs `fn` eagerly but returns its outputs in the same tensors at every call, as a CUDA-graph replay
    does: whatever a caller kept from an earlier call is overwritten by the next one."""
    buffers = []

    def replay(*args):
        flat, spec = tree_flatten(fn(*args))
        if not buffers:
            buffers.extend(torch.empty_like(t, requires_grad=False) for t in flat)
        for buffer, t in zip(buffers, flat, strict=True):
            buffer.copy_(t)  # differentiable: the energy's backward still reaches the actions
        return tree_unflatten(list(buffers), spec)

    return replay


@pytest.fixture
def replayed_graphs(monkeypatch):
    """The compiled encoder and energy replaced by stand-ins that overwrite their outputs at every call."""
    encoder, energy = replaying(EBVLA.encode_context), replaying(compile_ebvla.head_energy)
    monkeypatch.setattr(compile_ebvla, "compiled_context_encoder", lambda mode: encoder)
    monkeypatch.setattr(compile_ebvla, "compiled_head_energy", lambda mode: energy)


def test_outputs_of_a_replayed_graph_are_copied_out(eager, replayed_graphs):
    model = make_policy(compile_mode="reduce-overhead").model
    first, second = (
        tiny_batch(model.config, batch_size=BATCH_SIZE, seed=s, with_action=False) for s in (7, 8)
    )
    with torch.no_grad():
        kv = model._inference_context(first)
        model._inference_context(second)
        torch.testing.assert_close(kv, eager.model.encode_context(first), **TOL)
    energy_fn = model._inference_energy_fn(kv)
    actions = torch.randn(2, BATCH_SIZE, model.config.chunk_size, model.config.action_dim)
    energies = [energy_fn(a) for a in actions]
    with torch.no_grad():
        torch.testing.assert_close(energies[0], eager.model.head(actions[0], kv), **TOL)


def test_context_features_of_a_replayed_graph_are_copied_out(eager, replayed_graphs):
    """The pooled context a context-distance calibration scores comes from the compiled encoding's pass."""
    model = make_policy(compile_mode="reduce-overhead").model
    first, second = (
        tiny_batch(model.config, batch_size=BATCH_SIZE, seed=s, with_action=False) for s in (14, 15)
    )
    with torch.no_grad():
        _, features = model._inference_context(first, True)
        model._inference_context(second, True)
    torch.testing.assert_close(features, eager.context_features(first), **TOL)


def test_two_replayed_chunks_keep_their_own_energies(eager, replayed_graphs):
    policy = make_policy(compile_mode="reduce-overhead")
    first, second = (
        tiny_batch(policy.config, batch_size=BATCH_SIZE, seed=s, with_action=False) for s in (9, 10)
    )
    _, *energies = chunk(policy, first)
    kept = [e.clone() for e in energies]
    chunk(policy, second)
    torch.testing.assert_close(energies, kept, atol=0, rtol=0)
    torch.testing.assert_close(energies, list(chunk(eager, first)[1:]), **TOL)


def aot_eager_compiles(monkeypatch) -> list:
    """torch.compile records the mode it gets and builds an `aot_eager` graph (no code generation)."""
    real_compile, modes = torch.compile, []

    def compile_aot_eager(fn, mode=None, **kwargs):
        modes.append(mode)
        return real_compile(fn, backend="aot_eager", **kwargs)

    monkeypatch.setattr(torch, "compile", compile_aot_eager)
    return modes


@pytest.mark.parametrize(
    ("mode", "runs_as"),
    [
        ("default", None),
        ("max-autotune-no-cudagraphs", "max-autotune-no-cudagraphs"),
        ("reduce-overhead", None),
        ("max-autotune", "max-autotune-no-cudagraphs"),
    ],
)
def test_without_cuda_a_graph_mode_runs_inductor_without_graphs(eager, monkeypatch, caplog, mode, runs_as):
    """The encoder and the energy reach torch.compile in the mode that runs here, and give eager's chunk."""
    modes = aot_eager_compiles(monkeypatch)
    clear_compiled()  # built once per mode and process: build them here
    try:
        batch = tiny_batch(eager.config, batch_size=BATCH_SIZE, seed=11, with_action=False)
        with caplog.at_level(logging.WARNING, logger=compile_ebvla.__name__):
            got = chunk(make_policy(compile_mode=mode), batch)
    finally:
        clear_compiled()  # no later test may get the aot_eager graphs
    assert modes == [runs_as, runs_as]
    assert (f"`compile_mode={mode!r}` replays CUDA graphs" in caplog.text) == (
        mode in ("reduce-overhead", "max-autotune")
    )
    for got_tensor, expected in zip(got, chunk(eager, batch), strict=True):
        torch.testing.assert_close(got_tensor, expected, **TOL)


def test_on_cuda_a_graph_mode_keeps_its_graphs(eager, monkeypatch):
    """The CUDA-graph path (parameters marked static, outputs copied out) run on CPU through `aot_eager`."""
    modes = aot_eager_compiles(monkeypatch)
    clear_compiled()
    monkeypatch.setattr(compile_ebvla, "effective_compile_mode", lambda mode, device_type: mode)
    try:
        batch = tiny_batch(eager.config, batch_size=BATCH_SIZE, seed=13, with_action=False)
        got = chunk(make_policy(compile_mode="reduce-overhead"), batch)
    finally:
        compile_ebvla.compiled_head_energy.cache_clear()
        compile_ebvla.compiled_context_encoder.cache_clear()
    assert modes == ["reduce-overhead", "reduce-overhead"]
    for got_tensor, expected in zip(got, chunk(eager, batch), strict=True):
        torch.testing.assert_close(got_tensor, expected, **TOL)


def test_an_unknown_compile_mode_is_rejected():
    with pytest.raises(ValueError, match="`compile_mode` must be one of"):
        tiny_config(compile_mode="cudagraphs")


def test_a_mode_this_torch_does_not_know_is_rejected_naming_the_field(monkeypatch):
    monkeypatch.setattr(torch._inductor, "list_mode_options", lambda: {"default": {}, "reduce-overhead": {}})
    with pytest.raises(ValueError, match="`compile_mode='max-autotune'` is not a mode of torch"):
        compile_static(compile_ebvla.head_energy, "max-autotune")


@pytest.mark.parametrize(
    ("legacy", "compile_mode"),
    [
        ({"compile_refinement": True, "compile_refinement_mode": "reduce-overhead"}, "reduce-overhead"),
        ({"compile_refinement": True}, "default"),
        ({"compile_refinement": False, "compile_refinement_mode": "default"}, "off"),
    ],
)
def test_deprecated_compile_fields_map_to_compile_mode(tmp_path, legacy, compile_mode):
    write_legacy_config(tmp_path, **legacy)
    with pytest.warns(FutureWarning, match="saved before"):
        config = EBVLAConfig.from_pretrained(tmp_path)
    assert config.compile_mode == compile_mode
    assert not hasattr(config, "compile_refinement") and not hasattr(config, "compile_refinement_mode")


def test_deprecated_fields_that_contradict_compile_mode_are_rejected(tmp_path):
    write_legacy_config(
        tmp_path, compile_mode="default", compile_refinement=True, compile_refinement_mode="max-autotune"
    )
    with pytest.raises(ValueError, match="`compile_refinement=True`.*`compile_mode` is 'default'"):
        EBVLAConfig.from_pretrained(tmp_path)


def test_an_unknown_deprecated_mode_is_rejected_naming_the_field(tmp_path):
    write_legacy_config(tmp_path, compile_refinement=True, compile_refinement_mode="cudagraphs")
    with pytest.raises(ValueError, match="`compile_refinement_mode`"):
        EBVLAConfig.from_pretrained(tmp_path)


def write_legacy_config(path, **legacy) -> None:
    """config.json as a checkpoint saved before `compile_mode` holds it."""
    tiny_config().save_pretrained(path)
    config_file = path / "config.json"
    saved = json.loads(config_file.read_text())
    del saved["compile_mode"]
    config_file.write_text(json.dumps({**saved, **legacy}))


def test_a_checkpoint_saved_with_compile_refinement_loads_with_compile_mode(tmp_path):
    """What `lerobot-eval --policy.path` reads; saving again stores `compile_mode`."""
    write_legacy_config(tmp_path, compile_refinement=True, compile_refinement_mode="reduce-overhead")
    with pytest.warns(FutureWarning, match="compile_mode='reduce-overhead'"):
        config = EBVLAConfig.from_pretrained(tmp_path)
    assert isinstance(config, EBVLAConfig) and config.compile_mode == "reduce-overhead"
    config.save_pretrained(tmp_path / "again")
    saved = json.loads((tmp_path / "again" / "config.json").read_text())
    assert saved["compile_mode"] == "reduce-overhead" and "compile_refinement" not in saved


def test_a_policy_saved_with_compile_refinement_loads(tmp_path, eager):
    eager.save_pretrained(tmp_path)
    saved = json.loads((tmp_path / "config.json").read_text())
    del saved["compile_mode"]
    (tmp_path / "config.json").write_text(json.dumps({**saved, "compile_refinement": False}))
    with pytest.warns(FutureWarning, match="compile_mode='off'"):
        loaded = EBVLAPolicy.from_pretrained(tmp_path)
    batch = tiny_batch(eager.config, batch_size=BATCH_SIZE, seed=12, with_action=False)
    torch.testing.assert_close(chunk(loaded.eval(), batch), chunk(eager, batch), atol=0, rtol=0)


# Inductor compiles the tiny VLM for 1 minute (a chunk) to 4 (a training step) on a 2-core CPU: opt in.
inductor_opt_in = pytest.mark.skipif(
    os.environ.get("EBVLA_TEST_INDUCTOR") != "1", reason="compiles the tiny VLM with inductor; opt in"
)


def vlm_policy(lm_path, **overrides) -> EBVLAPolicy:
    """The tiny VLM of tests/test_backbone_vlm.py."""
    torch.manual_seed(0)
    return EBVLAPolicy(vlm_config(lm_path, **overrides)).eval()


def vlm_pair(tmp_path, with_action: bool, **compiled) -> tuple[EBVLAPolicy, EBVLAPolicy, dict]:
    """An eager tiny VLM, the same weights with the `compiled` fields, and a batch with an instruction."""
    lm_path = write_tiny_language_model(tmp_path / "tiny_lm")
    eager_vlm, compiled_vlm = vlm_policy(lm_path), vlm_policy(lm_path, **compiled)
    g = torch.Generator().manual_seed(0)
    batch = tiny_batch(eager_vlm.config, batch_size=BATCH_SIZE, with_action=with_action)
    batch[OBS_LANGUAGE_TOKENS] = torch.randint(0, 128, (BATCH_SIZE, 8), generator=g)
    batch[OBS_LANGUAGE_ATTENTION_MASK] = torch.arange(8).expand(BATCH_SIZE, 8) < 5
    return eager_vlm, compiled_vlm, batch


@pytest.mark.slow
@inductor_opt_in
def test_compiled_vlm_chunk_gives_the_eager_actions_and_energies(tmp_path):
    eager_vlm, compiled_vlm, batch = vlm_pair(tmp_path, with_action=False, compile_mode="default")
    for got, expected in zip(chunk(compiled_vlm, batch), chunk(eager_vlm, batch), strict=True):
        torch.testing.assert_close(got, expected, **TOL)


# `train_compile_mode`: the backbone pass and the warm-up MCMC steps of a training step, compiled.


def training_step(policy: EBVLAPolicy, batch: dict) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """One training step's loss and the gradient of every trainable weight."""
    policy.train()
    policy.zero_grad(set_to_none=True)
    loss, _ = policy.forward(batch)
    loss.backward()
    return loss.detach(), {n: p.grad.clone() for n, p in policy.named_parameters() if p.grad is not None}


@pytest.mark.parametrize("mode", ["default", "reduce-overhead"])
def test_a_compiled_training_step_gives_the_eager_loss_and_gradients(monkeypatch, mode):
    """Two steps (K, alpha, a^(0) and the noise drawn from the same saved seeds), traced through `aot_eager`;
    "reduce-overhead" keeps its CUDA-graph path here (static parameters, outputs copied out)."""
    modes = aot_eager_compiles(monkeypatch)
    clear_compiled()
    monkeypatch.setattr(compile_ebvla, "effective_compile_mode", lambda mode, device_type: mode)
    eager_policy, compiled_policy = make_policy(), make_policy(train_compile_mode=mode)
    try:
        for seed in (21, 22):
            batch = tiny_batch(eager_policy.config, batch_size=BATCH_SIZE, seed=seed)
            eager_loss, eager_grads = training_step(eager_policy, batch)
            compiled_loss, compiled_grads = training_step(compiled_policy, batch)
            torch.testing.assert_close(compiled_loss, eager_loss, **TOL)
            assert compiled_grads.keys() == eager_grads.keys() and eager_grads
            torch.testing.assert_close(compiled_grads, eager_grads, **TOL)
    finally:  # no later test may get the aot_eager graphs
        compile_ebvla.compiled_head_energy.cache_clear()
        compile_ebvla.compiled_context_encoder.cache_clear()
    # The context encoder and the warm-up steps' energy, each built once ("default" is torch.compile's None).
    assert modes == [None if mode == "default" else mode] * 2


def test_a_compiled_training_step_refuses_a_bf16_policy_on_the_cpu():
    policy = make_policy(train_compile_mode="default").to(torch.bfloat16)
    batch = tiny_batch(policy.config, batch_size=BATCH_SIZE)
    batch = {k: v.to(torch.bfloat16) if v.is_floating_point() else v for k, v in batch.items()}
    with pytest.raises(ValueError, match="`train_compile_mode='default'` is not supported for a bf16 policy"):
        policy.train().forward(batch)


def test_training_refuses_the_chunk_graph_mode():
    with pytest.raises(ValueError, match="`train_compile_mode` must be one of"):
        tiny_config(train_compile_mode="chunk-graph")


@pytest.mark.slow
@inductor_opt_in
def test_compiled_vlm_training_step_gives_the_eager_loss_and_gradients(tmp_path):
    """The LoRA language model's backward runs through inductor's generated kernels, as on a GPU."""
    eager_vlm, compiled_vlm, batch = vlm_pair(tmp_path, with_action=True, train_compile_mode="default")
    eager_loss, eager_grads = training_step(eager_vlm, batch)
    compiled_loss, compiled_grads = training_step(compiled_vlm, batch)
    torch.testing.assert_close(compiled_loss, eager_loss, **TOL)
    assert any("lora_" in name for name in eager_grads)
    torch.testing.assert_close(compiled_grads, eager_grads, **TOL)


def test_the_light_presets_training_step_compiled_by_inductor_gives_the_eager_loss_and_gradients():
    """The main job's policy at its batch of 16 under `train_compile_mode="default"` on the CPU (inductor, no
    stand-in backend): each block's keys and values, two views of one projection, once came back from the
    compiled context encoder rebuilt with garbage sizes (a RuntimeError at the first step; 2026-11-28)."""
    clear_compiled()
    fields = {
        "device": "cpu",
        "input_features": {
            "observation.image": PolicyFeature(FeatureType.VISUAL, (3, 64, 64)),
            "observation.state": PolicyFeature(FeatureType.STATE, (4,)),
        },
        "output_features": {"action": PolicyFeature(FeatureType.ACTION, (4,))},
        # Inside the compiled backbone inductor draws state dropout's mask from its own generator, and the
        # contrastive pass's dtype follows the CPU: both off, the two steps compute the same function.
        "resnet": {"state_dropout": 0.0},
        "contrastive": {"dtype": "float32"},
    }
    policies = []
    for mode in ("off", "default"):
        torch.manual_seed(0)
        policies.append(EBVLAPolicy(light_policy_config(**fields, train_compile_mode=mode)))
    try:
        batch = tiny_batch(policies[0].config, batch_size=16, seed=3)
        results = []
        # The same draws for both: E_c's corruptions and the MCMC chain's step sizes use torch's RNG.
        for policy in policies:
            torch.manual_seed(1)
            results.append(training_step(policy, batch))
        (eager_loss, eager_grads), (compiled_loss, compiled_grads) = results
    finally:
        clear_compiled()
    assert torch.isfinite(compiled_loss)
    torch.testing.assert_close(compiled_loss, eager_loss, atol=1e-4, rtol=1e-4)
    assert compiled_grads.keys() == eager_grads.keys()
    torch.testing.assert_close(compiled_grads, eager_grads, atol=1e-3, rtol=1e-3)
