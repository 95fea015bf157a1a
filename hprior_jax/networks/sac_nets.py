"""SAC networks as in BPref `agent/actor.py` and `agent/critic.py`."""
from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from hprior_jax.networks.mlp import MLP


class TanhGaussianActor(nn.Module):
    """Outputs (mu, log_std) of a Gaussian that is squashed by tanh (BPref DiagGaussianActor).

    log_std = tanh(raw) mapped affinely into [log_std_min, log_std_max]."""

    action_size: int
    hidden_dim: int
    depth: int
    log_std_min: float = -5.0
    log_std_max: float = 2.0

    @nn.compact
    def __call__(self, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
        out = MLP(self.hidden_dim, self.depth, 2 * self.action_size)(obs)
        mu, log_std = jnp.split(out, 2, axis=-1)
        log_std = jnp.tanh(log_std)
        log_std = self.log_std_min + 0.5 * (self.log_std_max - self.log_std_min) * (log_std + 1)
        return mu, log_std


class DoubleQCritic(nn.Module):
    """Two independent Q networks on concat(obs, action) (BPref DoubleQCritic)."""

    hidden_dim: int
    depth: int

    @nn.compact
    def __call__(self, obs: jax.Array, action: jax.Array) -> tuple[jax.Array, jax.Array]:
        x = jnp.concatenate([obs, action], axis=-1)
        q1 = MLP(self.hidden_dim, self.depth, 1, name="q1")(x)[..., 0]
        q2 = MLP(self.hidden_dim, self.depth, 1, name="q2")(x)[..., 0]
        return q1, q2


def squashed_gaussian_sample(key, mu, log_std):
    """Reparameterised tanh-Gaussian sample and its log-probability (summed over actions).

    log det of tanh uses BPref's stable form 2 (log 2 - u - softplus(-2u))."""
    std = jnp.exp(log_std)
    u = mu + std * jax.random.normal(key, mu.shape, mu.dtype)
    normal_log_prob = -0.5 * ((u - mu) / std) ** 2 - log_std - 0.5 * jnp.log(2 * jnp.pi)
    log_det = 2.0 * (jnp.log(2.0) - u - jax.nn.softplus(-2.0 * u))
    return jnp.tanh(u), jnp.sum(normal_log_prob - log_det, axis=-1)
