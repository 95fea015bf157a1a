"""MRN, Meta-Reward-Net (Liu et al. 2022; RyanLiu112/MRN `train_MRN.py`): PEBBLE plus a bi-level
meta step (hprior_jax.pbrl.meta_reward) that fits the reward ensemble to what the critic needs
to rank the labelled segments.

Schedule on top of PEBBLE's: at every global step t after the first round with
t % num_meta_steps == 0 while labels remain (the feedback given by the rounds at steps <= t is
below the budget), the meta step REPLACES that step's SAC update, and the whole replay buffer
is relabelled after it. Once the budget is spent, MRN is PEBBLE.

Decisions:
- The meta step runs as a host event before env step t (after a feedback round at the same
  step, as in the original), and the SAC phase skips its update at t. The original picks the
  action of step t before the update; here step t acts with the updated policy (as PEBBLE's
  rounds do in this loop).
- The outer loss reads the `queries_per_round` most recently stored pairs (the original's
  `reward_batch`, a ring slice ending at the write pointer).
- The bootstrap mask: the original's meta step uses `not_done`, which is 0 at time-limit ends,
  while every other update uses `not_done_no_max`. `time_limit_terminal` (default True)
  replicates that; False bootstraps as everywhere else.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from hprior_jax.buffers import replay
from hprior_jax.buffers.episodes import episode_ends
from hprior_jax.envs import task_info
from hprior_jax.methods.base import Phase
from hprior_jax.methods.pebble import Pebble
from hprior_jax.methods.pebble_family import PebbleConfig, PebbleState, pebble_preset
from hprior_jax.methods.registry import MethodSpec
from hprior_jax.pbrl.meta_reward import bilevel_update
from hprior_jax.pbrl.relabel import relabel_rewards


@dataclass(frozen=True)
class MrnConfig:
    num_meta_steps: int = 5000
    """Env steps between meta steps (MRN `config/train_MRN.yaml`; its README uses 1000 for
    walker and 10000 for door-open)."""
    outer_weight: float = 0.1
    """Weight of the outer (preference) loss on the virtually updated critic."""
    time_limit_terminal: bool = True
    """Treat time-limit ends as terminal in the meta step, as the original's `not_done`."""

    def __post_init__(self):
        if self.num_meta_steps <= 0 or self.outer_weight < 0:
            raise ValueError("need --mrn.num-meta-steps > 0 and --mrn.outer-weight >= 0")


class Mrn(Pebble):
    def __init__(self, cfg, kit):
        super().__init__(cfg, kit)
        self.mcfg = cfg.mrn
        m, first = cfg.mrn.num_meta_steps, self.first_round_step
        given = lambda t: sum(q for s, q in self.rounds() if s <= t)  # rounds run before
        self._meta_steps = [t for t in range((first // m + 1) * m, cfg.steps, m)
                            if given(t) < self.pcfg.max_feedback]

    def meta_steps(self) -> list[int]:
        """Global steps whose SAC update is a meta step: after the first round, multiples of
        `num_meta_steps`, while the feedback given so far is below the budget."""
        return self._meta_steps

    def event_steps(self):
        return sorted(set(super().event_steps()) | set(self.meta_steps()))

    def phases(self):
        """PEBBLE's, with the SAC update of a meta step skipped (the meta step made it)."""
        *before, sac = super().phases()
        meta = jnp.asarray(self.meta_steps() or [-1], jnp.int32)
        kit, update = self.kit, sac.step

        def step(rs, obs, t, keys):
            def skip(rs):
                zeros = jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype),
                                     jax.eval_shape(update, rs, obs, t, keys)[2])
                return kit.sac.act(rs.sac.actor, obs, keys[0]), rs, zeros

            return jax.lax.cond(jnp.any(t == meta), skip, lambda rs: update(rs, obs, t, keys), rs)

        return (*before, Phase(sac.name, sac.start, step, sac.metrics))

    # -- per-seed pure function --------------------------------------------------------------
    def meta_step(self, rs, step: jax.Array):
        buf, ms = rs.replay, rs.method
        key, k_sample, k_update = jax.random.split(rs.key, 3)
        idx = replay.sample_indices(buf, k_sample, self.kit.sac.cfg.batch_size)
        batch = replay.gather(buf, idx)
        if self.mcfg.time_limit_terminal:
            last = episode_ends(idx, self.kit.env.episode_length)
            batch = batch._replace(not_done=batch.not_done * (~last))
        pairs, mask = recent_pairs(ms, self.pcfg.queries_per_round)
        sac, params, opt, metrics = bilevel_update(
            self.kit.sac, rs.sac, ms.reward, ms.reward_opt, batch, pairs, mask, k_update, step,
            reward_tx=self.reward_tx, reward_cfg=self.reward_cfg,
            outer_weight=self.mcfg.outer_weight)
        reward = relabel_rewards(params, buf.obs, buf.action, buf.reward, buf.size,
                                 reward_cfg=self.reward_cfg)
        rs = rs.replace(sac=sac, replay=buf.replace(reward=reward), key=key,
                        method=ms.replace(reward=params, reward_opt=opt))
        return rs, {k: metrics[k] for k in ("mrn/outer_loss", "mrn/batch_reward",
                                            "train/critic_loss")}

    # -- host side -------------------------------------------------------------------------
    def run_event(self, rs, step: int):
        metrics = {}
        if step in super().event_steps():
            rs, metrics = super().run_event(rs, step)
        if step in self.meta_steps():
            fn = self._meta_program()
            t = np.int32(step)
            compiled = self.kit.compile("meta_step", fn, rs, t)
            t0 = time.perf_counter()
            rs, meta = jax.block_until_ready(compiled(rs, t))
            metrics = {**metrics, **meta,
                       "perf/meta_step_s": np.full(len(self.cfg.seeds), time.perf_counter() - t0)}
        return rs, metrics

    def programs(self, rs):
        meta = [("meta_step", self._meta_program(), (rs, np.int32(0)))] if self.meta_steps() else []
        return super().programs(rs) + meta

    def _meta_program(self):
        return self.kit.per_seed(self.meta_step, (0, None), donate_argnums=0)


def recent_pairs(ms: PebbleState, n: int):
    """The `n` most recently stored pairs (ring order, ending at the write pointer) and a mask
    of the rows that hold a pair."""
    prefs = ms.prefs
    rows = (prefs.ptr - n + jnp.arange(n)) % prefs.capacity
    mask = jnp.arange(n) >= n - prefs.count
    batch = jax.tree.map(lambda x: x[rows], prefs.as_batch())
    return batch, mask


def mrn_preset(task: str, preset: str, sac) -> dict:
    """PEBBLE's preset plus MRN's config; the smoke preset meta-steps every episode."""
    mrn = MrnConfig(num_meta_steps=task_info(task).episode_length) if preset == "smoke" else MrnConfig()
    return {**pebble_preset(task, preset, sac), "mrn": mrn}


def spec(name: str) -> MethodSpec:
    return MethodSpec(name=name, build=Mrn, sections={"pebble": PebbleConfig, "mrn": MrnConfig},
                      preset=mrn_preset)
