"""Transformer-XL decoder as TWM uses it (Robine et al. 2023, `twm/nets.py`; Dai et al. 2019).

Per layer (post-LN, as TWM's `TransformerXLDecoderLayer`):
    h = LN1(x + Dropout(RelAttn(x, mems)))
    y = LN2(h + Dropout(W2 · Dropout(act(W1 · h))))
`norm_first=True` gives the pre-LN variant (x + Attn(LN(x)), final LN) as an option.

Relative attention (TWM `RelativeMultiheadSelfAttention`):
    score[i, j] = ((q_i + u) · k_j + (q_i + v) · P_{pos(i) - pos(j)}) · scale
with q, k, v from one bias-free projection of [mems; x], P = a per-layer bias-free projection of
sinusoidal encodings of the relative distance (dropout on the encodings, shared by all layers),
u = r_w_bias and v = r_r_bias shared across layers (xavier-uniform), and scale = 1/sqrt(embed_dim)
(TWM's choice, not 1/sqrt(head_dim); `scale_by_model_dim=False` gives the usual one).
Masking: causal over memory + current tokens, optional window (max query-key distance in tokens,
TWM's memory window), optional key mask (invalid memory / padding). A query always sees itself,
so no row is empty. Attention dropout is applied after the weights are returned, so the returned
attention is the pre-dropout softmax (as TWM).

Memory: `mems[L, B, M, D]` holds each layer's *input* for M earlier tokens; the new memory is the
last `mem_len` of concat(mems, layer inputs), under stop_gradient (TWM `.detach()`).

The attention of every layer is an explicit output: attn[B, L, H, Tq, M + Tq].
Layers run under `nn.scan` (one compiled layer body; params stacked on a leading L axis), unrolled
or not (`unroll_layers`). SiLU is computed through tanh and dropout masks from hashed bits by
default (`networks.elementwise`: the same function and distribution, cheaper on XLA:CPU).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import flax.linen as nn
import jax
import jax.numpy as jnp

from hprior_jax.networks.elementwise import Dropout, DropoutBits, silu_tanh

# PyTorch nn.Linear default init (TWM keeps it inside the transformer): U(±1/sqrt(fan_in)).
torch_kernel_init = nn.initializers.variance_scaling(1.0 / 3.0, "fan_in", "uniform")

_ACT = {"silu": silu_tanh, "relu": nn.relu, "gelu": nn.gelu}


def torch_bias_init(fan_in: int):
    bound = 1.0 / math.sqrt(fan_in)

    def init(key, shape, dtype=jnp.float32):
        return jax.random.uniform(key, shape, dtype, -bound, bound)

    return init


@dataclass(frozen=True)
class TransformerXLConfig:
    """Defaults = TWM `dyn_*` config (Robine et al. 2023): 10 layers, 4 heads x 64, d 256, FFN 1024."""

    embed_dim: int = 256
    num_heads: int = 4
    head_dim: int = 64
    num_layers: int = 10
    ff_dim: int = 1024
    dropout: float = 0.1
    activation: str = "silu"
    mem_len: int = 102  # tokens kept as memory; TWM: memory_length * modalities + num_current
    window: int | None = None  # max query-key distance in tokens (None: unbounded)
    norm_first: bool = False  # TWM is post-LN
    scale_by_model_dim: bool = True  # TWM quirk: 1/sqrt(embed_dim)
    layer_norm_eps: float = 1e-5
    # Unrolled layers: same arithmetic, no loop stacking each layer's activations for the
    # backward pass (XLA's cost analysis also counts a loop body once, so FLOP counts need it).
    unroll_layers: bool = False
    dropout_bits: DropoutBits = "hash"  # see networks.elementwise.Dropout

    def __post_init__(self):
        if self.activation not in _ACT:
            raise ValueError(f"activation={self.activation!r}; choose one of {sorted(_ACT)}")
        if self.embed_dim % 2:
            raise ValueError("embed_dim must be even (sinusoidal encodings)")
        if self.num_layers < 1 or self.num_heads < 1:
            raise ValueError("num_layers and num_heads must be >= 1")
        if self.mem_len < 0:
            raise ValueError(f"mem_len={self.mem_len} must be >= 0")


def sinusoid_encodings(distances: jax.Array, dim: int) -> jax.Array:
    """TWM `PositionalEncoding`: enc[:, 0::2] = sin(d·w), enc[:, 1::2] = cos(d·w). -> [N, dim]."""
    div = jnp.exp(jnp.arange(0, dim, 2, dtype=jnp.float32) * (-math.log(10000.0) / dim))
    ang = distances.astype(jnp.float32)[:, None] * div[None, :]
    return jnp.stack([jnp.sin(ang), jnp.cos(ang)], axis=-1).reshape(distances.shape[0], dim)


def rel_shift(x: jax.Array) -> jax.Array:
    """Transformer-XL's shift. x[..., Tq, Tk] holds scores against distances Tk-1, ..., 0 (column
    p <-> distance Tk-1-p); returns y[..., i, j] = score at distance (Tk - Tq + i) - j, exact for
    every j <= Tk - Tq + i (the causal entries; the others are garbage and get masked)."""
    *lead, tq, tk = x.shape
    x = jnp.concatenate([jnp.zeros((*lead, tq, 1), x.dtype), x], axis=-1)
    x = x.reshape(*lead, tk + 1, tq)[..., 1:, :]
    return x.reshape(*lead, tq, tk)


def attention_mask(tq: int, m: int, window: int | None = None,
                   key_mask: jax.Array | None = None) -> jax.Array:
    """[..., Tq, M+Tq] bool, True = may attend. Query i sits at position M+i."""
    qpos = m + jnp.arange(tq)[:, None]
    kpos = jnp.arange(m + tq)[None, :]
    dist = qpos - kpos
    mask = dist >= 0
    if window is not None:
        mask = mask & (dist <= window)
    if key_mask is not None:
        mask = mask & (key_mask[..., None, :] | (dist == 0))
    return mask


def keep_last(x: jax.Array, n: int, axis: int) -> jax.Array:
    """The last n entries of x along a static axis; n = 0 gives an empty axis (a plain
    `x[..., -n:]` would return everything for n = 0)."""
    size = x.shape[axis]
    return jax.lax.slice_in_dim(x, size - min(n, size), size, axis=axis)


def new_mem_mask(mem_mask: jax.Array | None, batch: int, m: int, tq: int, mem_len: int) -> jax.Array:
    """Validity of the memory returned by TransformerXL: [B, min(M+Tq, mem_len)] (all current
    tokens are valid; `mem_mask` None means all M old ones are)."""
    old = jnp.ones((batch, m), bool) if mem_mask is None else mem_mask.astype(bool)
    return keep_last(jnp.concatenate([old, jnp.ones((batch, tq), bool)], axis=1), mem_len, axis=1)


class RelativeMultiheadSelfAttention(nn.Module):
    cfg: TransformerXLConfig
    deterministic: bool = True

    @nn.compact
    def __call__(self, x, mem, pos_enc, u, v, mask):
        """x[B,Tq,D], mem[B,M,D], pos_enc[Tk,D] (distances Tk-1..0), mask[B,Tq,Tk] -> (out, attn[B,H,Tq,Tk])."""
        c = self.cfg
        b, tq, d = x.shape
        hd = c.num_heads * c.head_dim
        cat = jnp.concatenate([mem, x], axis=1)
        tk = cat.shape[1]
        qkv = nn.Dense(3 * hd, use_bias=False, kernel_init=torch_kernel_init, name="qkv_proj")(cat)
        q, k, val = jnp.split(qkv, 3, axis=-1)
        q = q[:, -tq:].reshape(b, tq, c.num_heads, c.head_dim)
        k = k.reshape(b, tk, c.num_heads, c.head_dim)
        val = val.reshape(b, tk, c.num_heads, c.head_dim)
        p = nn.Dense(hd, use_bias=False, kernel_init=torch_kernel_init, name="pos_proj")(pos_enc)
        p = p.reshape(tk, c.num_heads, c.head_dim)
        content = jnp.einsum("bind,bjnd->bnij", q + u, k)
        position = rel_shift(jnp.einsum("bind,jnd->bnij", q + v, p))
        scale = 1.0 / math.sqrt(c.embed_dim if c.scale_by_model_dim else c.head_dim)
        score = (content + position) * scale
        score = jnp.where(mask[:, None], score, -jnp.inf)
        attn = jax.nn.softmax(score, axis=-1)
        dropped = Dropout(c.dropout, c.dropout_bits)(attn, self.deterministic)
        ctx = jnp.einsum("bnij,bjnd->bind", dropped, val).reshape(b, tq, hd)
        out = nn.Dense(d, use_bias=False, kernel_init=torch_kernel_init, name="out_proj")(ctx)
        return out, attn


class TransformerXLLayer(nn.Module):
    """One decoder layer in scan form: (x, mem_l, *broadcast) -> (x', (x, attn_l))."""

    cfg: TransformerXLConfig
    deterministic: bool = True

    @nn.compact
    def __call__(self, x, mem, pos_enc, u, v, mask):
        c = self.cfg
        det = self.deterministic
        drop = lambda y: Dropout(c.dropout, c.dropout_bits)(y, det)
        ln1 = nn.LayerNorm(epsilon=c.layer_norm_eps, name="norm1")
        ln2 = nn.LayerNorm(epsilon=c.layer_norm_eps, name="norm2")
        attn_mod = RelativeMultiheadSelfAttention(c, det, name="self_attn")
        lin1 = nn.Dense(c.ff_dim, kernel_init=torch_kernel_init,
                        bias_init=torch_bias_init(c.embed_dim), name="linear1")
        lin2 = nn.Dense(c.embed_dim, kernel_init=torch_kernel_init,
                        bias_init=torch_bias_init(c.ff_dim), name="linear2")
        ff = lambda y: drop(lin2(drop(_ACT[c.activation](lin1(y)))))
        if c.norm_first:
            # The memory of a pre-LN layer is its raw input; it is normalised like the current tokens.
            a, attn = attn_mod(ln1(x), ln1(mem), pos_enc, u, v, mask)
            h = x + drop(a)
            y = h + ff(ln2(h))
        else:
            a, attn = attn_mod(x, mem, pos_enc, u, v, mask)
            h = ln1(x + drop(a))
            y = ln2(h + ff(h))
        return y, (x, attn)


class TransformerXL(nn.Module):
    """x[B, Tq, D] (already embedded tokens) -> (out[B, Tq, D], new_mems[L, B, M', D],
    attn[B, L, H, Tq, M + Tq]) with M' = min(M + Tq, cfg.mem_len).

    mems: [L, B, M, D] or None (M = 0). key_mask: [B, M + Tq] bool (True = real token), e.g. to
    ignore not-yet-filled memory slots; None = all valid. Dropout needs rngs={'dropout': key}
    when deterministic=False.
    """

    cfg: TransformerXLConfig

    @nn.compact
    def __call__(self, x: jax.Array, mems: jax.Array | None = None,
                 key_mask: jax.Array | None = None, deterministic: bool = True):
        c = self.cfg
        b, tq, d = x.shape
        if d != c.embed_dim:
            raise ValueError(f"token width {d} != embed_dim {c.embed_dim}")
        if mems is None:
            mems = jnp.zeros((c.num_layers, b, 0, d), x.dtype)
        m = mems.shape[2]
        tk = m + tq
        xavier = nn.initializers.xavier_uniform()
        u = self.param("u_bias", xavier, (c.num_heads, c.head_dim))
        v = self.param("v_bias", xavier, (c.num_heads, c.head_dim))
        pos_enc = sinusoid_encodings(jnp.arange(tk - 1, -1, -1), d)  # TWM positions src_len-1 .. 0
        pos_enc = Dropout(c.dropout, c.dropout_bits)(pos_enc, deterministic)
        mask = jnp.broadcast_to(attention_mask(tq, m, c.window, key_mask), (b, tq, tk))
        Scan = nn.scan(TransformerXLLayer, variable_axes={"params": 0},
                       split_rngs={"params": True, "dropout": True},
                       in_axes=(0, nn.broadcast, nn.broadcast, nn.broadcast, nn.broadcast),
                       length=c.num_layers, unroll=c.num_layers if c.unroll_layers else 1)
        out, (layer_inputs, attn) = Scan(c, deterministic, name="layers")(x, mems, pos_enc, u, v, mask)
        if c.norm_first:
            out = nn.LayerNorm(epsilon=c.layer_norm_eps, name="final_norm")(out)
        new_mems = jax.lax.stop_gradient(
            keep_last(jnp.concatenate([mems, layer_inputs], axis=2), c.mem_len, axis=2))
        return out, new_mems, jnp.moveaxis(attn, 0, 1)
