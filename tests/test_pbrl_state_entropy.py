"""k-NN state-entropy reward and the running mean/std normaliser (BPref agent/sac.py, utils.py)."""
import hprior_jax  # noqa: F401

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hprior_jax.pbrl import state_entropy as S


def _np_knn(states, buffer, count, k):
    d = np.linalg.norm(states[:, None, :] - buffer[None, :count, :], axis=-1)
    return np.sort(d, axis=1)[:, k]  # torch.kthvalue(k + 1) = index k of the sorted row


@pytest.mark.parametrize("count,chunk", [(77, 17), (102, 17), (103, 500), (34, 34), (5, 17)])
def test_knn_matches_brute_force(count, chunk):
    rng = np.random.default_rng(count)
    cap, d, b, k = 103, 4, 9, 5
    buffer = rng.normal(size=(cap, d)).astype(np.float32)
    buffer[count:] = 0.0  # invalid rows near the batch must be ignored
    states = buffer[rng.integers(0, max(count, 1), size=b)]  # batch states are in the buffer
    got = jax.jit(partial(S.knn_distance, k=k, chunk_size=chunk))(
        jnp.asarray(states), jnp.asarray(buffer), jnp.asarray(count))
    if count >= k + 1:
        np.testing.assert_allclose(got, _np_knn(states, buffer, count, k), rtol=1e-5, atol=1e-6)
        assert np.all(np.asarray(got) > 0)
    else:
        assert np.all(np.isinf(np.asarray(got)))  # fewer than k + 1 states: undefined (BPref errors)


def test_knn_keeps_float32_accuracy_at_cheetah_scale():
    """|s|^2 - 2 s.r + |r|^2 loses digits to |s|^2: on states of cheetah's scale (positions
    ~1, velocities ~10) the distances stay within 1e-4 relative of float64 ones."""
    rng = np.random.default_rng(0)
    scale = np.r_[np.ones(8), 10 * np.ones(9)]
    buffer = (rng.normal(size=(2000, 17)) * scale).astype(np.float32)
    states = buffer[rng.integers(0, 1500, size=64)]
    got = jax.jit(partial(S.knn_distance, k=5))(jnp.asarray(states), jnp.asarray(buffer),
                                                 jnp.asarray(1500))
    want = _np_knn(states.astype(np.float64), buffer.astype(np.float64), 1500, 5)
    np.testing.assert_allclose(got, want, rtol=1e-4)


def test_knn_self_distance_is_the_first_neighbour():
    buffer = jnp.asarray([[0.0], [1.0], [3.0], [6.0], [10.0]])
    got = S.knn_distance(buffer[:2], buffer, jnp.asarray(5), k=1, chunk_size=2)
    np.testing.assert_allclose(got, [1.0, 1.0])  # k = 1 -> 2nd smallest incl. self


def _np_running(batches, bug):
    """Line-by-line port of BPref TorchRunningMeanStd (utils.py#L220-L250)."""
    mean, var, count = 0.0, 1.0, 1e-4
    for x in batches:
        bm, bv, bc = x.mean(), x.var(ddof=1), x.shape[0]
        delta = bm - mean
        tot = count + bc
        mean = mean + delta + bc / tot if bug else mean + delta * bc / tot
        m2 = var * count + bv * bc + delta ** 2 * count * bc / tot
        var, count = m2 / tot, tot
    return mean, var, count


@pytest.mark.parametrize("bug", [False, True])
def test_running_mean_std_matches_numpy(bug):
    rng = np.random.default_rng(0)
    batches = [rng.normal(3.0, 2.0, size=64).astype(np.float32) for _ in range(6)]
    upd = jax.jit(partial(S.update_running_mean_std, bpref_mean_bug=bug))
    st = S.init_running_mean_std()
    assert float(st.mean) == 0 and float(st.var) == 1 and np.isclose(float(st.count), 1e-4)
    for x in batches:
        st = upd(st, jnp.asarray(x))
    mean, var, count = _np_running(batches, bug)
    np.testing.assert_allclose([st.mean, st.var, st.count], [mean, var, count], rtol=1e-5)
    if not bug:  # the correct update tracks the data's moments
        allx = np.concatenate(batches)
        np.testing.assert_allclose(float(st.mean), allx.mean(), rtol=1e-4)
        np.testing.assert_allclose(float(st.std), allx.std(), rtol=0.02)
    else:
        # mean + delta = batch mean, so the buggy mean is the last batch's mean + bc / tot
        np.testing.assert_allclose(float(st.mean), batches[-1].mean() + 64 / (6 * 64 + 1e-4), rtol=1e-5)


def test_state_entropy_reward_normalises_by_updated_std_and_vmaps():
    rng = np.random.default_rng(1)
    buf = jnp.asarray(rng.normal(size=(2, 60, 3)).astype(np.float32))
    counts = jnp.asarray([40, 60])
    states = buf[:, :8]
    stats = jax.vmap(lambda _: S.init_running_mean_std())(jnp.arange(2))
    fn = jax.jit(jax.vmap(partial(S.state_entropy_reward, k=5, chunk_size=16)))
    r, new = fn(states, buf, counts, stats)
    for i in range(2):
        raw = _np_knn(np.asarray(states[i]), np.asarray(buf[i]), int(counts[i]), 5)
        _, var, _ = _np_running([raw], False)
        np.testing.assert_allclose(r[i], raw / np.sqrt(var), rtol=1e-4)
        np.testing.assert_allclose(new.var[i], var, rtol=1e-4)
