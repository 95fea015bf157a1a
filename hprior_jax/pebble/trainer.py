"""PEBBLE (Lee et al. 2021) on the shared training loop (BPref `train_PEBBLE.py`).

Schedule per seed, identical for every seed (so it is decided on the host):
  [0, seed)                uniform-random actions, no updates
  [seed, seed+unsup)       SAC whose critic target uses the k-NN state-entropy reward
  seed+unsup               first feedback round (always uniform queries), relabel the whole
                           buffer, reset the critic, `reset_update` SAC steps
  every num_interact after another round (configured query selection) while budget remains
  otherwise                one SAC step per env step on the learned reward

Deliberate differences from BPref, each harmless and stated here: BPref skips the SAC
update at exactly step `seed` and at step `seed+unsup` (its if/elif chain); we update there
too (2 extra updates in a run). The teacher reads true rewards from the replay buffer's
`true_reward` column; nothing that trains (SAC, the reward ensemble) ever reads it.
"""
from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from hprior_jax.buffers import preferences, replay
from hprior_jax.networks.reward_ensemble import RewardConfig, init_reward_ensemble, mean_reward
from hprior_jax.pebble.preference import PreferenceConfig, make_optimizer, train_reward
from hprior_jax.pebble.query import select_queries
from hprior_jax.pebble.relabel import relabel_rewards
from hprior_jax.pebble.state_entropy import (RunningMeanStd, init_running_mean_std,
                                             state_entropy_reward)
from hprior_jax.pebble.teacher import compute_thresholds, teacher_labels
from hprior_jax.train import RANDOM, SAC_METRICS, SAC_PHASE, RunState, Trainer

UNSUP = "unsup"
RETURN_WINDOW = 10  # BPref: teacher thresholds from the mean return of the last 10 episodes


@struct.dataclass
class PebbleState:
    reward: dict  # stacked ensemble params, leading axis K
    reward_opt: optax.OptState
    prefs: preferences.PreferenceStore
    entropy_stats: RunningMeanStd


class PebbleTrainer(Trainer):
    def __init__(self, cfg):
        super().__init__(cfg)
        p = self.pcfg = cfg.pebble
        L = self.env.episode_length
        if p.segment_len >= L:
            raise ValueError(f"--pebble.segment-len {p.segment_len} must be shorter than the "
                             f"episode ({L} steps) of {cfg.task}")
        if cfg.capacity % L or cfg.capacity < cfg.steps:
            raise ValueError(f"PbRL reads episodes straight from the replay buffer, so it must "
                             f"hold every step in whole episodes: make --steps a multiple of "
                             f"{L} and leave --replay-capacity at 0")
        if self.first_round_step >= cfg.steps:
            raise ValueError(f"no feedback round fits: the first comes at step "
                             f"{self.first_round_step} (seed + unsup steps) but --steps is "
                             f"{cfg.steps}; train longer or shorten pre-training")
        self.reward_cfg = RewardConfig(hidden_sizes=(p.reward_hidden,) * p.reward_depth,
                                       ensemble_size=p.ensemble_size)
        self.pref_cfg = PreferenceConfig(batch_size=p.reward_batch, max_epochs=p.reward_epochs,
                                         lr=p.reward_lr)
        self.reward_tx = make_optimizer(self.pref_cfg)

    # -- schedule --------------------------------------------------------------------------
    @property
    def first_round_step(self) -> int:
        return self.cfg.num_seed_steps + self.pcfg.num_unsup_steps

    @property
    def phases(self):
        return (RANDOM, UNSUP, SAC_PHASE)

    def phase_starts(self):
        return (self.cfg.num_seed_steps, self.first_round_step)

    def phase_metrics(self, phase):
        return {RANDOM: (), UNSUP: SAC_METRICS + ("train/intrinsic_reward",),
                SAC_PHASE: SAC_METRICS}[phase]

    def rounds(self) -> list[tuple[int, int]]:
        """(step, queries) of every feedback round: the last is clipped to the budget."""
        p = self.pcfg
        out = []
        for r in range(p.num_rounds):
            step = self.first_round_step + r * p.num_interact
            if step >= self.cfg.steps:
                break
            out.append((step, min(p.queries_per_round, p.max_feedback - r * p.queries_per_round)))
        return out

    def event_steps(self):
        return [s for s, _ in self.rounds()]

    # -- per-seed pure functions -----------------------------------------------------------
    def _init_extra(self, key):
        p = self.pcfg
        params = init_reward_ensemble(key, self.env.obs_size, self.env.action_size,
                                      self.reward_cfg)
        return PebbleState(
            reward=params, reward_opt=self.reward_tx.init(params),
            prefs=preferences.init(p.segment_len, self.env.obs_size, self.env.action_size,
                                   capacity=p.max_feedback),
            entropy_stats=init_running_mean_std())

    def _stored_reward(self, rs, obs, action, true_reward):
        # BPref stores r_hat(s, a) of the current ensemble with each new transition
        return mean_reward(rs.extra.reward, obs[None], action[None], self.reward_cfg)[0]

    def _intrinsic_reward(self, rs: RunState, batch):
        buf = rs.replay
        r, stats = state_entropy_reward(batch.obs, buf.obs, buf.size, rs.extra.entropy_stats,
                                        k=self.pcfg.knn_k,
                                        bpref_mean_bug=self.pcfg.bpref_entropy_mean_bug)
        rs = rs.replace(extra=rs.extra.replace(entropy_stats=stats))
        return r, rs, {"train/intrinsic_reward": jnp.mean(r)}

    def _phase_steps(self):
        steps = super()._phase_steps()
        steps[UNSUP] = partial(self._sac_step, reward_fn=self._intrinsic_reward)
        return steps

    def feedback_round(self, rs: RunState, num_queries: jax.Array, *, first: bool,
                       queries: int):
        """Query -> teacher -> reward update -> relabel (and, after the first round, the
        critic reset and `reset_update` SAC steps). Returns (rs, scalar metrics)."""
        p, L = self.pcfg, self.env.episode_length
        buf, ext = rs.replay, rs.extra
        key, k_query, k_teacher, k_reward, k_reset = jax.random.split(rs.key, 5)

        # the last `trajectory_episodes` complete episodes, straight from the replay buffer
        n_stored = buf.capacity // L
        window = min(p.trajectory_episodes, n_stored)
        n_episodes = buf.size // L
        start = jnp.maximum(n_episodes - window, 0)
        episodes = lambda x: jax.lax.dynamic_slice_in_dim(
            x.reshape((n_stored, L) + x.shape[1:]), start, window, axis=0)
        ep_obs, ep_act, ep_true = episodes(buf.obs), episodes(buf.action), episodes(buf.true_reward)
        count = jnp.minimum(n_episodes, window)

        pairs = select_queries(k_query, ext.reward, ep_obs, ep_act, ep_true, count,
                               rule="uniform" if first else p.feed_type, mb_size=queries,
                               segment_len=p.segment_len, large_batch=p.large_batch,
                               num_queries=num_queries, reward_cfg=self.reward_cfg)
        returns = ep_true.sum(-1)
        recent = (jnp.arange(window) < count) & (jnp.arange(window) >= count - RETURN_WINDOW)
        mean_return = jnp.sum(returns * recent) / jnp.maximum(recent.sum(), 1)
        thresholds = compute_thresholds(p.teacher, mean_return, p.segment_len, L,
                                        first_round=first)
        out = teacher_labels(k_teacher, pairs.true_r1, pairs.true_r2, p.teacher, thresholds)
        keep = out.valid & pairs.mask
        prefs = preferences.add(ext.prefs, preferences.PreferenceBatch(
            pairs.obs1, pairs.act1, pairs.obs2, pairs.act2, out.labels), keep)
        ext, rmetrics = self._train_reward(ext.replace(prefs=prefs), k_reward)
        reward = relabel_rewards(ext.reward, buf.obs, buf.action, buf.reward, buf.size,
                                 reward_cfg=self.reward_cfg)
        buf = buf.replace(reward=reward)
        sac = rs.sac
        if first:
            sac = self._reset_critic_and_update(sac, buf, k_reset)
        metrics = {
            "feedback/queries": num_queries.astype(jnp.float32),
            "feedback/labeled": jnp.sum(keep).astype(jnp.float32),
            "feedback/skipped": jnp.sum(pairs.mask & ~out.valid).astype(jnp.float32),
            "feedback/equal": jnp.sum(keep & out.equal).astype(jnp.float32),
            "feedback/mistakes": jnp.sum(keep & out.mistake & ~out.equal).astype(jnp.float32),
            "feedback/total_labeled": prefs.count.astype(jnp.float32),
            "reward/true_corr": masked_correlation(reward, buf.true_reward, buf.size),
            **rmetrics,
        }
        return rs.replace(sac=sac, replay=buf, extra=ext, key=key), metrics

    def _train_reward(self, ext: PebbleState, key: jax.Array):
        """The reward-ensemble update of a round on every stored pair (`ext.prefs`).
        -> (ext with the new reward params and optimiser state, scalar `reward/` metrics)."""
        params, opt, m = train_reward(ext.reward, ext.reward_opt, ext.prefs, key,
                                      tx=self.reward_tx, reward_cfg=self.reward_cfg,
                                      cfg=self.pref_cfg)
        return ext.replace(reward=params, reward_opt=opt), reward_round_metrics(m)

    def _reset_critic_and_update(self, sac_state, buf, key):
        """BPref `reset_critic` + `update_after_reset`: target EMA when index % 2 == 0."""
        k_init, k_updates = jax.random.split(key)
        sac_state = self.sac.reset_critic(sac_state, k_init)

        def body(state, i):
            k_sample, k_update = jax.random.split(jax.random.fold_in(k_updates, i))
            batch = replay.sample(buf, k_sample, self.sac.cfg.batch_size)
            return self.sac.update(state, batch, k_update, i)[0], None

        return jax.lax.scan(body, sac_state, jnp.arange(self.pcfg.reset_update))[0]

    # -- host side -------------------------------------------------------------------------
    def run_event(self, rs: RunState, step: int):
        rounds = dict(self.rounds())
        first = step == self.first_round_step
        queries = self.pcfg.queries_per_round
        fn = jax.jit(jax.vmap(partial(self.feedback_round, first=first, queries=queries),
                              in_axes=(0, None)), donate_argnums=0)
        n = np.int32(rounds[step])
        name = "feedback_round/first" if first else "feedback_round"
        return self._aot(name, fn, rs, n)(rs, n)


def reward_round_metrics(m: dict) -> dict:
    """The scalar `reward/` metrics logged per round from `train_reward`'s output."""
    return {"reward/epochs": m["reward/epochs"].astype(jnp.float32),
            "reward/train_acc": m["reward/train_acc"], "reward/loss": m["reward/loss"]}


def masked_correlation(x: jax.Array, y: jax.Array, n: jax.Array) -> jax.Array:
    """Pearson correlation of x[:n] and y[:n] (a diagnostic: learned vs true reward)."""
    w = (jnp.arange(x.shape[0]) < n).astype(jnp.float32)
    m = jnp.maximum(w.sum(), 1.0)
    xc = (x - jnp.sum(w * x) / m) * w
    yc = (y - jnp.sum(w * y) / m) * w
    return jnp.sum(xc * yc) / jnp.sqrt(jnp.sum(xc**2) * jnp.sum(yc**2) + 1e-12)
