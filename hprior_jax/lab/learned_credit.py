"""Learned credit in a lab round: a credit model (`lab.credit_models`) trained on the cell's
labelled pairs, then α of every stored pair and the model's mean α per position.

When α is computed: every round, for every stored pair, by a credit model trained afresh that
round on all the cell's labels so far (PRIOR's α is computed once, when a pair is stored, by a
world model that the lab keeps fixed). A credit model learns from the labels, which grow round
by round: α stored at query time would keep the verdict of a model that saw 10 labels for the
whole lab, and the pairs of the first rounds would be credited worst. Afresh, not warm-started,
so that α at a budget is the paper's procedure on that budget's labels (the penalty's ramp
restarts with it) and does not depend on the path of earlier rounds.

The positional control of a learned rule (`*_positional`) is that same model's mean α at each
position over `profile_segments` training segments drawn that round, the same for every
segment: what is left of its α without state information, as `positional` is for PRIOR.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import optax

from hprior_jax.buffers.preferences import PreferenceStore
from hprior_jax.lab import credit_models
from hprior_jax.lab.credit_models import CreditModelConfig
from hprior_jax.pbrl.preference import bt_loss_from_returns
from hprior_jax.prior import world_model as wm
from hprior_jax.prior.loss import PairCredit


def fit(kind: str, cfg: CreditModelConfig, key: jax.Array, prefs: PreferenceStore):
    """A credit model trained from scratch on the stored pairs of `prefs`: `cfg.steps` Adam
    steps, each on `cfg.batch_pairs` pairs drawn with replacement among the `count` stored;
    Bradley-Terry on the scores (equal labels: a 0.5 target) plus the model's penalty, ramped
    linearly over the first `cfg.ramp` of the steps. -> (params, the last step's BT accuracy)."""
    k_init, k_steps = jax.random.split(key)
    params = credit_models.init(kind, cfg, k_init, prefs.obs1[:1], prefs.act1[:1])
    tx = optax.adam(cfg.lr)
    ramp_steps = max(cfg.ramp * cfg.steps, 1.0)

    def loss(p, rows, i):
        both = lambda a, b: jnp.concatenate([a[rows], b[rows]])
        score, penalty = credit_models.score_and_penalty(
            kind, cfg, p, both(prefs.obs1, prefs.obs2), both(prefs.act1, prefs.act2))
        s1, s2 = jnp.split(score, 2)
        bt, _, correct, n = bt_loss_from_returns(s1[None], s2[None], prefs.labels[rows])
        ramp = jnp.minimum(i / ramp_steps, 1.0)
        return bt + ramp * penalty.mean(), correct[0] / jnp.maximum(n[0], 1.0)

    def step(carry, inp):
        p, opt = carry
        i, k = inp
        rows = jax.random.randint(k, (cfg.batch_pairs,), 0, jnp.maximum(prefs.count, 1))
        (_, acc), grads = jax.value_and_grad(loss, has_aux=True)(p, rows, i)
        updates, opt = tx.update(grads, opt, p)
        return (optax.apply_updates(p, updates), opt), acc

    (params, _), acc = jax.lax.scan(step, (params, tx.init(params)),
                                    (jnp.arange(cfg.steps, dtype=jnp.float32),
                                     jax.random.split(k_steps, cfg.steps)))
    return params, acc[-1]


def learned_credits(kind: str, cfg: CreditModelConfig, key: jax.Array, prefs: PreferenceStore,
                    train_obs: jax.Array, train_act: jax.Array, profile_segments: int):
    """One round's credit of a learned rule and of its positional control, for every stored
    row: (PairCredit of the model's α, PairCredit of its mean profile, the model's BT
    accuracy). `train_obs[E, L, ds]`, `train_act[E, L, da]`: the episodes the profile's
    segments are drawn from."""
    k_fit, k_seg = jax.random.split(key)
    params, acc = fit(kind, cfg, k_fit, prefs)
    of = lambda obs, act: credit_models.alpha(kind, cfg, params, obs, act)
    e, length = train_obs.shape[:2]
    flat = lambda x: x.reshape((e * length,) + x.shape[2:])
    seg_obs, seg_act = wm.sample_segments(k_seg, flat(train_obs), flat(train_act),
                                          jnp.int32(e * length), episode_len=length,
                                          batch_size=profile_segments,
                                          segment_len=prefs.obs1.shape[1])
    profile = jnp.broadcast_to(of(seg_obs, seg_act).mean(0), prefs.labels.shape + (
        prefs.obs1.shape[1],))
    return (PairCredit(of(prefs.obs1, prefs.act1), of(prefs.obs2, prefs.act2)),
            PairCredit(profile, profile), acc)
