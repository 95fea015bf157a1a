"""Per-dimension standardisation of the world model's observations (an ablation)."""
from __future__ import annotations

import flax.struct
import jax
import jax.numpy as jnp


@flax.struct.dataclass
class ObsScaler:
    """Per-dimension standardisation of the world model's observations, (obs - mean) / std:
    an ablation (`--prior.wm-normalize-obs`; TWM and the paper feed raw observations, whose
    velocities are of order 10 on cheetah and dominate the next-state loss)."""

    mean: jax.Array  # [ds]
    std: jax.Array  # [ds]

    def __call__(self, obs: jax.Array) -> jax.Array:
        return (obs - self.mean) / self.std


MIN_OBS_STD = 1e-2  # a constant dimension (MetaWorld's zero padding) maps to 0, not to inf


def fit_obs_scaler(obs_buf: jax.Array, size: jax.Array) -> ObsScaler:
    """Mean and std of every dimension over the valid rows 0..size-1 of obs_buf[C, ds]
    (std floored at MIN_OBS_STD)."""
    valid = (jnp.arange(obs_buf.shape[0]) < size)[:, None]
    n = jnp.maximum(size, 1).astype(jnp.float32)
    mean = jnp.where(valid, obs_buf, 0.0).sum(0) / n
    var = jnp.where(valid, (obs_buf - mean) ** 2, 0.0).sum(0) / n
    return ObsScaler(mean=mean, std=jnp.maximum(jnp.sqrt(var), MIN_OBS_STD))


def scaled(scaler: ObsScaler | None, obs: jax.Array) -> jax.Array:
    """`obs` as the world model reads it: standardised by `scaler`, or raw when None."""
    return obs if scaler is None else scaler(obs)
