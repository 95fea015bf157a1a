"""A seed's world model for the lab: trained once per seed on the training episodes, before
any round, and fixed after (the RL loop keeps training it; here the data does not change);
with the held-out segments its diagnostics read. Trained world models are kept on disk by
`lab.world_model_cache`, whose key includes this module's bytes.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from hprior_jax.lab.config import Episodes, LabConfig
from hprior_jax.lab.dataset import Dataset
from hprior_jax.prior import world_model as wm
from hprior_jax.prior.attention import segment_credit


@struct.dataclass
class SeedContext:
    """What a seed's rules share: the world model, its mean α per position and the
    standardisation of its observations (None: raw, the paper's)."""

    wm_params: wm.WorldModelParams | None
    profile: jax.Array  # [T]
    obs_scaler: wm.ObsScaler | None = None


def train_seed_context(cfg: LabConfig, segment_len: int, key: jax.Array,
                       train: Episodes) -> SeedContext:
    """A seed's world model trained on the training episodes (pre-training, then dynamics),
    and its mean α per position on `profile_segments` training segments; without a rule
that reads a world model, none and a uniform profile."""
    if not cfg.needs_world_model:
        return SeedContext(wm_params=None, profile=jnp.full((segment_len,), 1.0 / segment_len))
    k_init, k_pre, k_dyn, k_seg = jax.random.split(jax.random.fold_in(key, wm.RANDOM_STREAM), 4)
    obs, act = train.obs, train.act
    flat = lambda x: x.reshape((-1,) + x.shape[2:])
    size = jnp.int32(obs.shape[0] * obs.shape[1])
    scaler = wm.fit_obs_scaler(flat(obs), size) if cfg.wm_normalize_obs else None
    data = dict(obs_buf=flat(obs), act_buf=flat(act), size=size, cfg=cfg.world_model,
                episode_len=obs.shape[1], obs_scaler=scaler)
    state = wm.init(k_init, cfg.world_model)
    state, _ = wm.pretrain(state, k_pre, num_steps=cfg.wm_pretrain_steps,
                           order=cfg.wm_order, **data)
    if cfg.wm_steps:
        state, _ = wm.train(state, k_dyn, num_steps=cfg.wm_steps, observation_model=False,
                            dynamics_model=True, **data)
    seg_obs, seg_act = wm.sample_segments(
        k_seg, flat(obs), flat(act), size, episode_len=obs.shape[1],
        batch_size=cfg.profile_segments, segment_len=segment_len)
    alpha = segment_credit(state.params, wm.scaled(scaler, seg_obs), seg_act,
                           cfg.world_model, query=cfg.attention_query)
    return SeedContext(wm_params=state.params, profile=alpha.mean(0), obs_scaler=scaler)


def held_out_segments(data: Dataset, segment_len: int, num: int, seed: int = 0):
    """`num` fixed segments of the held-out episodes and a random step order for each:
    (obs, act, true reward, perm), the inputs of prior.diagnostics."""
    rng = np.random.default_rng(seed)
    ep = rng.integers(0, data.test_obs.shape[0], num)
    start = rng.integers(0, data.episode_length - segment_len + 1, num)
    steps = start[:, None] + np.arange(segment_len)
    cut = lambda x: jnp.asarray(x[ep[:, None], steps])
    perm = jnp.asarray(np.stack([rng.permutation(segment_len) for _ in range(num)]))
    return cut(data.test_obs), cut(data.test_act), cut(data.test_reward), perm

