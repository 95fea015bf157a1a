"""B-Pref scripted teacher: every knob on constructed segments."""
import hprior_jax  # noqa: F401  (XLA flag before jax)

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hprior_jax.pbrl import teacher as T

KEY = jax.random.key(0)


def _pairs_with_diffs(diffs, t=5):
    """r1 = 0, r2 spreads `diff` evenly over the steps -> R2 - R1 = diff (for gamma = 1)."""
    diffs = np.asarray(diffs, np.float32)
    r1 = np.zeros((len(diffs), t), np.float32)
    r2 = np.repeat(diffs[:, None] / t, t, axis=1)
    return jnp.asarray(r1), jnp.asarray(r2)


def test_presets_match_bpref():
    assert (T.ORACLE.beta, T.ORACLE.gamma, T.ORACLE.eps_mistake, T.ORACLE.eps_skip, T.ORACLE.eps_equal) == (-1, 1, 0, 0, 0)
    assert T.NOISY.beta == 1 and T.PRESETS["stoch"] is T.NOISY
    assert T.MISTAKE.eps_mistake == 0.1 and T.MISTAKE.deterministic
    assert T.SKIP.eps_skip == 0.1 and T.EQUAL.eps_equal == 0.1 and T.MYOPIC.gamma == 0.9
    assert T.TeacherConfig(beta=float("inf")).deterministic and T.TeacherConfig(beta=0.0).deterministic
    assert not T.TeacherConfig(beta=1e-3).deterministic


def test_oracle_is_rational_and_tie_prefers_first():
    r1, r2 = _pairs_with_diffs([1.0, -1.0, 0.0, 1e-3, -2.5])
    out = T.teacher_labels(KEY, r1, r2, T.ORACLE)
    np.testing.assert_array_equal(out.labels, [1, 0, 0, 1, 0])  # y = 1[R1 < R2]; a tie gives 0
    assert out.valid.all() and not out.equal.any() and not out.mistake.any()


@pytest.mark.parametrize("beta", [float("inf"), 0.0, -1.0])
def test_deterministic_betas(beta):
    r1, r2 = _pairs_with_diffs([0.3, -0.3] * 50)
    out = T.teacher_labels(KEY, r1, r2, T.TeacherConfig(beta=beta))
    np.testing.assert_array_equal(out.labels, [1, 0] * 50)


@pytest.mark.parametrize("beta", [1.0, 3.0])
def test_beta_matches_bradley_terry(beta):
    diffs = np.array([-1.0, 0.0, 0.5, 2.0], np.float32)
    n = 5000
    r1, r2 = _pairs_with_diffs(np.repeat(diffs, n))
    labels = np.asarray(T.teacher_labels(KEY, r1, r2, T.TeacherConfig(beta=beta)).labels).reshape(4, n)
    freq = labels.mean(axis=1)
    p = 1.0 / (1.0 + np.exp(-beta * diffs))  # softmax([βR1, βR2])[1]
    bound = 4.5 * np.sqrt(p * (1 - p) / n) + 1e-3  # ~4.5 sigma binomial
    assert np.all(np.abs(freq - p) < bound), (freq, p)


def test_myopic_weights_match_bpref_loop():
    t, gamma = 7, 0.9
    x = np.ones((1, t))
    for index in range(t - 1):  # BPref reward_model.py get_label
        x[:, :index + 1] *= gamma
    np.testing.assert_allclose(T.myopic_weights(t, gamma), x[0], rtol=1e-6)


def test_gamma_myopia_flips_preference_towards_recent_reward():
    t = 10
    r1 = jnp.zeros((1, t)).at[0, 0].set(1.0)  # reward early
    r2 = jnp.zeros((1, t)).at[0, -1].set(0.8)  # smaller reward at the last step
    assert int(T.teacher_labels(KEY, r1, r2, T.ORACLE).labels[0]) == 0
    assert int(T.teacher_labels(KEY, r1, r2, T.MYOPIC).labels[0]) == 1  # 0.9^9 = 0.387 < 0.8


def test_skip_threshold():
    r1 = jnp.array([[1.0, 1.0], [0.1, 0.1], [-2.0, 0.0], [0.0, 0.0]])
    r2 = jnp.array([[0.0, 0.0], [0.2, 0.0], [-1.0, 0.0], [0.5, 0.5]])
    th = T.TeacherThresholds(skip=jnp.asarray(0.9), equal=jnp.asarray(0.0))
    out = T.teacher_labels(KEY, r1, r2, T.SKIP, th)
    # max(R1, R2) = 2.0, 0.2, -1.0, 1.0 -> keep > 0.9
    np.testing.assert_array_equal(out.valid, [True, False, False, True])
    # threshold 0 disables skipping, even for negative returns (BPref `if thres_skip > 0`)
    out0 = T.teacher_labels(KEY, r1, r2, T.SKIP, T.TeacherThresholds(jnp.asarray(0.0), jnp.asarray(0.0)))
    assert out0.valid.all()


def test_equal_threshold_on_undiscounted_sums():
    r1 = jnp.array([[1.0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0]])
    r2 = jnp.array([[0, 0, 0, 1.05], [0, 0, 0, 0.5], [0, 0, 0, 0.2]])
    th = T.TeacherThresholds(skip=jnp.asarray(0.0), equal=jnp.asarray(0.3))
    cfg = T.TeacherConfig(gamma=0.5, eps_equal=0.1)
    out = T.teacher_labels(KEY, r1, r2, cfg, th)
    # |R1 - R2| = 0.05, 0.5, 0.2 -> equal, not, equal (myopic sums would give 1/8 vs 1.05 for pair 0)
    np.testing.assert_array_equal(out.equal, [True, False, True])
    np.testing.assert_array_equal(out.labels, [-1, 1, -1])


def test_mistake_rate_and_flips():
    n = 20000
    diffs = np.where(np.arange(n) % 2 == 0, 1.0, -1.0)
    r1, r2 = _pairs_with_diffs(diffs)
    oracle = np.asarray(T.teacher_labels(KEY, r1, r2, T.ORACLE).labels)
    out = T.teacher_labels(KEY, r1, r2, T.MISTAKE)
    mis = np.asarray(out.mistake)
    rate = mis.mean()
    assert abs(rate - 0.1) < 4.5 * np.sqrt(0.09 / n), rate
    np.testing.assert_array_equal(np.asarray(out.labels), np.where(mis, 1 - oracle, oracle))


def test_thresholds_first_and_later_rounds():
    cfg = T.TeacherConfig(eps_skip=0.1, eps_equal=0.2)
    th1 = T.compute_thresholds(cfg, 400.0, segment_len=50, max_episode_len=1000, first_round=True)
    np.testing.assert_allclose([th1.skip, th1.equal], [0.1 * 20.0, 0.2 * 20.0], rtol=1e-6)  # margin = 20
    th2 = T.compute_thresholds(cfg, 400.0, 50, 1000, first_round=False)
    np.testing.assert_allclose([th2.skip, th2.equal], [2.0, 4.0], rtol=1e-6)  # correct: no eps^2
    bug = T.TeacherConfig(eps_skip=0.1, eps_equal=0.2, bpref_squared_eps=True)
    th3 = T.compute_thresholds(bug, 400.0, 50, 1000, first_round=False)
    np.testing.assert_allclose([th3.skip, th3.equal], [0.01 * 20.0, 0.04 * 20.0], rtol=1e-6)
    th4 = T.compute_thresholds(bug, 400.0, 50, 1000, first_round=True)
    np.testing.assert_allclose([th4.skip, th4.equal], [2.0, 4.0], rtol=1e-6)


def test_jit_and_vmap():
    cfg = T.TeacherConfig(beta=2.0, gamma=0.95, eps_mistake=0.1, eps_skip=0.1, eps_equal=0.1)
    r1 = jax.random.normal(jax.random.key(1), (3, 16, 8))
    r2 = jax.random.normal(jax.random.key(2), (3, 16, 8))
    th = T.TeacherThresholds(skip=jnp.array([0.0, 0.5, 1.0]), equal=jnp.array([0.1, 0.2, 0.3]))
    keys = jax.random.split(KEY, 3)
    f = jax.jit(lambda k, a, b, t: T.teacher_labels(k, a, b, cfg, t))
    out_v = jax.vmap(f)(keys, r1, r2, th)
    for i in range(3):
        out_i = T.teacher_labels(keys[i], r1[i], r2[i], cfg, jax.tree_util.tree_map(lambda x: x[i], th))
        for a, b in zip(jax.tree_util.tree_leaves(out_v), jax.tree_util.tree_leaves(out_i)):
            np.testing.assert_array_equal(a[i], b)
    thj = jax.jit(lambda m, f: T.compute_thresholds(cfg, m, 50, 500, f))(jnp.asarray(100.0), jnp.asarray(False))
    np.testing.assert_allclose(thj.skip, 1.0, rtol=1e-6)
