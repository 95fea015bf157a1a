"""MLP trunk in BPref's layout: depth x [Dense(hidden) -> act] -> Dense(out)."""
from __future__ import annotations

from typing import Callable

import flax.linen as nn
import jax

# BPref's SAC nets (utils.weight_init): orthogonal weights (gain 1), zero biases.
orthogonal = nn.initializers.orthogonal()


class MLP(nn.Module):
    hidden_dim: int
    depth: int  # number of hidden layers (BPref's `hidden_depth`)
    out_dim: int
    activation: Callable[[jax.Array], jax.Array] = nn.relu
    kernel_init: Callable = orthogonal
    bias_init: Callable = nn.initializers.zeros

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        for _ in range(self.depth):
            x = self.activation(nn.Dense(self.hidden_dim, kernel_init=self.kernel_init,
                                         bias_init=self.bias_init)(x))
        return nn.Dense(self.out_dim, kernel_init=self.kernel_init, bias_init=self.bias_init)(x)
