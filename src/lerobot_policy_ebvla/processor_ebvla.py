"""Pre- and post-processing pipelines of the EB-VLA policy."""

from typing import Any

import torch
from lerobot.processor import (
    PolicyAction,
    PolicyProcessorPipeline,
    TokenizerProcessorStep,
    make_default_policy_processor_steps,
    make_policy_processor_pipelines,
)

from .configuration_ebvla import EBVLAConfig


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
    3. With the VLM backbone only: tokenize the task instruction into `observation.language.tokens`
       and `observation.language.attention_mask` with the language model's tokenizer.
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
            TokenizerProcessorStep(
                tokenizer_name=config.vlm_model_name,
                max_length=config.tokenizer_max_length,
                padding_side="right",
                padding="max_length",
            )
        )
    input_steps += [steps.to_device, steps.normalize]
    return make_policy_processor_pipelines(
        input_steps=input_steps, output_steps=[steps.unnormalize, steps.to_cpu]
    )
