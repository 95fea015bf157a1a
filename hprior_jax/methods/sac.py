"""SAC on the true reward (BPref `train_SAC.py`): the reference every PbRL score is
normalised by. Uniform-random actions for `num_seed_steps`, then one SAC update per env step
on the reward stored with each transition, here the task's own."""
from __future__ import annotations

from hprior_jax.methods.base import Method
from hprior_jax.methods.registry import MethodSpec


def spec(name: str) -> MethodSpec:
    return MethodSpec(name=name, build=Method)
