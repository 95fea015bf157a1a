"""Does the world model predict, and does its attention carry state information? Pure
diagnostics on fixed segments (they read true rewards: metrics only, never training).

* `next_state_errors`: the world model's next-state error (decoded, in state units, the
  dynamics loss's `next_obs` term without dropout) next to two predictors that need no model:
  persistence (s_{t+1} = s_t) and the mean state of the segments. A model that does not beat
  persistence has learned nothing a credit could use about the dynamics. Predicting states,
  the decoded error cannot fall below the observation model's reconstruction error
  (`wm/reconstruction_error`, of dec(enc(s_{t+1}))); predicting changes (`predict="delta"`)
  it can. `wm/latent_skill_vs_persistence` asks the same question where the transformer
  works, of ẑ_{t+1} against z_t for z_{t+1} = enc(s_{t+1}).
* `credit_diagnostics`: how much of α is position. `alpha/position_r2` is the share of α's
  variance over (segment, step) that its mean profile over segments explains (1: α is the same
  at each position whatever the segment). Time-shuffled segments (each segment's steps
  permuted, states with their actions) separate position from content: if α follows the
  content, α of the shuffled segment is α permuted the same way (`alpha/shuffle_tv_content`
  small); if it is positional, it stays where it was (`alpha/shuffle_tv_position` small). Both
  are total-variation distances (0..1), means over segments. `alpha/reward_corr`: Pearson
  correlation, within each segment, of α_t with the true reward's deviation from the
  segment's mean (mean over segments whose reward is not constant): positive when α credits
  the steps that pay more.
* `unreachable_targets`: the share of the prior's targets α_t·R̂ over the stored pairs that a
  tanh reward cannot reach (|target| > 1), mean over ensemble members.
"""
from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp

from hprior_jax.buffers.preferences import PreferenceStore
from hprior_jax.networks.reward_ensemble import member_rewards
from hprior_jax.prior import world_model as wm
from hprior_jax.prior.attention import segment_credit
from hprior_jax.prior.loss import PairCredit, target_saturation, variant_alpha


def _half_sq(pred: jax.Array, target: jax.Array) -> jax.Array:
    return 0.5 * jnp.sum((pred - target) ** 2, axis=-1).mean()


def next_state_errors(params: wm.WorldModelParams, obs: jax.Array, act: jax.Array,
                      cfg: wm.WorldModelConfig) -> dict[str, jax.Array]:
    """0.5·Σ_dims squared error of predictions of obs[:, 1:] from segments obs[B, T, ds],
    act[B, T, da]: the world model (deterministic), persistence and the mean state."""
    z_pred, model = wm.predict_next(params, obs, act, cfg)
    nxt = obs[:, 1:]
    z = wm.encode(params.obs, obs, cfg)
    mean = obs.reshape(-1, obs.shape[-1]).mean(0)
    errors = {"wm/next_obs_error": _half_sq(model, nxt),
              "wm/persistence_error": _half_sq(obs[:, :-1], nxt),
              "wm/mean_state_error": _half_sq(jnp.broadcast_to(mean, nxt.shape), nxt),
              "wm/reconstruction_error": _half_sq(wm.decode(params.obs, z[:, 1:], cfg), nxt),
              "wm/latent_error": _half_sq(z_pred, z[:, 1:]),
              "wm/latent_persistence_error": _half_sq(z[:, :-1], z[:, 1:])}
    skill = lambda err, base: 1.0 - errors[err] / jnp.maximum(errors[base], 1e-12)
    errors["wm/skill_vs_persistence"] = skill("wm/next_obs_error", "wm/persistence_error")
    errors["wm/latent_skill_vs_persistence"] = skill("wm/latent_error",
                                                     "wm/latent_persistence_error")
    return errors


def _tv(a: jax.Array, b: jax.Array) -> jax.Array:
    return 0.5 * jnp.abs(a - b).sum(-1).mean()


def credit_diagnostics(alpha: jax.Array, alpha_shuffled: jax.Array, perm: jax.Array,
                       true_r: jax.Array) -> dict[str, jax.Array]:
    """alpha[B, T] of segments, alpha_shuffled[B, T] of the same segments with their steps
    reordered so that shuffled step i is original step perm[b, i], true_r[B, T]."""
    profile = alpha.mean(0)
    total = jnp.sum((alpha - alpha.mean()) ** 2)
    r2 = 1.0 - jnp.sum((alpha - profile) ** 2) / jnp.maximum(total, 1e-20)
    content = jnp.take_along_axis(alpha, perm, axis=1)  # α carried along with the steps
    dev = true_r - true_r.mean(-1, keepdims=True)
    a_dev = alpha - alpha.mean(-1, keepdims=True)
    norm = jnp.sqrt(jnp.sum(dev ** 2, -1) * jnp.sum(a_dev ** 2, -1))
    varies = norm > 1e-12
    corr = jnp.where(varies, jnp.sum(dev * a_dev, -1) / jnp.maximum(norm, 1e-12), 0.0)
    return {"alpha/position_r2": r2,
            "alpha/shuffle_tv_position": _tv(alpha_shuffled, alpha),
            "alpha/shuffle_tv_content": _tv(alpha_shuffled, content),
            "alpha/reward_corr": corr.sum() / jnp.maximum(varies.sum(), 1),
            "alpha/last_step": alpha[:, -1].mean()}


def world_model_diagnostics(params: wm.WorldModelParams, obs: jax.Array, act: jax.Array,
                            true_r: jax.Array, perm: jax.Array, cfg: wm.WorldModelConfig, *,
                            query: str = "action") -> dict[str, jax.Array]:
    """Both groups on segments obs[B, T, ds], act[B, T, da], true_r[B, T]; perm[B, T] is
    each segment's step order for the shuffled copy."""
    alpha = segment_credit(params, obs, act, cfg, query=query)
    shuffle = lambda x: jnp.take_along_axis(x, perm[..., None], axis=1)
    alpha_shuffled = segment_credit(params, shuffle(obs), shuffle(act), cfg, query=query)
    return {**next_state_errors(params, obs, act, cfg),
            **credit_diagnostics(alpha, alpha_shuffled, perm, true_r)}


def unreachable_targets(reward_params, prefs: PreferenceStore, credit: PairCredit, reward_cfg,
                        variant: str = "raw", shift=0.0) -> jax.Array:
    """Share of the prior's targets (`prior.loss.prior_targets` of form `shift`) beyond
    [-1, 1] over the stored pairs' segments (both sides, the credit `variant` applied), mean
    over members k."""
    real = jnp.arange(prefs.capacity) < prefs.count
    mask2 = jnp.concatenate([real, real])
    alpha = variant_alpha(jnp.concatenate([credit.alpha1, credit.alpha2]), variant)
    obs = jnp.concatenate([prefs.obs1, prefs.obs2])
    act = jnp.concatenate([prefs.act1, prefs.act2])
    r = member_rewards(reward_params, obs, act, reward_cfg)  # [K, 2C, T]
    saturation = jax.vmap(partial(target_saturation, shift=shift))
    out = jax.vmap(lambda r_k: saturation(r_k, alpha))(r)  # [K, 2C]
    return jnp.sum(out.mean(0) * mask2) / (jnp.maximum(prefs.count, 1).astype(jnp.float32) * 2)
