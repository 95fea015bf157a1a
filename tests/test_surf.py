"""SURF's reward update: pseudo-labels, temporal crops, the batch loss, the sampler, the loop."""
import hprior_jax  # noqa: F401

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from hprior_jax.buffers import preferences as ps
from hprior_jax.networks import reward_ensemble as re
from hprior_jax.pbrl import surf as SU

DS, DA, H, W, C = 3, 2, 12, 5, 5
S = H + 2 * W
RCFG = re.RewardConfig(hidden_sizes=(8, 8), ensemble_size=2)


# ---------------------------------------------------------------- pseudo-labels
def test_pseudo_labels_threshold_and_tie():
    r1 = jnp.array([0.0, 2.0, 0.3, 0.3])
    r2 = jnp.array([2.0, 0.0, 0.3, 0.2999])
    p = np.asarray(jax.nn.softmax(jnp.stack([r1, r2], -1), -1)).max(-1)
    thr = float(p[0])  # exactly the first pair's max probability (float32)
    labels, conf = SU.pseudo_labels(r1, r2, thr)
    np.testing.assert_array_equal(labels, [1, 0, 0, 0])  # tie -> segment 1 (index 0)
    np.testing.assert_array_equal(conf, [True, True, False, False])  # >= threshold
    just_above = float(np.nextafter(np.float32(thr), np.float32(1.0)))
    _, conf = SU.pseudo_labels(r1, r2, just_above)
    np.testing.assert_array_equal(conf, [False, False, False, False])
    just_below = float(np.nextafter(np.float32(thr), np.float32(0.0)))
    _, conf = jax.jit(SU.pseudo_labels)(r1, r2, just_below)
    np.testing.assert_array_equal(conf, [True, True, False, False])
    _, conf = SU.pseudo_labels(r1, r2, 0.5)  # a tie has max p = 0.5
    np.testing.assert_array_equal(conf, [True, True, True, True])


# ---------------------------------------------------------------- crops
def _windows(m):
    """(start, length) of each row of a 0/1 mask, asserting it is one contiguous window."""
    m = np.asarray(m)
    length = m.sum(-1).astype(int)
    start = m.argmax(-1)
    t = np.arange(m.shape[-1])
    np.testing.assert_array_equal(m, (t >= start[:, None]) & (t < (start + length)[:, None]))
    return start, length


def test_crop_masks_support_and_independence():
    n = 20000
    m1, m2 = jax.jit(partial(SU.crop_masks, num_pairs=n, stored_len=S, segment_len=H,
                             crop_range=C))(jax.random.key(0))
    assert m1.shape == m2.shape == (n, S) and m1.dtype == jnp.float32
    s1, l1 = _windows(m1)
    s2, l2 = _windows(m2)
    np.testing.assert_array_equal(l1, l2)  # one length per pair
    assert set(l1.tolist()) == set(range(H - C, H + C + 1))
    for length in range(H - C, H + C + 1):
        sel = l1 == length
        for s in (s1[sel], s2[sel]):
            assert set(s.tolist()) == set(range(S - length + 1))
    assert (s1 != s2).mean() > 0.8  # independent starts (equal w.p. ~1/11 here)
    with pytest.raises(ValueError):
        SU.crop_masks(jax.random.key(0), 4, S, H, 2 * W + 1)  # crops longer than the segment


# ---------------------------------------------------------------- batch loss vs NumPy
def _np_rewards(params, obs, act, m):
    """float64 forward of member m (leaky ReLU hidden, tanh out): [..., T]."""
    d = jax.tree_util.tree_map(lambda x: np.asarray(x, np.float64), params["params"])
    x = np.concatenate([obs, act], -1).astype(np.float64)
    n = len(RCFG.hidden_sizes)
    for i in range(n):
        x = x @ d[f"Dense_{i}"]["kernel"][m] + d[f"Dense_{i}"]["bias"][m]
        x = np.where(x > 0, x, 0.01 * x)
    return np.tanh(x @ d[f"Dense_{n}"]["kernel"][m] + d[f"Dense_{n}"]["bias"][m])[..., 0]


def _np_surf_loss(params, lab, lmask, u, umask, masks, thr, lam):
    """SURF `semi_train_soft_reward` (label_margin 0) for one iteration, looping over members."""
    m1, m2, um1, um2 = (np.asarray(m, np.float64) for m in masks)
    total, conf, n_u = 0.0, 0.0, 0.0
    for k in range(RCFG.ensemble_size):
        rows = np.asarray(lmask[k])
        r1 = (_np_rewards(params, lab.obs1[k], lab.act1[k], k) * m1[k]).sum(-1)[rows]
        r2 = (_np_rewards(params, lab.obs2[k], lab.act2[k], k) * m2[k]).sum(-1)[rows]
        labels = np.asarray(lab.labels[k])[rows]
        target = np.zeros((len(labels), 2))
        target[np.arange(len(labels)), np.maximum(labels, 0)] = 1.0
        target[labels < 0] = 0.5
        logits = np.stack([r1, r2], -1)
        logp = logits - np.log(np.exp(logits).sum(-1, keepdims=True))
        ce = -(target * logp).sum() / len(labels)

        urows = np.asarray(umask[k])
        f1 = _np_rewards(params, u[0][k], u[1][k], k)[urows]
        f2 = _np_rewards(params, u[2][k], u[3][k], k)[urows]
        mid = np.stack([f1[:, W:-W].sum(-1), f2[:, W:-W].sum(-1)], -1)
        p = np.exp(mid) / np.exp(mid).sum(-1, keepdims=True)
        plabel, confident = p.argmax(-1), p.max(-1) >= thr
        ul = np.stack([(f1 * um1[k][urows]).sum(-1), (f2 * um2[k][urows]).sum(-1)], -1)
        ulogp = ul - np.log(np.exp(ul).sum(-1, keepdims=True))
        uce = -ulogp[np.arange(len(ul)), plabel]
        total += ce + lam * np.mean(uce * confident)
        conf += confident.sum()
        n_u += len(ul)
    return total, conf / n_u


def test_surf_batch_loss_matches_numpy():
    k, b, bu = RCFG.ensemble_size, 4, 6
    params = re.init_reward_ensemble(jax.random.key(1), DS, DA, RCFG)
    rng = np.random.default_rng(0)
    f = lambda *shape: jnp.asarray(rng.normal(size=shape), jnp.float32) * 2
    lab = ps.PreferenceBatch(obs1=f(k, b, S, DS), act1=f(k, b, S, DA), obs2=f(k, b, S, DS),
                             act2=f(k, b, S, DA), labels=jnp.array([[0, 1, -1, 1], [1, -1, 0, 0]]))
    u = (f(k, bu, S, DS), f(k, bu, S, DA), f(k, bu, S, DS), f(k, bu, S, DA))
    lmask = jnp.array([True, True, True, False])  # a short labelled batch
    umask = jnp.arange(bu) < 5  # a short unlabelled batch
    key = jax.random.key(7)
    thr, lam = 0.6, 0.7
    fn = jax.jit(partial(SU.surf_batch_loss, reward_cfg=RCFG, segment_len=H, window=W,
                         crop_range=C, threshold_u=thr, lambda_u=lam))
    loss, aux = fn(params, lab, lmask, *u, umask, key)
    masks = SU.surf_crops(key, k, b, bu, S, H, C)  # the crops surf_batch_loss drew from `key`
    kmask = lambda m: np.broadcast_to(np.asarray(m), (k, m.shape[0]))
    ref, conf = _np_surf_loss(params, lab, kmask(lmask), u, kmask(umask), masks, thr, lam)
    assert 0.0 < conf < 1.0  # both confident and unconfident pairs, so the mask is exercised
    np.testing.assert_allclose(float(loss), ref, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(float(aux["confident"]), conf, rtol=1e-6)
    np.testing.assert_array_equal(aux["count"], [3, 3])
    # Fresh crops from another key change the loss (the crops are used, not the whole segment).
    others = [float(fn(params, lab, lmask, *u, umask, jax.random.key(s))[0]) for s in range(8, 12)]
    assert np.ptp(others + [ref]) > 1e-2


# ---------------------------------------------------------------- sampler and loop
def test_minibatch_rows_short_batch_then_reshuffle():
    idx, mask = jax.jit(partial(SU.minibatch_rows, capacity=8, num_iters=9, ensemble_size=3,
                                batch_size=2))(jax.random.key(3), jnp.int32(5))
    idx, mask = np.asarray(idx), np.asarray(mask)
    assert idx.shape == (9, 3, 2)
    np.testing.assert_array_equal(mask.sum(-1), [2, 2, 1] * 3)
    perms = np.array([[np.concatenate([idx[e * 3 + j, m][mask[e * 3 + j]] for j in range(3)])
                       for m in range(3)] for e in range(3)])  # [epoch, member, 5]
    np.testing.assert_array_equal(np.sort(perms, -1), np.broadcast_to(np.arange(5), (3, 3, 5)))
    assert not np.array_equal(perms[0], perms[1]) and not np.array_equal(perms[1], perms[2])
    assert len({tuple(p) for p in perms[0]}) > 1  # members have their own permutations


def _store(rng, n, capacity, labels=None, constant=False):
    def seg(d):
        x = np.zeros((capacity, S, d), np.float32) if constant else \
            rng.normal(size=(capacity, S, d)).astype(np.float32)
        return jnp.asarray(x)

    lab = np.zeros(capacity, np.int32)
    if labels is not None:
        lab[:n] = labels
    else:
        lab[:n] = rng.integers(0, 2, size=n)
    st = ps.init(S, DS, DA, capacity)
    return st.replace(obs1=seg(DS), act1=seg(DA), obs2=seg(DS), act2=seg(DA),
                      labels=jnp.asarray(lab), count=jnp.int32(n), ptr=jnp.int32(n % capacity))


TX = optax.adam(1e-2)


def _train_fn(params, opt_state, store, pool, key, num_iters):
    return SU.train_reward_surf(params, opt_state, store, pool, key, num_iters, tx=TX,
                                reward_cfg=RCFG, batch_size=2, mu=2, segment_len=H, window=W,
                                crop_range=C, threshold_u=0.6, lambda_u=1.0)


_train = jax.jit(_train_fn)


def test_no_early_stop_and_every_row_per_pass():
    """Zero reward net -> every prediction ties -> predicts segment 1: at 100% accuracy SURF
    still takes all num_iters Adam steps; with 6 iterations over 5 pairs in batches of 2
    (2, 2, 1, reshuffle, 2, 2, 1) every pair is seen exactly twice, so accuracy = share of 0s."""
    rng = np.random.default_rng(4)
    params = re.init_reward_ensemble(jax.random.key(0), DS, DA, RCFG)
    params = jax.tree_util.tree_map_with_path(
        lambda path, x: jnp.zeros_like(x) if path[-2].key == "Dense_2" else x, params)
    pool = _store(rng, 7, 8, constant=True)
    assert int(SU.surf_iterations(2, 5, 2)) == 5 and int(SU.surf_iterations(50, 100)) == 40
    for labels, acc in (([0, 0, 0, 0, 0], 1.0), ([0, 1, 0, 1, 0], 0.6)):
        store = _store(rng, 5, 8, labels=labels, constant=True)
        _, opt, m = _train(params, TX.init(params), store, pool, jax.random.key(1), jnp.int32(6))
        assert int(opt[0].count) == 6 and int(m["reward/iterations"]) == 6
        np.testing.assert_allclose(m["reward/train_acc_member"], [acc, acc], rtol=1e-6)
    # An empty labelled store changes nothing, whatever num_iters says.
    empty = _store(rng, 0, 8)
    p2, opt, m = _train(params, TX.init(params), empty, pool, jax.random.key(1), jnp.int32(6))
    assert int(opt[0].count) == 0 and int(m["reward/iterations"]) == 0
    jax.tree_util.tree_map(np.testing.assert_array_equal, p2, params)


def test_vmap_over_seeds_equals_seed_alone():
    rng = np.random.default_rng(5)
    stack = lambda xs: jax.tree_util.tree_map(lambda *a: jnp.stack(a), *xs)
    params = [re.init_reward_ensemble(jax.random.key(s), DS, DA, RCFG) for s in (10, 11)]
    stores = [_store(rng, 5, 8), _store(rng, 3, 8)]  # different label counts per seed
    pools = [_store(rng, 7, 8), _store(rng, 4, 8)]
    keys = [jax.random.key(20), jax.random.key(21)]
    iters = [SU.surf_iterations(2, s.count, 2) for s in stores]  # 5 and 3
    args = [(params[i], TX.init(params[i]), stores[i], pools[i], keys[i], iters[i])
            for i in range(2)]
    pv, ov, mv = jax.jit(jax.vmap(_train_fn))(*[stack([a[j] for a in args]) for j in range(6)])
    np.testing.assert_array_equal(mv["reward/iterations"], [5, 3])
    np.testing.assert_array_equal(ov[0].count, [5, 3])
    p0, o0, m0 = _train(*args[1])
    slot = lambda t: jax.tree_util.tree_map(lambda x: x[1], t)
    close = partial(np.testing.assert_allclose, rtol=1e-6, atol=1e-6)
    jax.tree_util.tree_map(close, p0, slot(pv))
    for name in ("reward/train_acc", "reward/loss", "surf/unlabelled_loss", "surf/confident"):
        close(m0[name], mv[name][1])
    assert float(m0["reward/loss"]) > 0
    kernel = lambda p: p["params"]["Dense_0"]["kernel"]
    assert not np.allclose(kernel(p0), kernel(params[1]))  # it trained
