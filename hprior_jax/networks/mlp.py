"""MLP trunk in BPref's layout: depth x [Dense(hidden) -> act] -> Dense(out)."""
from __future__ import annotations

from typing import Callable

import math

import flax.linen as nn
import jax
import jax.numpy as jnp

# QR one matrix at a time, also under vmap. A vmapped QR becomes one batched LAPACK call that
# jaxlib (0.10.2) splits over XLA's intra-op thread pool (ParallelBatchMap) and then blocks on;
# when two such calls run at once (actor and critic init, vmapped over 2 seeds) both pool
# threads of a 2-core machine wait for work that no thread is left to run: the program hangs
# at 0% CPU (native stacks: both tf_XLAEigen threads in QrFactorization -> ParallelBatchMap).
_qr_sequential = jax.custom_batching.sequential_vmap(lambda a: jnp.linalg.qr(a))


def orthogonal(scale: float = 1.0):
    """torch.nn.init.orthogonal_ (QR of a Gaussian, signs fixed by diag(R)): Haar-distributed
    like flax's `orthogonal`, but safe to vmap on CPU (see `_qr_sequential`)."""
    def init(key, shape, dtype=jnp.float32):
        rows, cols = math.prod(shape[:-1]), shape[-1]
        tall = (rows, cols) if rows >= cols else (cols, rows)
        q, r = _qr_sequential(jax.random.normal(key, tall, jnp.float32))
        q = q * jnp.sign(jnp.diagonal(r))
        if rows < cols:
            q = q.T
        return (scale * q).reshape(shape).astype(dtype)

    return init


class MLP(nn.Module):
    hidden_dim: int
    depth: int  # number of hidden layers (BPref's `hidden_depth`)
    out_dim: int
    activation: Callable[[jax.Array], jax.Array] = nn.relu
    kernel_init: Callable = orthogonal()  # BPref's SAC nets (utils.weight_init): gain 1
    bias_init: Callable = nn.initializers.zeros

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        for _ in range(self.depth):
            x = self.activation(nn.Dense(self.hidden_dim, kernel_init=self.kernel_init,
                                         bias_init=self.bias_init)(x))
        return nn.Dense(self.out_dim, kernel_init=self.kernel_init, bias_init=self.bias_init)(x)
