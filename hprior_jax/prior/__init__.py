"""Hindsight PRIOR building blocks (pure, jit/vmap-able, static shapes).

world_model: TWM-style world model (MLP observation model + Transformer-XL dynamics), losses,
             separate update steps for the observation and dynamics models, segment sampler
attention:   world-model attention -> per-step credit α[T] (and α for every stored pair)
loss:        PRIOR targets α·sg(R̂), prior loss, NRP / RVAR variants, the prior as a reward
             term of hprior_jax.pbrl.preference.train_reward
The Transformer-XL itself is hprior_jax.networks.transformer_xl; the method that puts these
together is hprior_jax.methods.prior.
"""
