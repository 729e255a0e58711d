"""Energy-Based VLA (EB-VLA): "Energy-Based Action Heads Know When They Don't Know".

EB-VLA learns a scalar energy E_theta(a, C) over action chunks conditioned on the observation's context and
produces actions by gradient descent on it. The energy of the refined chunk is returned with it as a
confidence score: `EnergyReadout.final_energy` (higher means less expert-like). `runtime/` turns it into a
decision at run time; `monitoring/` studies it offline.
"""

import dataclasses
import logging
import math
import os
import tempfile
from collections import OrderedDict, deque
from collections.abc import Callable
from pathlib import Path

import torch
from huggingface_hub.constants import SAFETENSORS_SINGLE_FILE
from lerobot.configs import PreTrainedConfig
from lerobot.policies.pretrained import PreTrainedPolicy
from safetensors import SafetensorError
from torch import Tensor, nn
from torch.utils.hooks import RemovableHandle

from .backbone_resnet import EBVLAResNetBackbone
from .compile_ebvla import CHUNK_GRAPH_MODE, compiled_context, compiled_energy_fn, refinement_graphs
from .configuration_ebvla import EBVLAConfig, load_saved_config
from .configuration_groups import CONTEXT_FEATURE_SCORES
from .energy_head import ContextKV, EBVLAEnergyHead, pooled_context
from .inputs_ebvla import (
    batch_size_of,
    repeat_observations,
    validate_actions,
    validate_observation,
    without_inference_tensors,
)
from .mcmc import (
    EnergyFn,
    RefinementResult,
    RTCPrefix,
    draw_langevin_noise,
    refine_actions,
    sample_initial_actions,
)
from .phase_energy import PhaseEnergy
from .rtc_ebvla import rtc_prefix
from .runtime.readout import EnergyReadout
from .runtime.response import EnergyOODResponse, respond_to_energy
from .runtime.threshold import OODDecision
from .training_signal import EBVLAContextEnergy, compute_loss

logger = logging.getLogger(__name__)


# hook(policy, batch, readout, decision), called after each refined chunk the policy returns.
ChunkHook = Callable[["EBVLAPolicy", dict[str, Tensor], EnergyReadout, OODDecision | None], None]


class EBVLAPolicy(PreTrainedPolicy):
    """EB-VLA policy: a VLM (or light) backbone and an energy-based transformer head refined by MCMC."""

    config_class = EBVLAConfig
    name = "ebvla"

    def __init__(self, config: EBVLAConfig, dataset_meta=None, **kwargs):
        super().__init__(config)
        config.validate_features()
        if config.backbone == "resnet" and config.resnet.task_instructions == []:
            if dataset_meta is None:
                raise ValueError(
                    "`resnet.task_instructions=[]` asks for the training dataset's tasks, but no `dataset_meta` was "
                    "given: pass the dataset's metadata or list the instructions."
                )
            config.resnet.task_instructions = [str(task) for task in dataset_meta.tasks.index]
        self.config = config
        self.model = EBVLA(config)
        # Set by `configure_ood_response` from the checkpoint's ood_calibration.json (`runtime/response.py`).
        self.ood_response: EnergyOODResponse | None = None
        # An OrderedDict, as torch keeps module hooks: `RemovableHandle` holds a weak reference to it.
        self._chunk_hooks: OrderedDict[int, ChunkHook] = OrderedDict()
        self.reset()

    @classmethod
    def from_pretrained(
        cls,
        pretrained_name_or_path: str | Path,
        *,
        config: PreTrainedConfig | None = None,
        strict: bool = True,
        **kwargs,
    ) -> "EBVLAPolicy":
        """Loads a saved policy; every weight comes from the checkpoint, so no backbone is downloaded.

        The OOD response (`config.monitor.response`) takes its threshold from the checkpoint's
        `ood_calibration.json`, if there is one.
        """
        if config is None:
            config = load_saved_config(pretrained_name_or_path, **kwargs)
        config.vlm.load_pretrained_backbone = False
        try:
            policy = super().from_pretrained(pretrained_name_or_path, config=config, strict=strict, **kwargs)
        except SafetensorError as e:
            raise ValueError(
                f"The weights {SAFETENSORS_SINGLE_FILE} of {pretrained_name_or_path} cannot be read ({e}): the "
                "file is damaged or was only partly written or downloaded. Save or download it again."
            ) from e
        policy.configure_ood_response(pretrained_name_or_path)
        return policy

    def configure_ood_response(self, pretrained_name_or_path: str | Path, **overrides) -> None:
        """(Re)builds the OOD response from a checkpoint's calibration, after setting config fields.

        The config is the one source of truth: the `monitor` fields given here (`response`, `hold_action`,
        `threshold_k`) replace the config's (validated as at construction), then the response is rebuilt to match.

        Args:
            pretrained_name_or_path: The checkpoint whose `ood_calibration.json` (and, to hold, whose
                pre-processor's normalizer) the response uses.
            overrides: Any of `MonitorConfig`'s `response`, `hold_action`, `threshold_k`.
        """
        allowed = {"response", "hold_action", "threshold_k"}
        if unknown := set(overrides) - allowed:
            raise ValueError(f"Only `monitor.` {sorted(allowed)} can be changed here; got {sorted(unknown)}.")
        if overrides:
            monitor = dataclasses.replace(self.config.monitor, **overrides)  # runs its __post_init__'s checks
            config = dataclasses.replace(self.config, monitor=monitor)
            config.validate_features()
            self.config = self.model.config = config
        self.ood_response = EnergyOODResponse.from_pretrained(self.config, pretrained_name_or_path)

    def _save_pretrained(self, save_directory: Path, state_dict: dict[str, Tensor] | None = None) -> None:
        """Saves config and weights so that a save that fails midway leaves the previous files intact.

        Everything is written to a temporary folder beside `save_directory` first, then moved into place.
        Every fp32 tensor that bf16 holds exactly is stored in bf16: with `vlm.frozen_weights_dtype="bfloat16"`
        that is all the frozen backbone weights, which halves a full-size checkpoint and loses nothing
        (loading casts them back to the parameters' dtype).
        """
        state_dict = dict(self.state_dict() if state_dict is None else state_dict)
        for name, tensor in state_dict.items():
            if tensor.dtype == torch.float32 and torch.equal(tensor.to(torch.bfloat16).float(), tensor):
                state_dict[name] = tensor.to(torch.bfloat16)
        with tempfile.TemporaryDirectory(dir=save_directory.parent, prefix=f".{save_directory.name}-") as tmp:
            super()._save_pretrained(Path(tmp), state_dict=state_dict)
            for file in Path(tmp).iterdir():
                os.replace(file, save_directory / file.name)

    def get_optim_params(self) -> list[nn.Parameter]:
        return [p for p in self.parameters() if p.requires_grad]

    def supports_rtc(self) -> bool:
        """Real-time chunking is native to an energy head: `predict_action_chunk` inpaints the leftover.

        True for every configuration, as LeRobot asks before it sets `config.rtc_config` from
        `--inference.rtc.*`; RTC acts when `config.rtc_config` is set and enabled.
        """
        return True

    def reset(self) -> None:
        """Clears the action queue and the episode's chunk count; call it on `env.reset()`."""
        self._action_queue: deque[Tensor] = deque(maxlen=self.config.n_action_steps)
        self.last_energy: EnergyReadout | None = None
        self.last_ood_decision: OODDecision | None = None
        # Index of the next chunk in the episode: a phase-aware OOD calibration compares each chunk's energy
        # with the vanilla energies at the same index.
        self.chunk_index = 0

    def predict_action_chunk(
        self,
        batch: dict[str, Tensor],
        generator: torch.Generator | None = None,
        return_energy: bool = False,
        inference_delay: int | None = None,
        prev_chunk_left_over: Tensor | None = None,
        execution_horizon: int | None = None,
    ) -> Tensor | tuple[Tensor, EnergyReadout]:
        """Refines a chunk of (normalized) actions, (B, chunk_size, action_dim), for each observation.

        The chunk's energies are kept in `self.last_energy` and the OOD response to them (`runtime/response.py`:
        continue, hold or raise `EnergyOODError`) in `self.last_ood_decision`; held chunks are returned
        replaced by the hold action. Each call counts as the episode's next chunk: the readout's `chunk_index`.
        When the calibration's score reads the pooled context, the readout holds it (`context_features`), taken
        from the backbone pass that encodes the chunk's context: the backbone still runs once per chunk.

        Args:
            batch: A pre-processed observation batch.
            generator: Seeds a^(0) and the Langevin noise; on the policy's device.
            return_energy: Also return the chunk's initial and final energies.
            inference_delay: Real-time chunking (with `config.rtc_config` enabled): the number d of control
                steps the robot executes from the previous chunk before this one arrives, at most chunk_size.
            prev_chunk_left_over: The previous chunk's unexecuted (normalized) actions, (B, n, action_dim) or
                (n, action_dim) as `lerobot-rollout --inference.type=rtc` passes them; the first d are held,
                the rest of the overlap guided (`mcmc.py`). The energies are those of the whole returned chunk.
            execution_horizon: Overrides `rtc_config.execution_horizon`, the end of the guided overlap.
        """
        validate_observation(batch, self.config)
        monitor_reads_features = (
            self.ood_response is not None and self.ood_response.needs_context_features
        ) or self.config.monitor.failure_score in CONTEXT_FEATURE_SCORES
        needs_features = monitor_reads_features or self.model.needs_context_features
        # lerobot-eval runs under inference_mode, but refinement differentiates the energy w.r.t. a.
        with torch.inference_mode(False):
            prefix = rtc_prefix(
                self.config, batch_size_of(batch), inference_delay, prev_chunk_left_over, execution_horizon
            )
            refine_batch = without_inference_tensors(batch)
            generated = self.model.generate_actions(
                refine_batch, generator=generator, prefix=prefix, return_context_features=needs_features
            )
        actions, readout, features = generated if needs_features else (*generated, None)
        readout = dataclasses.replace(
            readout,
            chunk_index=self.chunk_index,
            context_features=features if monitor_reads_features else None,
            phase_energy=self.model.phase_energy_of(features, self.chunk_index),
        )
        self.last_energy = readout
        self.chunk_index += 1
        actions, self.last_ood_decision = respond_to_energy(
            self.ood_response, self.config, actions, readout, batch
        )
        for hook in list(self._chunk_hooks.values()):
            hook(self, batch, readout, self.last_ood_decision)
        return (actions, readout) if return_energy else actions

    def register_chunk_hook(self, hook: ChunkHook) -> RemovableHandle:
        """Calls `hook(policy, batch, readout, decision)` after every chunk the policy refines and returns.

        This is how rollout tools (the energy recorder, a logger) see each chunk's energies with the
        observation batch that produced them, whichever loop calls `select_action`. A chunk that raises
        `EnergyOODError` is not returned and reaches no hook. Remove the hook with `handle.remove()`.
        """
        handle = RemovableHandle(self._chunk_hooks)
        self._chunk_hooks[handle.id] = hook
        return handle

    @torch.no_grad()
    def select_action(self, batch: dict[str, Tensor], generator: torch.Generator | None = None) -> Tensor:
        """Returns the next action (B, action_dim), refining a new chunk every `n_action_steps` calls.

        After each refinement `self.last_energy` holds a new `EnergyReadout` for the refined chunk and
        `self.last_ood_decision` the OOD response to it.
        """
        if len(self._action_queue) == 0:
            actions = self.predict_action_chunk(batch, generator=generator)  # sets last_energy
            self._action_queue.extend(actions[:, : self.config.n_action_steps].transpose(0, 1))
        return self._action_queue.popleft()

    def score_action_chunks(self, batch: dict[str, Tensor], candidates: Tensor) -> Tensor:
        """Energies E(a, C) of candidate chunks (B, N, chunk_size, action_dim) in normalized action space.

        The context of each observation is encoded once for its N candidates. Returns (B, N).
        """
        validate_observation(batch, self.config)
        expected = (self.config.chunk_size, self.config.action_dim)
        if candidates.ndim != 4 or tuple(candidates.shape[2:]) != expected:
            raise ValueError(
                f"`candidates` must be (B, N, {expected[0]}, {expected[1]}). Got {tuple(candidates.shape)}."
            )
        with torch.inference_mode(False), torch.no_grad():
            batch = without_inference_tensors(batch)
            b, n = candidates.shape[:2]
            kv = self.model.encode_context(batch)  # the head scores the n candidates of a context together
            energies = self.model.head(candidates.clone().flatten(0, 1), kv).mean(dim=-1)
        return energies.view(b, n)

    def restart_spread(self, batch: dict[str, Tensor], n_chains: int, generator: torch.Generator) -> Tensor:
        """(B,) spread of `n_chains` chunks refined from independent a^(0) for each observation.

        The std over chains of the normalized actions, averaged over the chunk's H x d_a entries: an
        ensemble-disagreement baseline for the final energy. It costs `n_chains` refinements per observation.
        """
        if n_chains < 2:
            raise ValueError(f"`n_chains` must be >= 2 for a spread, got {n_chains}.")
        validate_observation(batch, self.config)
        with torch.inference_mode(False):
            batch = repeat_observations(batch, n_chains)
            actions, _ = self.model.generate_actions(batch, generator=generator)
        actions = actions.float().unflatten(0, (-1, n_chains))  # (B, N, H, d_a)
        return actions.std(dim=1, unbiased=False).mean(dim=(1, 2))

    def log_partition(self, batch: dict[str, Tensor], n_samples: int, generator: torch.Generator) -> Tensor:
        """(B,) Monte-Carlo log Z(C) = log mean_j exp(-E(a_j, C)), a_j ~ N(0, sigma_init^2 I) the MCMC prior.

        The energy is defined up to a per-context offset; E(a, C) + log Z(C) (`normalized_energy`) removes it.
        """
        if n_samples < 1:
            raise ValueError(f"`n_samples` must be >= 1, got {n_samples}.")
        cfg = self.config
        batch_size = batch_size_of(batch)
        shape = (batch_size, n_samples, cfg.chunk_size, cfg.action_dim)
        device = next(self.parameters()).device
        samples = cfg.init_action_std * torch.randn(shape, device=device, generator=generator)
        energies = self.score_action_chunks(batch, samples).float()  # (B, N)
        return torch.logsumexp(-energies, dim=1) - math.log(n_samples)

    def normalized_energy(
        self, batch: dict[str, Tensor], final_energy: Tensor, n_samples: int, generator: torch.Generator
    ) -> Tensor:
        """(B,) E(a^(K_inf), C) + log Z(C): the final energy relative to the prior's energies under the same
        context (`log_partition`), so that contexts whose whole landscape sits higher do not look OOD."""
        return final_energy.float() + self.log_partition(batch, n_samples, generator).to(final_energy.device)

    def context_features(self, batch: dict[str, Tensor]) -> Tensor:
        """(B, D) the last block's backbone context C_L, averaged over its tokens (`pooled_context`): the
        observation's embedding for the feature baselines (Mahalanobis, k-NN) and the context distance."""
        validate_observation(batch, self.config)
        with torch.inference_mode(False), torch.no_grad():
            contexts = self.model.backbone(without_inference_tensors(batch))
        return pooled_context(contexts)

    def forward(self, batch: dict[str, Tensor]) -> tuple[Tensor, dict]:
        """Training loss (Eq. 4) and logged metrics for a pre-processed batch with actions."""
        validate_observation(batch, self.config)
        validate_actions(batch, self.config)
        return compute_loss(self.model, batch)


class EBVLA(nn.Module):
    """The EB-VLA network: context encoding, energy, and the MCMC loops of inference and training.

    observation ──► backbone ──► C_1 .. C_L ──► per-block keys/values (once per observation)
                                                       │
    a^(0) ~ N(0, sigma_init^2) ──► e_t = E_theta(a + eps, C_i) ◄──┘
           ▲                              │ g = clip(grad_a E, c)                      (Eq. 2)
           └── a - alpha exp(e_t / tau) g, clamped to a_max ◄──┘  x K                   (Eq. 3)
    """

    def __init__(self, config: EBVLAConfig):
        super().__init__()
        self.config = config
        self.backbone = make_backbone(config)
        self.head = EBVLAEnergyHead(config, self.backbone.context_dim)
        # Training draws K, alpha, a^(0) and eps from a generator seeded by these two buffers (saved with the
        # weights, so a resumed run draws what an uninterrupted one would): `training_signal.training_generator`.
        self.register_buffer("mcmc_seed", torch.randint(0, 2**62, ()))
        self.register_buffer("train_steps", torch.zeros((), dtype=torch.long))
        # Built last, so that the backbone's and head's initial weights do not depend on it.
        self.context_energy = None
        self.observation_encoder = None
        if config.joint_energy.has_context_energy:
            self.context_energy = EBVLAContextEnergy(self.backbone.context_dim)
        if config.context_energy_on_own_encoder:
            self.observation_encoder = make_backbone(observation_encoder_config(config))
        # Fitted after training (`ebvla-fit-phase-energy`); until then it gives no energy. Built under its own
        # random state, so that a checkpoint with one draws the same a^(0) and Langevin noise as its source: a seeded
        # rollout of it is the source's, chunk for chunk.
        self.phase_energy = None
        if config.phase_energy.bins:
            with torch.random.fork_rng(devices=[]):
                self.phase_energy = PhaseEnergy(
                    self.backbone.context_dim, config.phase_energy.bins, config.phase_energy.hidden
                )

    def encode_context(
        self, batch: dict[str, Tensor], return_features: bool = False
    ) -> ContextKV | tuple[ContextKV, Tensor]:
        """Backbone contexts C_i projected to each head block's cross-attention keys and values; with
        `return_features`, also the pooled last-block context (`pooled_context`) of the same backbone pass."""
        contexts = self.backbone(batch)
        kv = self.head.context_kv(contexts)
        return (kv, pooled_context(contexts)) if return_features else kv

    def refine(
        self,
        kv: ContextKV,
        initial_actions: Tensor,
        step_sizes: list[float],
        generator: torch.Generator | None,
        create_graph: bool = False,
        early_stop_tol: float | None = None,
        energy_fn: EnergyFn | None = None,
        straight_through_clip: bool = False,
        prefix: RTCPrefix | None = None,
        noise: Tensor | None = None,
    ) -> RefinementResult:
        cfg = self.config
        return refine_actions(
            energy_fn or (lambda a: self.head(a, kv)),
            initial_actions,
            step_sizes,
            temperature=cfg.energy_temperature,
            langevin_std=cfg.langevin_noise_std,
            grad_clip=cfg.grad_clip,
            action_clamp=cfg.action_clamp,
            generator=generator,
            create_graph=create_graph,
            early_stop_tol=early_stop_tol,
            straight_through_clip=straight_through_clip,
            prefix=prefix,
            noise=noise,
        )

    def initial_actions(
        self, batch_size: int, reference: Tensor, generator: torch.Generator | None
    ) -> Tensor:
        """a^(0) on `reference`'s device, always fp32: the whole refinement (a, eps, updates) stays fp32 in a
        bf16 policy, where steps of alpha g and noise of sigma_L = 0.001 would round away near |a| = 1."""
        return sample_initial_actions(
            (batch_size, self.config.chunk_size, self.config.action_dim),
            self.config.init_action_std,
            device=reference.device,
            dtype=torch.float32,
            generator=generator,
        )

    def context_energy_of(self, batch: dict[str, Tensor], features: Tensor | None) -> Tensor | None:
        """(B,) E_c of the joint energy E(a, C) + E_c(C) (None without one): of `features`, the pooled context of
        the policy's own backbone pass, or of the observation encoder's (`joint_energy.target="observation"`)."""
        if self.context_energy is None:
            return None
        if self.observation_encoder is not None:
            features = pooled_context(self.observation_encoder(batch))
        return self.context_energy(features)

    def phase_energy_of(self, features: Tensor | None, chunk_index: int) -> Tensor | None:
        """(B,) E_tau(C, t) of the pooled contexts `features` at chunk index t (`phase_energy.py`); None without a
        fitted phase energy."""
        return self.phase_energy(features, chunk_index) if self.needs_context_features else None

    @property
    def needs_context_features(self) -> bool:
        """Whether every chunk's pooled context is read beside its refinement (a fitted phase energy reads it)."""
        return self.phase_energy is not None and self.phase_energy.fitted

    def _inference_context(
        self, batch: dict[str, Tensor], return_features: bool = False
    ) -> ContextKV | tuple[ContextKV, Tensor]:
        """`encode_context` for the inference chain: eager, or compiled in `compile_mode` (`compile_ebvla.py`)."""
        if self.config.compile_mode == "off":
            return self.encode_context(batch, return_features)
        return compiled_context(self, batch, return_features)

    @property
    def _records_whole_chain(self) -> bool:
        """Whether a chunk's refinement replays as one CUDA graph ("chunk-graph"): not with `early_stop_tol`, whose
        stop is decided on the host."""
        return self.config.compile_mode == CHUNK_GRAPH_MODE and self.config.early_stop_tol is None

    def _inference_energy_fn(self, kv: ContextKV) -> EnergyFn:
        """The energy of the inference MCMC steps: the head itself (eager, or recorded with the whole chain), or
        its compiled graph (`compile_mode`)."""
        if self.config.compile_mode == "off" or self._records_whole_chain:
            return lambda a: self.head(a, kv)
        return compiled_energy_fn(self.head, kv, self.config.compile_mode)

    def _inference_chain(
        self,
        kv: ContextKV,
        initial: Tensor,
        generator: torch.Generator | None,
        prefix: RTCPrefix | None,
    ) -> tuple[RefinementResult, Tensor]:
        """K_inf steps of constant size alpha from a^(0) = `initial`, and the final energies E(a^(K), C), (B,).

        In `compile_mode="chunk-graph"` (without `early_stop_tol`, whose stop is decided on the host) the noise
        of every step is drawn first, as the steps would draw it, and the chain replays as one CUDA graph."""
        cfg = self.config
        step_sizes = [cfg.inference_step_size] * cfg.inference_mcmc_steps

        def chain(kv, initial, noise, prefix) -> tuple[RefinementResult, Tensor]:
            result = self.refine(
                kv,
                initial,
                step_sizes,
                generator,
                early_stop_tol=cfg.early_stop_tol,
                energy_fn=self._inference_energy_fn(kv),
                prefix=prefix,
                noise=noise,
            )
            with torch.no_grad():
                return result, self.head(result.actions, kv).mean(dim=-1)

        if not self._records_whole_chain:
            return chain(kv, initial, None, prefix)
        noise = draw_langevin_noise(len(step_sizes), initial, generator)
        # Buffers too: `_apply` remakes the rotary frequencies even where it leaves the parameters in place.
        weights = [*self.head.parameters(), *self.head.buffers()]
        return refinement_graphs(self.head)(chain, weights, kv, initial, noise, prefix)

    def generate_actions(
        self,
        batch: dict[str, Tensor],
        generator: torch.Generator | None = None,
        prefix: RTCPrefix | None = None,
        return_context_features: bool = False,
    ) -> tuple[Tensor, EnergyReadout] | tuple[Tensor, EnergyReadout, Tensor]:
        """Inference: K_inf steps of constant size alpha from noise; with restarts, the lowest-energy chain.

        With an RTC `prefix` every chain inpaints it; the final energy is that of the whole chunk. With
        `return_context_features`, also the (B, D) pooled last-block context of each observation, from the
        backbone pass that encoded the context.
        """
        cfg = self.config
        with_features = return_context_features or (
            self.context_energy is not None and self.observation_encoder is None
        )
        with torch.no_grad():
            encoded = self._inference_context(batch, with_features)
            kv, features = encoded if with_features else (encoded, None)
            context_energy = self.context_energy_of(batch, features)
        adaptive = cfg.restart_energy_threshold is not None
        actions, readout = self._best_of_chains(
            kv, context_energy, 1 if adaptive else cfg.num_restarts, generator, prefix
        )
        if adaptive and cfg.num_restarts > 1:
            actions, readout = self._restart_unsure_chunks(
                kv, context_energy, actions, readout, generator, prefix
            )
        if return_context_features:
            return actions.detach(), readout, features
        return actions.detach(), readout

    def _best_of_chains(
        self,
        kv: ContextKV,
        context_energy: Tensor | None,
        chains: int,
        generator: torch.Generator | None,
        prefix: RTCPrefix | None,
    ) -> tuple[Tensor, EnergyReadout]:
        """Refines `chains` chunks per observation from independent a^(0) and keeps the lowest final energy.

        `context_energy`: E_c(C) of each observation, added to its chunks' final energies (the joint energy)."""
        batch_size = kv[0][0].shape[0]
        initial = self.initial_actions(batch_size * chains, kv[0][0], generator)
        if prefix is not None:
            actions = prefix.actions.to(initial.device).repeat_interleave(chains, dim=0)
            prefix = dataclasses.replace(prefix, actions=actions)
        result, final_energy = self._inference_chain(kv, initial, generator, prefix)
        if context_energy is not None:  # the joint energy E(a, C) + E_c(C)
            final_energy = final_energy + context_energy.repeat_interleave(chains)
        final_energy = torch.where(result.diverged, math.inf, final_energy)
        if result.diverged.any():
            logger.warning(
                "EB-VLA refinement met a non-finite energy or gradient for %d of %d chunks: they keep their "
                "last finite iterate and report final_energy=+inf.",
                int(result.diverged.sum()),
                result.diverged.numel(),
            )
        actions, initial_energy = result.actions, result.step_energies[0]
        if chains > 1:
            best = final_energy.view(batch_size, chains).argmin(dim=1)
            rows = torch.arange(batch_size, device=best.device) * chains + best
            actions, initial_energy, final_energy = actions[rows], initial_energy[rows], final_energy[rows]
        counts = torch.full((batch_size,), chains, dtype=torch.long, device=final_energy.device)
        return actions, EnergyReadout(
            initial_energy, final_energy, chains=counts, context_energy=context_energy
        )

    def _restart_unsure_chunks(
        self,
        kv: ContextKV,
        context_energy: Tensor | None,
        actions: Tensor,
        readout: EnergyReadout,
        generator: torch.Generator | None,
        prefix: RTCPrefix | None,
    ) -> tuple[Tensor, EnergyReadout]:
        """Adaptive best-of-N: observations whose first chunk's final energy is above the threshold get
        num_restarts - 1 more chains, and keep the lowest-energy chunk of all num_restarts."""
        cfg = self.config
        unsure = (readout.final_energy > cfg.restart_energy_threshold).nonzero().squeeze(1)
        if unsure.numel() == 0:
            return actions, readout
        if prefix is not None:
            weights = prefix.weights
            if weights is not None and weights.dim() == 2:
                weights = weights[unsure]
            prefix = dataclasses.replace(prefix, actions=prefix.actions[unsure], weights=weights)
        more_actions, more = self._best_of_chains(
            [(k[unsure], v[unsure]) for k, v in kv],
            None if context_energy is None else context_energy[unsure],
            cfg.num_restarts - 1,
            generator,
            prefix,
        )
        better = more.final_energy < readout.final_energy[unsure]
        rows = unsure[better]
        actions, initial, final = (
            actions.clone(),
            readout.initial_energy.clone(),
            readout.final_energy.clone(),
        )
        actions[rows] = more_actions[better]
        initial[rows], final[rows] = more.initial_energy[better], more.final_energy[better]
        chains = readout.chains.clone()
        chains[unsure] = cfg.num_restarts
        return actions, EnergyReadout(initial, final, chains=chains, context_energy=readout.context_energy)


def observation_encoder_config(config: EBVLAConfig) -> EBVLAConfig:
    """The config E_c's own encoder is built from: the policy's, at `joint_energy.encoder_resize_shape` where
    set (the whole frame resized, never cropped: E_c compares scenes, it is not trained for invariance)."""
    size = config.joint_energy.encoder_resize_shape
    if size is None:
        return config
    resnet = dataclasses.replace(config.resnet, resize_shape=tuple(size), crop_shape=None)
    return dataclasses.replace(config, resnet=resnet)


def make_backbone(config: EBVLAConfig) -> nn.Module:
    """The backbone named by `config.backbone`: its `forward(batch)` returns the context C_i of each block."""
    if config.backbone == "resnet":
        return EBVLAResNetBackbone(config)
    from .backbone_vlm import EBVLAVisionLanguageBackbone  # transformers/timm/peft are only needed here

    return EBVLAVisionLanguageBackbone(config)
