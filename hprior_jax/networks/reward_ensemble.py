"""Ensemble of learned reward nets r̂_i(s, a) (BPref `reward_model.py#L18-L32`).

Each member: concat(obs, act) -> len(hidden_sizes) x [Dense -> LeakyReLU(0.01)] -> Dense(1) -> tanh.
Members' parameters are stacked on a leading axis of size K (`ensemble_size`) and evaluated
with `jax.vmap`, so one optax optimizer over the stacked pytree is exactly PyTorch's single
Adam over all members (Adam is elementwise and members share no parameters).

Shapes: obs[..., obs_size], act[..., act_size] -> member rewards [K, ...], mean reward [...].
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

Params = Any

# PyTorch's default nn.Linear init (kaiming_uniform(a=sqrt(5))): W ~ U(±1/sqrt(fan_in)),
# which is variance_scaling(1/3, fan_in, uniform). BPref's reward nets keep this default
# (unlike its SAC nets, which use orthogonal init).
torch_kernel_init = nn.initializers.variance_scaling(1.0 / 3.0, "fan_in", "uniform")


def torch_bias_init(fan_in: int):
    """PyTorch default Linear bias: U(±1/sqrt(fan_in))."""
    bound = 1.0 / float(fan_in) ** 0.5

    def init(key, shape, dtype=jnp.float32):
        return jax.random.uniform(key, shape, dtype, -bound, bound)

    return init


_HIDDEN = {
    "leaky_relu": lambda x, slope: nn.leaky_relu(x, slope),
    "relu": lambda x, slope: nn.relu(x),
    "silu": lambda x, slope: nn.silu(x),
    "tanh": lambda x, slope: jnp.tanh(x),
}
# BPref's `activation` option: 'tanh' (used by every script), 'sig', anything else -> ReLU.
_OUTPUT = {
    "tanh": jnp.tanh,
    "sig": nn.sigmoid,
    "relu": nn.relu,
    "none": lambda x: x,
}


@dataclass(frozen=True)
class RewardConfig:
    """Architecture of the reward ensemble. Defaults = BPref/PEBBLE (3 x 256, K = 3, tanh out)."""

    hidden_sizes: tuple[int, ...] = (256, 256, 256)
    ensemble_size: int = 3
    hidden_activation: str = "leaky_relu"  # leaky_relu | relu | silu | tanh
    leaky_slope: float = 0.01  # PyTorch nn.LeakyReLU default (= flax default)
    output_activation: str = "tanh"  # tanh | sig | relu | none (BPref `activation`)

    def __post_init__(self):
        if self.hidden_activation not in _HIDDEN:
            raise ValueError(f"hidden_activation={self.hidden_activation!r}; choose one of {sorted(_HIDDEN)}")
        if self.output_activation not in _OUTPUT:
            raise ValueError(f"output_activation={self.output_activation!r}; choose one of {sorted(_OUTPUT)}")
        if self.ensemble_size < 1:
            raise ValueError("ensemble_size must be >= 1")


class RewardNet(nn.Module):
    """One ensemble member: x[..., in] -> r̂[...] (scalar per input row)."""

    cfg: RewardConfig

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        fan_in, lead = x.shape[-1], x.shape[:-1]
        # Rows flattened to one 2-D matmul per layer: on XLA CPU the [B, T, d] form under the
        # members' vmap made a reward-learning step at BPref's sizes 1.5-1.6x slower (315 ms
        # before, 192 and 209 ms after in two runs; benchmarks/reward_update.py,
        # results/reward_update*.csv). Same arithmetic per row.
        x = x.reshape(-1, fan_in)
        for width in self.cfg.hidden_sizes:
            x = nn.Dense(width, kernel_init=torch_kernel_init, bias_init=torch_bias_init(fan_in))(x)
            x = _HIDDEN[self.cfg.hidden_activation](x, self.cfg.leaky_slope)
            fan_in = width
        x = nn.Dense(1, kernel_init=torch_kernel_init, bias_init=torch_bias_init(fan_in))(x)
        return _OUTPUT[self.cfg.output_activation](x)[..., 0].reshape(lead)


def init_reward_ensemble(key: jax.Array, obs_size: int, act_size: int,
                         cfg: RewardConfig = RewardConfig()) -> Params:
    """Stacked params of K independent members; every leaf has a leading axis K."""
    net = RewardNet(cfg)
    dummy = jnp.zeros((1, obs_size + act_size), jnp.float32)
    # Same distribution as net.init (every kernel and bias ~ U(±1/sqrt(fan_in)), see
    # torch_kernel_init/torch_bias_init) but from ONE uniform draw for the whole ensemble: each
    # threefry call site costs ~1 s of XLA compile on CPU, and flax's init makes two per layer.
    shapes = jax.eval_shape(net.init, jax.random.key(0), dummy)
    leaves, treedef = jax.tree_util.tree_flatten_with_path(shapes)
    sizes = [cfg.ensemble_size * int(np.prod(leaf.shape)) for _, leaf in leaves]
    u = jax.random.uniform(key, (sum(sizes),), jnp.float32, -1.0, 1.0)
    fan_in = {}
    for path, leaf in leaves:  # Dense layer name -> fan_in (kernel is [fan_in, fan_out])
        if path[-1].key == "kernel":
            fan_in[path[-2].key] = leaf.shape[0]
    out, offset = [], 0
    for (path, leaf), size in zip(leaves, sizes):
        bound = 1.0 / np.sqrt(fan_in[path[-2].key])
        out.append(bound * u[offset:offset + size].reshape((cfg.ensemble_size,) + leaf.shape))
        offset += size
    return jax.tree_util.tree_unflatten(treedef, out)


def member_rewards(params: Params, obs: jax.Array, act: jax.Array,
                   cfg: RewardConfig = RewardConfig()) -> jax.Array:
    """Every member on the same inputs: obs[..., ds], act[..., da] -> [K, ...]."""
    x = jnp.concatenate([obs, act], axis=-1)
    net = RewardNet(cfg)
    return jax.vmap(lambda p: net.apply(p, x))(params)


def per_member_rewards(params: Params, obs: jax.Array, act: jax.Array,
                       cfg: RewardConfig = RewardConfig()) -> jax.Array:
    """Member i on its own inputs: obs[K, ..., ds], act[K, ..., da] -> [K, ...].

    Used by reward training, where each member sees its own shuffled minibatch (BPref).
    """
    x = jnp.concatenate([obs, act], axis=-1)
    net = RewardNet(cfg)
    return jax.vmap(net.apply)(params, x)


def mean_reward(params: Params, obs: jax.Array, act: jax.Array,
                cfg: RewardConfig = RewardConfig()) -> jax.Array:
    """The reward given to RL: mean over members (BPref `r_hat`/`r_hat_batch`). -> [...]."""
    return member_rewards(params, obs, act, cfg).mean(axis=0)
