"""BISIM's auxiliary reward loss (hprior_jax.pbrl.bisim, appendix G.2 eq. 8) and the reward
ensemble's next-embedding head (hprior_jax.networks.reward_ensemble)."""
import hprior_jax  # noqa: F401

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hprior_jax.buffers import preferences as ps
from hprior_jax.buffers import replay
from hprior_jax.networks import reward_ensemble as re
from hprior_jax.pbrl import bisim as B
from hprior_jax.pbrl import preference as P

DS, DA, K, EP = 3, 2, 2, 5
CFG = re.RewardConfig(hidden_sizes=(8, 8), ensemble_size=K, next_embedding_head=True)
PLAIN = re.RewardConfig(hidden_sizes=(8, 8), ensemble_size=K)
GAMMA = 0.9


def _np(tree):
    return jax.tree.map(lambda x: np.asarray(x, np.float64), tree)


def _np_forward(d, k, obs, act):
    """Member k in float64 from the param arrays: (r̂, z, ẑ') for x = [obs, act]."""
    x = np.concatenate([obs, act], -1).astype(np.float64)
    for i in range(2):
        x = x @ d[f"Dense_{i}"]["kernel"][k] + d[f"Dense_{i}"]["bias"][k]
        x = np.where(x > 0, x, 0.01 * x)
    r = np.tanh(x @ d["Dense_2"]["kernel"][k] + d["Dense_2"]["bias"][k])[..., 0]
    zn = x @ d["next_embedding"]["kernel"][k] + d["next_embedding"]["bias"][k]
    return r, x, zn


def _np_bisim(params, rows, mask, gamma):
    """Eq. 8 + the transition loss, per member, in float64. rows leaves [K, b, m, ...]."""
    d = _np(params["params"])
    bis, tra = [], []
    for k in range(K):
        r, z, zn = _np_forward(d, k, np.asarray(rows.obs[k]), np.asarray(rows.act[k]))
        _, z_next, _ = _np_forward(d, k, np.asarray(rows.next_obs[k]), np.asarray(rows.next_act[k]))
        r, z, zn, z_next = r.reshape(-1), z.reshape(-1, 8), zn.reshape(-1, 8), z_next.reshape(-1, 8)
        w = (np.asarray(mask)[:, None] & np.asarray(rows.valid[k])).reshape(-1).astype(np.float64)
        j = (np.arange(len(r)) + 1) % len(r)  # partner: the next transition (cyclic)
        res = (np.abs(z - z[j]).sum(-1) - np.abs(r - r[j])
               - gamma * np.sqrt(((zn - zn[j]) ** 2).sum(-1))) ** 2
        wp = w * w[j]
        bis.append((res * wp).sum() / wp.sum())
        tra.append((((zn - z_next) ** 2).mean(-1) * w).sum() / w.sum())
    return np.array(bis), np.array(tra)


def _rows(seed, b=3, m=4):
    rng = np.random.default_rng(seed)
    f = lambda *s: jnp.asarray(rng.normal(size=s).astype(np.float32))
    valid = jnp.asarray(rng.uniform(size=(K, b, m)) > 0.2)
    return B.BisimTransitions(obs=f(K, b, m, DS), act=f(K, b, m, DA), next_obs=f(K, b, m, DS),
                              next_act=f(K, b, m, DA), valid=valid)


MASK = jnp.array([True, True, False])
_loss = jax.jit(partial(B.bisim_loss, reward_cfg=CFG, discount=GAMMA))


# ---------------------------------------------------------------- the head in the ensemble
def _old_init(key, obs_size, act_size, cfg):
    """The ensemble's init before the head existed (one uniform draw over flax's leaves)."""
    shapes = jax.eval_shape(re.RewardNet(cfg).init, jax.random.key(0),
                            jnp.zeros((1, obs_size + act_size)))
    leaves, treedef = jax.tree_util.tree_flatten_with_path(shapes)
    sizes = [cfg.ensemble_size * int(np.prod(leaf.shape)) for _, leaf in leaves]
    u = jax.random.uniform(key, (sum(sizes),), jnp.float32, -1.0, 1.0)
    fan = {p[-2].key: leaf.shape[0] for p, leaf in leaves if p[-1].key == "kernel"}
    out, off = [], 0
    for (p, leaf), n in zip(leaves, sizes):
        bound = 1 / np.sqrt(fan[p[-2].key])
        out.append(bound * u[off:off + n].reshape((cfg.ensemble_size,) + leaf.shape))
        off += n
    return jax.tree_util.tree_unflatten(treedef, out)


def test_head_off_params_unchanged_and_head_on_keeps_rewards():
    key = jax.random.key(11)
    plain = re.init_reward_ensemble(key, DS, DA, PLAIN)
    old = _old_init(key, DS, DA, PLAIN)
    assert jax.tree.structure(plain) == jax.tree.structure(old)
    for a, b in zip(jax.tree.leaves(plain), jax.tree.leaves(old)):
        np.testing.assert_array_equal(a, b)
    assert re.NEXT_EMBEDDING not in plain["params"]

    head = re.init_reward_ensemble(key, DS, DA, CFG)
    assert set(head["params"]) == set(plain["params"]) | {"next_embedding"}
    for name in plain["params"]:  # the head does not shift the reward layers' draws
        for leaf in ("kernel", "bias"):
            np.testing.assert_array_equal(head["params"][name][leaf], plain["params"][name][leaf])
    hk, hb = head["params"]["next_embedding"]["kernel"], head["params"]["next_embedding"]["bias"]
    assert hk.shape == (K, 8, 8) and hb.shape == (K, 8)
    bound = 1 / np.sqrt(8)  # PyTorch default init, fan_in = the last hidden width
    assert np.abs(hk).max() <= bound + 1e-7 and np.abs(hk).max() > 0.7 * bound
    assert np.abs(hb).max() <= bound + 1e-7
    assert not np.allclose(hk[0], hk[1])

    rng = np.random.default_rng(0)
    obs = jnp.asarray(rng.normal(size=(4, 6, DS)), jnp.float32)
    act = jnp.asarray(rng.normal(size=(4, 6, DA)), jnp.float32)
    np.testing.assert_array_equal(re.mean_reward(head, obs, act, CFG),
                                  re.mean_reward(plain, obs, act, PLAIN))
    np.testing.assert_array_equal(re.member_rewards(head, obs, act, CFG),
                                  re.member_rewards(plain, obs, act, PLAIN))
    r, z, zn = re.member_embeddings(head, obs, act, CFG)
    assert r.shape == (K, 4, 6) and z.shape == zn.shape == (K, 4, 6, 8)
    np.testing.assert_array_equal(r, re.member_rewards(plain, obs, act, PLAIN))
    d = _np(head["params"])
    for k in range(K):
        want = _np_forward(d, k, np.asarray(obs), np.asarray(act))
        for got, w in zip((r[k], z[k], zn[k]), want):
            np.testing.assert_allclose(got, w, rtol=1e-5, atol=1e-6)
    # per-member inputs: member k on its own rows
    obs_k = jnp.stack([obs, obs[::-1]])
    act_k = jnp.stack([act, act[::-1]])
    rk, zk, znk = re.per_member_embeddings(head, obs_k, act_k, CFG)
    np.testing.assert_allclose(zk[1], re.member_embeddings(head, obs[::-1], act[::-1], CFG)[1][1],
                               rtol=1e-6)
    np.testing.assert_allclose(rk, re.per_member_rewards(head, obs_k, act_k, CFG), rtol=1e-6)
    with pytest.raises(ValueError):
        re.member_embeddings(plain, obs, act, PLAIN)
    with pytest.raises(ValueError):
        B.bisim_term(1.0, None, reward_cfg=PLAIN, discount=GAMMA)


# ---------------------------------------------------------------- eq. 8
def test_bisim_loss_matches_numpy_eq8():
    params = re.init_reward_ensemble(jax.random.key(1), DS, DA, CFG)
    rows = _rows(2)
    loss, aux = _loss(params, rows, MASK)
    bis, tra = _np_bisim(params, rows, MASK, GAMMA)
    np.testing.assert_allclose(aux["bisimulation"], bis, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(aux["transition"], tra, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(loss, (bis + tra).sum(), rtol=1e-5)
    assert aux["bisimulation"].shape == aux["transition"].shape == (K,) and np.all(bis > 0)
    # masked rows and invalid transitions do not count: changing them changes nothing
    junk = rows.replace(obs=rows.obs.at[:, 2].set(100.0), next_obs=rows.next_obs.at[:, 2].add(7.0))
    junk = junk.replace(obs=jnp.where(rows.valid[..., None], junk.obs, -50.0))
    np.testing.assert_allclose(_loss(params, junk, MASK)[0], loss, rtol=1e-6)


def _parts(params, rows, mask, gamma=GAMMA):
    _, aux = B.bisim_loss(params, rows, mask, reward_cfg=CFG, discount=gamma)
    return aux


def _manual_bisim(params, rows, mask, stop):
    """Eq. 8 residual, per member mean, written independently; `stop` = detach the target."""
    obs = rows.obs.reshape(K, -1, DS)
    act = rows.act.reshape(K, -1, DA)
    r, z, zn = re.per_member_embeddings(params, obs, act, CFG)
    sg = jax.lax.stop_gradient if stop else (lambda x: x)
    zj, rj, znj = (jnp.concatenate([x[:, 1:], x[:, :1]], axis=1) for x in (z, r, zn))
    w = (mask[None, :, None] & rows.valid).reshape(K, -1).astype(jnp.float32)
    wp = w * jnp.concatenate([w[:, 1:], w[:, :1]], axis=1)
    target = jnp.abs(r - rj) + GAMMA * jnp.sqrt(jnp.sum((zn - znj) ** 2, -1) + 1e-30)
    res = (jnp.abs(z - zj).sum(-1) - sg(target)) ** 2
    return ((res * wp).sum(-1) / wp.sum(-1)).sum()


def _manual_transition(params, rows, mask):
    r, z, zn = re.per_member_embeddings(params, rows.obs, rows.act, CFG)
    _, z_next, _ = re.per_member_embeddings(params, rows.next_obs, rows.next_act, CFG)
    w = (mask[None, :, None] & rows.valid).astype(jnp.float32)
    t = jnp.mean((zn - jax.lax.stop_gradient(z_next)) ** 2, -1)
    return ((t * w).sum((1, 2)) / w.sum((1, 2))).sum()


def test_gradients_reach_the_layers_and_stop_at_the_target():
    params = re.init_reward_ensemble(jax.random.key(3), DS, DA, CFG)
    rows = _rows(4)
    g = jax.grad(lambda p: B.bisim_loss(p, rows, MASK, reward_cfg=CFG, discount=GAMMA)[0])(params)
    g = g["params"]
    for name in ("Dense_0", "Dense_1", "next_embedding"):
        for leaf in ("kernel", "bias"):
            assert np.abs(np.asarray(g[name][leaf])).max() > 1e-6, (name, leaf)
            per_member = np.abs(np.asarray(g[name][leaf])).reshape(K, -1).max(-1)
            assert np.all(per_member > 0)  # every member
    # The final Dense(1) only enters through r, which is in the stopped target: no gradient.
    for leaf in ("kernel", "bias"):
        np.testing.assert_array_equal(g["Dense_2"][leaf], 0.0)

    # The bisim part: gradient = the manual eq. 8 with a detached target, not with a live one.
    gb = jax.grad(lambda p: _parts(p, rows, MASK)["bisimulation"].sum())(params)
    g_stop = jax.grad(_manual_bisim)(params, rows, MASK, True)
    g_live = jax.grad(_manual_bisim)(params, rows, MASK, False)
    for a, b in zip(jax.tree.leaves(gb), jax.tree.leaves(g_stop)):
        np.testing.assert_allclose(a, b, rtol=2e-4, atol=1e-6)
    live_diff = max(float(jnp.abs(a - b).max()) for a, b in
                    zip(jax.tree.leaves(gb["params"]["Dense_1"]),
                        jax.tree.leaves(g_live["params"]["Dense_1"])))
    assert live_diff > 1e-4  # the stop matters: a live target moves the hidden layers otherwise
    np.testing.assert_array_equal(gb["params"]["next_embedding"]["kernel"], 0.0)
    np.testing.assert_array_equal(gb["params"]["next_embedding"]["bias"], 0.0)

    # The whole gradient = detached eq. 8 + the transition loss with a detached next embedding;
    # the head's is the transition loss's alone ...
    g_all = jax.grad(lambda p: _manual_bisim(p, rows, MASK, True)
                     + _manual_transition(p, rows, MASK))(params)
    for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(g_all["params"])):
        np.testing.assert_allclose(a, b, rtol=2e-4, atol=1e-6)
    gt = jax.grad(_manual_transition)(params, rows, MASK)["params"]["next_embedding"]
    for leaf in ("kernel", "bias"):
        np.testing.assert_allclose(g["next_embedding"][leaf], gt[leaf], rtol=1e-4, atol=1e-7)
    # ... although the head does change eq. 8's value (through the stopped target).
    moved = jax.tree.map(lambda x: x, params)
    moved["params"]["next_embedding"] = jax.tree.map(lambda x: 3.0 * x,
                                                     params["params"]["next_embedding"])
    change = jnp.abs(_parts(moved, rows, MASK)["bisimulation"] - _parts(params, rows, MASK)["bisimulation"])
    assert float(change.max()) > 1e-4


def test_identical_transitions_give_finite_gradients():
    """‖ẑ'_i − ẑ'_j‖_2 at 0 (sqrt at 0) sits in the stopped target: no NaN."""
    params = re.init_reward_ensemble(jax.random.key(5), DS, DA, CFG)
    rows = _rows(6)
    same = jax.tree.map(lambda x: jnp.broadcast_to(x[:, :1, :1], x.shape), rows)
    g = jax.grad(lambda p: _loss(p, same, MASK)[0])(params)
    assert all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree.leaves(g))


# ---------------------------------------------------------------- sampling from the buffer
def _buffer(size, capacity=40, seed=None):
    buf = replay.init(capacity, DS, DA)
    i = np.arange(capacity, dtype=np.float32)
    if seed is None:  # rows identifiable by their content
        obs, act = np.stack([i, i + 0.5, -i], -1), np.stack([i, -i], -1)
    else:
        rng = np.random.default_rng(seed)
        obs = rng.normal(size=(capacity, DS)).astype(np.float32)
        act = rng.uniform(-1, 1, size=(capacity, DA)).astype(np.float32)
    return buf.replace(obs=jnp.asarray(obs), action=jnp.asarray(act),
                       not_done=jnp.ones(capacity), size=jnp.int32(size), index=jnp.int32(size))


_sample = jax.jit(B.sample_transitions, static_argnums=(2, 3, 4))


def test_sample_transitions_skip_last_steps_and_pair_with_the_next_row():
    buf = _buffer(23)  # 4 whole episodes of 5 steps, 3 steps of the fifth
    tr = _sample(jax.random.key(0), buf, EP, 50, 8)
    assert tr.obs.shape == (50, 8, DS) and tr.next_act.shape == (50, 8, DA)
    assert tr.valid.shape == (50, 8)
    idx = np.asarray(tr.obs[..., 0]).astype(int)
    assert np.all(np.asarray(tr.valid))
    assert np.all((idx + 1) % EP != 0) and np.all(idx + 1 < 23)  # never an episode's last step
    np.testing.assert_array_equal(tr.next_obs[..., 0], idx + 1)
    np.testing.assert_array_equal(tr.next_obs, buf.obs[idx + 1])
    np.testing.assert_array_equal(tr.next_act, buf.action[idx + 1])
    np.testing.assert_array_equal(tr.act, buf.action[idx])
    starts = {i for i in range(22) if (i + 1) % EP}
    assert set(idx.ravel()) == starts  # every eligible step is drawn (400 draws over 18)
    counts = np.bincount(idx.ravel(), minlength=22)[sorted(starts)]
    assert counts.min() > 5  # roughly uniform (expected 22 each)

    # a true termination ends the transition there
    done = buf.replace(not_done=buf.not_done.at[7].set(0.0))
    tr = _sample(jax.random.key(1), done, EP, 50, 8)
    idx = np.asarray(tr.obs[..., 0]).astype(int)
    np.testing.assert_array_equal(tr.valid, idx != 7)
    for size in (0, 1):
        assert not np.any(np.asarray(_sample(jax.random.key(2), _buffer(size), EP, 4, 3).valid))
    assert np.all(np.asarray(_sample(jax.random.key(2), _buffer(2), EP, 4, 3).obs[..., 0]) == 0)
    with pytest.raises(ValueError):
        B.sample_transitions(jax.random.key(0), buf, 1, 4, 3)


# ---------------------------------------------------------------- as a term of train_reward
CAP, T = 16, 4
PCFG = P.PreferenceConfig(batch_size=8, max_epochs=3, lr=3e-3)
TX = P.make_optimizer(PCFG)


def _store(seed, n):
    rng = np.random.default_rng(seed)
    f = lambda *shape: jnp.asarray(rng.normal(size=shape).astype(np.float32))
    b = ps.PreferenceBatch(obs1=f(n, T, DS), act1=f(n, T, DA), obs2=f(n, T, DS), act2=f(n, T, DA),
                           labels=jnp.asarray(rng.integers(0, 2, size=n), jnp.int32))
    return ps.add(ps.init(T, DS, DA, capacity=CAP), b, jnp.ones(n, bool))


_traces = [0]


def _train_bisim(p, o, st, tr, key, lam):
    _traces[0] += 1
    return P.train_reward(p, o, st, key, tx=TX, reward_cfg=CFG, cfg=PCFG,
                          terms=(B.bisim_term(lam, tr, reward_cfg=CFG, discount=GAMMA),))


_train_bisim_jit = jax.jit(_train_bisim)
_train_plain = jax.jit(partial(P.train_reward, tx=TX, reward_cfg=CFG, cfg=PCFG))


def test_term_trains_the_head_and_lambda_zero_is_pebble():
    st = _store(0, 12)  # 12 pairs, minibatches of 8: the second one is padded
    tr = _sample(jax.random.key(1), _buffer(33, seed=2), EP, CAP, 3)
    p0 = re.init_reward_ensemble(jax.random.key(3), DS, DA, CFG)
    key = jax.random.key(4)
    p_ref, _, m_ref = _train_plain(p0, TX.init(p0), st, key)
    p_0, _, m_0 = _train_bisim_jit(p0, TX.init(p0), st, tr, key, jnp.float32(0.0))
    for a, b in zip(jax.tree.leaves(p_ref), jax.tree.leaves(p_0)):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(p_0["params"]["next_embedding"]["kernel"],
                                  p0["params"]["next_embedding"]["kernel"])
    assert int(m_0["reward/epochs"]) == PCFG.max_epochs
    assert np.isfinite(float(m_0["bisim/loss"])) and float(m_0["bisim/loss"]) > 0.0

    traces = _traces[0]
    p_1, _, m_1 = _train_bisim_jit(p0, TX.init(p0), st, tr, key, jnp.float32(1.0))
    assert _traces[0] == traces  # λ is traced: one program for a sweep
    head_move = float(jnp.abs(p_1["params"]["next_embedding"]["kernel"]
                              - p0["params"]["next_embedding"]["kernel"]).max())
    assert head_move > 1e-3  # the head trains (Adam, lr 3e-3, 6 steps)
    hidden_move = float(jnp.abs(p_1["params"]["Dense_0"]["kernel"]
                                - p_ref["params"]["Dense_0"]["kernel"]).max())
    assert hidden_move > 1e-4  # and the term moves the shared layers
    assert np.isfinite(float(m_1["bisim/loss"]))
