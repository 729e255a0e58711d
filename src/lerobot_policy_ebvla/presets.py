"""Named `EBVLAConfig` presets: the fields a purpose changes from the paper's defaults, in one place.

A preset is a dict of fields; a group's fields (`resnet`, `vlm`, `contrastive`, `joint_energy`, `monitor`) sit in a dict of
their own under the group's name. `ebvla_config` builds the config from such dicts, and `command_line_flags`
writes them as the `--policy.<field>=...` / `--policy.<group>.<field>=...` flags draccus parses.
"""

import dataclasses
import json
from typing import Any

from .configuration_ebvla import EBVLAConfig
from .configuration_groups import (
    ContrastiveConfig,
    JointEnergyConfig,
    MonitorConfig,
    PhaseEnergyConfig,
    ResNetBackboneConfig,
    VLMBackboneConfig,
)

# The nested groups of `EBVLAConfig`, by field name.
GROUPS: dict[str, type] = {
    "resnet": ResNetBackboneConfig,
    "vlm": VLMBackboneConfig,
    "contrastive": ContrastiveConfig,
    "joint_energy": JointEnergyConfig,
    "phase_energy": PhaseEnergyConfig,
    "monitor": MonitorConfig,
}

LIGHT_POLICY: dict[str, Any] = {
    "backbone": "resnet",
    "resnet": {
        "resize_shape": (64, 64),
        # A 2-stage ResNet keeps an 8x8 keypoint map at 64 px (4 stages leave 2x2) and trains 4x faster.
        "vision_backbone_stages": 2,
        # With the paper's training signal alone the light policy learns from the 4-d state and ignores its
        # camera (research/docs/energy_study.md, section 1b). Hiding the state from half the samples and keeping each
        # expert chunk below the batch's other chunks (`contrastive`) is what made it read the camera and its
        # energy react.
        "state_dropout": 0.5,
    },
    "contrastive": {
        # Weight 0.2, not the study's 0.1: over five paired seeds of the quickstart, its energy separated both
        # camera shifts (AUROC >= 0.9) on 4 against 3, and its camera check was higher on 4 (research/docs/
        # benchmarks_history.md, section 7).
        "weight": 0.2,
        # The contrastive term is half of a light training step; its head pass in bf16 where the CPU (or GPU)
        # multiplies bf16 natively takes a step from about 231 to 198 ms on an AMD EPYC with AVX512-BF16, and
        # is fp32 elsewhere (research/docs/benchmarks_history.md, section 7, fourth round).
        "dtype": "auto",
    },
    # The joint energy E(a, C) + E_c(C), E_c on its own copy of the backbone, trained by a margin on generic
    # corruptions (issue 32): without it the final energy fell *below* vanilla under lighting and colour shifts
    # that made the policy fail. Over five training seeds of this preset its final energy pooled 0.91-0.95 over
    # 26 sweep conditions, where the context k-NN pooled 0.77-0.92 (research/docs/benchmarks_history.md, section 16); it still misses
    # mild blur and light direction. The policy's backbone and head train and refine exactly as without it; it
    # costs a second backbone pass per chunk and two per training step.
    "joint_energy": {
        "target": "observation",
        "weight": 0.01,
        "corruptions": ("channel_gain", "patch_swap", "shift", "state_noise"),
        # E_c flat at the data (a gradient penalty on its image gradient, R1): without it a mild shift the
        # margin never saw moved E_c by its gradient, up in one scene and down in another, and every score of
        # it was confidently wrong on some training seed; with it every sweep shift raises E_c, and its
        # one-sided score at each chunk index (`context_phase_energy`) was confidently wrong on none of four
        # seeds, two trained after the rule was written (research/results/metaworld_sweep_margin_full/
        # summary.md, "E_c flat at the data"). A training step costs about a third more. Its gradient reaches
        # E_c's own encoder only, and the policy's updates only through LeRobot's clipping of the total
        # gradient norm (10), which binds in the first steps: a new training realization, whose vanilla
        # success (110/160 on four seeds) is within the preset's spread over fourteen (50-82%).
        "gradient_penalty": 0.1,
        # E_c's own encoder at 32 px and its penalty on one step in 4 (at 4 times the weight): the joint energy was
        # half the light training step, and the two halve it (the main job in 4.3-4.9 minutes instead of 7.9 on a
        # 2-core AMD EPYC with AVX512-BF16). With `energy_bias_init` they passed the main job's check on three seeds
        # and the MetaWorld sweep's rule on two untouched ones (research/docs/benchmarks_speed.md, "Both E_c levers
        # with the raised starting energy"); a mild light-direction shift stays the 32 px E_c's blind spot.
        "encoder_resize_shape": (32, 32),
        "gradient_penalty_every": 4,
    },
    # The checkpoint is monitored with E_c against the vanilla E_c at each chunk index, the score this training
    # signal is matched to: every shift of the MetaWorld sweep raises an E_c trained flat at the data, and the
    # one-sided score was confidently wrong on none of four training seeds (docs/monitoring.md).
    "monitor": {"score": "context_phase_energy"},
    "dim_model": 128,
    "n_heads": 4,
    "n_blocks": 2,
    # A SwiGLU FFN of 2D instead of the paper's 4D: the FFN is two thirds of the head's work, and the head runs
    # on every contrastive candidate; a training step costs about 11% less, and in the quickstart's 1000 steps it
    # kept the energy's separation of both shifts on two seeds where the 4D head lost part of it
    # (research/docs/benchmarks_history.md, section 7).
    "ffn_multiplier": 2,
    "train_mcmc_steps_range": (2, 4),
    # The readout's energy starts at 18, so each step of Eq. 3 starts exp(18 / 9) = 7.4 times longer: a chain of
    # 2-4 steps from a^(0) ~ N(0, 1) reaches the data from the first steps instead of after the ~700 the head took
    # to raise its energy itself. In the main job's 1000 steps the chunk's L1 ends at 0.25-0.32 instead of
    # 0.65-0.73, and over three training seeds vanilla succeeds 29/30 instead of 17/30, at the same step cost
    # (research/docs/benchmarks_speed.md, "The energy's starting level").
    "energy_bias_init": 18.0,
    "optimizer_lr": 5e-4,
    "push_to_hub": False,
}
"""The light policy: EB-VLA trained offline on a small CPU in minutes (the quickstart, the examples).

Overrides of `EBVLAConfig`'s defaults (the paper's full VLA). Sizes: LeRobot's Diffusion Policy ResNet-18
image encoder from scratch (no VLM, no pretrained weights), 2 of its 4 stages, at 64x64 px; an energy head of
D=128, 4 heads, L=2 blocks and a 2D-wide FFN (the paper: D=896, 8 heads, L=4, 4D).

Its training recipe is NOT the paper's Table V: it samples K_train in (2, 4) MCMC steps per training step
instead of [8, 15], adds the contrastive term (`contrastive.weight=0.2`) and state dropout
(`resnet.state_dropout=0.5`), which the paper does not have, trains at a learning rate of 5e-4 instead of 1e-4, and
starts the head's energy readout at 18 (`energy_bias_init`) so that its short training chains reach the data.
The contrastive term and state dropout are what made this policy read its camera and its energy react to
camera shifts (research/docs/energy_study.md, section 1b). Its final energy is the joint energy E(a, C) + E_c(C)
(`joint_energy.target="observation"`), which keeps it from reading a shift as more familiar than vanilla, with E_c
trained flat at the data (`joint_energy.gradient_penalty=0.1`, on one step in 4) so that every shift raises it, on
its own encoder at 32 px (`joint_energy.encoder_resize_shape`); the checkpoint is
monitored with that E_c against vanilla's at each chunk index (`monitor.score="context_phase_energy"`).
Inference (K_inf, alpha, tau, ...) keeps Table V's values.
"""


def ebvla_config(*layers: dict[str, Any]) -> EBVLAConfig:
    """An `EBVLAConfig` from dicts of fields, each layer on top of the ones before it.

    A top-level field replaces the earlier value. A group (`GROUPS`) given as a dict of its fields changes only
    the fields it names; given as its dataclass (`JointEnergyConfig(...)`), it replaces the whole group. E.g.
    `ebvla_config(LIGHT_POLICY, {"dim_model": 64, "joint_energy": {"weight": 0.0}})`.
    """
    fields: dict[str, Any] = {}
    for layer in layers:
        for name, value in layer.items():
            earlier = fields.get(name)
            if name in GROUPS and isinstance(value, dict) and earlier is not None:
                earlier = vars(earlier) if isinstance(earlier, GROUPS[name]) else earlier
                value = {**earlier, **value}
            fields[name] = value
    for name, group in GROUPS.items():
        if isinstance(fields.get(name), dict):
            unknown = set(fields[name]) - {f.name for f in dataclasses.fields(group)}
            if unknown:
                raise ValueError(
                    f"`{name}` has no field {sorted(unknown)}: its fields are those of `{group.__name__}`."
                )
            fields[name] = group(**fields[name])
    return EBVLAConfig(**fields)


def light_policy_config(**overrides: Any) -> EBVLAConfig:
    """The `EBVLAConfig` of `LIGHT_POLICY`, with `overrides` on top: any top-level field, and any group's fields
    as a dict (`joint_energy={"weight": 0.0}` changes that field only) or as the group's dataclass (which replaces
    the preset's group whole)."""
    return ebvla_config(LIGHT_POLICY, overrides)


def command_line_flags(fields: dict[str, Any]) -> list[str]:
    """`fields` (a preset) as draccus flags: `--policy.<field>=<json>`, and `--policy.<group>.<field>=<json>`
    for a group's."""
    flags = []
    for name, value in fields.items():
        if name in GROUPS and isinstance(value, dict):
            flags += [f"--policy.{name}.{field}={json.dumps(v)}" for field, v in value.items()]
        else:
            flags.append(f"--policy.{name}={json.dumps(value)}")
    return flags
