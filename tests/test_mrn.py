"""MRN: the meta-gradient is the second-order derivative of the outer loss through the virtual
critic step; the real update is SAC's with the updated reward; the meta-step schedule (that
meta steps replace SAC steps in a run is checked in test_baselines.py)."""
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import optax

from hprior_jax import presets
from hprior_jax.agents.sac import SAC, Batch, SACConfig
from hprior_jax.buffers import preferences
from hprior_jax.runs.build import build_engine
from hprior_jax.methods.mrn import recent_pairs
from hprior_jax.methods.pebble_family import PebbleState
from hprior_jax.networks.reward_ensemble import RewardConfig, init_reward_ensemble, mean_reward
from hprior_jax.pbrl import meta_reward

OBS, ACT, B, P, T = 3, 2, 6, 4, 5
REWARD = RewardConfig(hidden_sizes=(4,), ensemble_size=2)
SMALL = dict(sac=SACConfig(hidden_dim=16, hidden_depth=1, batch_size=8), num_eval_episodes=2,
             seeds=(7,))


def _problem(dtype):
    sac = SAC(OBS, ACT, SACConfig(hidden_dim=8, hidden_depth=1, batch_size=B, lr=0.05))
    cast = lambda tree: jax.tree.map(lambda x: x.astype(dtype) if x.dtype == jnp.float32 else x, tree)
    state = cast(sac.init(jax.random.PRNGKey(0)))
    phi = cast(init_reward_ensemble(jax.random.PRNGKey(1), OBS, ACT, REWARD))
    k = jax.random.split(jax.random.PRNGKey(2), 8)
    batch = Batch(obs=jax.random.normal(k[0], (B, OBS), dtype),
                  action=jax.random.uniform(k[1], (B, ACT), dtype, -1, 1),
                  reward=jnp.zeros((B,), dtype), next_obs=jax.random.normal(k[2], (B, OBS), dtype),
                  not_done=jnp.asarray([1, 1, 0, 1, 1, 0], dtype))
    pairs = preferences.PreferenceBatch(
        obs1=jax.random.normal(k[3], (P, T, OBS), dtype),
        act1=jax.random.uniform(k[4], (P, T, ACT), dtype, -1, 1),
        obs2=jax.random.normal(k[5], (P, T, OBS), dtype),
        act2=jax.random.uniform(k[6], (P, T, ACT), dtype, -1, 1),
        labels=jnp.asarray([0, 1, 1, 0], jnp.int32))
    return sac, state, phi, batch, pairs, jnp.asarray([True, True, True, False])


def test_meta_gradient_matches_finite_differences_through_the_virtual_step():
    """float64, tiny nets: <∇_φ L_outer, v> equals the central difference of L_outer along v
    (L_outer reads φ only through the virtually updated critic θ'(φ): a second-order path)."""
    with jax.enable_x64(True):
        sac, state, phi, batch, pairs, mask = _problem(jnp.float64)
        key = jax.random.PRNGKey(3)
        f = jax.jit(lambda p: meta_reward.meta_objective(p, sac, state, batch, pairs, mask, key,
                                                         reward_cfg=REWARD, outer_weight=0.1))
        grad = jax.jit(jax.grad(f))(phi)
        v = jax.tree.map(lambda x: jax.random.normal(jax.random.PRNGKey(4), x.shape, x.dtype), phi)
        eps = 1e-6
        shift = lambda s: jax.tree.map(lambda p, d: p + s * eps * d, phi, v)
        fd = (f(shift(1.0)) - f(shift(-1.0))) / (2 * eps)
        analytic = sum(jnp.vdot(g, d) for g, d in zip(jax.tree.leaves(grad), jax.tree.leaves(v)))
        assert abs(float(fd)) > 1e-6  # the outer loss depends on φ only through θ'(φ)
        np.testing.assert_allclose(float(analytic), float(fd), rtol=1e-6)


def test_real_update_is_a_sac_update_that_reuses_the_inner_target():
    """After the meta step, the critic equals one Adam step on MSE to the inner target's value
    function (the original reuses it) with the updated reward."""
    sac, state, phi, batch, pairs, mask = _problem(jnp.float32)
    tx = optax.adam(3e-4)
    key, step = jax.random.PRNGKey(5), jnp.int32(10)
    new_state, new_phi, _, metrics = jax.jit(partial(
        meta_reward.bilevel_update, sac, reward_tx=tx, reward_cfg=REWARD, outer_weight=0.1))(
        state, phi, tx.init(phi), batch, pairs, mask, key, step)
    assert np.abs(np.asarray(jax.tree.leaves(new_phi)[0] - jax.tree.leaves(phi)[0])).max() > 0
    # the original's step 7 by hand: reward of the updated φ, target V' of the inner step
    k_critic, _ = jax.random.split(key)
    r_new = mean_reward(new_phi, batch.obs, batch.action, REWARD)
    y = jax.lax.stop_gradient(meta_reward.inner_target(sac, state, batch, r_new, k_critic))

    def critic_loss(c):
        q1, q2 = sac.critic_net.apply(c, batch.obs, batch.action)
        return jnp.mean((q1 - y) ** 2) + jnp.mean((q2 - y) ** 2)

    @jax.jit
    def by_hand(state):
        updates, _ = sac.critic_tx.update(jax.grad(critic_loss)(state.critic), state.critic_opt,
                                          state.critic)
        return optax.apply_updates(state.critic, updates)

    expected = by_hand(state)
    for a, b in zip(jax.tree.leaves(new_state.critic), jax.tree.leaves(expected)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-5, atol=1e-7)
    # and it is SAC.update with that reward (to the rounding of two compiled programs)
    plain, _ = jax.jit(sac.update)(state, batch._replace(reward=r_new), key, step)
    for a, b in zip(jax.tree.leaves(new_state), jax.tree.leaves(plain)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-7)


def test_the_meta_steps_time_limit_ends_are_the_buffers_episode_ends():
    """`time_limit_terminal` masks the rows the buffer's layout calls episode ends: row i with
    (i + 1) % L == 0, and never a row that `rows_with_next` may draw (a step with a next)."""
    from hprior_jax.buffers.episodes import episode_ends, rows_with_next

    L, capacity = 20, 200
    rows = jnp.arange(capacity)
    ends = np.asarray(episode_ends(rows, L))
    np.testing.assert_array_equal(ends, (np.arange(capacity) + 1) % L == 0)
    drawn, _ = rows_with_next(jax.random.key(0), jnp.asarray(150), L, (4096,), capacity)
    assert not ends[np.asarray(drawn)].any()
    assert set(np.flatnonzero(ends)) == set(range(L - 1, capacity, L))


def test_recent_pairs_is_a_ring_slice_ending_at_the_write_pointer():
    store = preferences.init(2, 1, 1, capacity=5)
    rows = lambda n: jnp.arange(n, dtype=jnp.int32)
    batch = lambda n, first: preferences.PreferenceBatch(
        *(jnp.full((n, 2, 1), 0.0) + (first + rows(n))[:, None, None] for _ in range(4)),
        labels=first + rows(n))
    store = preferences.add(store, batch(2, 0), jnp.ones(2, bool))  # rows 0, 1
    ms = PebbleState(reward=None, reward_opt=None, prefs=store, entropy_stats=None)
    pairs, mask = recent_pairs(ms, 3)
    assert mask.tolist() == [False, True, True] and pairs.labels[1:].tolist() == [0, 1]
    store = preferences.add(store, batch(4, 2), jnp.ones(4, bool))  # labels 2..5: wraps to row 0
    pairs, mask = recent_pairs(ms.replace(prefs=store), 3)
    assert mask.all() and pairs.labels.tolist() == [3, 4, 5]


def test_meta_steps_follow_the_original_schedule(tmp_path):
    cfg = presets.train_preset("toy_point", "mrn", "smoke", out=str(tmp_path / "m"), **SMALL)
    mrn = build_engine(cfg).method
    # rounds at 40, 80, 120, 160 (10 labels each, budget 40); a meta step every 20 steps
    # after the first round while the labels given so far are below 40: none from 160 on
    assert mrn.meta_steps() == [60, 80, 100, 120, 140]
    assert build_engine(cfg).event_steps() == [40, 60, 80, 100, 120, 140, 160]
