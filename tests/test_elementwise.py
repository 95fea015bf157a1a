"""The world model's dropout and SiLU forms (hprior_jax.networks.elementwise)."""
import numpy as np
import pytest

import tasks  # noqa: F401  (sets XLA_FLAGS before jax is imported)
import jax
import jax.numpy as jnp

from hprior_jax.networks.elementwise import Dropout, hashed_bits, silu_tanh


def _mask(key, shape, rate=0.1, bits="hash"):
    x = jnp.ones(shape)
    y = Dropout(rate, bits).apply({}, x, False, rngs={"dropout": key})
    return np.asarray(y)


def test_silu_tanh_equals_silu_and_its_gradient_to_float32_rounding():
    """Within a few float32 ulps of max(|x|, 1): the sigmoid through tanh is exact to rounding
    in absolute terms (not relative: in the far negative tail both are ~0)."""
    x = jnp.linspace(-30.0, 30.0, 100_001)
    ulp = 2.0**-23 * np.maximum(np.abs(np.asarray(x)), 1.0)
    assert np.all(np.abs(silu_tanh(x) - jax.nn.silu(x)) <= 4 * ulp)
    g, g_ref = jax.vmap(jax.grad(silu_tanh))(x), jax.vmap(jax.grad(jax.nn.silu))(x)
    assert np.all(np.abs(g - g_ref) <= 4 * ulp)
    assert not np.allclose(silu_tanh(x), jnp.tanh(x))  # not a stand-in that passes by accident


@pytest.mark.parametrize("bits", ["hash", "key"])
def test_dropout_drops_at_its_rate_and_rescales_the_rest(bits):
    rate, shape = 0.1, (64, 4, 50, 50)  # 640,000 elements, an attention map's layout
    y = _mask(jax.random.key(0), shape, rate, bits)
    kept = y != 0
    n = kept.size
    assert abs((1 - kept.mean()) - rate) < 5 * np.sqrt(rate * (1 - rate) / n)
    np.testing.assert_allclose(y[kept], 1 / (1 - rate), rtol=1e-6)
    x = jnp.arange(12.0).reshape(3, 4)
    assert np.array_equal(Dropout(rate, bits).apply({}, x, True), x)


def _corr(a, b):
    a, b = a.astype(float).ravel(), b.astype(float).ravel()
    return np.corrcoef(a, b)[0, 1]


def test_hashed_masks_show_no_correlation_between_neighbours_keys_or_layers():
    """|Pearson| of drop indicators under 5/sqrt(n) (n = 640,000: 0.006) for neighbours along
    each axis, the same element under two keys (two layers' masks) and under keys that differ
    in one bit of their seed; a correlated hash fails these (e.g. index + key)."""
    shape = (64, 4, 50, 50)
    bound = 5 / np.sqrt(np.prod(shape))
    m = _mask(jax.random.key(1), shape) == 0
    for axis in range(4):
        a = np.take(m, np.arange(m.shape[axis] - 1), axis=axis)
        b = np.take(m, np.arange(1, m.shape[axis]), axis=axis)
        assert abs(_corr(a, b)) < 2 * bound, axis  # fewer pairs along the short axes
    k1, k2 = jax.random.split(jax.random.key(2))
    assert abs(_corr(_mask(k1, shape) == 0, _mask(k2, shape) == 0)) < bound
    near = _mask(jax.random.key(3), shape) == 0, _mask(jax.random.key(4), shape) == 0
    assert abs(_corr(*near)) < bound


def test_hashed_bits_follow_the_key_and_are_uniform():
    key = jax.random.key(5)
    a, b = hashed_bits(key, (1000, 100)), hashed_bits(key, (1000, 100))
    assert np.array_equal(a, b)
    assert not np.array_equal(a, hashed_bits(jax.random.key(6), (1000, 100)))
    counts = np.bincount(np.asarray(a).ravel() >> 28, minlength=16)  # top 4 bits: 16 bins
    expected = a.size / 16
    chi2 = ((counts - expected) ** 2 / expected).sum()
    assert chi2 < 45  # 15 degrees of freedom: P(chi2 > 45) < 1e-4 for uniform bits
    with pytest.raises(ValueError, match="2\\*\\*32"):
        hashed_bits(key, (2**16, 2**16, 2))
