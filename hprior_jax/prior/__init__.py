"""Hindsight PRIOR building blocks (pure, jit/vmap-able, static shapes).

world_model: TWM-style world model (MLP observation model + Transformer-XL dynamics), losses,
             separate update steps for the observation and dynamics models, segment sampler
attention:   world-model attention -> per-step credit α[T] (and α for every stored pair)
loss:        PRIOR targets α·sg(R̂), prior loss, NRP / RVAR variants, reward training with
             CE + λ·L_prior on top of hprior_jax.pebble.preference
The Transformer-XL itself is hprior_jax.networks.transformer_xl.
"""
from hprior_jax.prior.loss import (LAMBDA_PRESETS, PairCredit, PriorConfig,  # noqa: F401
                                   prior_train_epoch, train_reward_with_prior)
from hprior_jax.prior.world_model import WorldModelConfig, WorldModelParams, WorldModelState  # noqa: F401
