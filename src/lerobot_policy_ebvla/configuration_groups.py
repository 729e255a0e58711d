"""The nested groups of `EBVLAConfig`: each backbone's options, and the training signals beyond the paper.

As LeRobot's `TrainPipelineConfig` nests `dataset`, `policy` and `eval`, the policy's config nests what only one
backbone or one opt-in training term reads, so that its top level reads like the paper's Table V. draccus parses
them as `--policy.<group>.<field>=...`, e.g. `--policy.joint_energy.weight=0.01`. Each group checks its own
fields in `__post_init__`, naming the dotted field; rules across groups live in `EBVLAConfig`.
"""

from dataclasses import dataclass, field

CAMERA_TOKENS = ("keypoints", "feature_map")
FROZEN_WEIGHTS_DTYPES = ("bfloat16", "float32")
CONTRASTIVE_DTYPES = ("float32", "bfloat16", "auto")
# The generic corruptions of `training_signal.corrupt_observation` (kept here: the config imports no torch).
OOD_CORRUPTIONS = ("channel_gain", "patch_swap", "shift", "state_noise", "random_conv", "shading")
OOD_MARGIN_CHUNKS = ("expert", "refined")
OOD_MARGIN_TARGETS = ("head", "context", "context_backbone", "observation")


@dataclass
class ResNetBackboneConfig:
    """The light backbone (`backbone="resnet"`): LeRobot's Diffusion Policy image encoder, its field names those of
    `DiffusionConfig`, for the paper's head-only experiments (Sec. III-A) and for CPU training.

    Args:
        vision_backbone: torchvision ResNet of the light backbone.
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
            training sample (a training signal beyond the paper). When the state alone predicts the expert well,
            a policy trained with it never learns to read its cameras; hiding it now and then makes the images
            pay. 0 (the paper) never hides it.
        task_instructions: The task instructions the light backbone tells apart, one learned context token
            each, for multi-task data whose tasks differ only by instruction (LIBERO-Object: the same scene,
            "pick up the X"). `[]` asks for the training dataset's tasks (`lerobot-train` passes its metadata to
            the policy, which fills the list, so the checkpoint's config keeps it); None (the default) adds no
            task token. The VLM backbone reads the instruction itself.
    """

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

    def __post_init__(self):
        check_fraction(self, "resnet", "state_dropout")
        check_one_of(self, "resnet", "camera_tokens", CAMERA_TOKENS)
        if self.vision_backbone_stages not in (1, 2, 3, 4):
            raise ValueError(
                "`resnet.vision_backbone_stages` must be 1, 2, 3 or 4 (ResNet stages kept). Got "
                f"{self.vision_backbone_stages}."
            )
        if self.use_group_norm and self.pretrained_backbone_weights:
            raise ValueError(
                "`resnet.use_group_norm=True` would discard the BatchNorm statistics of "
                f"`resnet.pretrained_backbone_weights={self.pretrained_backbone_weights!r}`: set one of them off."
            )


@dataclass
class VLMBackboneConfig:
    """The paper's vision-language backbone (`backbone="vlm"`, Sec. II-A): a fused DINOv2+SigLIP vision encoder
    and Qwen2.5-0.5B with LoRA, read through K_a latent tokens.

    Args:
        model_name: Hugging Face id (or local folder) of the language model and its tokenizer (Qwen2.5-0.5B).
            Read only when `model_config` is None, when loading pretrained weights, and when the pre-processor is
            first built; checkpoints carry the rest.
        dinov2_model_name: timm name of the DINOv2 encoder of the fused vision encoder, or a local folder in
            timm's Hub format (config.json + model.safetensors) as 'local-dir:/path'.
        siglip_model_name: timm name of the SigLIP encoder (or 'local-dir:/path'). The `.webli` tag pins the
            original SigLIP of Prismatic and OpenVLA-OFT: untagged, recent timm resolves to SigLIP 2.
        load_pretrained_backbone: Load the VLM and vision weights from the Hub, the local cache or the local
            folders the names point to; without them it raises `PretrainedWeightsUnavailableError`. False
            builds them with random weights from their configs (tests, meta-device sizing, and
            `EBVLAPolicy.from_pretrained`, whose checkpoint holds every weight).
        model_config: The language model's resolved config (`PretrainedConfig.to_diff_dict()`). None resolves
            it from `model_name` plus `model_config_overrides` at the first build and records it here, so that a
            saved `config.json` rebuilds the model with no network.
        model_config_overrides: Overrides applied to the language model's config when `model_config` is
            resolved, e.g. {"num_hidden_layers": 2, "hidden_size": 64} for a tiny model. Empty for the real
            model. Once `model_config` is recorded they are part of it; set `model_config=None` to re-resolve.
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
            h_a, h_t feed head block i; one entry per head block (`n_blocks`). None spreads the blocks evenly
            over the first `num_context_layers` hidden states 0..N_l - 1, both ends included: (0, 7, 15, 22) for
            Qwen2.5-0.5B (Table V). LoRA adapts only the layers up to the deepest l_i.
        num_context_layers: Number N_l of hidden states extracted, the embedding output included, when
            `context_layers` is None; at most the language model's layers + 1.
    """

    model_name: str = "Qwen/Qwen2.5-0.5B"
    dinov2_model_name: str = "vit_large_patch14_reg4_dinov2.lvd142m"
    siglip_model_name: str = "vit_so400m_patch14_siglip_224.webli"
    load_pretrained_backbone: bool = True
    model_config: dict | None = None
    model_config_overrides: dict = field(default_factory=dict)
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

    def __post_init__(self):
        check_at_least(
            self, "vlm", 1, "num_latent_tokens", "lora_rank", "tokenizer_max_length", "num_context_layers"
        )
        if self.context_layers is not None and min(self.context_layers, default=0) < 0:
            raise ValueError(
                "`vlm.context_layers` are hidden-state indices (0 is the embedding output). Got "
                f"{self.context_layers}."
            )
        check_one_of(self, "vlm", "frozen_weights_dtype", FROZEN_WEIGHTS_DTYPES)
        if self.vision_image_size < 14:
            raise ValueError(
                f"`vlm.vision_image_size` must be >= 14 (one patch). Got {self.vision_image_size}."
            )
        check_positive(self, "vlm", "lora_alpha")
        check_fraction(self, "vlm", "lora_dropout")
        if not self.lora_target_modules:
            raise ValueError("`vlm.lora_target_modules` must name at least one language-model module.")


@dataclass
class ContrastiveConfig:
    """An InfoNCE term that ranks the expert chunk a* below negatives under the same context (a training signal
    beyond the paper; `training_signal.contrastive_energy_loss`).

    Args:
        weight: Weight lambda of the term. Its negatives are the expert chunks of the batch's other
            observations (`mismatched` of them) and `negatives` noisy copies of a*. 0 (the paper) trains the
            energy only through the refined chunk's L1 loss (Eq. 4), which constrains its gradient, not its level.
        negatives: Noisy copies of a* per observation used as negatives.
        mismatched: Other observations' expert chunks per observation used as negatives; None takes all B - 1
            of the batch. The term costs one head forward and backward per (context, candidate) pair,
            B x (1 + mismatched + noisy) chunks a step, the largest share of a light training step
            (BENCHMARKS.md, section 7); fewer candidates make it proportionally cheaper.
        anchors: How many of the batch's observations rank their candidates (the first ones: the batch is
            shuffled); None takes all B. Each anchor keeps every mismatched candidate of the batch, so fewer
            anchors cut the term's cost in proportion while each ranking still sees the whole batch: an unbiased
            estimate of the same InfoNCE loss with more variance.
        noise_std: Std of the noise of the noisy copies (normalized action units).
        temperature: Temperature T of the InfoNCE logits -E / T. The energy level also sets the MCMC step
            length exp(e_t / tau) (Eq. 3); a small T asks for small energy gaps only, so the ranking does not
            inflate the energies that drive refinement.
        dtype: Precision of the head's matrix products in the term: "float32"; "bfloat16" (autocast; the
            candidates' energies and the loss stay fp32); "auto", bfloat16 where the device computes it natively
            (a CUDA GPU with bf16, a CPU with AVX512-BF16 or AMX) and float32 elsewhere, where emulated bf16
            would be slower. The term needs only first-order gradients and ranks energies against each other,
            so it tolerates bf16's rounding; the MCMC chain, whose last step is differentiated twice, always runs
            at the policy's own precision.
    """

    weight: float = 0.0
    negatives: int = 8
    mismatched: int | None = None
    anchors: int | None = None
    noise_std: float = 0.5
    temperature: float = 0.1
    dtype: str = "float32"

    def __post_init__(self):
        check_at_least(self, "contrastive", 0, "weight", "negatives")
        if self.mismatched is not None and self.mismatched < 0:
            raise ValueError(
                "`contrastive.mismatched` must be >= 0 or None (all of the batch's other chunks). Got "
                f"{self.mismatched}."
            )
        if self.anchors is not None and self.anchors < 1:
            raise ValueError(
                f"`contrastive.anchors` must be >= 1 or None (every observation of the batch). Got {self.anchors}."
            )
        check_one_of(self, "contrastive", "dtype", CONTRASTIVE_DTYPES)
        check_positive(self, "contrastive", "temperature", "noise_std")


@dataclass
class JointEnergyConfig:
    """Outlier exposure for the energy (issue 32; `training_signal`): under a generically corrupted copy of each
    observation, the energy must exceed its value under the real observation by a margin (hinge). The L1 and
    contrastive terms leave the energy's level per context free, so an unseen context can sit below the data and
    read as more familiar than vanilla; this term pins the level. With `target` other than "head" the final
    energy is the joint energy E(a, C) + E_c(C), E_c a small learned energy of the pooled context.

    Args:
        weight: Weight of the margin's term. 0 (default) is off. It costs one more backbone pass and one head
            pass per training step. With target "observation" give it a small weight (0.01): Adam normalizes
            the encoder's and E_c's own updates, so the weight only sets how much their gradients add to the
            norm LeRobot clips over all the policy's parameters (at 1.0 they held it at 18-34 for the first 400
            steps, shrinking the policy's updates).
        margin: Margin m of the hinge, in energy units.
        chunk: With target "head", which chunk's energies the hinge compares: "expert", a* under C~ against a*
            under C; "refined", the chunk refined under C~ (same a^(0) and step sizes, no graph) against the
            training chain's refined chunk under C, so that min_a E(a, C~) rises (the shift's refined energy can
            fall while E(a*, C~) rises: docs/energy_study.md).
        target: What the margin trains. "head": the head's energy E(a, C) itself (with `chunk`), through the
            backbone. "context": the joint energy, E_c reading the pooled (detached) context, trained by the
            margin alone and added to the final energy only: the refinement, whose step length exp(e_t / tau)
            grows with the head's energy, and the backbone are left as without the term. "context_backbone":
            the same joint energy, its margin also training the backbone (the context E_c reads is not
            detached), so that the backbone learns what sets a corrupted observation apart; E_c has no gradient
            in a, so the refinement's landscape and step lengths are still the head's alone. "observation": the
            same joint energy, E_c reading the pooled context of its own copy of the backbone (built as the
            policy's, trained by the margin alone): the policy's backbone and head train exactly as without the
            term. It costs a second backbone pass per chunk at inference and two per training step.
        corruptions: Corruptions drawn from (one per observation), a non-empty subset of
            `training_signal.CORRUPTIONS`: "channel_gain" (random per-channel gains), "patch_swap" (a
            rectangle from another observation of the batch), "shift" (a translation with a black border),
            "state_noise" (N(0, 1) added to the normalized state), "random_conv" (the image through a random
            3x3 or 5x5 convolution that mixes its channels, rescaled to [0, 1]: RandConv, Xu et al., ICLR 2021,
            a generic family of colour and texture changes), "shading" (the image times a smooth random
            achromatic gain field, a log-linear gradient plus one Gaussian blob: light falling unevenly).
        corruption_strength: Range [s_min, s_max] of each corruption's strength s, drawn per observation: the
            observation is moved the fraction s of the way to its corrupted copy (images and state,
            `training_signal.graded_corruption`) and its margin is s m, so that the energy learns to rise with
            how far an observation left the data, not only whether. (1, 1) (default): the full corruption at
            margin m. (0.1, 1) lifted mild blur and noise on two of three training seeds and inverted light
            direction on the third (docs/energy_study.md, section 8.7): opt-in.
        gradient_penalty: Weight gamma of a gradient penalty on the context energy at the data,
            gamma E ||d E_c(C(x)) / d x||^2 over the real images x (R1, Mescheder et al., ICML 2018), added to
            the margin's loss; needs target "observation" and `weight` > 0. The margin lifts E_c on the training
            corruptions only; a shift it never saw moves E_c by its gradient at the image, up in one scene and
            down in another (docs/energy_study.md, section 8.11). With no gradient at the data every small
            change of the image moves E_c at second order, where the margin has made it rise. 0 (default) is
            off; it differentiates E_c twice through the observation encoder at each training step.
        gradient_penalty_every: Lazy regularization (Karras et al., StyleGAN2, CVPR 2020): the penalty is
            taken on one training step in k, weighted k gamma, so that its expected gradient is unchanged. Its
            double backward through the observation encoder is about a quarter of a light training step on a
            CPU (research/docs/benchmarks_speed.md); 1 (default) takes it on every step.
        encoder_resize_shape: (height, width) the observation encoder resizes the frames to, for the light
            backbone with target "observation"; None (default) is the policy's own `resnet.resize_shape`. E_c
            reads the scene to tell it from the training data, not to act in it: a coarser frame costs its
            encoder (two passes and the penalty's double backward at each training step, one pass per chunk
            at inference) a quarter at half the side. On the MetaWorld sweep, 32 px with the penalty on one
            step in 4 pools as 64 px; a mild light-direction shift stays near chance at either side
            (research/results/metaworld_sweep_margin_full/summary.md, "A cheaper E_c" and "... with the raised
            starting energy"). The light preset sets (32, 32) and `gradient_penalty_every=4`.
    """

    weight: float = 0.0
    margin: float = 1.0
    chunk: str = "expert"
    target: str = "head"
    corruptions: tuple[str, ...] = ("channel_gain", "patch_swap", "shift")
    corruption_strength: tuple[float, float] = (1.0, 1.0)
    gradient_penalty: float = 0.0
    gradient_penalty_every: int = 1
    encoder_resize_shape: tuple[int, int] | None = None

    def __post_init__(self):
        check_at_least(self, "joint_energy", 0, "weight", "gradient_penalty")
        check_at_least(self, "joint_energy", 1, "gradient_penalty_every")
        check_positive(self, "joint_energy", "margin")
        check_one_of(self, "joint_energy", "chunk", OOD_MARGIN_CHUNKS)
        check_one_of(self, "joint_energy", "target", OOD_MARGIN_TARGETS)
        unknown = [kind for kind in self.corruptions if kind not in OOD_CORRUPTIONS]
        if unknown or not self.corruptions:
            raise ValueError(
                f"`joint_energy.corruptions` must be a non-empty subset of {OOD_CORRUPTIONS}. "
                f"Got {self.corruptions}."
            )
        low, high = self.corruption_strength
        if not 0.0 < low <= high <= 1.0:
            raise ValueError(
                "`joint_energy.corruption_strength` must be [s_min, s_max] with 0 < s_min <= s_max <= 1. "
                f"Got {self.corruption_strength}."
            )
        if self.gradient_penalty > 0 and not self.on_own_encoder:
            raise ValueError(
                "`joint_energy.gradient_penalty` > 0 differentiates the context energy of the observation "
                "encoder: it needs `joint_energy.target='observation'` and `joint_energy.weight` > 0. Got "
                f"target={self.target!r}, weight={self.weight}."
            )

        if self.encoder_resize_shape is not None:
            if len(self.encoder_resize_shape) != 2 or min(self.encoder_resize_shape) < 1:
                raise ValueError(
                    "`joint_energy.encoder_resize_shape` must be (height, width) in pixels, or None (the policy's). "
                    f"Got {self.encoder_resize_shape}."
                )
            if not self.on_own_encoder:
                raise ValueError(
                    "`joint_energy.encoder_resize_shape` sizes the frames of the observation encoder: it needs "
                    f"`joint_energy.target='observation'` and `joint_energy.weight` > 0. Got target={self.target!r}, "
                    f"weight={self.weight}."
                )

    @property
    def has_context_energy(self) -> bool:
        """Whether the policy adds a context energy E_c(C) to the head's final energy (the joint energy)."""
        return self.weight > 0 and self.target != "head"

    @property
    def on_own_encoder(self) -> bool:
        """Whether E_c reads the pooled context of its own copy of the backbone (target "observation")."""
        return self.weight > 0 and self.target == "observation"


@dataclass
class PhaseEnergyConfig:
    """The phase energy E_tau(C, t) = -log p(t | C), beyond the paper: how unlikely it is that a demonstration shows
    the pooled context C at chunk index t (`phase_energy.PhaseEnergy`). A per-chunk scalar of E_c or E - E_c cannot
    tell a rollout that never grasps from one that grasps on time; E_tau can, since the stalled rollout's context at
    chunk t is one the demonstrations show at an earlier t. It reads the backbone's pooled context and refines
    nothing: the actions and the other energies are unchanged.

    It is fitted after training, on the frozen backbone's contexts of the training demonstrations
    (`ebvla-fit-phase-energy`), so it reads the backbone the policy ships with rather than one that moved while it
    learned; that tool sets these fields in the checkpoint it writes.

    Args:
        bins: Chunk indices 0 .. bins - 1 that p(t | C) tells apart (later chunks share the last). 0 (the default):
            no phase energy.
        hidden: Width of the MLP f whose outputs are the energies of the bins, p(t | C) = softmax_t(-f(C))_t.
    """

    bins: int = 0
    hidden: int = 256

    def __post_init__(self):
        check_at_least(self, "phase_energy", 0, "bins")
        check_at_least(self, "phase_energy", 1, "hidden")
        if self.bins == 1:
            raise ValueError(
                "`phase_energy.bins` must be 0 (off) or >= 2: one bin tells no chunk from another."
            )


def check_at_least(config, group: str, minimum: int, *names: str) -> None:
    for name in names:
        if getattr(config, name) < minimum:
            raise ValueError(f"`{_dotted(group, name)}` must be >= {minimum}. Got {getattr(config, name)}.")


def check_positive(config, group: str, *names: str) -> None:
    for name in names:
        if not getattr(config, name) > 0:
            raise ValueError(f"`{_dotted(group, name)}` must be > 0. Got {getattr(config, name)}.")


def check_fraction(config, group: str, *names: str) -> None:
    for name in names:
        if not 0 <= getattr(config, name) < 1:
            raise ValueError(f"`{_dotted(group, name)}` must be in [0, 1). Got {getattr(config, name)}.")


def check_one_of(config, group: str, name: str, choices: tuple[str, ...]) -> None:
    if getattr(config, name) not in choices:
        raise ValueError(f"`{_dotted(group, name)}` must be one of {choices}. Got {getattr(config, name)!r}.")


def _dotted(group: str, name: str) -> str:
    """The field's name as the command line spells it: `group.name`, or `name` at the top level (group "")."""
    return f"{group}.{name}" if group else name


OOD_RESPONSES = ("continue", "hold", "raise")
HOLD_ACTIONS = ("zero_delta", "current_state")
# The scores a checkpoint can be monitored with (`runtime.scores.PACKAGE_SCORES`; the config imports no numpy),
# and those that read a joint energy's context term E_c.
MONITOR_SCORES = (
    "final_energy",
    "context_phase_energy",
    "head_energy_two_sided",
    "joint_phase_energy",
    "context_start_energy",
    "joint_phase_time_energy",
    "success_energy",
    "context_knn",
)
# The scores that read each chunk's pooled context: the policy passes it with the readout when one is monitored.
CONTEXT_FEATURE_SCORES = ("success_energy", "context_knn")
CONTEXT_ENERGY_SCORES = tuple(s for s in MONITOR_SCORES if s not in ("final_energy", *CONTEXT_FEATURE_SCORES))
# The scores that also read the phase energy E_tau (`phase_energy.bins` > 0).
PHASE_ENERGY_SCORES = ("joint_phase_time_energy",)
# The failure check of a checkpoint with a phase energy (the LIBERO ones `ebvla-fit-phase-energy` writes): the config's
# default where one is fitted, and what the fit sets (research/docs/libero_runs.md, "Narrower noisy copies, and a sixth
# set").
PHASE_FITTED_FAILURE_SCORE = "success_energy"
# The failure check stores no features (the success energy keeps a model, not contexts); "none" leaves it out.
FAILURE_SCORES = ("none", *(s for s in MONITOR_SCORES if s != "context_knn"))


@dataclass
class MonitorConfig:
    """How a checkpoint is monitored at run time: the score it is calibrated on, and what the policy does with
    a chunk that score flags (beyond the paper).

    Args:
        score: The chunk score `ebvla-ood-report --calibrate_to` calibrates and saves with the checkpoint (one
            of `runtime.scores.SCORES`'s package scores): "final_energy" (the paper's),
            "context_phase_energy" (a joint energy's context term E_c against the vanilla E_c at each chunk
            index: the light preset's, which trains E_c on its own encoder and flat at the data),
            "head_energy_two_sided" (the failure score: |z| of E - E_c at each chunk index),
            "joint_phase_energy" (z of E_c and of E - E_c at each chunk index, averaged),
            "joint_phase_time_energy" (those two and the z of the phase energy E_tau, averaged; needs
            `phase_energy.bins` > 0), "context_start_energy" (z of E_c and minus z of the head's energy of the MCMC's starting sample at
            each chunk index, averaged: the LIBERO checkpoints') or "context_knn" (the pooled context's distance
            to its nearest vanilla context, the feature baseline). The four E_c scores need the joint energy on
            its own encoder (`joint_energy.target="observation"` with
            `joint_energy.weight` > 0). None (the default) is decided by the training signal when the policy's
            config is made, and saved: "context_phase_energy" for a policy that trains E_c on its own encoder
            (an energy-only monitor, no features stored), "final_energy" otherwise.
        response: What the policy does with a refined chunk whose score exceeds the OOD threshold T of the
            checkpoint's `ood_calibration.json` (see `runtime/response.py`): "continue" executes it and logs a
            warning (the default; without a calibration nothing is checked), "hold" executes `hold_action`
            instead, "raise" raises `EnergyOODError`.
        hold_action: The action a held chunk repeats, required with `response="hold"` because it depends on
            the action space: "zero_delta" (raw action 0) for end-effector delta actions (LIBERO, MetaWorld),
            "current_state" (the observed `observation.state`) for absolute joint targets (SO-100); the latter
            needs state and action of the same size and, when known, the same names.
        threshold_k: Multiplier k of T = mu_v + k * sigma_v (Eq. 5); None uses the calibration's own k.
        failure_score: The energy score of the monitor's failure check (`runtime.EnergyMonitor`), which
            `ebvla-ood-report --calibrate_to` fits on the same vanilla rollouts and saves as
            `failure_calibration.json`: "head_energy_two_sided" (the head's part of the joint energy, E - E_c,
            against vanilla at each chunk index, on either side), "success_energy" (the success energy E_s(C, t),
            fitted by `--calibrate_to` on the successful calibration rollouts' pooled contexts and saved beside
            it: it needs about 100 of them, recorded with `--record_context_features=true`), another energy
            score, or "none". None (the default) is decided with `score`: "success_energy" where the policy trains
            E_c on its own encoder and has a phase energy (the LIBERO checkpoints `ebvla-fit-phase-energy`
            writes, calibrated on about 100 rollouts), "head_energy_two_sided" where it has E_c alone,
            "none" otherwise (without E_c no energy score told failures apart).
        failure_chunks: N, the first chunks the failure check scores; it decides at the end of chunk N.
    """

    score: str | None = None
    response: str = "continue"
    hold_action: str | None = None
    threshold_k: float | None = None
    failure_score: str | None = None
    failure_chunks: int = 3

    def __post_init__(self):
        if self.score is not None and self.score not in MONITOR_SCORES:
            raise ValueError(f"`monitor.score` must be one of {MONITOR_SCORES}. Got {self.score!r}.")
        if self.failure_score is not None and self.failure_score not in FAILURE_SCORES:
            raise ValueError(
                f"`monitor.failure_score` must be one of {FAILURE_SCORES}. Got {self.failure_score!r}."
            )
        if self.failure_chunks < 1:
            raise ValueError(f"`monitor.failure_chunks` must be >= 1. Got {self.failure_chunks}.")
        if self.response not in OOD_RESPONSES:
            raise ValueError(f"`monitor.response` must be one of {OOD_RESPONSES}. Got {self.response!r}.")
        if self.hold_action is not None and self.hold_action not in HOLD_ACTIONS:
            raise ValueError(
                f"`monitor.hold_action` must be one of {HOLD_ACTIONS} or None. Got {self.hold_action!r}."
            )
        if self.response == "hold" and self.hold_action is None:
            raise ValueError(
                "`monitor.response='hold'` needs an explicit `monitor.hold_action`, as holding depends on the "
                "action space: 'zero_delta' (a zero raw action) for end-effector delta actions such as LIBERO's "
                "and MetaWorld's, 'current_state' (the observed `observation.state`) for absolute joint targets "
                "such as SO-100's."
            )
        if self.threshold_k is not None and not 0 <= self.threshold_k < float("inf"):
            raise ValueError(
                f"`monitor.threshold_k` must be finite and >= 0, or None. Got {self.threshold_k}."
            )
