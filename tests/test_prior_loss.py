"""PRIOR's auxiliary reward loss (hprior_jax.prior.loss) as a reward term of PEBBLE's reward training."""
import hprior_jax  # noqa: F401

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hprior_jax.buffers import preferences as ps
from hprior_jax.networks import reward_ensemble as re
from hprior_jax.pbrl import preference as P
from hprior_jax.prior import loss as L
from hprior_jax.prior.loss import PairCredit
from tests.xla_opt import AS_RUNS

DS, DA, T, K = 3, 2, 6, 3
SMALL = re.RewardConfig(hidden_sizes=(16, 16))


def _simplex(rng, *shape):
    a = rng.uniform(0.05, 1.0, size=shape).astype(np.float32)
    return a / a.sum(-1, keepdims=True)


# ---------------------------------------------------------------- targets and loss
@pytest.mark.parametrize("member_alpha", [False, True])
def test_targets_redistribute_each_members_return(member_alpha):
    rng = np.random.default_rng(0)
    r = rng.normal(size=(K, 4, T)).astype(np.float32)
    alpha = _simplex(rng, *((K, 4, T) if member_alpha else (4, T)))
    tgt = np.asarray(L.prior_targets(jnp.asarray(r), jnp.asarray(alpha)))
    assert tgt.shape == (K, 4, T)
    np.testing.assert_allclose(tgt.sum(-1), r.sum(-1), rtol=1e-5, atol=1e-5)  # Σ_t target = R̂_k
    np.testing.assert_allclose(tgt, alpha * r.sum(-1, keepdims=True), rtol=1e-6)
    np.testing.assert_allclose(L.target_saturation(jnp.asarray(r), jnp.asarray(alpha)),
                               (np.abs(alpha * r.sum(-1, keepdims=True)) > 1).mean(), rtol=1e-6)


def test_clipped_targets_stay_in_the_reward_range_and_clip_may_be_traced():
    r = jnp.asarray([[[0.9, 0.9, 0.9, -0.1]]])  # R̂ = 2.6
    alpha = jnp.asarray([[0.5, 0.3, 0.2, 0.0]])  # targets 1.3, 0.78, 0.52, 0
    np.testing.assert_allclose(L.prior_targets(r, alpha), [[[1.3, 0.78, 0.52, 0.0]]], rtol=1e-6)
    np.testing.assert_allclose(L.prior_targets(r, alpha, True), [[[1.0, 0.78, 0.52, 0.0]]],
                               rtol=1e-6)
    by_flag = jax.jit(lambda c: L.prior_loss(r, alpha, clip=c)[0])
    assert by_flag(True) == pytest.approx(np.mean((np.array([0.9, 0.9, 0.9, -0.1])
                                                   - [1.0, 0.78, 0.52, 0.0]) ** 2))
    assert by_flag(False) == pytest.approx(float(L.prior_loss(r, alpha)[0]))


def test_prior_loss_matches_numpy_and_ignores_masked_segments():
    rng = np.random.default_rng(1)
    r = rng.normal(size=(K, 5, T)).astype(np.float32)
    alpha = _simplex(rng, 5, T)
    mask = np.array([True, False, True, True, False])
    total, per = L.prior_loss(jnp.asarray(r), jnp.asarray(alpha), jnp.asarray(mask))
    err = ((r - alpha * r.sum(-1, keepdims=True)) ** 2).mean(-1)  # [K, B]: mean over t
    ref = err[:, mask].mean(-1)
    np.testing.assert_allclose(per, ref, rtol=1e-5)
    np.testing.assert_allclose(total, ref.sum(), rtol=1e-5)  # Σ over members, not mean
    r2 = r.copy()
    r2[:, ~mask] = 50.0
    np.testing.assert_allclose(L.prior_loss(jnp.asarray(r2), jnp.asarray(alpha), jnp.asarray(mask))[0],
                               total, rtol=1e-6)


def test_unlabelled_prior_is_the_prior_on_each_members_pool_segments():
    """rows_of_pool: store row r holds pool segment r mod N. The term's loss on per-member
    rows (as train_reward gathers them) is Σ_k of the NumPy prior loss on member k's rewards
    of its own rows' segments, masked minibatch rows left out (--prior.unlabelled-segments)."""
    from hprior_jax.prior import unlabelled as U

    rng = np.random.default_rng(3)
    n, cap, b = 5, 12, 4
    obs = rng.normal(size=(n, T, DS)).astype(np.float32)
    act = rng.normal(size=(n, T, DA)).astype(np.float32)
    alpha = _simplex(rng, n, T)
    pool = U.rows_of_pool(jnp.asarray(obs), jnp.asarray(act), jnp.asarray(alpha), cap)
    np.testing.assert_array_equal(pool.obs, obs[np.arange(cap) % n])
    np.testing.assert_array_equal(pool.alpha, alpha[np.arange(cap) % n])
    params = re.init_reward_ensemble(jax.random.PRNGKey(0), DS, DA, SMALL)
    idx = rng.integers(0, cap, size=(K, b))
    rows = jax.tree.map(lambda x: x[idx], pool)
    mask = np.array([True, True, False, True])
    term = U.unlabelled_prior_term(2.0, pool, reward_cfg=SMALL)
    assert term.name == "prior/unlabelled_loss" and term.weight == 2.0
    got = term.loss(None, None, rows, jnp.asarray(mask), params)
    want = 0.0
    for k in range(K):
        seg = idx[k] % n
        r_k = np.asarray(re.member_rewards(params, jnp.asarray(obs[seg]), jnp.asarray(act[seg]),
                                           SMALL))[k]  # [b, T]
        err = ((r_k - alpha[seg] * r_k.sum(-1, keepdims=True)) ** 2).mean(-1)
        want += err[mask].mean()
    np.testing.assert_allclose(got, want, rtol=1e-5)


def test_pair_prior_loss_is_prior_loss_on_both_segments():
    rng = np.random.default_rng(2)
    r1, r2 = (rng.normal(size=(K, 4, T)).astype(np.float32) for _ in range(2))
    a1, a2 = _simplex(rng, 4, T), _simplex(rng, 4, T)
    mask = np.array([True, True, False, True])
    got = L.pair_prior_loss(jnp.asarray(r1), jnp.asarray(r2), jnp.asarray(a1), jnp.asarray(a2), jnp.asarray(mask))[0]
    err = lambda r, a: ((r - a * r.sum(-1, keepdims=True)) ** 2).mean(-1)[:, mask]
    ref = np.concatenate([err(r1, a1), err(r2, a2)], axis=1).mean(-1).sum()
    np.testing.assert_allclose(got, ref, rtol=1e-5)
    term = L.prior_term(7.0, None)
    value = term.loss(jnp.asarray(r1), jnp.asarray(r2), PairCredit(jnp.asarray(a1), jnp.asarray(a2)),
                      jnp.asarray(mask), None)  # the prior reads no network parameters
    np.testing.assert_allclose(value, ref, rtol=1e-5)  # the term is unweighted; λ is its weight
    assert term.weight == 7.0 and term.name == "prior/loss"


def test_prior_gradient_stops_at_alpha_and_return():
    """∂L/∂α = 0 exactly and ∂L/∂r̂_t = 2(r̂_t - target_t)/(T·N_real) with the target held fixed
    (without the stop-gradient on R̂ an extra -2Σ_t'(r̂_t' - target_t')α_t' term appears)."""
    rng = np.random.default_rng(3)
    r1, r2 = (jnp.asarray(rng.normal(size=(K, 3, T)).astype(np.float32)) for _ in range(2))
    a1, a2 = jnp.asarray(_simplex(rng, 3, T)), jnp.asarray(_simplex(rng, 3, T))
    mask = jnp.array([True, False, True])
    f = lambda r1, r2, a1, a2: L.pair_prior_loss(r1, r2, a1, a2, mask)[0]
    g_r1, g_r2, g_a1, g_a2 = jax.grad(f, argnums=(0, 1, 2, 3))(r1, r2, a1, a2)
    np.testing.assert_array_equal(g_a1, 0.0)
    np.testing.assert_array_equal(g_a2, 0.0)
    n_real = 2 * int(mask.sum())  # both segments of every real pair
    for r, a, g in ((r1, a1, g_r1), (r2, a2, g_r2)):
        r, a, g = np.asarray(r), np.asarray(a), np.asarray(g)
        want = 2 * (r - a * r.sum(-1, keepdims=True)) / (T * n_real) * np.asarray(mask)[None, :, None]
        np.testing.assert_allclose(g, want, rtol=1e-5, atol=1e-7)
    # the gradient is the regression one: Σ_t ∂L/∂r̂_t = 0 (the prior never moves the return)
    np.testing.assert_allclose(np.asarray(g_r1).sum(-1), 0.0, atol=1e-6)


# ---------------------------------------------------------------- NRP / RVAR variants
def _np_nrp(a):
    x = (a - a.min(-1, keepdims=True)) / (a.max(-1, keepdims=True) - a.min(-1, keepdims=True))
    e = np.exp(x)
    return e / e.sum(-1, keepdims=True)


def test_nrp_alpha_is_appendix_eq9():
    rng = np.random.default_rng(4)
    a = _simplex(rng, 2, 4, T)
    np.testing.assert_allclose(L.nrp_alpha(jnp.asarray(a)), _np_nrp(a), rtol=1e-5)
    peaked = np.array([0.9, 0.02, 0.02, 0.02, 0.02, 0.02], np.float32)
    out = np.asarray(L.nrp_alpha(jnp.asarray(peaked)))
    np.testing.assert_allclose(out[0] / out[1], np.e, rtol=1e-5)  # max/min ratio is e (flattening)
    np.testing.assert_allclose(L.nrp_alpha(jnp.full((3, T), 0.3)), np.full((3, T), 1 / T), rtol=1e-6)
    # masked steps: zero, and eq. 9 over the valid ones
    m = np.arange(T) < 4
    out = np.asarray(L.nrp_alpha(jnp.asarray(a), jnp.asarray(m)))
    np.testing.assert_array_equal(out[..., 4:], 0.0)
    np.testing.assert_allclose(out[..., :4], _np_nrp(a[..., :4]), rtol=1e-5)


def test_rvar_alpha_is_uniform_over_valid_steps():
    a = jnp.asarray(_simplex(np.random.default_rng(5), 4, T))
    np.testing.assert_allclose(L.rvar_alpha(a), np.full((4, T), 1 / T), rtol=1e-6)
    m = jnp.asarray(np.arange(T) < 2)
    np.testing.assert_allclose(L.rvar_alpha(a, m), np.broadcast_to([0.5, 0.5, 0, 0, 0, 0], (4, T)), rtol=1e-6)
    # RVAR target = R̂/|σ| whatever the credit
    r = jnp.asarray(np.random.default_rng(6).normal(size=(K, 4, T)).astype(np.float32))
    tgt = L.prior_targets(r, L.variant_alpha(a, "uniform"))
    np.testing.assert_allclose(tgt, np.broadcast_to(np.asarray(r).sum(-1, keepdims=True) / T, (K, 4, T)),
                               rtol=1e-5)


def test_unknown_variant_rejected():
    with pytest.raises(ValueError, match="variant"):
        L.prior_term(1.0, None, variant="nrpp")
    with pytest.raises(ValueError, match="variant"):
        L.variant_alpha(jnp.ones((2, T)), "bogus")
    L.prior_term(1000.0, None, variant="uniform")  # valid ones are accepted


# ---------------------------------------------------------------- training with the prior
CAP = 48
CFG = P.PreferenceConfig(batch_size=16, max_epochs=10, lr=3e-3)  # random labels: never 97 % accurate
TX = P.make_optimizer(CFG)


def _store(seed, n, t=T):
    rng = np.random.default_rng(seed)
    f = lambda *shape: jnp.asarray(rng.normal(size=shape).astype(np.float32))
    b = ps.PreferenceBatch(obs1=f(n, t, DS), act1=f(n, t, DA), obs2=f(n, t, DS), act2=f(n, t, DA),
                           labels=jnp.asarray(rng.integers(-1, 2, size=n), jnp.int32))
    return ps.add(ps.init(t, DS, DA, capacity=CAP), b, jnp.ones(n, bool))


def _random_credit(seed):
    rng = np.random.default_rng(seed)
    return PairCredit(alpha1=jnp.asarray(_simplex(rng, CAP, T)), alpha2=jnp.asarray(_simplex(rng, CAP, T)))


def _one_hot_credit(step):
    a = jnp.zeros((CAP, T)).at[:, step].set(1.0)
    return PairCredit(alpha1=a, alpha2=a)


_traces = {"prior": 0}


def _prior_train_counted(params, opt, store, credit, key, lam, variant="raw"):
    _traces["prior"] += 1
    return P.train_reward(params, opt, store, key, tx=TX, reward_cfg=SMALL, cfg=CFG,
                          terms=(L.prior_term(lam, credit, variant),))


# compiled as runs do: λ = 0 is PEBBLE bit for bit there (tests/xla_opt.py)
_train_prior = jax.jit(_prior_train_counted, static_argnames="variant", compiler_options=AS_RUNS)
_epoch = jax.jit(lambda p, o, s, c, k, lam, variant="raw": P.train_epoch(
    p, o, s, k, tx=TX, reward_cfg=SMALL, cfg=CFG, terms=(L.prior_term(lam, c, variant),)),
    static_argnames="variant")
_train_pebble = jax.jit(partial(P.train_reward, tx=TX, reward_cfg=SMALL, cfg=CFG),
                        compiler_options=AS_RUNS)


def test_lambda_zero_is_pebble_and_lambda_is_traced():
    st = _store(0, 40)
    p0 = re.init_reward_ensemble(jax.random.key(1), DS, DA, SMALL)
    key = jax.random.key(2)
    credit = _random_credit(3)
    p_ref, o_ref, m_ref = _train_pebble(p0, TX.init(p0), st, key)
    p_0, o_0, m_0 = _train_prior(p0, TX.init(p0), st, credit, key, jnp.float32(0.0))
    traces0 = _traces["prior"]
    for a, b in zip(jax.tree_util.tree_leaves((p_ref, o_ref)), jax.tree_util.tree_leaves((p_0, o_0))):
        np.testing.assert_array_equal(a, b)
    for k in m_ref:
        np.testing.assert_array_equal(m_ref[k], m_0[k])
    assert float(m_0["prior/loss"]) > 0.0 and int(m_0["reward/epochs"]) == CFG.max_epochs
    p_5, _, m_5 = _train_prior(p0, TX.init(p0), st, credit, key, jnp.float32(5.0))
    assert _traces["prior"] == traces0  # λ is a traced value: one program for a λ sweep
    assert float(m_5["prior/loss"]) > 0.0
    diff = max(float(jnp.abs(a - b).max()) for a, b in
               zip(jax.tree_util.tree_leaves(p_5), jax.tree_util.tree_leaves(p_ref)))
    assert diff > 1e-4  # the hook is live: λ > 0 changes the trained reward


def test_epoch_metrics_report_the_unweighted_prior_loss():
    """With all pairs in one minibatch the epoch's prior term = L_prior at the initial params
    (each member sees a permutation of the same pairs; the loss is a mean over them), logged
    without λ, and the CE part is PEBBLE's."""
    st = _store(4, 12)
    p0 = re.init_reward_ensemble(jax.random.key(5), DS, DA, SMALL)
    credit = _random_credit(6)
    lam = 3.0
    _, _, m = _epoch(p0, TX.init(p0), st, credit, jax.random.key(7), jnp.float32(lam))
    n = 12
    s1 = re.member_rewards(p0, st.obs1[:n], st.act1[:n], SMALL)
    s2 = re.member_rewards(p0, st.obs2[:n], st.act2[:n], SMALL)
    want = L.pair_prior_loss(s1, s2, credit.alpha1[:n], credit.alpha2[:n])[0]
    np.testing.assert_allclose(m["terms"]["prior/loss"], want, rtol=1e-5)
    ce = P.bt_loss_from_returns(s1.sum(-1), s2.sum(-1), st.labels[:n])[0]
    np.testing.assert_allclose(m["loss"], ce, rtol=1e-5)


def test_rvar_ignores_the_credit():
    """RVAR = PRIOR's loss with a uniform credit, whatever credit it is given."""
    st = _store(8, 20)
    p0 = re.init_reward_ensemble(jax.random.key(9), DS, DA, SMALL)
    key = jax.random.key(10)
    p_rvar, _, m_rvar = _epoch(p0, TX.init(p0), st, _random_credit(3), key, jnp.float32(2.0),
                               variant="uniform")
    p_uni, _, m_uni = _epoch(p0, TX.init(p0), st, PairCredit.uniform(CAP, T), key, jnp.float32(2.0))
    np.testing.assert_allclose(m_rvar["terms"]["prior/loss"], m_uni["terms"]["prior/loss"], rtol=1e-6)
    for a, b in zip(jax.tree_util.tree_leaves(p_rvar), jax.tree_util.tree_leaves(p_uni)):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7)
    assert float(m_rvar["terms"]["prior/loss"]) > 0.0


def test_one_hot_credit_moves_reward_onto_that_step():
    """Credit all on step 2: with λ > 0 the learned per-step rewards concentrate there
    (share of |r̂| on step 2 well above λ = 0's ~1/T). Step 2 is marked in obs[..., 0] (as the
    world model's credit follows state features); without a mark r̂(s, a) cannot tell the steps
    apart and no reward can follow the credit."""
    st = _store(11, 40)
    mark = jnp.zeros((CAP, T)).at[:, 2].set(2.0)
    st = st.replace(obs1=st.obs1.at[..., 0].set(mark), obs2=st.obs2.at[..., 0].set(mark))
    p0 = re.init_reward_ensemble(jax.random.key(12), DS, DA, SMALL)
    key = jax.random.key(13)
    credit = _one_hot_credit(2)

    def share(params):
        r = np.abs(np.asarray(re.member_rewards(params, st.obs1[:40], st.act1[:40], SMALL)))  # [K, 40, T]
        return (r[..., 2] / r.sum(-1)).mean()

    p_0, _, _ = _train_prior(p0, TX.init(p0), st, credit, key, jnp.float32(0.0))
    p_l, _, _ = _train_prior(p0, TX.init(p0), st, credit, key, jnp.float32(5.0))
    s0, sl = share(p_0), share(p_l)
    assert s0 < 0.3, s0  # measured 0.21
    assert sl > s0 + 0.25, (s0, sl)  # measured 0.65


def test_the_shifted_target_keeps_the_return_and_equals_rvar_under_uniform_credit():
    """α·(R̂ + T·c) − c: Σ_t target = R̂ for any α summing to 1; with α = 1/T it is R̂/T, the
    raw uniform target; under tanh c = 1 and a segment with R̂ < 0 still gets its
    most-credited step the highest target (the raw form gives it the lowest)."""
    r = jnp.asarray([[[-0.5, -0.4, -0.3, -0.2]]])  # R̂ = -1.4
    alpha = jnp.asarray([[0.7, 0.1, 0.1, 0.1]])
    c = L.target_shift("shifted", "tanh")
    assert c == 1.0 and L.target_shift("raw", "tanh") == 0.0
    assert L.target_shift("shifted", "sig") == 0.0  # a floor at 0: both forms coincide
    shifted = np.asarray(L.prior_targets(r, alpha, shift=c))
    raw = np.asarray(L.prior_targets(r, alpha))
    np.testing.assert_allclose(shifted.sum(-1), -1.4, rtol=1e-6)
    np.testing.assert_allclose(shifted, [[[0.7 * 2.6 - 1, 0.1 * 2.6 - 1, 0.1 * 2.6 - 1,
                                           0.1 * 2.6 - 1]]], rtol=1e-6)
    assert shifted[0, 0].argmax() == 0 and raw[0, 0].argmin() == 0
    uniform = jnp.full((1, 4), 0.25)
    np.testing.assert_allclose(L.prior_targets(r, uniform, shift=c),
                               L.prior_targets(r, uniform), atol=1e-6)
    by_shift = jax.jit(lambda s: L.prior_loss(r, alpha, shift=s)[0])  # traced, as in the lab
    assert float(by_shift(c)) == pytest.approx(float(L.prior_loss(r, alpha, shift=1.0)[0]))
    assert float(by_shift(c)) != pytest.approx(float(by_shift(0.0)))
    with pytest.raises(ValueError):
        L.target_shift("floor", "tanh")
