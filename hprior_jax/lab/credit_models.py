"""Two credit models that learn α from the preference labels alone (no dynamics): each scores
a segment of T steps, is trained on Bradley-Terry over labelled pairs (`lab.learned_credit`),
and gives α[B, T] (non-negative, rows sum to 1, under stop-gradient) for the prior loss.

state_importance   Zhang & Kashima, "Learning State Importance for Preference-based
                   Reinforcement Learning" (Machine Learning, 2024; their LassoBT):
                   score(σ) = Σ_t w(s_t)·r(s_t), a weight head w and a reward head r on one
                   state encoder φ; loss = BT + ramp·(l1·Σ_t |w_t| + l2·Σ_t (w_t − w_{t+1})²)
                   (sums over a segment's steps, means over segments), the ramp linear from 0
                   to 1 over the first half of the training steps; α_t = |w_t| / Σ_k |w_k|.
                   Choices: states only, as the paper's (its inputs are frames; the lab's
                   true rewards read the state); φ a 2-layer ELU MLP (the paper's continuous
                   encoder, narrower for the CPU); w an ELU MLP on φ (the paper's clip
                   encoder); r = tanh(φ·v), bounded as the lab's reward head, where the
                   paper's r is linear: with r free, w·r has a scale symmetry (w/c, c·r) that
                   makes the L1 penalty on w free to shrink, so bounding r is what makes the
                   penalty bite; the penalty weights are the paper code's (0.01 and 0.01).
                   A segment whose |w| all vanish gets uniform α.
pref_attention     Preference Transformer (Kim et al., ICLR 2023; their Flax code): a causal
                   transformer over the segment's steps, then a preference attention layer
                   (not causal, as theirs) whose output at step t is Σ_i A_{t,i} v_i; the score
                   is its mean over t (their `train_type="mean"`), so score = Σ_i α_i v_i with
                   α_i = mean over heads and query steps of A_{·,i}: the weight the score puts
                   on step i. Choices: one token per step from (s_t, a_t) (theirs has a state
                   and an action token); a learned embedding of the position within the
                   segment (theirs embeds the episode's time step, which stored pairs do not
                   keep); one causal block, pre-LayerNorm as GPT-2's, no dropout; H heads in
                   the preference layer share one value v (theirs has one head), so that the
                   mean over heads is exactly the score's weight.
"""
from __future__ import annotations

from dataclasses import dataclass

import flax.linen as nn
import jax
import jax.numpy as jnp

KINDS = ("state_importance", "pref_attention")


@dataclass(frozen=True)
class CreditModelConfig:
    """Sizes and training of the credit models: small, the lab runs on CPU. `steps` Adam
    steps a round on `batch_pairs` labelled pairs drawn with replacement from the stored ones
    (a fixed cost a round, whatever the label count)."""

    steps: int = 300
    batch_pairs: int = 32
    lr: float = 3e-3
    hidden: int = 32  # state importance: φ and w's widths
    l1: float = 0.01  # the paper code's ClipEncoder.l1_weight
    temporal_l2: float = 0.01  # ... and temporal_l2_weight
    ramp: float = 0.5  # share of the steps over which the penalties ramp up (lasso_bt3's 1/2)
    embed: int = 32  # preference attention: width of the tokens
    heads: int = 2
    key_dim: int = 16  # per head, in both attention layers
    ff: int = 64

    def __post_init__(self):
        if min(self.steps, self.batch_pairs, self.hidden, self.embed, self.heads,
               self.key_dim, self.ff) < 1:
            raise ValueError("credit model sizes and steps must be positive")


class StateImportanceNet(nn.Module):
    """obs[..., T, ds] -> (w[..., T], r[..., T])."""

    hidden: int

    @nn.compact
    def __call__(self, obs):
        phi = nn.Dense(self.hidden)(nn.elu(nn.Dense(self.hidden)(obs)))
        r = jnp.tanh(nn.Dense(1, use_bias=False)(phi))[..., 0]
        w = nn.Dense(1)(nn.elu(nn.Dense(self.hidden)(phi)))[..., 0]
        return w, r


class PreferenceAttentionNet(nn.Module):
    """obs[B, T, ds], act[B, T, da] -> (score[B], α[B, T], v[B, T])."""

    embed: int
    heads: int
    key_dim: int
    ff: int

    @nn.compact
    def __call__(self, obs, act):
        b, t, _ = obs.shape
        position = self.param("position", nn.initializers.normal(0.02), (t, self.embed))
        token = nn.Dense(self.embed)(jnp.concatenate([obs, act], -1))
        x = nn.LayerNorm()(token + position)
        h = nn.LayerNorm()(x)
        x = x + nn.MultiHeadDotProductAttention(
            num_heads=self.heads, qkv_features=self.heads * self.key_dim,
            out_features=self.embed)(h, h, mask=nn.make_causal_mask(jnp.ones((b, t))))
        x = x + nn.Dense(self.embed)(nn.gelu(nn.Dense(self.ff)(nn.LayerNorm()(x))))
        x = nn.LayerNorm()(x)
        v = nn.Dense(1)(x)[..., 0]  # each step's value, from its causal context as theirs
        split = lambda y: y.reshape(b, t, self.heads, self.key_dim)
        q = split(nn.Dense(self.heads * self.key_dim)(x))
        k = split(nn.Dense(self.heads * self.key_dim)(x))
        weights = jax.nn.softmax(jnp.einsum("bthd,bshd->bhts", q, k) / self.key_dim ** 0.5)
        alpha = weights.mean(axis=(1, 2))  # over heads and query steps: [B, T]
        return (alpha * v).sum(-1), alpha, v


def network(kind: str, cfg: CreditModelConfig) -> nn.Module:
    if kind == "state_importance":
        return StateImportanceNet(cfg.hidden)
    if kind == "pref_attention":
        return PreferenceAttentionNet(cfg.embed, cfg.heads, cfg.key_dim, cfg.ff)
    raise ValueError(f"credit model {kind!r}; choose one of {KINDS}")


def init(kind: str, cfg: CreditModelConfig, key: jax.Array, obs: jax.Array, act: jax.Array):
    """Fresh parameters for segments shaped like obs[B, T, ds], act[B, T, da]."""
    net = network(kind, cfg)
    return net.init(key, obs) if kind == "state_importance" else net.init(key, obs, act)


def score_and_penalty(kind: str, cfg: CreditModelConfig, params, obs, act):
    """obs[B, T, ds], act[B, T, da] -> (score[B], penalty per segment [B], before the ramp:
    state importance's L1 and temporal L2 on w; 0 for preference attention)."""
    if kind == "state_importance":
        w, r = network(kind, cfg).apply(params, obs)
        penalty = (cfg.l1 * jnp.abs(w).sum(-1)
                   + cfg.temporal_l2 * ((w[..., 1:] - w[..., :-1]) ** 2).sum(-1))
        return (w * r).sum(-1), penalty
    score, _, _ = network(kind, cfg).apply(params, obs, act)
    return score, jnp.zeros(score.shape)


def alpha(kind: str, cfg: CreditModelConfig, params, obs, act) -> jax.Array:
    """α[B, T] of segments obs[B, T, ds], act[B, T, da]: non-negative, rows sum to 1, under
    stop-gradient (the reward's loss never trains the credit model through it)."""
    if kind == "state_importance":
        w, _ = network(kind, cfg).apply(params, obs)
        size = jnp.abs(w)
        total = size.sum(-1, keepdims=True)
        out = jnp.where(total > 1e-12, size / jnp.maximum(total, 1e-12), 1.0 / w.shape[-1])
    else:
        _, out, _ = network(kind, cfg).apply(params, obs, act)
    return jax.lax.stop_gradient(out)
