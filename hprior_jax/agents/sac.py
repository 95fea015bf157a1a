"""Soft Actor-Critic as in BPref `agent/sac.py` (the SAC under every PbRL baseline).

Pure functions over an `SACState` pytree; the static pieces (network shapes, optimizers,
hyper-parameters) live in the `SAC` object. Reference: BPref `agent/sac.py`, appendix
Table 2.

- critic target  y = r + not_done * gamma * (min(Q1', Q2')(s', a') - alpha * log pi(a'|s'))
  with a' ~ pi(.|s') reparameterised; `not_done` is 0 only at true terminations, so the
  critic bootstraps through time limits (BPref's `not_done_no_max`).
- actor loss     mean(alpha * log pi(a|s) - min(Q1, Q2)(s, a)) with the just-updated critic.
- temperature    loss mean(alpha * stop_grad(-log pi - target_entropy)), alpha = exp(log_alpha).
- target EMA     theta' <- tau theta + (1 - tau) theta' when global_step % target_update_every == 0.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax
from flax import struct

from hprior_jax.networks.sac_nets import DoubleQCritic, TanhGaussianActor, squashed_gaussian_sample


@dataclass(frozen=True)
class SACConfig:
    hidden_dim: int = 1024  # appendix/BPref: 1024 x 2 for DMC, 256 x 3 for MetaWorld
    hidden_depth: int = 2
    batch_size: int = 512  # appendix Table 2: 512 (DMC), 1024 (MetaWorld)
    lr: float = 1e-3  # actor and critic; appendix Table 2 per task
    alpha_lr: float = 1e-4  # BPref: never overridden
    init_temperature: float = 0.1
    discount: float = 0.99
    tau: float = 5e-3
    target_update_every: int = 2
    actor_update_every: int = 1
    log_std_min: float = -5.0
    log_std_max: float = 2.0
    adam_b1: float = 0.9
    adam_b2: float = 0.999

    def __post_init__(self):
        if self.hidden_dim <= 0 or self.hidden_depth < 0 or self.batch_size <= 0:
            raise ValueError(
                f"SAC sizes must be positive (hidden_dim={self.hidden_dim}, "
                f"hidden_depth={self.hidden_depth}, batch_size={self.batch_size}); "
                "fix --sac.hidden-dim/--sac.hidden-depth/--sac.batch-size")
        if not (0 < self.tau <= 1) or not (0 <= self.discount <= 1):
            raise ValueError("need 0 < --sac.tau <= 1 and 0 <= --sac.discount <= 1")
        if self.lr <= 0 or self.alpha_lr <= 0:
            raise ValueError("learning rates must be positive (--sac.lr, --sac.alpha-lr)")
        if self.target_update_every < 1 or self.actor_update_every < 1:
            raise ValueError("--sac.target-update-every and --sac.actor-update-every must be >= 1")


@struct.dataclass
class SACState:
    actor: dict
    critic: dict
    critic_target: dict
    log_alpha: jax.Array
    actor_opt: optax.OptState
    critic_opt: optax.OptState
    alpha_opt: optax.OptState


class Batch(NamedTuple):
    """What the agent may see of a transition (never the true reward unless it *is* the
    training reward, as for SAC on the true reward)."""

    obs: jax.Array
    action: jax.Array
    reward: jax.Array
    next_obs: jax.Array
    not_done: jax.Array


class SAC:
    def __init__(self, obs_size: int, action_size: int, cfg: SACConfig):
        self.cfg = cfg
        self.obs_size, self.action_size = obs_size, action_size
        self.target_entropy = -float(action_size)
        self.actor_net = TanhGaussianActor(action_size, cfg.hidden_dim, cfg.hidden_depth,
                                           cfg.log_std_min, cfg.log_std_max)
        self.critic_net = DoubleQCritic(cfg.hidden_dim, cfg.hidden_depth)
        adam = lambda lr: optax.adam(lr, b1=cfg.adam_b1, b2=cfg.adam_b2, eps=1e-8)  # torch eps
        self.actor_tx = adam(cfg.lr)
        self.critic_tx = adam(cfg.lr)
        self.alpha_tx = adam(cfg.alpha_lr)

    # -- init -----------------------------------------------------------------------------
    def init_critic(self, key: jax.Array):
        obs = jnp.zeros((1, self.obs_size))
        act = jnp.zeros((1, self.action_size))
        critic = self.critic_net.init(key, obs, act)
        return critic, self.critic_tx.init(critic)

    def init(self, key: jax.Array) -> SACState:
        k_actor, k_critic = jax.random.split(key)
        actor = self.actor_net.init(k_actor, jnp.zeros((1, self.obs_size)))
        critic, critic_opt = self.init_critic(k_critic)
        log_alpha = jnp.asarray(jnp.log(self.cfg.init_temperature), jnp.float32)
        return SACState(actor=actor, critic=critic, critic_target=critic, log_alpha=log_alpha,
                        actor_opt=self.actor_tx.init(actor), critic_opt=critic_opt,
                        alpha_opt=self.alpha_tx.init(log_alpha))

    def reset_critic(self, state: SACState, key: jax.Array) -> SACState:
        """PEBBLE's critic reset after pre-training: new critic, target copied, fresh Adam;
        actor, temperature and their optimizers are kept."""
        critic, critic_opt = self.init_critic(key)
        return state.replace(critic=critic, critic_target=critic, critic_opt=critic_opt)

    # -- acting ---------------------------------------------------------------------------
    def act(self, actor_params, obs: jax.Array, key: jax.Array, deterministic: bool = False):
        mu, log_std = self.actor_net.apply(actor_params, obs)
        if deterministic:
            return jnp.tanh(mu)
        action, _ = squashed_gaussian_sample(key, mu, log_std)
        return jnp.clip(action, -1.0, 1.0)

    def _sample(self, actor_params, obs, key):
        mu, log_std = self.actor_net.apply(actor_params, obs)
        return squashed_gaussian_sample(key, mu, log_std)

    # -- losses ---------------------------------------------------------------------------
    def target_value(self, state: SACState, next_obs, key):
        """V'(s') = min(Q1', Q2')(s', a') - alpha * log pi(a'|s'), a' ~ pi(.|s') drawn from `key`
        (no gradient: a regression target)."""
        next_action, next_log_prob = self._sample(state.actor, next_obs, key)
        tq1, tq2 = self.critic_net.apply(state.critic_target, next_obs, next_action)
        return jax.lax.stop_gradient(
            jnp.minimum(tq1, tq2) - jnp.exp(state.log_alpha) * next_log_prob)

    def critic_loss(self, critic, state: SACState, batch: Batch, key):
        target_v = self.target_value(state, batch.next_obs, key)
        target_q = jax.lax.stop_gradient(
            batch.reward + batch.not_done * self.cfg.discount * target_v)
        q1, q2 = self.critic_net.apply(critic, batch.obs, batch.action)
        loss = jnp.mean((q1 - target_q) ** 2) + jnp.mean((q2 - target_q) ** 2)
        return loss, {"train/critic_loss": loss, "train/q": jnp.mean(q1)}

    def actor_loss(self, actor, state: SACState, obs, key):
        action, log_prob = self._sample(actor, obs, key)
        q1, q2 = self.critic_net.apply(state.critic, obs, action)
        alpha = jax.lax.stop_gradient(jnp.exp(state.log_alpha))
        loss = jnp.mean(alpha * log_prob - jnp.minimum(q1, q2))
        return loss, log_prob

    def alpha_loss(self, log_alpha, log_prob):
        return jnp.mean(jnp.exp(log_alpha)
                        * jax.lax.stop_gradient(-log_prob - self.target_entropy))

    # -- update ---------------------------------------------------------------------------
    def update(self, state: SACState, batch: Batch, key: jax.Array, global_step: jax.Array):
        """One SAC gradient step (critic, then actor and temperature, then target EMA)."""
        k_critic, k_actor = jax.random.split(key)
        grads, metrics = jax.grad(self.critic_loss, has_aux=True)(state.critic, state, batch,
                                                                  k_critic)
        updates, critic_opt = self.critic_tx.update(grads, state.critic_opt, state.critic)
        state = state.replace(critic=optax.apply_updates(state.critic, updates),
                              critic_opt=critic_opt)

        (a_loss, log_prob), a_grads = jax.value_and_grad(self.actor_loss, has_aux=True)(
            state.actor, state, batch.obs, k_actor)
        al_loss, al_grad = jax.value_and_grad(self.alpha_loss)(state.log_alpha, log_prob)
        do_actor = (global_step % self.cfg.actor_update_every) == 0
        a_updates, actor_opt = self.actor_tx.update(a_grads, state.actor_opt, state.actor)
        al_updates, alpha_opt = self.alpha_tx.update(al_grad, state.alpha_opt, state.log_alpha)
        new = state.replace(actor=optax.apply_updates(state.actor, a_updates), actor_opt=actor_opt,
                            log_alpha=optax.apply_updates(state.log_alpha, al_updates),
                            alpha_opt=alpha_opt)
        if self.cfg.actor_update_every == 1:  # BPref default: every step, no select needed
            state = new
        else:
            state = jax.tree.map(lambda n, o: jnp.where(do_actor, n, o), new, state)

        # EMA gated by a scalar weight instead of a branch (cheap, and vmap-friendly)
        tau = jnp.where(global_step % self.cfg.target_update_every == 0, self.cfg.tau, 0.0)
        target = jax.tree.map(lambda p, t: tau * p + (1 - tau) * t, state.critic,
                              state.critic_target)
        state = state.replace(critic_target=target)
        metrics.update({"train/actor_loss": a_loss, "train/alpha_loss": al_loss,
                        "train/alpha": jnp.exp(state.log_alpha),
                        "train/entropy": -jnp.mean(log_prob)})
        return state, metrics
