"""Hindsight PRIOR on the PEBBLE loop: PEBBLE plus a world model whose attention guides reward
learning (appendix C.3, Table 4; reference/prior_spec.md §1.8).

Schedule on top of PEBBLE's (decided on the host, the same for every seed):
  seed + unsup (first round)  observation + dynamics model trained on the replay buffer
                              (`wm_pretrain_steps`), then PEBBLE's first feedback round
  every multiple of j after   dynamics model only (`wm_update_steps`), on segments sampled from
                              the whole replay buffer (TWM trains on its bank of transitions;
                              "incoming data" in C.3 is in that bank)
  every feedback round        α for every stored pair from the current world model, then the
                              reward update with CE + λ·L_prior

Decision: α is recomputed at each round, not after each world-model update. It is read only by
the reward update, which happens only at rounds, so the values are identical and the rounds
between updates cost nothing (prior_spec.md §5 row 16 asks for "recompute after each update").
Variant `rvar` needs no world model: none is trained and α is uniform.
"""
from __future__ import annotations

import time
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from hprior_jax.networks.reward_ensemble import member_rewards
from hprior_jax.pebble.trainer import PebbleState, PebbleTrainer, reward_round_metrics
from hprior_jax.prior import world_model as wm
from hprior_jax.prior.attention import pair_credit
from hprior_jax.prior.loss import PairCredit, target_saturation, train_reward_with_prior, variant_alpha
from hprior_jax.train import RunState

_WM_STREAM = 0x574D  # fold_in tag of the world model's random stream


@struct.dataclass
class PriorState(PebbleState):
    wm: wm.WorldModelState
    credit: PairCredit  # α of both segments of every stored pair, as of the last round


class PriorTrainer(PebbleTrainer):
    def __init__(self, cfg):
        super().__init__(cfg)
        self.prior_cfg = cfg.prior
        self.loss_cfg = cfg.prior.loss()
        self.wm_cfg = cfg.prior.world_model(self.env.obs_size, self.env.action_size,
                                            self.pcfg.segment_len)
        self.uses_world_model = cfg.prior.variant != "rvar"

    # -- schedule --------------------------------------------------------------------------
    def wm_steps(self) -> list[int]:
        """Global steps before which the world model trains: the first is the pre-training."""
        if not self.uses_world_model:
            return []
        first, j = self.first_round_step, self.prior_cfg.wm_every
        later = range((first // j + 1) * j, self.cfg.steps, j) if self.prior_cfg.wm_update_steps else []
        return [first, *later]

    def event_steps(self):
        return sorted(set(super().event_steps()) | set(self.wm_steps()))

    # -- per-seed pure functions -----------------------------------------------------------
    # World-model randomness is folded out of the keys PEBBLE uses, never split from them, so
    # every PEBBLE draw is unchanged: with λ = 0 a PRIOR run trains exactly PEBBLE's agent.
    def _init_extra(self, key):
        base = super()._init_extra(key)
        return PriorState(**{f: getattr(base, f) for f in base.__dataclass_fields__},
                          wm=wm.init(jax.random.fold_in(key, _WM_STREAM), self.wm_cfg),
                          credit=PairCredit.uniform(self.pcfg.max_feedback, self.pcfg.segment_len))

    def train_world_model(self, rs: RunState, *, pretrain: bool):
        """Pre-training: observation and dynamics model; later: dynamics only (appendix C.3)."""
        p = self.prior_cfg
        state, metrics = wm.train(
            rs.extra.wm, jax.random.fold_in(rs.key, _WM_STREAM), rs.replay.obs, rs.replay.action,
            rs.replay.size, cfg=self.wm_cfg, episode_len=self.env.episode_length,
            num_steps=p.wm_pretrain_steps if pretrain else p.wm_update_steps,
            observation_model=pretrain, dynamics_model=True)
        return rs.replace(extra=rs.extra.replace(wm=state)), metrics

    def _train_reward(self, ext: PriorState, key: jax.Array):
        """CE + λ·L_prior on every stored pair, α from the current world model."""
        credit = None
        if self.uses_world_model:
            credit = pair_credit(ext.wm.params, ext.prefs, self.wm_cfg, credit=ext.credit,
                                 query=self.prior_cfg.attention_query)
        params, opt, m = train_reward_with_prior(
            ext.reward, ext.reward_opt, ext.prefs, credit, key, tx=self.reward_tx,
            reward_cfg=self.reward_cfg, cfg=self.pref_cfg, prior_cfg=self.loss_cfg)
        metrics = {**reward_round_metrics(m),
                   "prior/loss": m["reward/extra_loss"] / max(self.loss_cfg.lam, 1e-12)}
        if credit is not None:
            metrics.update(self._credit_diagnostics(params, ext.prefs, credit))
            ext = ext.replace(credit=credit)
        return ext.replace(reward=params, reward_opt=opt), metrics

    def _credit_diagnostics(self, reward_params, prefs, credit: PairCredit) -> dict:
        """Attention entropy (normalised by log T: 1 = uniform) and the fraction of targets
        α·R̂ outside the tanh reward's range [-1, 1], over the stored pairs."""
        real = jnp.arange(prefs.capacity) < prefs.count
        n = jnp.maximum(prefs.count, 1).astype(jnp.float32) * 2
        t = credit.alpha1.shape[-1]
        alpha = jnp.concatenate([credit.alpha1, credit.alpha2])
        alpha = variant_alpha(alpha, self.loss_cfg.variant)
        ent = -jnp.sum(alpha * jnp.log(jnp.maximum(alpha, 1e-12)), -1) / jnp.log(t)
        mask2 = jnp.concatenate([real, real])
        obs = jnp.concatenate([prefs.obs1, prefs.obs2])
        act = jnp.concatenate([prefs.act1, prefs.act2])
        r = member_rewards(reward_params, obs, act, self.reward_cfg)  # [K, 2C, T]
        out = jax.vmap(lambda r_k: jax.vmap(target_saturation)(r_k, alpha))(r)  # [K, 2C]
        return {"prior/attention_entropy": jnp.sum(ent * mask2) / n,
                "prior/target_out_of_range": jnp.sum(out.mean(0) * mask2) / n}

    # -- host side -------------------------------------------------------------------------
    def run_event(self, rs: RunState, step: int):
        metrics = {}
        if step in self.wm_steps():
            pretrain = step == self.first_round_step
            name = "world_model/pretrain" if pretrain else "world_model/update"
            fn = jax.jit(jax.vmap(partial(self.train_world_model, pretrain=pretrain)),
                         donate_argnums=0)
            compiled = self._aot(name, fn, rs)
            t0 = time.perf_counter()
            rs, metrics = jax.block_until_ready(compiled(rs))
            metrics = dict(metrics)
            metrics["perf/world_model_s"] = np.full(len(self.cfg.seeds), time.perf_counter() - t0)
        if step in dict(self.rounds()):
            rs, round_metrics = super().run_event(rs, step)
            metrics.update(round_metrics)
        return rs, metrics
