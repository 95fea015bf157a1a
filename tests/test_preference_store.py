"""Fixed-capacity labelled-pair store: compaction, ring wrap, no true rewards."""
import hprior_jax  # noqa: F401

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from hprior_jax.buffers import preferences as ps

T_, DS, DA = 3, 2, 1


def _batch(ids, labels):
    """Pair i carries its id in every obs entry of segment 1 and -id in segment 2."""
    ids = jnp.asarray(ids, jnp.float32)
    o = jnp.broadcast_to(ids[:, None, None], (len(ids), T_, DS))
    a = jnp.broadcast_to(ids[:, None, None], (len(ids), T_, DA))
    return ps.PreferenceBatch(obs1=o, act1=a, obs2=-o, act2=-a, labels=jnp.asarray(labels, jnp.int32))


def test_add_compacts_valid_pairs():
    st = ps.init(T_, DS, DA, capacity=10)
    assert st.capacity == 10 and int(st.count) == 0
    st = ps.add(st, _batch([1, 2, 3, 4, 5], [0, 1, -1, 1, 0]), jnp.array([True, False, True, False, True]))
    assert int(st.count) == 3 and int(st.ptr) == 3
    np.testing.assert_array_equal(st.obs1[:3, 0, 0], [1, 3, 5])
    np.testing.assert_array_equal(st.obs2[:3, 0, 0], [-1, -3, -5])
    np.testing.assert_array_equal(st.act1[:3, 0, 0], [1, 3, 5])
    np.testing.assert_array_equal(st.labels[:3], [0, -1, 0])
    np.testing.assert_array_equal(st.obs1[3:], 0)  # untouched
    np.testing.assert_array_equal(ps.valid_mask(st), [True] * 3 + [False] * 7)


def test_ring_wraps_and_count_saturates():
    st = ps.init(T_, DS, DA, capacity=5)
    st = ps.add(st, _batch([1, 2, 3, 4], [1] * 4), jnp.ones(4, bool))
    st = ps.add(st, _batch([5, 6, 7], [0] * 3), jnp.ones(3, bool))
    assert int(st.count) == 5 and int(st.ptr) == 2
    np.testing.assert_array_equal(st.obs1[:, 0, 0], [6, 7, 3, 4, 5])  # oldest (1, 2) overwritten
    np.testing.assert_array_equal(st.labels, [0, 0, 1, 1, 0])
    st = ps.add(st, _batch([8, 9], [1, 1]), jnp.zeros(2, bool))  # nothing valid: no change
    assert int(st.count) == 5 and int(st.ptr) == 2


def test_store_never_holds_true_rewards():
    names = {f.name for f in dataclasses.fields(ps.PreferenceStore)}
    assert not any("true" in n or "reward" in n for n in names), names
    assert ps.DEFAULT_CAPACITY == 500_000


def test_jit_and_vmap():
    st = jax.vmap(lambda _: ps.init(T_, DS, DA, capacity=6))(jnp.arange(2))
    b = jax.tree_util.tree_map(lambda x: jnp.stack([x, x + 10 * (x != 0)]), _batch([1, 2, 3], [0, 1, 0]))
    valid = jnp.array([[True, True, False], [False, True, True]])
    out = jax.jit(jax.vmap(ps.add))(st, b, valid)
    np.testing.assert_array_equal(out.count, [2, 2])
    np.testing.assert_array_equal(out.obs1[0, :2, 0, 0], [1, 2])
    np.testing.assert_array_equal(out.obs1[1, :2, 0, 0], [12, 13])
