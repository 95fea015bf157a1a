"""PRIOR credit assignment: world-model attention -> per-step credit α (hprior_jax.prior.attention).

Hand-built attention tensors pin down credit_from_attention's indexing; a tiny world model checks
causality, the one-pass == autoregressive equivalence, pair_credit's row handling and that the
jitted credit functions compile once per shape.
"""
import hprior_jax  # noqa: F401

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hprior_jax.buffers import preferences as ps
from hprior_jax.prior import attention as A
from hprior_jax.prior import world_model as wm
from hprior_jax.prior.loss import PairCredit

DS, DA, T = 3, 2, 6
CFG = wm.WorldModelConfig(obs_size=DS, act_size=DA, latent_dim=4, obs_hidden=(32,), embed_dim=16,
                          num_heads=2, head_dim=8, num_layers=2, ff_dim=32, head_hidden=(32,),
                          segment_len=T, memory_len=T, batch_size=8)


# ---------------------------------------------------------------- hand-built attention
def _attn(t=4, layers=1, heads=1, tq=None, mem=0):
    """Zero attention [L, H, Tq, mem + 2T] (the tests fill the rows they read)."""
    tq = 2 * t if tq is None else tq
    return np.zeros((layers, heads, tq, mem + 2 * t), np.float32)


def _credit(attn, t, **kw):
    return np.asarray(A.credit_from_attention(jnp.asarray(attn), t, **kw))


def test_one_hot_state_attention_gives_one_hot_alpha():
    a = _attn(4)
    a[0, 0, 7, 4] = 1.0  # last query (a_3) looks only at s_2
    np.testing.assert_allclose(_credit(a, 4), [0, 0, 1, 0], atol=1e-7)
    a = _attn(4)
    a[0, 0, 7, 1] = 1.0  # ... only at a_0
    np.testing.assert_allclose(_credit(a, 4), [1, 0, 0, 0], atol=1e-7)


def test_state_and_action_entries_add_and_layers_heads_average():
    a = _attn(4)
    a[0, 0, 7, [2, 3, 6]] = [0.3, 0.5, 0.2]  # s_1, a_1, s_3
    np.testing.assert_allclose(_credit(a, 4), [0, 0.8, 0, 0.2], atol=1e-6)
    # mean over layers and heads: 3 of 4 (layer, head) rows on s_0, one on a_3
    a = _attn(4, layers=2, heads=2)
    a[:, :, 7, 0] = 1.0
    a[1, 1, 7, 0], a[1, 1, 7, 7] = 0.0, 1.0
    np.testing.assert_allclose(_credit(a, 4), [0.75, 0, 0, 0.25], atol=1e-6)


def test_masked_steps_get_zero_and_alpha_renormalises():
    a = _attn(4)
    # last valid step is 2 -> its action query is row 5; it (wrongly) also puts 0.2 on s_3
    a[0, 0, 5] = [0.1, 0.1, 0.1, 0.1, 0.2, 0.2, 0.2, 0.0]
    a[0, 0, 7] = [0, 0, 0, 0, 0, 0, 0, 1.0]  # row of the masked last step: must not be read
    alpha = _credit(a, 4, step_mask=jnp.array([True, True, True, False]))
    np.testing.assert_allclose(alpha, [0.25, 0.25, 0.5, 0.0], atol=1e-6)
    assert alpha[3] == 0.0
    # all steps masked: zeros, not NaN
    np.testing.assert_array_equal(_credit(a, 4, step_mask=jnp.zeros(4, bool)), np.zeros(4))


def test_without_the_own_step_alpha_renormalises_over_the_others():
    a = _attn(4)
    a[0, 0, 7] = [0.1, 0.1, 0.1, 0.1, 0.2, 0.0, 0.2, 0.2]  # 0.4 on the own step (s_3, a_3)
    np.testing.assert_allclose(_credit(a, 4, own_step=False), [1 / 3, 1 / 3, 1 / 3, 0], atol=1e-6)
    # with padding the own step is the last valid one (2, query row 5), not the last one
    a[0, 0, 5] = [0.1, 0.1, 0.1, 0.1, 0.3, 0.3, 0.0, 0.0]
    mask = jnp.array([True, True, True, False])
    np.testing.assert_allclose(_credit(a, 4, step_mask=mask, own_step=False), [0.5, 0.5, 0, 0],
                               atol=1e-6)


def test_state_vs_action_query_rows():
    a = _attn(4)
    a[0, 0, 6, 0] = 1.0  # s_3's row -> s_0
    a[0, 0, 7, 3] = 1.0  # a_3's row -> a_1
    np.testing.assert_allclose(_credit(a, 4, query="state"), [1, 0, 0, 0], atol=1e-7)
    np.testing.assert_allclose(_credit(a, 4, query="action"), [0, 1, 0, 0], atol=1e-7)
    # autoregressive layout: only the last step's 2 queries (Tq = 2) over 2T keys
    b = _attn(4, tq=2)
    b[0, 0, 0, 2] = 1.0
    b[0, 0, 1, 5] = 1.0
    np.testing.assert_allclose(_credit(b, 4, query="state"), [0, 1, 0, 0], atol=1e-7)
    np.testing.assert_allclose(_credit(b, 4, query="action"), [0, 0, 1, 0], atol=1e-7)


def test_random_causal_attention_with_memory_matches_numpy():
    """Softmax attention with 3 memory keys: α >= 0, Σα = 1, memory ignored, = NumPy reference."""
    rng = np.random.default_rng(0)
    t, mem, L, H = 5, 3, 2, 3
    tq, tk = 2 * t, mem + 2 * t
    s = rng.normal(size=(L, H, tq, tk)) * 2
    causal = (mem + np.arange(tq)[:, None]) >= np.arange(tk)[None, :]
    s = np.where(causal, s, -np.inf)
    a = np.exp(s - s.max(-1, keepdims=True))
    a = (a / a.sum(-1, keepdims=True)).astype(np.float32)
    assert a[..., -1, :mem].mean() > 0.05  # memory gets real weight, which α must drop
    for query, row in (("action", tq - 1), ("state", tq - 2)):
        alpha = _credit(a, t, query=query)
        ref = a[:, :, row, mem:].mean((0, 1)).reshape(t, 2).sum(-1)
        np.testing.assert_allclose(alpha, ref / ref.sum(), rtol=1e-5)
        assert np.all(alpha >= 0) and abs(alpha.sum() - 1) < 1e-5


def test_bad_query_and_too_few_keys_raise():
    with pytest.raises(ValueError, match="query"):
        A.credit_from_attention(jnp.zeros((1, 1, 8, 8)), 4, query="reward")
    with pytest.raises(ValueError, match="keys"):
        A.credit_from_attention(jnp.zeros((1, 1, 8, 6)), 4)


# ---------------------------------------------------------------- real (tiny) world model
def _segments(seed, b, t=T):
    rng = np.random.default_rng(seed)
    return (jnp.asarray(rng.normal(size=(b, t, DS)).astype(np.float32)),
            jnp.asarray(rng.uniform(-1, 1, size=(b, t, DA)).astype(np.float32)))


PARAMS = jax.jit(wm.init, static_argnums=1)(jax.random.key(0), CFG).params
_dynamics = jax.jit(partial(wm.dynamics, cfg=CFG))
_credit_fn = jax.jit(partial(A.segment_credit, cfg=CFG), static_argnames="query")
_ar_credit = jax.jit(partial(A.autoregressive_credit, cfg=CFG), static_argnames="query")


B = 10  # one batch size for every jitted credit call below: one compile each


def test_segment_credit_is_a_distribution():
    obs, act = _segments(1, B)
    alpha = np.asarray(_credit_fn(PARAMS, obs, act))
    assert alpha.shape == (B, T)
    assert np.all(alpha >= 0)
    np.testing.assert_allclose(alpha.sum(-1), 1.0, rtol=1e-5)
    assert np.abs(alpha - 1 / T).max() > 1e-3  # an actual (non-uniform) credit


def test_dynamics_is_causal():
    """Changing the last step's state/action leaves every earlier output and attention row alone."""
    obs, act = _segments(2, 3)
    z0, _, a0 = _dynamics(PARAMS, obs, act)
    z1, _, a1 = _dynamics(PARAMS, obs.at[:, -1].add(3.0), act)
    z2, _, a2 = _dynamics(PARAMS, obs, act.at[:, -1].add(1.5))
    a0, a1, a2 = map(np.asarray, (a0, a1, a2))
    np.testing.assert_allclose(z1[:, :-1], z0[:, :-1], atol=1e-6)
    np.testing.assert_allclose(z2[:, :-1], z0[:, :-1], atol=1e-6)
    assert np.abs(z1[:, -1] - z0[:, -1]).max() > 1e-3  # the last step does see its own input
    assert np.abs(z2[:, -1] - z0[:, -1]).max() > 1e-3
    # token rows: s_{T-1} is row 2T-2, a_{T-1} is row 2T-1
    np.testing.assert_allclose(a1[..., :2 * T - 2, :], a0[..., :2 * T - 2, :], atol=1e-6)
    np.testing.assert_allclose(a2[..., :2 * T - 1, :], a0[..., :2 * T - 1, :], atol=1e-6)
    assert np.abs(a1[..., 2 * T - 2, :] - a0[..., 2 * T - 2, :]).max() > 1e-4
    upper = np.triu(np.ones((2 * T, 2 * T), bool), k=1)
    assert np.all(a0[..., upper] == 0)  # no attention to future tokens


@pytest.mark.parametrize("query", ["action", "state"])
def test_one_pass_credit_equals_autoregressive_procedure(query):
    obs, act = _segments(3, B)
    one = np.asarray(_credit_fn(PARAMS, obs, act, query=query))
    ar = np.asarray(_ar_credit(PARAMS, obs, act, query=query))
    np.testing.assert_allclose(one, ar, rtol=1e-4, atol=1e-6)
    assert np.abs(one - 1 / T).max() > 1e-3


def test_autoregressive_credit_single_step_segment():
    """T = 1 (an empty memory): used to crash on `x[-0:]` slicing the memory."""
    obs, act = _segments(4, 2, t=1)
    np.testing.assert_allclose(_ar_credit(PARAMS, obs, act), np.ones((2, 1)))


def test_step_mask_equals_truncated_segment():
    """Padding at the end: α over the real steps = α of the segment cut to its real steps."""
    obs, act = _segments(5, B)
    mask = jnp.asarray(np.arange(T) < T - 2)
    full = np.asarray(_credit_fn(PARAMS, obs, act, step_mask=jnp.broadcast_to(mask, (B, T))))
    cut = np.asarray(_credit_fn(PARAMS, obs[:, :T - 2], act[:, :T - 2]))
    np.testing.assert_array_equal(full[:, T - 2:], 0.0)
    np.testing.assert_allclose(full[:, :T - 2], cut, rtol=1e-4, atol=1e-6)


# ---------------------------------------------------------------- pair_credit
CAP = B
SENTINEL = -1.0  # α is never negative


def _store(count):
    o1, a1 = _segments(10, CAP)
    o2, a2 = _segments(11, CAP)
    return ps.PreferenceStore(obs1=o1, act1=a1, obs2=o2, act2=a2, labels=jnp.zeros(CAP, jnp.int32),
                              ptr=jnp.asarray(count % CAP, jnp.int32), count=jnp.asarray(count, jnp.int32))


_traces = {"pair": 0}


def _pair_credit_counted(params, store, credit):
    _traces["pair"] += 1  # runs only while tracing
    return A.pair_credit(params, store, CFG, chunk=4, credit=credit)


_pair_credit = jax.jit(_pair_credit_counted)


def test_pair_credit_fills_rows_below_count_only():
    """chunk 4, capacity 10: count 9 needs an overlapping last chunk (rows 6..9, row 9 not real)."""
    sentinel = PairCredit(alpha1=jnp.full((CAP, T), SENTINEL), alpha2=jnp.full((CAP, T), SENTINEL))
    st = _store(CAP)
    want1 = np.asarray(_credit_fn(PARAMS, st.obs1, st.act1))
    want2 = np.asarray(_credit_fn(PARAMS, st.obs2, st.act2))
    assert not np.allclose(want1, want2)  # the two segments of a pair get their own α
    traces = []
    for count in (9, 3, 0, CAP):
        c = _pair_credit(PARAMS, _store(count), sentinel)
        traces.append(_traces["pair"])
        for got, want in ((c.alpha1, want1), (c.alpha2, want2)):
            got = np.asarray(got)
            np.testing.assert_allclose(got[:count], want[:count], rtol=1e-5, atol=1e-6)
            np.testing.assert_array_equal(got[count:], SENTINEL)
    assert len(set(traces)) == 1  # a new count is a new value, not a new program


# ---------------------------------------------------------------- compile once per shape
def test_segment_credit_compiles_once_per_shape():
    traces = []

    def credit(params, obs, act):
        traces.append(obs.shape)
        return A.segment_credit(params, obs, act, CFG)

    f = jax.jit(credit)
    o1, a1 = _segments(20, B)
    o2, a2 = _segments(21, B)
    params2 = jax.tree.map(lambda x: x * 1.1, PARAMS)
    r1 = f(PARAMS, o1, a1)
    r2 = f(params2, o2, a2)
    f(PARAMS, o2, a1).block_until_ready()
    assert not np.allclose(r1, r2)  # the second call really computed new values
    assert len(traces) == 1 and f._cache_size() == 1
    f.lower(PARAMS, o1[:2], a1[:2])  # a new shape is a new trace (the counter does count)
    assert len(traces) == 2
