import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hprior_jax.agents.sac import SAC, Batch, SACConfig
from hprior_jax.networks.sac_nets import squashed_gaussian_sample

CFG = SACConfig(hidden_dim=32, hidden_depth=2, batch_size=16, lr=1e-3)


def _batch(key, n=16, obs=5, act=2):
    k = jax.random.split(key, 3)
    return Batch(obs=jax.random.normal(k[0], (n, obs)),
                 action=jax.random.uniform(k[1], (n, act), minval=-1, maxval=1),
                 reward=jax.random.normal(k[2], (n,)), next_obs=jax.random.normal(k[0], (n, obs)),
                 not_done=jnp.ones((n,)))


def test_squashed_gaussian_log_prob_matches_change_of_variables():
    mu = jnp.array([[0.3, -1.2]])
    log_std = jnp.array([[-0.5, 0.2]])
    key = jax.random.PRNGKey(0)
    a, logp = squashed_gaussian_sample(key, mu, log_std)
    u = mu + jnp.exp(log_std) * jax.random.normal(key, mu.shape)
    ref = (-0.5 * ((u - mu) / jnp.exp(log_std)) ** 2 - log_std - 0.5 * np.log(2 * np.pi)
           - jnp.log(1 - jnp.tanh(u) ** 2)).sum(-1)
    np.testing.assert_allclose(np.asarray(a), np.tanh(np.asarray(u)), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(logp), np.asarray(ref), rtol=1e-4)


def test_init_matches_bpref_conventions():
    sac = SAC(5, 2, CFG)
    st = sac.init(jax.random.PRNGKey(0))
    np.testing.assert_allclose(float(jnp.exp(st.log_alpha)), 0.1, rtol=1e-6)
    assert sac.target_entropy == -2.0
    # target starts as a copy of the critic; biases zero; orthogonal kernels (W^T W = I)
    chex_equal = jax.tree.map(lambda a, b: np.array_equal(a, b), st.critic, st.critic_target)
    assert all(jax.tree.leaves(chex_equal))
    k = st.actor["params"]["MLP_0"]["Dense_1"]["kernel"]
    np.testing.assert_allclose(np.asarray(k.T @ k), np.eye(k.shape[1]), atol=1e-5)
    assert not np.asarray(st.actor["params"]["MLP_0"]["Dense_0"]["bias"]).any()


def test_log_std_stays_in_bounds():
    sac = SAC(5, 2, CFG)
    st = sac.init(jax.random.PRNGKey(0))
    _, log_std = sac.actor_net.apply(st.actor, 1e3 * jnp.ones((1, 5)))
    assert np.all(np.asarray(log_std) >= -5.0) and np.all(np.asarray(log_std) <= 2.0)


def test_target_ema_only_on_even_steps_and_update_reduces_critic_loss():
    sac = SAC(5, 2, CFG)
    st = sac.init(jax.random.PRNGKey(0))
    batch = _batch(jax.random.PRNGKey(1))
    upd = jax.jit(sac.update)
    st1, _ = upd(st, batch, jax.random.PRNGKey(2), jnp.int32(1))  # odd: no EMA
    same = jax.tree.map(np.array_equal, st1.critic_target, st.critic_target)
    assert all(jax.tree.leaves(same))
    st2, _ = upd(st1, batch, jax.random.PRNGKey(3), jnp.int32(2))  # even: EMA with tau
    expect = jax.tree.map(lambda p, t: CFG.tau * p + (1 - CFG.tau) * t, st2.critic,
                          st1.critic_target)
    for a, b in zip(jax.tree.leaves(expect), jax.tree.leaves(st2.critic_target)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-7)
    # fitting a fixed batch: the critic loss falls over a few updates
    losses = []
    s = st
    for i in range(30):
        s, m = upd(s, batch, jax.random.PRNGKey(10 + i), jnp.int32(i))
        losses.append(float(m["train/critic_loss"]))
    assert losses[-1] < 0.5 * losses[0]


def test_not_done_zero_stops_bootstrapping():
    sac = SAC(5, 2, CFG)
    st = sac.init(jax.random.PRNGKey(0))
    b = _batch(jax.random.PRNGKey(1))._replace(not_done=jnp.zeros((16,)))
    # with not_done = 0 the target is the reward: loss equals MSE of (Q - r) for both heads
    loss, _ = sac.critic_loss(st.critic, st, b, jax.random.PRNGKey(2))
    q1, q2 = sac.critic_net.apply(st.critic, b.obs, b.action)
    ref = jnp.mean((q1 - b.reward) ** 2) + jnp.mean((q2 - b.reward) ** 2)
    np.testing.assert_allclose(float(loss), float(ref), rtol=1e-5)


def test_reset_critic_keeps_actor_and_temperature():
    sac = SAC(5, 2, CFG)
    st = sac.init(jax.random.PRNGKey(0))
    st, _ = sac.update(st, _batch(jax.random.PRNGKey(1)), jax.random.PRNGKey(2), jnp.int32(0))
    r = sac.reset_critic(st, jax.random.PRNGKey(9))
    assert all(jax.tree.leaves(jax.tree.map(np.array_equal, r.actor, st.actor)))
    assert float(r.log_alpha) == float(st.log_alpha)
    assert not all(jax.tree.leaves(jax.tree.map(np.array_equal, r.critic, st.critic)))
    assert all(jax.tree.leaves(jax.tree.map(np.array_equal, r.critic, r.critic_target)))


def test_update_vmaps_over_seeds_like_single_seed():
    sac = SAC(5, 2, CFG)
    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    states = jax.vmap(sac.init)(keys)
    batch = _batch(jax.random.PRNGKey(1))
    vm = jax.jit(jax.vmap(sac.update, in_axes=(0, None, 0, None)))
    out, _ = vm(states, batch, keys, jnp.int32(0))
    single, _ = jax.jit(sac.update)(sac.init(keys[1]), batch, keys[1], jnp.int32(0))
    for a, b in zip(jax.tree.leaves(single.actor), jax.tree.leaves(out.actor)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b[1]), rtol=1e-4, atol=1e-6)


def test_config_rejects_bad_sizes_with_the_flag_name():
    with pytest.raises(ValueError, match="--sac.hidden-dim"):
        SACConfig(hidden_dim=0)
    with pytest.raises(ValueError, match="--sac.tau"):
        SACConfig(tau=0.0)


def test_vmapped_init_keeps_every_qr_unbatched():
    """Seeds are vmapped, so a plain orthogonal init becomes batched LAPACK QR calls, which
    jaxlib splits over XLA's intra-op pool and which hung 2-seed runs on a 2-core machine
    (hprior_jax/networks/mlp.py). Every QR in the lowered program must be unbatched."""
    import re

    sac = SAC(5, 2, CFG)
    text = jax.jit(jax.vmap(sac.init)).lower(jax.random.split(jax.random.PRNGKey(0), 2)).as_text()
    qr_calls = [l for l in text.splitlines() if re.search(r"lapack_\w*(geqrf|orgqr)", l)]
    assert qr_calls, "orthogonal init no longer uses QR: update this test"
    assert all('num_batch_dims = "0"' in l for l in qr_calls), qr_calls[:2]
    w = jax.vmap(sac.init)(jax.random.split(jax.random.PRNGKey(0), 2)).critic
    kernel = jax.tree.leaves(w)[1]  # a hidden layer kernel of seed 0 and 1
    assert not np.allclose(np.asarray(kernel[0]), np.asarray(kernel[1]))
