"""Relabel the replay buffer with the current reward model (BPref `replay_buffer.py#L70-L87`).

After every reward update PEBBLE overwrites the reward of every stored transition with the
ensemble mean r̂(s, a) (never s'). BPref does it in chunks of 200 on the GPU; here the chunk is a
static size and the loop runs ceil(size / chunk) times, so a 1M-row buffer that holds 20k
transitions costs 20k evaluations. Rows at index >= size are returned unchanged.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from hprior_jax.networks.reward_ensemble import Params, RewardConfig, mean_reward


def relabel_rewards(params: Params, obs: jax.Array, act: jax.Array, rewards: jax.Array,
                    size: jax.Array, chunk_size: int = 4096,
                    reward_cfg: RewardConfig = RewardConfig()) -> jax.Array:
    """obs[C, ds], act[C, da], rewards[C] or [C, 1] -> rewards with rows 0..size-1 = mean r̂.

    A ring buffer that has wrapped has size == C, so every row is relabelled.
    """
    cap = rewards.shape[0]
    chunk = min(int(chunk_size), cap)
    n_chunks = (size + chunk - 1) // chunk

    def body(i, rew):
        start = i * chunk
        s0 = jnp.minimum(start, cap - chunk)  # keep the slice in bounds; rows < start are done
        o = jax.lax.dynamic_slice_in_dim(obs, s0, chunk, axis=0)
        a = jax.lax.dynamic_slice_in_dim(act, s0, chunk, axis=0)
        old = jax.lax.dynamic_slice_in_dim(rew, s0, chunk, axis=0)
        new = mean_reward(params, o, a, reward_cfg).reshape(old.shape).astype(old.dtype)
        idx = s0 + jnp.arange(chunk)
        ok = ((idx >= start) & (idx < size)).reshape((chunk,) + (1,) * (old.ndim - 1))
        return jax.lax.dynamic_update_slice_in_dim(rew, jnp.where(ok, new, old), s0, axis=0)

    return jax.lax.fori_loop(0, n_chunks, body, rewards)
