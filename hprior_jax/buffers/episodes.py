"""The replay buffer's episode layout, in one place. The preference-based runs keep one env's
transitions in order from row 0, never wrapped, so episode e is rows [e·L, (e+1)·L) (the
last one possibly unfinished) and row i + 1 follows row i unless i is an episode's last step.
Segments, transitions and episode windows are read from that layout here only."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def segment_rows(key: jax.Array, size: jax.Array, *, episode_len: int, batch_size: int,
                 segment_len: int) -> jax.Array:
    """Replay rows idx[B, T] of uniform segments within episodes.

    Layout assumed (hprior_jax.buffers.replay with one env, never wrapped): rows 0..size-1 are
    valid and episode e occupies rows [e·L, (e+1)·L), the last one possibly unfinished. Starts are
    uniform over every (episode, offset) whose T steps lie inside one episode and inside the valid
    prefix, so obs[:, t+1] is the true next state of obs[:, t]. Needs size >= segment_len (the
    caller's schedule guarantees it; with fewer rows the result is meaningless).
    """
    if segment_len > episode_len:
        raise ValueError(f"segment_len={segment_len} exceeds episode_len={episode_len}")
    per_ep = episode_len - segment_len + 1
    full, rem = size // episode_len, size % episode_len
    n_valid = full * per_ep + jnp.maximum(rem - segment_len + 1, 0)
    u = jax.random.randint(key, (batch_size,), 0, jnp.maximum(n_valid, 1))
    start = (u // per_ep) * episode_len + u % per_ep
    return start[:, None] + jnp.arange(segment_len)[None, :]


def episode_ends(rows: jax.Array, episode_len: int) -> jax.Array:
    """bool[...]: whether each replay row is the last step of its episode (its time limit)."""
    return (rows + 1) % episode_len == 0


def rows_with_next(key: jax.Array, size: jax.Array, episode_len: int, shape: tuple,
                   capacity: int) -> tuple[jax.Array, jax.Array]:
    """Rows i[shape] drawn uniformly (with replacement) among the stored steps that are not
    their episode's last, so row i + 1 is the step after i; and whether any such step exists
    (with fewer than 2 stored steps, i is a placeholder kept in range)."""
    if episode_len < 2:
        raise ValueError(f"episode_len={episode_len}: a transition needs an episode of 2 steps")
    per_ep = episode_len - 1  # transitions per episode
    last = jnp.maximum(size.astype(jnp.int32) - 1, 0)  # rows 0..size-2 can start one
    n = last - last // episode_len  # of which the non-last steps: a prefix of the order below
    u = jax.random.randint(key, shape, 0, jnp.maximum(n, 1))
    i = (u // per_ep) * episode_len + u % per_ep  # the u-th non-last step, in buffer order
    return jnp.minimum(i, capacity - 2), n > 0


def last_episodes(size: jax.Array, capacity: int, episode_len: int, most: int):
    """(view, count): `view(column[C, ...])` -> the last min(most, C // L) episode slots
    [W, L, ...] ending at the last complete episode; `count` of them are complete (rows
    0..count-1 of the view)."""
    n_stored = capacity // episode_len
    window = min(most, n_stored)
    complete = size // episode_len
    start = jnp.maximum(complete - window, 0)

    def view(column):
        shaped = column[:n_stored * episode_len].reshape(
            (n_stored, episode_len) + column.shape[1:])
        return jax.lax.dynamic_slice_in_dim(shaped, start, window, axis=0)
    return view, jnp.minimum(complete, window)


def split_column(x, episode_length: int, heldout_every: int = 3):
    """One replay column's rows -> (train, held-out) episodes [E, L, ...] (`lab.dataset.split_episodes`)."""
    n = x.shape[0] // episode_length
    ep = x[: n * episode_length].reshape((n, episode_length) + x.shape[1:])
    held = np.arange(n) % heldout_every == heldout_every - 1
    return ep[~held], ep[held]
