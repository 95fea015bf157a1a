"""Replay-buffer relabelling: every valid transition gets the ensemble mean, nothing else moves."""
import hprior_jax  # noqa: F401

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hprior_jax.networks import reward_ensemble as re
from hprior_jax.pbrl.relabel import relabel_rewards

CAP, DS, DA = 50, 3, 2
RCFG = re.RewardConfig(hidden_sizes=(8,))
SENTINEL = 123.0  # tanh outputs are in (-1, 1), so a relabelled row can never equal this


def _data(key):
    k1, k2 = jax.random.split(key)
    return jax.random.normal(k1, (CAP, DS)), jax.random.normal(k2, (CAP, DA))


@pytest.mark.parametrize("size,chunk", [(23, 8), (50, 8), (0, 8), (48, 16), (50, 64), (1, 8)])
def test_relabels_exactly_the_first_size_rows(size, chunk):
    p = re.init_reward_ensemble(jax.random.key(0), DS, DA, RCFG)
    obs, act = _data(jax.random.key(1))
    rew = jnp.full((CAP,), SENTINEL)
    out = np.asarray(jax.jit(partial(relabel_rewards, chunk_size=chunk, reward_cfg=RCFG))(
        p, obs, act, rew, jnp.asarray(size)))
    want = np.asarray(jax.jit(partial(re.mean_reward, cfg=RCFG))(p, obs, act))
    np.testing.assert_allclose(out[:size], want[:size], rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(out[size:], SENTINEL)


def test_column_rewards_and_vmap_over_seeds():
    p = re.init_reward_ensemble(jax.random.key(0), DS, DA, RCFG)
    obs, act = _data(jax.random.key(2))
    stack = lambda x: jnp.stack([x, x])
    rew = jnp.full((2, CAP, 1), SENTINEL)  # [C, 1] layout, two seeds
    sizes = jnp.asarray([7, 33])
    fn = jax.jit(jax.vmap(partial(relabel_rewards, chunk_size=10, reward_cfg=RCFG)))
    out = np.asarray(fn(jax.tree_util.tree_map(stack, p), stack(obs), stack(act), rew, sizes))
    want = np.asarray(jax.jit(partial(re.mean_reward, cfg=RCFG))(p, obs, act))
    for i, n in enumerate([7, 33]):
        np.testing.assert_allclose(out[i, :n, 0], want[:n], rtol=1e-5, atol=1e-6)
        np.testing.assert_array_equal(out[i, n:, 0], SENTINEL)
