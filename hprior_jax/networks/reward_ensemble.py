"""Ensemble of learned reward nets r̂_i(s, a) (BPref `reward_model.py#L18-L32`).

Each member: concat(obs, act) -> len(hidden_sizes) x [Dense -> LeakyReLU(0.01)] -> Dense(1) -> tanh.
Members' parameters are stacked on a leading axis of size K (`ensemble_size`) and evaluated
with `jax.vmap`, so one optax optimizer over the stacked pytree is exactly PyTorch's single
Adam over all members (Adam is elementwise and members share no parameters).

Shapes: obs[..., obs_size], act[..., act_size] -> member rewards [K, ...], mean reward [...].

Optional (`RewardConfig.next_embedding_head`, BISIM's baseline, appendix G.2): a per-member Dense
`next_embedding` head on the penultimate activation z (the input of the final Dense(1)),
predicting the next step's z; `member_embeddings` returns (r̂, z, ẑ'). The rewards never read it.
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
    # BISIM (appendix G.2): add a per-member Dense `next_embedding` (width = the last hidden
    # width) on the penultimate activation, predicting the next step's embedding. Off: the
    # parameters are exactly those of the plain ensemble.
    next_embedding_head: bool = False

    def __post_init__(self):
        if self.hidden_activation not in _HIDDEN:
            raise ValueError(f"hidden_activation={self.hidden_activation!r}; choose one of {sorted(_HIDDEN)}")
        if self.output_activation not in _OUTPUT:
            raise ValueError(f"output_activation={self.output_activation!r}; choose one of {sorted(_OUTPUT)}")
        if self.ensemble_size < 1:
            raise ValueError("ensemble_size must be >= 1")


NEXT_EMBEDDING = "next_embedding"  # the BISIM head's layer name


class RewardNet(nn.Module):
    """One ensemble member: x[..., in] -> r̂[...] (scalar per input row).

    With `embeddings=True` (needs `cfg.next_embedding_head`): -> (r̂[...], z[..., h], ẑ'[..., h]),
    z = the last hidden activation (the input of the final Dense(1)), ẑ' = next_embedding(z)."""

    cfg: RewardConfig

    @nn.compact
    def __call__(self, x: jax.Array, embeddings: bool = False):
        if embeddings and not self.cfg.next_embedding_head:
            raise ValueError("embeddings=True needs RewardConfig(next_embedding_head=True)")
        fan_in, lead = x.shape[-1], x.shape[:-1]
        # Rows flattened to one 2-D matmul per layer: on XLA CPU the [B, T, d] form under the
        # members' vmap made a reward-learning step at BPref's sizes 1.5-1.6x slower (315 ms
        # before, 192 and 209 ms after in two runs; benchmarks/updates/reward_update.py,
        # results/updates/reward_update*.csv). Same arithmetic per row.
        x = x.reshape(-1, fan_in)
        for width in self.cfg.hidden_sizes:
            x = nn.Dense(width, kernel_init=torch_kernel_init, bias_init=torch_bias_init(fan_in))(x)
            x = _HIDDEN[self.cfg.hidden_activation](x, self.cfg.leaky_slope)
            fan_in = width
        z = x
        x = nn.Dense(1, kernel_init=torch_kernel_init, bias_init=torch_bias_init(fan_in))(x)
        r = _OUTPUT[self.cfg.output_activation](x)[..., 0].reshape(lead)
        if not embeddings:
            return r
        # Named (not Dense_{n+1}) and created after Dense(1): the reward layers keep their names.
        z_next = nn.Dense(fan_in, kernel_init=torch_kernel_init, bias_init=torch_bias_init(fan_in),
                          name=NEXT_EMBEDDING)(z)
        return r, z.reshape(lead + (fan_in,)), z_next.reshape(lead + (fan_in,))


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
    params = jax.tree_util.tree_unflatten(treedef, out)
    if cfg.next_embedding_head:
        head_key = jax.random.fold_in(key, 1)
        params = _add_next_embedding_head(head_key, params, obs_size + act_size, cfg)
    return params


def _add_next_embedding_head(key: jax.Array, params: Params, in_size: int,
                             cfg: RewardConfig) -> Params:
    """Adds the BISIM head `next_embedding` (Dense h -> h, h = the last hidden width; PyTorch's
    default init, U(±1/sqrt(h)), one draw). Its own key (folded off init's key) and its own
    draw: the reward layers keep exactly the values they have without the head."""
    h = cfg.hidden_sizes[-1] if cfg.hidden_sizes else in_size
    k = cfg.ensemble_size
    u = jax.random.uniform(key, (k * (h * h + h),), jnp.float32, -1.0, 1.0) / np.sqrt(h)
    head = {"kernel": u[:k * h * h].reshape(k, h, h), "bias": u[k * h * h:].reshape(k, h)}
    return {**params, "params": {**params["params"], NEXT_EMBEDDING: head}}


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


def member_embeddings(params: Params, obs: jax.Array, act: jax.Array,
                      cfg: RewardConfig = RewardConfig()):
    """Every member on the same inputs (needs `cfg.next_embedding_head`): obs[..., ds],
    act[..., da] -> (r̂ [K, ...], z [K, ..., h], ẑ' [K, ..., h]), z = member k's penultimate
    activation, ẑ' = its `next_embedding` head on z."""
    x = jnp.concatenate([obs, act], axis=-1)
    net = RewardNet(cfg)
    return jax.vmap(lambda p: net.apply(p, x, embeddings=True))(params)


def per_member_embeddings(params: Params, obs: jax.Array, act: jax.Array,
                          cfg: RewardConfig = RewardConfig()):
    """Member k on its own inputs: obs[K, ..., ds], act[K, ..., da] -> (r̂ [K, ...],
    z [K, ..., h], ẑ' [K, ..., h])."""
    x = jnp.concatenate([obs, act], axis=-1)
    net = RewardNet(cfg)
    return jax.vmap(lambda p, xk: net.apply(p, xk, embeddings=True))(params, x)


def mean_reward(params: Params, obs: jax.Array, act: jax.Array,
                cfg: RewardConfig = RewardConfig()) -> jax.Array:
    """The reward given to RL: mean over members (BPref `r_hat`/`r_hat_batch`). -> [...]."""
    return member_rewards(params, obs, act, cfg).mean(axis=0)
