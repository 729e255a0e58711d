"""`compile_mode`: the inference chain of every chunk under torch.compile.

Two parts of a chunk's inference are compiled, each built once per process and mode:

- the context encoding (`EBVLA.encode_context`: the backbone forward and the head's per-block keys and values),
  `compiled_context`;
- the energy's forward and grad_a backward at each MCMC step, `compiled_energy_fn`, with the head's parameters
  detached so that no weight gradient is computed.

The sampling loop around them (`mcmc.refine_actions`: noise, clip, step, clamp, RTC guidance) and the
final-energy forward stay eager; training is never compiled. Shapes are static: each batch size (times
`num_restarts` for the energy) compiles on its first chunk. The graph modes ("reduce-overhead",
"max-autotune") replay CUDA graphs on a CUDA device and run their no-graph form elsewhere
(`effective_compile_mode`). A replay reuses its output buffers, so everything the compiled code returns is copied
out. Compile times and gains: docs/benchmarks_speed.md and docs/vlm_backbone.md.
"""

import functools
import logging
from collections.abc import Callable
from typing import TYPE_CHECKING

import torch
from torch import Tensor
from torch.func import functional_call

from .energy_head import ContextKV, EBVLAEnergyHead
from .mcmc import EnergyFn

if TYPE_CHECKING:
    from .modeling_ebvla import EBVLA

logger = logging.getLogger(__name__)

# torch.compile's modes that replay the compiled code in CUDA graphs, and what runs in their place without CUDA.
CUDA_GRAPH_MODES = {"reduce-overhead": "default", "max-autotune": "max-autotune-no-cudagraphs"}


def head_energy(head: EBVLAEnergyHead, params: dict[str, Tensor], actions: Tensor, kv: ContextKV) -> Tensor:
    """Per-timestep energies of `actions` under `kv`, with `params` in place of the head's own."""
    return functional_call(head, params, (actions, kv))


def encode_context(model: "EBVLA", batch: dict[str, Tensor], return_features: bool = False):
    """`model.encode_context(batch, return_features)`, as a function torch.compile can take."""
    return model.encode_context(batch, return_features)


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
    model: "EBVLA", batch: dict[str, Tensor], return_features: bool = False
) -> ContextKV | tuple[ContextKV, Tensor]:
    """`model.encode_context` compiled in `model.config.compile_mode`, its outputs copied out."""
    mode = effective_compile_mode(model.config.compile_mode, model.head.energy_out.weight.device.type)
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
    mode = effective_compile_mode(compile_mode, kv[0][0].device.type)
    if mode in CUDA_GRAPH_MODES:
        for tensor in params.values():
            # The parameters never move, so CUDA graphs read them in place instead of copying every weight
            # into the graph's input buffers at each replay.
            torch._dynamo.mark_static_address(tensor)
    energy = compiled_head_energy(mode)
    # A CUDA-graph replay overwrites the buffers of the previous one: the step energies kept in
    # `RefinementResult` (and `last_energy`) must be copies.
    return lambda a: energy(head, params, a, kv).clone()
