"""MRN's bi-level update (Liu et al. 2022; RyanLiu112/MRN `train_MRN.py` `bilevel_update`).

On one SAC batch (s, a, s', not_done) and the most recent labelled pairs:
  1. r = r̂_φ(s, a), the ensemble mean, differentiable in φ;
  2. inner target y = r + not_done · γ · sg(min Q'(s', a') − α log π(a'|s')), a' ~ π(·|s');
  3. one virtual SGD step of the critic: θ'(φ) = θ − lr_critic · ∇_θ [MSE(Q1_θ, y) + MSE(Q2_θ, y)]
     (the original loads the critic's Adam state into `MetaOptim` but `meta_step` is plain SGD);
  4. outer loss = outer_weight · [CE([Q1_θ'(σ¹_0), Q1_θ'(σ²_0)], y) + CE(Q2 likewise)], each
     segment scored by the virtually updated critic at its FIRST step only;
  5. one step of the reward ensemble's own Adam on ∇_φ outer (second order: through θ'(φ));
  6. the real SAC update on the same batch with r̂ of the updated ensemble.
Step 6 reuses step 2's target in the original; here the inner target draws a' with the very key
SAC's critic update draws it with, so `SAC.update` on the same batch and key recomputes the same
target: the real update IS a plain SAC update with the updated reward.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import optax

from hprior_jax.agents.sac import SAC, Batch, SACState
from hprior_jax.buffers.preferences import PreferenceBatch
from hprior_jax.networks.reward_ensemble import RewardConfig, mean_reward
from hprior_jax.pbrl.preference import bt_loss_from_returns


def inner_target(sac: SAC, state: SACState, batch: Batch, reward: jax.Array,
                 key: jax.Array) -> jax.Array:
    """y = r + not_done · γ · sg(V'(s')), with a' drawn as `SAC.critic_loss` draws it from `key`
    (the critic's half of `SAC.update`'s key)."""
    return reward + batch.not_done * sac.cfg.discount * sac.target_value(state, batch.next_obs, key)


def virtual_critic(sac: SAC, critic, batch: Batch, target: jax.Array, lr: float):
    """θ' = θ − lr · ∇_θ [MSE(Q1, y) + MSE(Q2, y)]: differentiable in y (and so in φ)."""
    def loss(c):
        q1, q2 = sac.critic_net.apply(c, batch.obs, batch.action)
        return jnp.mean((q1 - target) ** 2) + jnp.mean((q2 - target) ** 2)

    grads = jax.grad(loss)(critic)
    return jax.tree.map(lambda p, g: p - lr * g, critic, grads)


def outer_loss(sac: SAC, critic, pairs: PreferenceBatch, mask: jax.Array) -> jax.Array:
    """CE of each critic head's Q at the segments' first step against the labels, summed over
    the two heads (each a mean over the real pairs)."""
    q1a, q2a = sac.critic_net.apply(critic, pairs.obs1[:, 0], pairs.act1[:, 0])
    q1b, q2b = sac.critic_net.apply(critic, pairs.obs2[:, 0], pairs.act2[:, 0])
    return bt_loss_from_returns(jnp.stack([q1a, q2a]), jnp.stack([q1b, q2b]), pairs.labels,
                                mask)[0]


def meta_objective(reward_params, sac: SAC, state: SACState, batch: Batch,
                   pairs: PreferenceBatch, mask: jax.Array, key: jax.Array, *,
                   reward_cfg: RewardConfig, outer_weight: float) -> jax.Array:
    """outer_weight · outer loss of the critic after one virtual step, as a function of φ."""
    reward = mean_reward(reward_params, batch.obs, batch.action, reward_cfg)
    target = inner_target(sac, state, batch, reward, key)
    critic = virtual_critic(sac, state.critic, batch, target, sac.cfg.lr)
    return outer_weight * outer_loss(sac, critic, pairs, mask)


def bilevel_update(sac: SAC, state: SACState, reward_params, reward_opt, batch: Batch,
                   pairs: PreferenceBatch, mask: jax.Array, key: jax.Array, step: jax.Array, *,
                   reward_tx: optax.GradientTransformation, reward_cfg: RewardConfig,
                   outer_weight: float):
    """Steps 1-6 above. `batch.not_done` is the bootstrap mask the original uses here (its
    `not_done`: time-limit ends count as terminal). -> (sac state, reward params, reward
    optimiser state, metrics)."""
    k_critic, _ = jax.random.split(key)  # SAC.update's split: its critic draws a' from k_critic
    outer, grads = jax.value_and_grad(meta_objective)(
        reward_params, sac, state, batch, pairs, mask, k_critic, reward_cfg=reward_cfg,
        outer_weight=outer_weight)
    updates, reward_opt = reward_tx.update(grads, reward_opt, reward_params)
    reward_params = optax.apply_updates(reward_params, updates)
    reward = mean_reward(reward_params, batch.obs, batch.action, reward_cfg)
    state, metrics = sac.update(state, batch._replace(reward=reward), key, step)
    return state, reward_params, reward_opt, {**metrics, "mrn/outer_loss": outer,
                                              "mrn/batch_reward": jnp.mean(reward)}
