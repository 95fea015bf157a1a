"""Dropout and SiLU in forms that XLA:CPU runs cheaply, computing what the usual forms compute.

`silu_tanh(x) = x·(½·tanh(½x) + ½)` is x·sigmoid(x) (equal to float32 rounding); XLA:CPU
vectorises tanh but lowers sigmoid to an exp and a division.

`Dropout(rate, bits="hash")` drops each element independently with probability
floor(rate·2³²)/2³² (0.1 -> 0.09999999986) and scales the kept ones by 1/(1-rate), as
`flax.linen.Dropout`; only where the random bits come from differs. Its bits are a keyed
integer hash of the element's index: the key's 64 random bits enter two rounds of the
`lowbias32` mixer (C. Wellons' hash-prospector; each round a bijection of 32 bits), so XLA
fuses the bits into the op that applies the mask instead of writing them to memory, as
RngBitGenerator and threefry do. bits="key" draws them with `jax.random.bernoulli` from the
key's own implementation (rbg or threefry), as flax does.
"""
from __future__ import annotations

from typing import Literal, get_args

import flax.linen as nn
import jax
import jax.numpy as jnp

DropoutBits = Literal["hash", "key"]
DROPOUT_BITS = get_args(DropoutBits)


def silu_tanh(x: jax.Array) -> jax.Array:
    with jax.named_scope("silu"):  # profiles (benchmarks.updates.op_profile) find it by this name
        return x * (0.5 * jnp.tanh(0.5 * x) + 0.5)


def _lowbias32(x: jax.Array) -> jax.Array:
    x = (x ^ (x >> 16)) * jnp.uint32(0x7FEB352D)
    x = (x ^ (x >> 15)) * jnp.uint32(0x846CA68B)
    return x ^ (x >> 16)


def hashed_bits(key: jax.Array, shape: tuple[int, ...]) -> jax.Array:
    """uint32[shape]: a keyed hash of each element's row-major index (at most 2³² elements)."""
    size = 1
    for n in shape:
        size *= n
    if size > 2**32:
        raise ValueError(f"hashed dropout bits index at most 2**32 elements, got shape {shape}")
    k = jax.random.bits(key, (2,), jnp.uint32)
    index, stride = jnp.zeros(shape, jnp.uint32), 1
    for axis in reversed(range(len(shape))):
        index = index + jax.lax.broadcasted_iota(jnp.uint32, shape, axis) * jnp.uint32(stride)
        stride *= shape[axis]
    return _lowbias32(_lowbias32(index ^ k[0]) ^ k[1])


class Dropout(nn.Module):
    """Inverted dropout on the 'dropout' rng stream; `bits` picks the source of the mask."""

    rate: float
    bits: DropoutBits = "hash"

    @nn.compact
    def __call__(self, x: jax.Array, deterministic: bool) -> jax.Array:
        if deterministic or self.rate == 0.0:
            return x
        if not 0.0 < self.rate < 1.0:
            raise ValueError(f"dropout rate {self.rate} must be in [0, 1)")
        if self.bits not in DROPOUT_BITS:
            raise ValueError(f"bits={self.bits!r}; choose one of {DROPOUT_BITS}")
        key = self.make_rng("dropout")
        if self.bits == "hash":
            keep = hashed_bits(key, x.shape) >= jnp.uint32(int(self.rate * 2**32))
        else:
            keep = jax.random.bernoulli(key, 1.0 - self.rate, x.shape)
        return jnp.where(keep, x * (1.0 / (1.0 - self.rate)), 0.0)
