"""Replay buffer as a pytree plus pure ops (BPref `replay_buffer.py`).

Capacity defaults to the number of training steps, so the buffer never wraps (as BPref);
it is a ring all the same. `true_reward` is stored for the scripted teacher and for
diagnostics only: `sample` never returns it. `physics` (only when a person labels: the
physics state behind each `obs`, to render the segments shown) is never sampled either.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from hprior_jax.agents.sac import Batch


@struct.dataclass
class ReplayState:
    obs: jax.Array  # [C, obs]
    action: jax.Array  # [C, act]
    reward: jax.Array  # [C] the reward the agent trains on (true for SAC, learned for PbRL)
    next_obs: jax.Array  # [C, obs]
    not_done: jax.Array  # [C] 0 only at true terminations (BPref not_done_no_max)
    true_reward: jax.Array  # [C] teacher/diagnostics only
    index: jax.Array  # int32[] next write position
    size: jax.Array  # int32[] number of valid transitions (<= C)
    physics: dict | None = None  # {field: [C, ...]} the state each obs was read from, or None

    @property
    def capacity(self) -> int:
        return self.reward.shape[-1]


def init(capacity: int, obs_size: int, action_size: int,
         physics: dict | None = None) -> ReplayState:
    """`physics`: {field: one state's array} to record beside each obs (None: nothing)."""
    f = jnp.float32
    columns = None if physics is None else {
        k: jnp.zeros((capacity,) + jnp.shape(v), jnp.result_type(v)) for k, v in physics.items()}
    return ReplayState(
        obs=jnp.zeros((capacity, obs_size), f), action=jnp.zeros((capacity, action_size), f),
        reward=jnp.zeros((capacity,), f), next_obs=jnp.zeros((capacity, obs_size), f),
        not_done=jnp.zeros((capacity,), f), true_reward=jnp.zeros((capacity,), f),
        index=jnp.zeros((), jnp.int32), size=jnp.zeros((), jnp.int32), physics=columns)


def add(buf: ReplayState, obs, action, reward, next_obs, not_done, true_reward,
        index=None, physics: dict | None = None) -> ReplayState:
    """Adds one transition (unbatched leaves) at `index` (default `buf.index`); `physics`
    (the state `obs` was read from) where the buffer records it."""
    i = buf.index if index is None else index
    cap = buf.capacity
    put = lambda col, x: jax.lax.dynamic_update_index_in_dim(col, jnp.asarray(x, col.dtype), i, 0)
    columns = buf.physics
    if columns is not None:
        columns = {k: put(col, physics[k]) for k, col in columns.items()}
    return buf.replace(
        obs=put(buf.obs, obs), action=put(buf.action, action), reward=put(buf.reward, reward),
        next_obs=put(buf.next_obs, next_obs), not_done=put(buf.not_done, not_done),
        true_reward=put(buf.true_reward, true_reward), physics=columns,
        index=(i + 1) % cap, size=jnp.minimum(buf.size + 1, cap))


def sample(buf: ReplayState, key: jax.Array, batch_size: int) -> Batch:
    """Uniform with replacement over the valid transitions."""
    return gather(buf, sample_indices(buf, key, batch_size))


def sample_indices(buf: ReplayState, key: jax.Array, batch_size: int) -> jax.Array:
    return jax.random.randint(key, (batch_size,), 0, jnp.maximum(buf.size, 1))


def gather(buf: ReplayState, idx: jax.Array) -> Batch:
    return Batch(obs=buf.obs[idx], action=buf.action[idx], reward=buf.reward[idx],
                 next_obs=buf.next_obs[idx], not_done=buf.not_done[idx])


def grow(buf: ReplayState, capacity: int) -> ReplayState:
    """The same buffer with room for `capacity` transitions (used when a resumed run is
    extended: BPref's buffer holds every step, so it must grow with the budget). A buffer
    that has wrapped around keeps its oldest-first order only if `index == 0`; callers check
    that on the host (`has_wrapped`)."""
    extra = capacity - buf.capacity
    if extra < 0:
        raise ValueError(f"cannot shrink a replay buffer from {buf.capacity} to {capacity}")
    if extra == 0:
        return buf
    pad = lambda x: jnp.concatenate([x, jnp.zeros((extra,) + x.shape[1:], x.dtype)])
    index = jnp.where(buf.size == buf.capacity, buf.capacity, buf.index).astype(jnp.int32)
    return buf.replace(obs=pad(buf.obs), action=pad(buf.action), reward=pad(buf.reward),
                       next_obs=pad(buf.next_obs), not_done=pad(buf.not_done),
                       true_reward=pad(buf.true_reward), index=index,
                       physics=jax.tree.map(pad, buf.physics))


def has_wrapped(buf: ReplayState) -> bool:
    """Host-side: True if a ring write has overwritten old transitions (any seed)."""
    import numpy as np

    return bool(np.any((np.asarray(buf.size) == buf.capacity) & (np.asarray(buf.index) != 0)))
