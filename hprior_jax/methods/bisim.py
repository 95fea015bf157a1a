"""BISIM (appendix G.2, eq. 8): PEBBLE plus a bisimulation loss on the reward model's
embedding (hprior_jax.pbrl.bisim), weighted by λ_bisim.

    J_bisim = (‖z_i − z_j‖_1 − |r_i − r_j| − γ ‖ẑ'_i − ẑ'_j‖)²

z is each member's penultimate-layer activation, r its predicted reward, ẑ' a head added on the
penultimate layer that predicts the next step's embedding (trained by a transition loss beside
eq. 8). The states come from the replay buffer PRIOR's world model trains on: each round draws
`transitions_per_pair` transitions per stored-pair row, so a reward minibatch of b labelled
pairs carries b x `transitions_per_pair` transitions. γ is SAC's discount. The appendix gives
no λ_bisim or batch size: ours are below.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import jax
import jax.numpy as jnp
from flax import struct

from hprior_jax.methods.pebble import Pebble
from hprior_jax.methods.pebble_family import (Extension, PebbleConfig, PebbleState, pebble_preset,
                                             reward_config)
from hprior_jax.methods.registry import MethodSpec
from hprior_jax.pbrl.bisim import bisim_term, sample_transitions

_STREAM = 0xB151  # fold_in tag: BISIM's draws leave PEBBLE's untouched


@dataclass(frozen=True)
class BisimConfig:
    lam: float = 0.5
    """λ_bisim (not given by the paper; 0.5 is DBC's `bisim_coef`, Zhang et al. 2021)."""
    transitions_per_pair: int = 4

    def __post_init__(self):
        if self.lam < 0 or self.transitions_per_pair < 1:
            raise ValueError("need --bisim.lam >= 0 and --bisim.transitions-per-pair >= 1")


@struct.dataclass
class BisimState:
    lam: jax.Array  # a leaf: a λ sweep vmaps


class BisimPrior(Extension):
    def __init__(self, cfg, kit):
        self.cfg, self.kit = cfg.bisim, kit
        self.discount = cfg.sac.discount
        self.reward_cfg = self.reward_config(reward_config(cfg.pebble))

    def reward_config(self, base):
        return dataclasses.replace(base, next_embedding_head=True)

    def init(self, key):
        return BisimState(lam=jnp.asarray(self.cfg.lam, jnp.float32))

    def reward_terms(self, rs, ms: PebbleState):
        transitions = sample_transitions(jax.random.fold_in(rs.key, _STREAM), rs.replay,
                                         self.kit.env.episode_length, ms.prefs.capacity,
                                         self.cfg.transitions_per_pair)
        return (bisim_term(ms.ext.lam, transitions, reward_cfg=self.reward_cfg,
                           discount=self.discount),), ms


def spec(name: str) -> MethodSpec:
    return MethodSpec(
        name=name, build=lambda cfg, kit: Pebble(cfg, kit, BisimPrior(cfg, kit)),
        sections={"pebble": PebbleConfig, "bisim": BisimConfig},
        preset=lambda task, preset, sac: {**pebble_preset(task, preset, sac),
                                          "bisim": BisimConfig()})
