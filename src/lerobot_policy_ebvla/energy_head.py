"""The energy-based transformer (EBT) action head of EB-VLA (paper Sec. II-B).

The head scores a candidate action chunk a in R^{H x d_a} against the VLM context C with per-timestep
energies e_t; the chunk's energy is their mean E(a, C) = 1/H sum_t e_t. Action tokens attend to the context,
never the reverse, so the context's keys and values depend on the observation only: `context_kv` computes
them once, and every MCMC step reuses them.
"""

import math

import torch
import torch.nn.functional as F  # noqa: N812
from einops import rearrange
from torch import Tensor, nn

from .configuration_ebvla import EBVLAConfig

# One (key, value) pair per head block, each (B, n_heads, S_i, head_dim).
ContextKV = list[tuple[Tensor, Tensor]]


def pooled_context(contexts: list[Tensor]) -> Tensor:
    """(B, D) the last block's context C_L averaged over its tokens, in fp32: the observation's embedding that
    the context distance and the feature baselines compare (`EBVLAPolicy.context_features`)."""
    return contexts[-1].float().mean(dim=1)


class EBVLARotaryEmbedding(nn.Module):
    """Rotary position embedding over the H action timesteps (RoFormer); frequencies always in fp32."""

    def __init__(self, head_dim: int, base: float):
        super().__init__()
        self.head_dim, self.base = head_dim, base
        self.register_buffer("inv_freq", self._frequencies(None), persistent=False)

    def _frequencies(self, device: torch.device | None) -> Tensor:
        exponents = torch.arange(0, self.head_dim, 2, device=device, dtype=torch.float32) / self.head_dim
        return 1.0 / self.base**exponents

    def _apply(self, fn, recurse=True):
        # `policy.to(torch.bfloat16)` would round the frequencies, and with them every angle: recompute them in
        # fp32 on the new device instead.
        super()._apply(fn, recurse)
        self.inv_freq = self._frequencies(self.inv_freq.device)
        return self

    def forward(self, seq_len: int, device: torch.device, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
        positions = torch.arange(seq_len, device=device, dtype=torch.float32)
        angles = torch.outer(positions, self.inv_freq.to(device))  # (H, head_dim / 2)
        angles = torch.cat([angles, angles], dim=-1)  # (H, head_dim)
        return angles.cos().to(dtype), angles.sin().to(dtype)


def apply_rotary(x: Tensor, cos: Tensor, sin: Tensor) -> Tensor:
    """Rotates channel pairs (i, i + head_dim / 2) of x (B, nh, H, hd) by position-dependent angles."""
    x1, x2 = x.chunk(2, dim=-1)
    return x * cos + torch.cat([-x2, x1], dim=-1) * sin


class EBVLASelfAttention(nn.Module):
    """Bidirectional self-attention over the action tokens, with RoPE on queries and keys."""

    def __init__(self, dim: int, n_heads: int, dropout: float):
        super().__init__()
        self.n_heads = n_heads
        self.qkv = nn.Linear(dim, 3 * dim, bias=False)
        self.out = nn.Linear(dim, dim, bias=False)
        self.dropout = dropout

    def forward(self, x: Tensor, cos: Tensor, sin: Tensor) -> Tensor:
        q, k, v = rearrange(self.qkv(x), "b t (three nh hd) -> three b nh t hd", three=3, nh=self.n_heads)
        # Under bf16 autocast q and k come out in bf16: fp32 angles would promote them, and the attention with
        # them, back to fp32.
        cos, sin = cos.to(q.dtype), sin.to(q.dtype)
        q, k = apply_rotary(q, cos, sin), apply_rotary(k, cos, sin)
        y = F.scaled_dot_product_attention(q, k, v, dropout_p=self.dropout if self.training else 0.0)
        return self.out(rearrange(y, "b nh t hd -> b t (nh hd)"))


class EBVLACrossAttention(nn.Module):
    """Cross-attention of the action tokens into one block's context C_i (Eq. 1).

    The context side (norm and key/value projection) lives in `context_kv` so it can run once per
    observation; `forward` only projects the queries.
    """

    def __init__(self, dim: int, context_dim: int, n_heads: int, dropout: float):
        super().__init__()
        self.n_heads = n_heads
        self.context_norm = nn.RMSNorm(context_dim)
        self.q = nn.Linear(dim, dim, bias=False)
        self.kv = nn.Linear(context_dim, 2 * dim, bias=False)
        self.out = nn.Linear(dim, dim, bias=False)
        self.dropout = dropout

    def context_kv(self, context: Tensor) -> tuple[Tensor, Tensor]:
        k, v = rearrange(
            self.kv(self.context_norm(context)), "b s (two nh hd) -> two b nh s hd", two=2, nh=self.n_heads
        )
        return k, v

    def forward(self, x: Tensor, kv: tuple[Tensor, Tensor]) -> Tensor:
        """x (B * N, H, D): N consecutive candidate chunks per context of `kv` (batch B)."""
        k, v = kv
        candidates = x.shape[0] // k.shape[0]
        # Queries attend to the context independently of each other, so the N candidates of one context can
        # share one attention call as N * H queries: no copy of the keys and values per candidate (nor its
        # summed gradient), and larger matrix products.
        q = rearrange(self.q(x), "(b n) t (nh hd) -> b nh (n t) hd", n=candidates, nh=self.n_heads)
        y = F.scaled_dot_product_attention(q, k, v, dropout_p=self.dropout if self.training else 0.0)
        return self.out(rearrange(y, "b nh (n t) hd -> (b n) t (nh hd)", n=candidates))


class EBVLASwiGLU(nn.Module):
    """SwiGLU feed-forward network (Shazeer, 2020)."""

    def __init__(self, dim: int, hidden_dim: int, dropout: float):
        super().__init__()
        self.gate_up = nn.Linear(dim, 2 * hidden_dim, bias=False)
        self.down = nn.Linear(hidden_dim, dim, bias=False)
        self.dropout = nn.Dropout(dropout)

    def forward(self, x: Tensor) -> Tensor:
        gate, up = self.gate_up(x).chunk(2, dim=-1)
        return self.dropout(self.down(F.silu(gate) * up))


class EBVLABlock(nn.Module):
    """One EBT block: (i) self-attention with RoPE, (ii) cross-attention into C_i, (iii) SwiGLU; pre-norm."""

    def __init__(self, config: EBVLAConfig, context_dim: int):
        super().__init__()
        dim = config.dim_model
        self.self_attn_norm = nn.RMSNorm(dim)
        self.self_attn = EBVLASelfAttention(dim, config.n_heads, config.dropout)
        self.cross_attn_norm = nn.RMSNorm(dim)
        self.cross_attn = EBVLACrossAttention(dim, context_dim, config.n_heads, config.dropout)
        self.ffn_norm = nn.RMSNorm(dim)
        self.ffn = EBVLASwiGLU(dim, config.ffn_multiplier * dim, config.dropout)

    def forward(self, x: Tensor, kv: tuple[Tensor, Tensor], cos: Tensor, sin: Tensor) -> Tensor:
        x = x + self.self_attn(self.self_attn_norm(x), cos, sin)
        x = x + self.cross_attn(self.cross_attn_norm(x), kv)
        return x + self.ffn(self.ffn_norm(x))


class EBVLAEnergyHead(nn.Module):
    """The energy E_theta(a, C) of an action chunk under a per-block context.

        a (B, H, d_a) --Linear--> z (B, H, D) --[L x EBVLABlock(C_i)]--> RMSNorm --Linear--> e (B, H)

    `context_kv(C_1..C_L)` must be called once per observation; `forward(a, kv)` is then cheap enough to
    run at every MCMC step.
    """

    def __init__(self, config: EBVLAConfig, context_dim: int):
        super().__init__()
        self.config = config
        self.action_in = nn.Linear(config.action_dim, config.dim_model)
        self.rotary = EBVLARotaryEmbedding(config.dim_model // config.n_heads, config.rope_base)
        self.blocks = nn.ModuleList(EBVLABlock(config, context_dim) for _ in range(config.n_blocks))
        self.final_norm = nn.RMSNorm(config.dim_model)
        self.energy_out = nn.Linear(config.dim_model, 1)
        self.apply(self._init_weights)
        # Eq. 3 scales each step by exp(e_t / tau): the readout's bias sets how far the first chains can move.
        nn.init.constant_(self.energy_out.bias, config.energy_bias_init)

    @staticmethod
    def _init_weights(module: nn.Module) -> None:
        if isinstance(module, nn.Linear):
            nn.init.normal_(module.weight, std=1.0 / math.sqrt(module.in_features))
            if module.bias is not None:
                nn.init.zeros_(module.bias)

    def context_kv(self, contexts: list[Tensor]) -> ContextKV:
        """Projects each block's context C_i (B, S_i, context_dim) to its cross-attention keys and values."""
        if len(contexts) != len(self.blocks):
            raise ValueError(
                f"Expected one context per head block ({len(self.blocks)}), got {len(contexts)}."
            )
        return [block.cross_attn.context_kv(c) for block, c in zip(self.blocks, contexts, strict=True)]

    def forward(self, actions: Tensor, kv: ContextKV) -> Tensor:
        """Returns the per-timestep energies e_t (B * N, H) of action chunks (B * N, H, d_a) under `kv` of batch
        B: N >= 1 consecutive candidate chunks per context (the contrastive candidates, the restarts).

        Actions come in and energies go out in fp32 whatever the head's dtype: the MCMC iterate, its Langevin
        noise (sigma_L = 0.001 is below bf16's spacing near 1) and the energy readout stay fp32 in a bf16
        policy. The input projection runs in fp32 too (under autocast as well), so a + eps reaches z before
        any rounding.
        """
        contexts = kv[0][0].shape[0]
        if actions.shape[0] % contexts:
            raise ValueError(
                f"`actions` hold {actions.shape[0]} chunks for {contexts} contexts: expected a whole number of "
                f"candidate chunks per context (consecutive rows)."
            )
        weight, bias = self.action_in.weight, self.action_in.bias
        with torch.autocast(actions.device.type, enabled=False):
            z = F.linear(actions.float(), weight.float(), bias.float()).to(weight.dtype)  # (B, H, D)
        cos, sin = self.rotary(actions.shape[1], actions.device, z.dtype)
        for block, block_kv in zip(self.blocks, kv, strict=True):
            z = block(z, block_kv, cos, sin)
        return self.energy_out(self.final_norm(z)).squeeze(-1).float()  # (B, H)
