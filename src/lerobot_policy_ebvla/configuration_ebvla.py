"""Configuration of the Energy-Based VLA (EB-VLA) policy.

Defaults are the paper's (Table V): the full VLA with a fused DINOv2+SigLIP vision encoder, Qwen2.5-0.5B
with LoRA, K_a = 64 latent tokens and an L = 4 block, D = 896 energy head refined by 15 MCMC steps.
The light backbone (`backbone="resnet"`) is LeRobot's Diffusion Policy image encoder, for the paper's
head-only experiments (Sec. III-A) and for CPU training.
"""

import dataclasses
import json
import math
import tempfile
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import draccus
from huggingface_hub.constants import CONFIG_NAME
from lerobot.configs import NormalizationMode, PreTrainedConfig
from lerobot.optim import AdamWConfig, CosineDecayWithWarmupSchedulerConfig
from lerobot.policies.rtc.configuration_rtc import RTCConfig
from lerobot.utils.constants import ACTION, OBS_STATE

from .configuration_groups import (
    CONTEXT_ENERGY_SCORES,
    PHASE_ENERGY_SCORES,
    PHASE_FITTED_FAILURE_SCORE,
    ContrastiveConfig,
    JointEnergyConfig,
    MonitorConfig,
    PhaseEnergyConfig,
    ResNetBackboneConfig,
    VLMBackboneConfig,
    check_at_least,
    check_fraction,
    check_one_of,
    check_positive,
)

BACKBONES = ("vlm", "resnet")
STEP_SIZE_SAMPLINGS = ("per_chain", "per_mcmc_step")
COMPILE_MODES = (
    "off",
    "default",
    "reduce-overhead",
    "max-autotune",
    "max-autotune-no-cudagraphs",
    "chunk-graph",
)
# A chunk graph records inference's whole refinement; training compiles its parts in the other modes.
TRAIN_COMPILE_MODES = tuple(mode for mode in COMPILE_MODES if mode != "chunk-graph")


@PreTrainedConfig.register_subclass("ebvla")
@dataclass
class EBVLAConfig(PreTrainedConfig):
    """Configuration class for `EBVLAPolicy`.

    Inputs are one or more camera images (`observation.images.*`), an optional proprioceptive state
    (`observation.state`) and, with the VLM backbone, a task instruction (`task`). The output is a chunk of
    `chunk_size` actions (`action`). Symbols in brackets are the paper's.

    Args:
        n_obs_steps: Number of observation steps the policy sees. EB-VLA conditions on the current one only.
        chunk_size: Length H of the action chunk the energy scores and MCMC refines.
        n_action_steps: How many actions of each refined chunk are executed before refining a new one.
        normalization_mapping: Normalization mode per feature type. Actions are mean/std normalized so
            that the N(0, sigma_init^2) initialisation and the clamp a_max are in units of the data's std.
        backbone: "vlm" for the paper's vision-language backbone, "resnet" for the light image encoder.
        resnet: The light backbone's options (`ResNetBackboneConfig`: LeRobot's Diffusion Policy encoder and
            its field names, state dropout, task tokens); read only with `backbone="resnet"`.
        vlm: The VLM backbone's options (`VLMBackboneConfig`: model names, LoRA, latent tokens, context
            layers); read only with `backbone="vlm"`.
        dim_model: Hidden dimension D of the energy head.
        n_heads: Attention heads of the energy head.
        n_blocks: Number L of energy-head transformer blocks.
        ffn_multiplier: Inner width of the SwiGLU FFN, in multiples of D.
        rope_base: Base of the rotary position embedding over action timesteps.
        dropout: Dropout in the energy head.
        energy_temperature: Temperature tau of the energy-scaled step size (Eq. 3).
        init_action_std: Std sigma_init of the Gaussian initialisation a^(0).
        langevin_noise_std: Std sigma_L of the Langevin perturbation (Eq. 2).
        grad_clip: Element-wise gradient clip c.
        action_clamp: Bound a_max of the refined (normalized) actions.
        inference_step_size: Constant step size alpha at inference.
        train_step_size_range: [alpha_min, alpha_max] of the step size sampled at every training step.
        train_step_size_sampling: "per_chain" draws one alpha per training step, constant along its MCMC
            chain as at inference (our reading of the paper's "resample the base step size each step");
            "per_mcmc_step" draws a new alpha for every MCMC step of the chain.
        train_straight_through_clip: In training, differentiate the element-wise gradient clip c as the
            identity (the forward values stay clipped). The paper's hard clip passes no learning signal
            through any gradient entry it clips. Inference is unchanged.
        energy_bias_init: Initial bias b of the head's energy readout (its last linear layer). Every e_t starts
            near b, so every MCMC step starts exp(b / tau) times longer (Eq. 3); the readout still learns b. A
            chain of few steps from a^(0) ~ N(0, sigma_init^2) (the light preset's K_train 2-4) reaches the data
            only once the head has raised its energy so far, which took the light policy about 700 of its 1000
            steps from b = 0 (research/docs/benchmarks_speed.md, "The energy's starting level"). 0 (the default):
            the plain initialization, the paper's recipe unchanged. Read once, when the head is built.
        train_compile_mode: torch.compile a training step's backbone pass (forward and backward) and its
            K - 1 warm-up MCMC steps in this mode (`compile_ebvla.py`); the last, second-order step stays eager.
            "off" (the default) trains eagerly; the modes are `compile_mode`'s but "chunk-graph" (inference
            only). Losses equal eager training up to float rounding (tests/test_compile_mode.py); each batch
            shape compiles on its first step. Gains: research/docs/vlm_gpu.md.
        contrastive: The contrastive term beyond the paper (`ContrastiveConfig`; off by default).
        joint_energy: The energy's margin on corrupted observations and the joint energy E(a, C) + E_c(C)
            (`JointEnergyConfig`; off by default).
        train_mcmc_steps_range: [K_min, K_max] of the number of MCMC steps sampled at every training step.
        inference_mcmc_steps: Number K_inf of MCMC steps at inference.
        num_restarts: Refine this many chains per observation and keep the one with the lowest final
            energy (energy as a verifier). 1 is the paper.
        restart_energy_threshold: Adaptive restarts ("think more when unsure"): refine one chain, and only
            where its final energy is above this value the other `num_restarts` - 1 (needs `num_restarts` >= 2).
            A threshold in the energy's units, e.g. a high percentile of calibration rollouts' final energies;
            None (the default) refines all `num_restarts` chains for every chunk.
        early_stop_tol: Stop refining once no action moves more than this in one step. None (the paper)
            runs all K_inf steps.
        compile_mode: torch.compile the inference chain of every chunk (`compile_ebvla.py`): the context
            encoding and the energy's forward and grad_a backward at each MCMC step (training: `train_compile_mode`).
            "off" (the default) runs eagerly; "default" (inductor), "max-autotune" and
            "max-autotune-no-cudagraphs" are torch.compile's modes; "reduce-overhead" and "max-autotune"
            replay CUDA graphs on a CUDA device and run their no-graph form elsewhere, with a warning.
            "chunk-graph" encodes the context as "reduce-overhead" and captures each chunk's whole refinement
            (the K_inf steps of the eager head, the Langevin noise drawn beforehand, and the final energy) in one
            CUDA graph per input shape, replayed once per chunk (`compile_ebvla.RefinementGraphs`); with
            `early_stop_tol` its steps are graphed one by one instead, and without CUDA it runs the context as
            "default" and the refinement eagerly. Shapes
            are static: each batch size compiles on its first chunk, and dynamo keeps 8 of them per process
            (`torch._dynamo.config.recompile_limit`), so warm up with one chunk at every batch size you deploy;
            each new combination of the light backbone's `resnet.task_instructions` in a batch compiles the encoding
            again. Actions and energies equal eager mode up to float rounding (within 1e-5 in fp32;
            tests/test_compile_mode.py). Compile times and gains: docs/benchmarks_speed.md (CPU) and
            docs/vlm_backbone.md (H100).
        rtc_config: LeRobot's real-time chunking (`RTCConfig`), which `lerobot-rollout --inference.type=rtc`
            sets from `--inference.rtc.*`. When set and enabled, `predict_action_chunk(batch, inference_delay=d,
            prev_chunk_left_over=abar)` refines the chunk as inpainting (`mcmc.py`): the first d actions are
            held at the previous chunk's leftover abar, and the next ones up to `execution_horizon` are pulled
            towards it with LeRobot's `prefix_attention_schedule` weights w_t and guidance weight
            lambda = `max_guidance_weight` (each MCMC step closes a fraction min(1, alpha lambda w_t) of the
            gap). None (the default) or `enabled=False` refines every chunk from scratch.
        phase_energy: The phase energy E_tau(C, t) beyond the paper (`PhaseEnergyConfig`; off by default, set by
            `ebvla-fit-phase-energy` on a trained checkpoint).
        monitor: How the checkpoint is monitored at run time (`MonitorConfig`): the score `ebvla-ood-report
            --calibrate_to` calibrates (unset: E_c's per-index score with E_c on its own encoder, else the
            paper's final energy), and the policy's response to a
            flagged chunk (continue, hold or raise).
        action_feature_names: Names of the action dimensions, filled from the dataset by LeRobot's
            `make_policy`; `lerobot-rollout` maps actions to robot motors with them.
        state_feature_names: Names of the `observation.state` dimensions, filled from the dataset.
        optimizer_lr: AdamW learning rate.
        optimizer_betas: AdamW betas.
        optimizer_eps: AdamW epsilon.
        optimizer_weight_decay: AdamW weight decay.
        optimizer_grad_clip_norm: Gradient-norm clip applied by lerobot-train.
        scheduler_warmup_steps: Linear warm-up steps of the cosine schedule.
        scheduler_decay_steps: Cosine decay steps.
        scheduler_decay_lr: Learning rate at the end of the decay.

    Every field is checked in `__post_init__` (a group's in its own), which raises a ValueError naming it
    (`joint_energy.weight` for a nested one). A `config.json` saved before the groups (flat keys such as
    `joint_energy.weight`) loads through `LEGACY_FIELDS`.
    """

    # Inputs / output structure.
    n_obs_steps: int = 1
    chunk_size: int = 8
    n_action_steps: int = 8

    normalization_mapping: dict[str, NormalizationMode] = field(
        default_factory=lambda: {
            "VISUAL": NormalizationMode.IDENTITY,
            "STATE": NormalizationMode.MEAN_STD,
            "ACTION": NormalizationMode.MEAN_STD,
        }
    )

    # Backbone choice.
    backbone: str = "vlm"

    # Backbone options, read by the backbone `backbone` names.
    resnet: ResNetBackboneConfig = field(default_factory=ResNetBackboneConfig)
    vlm: VLMBackboneConfig = field(default_factory=VLMBackboneConfig)

    # Energy head (Sec. II-B).
    dim_model: int = 896
    n_heads: int = 8
    n_blocks: int = 4
    ffn_multiplier: int = 4
    rope_base: float = 10000.0
    dropout: float = 0.0

    # MCMC refinement (Sec. II-C).
    energy_temperature: float = 9.0
    init_action_std: float = 1.0
    langevin_noise_std: float = 0.001
    grad_clip: float = 1.0
    action_clamp: float = 10.0
    inference_step_size: float = 0.22
    train_step_size_range: tuple[float, float] = (0.05, 0.4)
    train_mcmc_steps_range: tuple[int, int] = (8, 15)
    inference_mcmc_steps: int = 15

    # Training signal beyond the paper (off by default).
    train_step_size_sampling: str = "per_chain"
    train_straight_through_clip: bool = False
    energy_bias_init: float = 0.0
    train_compile_mode: str = "off"
    contrastive: ContrastiveConfig = field(default_factory=ContrastiveConfig)
    joint_energy: JointEnergyConfig = field(default_factory=JointEnergyConfig)

    # Inference options beyond the paper (off by default).
    num_restarts: int = 1
    restart_energy_threshold: float | None = None
    early_stop_tol: float | None = None
    compile_mode: str = "off"
    rtc_config: RTCConfig | None = None

    # Deployment.
    phase_energy: PhaseEnergyConfig = field(default_factory=PhaseEnergyConfig)
    monitor: MonitorConfig = field(default_factory=MonitorConfig)
    action_feature_names: list[str] | None = None
    state_feature_names: list[str] | None = None

    # Training presets.
    optimizer_lr: float = 1e-4
    optimizer_betas: tuple[float, float] = (0.9, 0.95)
    optimizer_eps: float = 1e-8
    optimizer_weight_decay: float = 1e-4
    optimizer_grad_clip_norm: float = 10.0
    scheduler_warmup_steps: int = 500
    scheduler_decay_steps: int = 30_000
    scheduler_decay_lr: float = 1e-5

    def __post_init__(self):
        super().__post_init__()
        self._validate_structure()
        self._validate_energy_head()
        self._validate_mcmc()
        self._validate_inference_options()
        self._validate_deployment()

    def _validate_structure(self) -> None:
        check_one_of(self, "", "backbone", BACKBONES)
        groups = {"resnet": ResNetBackboneConfig, "vlm": VLMBackboneConfig}
        groups |= {"contrastive": ContrastiveConfig, "joint_energy": JointEnergyConfig}
        for name, group in groups.items():
            if not isinstance(getattr(self, name), group):
                raise ValueError(
                    f"`{name}` must be a `{group.__name__}` (`--policy.{name}.<field>=...` on the command line). "
                    f"Got {getattr(self, name)!r}."
                )
        layers = self.vlm.context_layers
        if layers is not None and len(layers) != self.n_blocks:
            raise ValueError(
                f"`vlm.context_layers` needs one hidden-state index per head block (n_blocks={self.n_blocks}). "
                f"Got {layers}."
            )
        if self.n_obs_steps != 1:
            raise ValueError(
                f"`n_obs_steps` must be 1: EB-VLA conditions on one observation. Got {self.n_obs_steps}."
            )
        check_at_least(self, "", 1, "chunk_size")
        if not 1 <= self.n_action_steps <= self.chunk_size:
            raise ValueError(
                f"`n_action_steps` must be in [1, chunk_size={self.chunk_size}]. Got {self.n_action_steps}."
            )

    def _validate_energy_head(self) -> None:
        check_at_least(self, "", 1, "n_blocks", "n_heads", "ffn_multiplier")
        if self.dim_model % self.n_heads != 0 or (self.dim_model // self.n_heads) % 2 != 0:
            raise ValueError(
                f"`dim_model` ({self.dim_model}) must be divisible by `n_heads` ({self.n_heads}) into an even "
                "head size (RoPE rotates pairs of channels)."
            )
        check_fraction(self, "", "dropout")
        if not math.isfinite(self.energy_bias_init):
            raise ValueError(f"`energy_bias_init` must be a finite energy. Got {self.energy_bias_init}.")

    def _validate_mcmc(self) -> None:
        check_positive(self, "", "energy_temperature", "grad_clip", "action_clamp", "inference_step_size")
        check_positive(self, "", "init_action_std")
        check_at_least(self, "", 0, "langevin_noise_std")
        check_at_least(self, "", 1, "inference_mcmc_steps")
        check_one_of(self, "", "train_step_size_sampling", STEP_SIZE_SAMPLINGS)
        alpha_min, alpha_max = self.train_step_size_range
        if not 0 < alpha_min <= alpha_max:
            raise ValueError(
                f"`train_step_size_range` must satisfy 0 < alpha_min <= alpha_max. Got {self.train_step_size_range}."
            )
        k_min, k_max = self.train_mcmc_steps_range
        if not 1 <= k_min <= k_max:
            raise ValueError(
                f"`train_mcmc_steps_range` must satisfy 1 <= K_min <= K_max. Got {self.train_mcmc_steps_range}."
            )

    def _validate_inference_options(self) -> None:
        check_at_least(self, "", 1, "num_restarts")
        if self.restart_energy_threshold is not None:
            if not math.isfinite(self.restart_energy_threshold):
                raise ValueError(
                    f"`restart_energy_threshold` must be a finite energy or None. Got {self.restart_energy_threshold}."
                )
            if self.num_restarts < 2:
                raise ValueError(
                    "`restart_energy_threshold` restarts unsure chunks with `num_restarts` chains: set "
                    f"`num_restarts` >= 2 (got {self.num_restarts}), or leave the threshold None."
                )
        if self.early_stop_tol is not None and self.early_stop_tol <= 0:
            raise ValueError(f"`early_stop_tol` must be > 0 or None. Got {self.early_stop_tol}.")
        check_one_of(self, "", "compile_mode", COMPILE_MODES)
        check_one_of(self, "", "train_compile_mode", TRAIN_COMPILE_MODES)
        if self.rtc_config is not None and self.rtc_config.execution_horizon < 1:
            raise ValueError(
                f"`rtc_config.execution_horizon` must be >= 1. Got {self.rtc_config.execution_horizon}."
            )

    def _validate_deployment(self) -> None:
        if isinstance(self.monitor, dict):  # a nested config given as a mapping (a preset, a test)
            self.monitor = MonitorConfig(**self.monitor)
        if self.monitor.score is None:  # decided here, by the training signal, and saved with the checkpoint
            self.monitor.score = (
                "context_phase_energy" if self.context_energy_on_own_encoder else "final_energy"
            )
        if isinstance(self.phase_energy, dict):
            self.phase_energy = PhaseEnergyConfig(**self.phase_energy)
        if self.monitor.failure_score is None:
            self.monitor.failure_score = (
                (PHASE_FITTED_FAILURE_SCORE if self.phase_energy.bins else "head_energy_two_sided")
                if self.context_energy_on_own_encoder
                else "none"
            )
        for option in ("score", "failure_score"):
            score = getattr(self.monitor, option)
            if score in PHASE_ENERGY_SCORES and not self.phase_energy.bins:
                raise ValueError(
                    f"`monitor.{option}={score!r}` reads the phase energy E_tau, which this policy does not have: "
                    "fit one with `ebvla-fit-phase-energy` (it sets `phase_energy.bins`)."
                )
            if score in CONTEXT_ENERGY_SCORES and not self.context_energy_on_own_encoder:
                raise ValueError(
                    f"`monitor.{option}={score!r}` reads the joint energy's context term E_c on its own "
                    "encoder, which this policy does not train: set `joint_energy.target='observation'` with "
                    "`joint_energy.weight` > 0, or use 'final_energy'"
                    + (" or 'context_knn'." if option == "score" else " or 'none'.")
                )

    @classmethod
    def from_pretrained(cls, pretrained_name_or_path: str | Path, **kwargs) -> "EBVLAConfig":
        """`PreTrainedConfig.from_pretrained`, reading a `config.json` saved before the nested groups too
        (`upgrade_legacy_fields`). LeRobot's own loader (`lerobot-eval --policy.path=...`) reads only today's
        form: `EBVLAConfig.from_pretrained(folder).save_pretrained(folder)` upgrades a folder once."""
        folder = Path(pretrained_name_or_path)
        if not (folder / CONFIG_NAME).is_file():
            return super().from_pretrained(pretrained_name_or_path, **kwargs)
        fields = json.loads((folder / CONFIG_NAME).read_text())
        upgraded = upgrade_legacy_fields(fields)
        if upgraded == fields:
            return super().from_pretrained(pretrained_name_or_path, **kwargs)
        with tempfile.TemporaryDirectory() as tmp:
            (Path(tmp) / CONFIG_NAME).write_text(json.dumps(upgraded))
            return super().from_pretrained(tmp, **kwargs)

    def get_optimizer_preset(self) -> AdamWConfig:
        return AdamWConfig(
            lr=self.optimizer_lr,
            betas=self.optimizer_betas,
            eps=self.optimizer_eps,
            weight_decay=self.optimizer_weight_decay,
            grad_clip_norm=self.optimizer_grad_clip_norm,
        )

    def get_scheduler_preset(self) -> CosineDecayWithWarmupSchedulerConfig:
        return CosineDecayWithWarmupSchedulerConfig(
            peak_lr=self.optimizer_lr,
            decay_lr=self.scheduler_decay_lr,
            num_warmup_steps=self.scheduler_warmup_steps,
            num_decay_steps=self.scheduler_decay_steps,
        )

    def validate_features(self) -> None:
        if not self.image_features:
            raise ValueError(
                "EB-VLA needs at least one camera (a VISUAL input feature such as `observation.image` or "
                f"`observation.images.<camera>`). Got input features {list(self.input_features)}."
            )
        if self.action_feature is None:
            raise ValueError(f"EB-VLA needs an 'action' output feature. Got {list(self.output_features)}.")
        crop, resize = self.resnet.crop_shape, self.resnet.resize_shape
        if self.backbone == "resnet" and resize is None and crop is not None:
            for key, feature in self.image_features.items():
                if crop[0] > feature.shape[1] or crop[1] > feature.shape[2]:
                    raise ValueError(
                        f"`resnet.crop_shape` {crop} does not fit in `{key}` of shape {feature.shape}."
                    )
        if self.backbone == "resnet":
            height, width = crop or resize or next(iter(self.image_features.values())).shape[1:]
            self.validate_light_backbone_image(height, width)
        if self.joint_energy.encoder_resize_shape is not None:
            if self.backbone != "resnet":
                raise ValueError(
                    "`joint_energy.encoder_resize_shape` sizes the light backbone's frames; the VLM backbone "
                    f"reads them at its own size. Got backbone={self.backbone!r}."
                )
            self.validate_light_backbone_image(
                *self.joint_energy.encoder_resize_shape, fields="`joint_energy.encoder_resize_shape`"
            )
        if self.monitor.response == "hold" and self.monitor.hold_action == "current_state":
            self._validate_current_state_hold()
        if self.backbone == "resnet" and len({f.shape for f in self.image_features.values()}) > 1:
            raise ValueError(
                "The light backbone needs all cameras at the same shape (set `resnet.resize_shape`). Got "
                f"{ {k: tuple(f.shape) for k, f in self.image_features.items()} }."
            )

    def validate_light_backbone_image(
        self, height: int, width: int, fields: str = "`resnet.resize_shape`/`resnet.crop_shape`"
    ) -> None:
        """Raises a ValueError when images of height x width (after resize and crop, as `fields` set them) are too
        small for the light backbone's kept ResNet stages."""
        # Each kept ResNet stage halves the map after a 4x stem; on a 1x1 map the keypoints are constant.
        stages = self.resnet.vision_backbone_stages
        stride = 2 ** (stages + 1)
        if min(height, width) <= stride:
            raise ValueError(
                f"The light backbone with `resnet.vision_backbone_stages={stages}` needs "
                f"images larger than {stride} px (got {height}x{width} after {fields}): "
                "smaller ones give a 1x1 ResNet feature map whose keypoints carry no information."
            )

    def _validate_current_state_hold(self) -> None:
        """Holding the current state sends `observation.state` as the action: both must mean the same."""
        if self.state_dim != self.action_dim:
            raise ValueError(
                "`monitor.hold_action='current_state'` sends `observation.state` as the action, so both must have the "
                f"same size. Got state {self.state_dim} and action {self.action_dim}: use 'zero_delta' for "
                "delta actions."
            )
        names = (self.state_feature_names, self.action_feature_names)
        if None not in names and list(names[0]) != list(names[1]):
            raise ValueError(
                "`monitor.hold_action='current_state'` needs `state_feature_names` and `action_feature_names` to match, "
                f"dimension by dimension. Got {names[0]} and {names[1]}."
            )

    def set_dataset_feature_metadata(self, features: dict[str, dict]) -> None:
        """Records the dataset's state and action names; LeRobot's `make_policy` calls it with the dataset."""
        self.state_feature_names = _names(features, OBS_STATE)
        self.action_feature_names = _names(features, ACTION)

    @property
    def context_energy_on_own_encoder(self) -> bool:
        """Whether the policy adds the joint energy's E_c(C) read through its own copy of the backbone."""
        return self.joint_energy.on_own_encoder

    @property
    def action_dim(self) -> int:
        return self.action_feature.shape[0]

    @property
    def state_dim(self) -> int | None:
        state = self.robot_state_feature
        return None if state is None else state.shape[0]

    @property
    def observation_delta_indices(self) -> None:
        return None

    @property
    def action_delta_indices(self) -> list[int]:
        return list(range(self.chunk_size))

    @property
    def reward_delta_indices(self) -> None:
        return None


def load_saved_config(pretrained_name_or_path: str | Path, **kwargs) -> PreTrainedConfig:
    """The saved config; a value its checks reject is reported with the file and the field, which draccus's
    own "Couldn't instantiate class" message leaves out."""
    try:
        return EBVLAConfig.from_pretrained(pretrained_name_or_path, **kwargs)
    except draccus.utils.ParsingError as e:
        if not isinstance(e.__cause__, ValueError | TypeError):
            raise
        raise ValueError(f"{CONFIG_NAME} of {pretrained_name_or_path}: {e.__cause__}") from e


def _names(features: dict[str, dict], key: str) -> list[str] | None:
    """The per-dimension names of a dataset feature (LeRobot's `names`), None when it has none."""
    names = features.get(key, {}).get("names")
    if isinstance(names, dict):  # {"motors": [...]} in some datasets
        names = next(iter(names.values()), None)
    return None if names is None else [str(n) for n in names]


# Where each field of a `config.json` saved before the nested groups lives now (`group.field`). A key that is
# still a field of `EBVLAConfig` is not moved.
LEGACY_FIELDS: dict[str, str] = {
    "vision_backbone": "resnet.vision_backbone",
    "pretrained_backbone_weights": "resnet.pretrained_backbone_weights",
    "resize_shape": "resnet.resize_shape",
    "crop_shape": "resnet.crop_shape",
    "crop_is_random": "resnet.crop_is_random",
    "use_group_norm": "resnet.use_group_norm",
    "spatial_softmax_num_keypoints": "resnet.spatial_softmax_num_keypoints",
    "vision_backbone_stages": "resnet.vision_backbone_stages",
    "camera_tokens": "resnet.camera_tokens",
    "use_separate_rgb_encoder_per_camera": "resnet.use_separate_rgb_encoder_per_camera",
    "state_dropout": "resnet.state_dropout",
    "task_instructions": "resnet.task_instructions",
    "vlm_model_name": "vlm.model_name",
    "dinov2_model_name": "vlm.dinov2_model_name",
    "siglip_model_name": "vlm.siglip_model_name",
    "load_pretrained_backbone": "vlm.load_pretrained_backbone",
    "vlm_config": "vlm.model_config",
    "vlm_config_overrides": "vlm.model_config_overrides",
    "vision_model_overrides": "vlm.vision_model_overrides",
    "vision_image_size": "vlm.vision_image_size",
    "freeze_vision_encoder": "vlm.freeze_vision_encoder",
    "frozen_weights_dtype": "vlm.frozen_weights_dtype",
    "lora_rank": "vlm.lora_rank",
    "lora_alpha": "vlm.lora_alpha",
    "lora_dropout": "vlm.lora_dropout",
    "lora_target_modules": "vlm.lora_target_modules",
    "num_latent_tokens": "vlm.num_latent_tokens",
    "tokenizer_max_length": "vlm.tokenizer_max_length",
    "context_layers": "vlm.context_layers",
    "num_context_layers": "vlm.num_context_layers",
    "energy_contrastive_weight": "contrastive.weight",
    "energy_contrastive_negatives": "contrastive.negatives",
    "energy_contrastive_mismatched": "contrastive.mismatched",
    "energy_contrastive_anchors": "contrastive.anchors",
    "energy_contrastive_noise_std": "contrastive.noise_std",
    "energy_contrastive_temperature": "contrastive.temperature",
    "energy_contrastive_dtype": "contrastive.dtype",
    "energy_ood_margin_weight": "joint_energy.weight",
    "energy_ood_margin": "joint_energy.margin",
    "energy_ood_margin_chunk": "joint_energy.chunk",
    "energy_ood_margin_on": "joint_energy.target",
    "energy_ood_corruptions": "joint_energy.corruptions",
    "energy_ood_corruption_strength": "joint_energy.corruption_strength",
    "energy_ood_gradient_penalty": "joint_energy.gradient_penalty",
    "ood_response": "monitor.response",
    "hold_action": "monitor.hold_action",
    "ood_threshold_k": "monitor.threshold_k",
}
# Configs saved before `compile_mode`: `compile_refinement=True` compiled the MCMC steps' energy in
# `compile_refinement_mode` ("default" when None); `compile_mode` compiles the context encoding too.
LEGACY_COMPILE_FIELDS = ("compile_refinement", "compile_refinement_mode")


def upgrade_legacy_fields(fields: dict) -> dict:
    """A saved config's fields (a `config.json`, its "type" removed or not) in today's shape: each flat key of
    `LEGACY_FIELDS` moved into its group, and `compile_refinement`/`compile_refinement_mode` read into
    `compile_mode`, with one FutureWarning naming what moved. Today's fields pass unchanged."""
    current = {f.name for f in dataclasses.fields(EBVLAConfig)}
    fields, moved = dict(fields), []
    for old, new in LEGACY_FIELDS.items():
        if old not in fields or old in current:
            continue
        group, name = new.split(".")
        nested = fields.get(group, {})
        if not isinstance(nested, dict) or name in nested:
            raise ValueError(
                f"The saved config sets both `{old}` (saved before the nested groups) and `{new}`."
            )
        fields[group] = {**nested, name: fields.pop(old)}
        moved.append(f"{old} -> {new}")
    if any(key in fields for key in LEGACY_COMPILE_FIELDS):
        enabled, legacy_mode = (fields.pop(key, None) for key in LEGACY_COMPILE_FIELDS)
        legacy_mode = legacy_mode or "default"
        if legacy_mode not in COMPILE_MODES[1:]:
            raise ValueError(
                f"`compile_refinement_mode` (deprecated, read into `compile_mode`) must be one of "
                f"{COMPILE_MODES[1:]}. Got {legacy_mode!r}."
            )
        if enabled:
            if fields.get("compile_mode", "off") not in ("off", legacy_mode):
                raise ValueError(
                    f"`compile_refinement=True` with `compile_refinement_mode={legacy_mode!r}` (deprecated) asks "
                    f"for `compile_mode={legacy_mode!r}`, but `compile_mode` is {fields['compile_mode']!r}: set "
                    "`compile_mode` alone."
                )
            fields["compile_mode"] = legacy_mode
        if enabled is not None:
            moved.insert(
                0, f"compile_refinement={enabled} -> compile_mode={fields.get('compile_mode', 'off')!r}"
            )
    if moved:
        warnings.warn(
            f"This EB-VLA config was saved before its fields were grouped: {len(moved)} read into today's form "
            f"(LEGACY_FIELDS): {', '.join(moved[:3])}{', ...' if len(moved) > 3 else ''}. Saving the config "
            "again stores the new form.",
            FutureWarning,
            stacklevel=2,
        )
    return fields
