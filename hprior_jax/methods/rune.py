"""RUNE (Liang et al. 2022; rll-research/rune): PEBBLE plus an exploration bonus, the reward
ensemble's disagreement, in the critic target only.

    y = r̂_mean(s, a) + β_t · std_k r̂_k(s, a) + γ · not_done · (min Q'(s', a') − α log π(a'|s'))
    β_t = β_0 (1 − ρ)^t,   t = the global env step (pre-training counted)

As the original (`agent/sac_explore.py`): the std is the population std (ddof 0) of the members'
tanh outputs, not normalised; the bonus enters every SAC update after pre-training, the
`reset_update` steps after the critic reset included (there at the step of the first round);
pre-training keeps PEBBLE's state-entropy reward; actor and temperature losses are unchanged.
The original's schedule is named `linear_decay` but is exponential, as written above.

Decision: RUNE stores the std with each transition and relabels it with r̂ after every reward
update; we compute it from the current ensemble for each sampled batch. The values are the
same: the ensemble changes only in a feedback round, after which the original relabels every
stored transition, so a stored std always equals the current ensemble's. Computing it costs one
ensemble forward pass on the SAC batch and saves a replay column.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import jax
import jax.numpy as jnp

from hprior_jax.methods.pebble import Pebble
from hprior_jax.methods.pebble_family import Extension, PebbleConfig, pebble_preset, reward_config
from hprior_jax.methods.registry import MethodSpec
from hprior_jax.networks.reward_ensemble import member_rewards


@dataclass(frozen=True)
class RuneConfig:
    beta_init: float = 0.05
    """β_0 (rune `config/agent/sac_explore.yaml`)."""
    beta_decay: float = 1e-5
    """ρ: β_t = β_0 (1 − ρ)^t (the scripts use 1e-3 for drawer-open at 5000 labels)."""
    beta_schedule: Literal["exponential", "constant"] = "exponential"
    """The original's `linear_decay` (which is exponential) or `constant` (β_t = β_0)."""

    def __post_init__(self):
        if self.beta_init < 0 or not 0 <= self.beta_decay < 1:
            raise ValueError("need --rune.beta-init >= 0 and 0 <= --rune.beta-decay < 1")


def beta(cfg: RuneConfig, t: jax.Array) -> jax.Array:
    """β_t at global step t (float32; (1 − ρ)^t as exp(t · log1p(−ρ)), accurate for small ρ)."""
    if cfg.beta_schedule == "constant":
        return jnp.asarray(cfg.beta_init, jnp.float32)
    return cfg.beta_init * jnp.exp(jnp.asarray(t, jnp.float32) * jnp.log1p(-cfg.beta_decay))


def disagreement_bonus(params, obs: jax.Array, action: jax.Array, reward_cfg) -> jax.Array:
    """[B] population std over the members of r̂_k(s, a) (rune `r_hat_disagreement`)."""
    return member_rewards(params, obs, action, reward_cfg).std(axis=0)


class DisagreementBonus(Extension):
    agent_metrics = ("train/rune_bonus", "train/rune_beta")

    def __init__(self, cfg):
        self.cfg = cfg.rune
        self.reward_cfg = reward_config(cfg.pebble)

    def agent_reward(self, rs, batch, t):
        bonus = disagreement_bonus(rs.method.reward, batch.obs, batch.action, self.reward_cfg)
        b = beta(self.cfg, t)
        return batch.reward + b * bonus, rs, {"train/rune_bonus": jnp.mean(bonus),
                                               "train/rune_beta": b}


def spec(name: str) -> MethodSpec:
    return MethodSpec(
        name=name, build=lambda cfg, kit: Pebble(cfg, kit, DisagreementBonus(cfg)),
        sections={"pebble": PebbleConfig, "rune": RuneConfig},
        preset=lambda task, preset, sac: {**pebble_preset(task, preset, sac),
                                          "rune": RuneConfig()})
