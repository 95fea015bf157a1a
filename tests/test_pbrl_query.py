"""Segment-pair sampling (B-Pref layout, off-by-one kept) and query selection rules."""
import hprior_jax  # noqa: F401

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hprior_jax.networks import reward_ensemble as re
from hprior_jax.pbrl import query as Q

N_EP, L, DS, DA, H = 6, 12, 2, 1, 4
RCFG = re.RewardConfig(hidden_sizes=(16,), ensemble_size=3)


def _store():
    """obs[..., 0] = 100 * episode + t, so a segment tells where it was cut from."""
    ep = np.arange(N_EP)[:, None]
    t = np.arange(L)[None, :]
    code = (100 * ep + t).astype(np.float32)
    obs = np.stack([code, -code], -1)
    act = code[..., None] * 0.5
    true_r = code * 0.01
    return jnp.asarray(obs), jnp.asarray(act), jnp.asarray(true_r)


@pytest.mark.parametrize("include_last_step", [False, True])
def test_segments_are_contiguous_slices_from_valid_episodes(include_last_step):
    obs, act, r = _store()
    n_valid = 4
    sample = jax.jit(partial(Q.sample_segment_pairs, num_pairs=3000, segment_len=H,
                             include_last_step=include_last_step))
    pairs = sample(jax.random.key(0), obs, act, r, jnp.asarray(n_valid))
    for o, a, tr in ((pairs.obs1, pairs.act1, pairs.true_r1), (pairs.obs2, pairs.act2, pairs.true_r2)):
        code = np.asarray(o[..., 0])
        ep, start = code[:, 0] // 100, code[:, 0] % 100
        np.testing.assert_array_equal(code, (100 * ep + start)[:, None] + np.arange(H))  # contiguous
        np.testing.assert_array_equal(o[..., 1], -o[..., 0])
        np.testing.assert_allclose(a[..., 0], 0.5 * code)
        np.testing.assert_allclose(tr, 0.01 * code, rtol=1e-6)  # true reward aligned with obs
        assert set(ep.astype(int)) == set(range(n_valid))  # only valid episodes, all of them
        last = L - H - (0 if include_last_step else 1)
        # B-Pref: np.random.choice(L - H) -> starts 0..L-H-1; the episode's last step is never used
        assert start.min() == 0 and start.max() == last
    same = np.asarray(pairs.obs1[:, 0, 0] // 100 == pairs.obs2[:, 0, 0] // 100)
    assert 0.15 < same.mean() < 0.35  # with replacement: both from one episode ~1/4 of the time
    assert pairs.mask.all()
    with pytest.raises(ValueError):
        Q.sample_segment_pairs(jax.random.key(0), obs, act, r, 4, 2, segment_len=L)


def _np_probs(p, o1, a1, o2, a2):
    mr = jax.jit(partial(re.member_rewards, cfg=RCFG))
    r1 = np.asarray(mr(p, o1, a1)).sum(-1)
    r2 = np.asarray(mr(p, o2, a2)).sum(-1)
    return 1.0 / (1.0 + np.exp(r2 - r1))  # softmax([R1, R2])[0], [K, B]


@pytest.mark.parametrize("rule", ["disagreement", "entropy"])
def test_select_from_pool_picks_top_scores(rule):
    key = jax.random.key(1)
    p = re.init_reward_ensemble(key, DS, DA, RCFG)
    obs = jax.random.normal(jax.random.key(2), (N_EP, L, DS)) * 3
    act = jax.random.normal(jax.random.key(3), (N_EP, L, DA))
    pool = Q.sample_segment_pairs(jax.random.key(4), obs, act, obs[..., 0], jnp.asarray(N_EP), 60, H)
    sel = jax.jit(partial(Q.select_from_pool, rule=rule, mb_size=8, reward_cfg=RCFG))(p, pool)
    probs = _np_probs(p, pool.obs1, pool.act1, pool.obs2, pool.act2)
    if rule == "disagreement":
        score = probs.std(0)  # np.std, ddof 0 (BPref get_rank_probability)
    else:
        ent = -(probs * np.log(probs) + (1 - probs) * np.log(1 - probs))
        score = ent.mean(0)
    # identify each selected pair in the pool (segments are distinct), compare scores: near
    # p = 0.5 the entropy is flat, so float32 ties may order equal-score pairs differently
    code = np.asarray(pool.obs1[:, :, 0].sum(1) + 7 * pool.obs2[:, :, 0].sum(1))
    sel_code = np.asarray(sel.obs1[:, :, 0].sum(1) + 7 * sel.obs2[:, :, 0].sum(1))
    idx = np.array([int(np.argmin(np.abs(code - c))) for c in sel_code])
    np.testing.assert_allclose(sel.true_r2, pool.true_r2[idx], rtol=1e-6)
    np.testing.assert_allclose(score[idx], np.sort(score)[::-1][:8], rtol=1e-5, atol=1e-6)
    assert score[idx].min() > np.median(score) and np.ptp(score) > 1e-3  # informative scores


def test_disagreement_prefers_pairs_members_disagree_on():
    """Build an ensemble whose members agree except on one obs direction; the selected pairs
    must be the ones that differ along it."""
    cfg = re.RewardConfig(hidden_sizes=(1,), ensemble_size=3, hidden_activation="relu", output_activation="none")
    p = re.init_reward_ensemble(jax.random.key(0), 2, 1, cfg)
    # member k: r = relu(x0 + s_k x1), s = (-1, 0, 1): members agree on x0 and disagree on x1
    k0 = jnp.zeros((3, 3, 1)).at[:, 0, 0].set(1.0).at[:, 1, 0].set(jnp.array([-1.0, 0.0, 1.0]))
    p = {"params": {"Dense_0": {"kernel": k0, "bias": jnp.zeros((3, 1)) + 10.0},
                    "Dense_1": {"kernel": jnp.ones((3, 1, 1)), "bias": jnp.zeros((3, 1))}}}
    b, t = 40, 3
    rng = np.random.default_rng(0)
    o1 = rng.normal(size=(b, t, 2)).astype(np.float32) * 0.1
    o2 = o1.copy()
    o2[:, :, 0] += 0.05  # tiny agreed-upon difference everywhere
    hot = np.array([3, 17, 29, 33])
    o2[hot, :, 1] += 1.0  # large difference along the disputed direction
    z = np.zeros((b, t, 1), np.float32)
    pool = Q.SegmentPairs(obs1=jnp.asarray(o1), act1=jnp.asarray(z), true_r1=jnp.zeros((b, t)),
                          obs2=jnp.asarray(o2), act2=jnp.asarray(z), true_r2=jnp.zeros((b, t)),
                          mask=jnp.ones(b, bool))
    sel = Q.select_from_pool(p, pool, rule="disagreement", mb_size=4, reward_cfg=cfg)
    picked = {int(np.argmin(np.abs(o1[:, 0, 0] - v))) for v in np.asarray(sel.obs1[:, 0, 0])}
    assert picked == set(hot.tolist())


@pytest.mark.parametrize("rule", ["uniform", "disagreement", "entropy"])
def test_select_queries_jit_vmap_and_budget_mask(rule):
    p = re.init_reward_ensemble(jax.random.key(1), DS, DA, RCFG)
    obs, act, r = _store()
    fn = jax.jit(partial(Q.select_queries, rule=rule, mb_size=5, segment_len=H, large_batch=4, reward_cfg=RCFG))
    out = fn(jax.random.key(0), p, obs, act, r, jnp.asarray(3), num_queries=jnp.asarray(2))
    assert out.obs1.shape == (5, H, DS) and out.true_r1.shape == (5, H)
    np.testing.assert_array_equal(out.mask, [True, True, False, False, False])
    assert np.all(np.asarray(out.obs1[..., 0]) // 100 < 3)
    if rule != "disagreement":  # one vmap check is enough (compile time)
        return
    keys = jax.random.split(jax.random.key(5), 2)
    n_ep = jnp.asarray([2, 6])
    outv = jax.vmap(lambda k, n: fn(k, p, obs, act, r, n))(keys, n_ep)
    for i in range(2):
        oi = fn(keys[i], p, obs, act, r, n_ep[i])
        np.testing.assert_array_equal(outv.obs2[i], oi.obs2)


def test_unknown_rule_is_rejected():
    with pytest.raises(ValueError, match="rule"):
        Q.select_queries(jax.random.key(0), None, *_store(), 3, rule="kcenter", mb_size=5, segment_len=H)


def test_round_queries_are_uniform_on_the_first_round_and_the_feed_after():
    """`first` is traced: one program picks between the two rules' pairs."""
    p = re.init_reward_ensemble(jax.random.key(1), DS, DA, RCFG)
    args = (jax.random.key(3), p, *_store(), jnp.asarray(N_EP))
    kw = dict(mb_size=5, segment_len=H, large_batch=4, reward_cfg=RCFG)
    fn = jax.jit(partial(Q.round_queries, feed="disagreement", **kw))
    for first, rule in ((True, "uniform"), (False, "disagreement")):
        want = Q.select_queries(*args, rule=rule, **kw)
        got = fn(*args, first=jnp.asarray(first))
        for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
            np.testing.assert_array_equal(a, b)
    uniform = Q.round_queries(*args, first=jnp.asarray(False), feed="uniform", **kw)
    np.testing.assert_array_equal(uniform.obs1, Q.select_queries(*args, rule="uniform",
                                                                 **kw).obs1)
    assert not np.array_equal(uniform.obs1, fn(*args, first=jnp.asarray(False)).obs1)
