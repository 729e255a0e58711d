"""The pretrained-loading path (`load_pretrained_backbone=True`), proven without the Hub.

Hub-shaped copies of the three repositories the default config names are written at tiny size with random
weights: `Qwen/Qwen2.5-0.5B` by transformers' `save_pretrained` (a `Qwen2ForCausalLM` in bf16 with tied
embeddings, plus its tokenizer, as the Hub serves it) and the two timm encoders by timm's `save_for_hf`
(config.json + model.safetensors, the files of the `timm/<name>` repositories). They are loaded

- from a Hugging Face cache in offline mode under the default names: the code a user with the Hub runs, down
  to `hf_hub_download`, which finds the files in the cache instead of downloading them;
- from local folders named in the config (`local-dir:` for timm, a path for transformers).

Every weight the backbone holds must equal the saved one: nothing is silently left random.
"""

from pathlib import Path

import pytest
import timm
import torch
from huggingface_hub import constants as hub_constants
from lerobot.utils.constants import OBS_LANGUAGE_TOKENS
from safetensors.torch import load_file
from transformers import AutoTokenizer, Qwen2Config, Qwen2ForCausalLM

from lerobot_policy_ebvla import EBVLAConfig, EBVLAPolicy
from lerobot_policy_ebvla.backbone_vlm import PretrainedWeightsUnavailableError
from lerobot_policy_ebvla.processor_ebvla import make_ebvla_pre_post_processors

from .test_backbone_vlm import TASKS, TINY_VISION, raw_batch, vlm_config, write_tiny_language_model

DEFAULTS = EBVLAConfig()
QWEN, DINOV2, SIGLIP = DEFAULTS.vlm.model_name, DEFAULTS.vlm.dinov2_model_name, DEFAULTS.vlm.siglip_model_name
IMAGE_SIZE = (
    28  # the encoders are saved at the size the policy uses, so timm has no position grid to resample
)
COMMIT = "0123456789abcdef0123456789abcdef01234567"


def write_language_model_repo(root: Path) -> Path:
    """Qwen2.5's Hub files at tiny size: config, bf16 weights (lm_head tied, so not stored), tokenizer."""
    write_tiny_language_model(root)
    config = Qwen2Config(
        vocab_size=128,
        hidden_size=64,
        intermediate_size=128,
        num_hidden_layers=2,
        num_attention_heads=4,
        num_key_value_heads=2,
        tie_word_embeddings=True,
    )
    torch.manual_seed(1)
    Qwen2ForCausalLM(config).to(torch.bfloat16).save_pretrained(root)
    return root


def write_timm_repo(root: Path, model_name: str, seed: int) -> Path:
    """A `timm/<name>` Hub repository at tiny size: what `timm.models.push_to_hf_hub` uploads."""
    torch.manual_seed(seed)
    model = timm.create_model(model_name, pretrained=False, img_size=IMAGE_SIZE, num_classes=0, **TINY_VISION)
    timm.models.save_for_hf(model, root, safe_serialization=True)
    return root


def timm_repo_id(model_name: str) -> str:
    return timm.models.get_pretrained_cfg(model_name).hf_hub_id


@pytest.fixture(scope="module")
def repos(tmp_path_factory) -> dict[str, Path]:
    """The three repositories, keyed by the Hub id each stands in for."""
    root = tmp_path_factory.mktemp("repos")
    return {
        QWEN: write_language_model_repo(root / "qwen"),
        timm_repo_id(DINOV2): write_timm_repo(root / "dinov2", DINOV2, seed=2),
        timm_repo_id(SIGLIP): write_timm_repo(root / "siglip", SIGLIP, seed=3),
    }


def populate_cache(cache: Path, repos: dict[str, Path]) -> None:
    """Lays the repositories out as `hf_hub_download` caches them: refs/main -> snapshots/<commit>/<files>."""
    for repo_id, folder in repos.items():
        storage = cache / f"models--{repo_id.replace('/', '--')}"
        (storage / "refs").mkdir(parents=True)
        (storage / "refs" / "main").write_text(COMMIT)
        snapshot = storage / "snapshots" / COMMIT
        snapshot.mkdir(parents=True)
        for file in folder.iterdir():
            (snapshot / file.name).write_bytes(file.read_bytes())


@pytest.fixture
def offline_cache(tmp_path, monkeypatch) -> Path:
    """An empty Hugging Face cache in offline mode (HF_HUB_OFFLINE=1), as on a machine with no network."""
    cache = tmp_path / "hf_cache"
    cache.mkdir()
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setattr(hub_constants, "HF_HUB_OFFLINE", True)
    monkeypatch.setattr(hub_constants, "HF_HUB_CACHE", str(cache))
    return cache


def pretrained_config(**names) -> EBVLAConfig:
    """The tiny test config, loading pretrained weights under the default names unless `names` (fields of the
    `vlm` group) override them."""
    names.setdefault("model_name", QWEN)
    return vlm_config(
        Path(names.pop("model_name")),
        vlm={"load_pretrained_backbone": True, "vision_image_size": IMAGE_SIZE, **names},
    )


def assert_backbone_holds_saved_weights(policy: EBVLAPolicy, repos: dict[str, Path], rounding: torch.dtype):
    backbone = policy.model.backbone

    def expected(tensor: torch.Tensor) -> torch.Tensor:
        return tensor.to(rounding).float()

    saved_lm = load_file(repos[QWEN] / "model.safetensors")
    assert all(t.dtype == torch.bfloat16 for t in saved_lm.values())  # as Qwen2.5 is served
    lm_weights = {
        name.replace(".base_layer", ""): tensor
        for name, tensor in backbone.lm.state_dict().items()
        if "lora_" not in name
    }
    # Every key matched, both ways: the Hub's "model." prefix is the causal LM's, the head is tied.
    assert {f"model.{name}" for name in lm_weights} == set(saved_lm)
    for name, tensor in lm_weights.items():
        torch.testing.assert_close(tensor, expected(saved_lm[f"model.{name}"]), rtol=0, atol=0, msg=name)

    for name, model_name in (("dinov2", DINOV2), ("siglip", SIGLIP)):
        saved = load_file(repos[timm_repo_id(model_name)] / "model.safetensors")
        encoder = backbone.vision.encoders[name]
        depth = TINY_VISION["depth"]
        # timm loads strictly into the full model; what the backbone lacks is exactly what it prunes away.
        pruned = {
            key for key in saved if key.startswith((f"blocks.{depth - 1}.", "norm.", "attn_pool.", "head."))
        }
        assert set(encoder.state_dict()) == set(saved) - pruned
        for key, tensor in encoder.state_dict().items():
            torch.testing.assert_close(tensor, expected(saved[key]), rtol=0, atol=0, msg=f"{name}: {key}")


@pytest.mark.parametrize("frozen_weights_dtype", ["float32", "bfloat16"])
def test_default_names_load_every_weight_from_the_hub_cache(repos, offline_cache, frozen_weights_dtype):
    populate_cache(offline_cache, repos)
    config = pretrained_config(frozen_weights_dtype=frozen_weights_dtype)
    assert (config.vlm.dinov2_model_name, config.vlm.siglip_model_name) == (DINOV2, SIGLIP)
    policy = EBVLAPolicy(config)
    assert_backbone_holds_saved_weights(policy, repos, getattr(torch, frozen_weights_dtype))


def test_tokenizer_comes_from_the_hub_cache(repos, offline_cache):
    populate_cache(offline_cache, repos)
    preprocessor, _ = make_ebvla_pre_post_processors(pretrained_config())
    tokens = preprocessor(raw_batch())[OBS_LANGUAGE_TOKENS]
    expected = AutoTokenizer.from_pretrained(repos[QWEN])(TASKS[0])["input_ids"]
    assert tokens[0, : len(expected)].tolist() == expected


def test_local_folders_load_every_weight(repos, offline_cache):
    config = pretrained_config(
        model_name=str(repos[QWEN]),
        dinov2_model_name=f"local-dir:{repos[timm_repo_id(DINOV2)]}",
        siglip_model_name=f"local-dir:{repos[timm_repo_id(SIGLIP)]}",
        frozen_weights_dtype="float32",
    )
    assert_backbone_holds_saved_weights(EBVLAPolicy(config), repos, torch.float32)


@pytest.mark.parametrize(
    ("cached", "field", "name"),
    [
        ((), "vlm.dinov2_model_name", DINOV2),
        ((timm_repo_id(DINOV2),), "vlm.siglip_model_name", SIGLIP),
        ((timm_repo_id(DINOV2), timm_repo_id(SIGLIP)), "vlm.model_name", QWEN),
    ],
    ids=["dinov2", "siglip", "language_model"],
)
def test_default_offline_without_weights_names_them_and_how_to_proceed(
    repos, offline_cache, cached, field, name
):
    populate_cache(offline_cache, {repo_id: repos[repo_id] for repo_id in cached})
    with pytest.raises(PretrainedWeightsUnavailableError) as error:
        EBVLAPolicy(pretrained_config())
    message = str(error.value)
    assert "\n" not in message
    for expected in (
        f"`{field}={name!r}`",
        "Hugging Face cache",
        f"--policy.{field}",
        "--policy.backbone=resnet",
    ):
        assert expected in message


def test_preprocessor_offline_without_the_tokenizer_names_it(offline_cache):
    with pytest.raises(PretrainedWeightsUnavailableError, match=f"tokenizer `vlm.model_name={QWEN!r}`"):
        make_ebvla_pre_post_processors(pretrained_config())
