"""Fixed-capacity store of labelled segment pairs (BPref `RewardModel.buffer_seg1/2/label`).

A ring of `capacity` pairs (BPref: 5e5, never reset). Only pairs the teacher did not skip are
stored, written contiguously (compacted) after the last stored pair, wrapping at capacity as
BPref's `put_queries` does. Labels follow BPref: 1 = segment 2 preferred, 0 = segment 1
preferred, -1 = "equally preferable" (trained on a 0.5/0.5 target).

Only segment observations/actions and labels are kept; the teacher's true rewards never enter
this store (the reward learner must not see `true_*` quantities).

Memory: the store holds 2 x capacity x H x (ds + da) float32 (BPref's 5e5 pairs, H = 50, walker
ds + da = 30: 6 GB, per seed on device). Since it is never reset and a run can label at most
`max_feedback` pairs, capacity = max_feedback trains the same (up to the shuffle stream) at a fraction of
the memory; training cost scales with `count`, not capacity, except one O(capacity) argsort per
member per epoch.
"""
from __future__ import annotations

import flax.struct
import jax
import jax.numpy as jnp

DEFAULT_CAPACITY = 500_000  # BPref `capacity = 5e5`


@flax.struct.dataclass
class PreferenceBatch:
    """A batch of B labelled pairs: obs*[B, T, ds], act*[B, T, da], labels[B] int32 in {-1, 0, 1}."""

    obs1: jax.Array
    act1: jax.Array
    obs2: jax.Array
    act2: jax.Array
    labels: jax.Array


@flax.struct.dataclass
class PreferenceStore:
    """obs*[C, T, ds], act*[C, T, da], labels[C]; `ptr` = next write slot, `count` = valid pairs.

    The valid pairs are rows 0..count-1 (the ring fills from row 0, and once full every row is
    valid), so readers mask with `arange(C) < count`.
    """

    obs1: jax.Array
    act1: jax.Array
    obs2: jax.Array
    act2: jax.Array
    labels: jax.Array
    ptr: jax.Array
    count: jax.Array

    @property
    def capacity(self) -> int:
        return self.labels.shape[-1]

    def as_batch(self) -> PreferenceBatch:
        return PreferenceBatch(self.obs1, self.act1, self.obs2, self.act2, self.labels)


def init(segment_len: int, obs_size: int, act_size: int,
         capacity: int = DEFAULT_CAPACITY, dtype=jnp.float32) -> PreferenceStore:
    capacity = int(capacity)
    if capacity < 1:
        raise ValueError("capacity must be >= 1")
    o = jnp.zeros((capacity, segment_len, obs_size), dtype)
    a = jnp.zeros((capacity, segment_len, act_size), dtype)
    return PreferenceStore(obs1=o, act1=a, obs2=o, act2=a,
                           labels=jnp.zeros((capacity,), jnp.int32),
                           ptr=jnp.zeros((), jnp.int32), count=jnp.zeros((), jnp.int32))


def add(store: PreferenceStore, batch: PreferenceBatch, valid: jax.Array) -> PreferenceStore:
    """Append the pairs with `valid[b]` (e.g. not skipped, within the feedback budget).

    Valid pairs keep their order and are written to consecutive ring slots starting at `ptr`;
    invalid ones are dropped. Static shapes: batch size B <= capacity.
    """
    cap = store.capacity
    slot = slots(store, valid)
    n_new = valid.astype(bool).sum().astype(jnp.int32)
    put = lambda dst, src: put_rows(dst, src, slot)
    return store.replace(
        obs1=put(store.obs1, batch.obs1), act1=put(store.act1, batch.act1),
        obs2=put(store.obs2, batch.obs2), act2=put(store.act2, batch.act2),
        labels=put(store.labels, batch.labels),
        ptr=(store.ptr + n_new) % cap,
        count=jnp.minimum(store.count + n_new, cap),
    )


def slots(store: PreferenceStore, valid: jax.Array) -> jax.Array:
    """[B] int32: the rows `add` writes the valid pairs to (capacity = dropped), so that data
    kept beside the store (e.g. a credit per pair) can be written to the same rows."""
    cap = store.capacity
    b = valid.shape[0]
    if b > cap:
        raise ValueError(f"batch of {b} pairs exceeds the store capacity {cap}; raise capacity")
    valid = valid.astype(bool)
    rank = jnp.cumsum(valid.astype(jnp.int32)) - 1  # position among the valid pairs
    return jnp.where(valid, (store.ptr + rank) % cap, cap)  # cap = out of bounds -> dropped


def put_rows(dst: jax.Array, src: jax.Array, slot: jax.Array) -> jax.Array:
    return dst.at[slot].set(src.astype(dst.dtype), mode="drop")


def valid_mask(store: PreferenceStore) -> jax.Array:
    """[C] bool, True on stored pairs."""
    return jnp.arange(store.capacity) < store.count
