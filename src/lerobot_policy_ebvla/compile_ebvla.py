"""`compile_mode`: the inference chain of every chunk under torch.compile, or in one CUDA graph.

Two parts of a chunk's inference are compiled, each built once per process and mode:

- the context encoding (`EBVLA.encode_context`: the backbone forward and the head's per-block keys and values),
  `compiled_context`;
- the energy's forward and grad_a backward at each MCMC step, `compiled_energy_fn`, with the head's parameters
  detached so that no weight gradient is computed.

The sampling loop around them (`mcmc.refine_actions`: noise, clip, step, clamp, RTC guidance) and the
final-energy forward stay eager. Shapes are static: each batch size (times
`num_restarts` for the energy) compiles on its first chunk. The graph modes ("reduce-overhead",
"max-autotune") replay CUDA graphs on a CUDA device and run their no-graph form elsewhere
(`effective_compile_mode`). A replay reuses its output buffers, so everything the compiled code returns is copied
out. Compile times and gains: research/docs/benchmarks_speed.md and research/docs/vlm_gpu.md.

"chunk-graph" goes further where the per-step graphs leave the GPU idle: after each of the K_inf graph replays the
eager sampling loop and the autograd call cost more host time than the step's GPU work. It encodes the context as
"reduce-overhead" does and captures the whole refinement of a chunk, the K_inf steps of the eager head with their
Langevin noise drawn beforehand and the final energy, in one CUDA graph per input shape (`RefinementGraphs`),
replayed once per chunk. Capturing takes a few eager chains, not a compilation. Without CUDA the same chain runs
eagerly from the same pre-drawn noise, and the context is compiled as "default".

`train_compile_mode` compiles the same two parts in a training step (`training_signal.compute_loss`): the backbone
pass, forward and backward, and the energy of the K - 1 warm-up MCMC steps, whose context is detached. The last
step, which is differentiated through grad_a E (second order), stays eager: AOTAutograd has no double backward.
"""

import dataclasses
import functools
import logging
import weakref
from collections import OrderedDict
from collections.abc import Callable

import torch
from torch import Tensor, nn
from torch.func import functional_call

from .energy_head import ContextKV, EBVLAEnergyHead
from .mcmc import EnergyFn, RefinementResult, RTCPrefix

logger = logging.getLogger(__name__)

# The mode that captures a chunk's whole refinement in one CUDA graph (`RefinementGraphs`); its context encoding
# is compiled as "reduce-overhead".
CHUNK_GRAPH_MODE = "chunk-graph"
# The modes that replay CUDA graphs, and what runs in their place without CUDA.
CUDA_GRAPH_MODES = {
    "reduce-overhead": "default",
    "max-autotune": "max-autotune-no-cudagraphs",
    CHUNK_GRAPH_MODE: "default",
}


def head_energy(head: EBVLAEnergyHead, params: dict[str, Tensor], actions: Tensor, kv: ContextKV) -> Tensor:
    """Per-timestep energies of `actions` under `kv`, with `params` in place of the head's own."""
    return functional_call(head, params, (actions, kv))


def encode_context(model: nn.Module, batch: dict[str, Tensor], return_features: bool = False):
    """`model.encode_context(batch, return_features)`, as a function torch.compile can take.

    Each block's keys and values are two views of one projection; returned as such, AOTAutograd rebuilds them
    from their base after the compiled forward, and torch 2.11 on the CPU rebuilt them with garbage sizes in a
    training step (`RuntimeError: shape '[93954964401046, ...]' is invalid`). Copies inside the graph leave no
    output aliasing another."""
    encoded = model.encode_context(batch, return_features)
    kv, features = encoded if return_features else (encoded, None)
    kv = [
        (k.clone(memory_format=torch.contiguous_format), v.clone(memory_format=torch.contiguous_format))
        for k, v in kv
    ]
    return (kv, features) if return_features else kv


@functools.cache
def effective_compile_mode(mode: str, device_type: str) -> str:
    """`compile_mode` as it runs on `device_type`: CUDA graphs need CUDA; elsewhere a graph mode runs its
    no-graph form (inductor alone), with a warning once per process."""
    if mode not in CUDA_GRAPH_MODES or device_type == "cuda":
        return mode
    logger.warning(
        "`compile_mode=%r` replays CUDA graphs, which a %s device has not: it runs as %r (inductor without "
        "graphs).",
        mode,
        device_type,
        CUDA_GRAPH_MODES[mode],
    )
    return CUDA_GRAPH_MODES[mode]


def compiled_part_mode(mode: str, device_type: str) -> str:
    """The torch.compile mode of the compiled parts (the context encoder, the per-step energy) under
    `compile_mode=mode` on `device_type`: "chunk-graph" compiles its parts as "reduce-overhead"."""
    mode = effective_compile_mode(mode, device_type)
    return "reduce-overhead" if mode == CHUNK_GRAPH_MODE else mode


def compile_static(fn: Callable, mode: str) -> Callable:
    """`fn` under torch.compile in `mode` ("default": inductor's default), one graph per input shape."""
    from torch._inductor import list_mode_options

    if mode != "default" and mode not in list_mode_options():
        raise ValueError(
            f"`compile_mode={mode!r}` is not a mode of torch {torch.__version__}'s torch.compile, which knows "
            f"{sorted(list_mode_options())}: choose one of them or 'off'."
        )
    return torch.compile(fn, dynamic=False, mode=None if mode == "default" else mode)


@functools.cache
def compiled_head_energy(mode: str = "default"):
    """`head_energy` compiled in `mode`, built once per process and mode (`compile_mode`)."""
    return compile_static(head_energy, mode)


@functools.cache
def compiled_context_encoder(mode: str = "default"):
    """`encode_context(model, batch, return_features)` compiled in `mode`, built once per process and mode
    (`compile_mode`): the backbone forward and the head's per-block keys and values, one graph per batch size."""
    return compile_static(encode_context, mode)


def compiled_context(
    model: nn.Module, batch: dict[str, Tensor], return_features: bool = False, compile_mode: str | None = None
) -> ContextKV | tuple[ContextKV, Tensor]:
    """`model.encode_context` compiled in `compile_mode` (default: `model.config.compile_mode`), its outputs copied
    out. In training the copies carry the gradient into the compiled backward."""
    compile_mode = model.config.compile_mode if compile_mode is None else compile_mode
    mode = compiled_part_mode(compile_mode, model.head.energy_out.weight.device.type)
    encoded = compiled_context_encoder(mode)(model, batch, return_features)
    kv, features = encoded if return_features else (encoded, None)
    # A CUDA-graph replay reuses its output buffers: the next chunk would overwrite this chunk's outputs.
    kv = [(k.clone(), v.clone()) for k, v in kv]
    return (kv, features.clone()) if return_features else kv


def compiled_energy_fn(head: EBVLAEnergyHead, kv: ContextKV, compile_mode: str) -> EnergyFn:
    """The energy of the inference MCMC steps under `kv`, compiled in `compile_mode`, its outputs copied out."""
    # Detached parameters: the compiled backward then computes grad_a only. With parameters that require
    # grad, AOTAutograd's backward would also compute every weight gradient (the eager engine skips them).
    params = {name: p.detach() for name, p in head.named_parameters()}
    params.update(head.named_buffers())
    # Under "chunk-graph" this runs only for a chain that cannot be captured whole (`early_stop_tol`).
    mode = compiled_part_mode(compile_mode, kv[0][0].device.type)
    if mode in CUDA_GRAPH_MODES:
        for tensor in params.values():
            # The parameters never move, so CUDA graphs read them in place instead of copying every weight
            # into the graph's input buffers at each replay.
            torch._dynamo.mark_static_address(tensor)
    energy = compiled_head_energy(mode)
    # A CUDA-graph replay overwrites the buffers of the previous one: the step energies kept in
    # `RefinementResult` (and `last_energy`) must be copies.
    return lambda a: energy(head, params, a, kv).clone()


def begin_compiled_training_step(model: nn.Module) -> None:
    """Starts a training step in `model.config.train_compile_mode`: tells CUDA graphs that the last step's graph
    outputs are no longer read (this step's replays may reuse their memory), and refuses a bf16 policy on the CPU."""
    weight = model.head.energy_out.weight
    if weight.device.type == "cpu" and weight.dtype == torch.bfloat16:
        # Seen on torch 2.11 (2026-11-27): inductor's C++ kernels for the tiny VLM's bf16 training step crashed
        # the process (a segmentation fault), which would lose a user's run with no message.
        raise ValueError(
            f"`train_compile_mode={model.config.train_compile_mode!r}` is not supported for a bf16 policy on the "
            "CPU (inductor crashed compiling its training step): train in float32, on CUDA, or with "
            "`train_compile_mode='off'`."
        )
    if compiled_part_mode(model.config.train_compile_mode, weight.device.type) in CUDA_GRAPH_MODES:
        torch.compiler.cudagraph_mark_step_begin()


# A refinement chain to capture: (kv, a^(0), noise, prefix) -> (its result, the final energies E(a^(K), C), (B,)).
RefinementChain = Callable[[ContextKV, Tensor, Tensor, RTCPrefix | None], tuple[RefinementResult, Tensor]]


class RefinementGraphs:
    """A chunk's whole refinement, the K_inf steps of Eq. 2-3 and the final energy, as one CUDA graph per input
    shape (`compile_mode="chunk-graph"`).

    A graph is captured from the call's `chain` on the first chunk of each shape (kv, a^(0), RTC prefix) and
    replayed on the next ones: each call copies its inputs into the graph's own buffers, replays it and copies the
    outputs out. The graph reads the head's parameters where they are, so updated weights are used as they are;
    weights moved to new memory (`policy.to(...)`) drop the graphs of the old memory. At most `max_graphs` shapes
    are kept, the least recently used dropped first (adaptive restarts refine a varying number of chunks).

    Off CUDA, `chain` runs eagerly on the call's own tensors: the same chain, unrecorded. So does a shape whose
    capture failed (the error is logged once and kept in `failures`): a robot keeps its eager policy. The chain is
    an argument of each call, not kept: nothing here refers back to the policy.
    """

    def __init__(self, max_graphs: int = 8, warmup_chains: int = 3):
        self.max_graphs, self.warmup_chains = max_graphs, warmup_chains
        self.graphs: OrderedDict[tuple, tuple] = OrderedDict()
        self.failures: dict[tuple, str] = {}
        self.weights_key: tuple | None = None

    def __call__(
        self,
        chain: RefinementChain,
        weights: list[Tensor],
        kv: ContextKV,
        initial_actions: Tensor,
        noise: Tensor,
        prefix: RTCPrefix | None,
    ) -> tuple[RefinementResult, Tensor]:
        """Refines `initial_actions` under `kv` with the Langevin draws `noise` (K, B, H, d_a); `weights` are
        the parameters and buffers the chain reads (their memory keys the graphs)."""
        if not self.records(initial_actions):
            return chain(kv, initial_actions, noise, prefix)
        weights_key = tuple(w.data_ptr() for w in weights)
        if weights_key != self.weights_key:
            self.graphs.clear()
            self.weights_key = weights_key
        inputs = _graph_inputs(kv, initial_actions, noise, prefix)
        # The prefix's numbers are recorded as constants; its tensors are among the inputs.
        key = (
            tuple((t.shape, t.dtype) for t in inputs),
            None if prefix is None else (prefix.held_steps, prefix.guidance_weight),
        )
        if key in self.failures:
            return chain(kv, initial_actions, noise, prefix)
        if key not in self.graphs:
            try:
                self.graphs[key] = self._capture(chain, kv, initial_actions, noise, prefix)
            except RuntimeError as error:
                self.failures[key] = f"{type(error).__name__}: {error}"
                logger.warning(
                    "`compile_mode='chunk-graph'` could not capture the refinement of chunks shaped %s in a CUDA "
                    "graph; they are refined eagerly. %s",
                    tuple(initial_actions.shape),
                    self.failures[key],
                )
                return chain(kv, initial_actions, noise, prefix)
            if len(self.graphs) > self.max_graphs:
                self.graphs.popitem(last=False)
        self.graphs.move_to_end(key)
        replay, static_inputs, (result, final_energy) = self.graphs[key]
        for static, tensor in zip(static_inputs, inputs, strict=True):
            static.copy_(tensor)
        replay()
        # The next replay overwrites these buffers.
        return RefinementResult(
            actions=result.actions.clone(),
            step_energies=result.step_energies.clone(),
            diverged=result.diverged.clone(),
        ), final_energy.clone()

    @staticmethod
    def records(initial_actions: Tensor) -> bool:
        """Whether chains of `initial_actions` are captured: on CUDA only."""
        return initial_actions.device.type == "cuda"

    def _capture(self, chain: RefinementChain, kv, initial_actions, noise, prefix) -> tuple:
        """`chain` recorded on input buffers of its own: (replay, those buffers, its output buffers)."""
        kv = [(k.clone(), v.clone()) for k, v in kv]
        initial_actions, noise = initial_actions.clone(), noise.clone()
        if prefix is not None:
            weights = None if prefix.weights is None else prefix.weights.clone()
            prefix = dataclasses.replace(prefix, actions=prefix.actions.clone(), weights=weights)
        replay, outputs = record_cuda_graph(
            lambda: chain(kv, initial_actions, noise, prefix), self.warmup_chains
        )
        return replay, _graph_inputs(kv, initial_actions, noise, prefix), outputs


def record_cuda_graph(fn: Callable[[], object], warmup_calls: int) -> tuple[Callable[[], None], object]:
    """Captures `fn()` in a CUDA graph: (its replay, the outputs the replays write into).

    `warmup_calls` eager calls on a side stream come first: they settle cuBLAS's workspaces and autograd's state,
    which must not be created while recording."""
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        for _ in range(warmup_calls):
            fn()
    torch.cuda.current_stream().wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        outputs = fn()
    return graph.replay, outputs


def _graph_inputs(
    kv: ContextKV, initial_actions: Tensor, noise: Tensor, prefix: RTCPrefix | None
) -> list[Tensor]:
    """Every tensor a refinement chain reads, in a fixed order: the graph's input buffers."""
    inputs = [t for pair in kv for t in pair] + [initial_actions, noise]
    if prefix is not None:
        inputs.append(prefix.actions)
        if prefix.weights is not None:
            inputs.append(prefix.weights)
    return inputs


# One `RefinementGraphs` per energy head, dropped with the head (no state on the policy, which stays copyable).
_REFINEMENT_GRAPHS: "weakref.WeakKeyDictionary[EBVLAEnergyHead, RefinementGraphs]" = (
    weakref.WeakKeyDictionary()
)


def refinement_graphs(head: EBVLAEnergyHead) -> RefinementGraphs:
    """The `RefinementGraphs` of `head`, made on first use."""
    if head not in _REFINEMENT_GRAPHS:
        _REFINEMENT_GRAPHS[head] = RefinementGraphs()
    return _REFINEMENT_GRAPHS[head]
