"""RVAR (appendix G.1): PEBBLE plus the prior loss with the segment's return spread uniformly
over its steps (target R̂/|σ| for every step). PRIOR's ablation without a world model: what
PRIOR adds over it is the attention's shape, not the redistribution itself."""
from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import Literal

import jax
import jax.numpy as jnp
from flax import struct

from hprior_jax.agents.sac import SACConfig
from hprior_jax import task_table
from hprior_jax.methods.pebble import Pebble
from hprior_jax.methods.pebble_family import (Extension, PebbleConfig, PebbleState, pebble_preset,
                                             reward_config)
from hprior_jax.methods.registry import MethodSpec
from hprior_jax.prior.loss import TARGETS, PairCredit, prior_term, rvar_alpha, target_shift
from hprior_jax.prior.unlabelled import replay_segments, rows_of_pool, unlabelled_prior_term


@dataclass(frozen=True)
class RvarConfig:
    lam: float = 5.0
    """λ, the weight of the uniform prior (the presets use PRIOR's: 5 DMC, 1000 MetaWorld)."""
    target: Literal["raw", "shifted"] = "raw"
    """As --prior.target. With uniform credit both forms give R̂/|σ| (prior/loss.py): the flag
    exists so that a comparison can name the same form for every method."""
    unlabelled_segments: int = 0
    """Not in the paper (0 is off): the uniform prior also on this many unlabelled segments
    of the replay buffer, drawn afresh each round, with the same λ (as
    --prior.unlabelled-segments)."""

    def __post_init__(self):
        if self.lam < 0:
            raise ValueError(f"--rvar.lam must be >= 0, got {self.lam}")
        if self.unlabelled_segments < 0:
            raise ValueError("--rvar.unlabelled-segments must be >= 0")
        if self.target not in TARGETS:
            raise ValueError(f"--rvar.target must be one of {TARGETS}, got {self.target!r}")


@struct.dataclass
class RvarState:
    lam: jax.Array  # a leaf: λ sweeps vmap


class UniformPrior(Extension):
    def __init__(self, cfg, kit):
        self.cfg, self.kit = cfg, kit
        self.lam = cfg.rvar.lam
        self.credit = partial(PairCredit.uniform, cfg.pebble.max_feedback, cfg.pebble.segment_len)
        self.shift = target_shift(cfg.rvar.target, reward_config(cfg.pebble).output_activation)

    def init(self, key):
        return RvarState(lam=jnp.asarray(self.lam, jnp.float32))

    def reward_terms(self, rs, ms: PebbleState):
        terms = (prior_term(ms.ext.lam, self.credit(), "uniform", shift=self.shift),)
        num = self.cfg.rvar.unlabelled_segments
        if num:
            obs, act = replay_segments(rs.key, rs.replay, num,
                                       segment_len=self.cfg.pebble.segment_len,
                                       episode_len=self.kit.env.episode_length)
            rows = rows_of_pool(obs, act, rvar_alpha(obs[..., 0]), ms.prefs.capacity)
            terms += (unlabelled_prior_term(ms.ext.lam, rows, shift=self.shift,
                                            reward_cfg=reward_config(self.cfg.pebble)),)
        return terms, ms


def rvar_preset(task: str, preset: str, sac: SACConfig) -> dict:
    return {**pebble_preset(task, preset, sac),
            "rvar": RvarConfig(lam=task_table.values(task).prior_lambda)}


def spec(name: str) -> MethodSpec:
    return MethodSpec(name=name, build=lambda cfg, kit: Pebble(cfg, kit, UniformPrior(cfg, kit)),
                      sections={"pebble": PebbleConfig, "rvar": RvarConfig}, preset=rvar_preset)
