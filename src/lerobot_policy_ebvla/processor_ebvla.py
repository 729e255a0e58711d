"""Pre- and post-processing pipelines of the EB-VLA policy."""

import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from lerobot.lerobot_types import EnvTransition, TransitionKey
from lerobot.processor import (
    PolicyAction,
    PolicyProcessorPipeline,
    ProcessorStepRegistry,
    TokenizerProcessorStep,
    make_default_policy_processor_steps,
    make_policy_processor_pipelines,
)
from transformers import AutoTokenizer

from .configuration_ebvla import EBVLAConfig


@dataclass
@ProcessorStepRegistry.register(name="ebvla_tokenizer_processor")
class EBVLATokenizerProcessorStep(TokenizerProcessorStep):
    """LeRobot's tokenizer step, with the tokenizer's files saved in the processor's state.

    LeRobot's `TokenizerProcessorStep` saves only the tokenizer's name and downloads it again on reload.
    This step saves the files of `tokenizer.save_pretrained` as byte tensors in its state (the processor's
    `.safetensors`), so a saved pre-processor tokenizes with no network. It also rejects empty instructions,
    which would leave the latents with nothing to condition on.

    Attributes:
        tokenizer_name: Hub id or local folder of the tokenizer, read once when the step is first built. A
            step reloaded from a checkpoint has none and rebuilds the tokenizer from its state.
    """

    _tokenizer_files: dict[str, bytes] = field(default_factory=dict, init=False, repr=False)

    def __post_init__(self):
        # Unlike the parent, a step with neither tokenizer nor name is valid: `load_state_dict` provides it.
        if self.tokenizer is not None:
            self.input_tokenizer = self.tokenizer
        elif self.tokenizer_name is not None:
            from .backbone_vlm import fetching  # the same one-line error as the backbone's when offline

            with fetching("vlm.model_name", self.tokenizer_name, "tokenizer"):
                self.input_tokenizer = AutoTokenizer.from_pretrained(self.tokenizer_name)
        if self.input_tokenizer is not None and self.input_tokenizer.pad_token is None:
            self.input_tokenizer.pad_token = self.input_tokenizer.eos_token

    def get_task(self, transition: EnvTransition) -> list[str] | None:
        complementary_data = transition.get(TransitionKey.COMPLEMENTARY_DATA) or {}
        if complementary_data.get(self.task_key) is None:
            raise ValueError(
                f"EB-VLA conditions on a task instruction under `{self.task_key}`, and the batch has none."
            )
        tasks = super().get_task(transition)
        if tasks is None or any(not task.strip() for task in tasks):
            raise ValueError(
                f"EB-VLA needs a non-empty task instruction under `{self.task_key}`. Got {tasks!r}."
            )
        return tasks

    def observation(self, observation: dict[str, Any]) -> dict[str, Any]:
        if self.input_tokenizer is None:
            raise ValueError(
                "The tokenizer step has no tokenizer: build it with `tokenizer_name` or load its state."
            )
        return super().observation(observation)

    def get_config(self) -> dict[str, Any]:
        # Without the name, a reload never reaches for the Hub: the tokenizer comes from the state.
        config = super().get_config()
        config.pop("tokenizer_name", None)
        return config

    def state_dict(self) -> dict[str, torch.Tensor]:
        if not self._tokenizer_files and self.input_tokenizer is not None:
            with tempfile.TemporaryDirectory() as tmp:
                self.input_tokenizer.save_pretrained(tmp)
                self._tokenizer_files = {path.name: path.read_bytes() for path in Path(tmp).iterdir()}
        return {
            name: torch.frombuffer(bytearray(content), dtype=torch.uint8)
            for name, content in self._tokenizer_files.items()
        }

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        self._tokenizer_files = {name: bytes(tensor.numpy()) for name, tensor in state.items()}
        with tempfile.TemporaryDirectory() as tmp:
            for name, content in self._tokenizer_files.items():
                (Path(tmp) / name).write_bytes(content)
            self.input_tokenizer = AutoTokenizer.from_pretrained(tmp)


def make_ebvla_pre_post_processors(
    config: EBVLAConfig,
    dataset_stats: dict[str, dict[str, torch.Tensor]] | None = None,
) -> tuple[
    PolicyProcessorPipeline[dict[str, Any], dict[str, Any]],
    PolicyProcessorPipeline[PolicyAction, PolicyAction],
]:
    """Builds the EB-VLA pre- and post-processing pipelines.

    Pre-processing, in order:
    1. Rename observation keys (`rename_observations_processor`).
    2. Add a batch dimension to unbatched observations.
    3. With the VLM backbone only: tokenize the task instruction (`task`, must be non-empty) into
       `observation.language.tokens` and `observation.language.attention_mask`, padded to
       `vlm.tokenizer_max_length`, with the language model's tokenizer (`EBVLATokenizerProcessorStep`; it saves
       the tokenizer's files with the processor, so reloading needs no network).
    4. Move tensors to `config.device`.
    5. Normalize state and action (mean/std by default) with the dataset statistics.

    Post-processing, in order:
    1. Unnormalize the refined action chunk back to the dataset's units.
    2. Move it to the CPU.

    Args:
        config: The EB-VLA configuration.
        dataset_stats: Per-feature statistics used by the (un)normalizer.

    Returns:
        The pre-processor and the post-processor pipelines.
    """
    steps = make_default_policy_processor_steps(config, dataset_stats)
    input_steps = [steps.rename_observations, steps.add_batch_dim]
    if config.backbone == "vlm":
        input_steps.append(
            EBVLATokenizerProcessorStep(
                tokenizer_name=config.vlm.model_name,
                max_length=config.vlm.tokenizer_max_length,
                padding_side="right",
                padding="max_length",
            )
        )
    input_steps += [steps.to_device, steps.normalize]
    return make_policy_processor_pipelines(
        input_steps=input_steps, output_steps=[steps.unnormalize, steps.to_cpu]
    )
