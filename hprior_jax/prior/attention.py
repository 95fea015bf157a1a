"""World-model attention -> per-step credit α (appendix C).

Appendix C: "feed in a trajectory auto-regressively, i.e. first the first (state, action) tuple as
a trajectory of size 1, then the next, and so on. At the final step take the attention vector
from the attention layers." We read it as: at the final step, the query of the last token attends
over every earlier state and action token of the segment; average layers and heads; add each
step's state and action entries:
    ā_j = mean_{l,h} A^{(l,h)}[q*, j],   α_t = ā_{s_t} + ā_{a_t}.

Choices where the paper is ambiguous (one reason each):
- Query q* = the action token of the last step (default `query="action"`): its output is the one
  TWM's heads read to predict s_{T+1}, and it is the only final-step token that sees both tokens
  of every step (the state query cannot see a_T). `query="state"` is kept as an ablation.
- Mean over heads and layers: the paper's A has no head index (its third reviewer on
  OpenReview, ICLR 2024, points that out); TWM's play.py and WiseRL average heads, WiseRL
  averages layers.
- State and action entries added with equal weight (the paper's first OpenReview reviewer
  asks why they are weighted equally).
- One causal pass instead of T incremental passes: with causal masking and XL memory holding
  every earlier token, token i's hidden states never depend on later tokens, so the cached layer
  inputs used at step k equal those of a full pass, and relative distances are the same; hence the
  final step's attention = the last query row of one causal pass over the 2T tokens (needs memory
  >= 2(T-1) tokens and a window covering the segment, which WorldModelConfig enforces).
  `autoregressive_credit` runs the literal procedure; tests check the two agree. The single pass
  costs one forward instead of T.
- No XL memory from before the segment: the segment is fed on its own (Table 5 sets sequence =
  memory = segment length so the whole segment is the input), and a query segment's predecessor
  is not in the preference store anyway.
- Eval mode (no dropout); TWM returns pre-dropout weights anyway.
- Normalisation: α is renormalised over the segment's valid steps. Without memory or padding the
  row already sums to 1 (a no-op up to rounding); with memory keys or masked steps it restores
  Σα = 1, which the redistribution R_target = α·R̂ relies on.
"""
from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp

from hprior_jax.buffers.preferences import PreferenceStore
from hprior_jax.networks.transformer_xl import keep_last
from hprior_jax.prior import world_model as wm
from hprior_jax.prior.loss import PairCredit

_QUERY_OFFSET = {"state": 0, "action": 1}


def credit_from_attention(attn: jax.Array, num_steps: int, *, query: str = "action",
                          step_mask: jax.Array | None = None, own_step: bool = True) -> jax.Array:
    """attn[L, H, Tq, Tk] (one sequence) -> α[T], T = num_steps.

    Layout: the last 2T keys are the segment's tokens s_0, a_0, ..., s_{T-1}, a_{T-1} (earlier keys,
    e.g. XL memory, are ignored) and the last Tq queries are the last Tq of those tokens. The query
    read is the `query` token of the last valid step (last True of `step_mask`; padded steps must
    not come before real ones if Tq < 2T). α is zero on masked steps, non-negative, sums to 1.
    `own_step=False` (an ablation): α is also zero on the query's own step, the last valid one,
    whose share (α_T ≈ 0.32 in the reduced cheetah runs) holds the query's attention to its own
    tokens.
    """
    if query not in _QUERY_OFFSET:
        raise ValueError(f"query={query!r}; choose 'action' or 'state'")
    _, _, tq, tk = attn.shape
    t = num_steps
    if tk < 2 * t:
        raise ValueError(f"attention has {tk} keys, fewer than 2·num_steps = {2 * t}")
    mask = jnp.ones((t,), bool) if step_mask is None else step_mask.astype(bool)
    last = jnp.max(jnp.where(mask, jnp.arange(t), 0))
    row = tq - 2 * t + 2 * last + _QUERY_OFFSET[query]
    a = jax.lax.dynamic_index_in_dim(attn, row, axis=2, keepdims=False)  # [L, H, Tk]
    a = a.mean(axis=(0, 1))[tk - 2 * t:]  # mean over layers and heads; segment keys only
    if not own_step:
        mask = mask & (jnp.arange(t) != last)
    alpha = a.reshape(t, 2).sum(-1) * mask
    return alpha / jnp.maximum(alpha.sum(), jnp.finfo(alpha.dtype).tiny)


def segment_attention(params: wm.WorldModelParams, obs: jax.Array, act: jax.Array,
                      cfg: wm.WorldModelConfig) -> jax.Array:
    """One deterministic causal pass over segments obs[B, T, ds], act[B, T, da], no memory.
    -> attn[B, L, H, 2T, 2T]."""
    _, _, attn = wm.dynamics(params, obs, act, cfg, deterministic=True)
    return attn


def segment_credit(params: wm.WorldModelParams, obs: jax.Array, act: jax.Array,
                   cfg: wm.WorldModelConfig, *, query: str = "action",
                   step_mask: jax.Array | None = None, own_step: bool = True) -> jax.Array:
    """α[B, T] for segments obs[B, T, ds], act[B, T, da] (step_mask[B, T] optional).

    Padded steps should be at the end: under causal attention the real tokens then never see them.
    """
    t = obs.shape[1]
    attn = segment_attention(params, obs, act, cfg)
    credit = partial(credit_from_attention, num_steps=t, query=query, own_step=own_step)
    if step_mask is None:
        return jax.vmap(credit)(attn)
    return jax.vmap(lambda a, m: credit(a, step_mask=m))(attn, step_mask)


def autoregressive_credit(params: wm.WorldModelParams, obs: jax.Array, act: jax.Array,
                          cfg: wm.WorldModelConfig, *, query: str = "action") -> jax.Array:
    """The appendix's literal procedure: feed (s_0, a_0), then (s_1, a_1) with the XL memory of
    the earlier steps, ...; α from the final step's attention. -> α[B, T].

    Static shapes: a fixed memory of 2(T-1) tokens whose not-yet-filled (leftmost) slots are
    masked; the valid ones sit at the right end, so relative distances are exact.
    """
    b, t, _ = obs.shape
    tcfg = cfg.transformer()
    size = 2 * (t - 1)
    if tcfg.mem_len < size:
        raise ValueError(f"memory of {tcfg.mem_len} tokens cannot hold {size}; raise memory_len")
    z = jax.lax.stop_gradient(wm.encode(params.obs, obs, cfg))
    model = wm.DynamicsModel(cfg)
    mems0 = jnp.zeros((cfg.num_layers, b, size, cfg.embed_dim), jnp.float32)
    valid0 = jnp.zeros((b, size), bool)

    def step(carry, xs):
        mems, valid = carry
        z_k, a_k = xs  # [B, dz], [B, da]
        key_mask = jnp.concatenate([valid, jnp.ones((b, 2), bool)], axis=1)
        _, new_mems, attn = model.apply(params.dyn, z_k[:, None], a_k[:, None], mems, key_mask, True)
        valid = keep_last(jnp.concatenate([valid, jnp.ones((b, 2), bool)], axis=1), size, axis=1)
        return (keep_last(new_mems, size, axis=2), valid), attn

    (_, _), attns = jax.lax.scan(step, (mems0, valid0), (jnp.swapaxes(z, 0, 1), jnp.swapaxes(act, 0, 1)))
    last = attns[-1]  # [B, L, H, 2, 2T]
    return jax.vmap(lambda a: credit_from_attention(a, t, query=query))(last)


def pair_credit(params: wm.WorldModelParams, store: PreferenceStore, cfg: wm.WorldModelConfig, *,
                chunk: int = 50, query: str = "action", credit: PairCredit | None = None,
                own_step: bool = True, obs_scaler: wm.ObsScaler | None = None) -> PairCredit:
    """α for both segments of every stored pair (rows 0..count-1), `chunk` pairs per forward
    (their observations standardised by `obs_scaler` when given, as the world model trained).

    Cost scales with `count`, not capacity. Rows >= count keep their old value (`credit`, or the
    uniform 1/T when None). α is read only by the reward update, so computing it once per
    feedback round gives the same values as after every world-model update.
    """
    cap, t = store.labels.shape[0], store.obs1.shape[1]
    chunk = min(chunk, cap)
    if credit is None:
        credit = PairCredit.uniform(cap, t)
    n_chunks = (store.count + chunk - 1) // chunk

    def body(i, c: PairCredit):
        start = jnp.minimum(i * chunk, cap - chunk)  # the last chunk may overlap the previous one
        take = lambda x: jax.lax.dynamic_slice_in_dim(x, start, chunk, axis=0)
        obs = wm.scaled(obs_scaler, jnp.concatenate([take(store.obs1), take(store.obs2)], axis=0))
        act = jnp.concatenate([take(store.act1), take(store.act2)], axis=0)
        alpha = segment_credit(params, obs, act, cfg, query=query, own_step=own_step)
        real = (start + jnp.arange(chunk) < store.count)[:, None]

        def put(dst, src):
            src = jnp.where(real, src, take(dst))
            return jax.lax.dynamic_update_slice_in_dim(dst, src, start, axis=0)

        return PairCredit(alpha1=put(c.alpha1, alpha[:chunk]), alpha2=put(c.alpha2, alpha[chunk:]))

    return jax.lax.fori_loop(0, n_chunks, body, credit)
