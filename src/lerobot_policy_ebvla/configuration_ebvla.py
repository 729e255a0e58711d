"""Configuration of the Energy-Based VLA (EB-VLA) policy.

Defaults are the paper's (Table V): the full VLA with a fused DINOv2+SigLIP vision encoder, Qwen2.5-0.5B
with LoRA, K_a = 64 latent tokens and an L = 4 block, D = 896 energy head refined by 15 MCMC steps.
The light backbone (`backbone="resnet"`) is LeRobot's Diffusion Policy image encoder, for the paper's
head-only experiments (Sec. III-A) and for CPU training.
"""

import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import draccus
from huggingface_hub.constants import CONFIG_NAME
from lerobot.configs import NormalizationMode, PreTrainedConfig
from lerobot.optim import AdamWConfig, CosineDecayWithWarmupSchedulerConfig
from lerobot.policies.rtc.configuration_rtc import RTCConfig
from lerobot.utils.constants import ACTION, OBS_STATE

BACKBONES = ("vlm", "resnet")
CAMERA_TOKENS = ("keypoints", "feature_map")
STEP_SIZE_SAMPLINGS = ("per_chain", "per_mcmc_step")
OOD_RESPONSES = ("continue", "hold", "raise")
HOLD_ACTIONS = ("zero_delta", "current_state")
COMPILE_MODES = (
    "off",
    "default",
    "reduce-overhead",
    "max-autotune",
    "max-autotune-no-cudagraphs",
    "chunk-graph",
)
FROZEN_WEIGHTS_DTYPES = ("bfloat16", "float32")
CONTRASTIVE_DTYPES = ("float32", "bfloat16", "auto")
# The generic corruptions of `training_signal.corrupt_observation` (kept here: the config imports no torch).
OOD_CORRUPTIONS = ("channel_gain", "patch_swap", "shift", "state_noise", "random_conv", "shading")
OOD_MARGIN_CHUNKS = ("expert", "refined")
OOD_MARGIN_TARGETS = ("head", "context", "context_backbone", "observation")


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
        vision_backbone: torchvision ResNet of the light backbone (LeRobot's Diffusion Policy encoder).
        pretrained_backbone_weights: torchvision weights of the light backbone; None trains from scratch
            (the default, as torchvision's weights need a download).
        resize_shape: (H, W) the light backbone resizes images to before cropping; None keeps their size.
        crop_shape: (H, W) crop of the light backbone (random when training if `crop_is_random`).
        crop_is_random: Random crop at training time, center crop at inference.
        use_group_norm: Replace the ResNet's BatchNorm by GroupNorm (needs `pretrained_backbone_weights=None`).
        spatial_softmax_num_keypoints: Keypoints of the light backbone's spatial-softmax pooling.
        vision_backbone_stages: How many of the ResNet's four stages the light backbone keeps. Diffusion
            Policy keeps all 4 (stride 32: a 3x3 map at 96 px, on which the keypoints barely move); 2 keeps a
            stride-8 map (12x12 at 96 px) whose keypoints can follow an object from scratch in minutes.
        camera_tokens: What the light backbone passes on per camera. "keypoints" (Diffusion Policy's encoder):
            one token from spatial-softmax keypoints. "feature_map": one token per cell of the last kept ResNet
            feature map (with `vision_backbone_stages=3`, 6x6 at 96 px), which the head's cross-attention reads
            like the VLM's patch tokens; it learns to see far sooner (docs/energy_study.md).
        use_separate_rgb_encoder_per_camera: One light image encoder per camera instead of a shared one.
        state_dropout: Probability of hiding the state token p from the light backbone's context for a
            training sample. When the state alone predicts the expert well, a policy trained with it never
            learns to read its cameras; hiding it now and then makes the images pay. 0 (the paper) never hides it.
        task_instructions: Light backbone only: the task instructions it tells apart, one learned context token
            each, for multi-task data whose tasks differ only by instruction (LIBERO-Object: the same scene,
            "pick up the X"). `[]` asks for the training dataset's tasks (`lerobot-train` passes its metadata to
            the policy, which fills the list, so the checkpoint's config keeps it); None (the default) adds no
            task token. The VLM backbone reads the instruction itself and ignores this field.
        vlm_model_name: Hugging Face id (or local folder) of the language model and its tokenizer
            (Qwen2.5-0.5B). Read only when `vlm_config` is None, when loading pretrained weights, and when
            the pre-processor is first built; checkpoints carry the rest.
        dinov2_model_name: timm name of the DINOv2 encoder of the fused vision encoder, or a local folder in
            timm's Hub format (config.json + model.safetensors) as 'local-dir:/path'.
        siglip_model_name: timm name of the SigLIP encoder (or 'local-dir:/path'). The `.webli` tag pins the
            original SigLIP of Prismatic and OpenVLA-OFT: untagged, recent timm resolves to SigLIP 2.
        load_pretrained_backbone: Load the VLM and vision weights from the Hub, the local cache or the local
            folders the names point to; without them it raises `PretrainedWeightsUnavailableError`. False
            builds them with random weights from their configs (tests, meta-device sizing, and
            `EBVLAPolicy.from_pretrained`, whose checkpoint holds every weight).
        vlm_config: The language model's resolved config (`PretrainedConfig.to_diff_dict()`). None resolves
            it from `vlm_model_name` plus `vlm_config_overrides` at the first build and records it here, so
            that a saved `config.json` rebuilds the model with no network.
        vlm_config_overrides: Overrides applied to the language model's config when `vlm_config` is
            resolved, e.g. {"num_hidden_layers": 2, "hidden_size": 64} for a tiny model. Empty for the real
            model. Once `vlm_config` is recorded they are part of it; set `vlm_config=None` to re-resolve.
        vision_model_overrides: Keyword arguments passed to both `timm.create_model` calls of the vision
            encoder, e.g. {"depth": 2, "embed_dim": 32, "num_heads": 2} for tiny test encoders.
        vision_image_size: Side of the square images the vision encoders see (224 in Prismatic). Each
            camera gives (vision_image_size / 14)^2 tokens, 256 at 224 px.
        freeze_vision_encoder: Keep the DINOv2 and SigLIP weights frozen (the paper's setting).
        frozen_weights_dtype: Precision of the frozen weights (vision encoders when frozen, base language
            model): "bfloat16" rounds them to bf16 when the backbone is built, the precision they run at
            on a GPU, so checkpoints store them in bf16 at no loss (about half the size at full scale);
            "float32" keeps them as loaded, and checkpoints then store them in fp32.
        lora_rank: LoRA rank of the language model's adapters.
        lora_alpha: LoRA scaling alpha (updates scaled by alpha / rank). 128 = 2 x rank is VLA-Adapter's
            choice for this Qwen2.5-0.5B backbone; OpenVLA-OFT uses min(rank, 16) on its 7B model.
        lora_dropout: LoRA dropout.
        lora_target_modules: Language-model modules that receive LoRA adapters.
        num_latent_tokens: Number K_a of learned latent embeddings appended to the prompt.
        tokenizer_max_length: Number of prompt tokens of the task instruction (padded or truncated to it).
        context_layers: Hidden-state index l_i (0 is the embedding output, N_layers the last layer) whose
            h_a, h_t feed head block i; one entry per head block. None spreads the blocks evenly over the
            first `num_context_layers` hidden states 0..N_l - 1, both ends included: (0, 7, 15, 22) for
            Qwen2.5-0.5B (Table V). LoRA adapts only the layers up to the deepest l_i.
        num_context_layers: Number N_l of hidden states extracted, the embedding output included, when
            `context_layers` is None; at most the language model's layers + 1.
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
        energy_contrastive_weight: Weight lambda of an added InfoNCE term that ranks the expert chunk a*
            below negatives under the same context: the expert chunks of the batch's other observations
            (`energy_contrastive_mismatched` of them) and `energy_contrastive_negatives` noisy copies of a*. 0 (the paper) trains the energy only
            through the refined chunk's L1 loss (Eq. 4), which constrains its gradient, not its level.
        energy_contrastive_negatives: Noisy copies of a* per observation used as negatives.
        energy_contrastive_mismatched: Other observations' expert chunks per observation used as negatives;
            None takes all B - 1 of the batch. The term costs one head forward and backward per (context,
            candidate) pair, B x (1 + mismatched + noisy) chunks a step, the largest share of a light training
            step (BENCHMARKS.md, section 7); fewer candidates make it proportionally cheaper.
        energy_contrastive_anchors: How many of the batch's observations rank their candidates (the first ones:
            the batch is shuffled); None takes all B. Each anchor keeps every mismatched candidate of the batch,
            so fewer anchors cut the term's cost in proportion while each ranking still sees the whole batch:
            an unbiased estimate of the same InfoNCE loss with more variance.
        energy_contrastive_noise_std: Std of the noise of those copies (normalized action units).
        energy_contrastive_dtype: Precision of the head's matrix products in the contrastive term: "float32";
            "bfloat16" (autocast; the candidates' energies and the loss stay fp32); "auto", bfloat16 where the
            device computes it natively (a CUDA GPU with bf16, a CPU with AVX512-BF16 or AMX) and float32
            elsewhere, where emulated bf16 would be slower. The term needs only first-order gradients and ranks
            energies against each other, so it tolerates bf16's rounding; the MCMC chain, whose last step is
            differentiated twice, always runs at the policy's own precision.
        energy_contrastive_temperature: Temperature of the InfoNCE logits -E / T. The energy level also sets
            the MCMC step length exp(e_t / tau) (Eq. 3); a small T asks for small energy gaps only, so the
            ranking does not inflate the energies that drive refinement.
        energy_ood_margin_weight: Weight of an added outlier-exposure term (`training_signal`, issue 32):
            under a generically corrupted copy of each observation (`energy_ood_corruptions`), the expert
            chunk's energy must exceed its energy under the real observation by `energy_ood_margin` (hinge).
            The L1 and contrastive terms leave the energy's level per context free, so an unseen context can
            sit below the data and read as more familiar than vanilla; this term pins the level. 0 (default)
            is off. It costs one more backbone pass and one head pass per training step.
        energy_ood_margin: Margin m of that hinge, in energy units.
        energy_ood_margin_on: What the margin trains. "head": the head's energy E(a, C) itself (with
            `energy_ood_margin_chunk`), through the backbone. "context": a joint energy E(a, C) + E_c(C), E_c a
            small learned energy of the pooled (detached) context, trained by the margin alone and added to the
            final energy only: the refinement, whose step length exp(e_t / tau) grows with the head's energy,
            and the backbone are left as without the term. "context_backbone": the same joint energy, its margin
            also training the backbone (the context E_c reads is not detached), so that the backbone learns
            what sets a corrupted observation apart; E_c has no gradient in a, so the refinement's landscape
            and step lengths are still the head's alone, and the actions change only as the shared context does.
            "observation": the same joint energy, E_c reading the pooled context of its own copy of the
            backbone (built as the policy's, trained by the margin alone): E_c learns what sets a corrupted
            observation apart, as through the backbone, while the policy's backbone and head train exactly as
            without the term. It costs a second backbone pass per chunk at inference and two per training step.
            Give it a small weight (0.01): Adam normalizes the encoder's and E_c's own updates, so the weight
            only sets how much their gradients add to the norm LeRobot clips over all the policy's parameters
            (at 1.0 they held it at 18-34 for the first 400 steps, shrinking the policy's updates).
        energy_ood_margin_chunk: Which chunk's energies the hinge compares: "expert", a* under C~ against a*
            under C; "refined", the chunk refined under C~ (same a^(0) and step sizes, no graph) against the
            training chain's refined chunk under C, so that min_a E(a, C~) rises (the shift's refined energy can
            fall while E(a*, C~) rises: docs/energy_study.md).
        energy_ood_corruptions: Corruptions drawn from (one per observation), a non-empty subset of
            `training_signal.CORRUPTIONS`: "channel_gain" (random per-channel gains), "patch_swap" (a
            rectangle from another observation of the batch), "shift" (a translation with a black border),
            "state_noise" (N(0, 1) added to the normalized state), "random_conv" (the image through a random
            3x3 or 5x5 convolution that mixes its channels, rescaled to [0, 1]: RandConv, Xu et al., ICLR 2021,
            a generic family of colour and texture changes), "shading" (the image times a smooth random
            achromatic gain field, a log-linear gradient plus one Gaussian blob: light falling unevenly).
        energy_ood_corruption_strength: Range [s_min, s_max] of each corruption's strength s, drawn per
            observation: the observation is moved the fraction s of the way to its corrupted copy (images and
            state, `training_signal.graded_corruption`) and its margin is s m, so that the energy learns to
            rise with how far an observation left the data, not only whether. (1, 1) (default): the full
            corruption at margin m. (0.1, 1) lifted mild blur and noise on two of three training seeds and
            inverted light direction on the third (docs/energy_study.md, section 8.7): opt-in.
        energy_ood_gradient_penalty: Weight gamma of a gradient penalty on the context energy at the data,
            gamma E ||d E_c(C(x)) / d x||^2 over the real images x (R1, Mescheder et al., ICML 2018), added to
            the margin's loss; needs `energy_ood_margin_on="observation"`. The margin lifts E_c on the training
            corruptions only; a shift it never saw moves E_c by its gradient at the image, up in one scene and
            down in another, and a mild one lands inside the vanilla band on either side (docs/energy_study.md,
            section 8.11). With no gradient at the data every small change of the image moves E_c at second
            order, where the margin has made it rise. 0 (default) is off; it differentiates E_c twice through
            the observation encoder at each training step.
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
            encoding and the energy's forward and grad_a backward at each MCMC step; training is never
            compiled. "off" (the default) runs eagerly; "default" (inductor), "max-autotune" and
            "max-autotune-no-cudagraphs" are torch.compile's modes; "reduce-overhead" and "max-autotune"
            replay CUDA graphs on a CUDA device and run their no-graph form elsewhere, with a warning.
            "chunk-graph" encodes the context as "reduce-overhead" and captures each chunk's whole refinement
            (the K_inf steps of the eager head, the Langevin noise drawn beforehand, and the final energy) in one
            CUDA graph per input shape, replayed once per chunk (`compile_ebvla.RefinementGraphs`); with
            `early_stop_tol` its steps are graphed one by one instead, and without CUDA it runs the context as
            "default" and the refinement eagerly. Shapes
            are static: each batch size compiles on its first chunk, and dynamo keeps 8 of them per process
            (`torch._dynamo.config.recompile_limit`), so warm up with one chunk at every batch size you deploy;
            each new combination of the light backbone's `task_instructions` in a batch compiles the encoding
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
        ood_response: What the policy does with a refined chunk whose score (the calibration's, one of the
            registry `runtime.scores.SCORES`: `context_knn` as `ebvla-ood-report --calibrate_to` saves it
            without `--score`, `final_energy` for the paper's) exceeds the OOD
            threshold T of the checkpoint's `ood_calibration.json` (see `runtime/response.py`): "continue"
            executes it and logs a warning (the default; without a calibration nothing is checked), "hold"
            executes `hold_action` instead, "raise" raises `EnergyOODError`.
        hold_action: The action a held chunk repeats, required with `ood_response="hold"` because it depends
            on the action space: "zero_delta" (raw action 0) for end-effector delta actions (LIBERO,
            MetaWorld), "current_state" (the observed `observation.state`) for absolute joint targets
            (SO-100); the latter needs state and action of the same size and, when known, the same names.
        ood_threshold_k: Multiplier k of T = mu_v + k * sigma_v (Eq. 5); None uses the calibration's own k.
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
        compile_refinement: Deprecated, read only from configs saved before `compile_mode`: True maps to
            `compile_mode=compile_refinement_mode` (it compiled the MCMC steps' energy only; the context
            encoding is now compiled too), False to leaving `compile_mode` as it is, with a FutureWarning.
            Both fields are then reset to None. A `compile_mode` other than "off" that differs from the
            mapped mode is an error.
        compile_refinement_mode: Deprecated: the mode of `compile_refinement` ("default" when None).

    Every field is checked in `__post_init__`, which raises a ValueError naming it.
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

    # Light backbone: LeRobot's Diffusion Policy image encoder (field names match `DiffusionConfig`).
    vision_backbone: str = "resnet18"
    pretrained_backbone_weights: str | None = None
    resize_shape: tuple[int, int] | None = None
    crop_shape: tuple[int, int] | None = None
    crop_is_random: bool = True
    use_group_norm: bool = True
    spatial_softmax_num_keypoints: int = 32
    vision_backbone_stages: int = 4
    camera_tokens: str = "keypoints"
    use_separate_rgb_encoder_per_camera: bool = False
    state_dropout: float = 0.0
    task_instructions: list[str] | None = None

    # VLM backbone (Sec. II-A).
    vlm_model_name: str = "Qwen/Qwen2.5-0.5B"
    dinov2_model_name: str = "vit_large_patch14_reg4_dinov2.lvd142m"
    siglip_model_name: str = "vit_so400m_patch14_siglip_224.webli"
    load_pretrained_backbone: bool = True
    vlm_config: dict | None = None
    vlm_config_overrides: dict = field(default_factory=dict)
    vision_model_overrides: dict = field(default_factory=dict)
    vision_image_size: int = 224
    freeze_vision_encoder: bool = True
    frozen_weights_dtype: str = "bfloat16"
    lora_rank: int = 64
    lora_alpha: int = 128
    lora_dropout: float = 0.0
    lora_target_modules: tuple[str, ...] = (
        "q_proj",
        "k_proj",
        "v_proj",
        "o_proj",
        "gate_proj",
        "up_proj",
        "down_proj",
    )
    num_latent_tokens: int = 64
    tokenizer_max_length: int = 48
    context_layers: tuple[int, ...] | None = None
    num_context_layers: int = 23

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
    energy_contrastive_weight: float = 0.0
    energy_contrastive_negatives: int = 8
    energy_contrastive_mismatched: int | None = None
    energy_contrastive_anchors: int | None = None
    energy_contrastive_noise_std: float = 0.5
    energy_contrastive_temperature: float = 0.1
    energy_contrastive_dtype: str = "float32"
    energy_ood_margin_weight: float = 0.0
    energy_ood_margin: float = 1.0
    energy_ood_margin_chunk: str = "expert"
    energy_ood_margin_on: str = "head"
    energy_ood_corruptions: tuple[str, ...] = ("channel_gain", "patch_swap", "shift")
    energy_ood_corruption_strength: tuple[float, float] = (1.0, 1.0)
    energy_ood_gradient_penalty: float = 0.0

    # Inference options beyond the paper (off by default).
    num_restarts: int = 1
    restart_energy_threshold: float | None = None
    early_stop_tol: float | None = None
    compile_mode: str = "off"
    rtc_config: RTCConfig | None = None

    # Deployment.
    ood_response: str = "continue"
    hold_action: str | None = None
    ood_threshold_k: float | None = None
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

    # Deprecated: declared only so that configs saved before `compile_mode` load; read into it, then cleared.
    compile_refinement: bool | None = None
    compile_refinement_mode: str | None = None

    def __post_init__(self):
        super().__post_init__()
        self._validate_structure()
        self._validate_light_backbone()
        self._validate_vlm_backbone()
        self._validate_energy_head()
        self._validate_mcmc()
        self._validate_training_signal()
        self._map_deprecated_compile_fields()
        self._validate_inference_options()
        self._validate_deployment()

    def _validate_structure(self) -> None:
        _check_one_of(self, "backbone", BACKBONES)
        if self.n_obs_steps != 1:
            raise ValueError(
                f"`n_obs_steps` must be 1: EB-VLA conditions on one observation. Got {self.n_obs_steps}."
            )
        _check_at_least(self, 1, "chunk_size")
        if not 1 <= self.n_action_steps <= self.chunk_size:
            raise ValueError(
                f"`n_action_steps` must be in [1, chunk_size={self.chunk_size}]. Got {self.n_action_steps}."
            )

    def _validate_light_backbone(self) -> None:
        _check_fraction(self, "state_dropout")
        _check_one_of(self, "camera_tokens", CAMERA_TOKENS)
        if self.vision_backbone_stages not in (1, 2, 3, 4):
            raise ValueError(
                f"`vision_backbone_stages` must be 1, 2, 3 or 4 (ResNet stages kept). Got {self.vision_backbone_stages}."
            )
        if self.use_group_norm and self.pretrained_backbone_weights:
            raise ValueError(
                "`use_group_norm=True` would discard the BatchNorm statistics of "
                f"`pretrained_backbone_weights={self.pretrained_backbone_weights!r}`: set one of them off."
            )

    def _validate_vlm_backbone(self) -> None:
        _check_at_least(
            self, 1, "num_latent_tokens", "lora_rank", "tokenizer_max_length", "num_context_layers"
        )
        if self.context_layers is not None and len(self.context_layers) != self.n_blocks:
            raise ValueError(
                f"`context_layers` needs one hidden-state index per head block (n_blocks={self.n_blocks}). "
                f"Got {self.context_layers}."
            )
        if self.context_layers is not None and min(self.context_layers) < 0:
            raise ValueError(
                f"`context_layers` are hidden-state indices (0 is the embedding output). Got {self.context_layers}."
            )
        _check_one_of(self, "frozen_weights_dtype", FROZEN_WEIGHTS_DTYPES)
        if self.vision_image_size < 14:
            raise ValueError(f"`vision_image_size` must be >= 14 (one patch). Got {self.vision_image_size}.")
        _check_positive(self, "lora_alpha")
        _check_fraction(self, "lora_dropout")
        if not self.lora_target_modules:
            raise ValueError("`lora_target_modules` must name at least one language-model module.")

    def _validate_energy_head(self) -> None:
        _check_at_least(self, 1, "n_blocks", "n_heads", "ffn_multiplier")
        if self.dim_model % self.n_heads != 0 or (self.dim_model // self.n_heads) % 2 != 0:
            raise ValueError(
                f"`dim_model` ({self.dim_model}) must be divisible by `n_heads` ({self.n_heads}) into an even "
                "head size (RoPE rotates pairs of channels)."
            )
        _check_fraction(self, "dropout")

    def _validate_mcmc(self) -> None:
        _check_positive(self, "energy_temperature", "grad_clip", "action_clamp", "inference_step_size")
        _check_positive(self, "init_action_std")
        _check_at_least(self, 0, "langevin_noise_std")
        _check_at_least(self, 1, "inference_mcmc_steps")
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

    def _validate_training_signal(self) -> None:
        _check_one_of(self, "train_step_size_sampling", STEP_SIZE_SAMPLINGS)
        _check_at_least(self, 0, "energy_contrastive_weight", "energy_contrastive_negatives")
        if self.energy_contrastive_mismatched is not None and self.energy_contrastive_mismatched < 0:
            raise ValueError(
                "`energy_contrastive_mismatched` must be >= 0 or None (all of the batch's other chunks). Got "
                f"{self.energy_contrastive_mismatched}."
            )
        if self.energy_contrastive_anchors is not None and self.energy_contrastive_anchors < 1:
            raise ValueError(
                "`energy_contrastive_anchors` must be >= 1 or None (every observation of the batch). Got "
                f"{self.energy_contrastive_anchors}."
            )
        _check_one_of(self, "energy_contrastive_dtype", CONTRASTIVE_DTYPES)
        _check_positive(self, "energy_contrastive_temperature", "energy_contrastive_noise_std")
        self._validate_ood_margin()

    def _validate_ood_margin(self) -> None:
        if self.energy_ood_margin_weight < 0:
            raise ValueError(f"`energy_ood_margin_weight` must be >= 0. Got {self.energy_ood_margin_weight}.")
        _check_positive(self, "energy_ood_margin")
        _check_one_of(self, "energy_ood_margin_chunk", OOD_MARGIN_CHUNKS)
        _check_one_of(self, "energy_ood_margin_on", OOD_MARGIN_TARGETS)
        unknown = [kind for kind in self.energy_ood_corruptions if kind not in OOD_CORRUPTIONS]
        if unknown or not self.energy_ood_corruptions:
            raise ValueError(
                f"`energy_ood_corruptions` must be a non-empty subset of {OOD_CORRUPTIONS}. "
                f"Got {self.energy_ood_corruptions}."
            )
        low, high = self.energy_ood_corruption_strength
        if not 0.0 < low <= high <= 1.0:
            raise ValueError(
                "`energy_ood_corruption_strength` must be [s_min, s_max] with 0 < s_min <= s_max <= 1. "
                f"Got {self.energy_ood_corruption_strength}."
            )
        if self.energy_ood_gradient_penalty < 0:
            raise ValueError(
                f"`energy_ood_gradient_penalty` must be >= 0. Got {self.energy_ood_gradient_penalty}."
            )
        if self.energy_ood_gradient_penalty > 0 and not self.context_energy_on_own_encoder:
            raise ValueError(
                "`energy_ood_gradient_penalty` > 0 differentiates the context energy of the observation encoder: "
                "it needs `energy_ood_margin_on='observation'` and `energy_ood_margin_weight` > 0. Got "
                f"energy_ood_margin_on={self.energy_ood_margin_on!r}, "
                f"energy_ood_margin_weight={self.energy_ood_margin_weight}."
            )

    def _validate_inference_options(self) -> None:
        _check_at_least(self, 1, "num_restarts")
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
        _check_one_of(self, "compile_mode", COMPILE_MODES)
        if self.rtc_config is not None and self.rtc_config.execution_horizon < 1:
            raise ValueError(
                f"`rtc_config.execution_horizon` must be >= 1. Got {self.rtc_config.execution_horizon}."
            )

    def _validate_deployment(self) -> None:
        _check_one_of(self, "ood_response", OOD_RESPONSES)
        if self.hold_action is not None and self.hold_action not in HOLD_ACTIONS:
            raise ValueError(
                f"`hold_action` must be one of {HOLD_ACTIONS} or None. Got {self.hold_action!r}."
            )
        if self.ood_response == "hold" and self.hold_action is None:
            raise ValueError(
                "`ood_response='hold'` needs an explicit `hold_action`, as holding depends on the action space: "
                "'zero_delta' (a zero raw action) for end-effector delta actions such as LIBERO's and "
                "MetaWorld's, 'current_state' (the observed `observation.state`) for absolute joint targets "
                "such as SO-100's."
            )
        if self.ood_threshold_k is not None and not 0 <= self.ood_threshold_k < float("inf"):
            raise ValueError(
                f"`ood_threshold_k` must be finite and >= 0, or None. Got {self.ood_threshold_k}."
            )

    def _map_deprecated_compile_fields(self) -> None:
        """Reads `compile_refinement`/`compile_refinement_mode` (configs saved before `compile_mode`) into
        `compile_mode`, then clears them, so that a config saved again stores `compile_mode` (and None here)."""
        if self.compile_refinement is None and self.compile_refinement_mode is None:
            return
        legacy_mode = self.compile_refinement_mode or "default"
        if legacy_mode not in COMPILE_MODES[1:]:
            raise ValueError(
                f"`compile_refinement_mode` (deprecated, read into `compile_mode`) must be one of "
                f"{COMPILE_MODES[1:]}. Got {legacy_mode!r}."
            )
        if self.compile_refinement:
            if self.compile_mode not in ("off", legacy_mode):
                raise ValueError(
                    f"`compile_refinement=True` with `compile_refinement_mode={legacy_mode!r}` (deprecated) asks "
                    f"for `compile_mode={legacy_mode!r}`, but `compile_mode` is {self.compile_mode!r}: set "
                    "`compile_mode` alone."
                )
            self.compile_mode = legacy_mode
        warnings.warn(
            f"`compile_refinement={self.compile_refinement}` and `compile_refinement_mode="
            f"{self.compile_refinement_mode!r}` are deprecated; the config now has `compile_mode="
            f"{self.compile_mode!r}` (a compiled mode compiles the context encoding too, not only the MCMC "
            "steps' energy). Set `compile_mode` instead; saving the config again stores it.",
            FutureWarning,
            stacklevel=3,
        )
        self.compile_refinement = self.compile_refinement_mode = None

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
        if self.backbone == "resnet" and self.resize_shape is None and self.crop_shape is not None:
            for key, feature in self.image_features.items():
                if self.crop_shape[0] > feature.shape[1] or self.crop_shape[1] > feature.shape[2]:
                    raise ValueError(
                        f"`crop_shape` {self.crop_shape} does not fit in `{key}` of shape {feature.shape}."
                    )
        if self.backbone == "resnet":
            height, width = (
                self.crop_shape or self.resize_shape or next(iter(self.image_features.values())).shape[1:]
            )
            self.validate_light_backbone_image(height, width)
        if self.ood_response == "hold" and self.hold_action == "current_state":
            self._validate_current_state_hold()
        if self.backbone == "resnet" and len({f.shape for f in self.image_features.values()}) > 1:
            raise ValueError(
                "The light backbone needs all cameras at the same shape (set `resize_shape`). Got "
                f"{ {k: tuple(f.shape) for k, f in self.image_features.items()} }."
            )

    def validate_light_backbone_image(self, height: int, width: int) -> None:
        """Raises a ValueError when images of height x width (after resize and crop) are too small for the light
        backbone's kept ResNet stages."""
        # Each kept ResNet stage halves the map after a 4x stem; on a 1x1 map the keypoints are constant.
        stride = 2 ** (self.vision_backbone_stages + 1)
        if min(height, width) <= stride:
            raise ValueError(
                f"The light backbone with `vision_backbone_stages={self.vision_backbone_stages}` needs "
                f"images larger than {stride} px (got {height}x{width} after `resize_shape`/`crop_shape`): "
                "smaller ones give a 1x1 ResNet feature map whose keypoints carry no information."
            )

    def _validate_current_state_hold(self) -> None:
        """Holding the current state sends `observation.state` as the action: both must mean the same."""
        if self.state_dim != self.action_dim:
            raise ValueError(
                "`hold_action='current_state'` sends `observation.state` as the action, so both must have the "
                f"same size. Got state {self.state_dim} and action {self.action_dim}: use 'zero_delta' for "
                "delta actions."
            )
        names = (self.state_feature_names, self.action_feature_names)
        if None not in names and list(names[0]) != list(names[1]):
            raise ValueError(
                "`hold_action='current_state'` needs `state_feature_names` and `action_feature_names` to match, "
                f"dimension by dimension. Got {names[0]} and {names[1]}."
            )

    def set_dataset_feature_metadata(self, features: dict[str, dict]) -> None:
        """Records the dataset's state and action names; LeRobot's `make_policy` calls it with the dataset."""
        self.state_feature_names = _names(features, OBS_STATE)
        self.action_feature_names = _names(features, ACTION)

    @property
    def context_energy_on_own_encoder(self) -> bool:
        """Whether the policy adds the joint energy's E_c(C) read through its own copy of the backbone."""
        return context_energy_on_own_encoder(self.energy_ood_margin_on, self.energy_ood_margin_weight)

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
        return PreTrainedConfig.from_pretrained(pretrained_name_or_path, **kwargs)
    except draccus.utils.ParsingError as e:
        if not isinstance(e.__cause__, ValueError | TypeError):
            raise
        raise ValueError(f"{CONFIG_NAME} of {pretrained_name_or_path}: {e.__cause__}") from e


def context_energy_on_own_encoder(margin_on: str, margin_weight: float) -> bool:
    """The rule of `EBVLAConfig.context_energy_on_own_encoder` from the two fields, for a saved `config.json`."""
    return margin_weight > 0 and margin_on == "observation"


def _names(features: dict[str, dict], key: str) -> list[str] | None:
    """The per-dimension names of a dataset feature (LeRobot's `names`), None when it has none."""
    names = features.get(key, {}).get("names")
    if isinstance(names, dict):  # {"motors": [...]} in some datasets
        names = next(iter(names.values()), None)
    return None if names is None else [str(n) for n in names]


def _check_at_least(config: EBVLAConfig, minimum: int, *names: str) -> None:
    for name in names:
        if getattr(config, name) < minimum:
            raise ValueError(f"`{name}` must be >= {minimum}. Got {getattr(config, name)}.")


def _check_positive(config: EBVLAConfig, *names: str) -> None:
    for name in names:
        if not getattr(config, name) > 0:
            raise ValueError(f"`{name}` must be > 0. Got {getattr(config, name)}.")


def _check_fraction(config: EBVLAConfig, *names: str) -> None:
    for name in names:
        if not 0 <= getattr(config, name) < 1:
            raise ValueError(f"`{name}` must be in [0, 1). Got {getattr(config, name)}.")


def _check_one_of(config: EBVLAConfig, name: str, choices: tuple[str, ...]) -> None:
    if getattr(config, name) not in choices:
        raise ValueError(f"`{name}` must be one of {choices}. Got {getattr(config, name)!r}.")
