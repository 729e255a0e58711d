"""The VLM backbone (Sec. II-A) at tiny size: token layout of Eq. 1, gradients, processors, offline reload.

The Hub is not reachable in tests: the language model's config and a tiny BPE tokenizer are written to a
local folder that stands in for `Qwen/Qwen2.5-0.5B`, and the timm encoders get random weights.
"""

import shutil
from pathlib import Path

import pytest
import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.policies.factory import make_pre_post_processors
from lerobot.utils.constants import ACTION, OBS_LANGUAGE_ATTENTION_MASK, OBS_LANGUAGE_TOKENS, OBS_STATE
from safetensors import safe_open
from tokenizers import Tokenizer, models, pre_tokenizers, trainers
from transformers import PreTrainedTokenizerFast, Qwen2Config

from lerobot_policy_ebvla import EBVLAConfig, EBVLAPolicy
from lerobot_policy_ebvla.backbone_vlm import EBVLAVisionLanguageBackbone, default_context_layers
from lerobot_policy_ebvla.presets import ebvla_config
from lerobot_policy_ebvla.processor_ebvla import make_ebvla_pre_post_processors

CAMERAS = {"observation.images.primary": (3, 32, 32), "observation.images.wrist": (3, 24, 24)}
TINY_VISION = {"depth": 2, "embed_dim": 32, "num_heads": 2}
TASKS = ["pick up the red block", "open the top drawer"]
STATS = {
    OBS_STATE: {"mean": torch.zeros(4), "std": torch.ones(4)},
    ACTION: {"mean": torch.zeros(3), "std": 2 * torch.ones(3)},
}


def write_tiny_language_model(root: Path) -> Path:
    """A local stand-in for a Hub language model: a 2-layer, 64-wide Qwen2 config and a BPE tokenizer."""
    root.mkdir(parents=True, exist_ok=True)
    tokenizer = Tokenizer(models.BPE(unk_token="<unk>"))
    tokenizer.pre_tokenizer = pre_tokenizers.Whitespace()
    corpus = TASKS + ["put the bowl on the plate", "close the drawer and push the button"]
    tokenizer.train_from_iterator(
        corpus, trainers.BpeTrainer(vocab_size=100, special_tokens=["<pad>", "<unk>"])
    )
    PreTrainedTokenizerFast(tokenizer_object=tokenizer, pad_token="<pad>", unk_token="<unk>").save_pretrained(
        root
    )
    Qwen2Config(
        vocab_size=128,
        hidden_size=64,
        intermediate_size=128,
        num_hidden_layers=2,
        num_attention_heads=4,
        num_key_value_heads=2,
    ).save_pretrained(root)
    return root


@pytest.fixture(scope="module")
def tiny_lm(tmp_path_factory) -> Path:
    return write_tiny_language_model(tmp_path_factory.mktemp("tiny_lm"))


def vlm_config(lm_path: Path, with_state: bool = True, **overrides) -> EBVLAConfig:
    input_features = {key: PolicyFeature(FeatureType.VISUAL, shape) for key, shape in CAMERAS.items()}
    if with_state:
        input_features[OBS_STATE] = PolicyFeature(FeatureType.STATE, (4,))
    fields = {
        "device": "cpu",
        "vlm": {
            "model_name": str(lm_path),
            "load_pretrained_backbone": False,
            "vision_image_size": 28,  # 2 x 2 patches of 14 px per camera
            "vision_model_overrides": TINY_VISION,
            "num_latent_tokens": 4,
            "tokenizer_max_length": 8,
            "lora_rank": 4,
            "lora_alpha": 8,
            "num_context_layers": 3,
        },
        "dim_model": 32,
        "n_heads": 2,
        "n_blocks": 2,
        "input_features": input_features,
        "output_features": {ACTION: PolicyFeature(FeatureType.ACTION, (3,))},
    }
    return ebvla_config(fields, overrides)


def raw_batch(batch_size: int = 2, with_action: bool = False, seed: int = 0) -> dict:
    g = torch.Generator().manual_seed(seed)
    batch = {key: torch.rand(batch_size, *shape, generator=g) for key, shape in CAMERAS.items()}
    batch[OBS_STATE] = torch.randn(batch_size, 4, generator=g)
    batch["task"] = TASKS[:batch_size]
    if with_action:
        batch[ACTION] = torch.randn(batch_size, 8, 3, generator=g)
        batch["action_is_pad"] = torch.zeros(batch_size, 8, dtype=torch.bool)
    return batch


def build(config: EBVLAConfig) -> tuple[EBVLAVisionLanguageBackbone, dict]:
    torch.manual_seed(0)
    backbone = EBVLAVisionLanguageBackbone(config)
    preprocessor, _ = make_ebvla_pre_post_processors(config)
    return backbone, preprocessor(raw_batch())


def test_context_follows_eq1_one_tensor_per_block(tiny_lm):
    config = vlm_config(tiny_lm)
    backbone, batch = build(config)
    contexts = backbone(batch)
    k_t = 4 * len(CAMERAS)
    assert backbone.num_vision_tokens == k_t
    assert backbone.context_dim == 64
    assert len(contexts) == config.n_blocks
    for context in contexts:
        assert context.shape == (2, config.vlm.num_latent_tokens + 1 + k_t, 64)


def test_context_is_latents_then_state_then_vision_tokens(tiny_lm):
    # Hidden state 0 is the embedding output, so its h_t is the projected vision tokens and h_a the latents.
    config = vlm_config(tiny_lm, vlm={"context_layers": (0, 2)})
    backbone, batch = build(config)
    k_a = config.vlm.num_latent_tokens
    with torch.no_grad():
        context = backbone(batch)[0]
        torch.testing.assert_close(context[:, :k_a], backbone.latents.expand(2, -1, -1))
        torch.testing.assert_close(context[:, k_a], backbone.state_proj(batch[OBS_STATE]))
        torch.testing.assert_close(context[:, k_a + 1 :], backbone.encode_images(batch))


def test_camera_gives_256_tokens_at_224_px(tiny_lm):
    backbone = EBVLAVisionLanguageBackbone(vlm_config(tiny_lm, vlm={"vision_image_size": 224}))
    assert backbone.vision.num_patches == 256
    assert backbone.num_vision_tokens == 256 * len(CAMERAS)


def test_default_context_layers_spread_over_the_first_n_l_states_embedding_included():
    # Table V: N_l = 23 states with the embedding, i.e. states 0..22 of Qwen2.5-0.5B's 25; L = 4 head blocks.
    assert default_context_layers(23, 4) == (0, 7, 15, 22)
    assert default_context_layers(25, 5) == (0, 6, 12, 18, 24)
    assert default_context_layers(23, 1) == (22,)


def test_lora_adapts_only_the_layers_the_head_reads(tiny_lm):
    # Hidden state 1 is layer 0's output: layer 1 never reaches the head, so it gets no adapter.
    backbone = EBVLAVisionLanguageBackbone(vlm_config(tiny_lm, vlm={"context_layers": (0, 1)}))
    adapted = {name.split(".")[1] for name, _ in backbone.lm.named_parameters() if "lora_" in name}
    assert adapted == {"0"}


def test_only_lora_projector_latents_and_state_projection_train(tiny_lm):
    backbone, batch = build(vlm_config(tiny_lm))
    sum(context.square().mean() for context in backbone(batch)).backward()
    trainable = {name for name, param in backbone.named_parameters() if param.requires_grad}
    assert trainable, "nothing to train"
    for name in trainable:
        assert "lora_" in name or name.startswith(("projector.", "latents", "state_proj.")), name
    for name, param in backbone.named_parameters():
        if (
            param.requires_grad and "lora_A" not in name
        ):  # lora_B starts at zero, so lora_A's first gradient is 0
            assert param.grad is not None and param.grad.abs().sum() > 0, name
        if not param.requires_grad:
            assert param.grad is None, name
    frozen_prefixes = ("vision.", "lm.embed_tokens.", "lm.norm.")
    assert all(not p.requires_grad for n, p in backbone.named_parameters() if n.startswith(frozen_prefixes))
    assert not any(p.requires_grad for n, p in backbone.lm.named_parameters() if "lora_" not in n)


def test_latents_read_the_instruction_and_vision_tokens_do_not(tiny_lm):
    config = vlm_config(tiny_lm, vlm={"context_layers": (2, 2)})
    backbone, batch = build(config)
    other = dict(
        batch,
        **{
            OBS_LANGUAGE_TOKENS: batch[OBS_LANGUAGE_TOKENS].flip(0),
            OBS_LANGUAGE_ATTENTION_MASK: batch[OBS_LANGUAGE_ATTENTION_MASK].flip(0),
        },
    )
    k_a = config.vlm.num_latent_tokens
    with torch.no_grad():
        context, other_context = backbone(batch)[0], backbone(other)[0]
    torch.testing.assert_close(context[:, k_a + 1 :], other_context[:, k_a + 1 :])  # causal: h_t sees no text
    assert not torch.allclose(context[:, :k_a], other_context[:, :k_a])


def test_instruction_padding_does_not_change_the_context(tiny_lm):
    short, long = (
        vlm_config(tiny_lm, vlm={"tokenizer_max_length": 8}),
        vlm_config(tiny_lm, vlm={"tokenizer_max_length": 16}),
    )
    backbone, batch = build(short)
    long_batch = make_ebvla_pre_post_processors(long)[0](raw_batch())
    assert long_batch[OBS_LANGUAGE_TOKENS].shape[1] == 16
    with torch.no_grad():
        for context, long_context in zip(backbone(batch), backbone(long_batch), strict=True):
            torch.testing.assert_close(context, long_context, atol=1e-5, rtol=1e-5)


def test_learned_state_token_without_state(tiny_lm):
    config = vlm_config(tiny_lm, with_state=False)
    backbone, batch = build(config)
    batch.pop(OBS_STATE)
    assert backbone.state_proj is None
    context = backbone(batch)[0]
    torch.testing.assert_close(context[:, config.vlm.num_latent_tokens], backbone.state_token.expand(2, -1))


def test_language_model_config_is_recorded_in_the_policy_config(tiny_lm):
    config = vlm_config(
        tiny_lm,
        vlm={"model_config_overrides": {"num_hidden_layers": 1}, "num_context_layers": 1},
    )
    assert config.vlm.model_config is None
    backbone = EBVLAVisionLanguageBackbone(config)
    assert config.vlm.model_config["model_type"] == "qwen2"
    assert config.vlm.model_config["num_hidden_layers"] == 1 == len(backbone.lm.layers)
    assert backbone.context_layers == (0, 0)  # N_l = 1: both blocks on the only extracted state


@pytest.mark.parametrize(
    ("overrides", "match"),
    [
        ({"context_layers": (0, 3)}, "vlm.context_layers"),
        ({"num_context_layers": 4}, "vlm.num_context_layers"),
    ],
)
def test_context_layers_beyond_the_language_model_are_rejected(tiny_lm, overrides, match):
    with pytest.raises(ValueError, match=match):
        EBVLAVisionLanguageBackbone(vlm_config(tiny_lm, vlm=overrides))


def test_missing_language_tokens_name_the_keys(tiny_lm):
    backbone, batch = build(vlm_config(tiny_lm))
    batch.pop(OBS_LANGUAGE_TOKENS)
    with pytest.raises(ValueError, match=OBS_LANGUAGE_TOKENS):
        backbone(batch)


@pytest.mark.parametrize("task", ["", "   "])
def test_empty_task_is_rejected_naming_the_key(tiny_lm, task):
    preprocessor, _ = make_ebvla_pre_post_processors(vlm_config(tiny_lm))
    with pytest.raises(ValueError, match="`task`"):
        preprocessor(dict(raw_batch(), task=[TASKS[0], task]))


def test_preprocessor_tokenizes_offline_after_reload(tmp_path):
    lm_path = write_tiny_language_model(tmp_path / "lm")
    preprocessor, postprocessor = make_ebvla_pre_post_processors(vlm_config(lm_path))
    expected = preprocessor(raw_batch())
    preprocessor.save_pretrained(tmp_path / "ckpt")
    postprocessor.save_pretrained(tmp_path / "ckpt")
    shutil.rmtree(lm_path)  # the tokenizer's source is gone: the reload must use the saved state
    reloaded, _ = make_pre_post_processors(vlm_config(lm_path), pretrained_path=str(tmp_path / "ckpt"))
    batch = reloaded(raw_batch())
    assert torch.equal(batch[OBS_LANGUAGE_TOKENS], expected[OBS_LANGUAGE_TOKENS])
    assert torch.equal(batch[OBS_LANGUAGE_ATTENTION_MASK], expected[OBS_LANGUAGE_ATTENTION_MASK])


def test_training_step_through_the_pipeline_reaches_lora_and_projector(tiny_lm):
    config = vlm_config(tiny_lm)
    torch.manual_seed(0)
    policy = EBVLAPolicy(config)
    preprocessor, _ = make_pre_post_processors(config, dataset_stats=STATS)
    loss, _ = policy.forward(preprocessor(raw_batch(with_action=True)))
    loss.backward()
    backbone = policy.model.backbone
    # The loss sees the context only through grad_a E of the last MCMC step (second order).
    lora_b = [p for n, p in backbone.named_parameters() if "lora_B" in n]
    assert all(p.grad is not None for p in lora_b)
    assert sum(p.grad.abs().sum() for p in lora_b) > 0
    assert backbone.projector.mlp[0].weight.grad.abs().sum() > 0
    assert all(p.grad is None for p in backbone.vision.parameters())


def test_saved_policy_reloads_offline_with_identical_actions(tmp_path):
    lm_path = write_tiny_language_model(tmp_path / "lm")
    config = vlm_config(lm_path)
    torch.manual_seed(0)
    policy = EBVLAPolicy(config).eval()
    preprocessor, postprocessor = make_pre_post_processors(config, dataset_stats=STATS)
    actions = policy.predict_action_chunk(
        preprocessor(raw_batch()), generator=torch.Generator().manual_seed(1)
    )
    for saved in (policy, preprocessor, postprocessor):
        saved.save_pretrained(tmp_path / "ckpt")

    shutil.rmtree(lm_path)  # the LM config must come from config.json, the tokenizer from the processor
    reloaded = EBVLAPolicy.from_pretrained(tmp_path / "ckpt").eval()
    preprocessor, _ = make_pre_post_processors(reloaded.config, pretrained_path=str(tmp_path / "ckpt"))
    reloaded_actions = reloaded.predict_action_chunk(
        preprocessor(raw_batch()), generator=torch.Generator().manual_seed(1)
    )
    torch.testing.assert_close(reloaded_actions, actions, atol=0, rtol=0)


@pytest.mark.parametrize("frozen_weights_dtype", ["bfloat16", "float32"])
def test_checkpoint_stores_frozen_weights_in_frozen_weights_dtype(tiny_lm, tmp_path, frozen_weights_dtype):
    torch.manual_seed(0)
    policy = EBVLAPolicy(vlm_config(tiny_lm, vlm={"frozen_weights_dtype": frozen_weights_dtype}))
    policy.save_pretrained(tmp_path)
    with safe_open(tmp_path / "model.safetensors", framework="pt") as f:
        dtypes = {key: f.get_slice(key).get_dtype() for key in f.keys()}  # noqa: SIM118
    # Matrices: vectors such as norm weights of ones are stored in bf16 whenever that is exact.
    frozen = {
        f"model.backbone.{name}"
        for name, param in policy.model.backbone.named_parameters()
        if not param.requires_grad and param.ndim >= 2
    }
    assert frozen
    assert {dtypes[key] for key in frozen} == {"BF16" if frozen_weights_dtype == "bfloat16" else "F32"}
    assert dtypes["model.backbone.projector.mlp.0.weight"] == dtypes["model.head.action_in.weight"] == "F32"


def test_resaving_a_checkpoint_with_float32_frozen_weights_loses_nothing(tiny_lm, tmp_path):
    # A checkpoint saved before `frozen_weights_dtype` existed: fp32 frozen weights, no such field in its config.
    torch.manual_seed(0)
    EBVLAPolicy(vlm_config(tiny_lm, vlm={"frozen_weights_dtype": "float32"})).save_pretrained(
        tmp_path / "old"
    )
    config_file = tmp_path / "old" / "config.json"
    config_file.write_text(config_file.read_text().replace('"frozen_weights_dtype": "float32",', ""))
    old = EBVLAPolicy.from_pretrained(tmp_path / "old")
    assert (
        old.config.vlm.frozen_weights_dtype == "bfloat16"
    )  # the new default applies, yet nothing is rounded
    old.save_pretrained(tmp_path / "new")
    new = EBVLAPolicy.from_pretrained(tmp_path / "new")
    for (name, tensor), (_, reloaded) in zip(old.state_dict().items(), new.state_dict().items(), strict=True):
        assert torch.equal(tensor, reloaded), name
