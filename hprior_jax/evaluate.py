"""Evaluation rollouts: deterministic policy (tanh of the mean), whole episodes, true return.

BPref evaluates 10 deterministic episodes every 10k steps and counts MetaWorld success at
any step of an episode. We run the episodes in parallel in a separate
environment batch, so evaluation never perturbs the training environment or its keys.
"""
from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp

from hprior_jax.envs import VecEnv


def evaluate_policy(env: VecEnv, policy: Callable[[jax.Array], jax.Array], key: jax.Array):
    """Returns (episode_return[N], episode_success[N]) of `env.num_envs` whole episodes.

    `policy` maps a batch of observations [N, obs] to actions [N, act]."""

    def body(state, t):
        state, tr = env.advance(state, policy(state.task.obs), t)
        return state, None

    state, _ = jax.lax.scan(body, env.reset(key), jnp.arange(env.episode_length))
    return state.episode_return, state.episode_success
