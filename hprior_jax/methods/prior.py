"""Hindsight PRIOR on the PEBBLE loop: PEBBLE plus a world model whose attention guides reward
learning (appendix C.3, Table 4).

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
between updates cost nothing (a spec that says "recompute after each update" means the same).
PRIOR-NRP (`prior_nrp`) is the same method with α min-max normalised and softmaxed
(appendix eq. 9). λ is a leaf of the run state (`ext.lam`), so runs that differ only in λ
share one compiled program and can be vmapped side by side.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from functools import partial
from typing import Literal

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from hprior_jax.agents.sac import SACConfig
from hprior_jax import task_table
from hprior_jax.loop.state import RunState
from hprior_jax.methods.pebble import Pebble
from hprior_jax.methods.pebble_family import (Extension, PebbleConfig, PebbleState, pebble_preset,
                                             reward_config)
from hprior_jax.methods.registry import MethodSpec
from hprior_jax.prior import world_model as wm
from hprior_jax.prior.attention import pair_credit, segment_credit
from hprior_jax.prior.diagnostics import unreachable_targets, world_model_diagnostics
from hprior_jax.prior.loss import TARGETS, PairCredit, prior_term, target_shift, variant_alpha
from hprior_jax.prior.unlabelled import replay_segments, rows_of_pool, unlabelled_prior_term
from hprior_jax.prior.world_model import DropoutRng, WorldModelConfig

DIAGNOSTIC_SEGMENTS = 64  # replay segments the world-model diagnostics are measured on
DIAGNOSTICS_STREAM = 0x6469  # folded off the world model's key: its training draws are unchanged


@dataclass(frozen=True)
class PriorConfig:
    lam: float = 5.0
    """λ, the prior loss weight: appendix Table 4 gives 5 for DMC and 1000 for MetaWorld (the
    presets pick the task's). 0 trains exactly PEBBLE's reward."""
    wm_every: int = 2000
    """j: env steps between dynamics-model updates after pre-training (appendix C.3)."""
    wm_pretrain_steps: int = 1000
    """Gradient steps on observation + dynamics model at the end of pre-training. The paper does
    not give this number; ours, with `wm_update_steps`, keeps ~1 world-model step per 20 env steps."""
    wm_update_steps: int = 100
    """Dynamics-model gradient steps every `wm_every` env steps (not given by the paper)."""
    wm_order: wm.PretrainOrder = "joint"
    """Pre-training order: "joint" (appendix C.3: observation and dynamics model together for
    `wm_pretrain_steps`) or "observation_first" (an ablation, TWM's order: the observation
    model alone for `wm_pretrain_steps`, then the dynamics alone as long on its encodings)."""
    attention_query: Literal["action", "state"] = "action"
    """Which final-step token's attention row is read (see prior/attention.py for why action)."""
    exclude_own_step: bool = False
    """Ablation (not in the paper): α without the query's own (last) step, renormalised over
    the others. In the reduced cheetah runs that step held about a third of α's mass."""
    target: Literal["raw", "shifted"] = "raw"
    """The prior's target form (prior/loss.py): "raw", the paper's α_t·R̂ (its sign follows
    R̂, which the preference loss leaves free), or "shifted", α_t·(R̂ + T) − 1, the return
    redistributed from the tanh head's floor. The paper is silent on R̂'s sign; raw stays the
    default until a measurement shows a gain."""
    clip_targets: bool = False
    """Ablation (not in the paper): the targets α_t·R̂ clipped to [-1, 1], the tanh reward's
    range; unclipped, 1-12% of them were out of reach in the reduced cheetah runs."""
    unlabelled_segments: int = 0
    """Ablation (one reading of appendix G.2; 0, the paper's default, is off): the prior also
    on this many unlabelled segments of the replay buffer, drawn afresh each round, their α
    from the world model, with the same λ (prior/unlabelled.py)."""
    wm_normalize_obs: bool = False
    """Ablation (not in the paper, nor TWM, which feed raw observations): the world model's
    observations standardised per dimension by the replay buffer's mean and std, recomputed
    from the buffer whenever the world model trains or gives credit."""
    wm_predict: wm.Prediction = "state"
    """Option (not in the paper, nor TWM, which predict the next latent itself): "delta"
    predicts its change, ẑ_{t+1} = z_t + head, decoded as s_t + dec(ẑ_{t+1}) - dec(z_t). On
    MetaWorld, where states barely move per step, the "state" model loses to persistence."""
    # world model sizes: WorldModelConfig's defaults, which hold them (TWM's; appendix Table 5
    # sets sequence = memory = segment length)
    wm_batch: int = WorldModelConfig.batch_size
    wm_latent: int = WorldModelConfig.latent_dim
    wm_obs_hidden: int = WorldModelConfig.obs_hidden[0]
    wm_obs_depth: int = len(WorldModelConfig.obs_hidden)
    wm_embed: int = WorldModelConfig.embed_dim
    wm_layers: int = WorldModelConfig.num_layers
    wm_heads: int = WorldModelConfig.num_heads
    wm_head_dim: int = WorldModelConfig.head_dim
    wm_ff: int = WorldModelConfig.ff_dim
    wm_head_hidden: int = WorldModelConfig.head_hidden[0]
    wm_head_depth: int = len(WorldModelConfig.head_hidden)
    wm_dropout: float = WorldModelConfig.dropout
    wm_dropout_rng: DropoutRng = WorldModelConfig.dropout_rng
    """Source of the world model's dropout bits: hash is the fastest on CPU (see WorldModelConfig)."""
    # one learning rate for both of the world model's optimisers (whose defaults are equal)
    wm_lr: float = WorldModelConfig.dyn_lr

    def __post_init__(self):
        if self.lam < 0:
            raise ValueError(f"--prior.lam must be >= 0, got {self.lam}")
        for name in ("wm_every", "wm_batch", "wm_latent", "wm_obs_hidden", "wm_embed",
                     "wm_layers", "wm_heads", "wm_head_dim", "wm_ff", "wm_head_hidden"):
            if getattr(self, name) <= 0:
                raise ValueError(f"--prior.{name.replace('_', '-')} must be positive, "
                                 f"got {getattr(self, name)}")
        if self.wm_pretrain_steps < 1:
            raise ValueError("--prior.wm-pretrain-steps must be >= 1: attention from an untrained "
                             "world model is noise (use --algo rvar for no world model)")
        if self.wm_order not in wm.PRETRAIN_ORDERS:
            raise ValueError(f"--prior.wm-order must be one of {wm.PRETRAIN_ORDERS}")
        if self.unlabelled_segments < 0:
            raise ValueError("--prior.unlabelled-segments must be >= 0")
        if self.target not in TARGETS:
            raise ValueError(f"--prior.target must be one of {TARGETS}, got {self.target!r}")
        if self.wm_update_steps < 0:
            raise ValueError("--prior.wm-update-steps must be >= 0")
        if not 0.0 <= self.wm_dropout < 1.0:
            raise ValueError(f"--prior.wm-dropout must be in [0, 1), got {self.wm_dropout}")

    def world_model(self, obs_size: int, act_size: int, segment_len: int) -> WorldModelConfig:
        return WorldModelConfig(
            obs_size=obs_size, act_size=act_size, latent_dim=self.wm_latent,
            obs_hidden=(self.wm_obs_hidden,) * self.wm_obs_depth, embed_dim=self.wm_embed,
            num_heads=self.wm_heads, head_dim=self.wm_head_dim, num_layers=self.wm_layers,
            ff_dim=self.wm_ff, dropout=self.wm_dropout, dropout_rng=self.wm_dropout_rng,
            predict=self.wm_predict,
            head_hidden=(self.wm_head_hidden,) * self.wm_head_depth, segment_len=segment_len,
            memory_len=segment_len, batch_size=self.wm_batch, obs_lr=self.wm_lr, dyn_lr=self.wm_lr)


@struct.dataclass
class PriorExtState:
    wm: wm.WorldModelState
    credit: PairCredit  # α of both segments of every stored pair, as of the last round
    lam: jax.Array  # λ: a leaf, so a λ sweep vmaps instead of recompiling


class WorldModelPrior(Extension):
    """PEBBLE's reward update plus λ·L_prior with α from the world model's attention."""

    def __init__(self, cfg, kit, variant: str):
        self.cfg, self.kit, self.variant = cfg, kit, variant
        self.prior_cfg = cfg.prior
        self.segment_len = cfg.pebble.segment_len
        self.wm_cfg = cfg.prior.world_model(kit.env.obs_size, kit.env.action_size,
                                            self.segment_len)
        self.first_round_step = cfg.num_seed_steps + cfg.pebble.num_unsup_steps
        self.shift = target_shift(cfg.prior.target, reward_config(cfg.pebble).output_activation)

    # -- schedule --------------------------------------------------------------------------
    def event_steps(self) -> list[int]:
        """Global steps before which the world model trains: the first is the pre-training."""
        first, j = self.first_round_step, self.prior_cfg.wm_every
        later = range((first // j + 1) * j, self.cfg.steps, j) if self.prior_cfg.wm_update_steps else []
        return [first, *later]

    def obs_scaler(self, replay) -> wm.ObsScaler | None:
        """The standardisation of the world model's observations (`wm_normalize_obs`), from
        the replay buffer as it is now; None: raw observations (the paper's)."""
        if not self.prior_cfg.wm_normalize_obs:
            return None
        return wm.fit_obs_scaler(replay.obs, replay.size)

    # -- per-seed pure functions -----------------------------------------------------------
    # World-model randomness is folded out of the keys PEBBLE uses, never split from them, so
    # every PEBBLE draw is unchanged: with λ = 0 a PRIOR run trains exactly PEBBLE's agent.
    def init(self, key):
        return PriorExtState(wm=wm.init(jax.random.fold_in(key, wm.RANDOM_STREAM), self.wm_cfg),
                             credit=PairCredit.uniform(self.cfg.pebble.max_feedback,
                                                       self.segment_len),
                             lam=jnp.asarray(self.prior_cfg.lam, jnp.float32))

    def train_world_model(self, rs: RunState, *, pretrain: bool):
        """Pre-training: observation and dynamics model; later: dynamics only (appendix C.3).
        Metrics: the training losses and, after the update, `diagnose_world_model`'s."""
        p, ext = self.prior_cfg, rs.method.ext
        key = jax.random.fold_in(rs.key, wm.RANDOM_STREAM)
        scaler = self.obs_scaler(rs.replay)
        data = dict(obs_buf=rs.replay.obs, act_buf=rs.replay.action, size=rs.replay.size,
                    cfg=self.wm_cfg, episode_len=self.kit.env.episode_length, obs_scaler=scaler)
        if pretrain:
            state, metrics = wm.pretrain(ext.wm, key, num_steps=p.wm_pretrain_steps,
                                         order=p.wm_order, **data)
        else:
            state, metrics = wm.train(ext.wm, key, num_steps=p.wm_update_steps,
                                      observation_model=False, dynamics_model=True, **data)
        metrics = {**metrics, **self.diagnose_world_model(
            state.params, rs.replay, jax.random.fold_in(key, DIAGNOSTICS_STREAM), scaler)}
        return rs.replace(method=rs.method.replace(ext=ext.replace(wm=state))), metrics

    def diagnose_world_model(self, params, buf, key, scaler: wm.ObsScaler | None) -> dict:
        """prior.diagnostics on `DIAGNOSTIC_SEGMENTS` segments of the replay buffer (the data
        it trains on, so in-sample; the reward lab measures them on held-out episodes):
        next-state error against persistence and the mean state, and how much of α is
        position. Metrics only: the true reward enters nothing that trains."""
        k_rows, k_perm = jax.random.split(key)
        t = self.wm_cfg.segment_len
        idx = wm.segment_rows(k_rows, buf.size, episode_len=self.kit.env.episode_length,
                              batch_size=DIAGNOSTIC_SEGMENTS, segment_len=t)
        perm = jax.vmap(lambda k: jax.random.permutation(k, t))(
            jax.random.split(k_perm, DIAGNOSTIC_SEGMENTS))
        # with wm_normalize_obs the errors are in standardised units, as the model trains
        diag = world_model_diagnostics(params, wm.scaled(scaler, buf.obs[idx]),
                                       buf.action[idx], buf.true_reward[idx], perm, self.wm_cfg,
                                       query=self.prior_cfg.attention_query)
        return {f"prior/{k}": v for k, v in diag.items()}

    def reward_terms(self, rs, ms: PebbleState):
        """α for every stored pair from the current world model, then the prior term."""
        p = self.prior_cfg
        scaler = self.obs_scaler(rs.replay)
        credit = pair_credit(ms.ext.wm.params, ms.prefs, self.wm_cfg, credit=ms.ext.credit,
                             query=p.attention_query, own_step=not p.exclude_own_step,
                             obs_scaler=scaler)
        ms = ms.replace(ext=ms.ext.replace(credit=credit))
        terms = (prior_term(ms.ext.lam, credit, self.variant, clip=p.clip_targets,
                            shift=self.shift),)
        if p.unlabelled_segments:
            terms += (unlabelled_prior_term(
                ms.ext.lam, self.unlabelled_segments(rs, ms.ext.wm.params, ms.prefs.capacity,
                                                     scaler),
                reward_cfg=reward_config(self.cfg.pebble), clip=p.clip_targets,
                shift=self.shift),)
        return terms, ms

    def unlabelled_segments(self, rs: RunState, params, capacity: int, scaler):
        """`unlabelled_segments` segments of the replay buffer, drawn afresh for the round,
        with their α (the method's variant), as rows of the preference store."""
        p = self.prior_cfg
        obs, act = replay_segments(rs.key, rs.replay, p.unlabelled_segments,
                                   segment_len=self.segment_len,
                                   episode_len=self.kit.env.episode_length)
        alpha = segment_credit(params, wm.scaled(scaler, obs), act, self.wm_cfg,
                               query=p.attention_query, own_step=not p.exclude_own_step)
        return rows_of_pool(obs, act, variant_alpha(alpha, self.variant), capacity)

    def round_metrics(self, ms: PebbleState, reward_cfg) -> dict:
        """Attention entropy (normalised by log T: 1 = uniform) and the fraction of targets
        α·R̂ outside the tanh reward's range [-1, 1], over the stored pairs."""
        prefs, credit = ms.prefs, ms.ext.credit
        real = jnp.arange(prefs.capacity) < prefs.count
        n = jnp.maximum(prefs.count, 1).astype(jnp.float32) * 2
        t = credit.alpha1.shape[-1]
        alpha = variant_alpha(jnp.concatenate([credit.alpha1, credit.alpha2]), self.variant)
        ent = -jnp.sum(alpha * jnp.log(jnp.maximum(alpha, 1e-12)), -1) / jnp.log(t)
        mask2 = jnp.concatenate([real, real])
        return {"prior/attention_entropy": jnp.sum(ent * mask2) / n,
                "prior/target_out_of_range": unreachable_targets(
                    ms.reward, prefs, credit, reward_cfg, self.variant, self.shift)}

    # -- host side -------------------------------------------------------------------------
    def run_event(self, rs: RunState, step: int):
        name, fn = self._world_model_program(step == self.first_round_step)
        compiled = self.kit.compile(name, fn, rs)
        t0 = time.perf_counter()
        rs, metrics = jax.block_until_ready(compiled(rs))
        metrics = dict(metrics)
        metrics["perf/world_model_s"] = np.full(len(self.cfg.seeds), time.perf_counter() - t0)
        return rs, metrics

    def programs(self, rs: RunState):
        later = len(self.event_steps()) > 1
        return [(*self._world_model_program(pretrain), (rs,))
                for pretrain in (True, False) if pretrain or later]

    def _world_model_program(self, pretrain: bool):
        return ("world_model/pretrain" if pretrain else "world_model/update",
                self.kit.per_seed(partial(self.train_world_model, pretrain=pretrain),
                                  donate_argnums=0, physics_free=True))


# the world model at the paper's size (TWM: 10 layers x 256) costs seconds per update on a CPU;
# the CPU presets shrink it and keep the schedule (j = 2000) and the loss
REDUCED_WORLD_MODEL = dict(wm_embed=64, wm_layers=2, wm_heads=2, wm_head_dim=32, wm_ff=256,
                           wm_obs_hidden=256, wm_head_hidden=256, wm_head_depth=2, wm_batch=32,
                           wm_pretrain_steps=300, wm_update_steps=30)
SMOKE_WORLD_MODEL = dict(wm_embed=32, wm_layers=1, wm_heads=2, wm_head_dim=16, wm_ff=64,
                         wm_obs_hidden=64, wm_obs_depth=1, wm_head_hidden=64, wm_head_depth=1,
                         wm_batch=8, wm_pretrain_steps=10, wm_update_steps=2)


def prior_preset(task: str, preset: str, sac: SACConfig) -> dict:
    """PEBBLE's preset plus λ from appendix Table 4 (5 DMC, 1000 MetaWorld) and the world
    model's size per preset."""
    sizes = {"paper": {}, "reduced": REDUCED_WORLD_MODEL, "smoke": SMOKE_WORLD_MODEL}[preset]
    return {**pebble_preset(task, preset, sac),
            "prior": PriorConfig(lam=task_table.values(task).prior_lambda, **sizes)}


_VARIANT = {"prior": "raw", "prior_nrp": "nrp"}


def build(cfg, kit, variant: str) -> Pebble:
    return Pebble(cfg, kit, extension=WorldModelPrior(cfg, kit, variant))


def spec(name: str) -> MethodSpec:
    return MethodSpec(name=name, build=partial(build, variant=_VARIANT[name]),
                      sections={"pebble": PebbleConfig, "prior": PriorConfig},
                      preset=prior_preset, has_world_model=True)
