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

With `--teacher human` a round is two programs with a person between them: `human_queries`
proposes the pairs (the same draws as the scripted round) and returns what their clips need,
the host asks the person (`kit.person`), and `human_learn` stores the answers and trains on
them exactly as the scripted round trains on its teacher's labels.
"""
from __future__ import annotations

from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from hprior_jax.buffers import episodes, preferences, replay
from hprior_jax.loop.devices import fetch
from hprior_jax.loop.state import RunState
from hprior_jax.methods.base import (RANDOM, SAC_METRICS, SAC_PHASE, Method, Phase, random_step,
                                     sac_step)
from hprior_jax.methods.pebble_family import (EpisodeWindow, Extension, PebbleConfig, PebbleState,
                                              pebble_preset, reward_config)
from hprior_jax.methods.registry import MethodSpec
from hprior_jax.networks.reward_ensemble import init_reward_ensemble, mean_reward
from hprior_jax.pbrl.preference import PreferenceConfig, make_optimizer, train_reward
from hprior_jax.pbrl.query import SegmentPairs, cut_segments, select_queries
from hprior_jax.pbrl.relabel import relabel_rewards
from hprior_jax.pbrl.state_entropy import init_running_mean_std, state_entropy_reward
from hprior_jax.pbrl.teacher import (TeacherOutput, TeacherThresholds, compute_thresholds,
                                     teacher_labels)

UNSUP = "unsup"
RETURN_WINDOW = 10  # BPref: teacher thresholds from the mean return of the last 10 episodes


class Pebble(Method):
    def __init__(self, cfg, kit, extension: Extension | None = None):
        super().__init__(cfg, kit)
        self.ext = extension or Extension()
        p = self.pcfg = cfg.pebble
        L = kit.env.episode_length
        if self.stored_segment_len >= L:
            raise ValueError(f"stored segments of {self.stored_segment_len} steps "
                             f"(--pebble.segment-len {p.segment_len}) must be shorter than the "
                             f"episode ({L} steps) of {cfg.task}")
        if cfg.capacity % L or cfg.capacity < cfg.steps:
            raise ValueError(f"PbRL reads episodes straight from the replay buffer, so it must "
                             f"hold every step in whole episodes: make --steps a multiple of "
                             f"{L} and leave --replay-capacity at 0")
        if self.first_round_step >= cfg.steps:
            raise ValueError(f"no feedback round fits: the first comes at step "
                             f"{self.first_round_step} (seed + unsup steps) but --steps is "
                             f"{cfg.steps}; train longer or shorten pre-training")
        self.reward_cfg = self.ext.reward_config(reward_config(p))
        self.pref_cfg = PreferenceConfig(batch_size=p.reward_batch, max_epochs=p.reward_epochs,
                                         lr=p.reward_lr)
        self.reward_tx = make_optimizer(self.pref_cfg)
        # a person's labels: the replay buffer keeps the physics state the clips are drawn from
        self.asks_person = p.teacher.human

    @property
    def stored_segment_len(self) -> int:
        """Steps of a stored (queried) segment: the teacher's H, longer for SURF's crops."""
        return self.pcfg.segment_len

    @property
    def judged_steps(self) -> slice:
        """The steps of a stored segment the teacher judges (and a person sees)."""
        return slice(0, self.stored_segment_len)

    # -- schedule --------------------------------------------------------------------------
    @property
    def first_round_step(self) -> int:
        return self.cfg.num_seed_steps + self.pcfg.num_unsup_steps

    def phases(self):
        kit = self.kit
        return (Phase(RANDOM, 0, random_step(kit)),
                Phase(UNSUP, self.cfg.num_seed_steps,
                      sac_step(kit, reward_fn=self._intrinsic_reward),
                      SAC_METRICS + ("train/intrinsic_reward",)),
                Phase(SAC_PHASE, self.first_round_step,
                      sac_step(kit, reward_fn=self.ext.agent_reward),
                      SAC_METRICS + self.ext.agent_metrics))

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
        return sorted({s for s, _ in self.rounds()} | set(self.ext.event_steps()))

    # -- per-seed pure functions -----------------------------------------------------------
    def init(self, key):
        p, env = self.pcfg, self.kit.env
        params = init_reward_ensemble(key, env.obs_size, env.action_size, self.reward_cfg)
        return PebbleState(
            reward=params, reward_opt=self.reward_tx.init(params),
            prefs=preferences.init(self.stored_segment_len, env.obs_size, env.action_size,
                                   capacity=p.max_feedback),
            entropy_stats=init_running_mean_std(), ext=self.ext.init(key))

    def stored_reward(self, rs, obs, action, true_reward):
        # BPref stores r_hat(s, a) of the current ensemble with each new transition
        return mean_reward(rs.method.reward, obs[None], action[None], self.reward_cfg)[0]

    def _intrinsic_reward(self, rs: RunState, batch, t):
        buf = rs.replay
        r, stats = state_entropy_reward(batch.obs, buf.obs, buf.size, rs.method.entropy_stats,
                                        k=self.pcfg.knn_k,
                                        bpref_mean_bug=self.pcfg.bpref_entropy_mean_bug)
        rs = rs.replace(method=rs.method.replace(entropy_stats=stats))
        return r, rs, {"train/intrinsic_reward": jnp.mean(r)}

    def feedback_round(self, rs: RunState, num_queries: jax.Array, *, first: bool,
                       queries: int):
        """Query -> teacher -> reward update -> relabel (and, after the first round, the
        critic reset and `reset_update` SAC steps). Returns (rs, scalar metrics)."""
        pairs, thresholds = self.propose(rs, num_queries, first=first, queries=queries)
        out = teacher_labels(_round_keys(rs).teacher, *self.teacher_rewards(pairs),
                             self.pcfg.teacher, thresholds)
        return self.learn(rs, pairs, out, num_queries, first=first)

    def propose(self, rs: RunState, num_queries: jax.Array, *, first: bool, queries: int
                ) -> tuple[SegmentPairs, TeacherThresholds]:
        """This round's pairs (`queries` static, the first `num_queries` inside the budget)
        and the scripted teacher's skip/equal thresholds."""
        p, L = self.pcfg, self.kit.env.episode_length
        window = self.recent_episodes(rs.replay)
        pairs = select_queries(_round_keys(rs).query, rs.method.reward, window.obs, window.act,
                               window.true_reward, window.count,
                               rule="uniform" if first else p.feed_type,
                               mb_size=queries, segment_len=self.stored_segment_len,
                               large_batch=p.large_batch, num_queries=num_queries,
                               reward_cfg=self.reward_cfg)
        returns = window.true_reward.sum(-1)
        n = window.true_reward.shape[0]
        recent = (jnp.arange(n) < window.count) & (jnp.arange(n) >= window.count - RETURN_WINDOW)
        mean_return = jnp.sum(returns * recent) / jnp.maximum(recent.sum(), 1)
        return pairs, compute_thresholds(p.teacher, mean_return, p.segment_len, L,
                                         first_round=first)

    def learn(self, rs: RunState, pairs: SegmentPairs, out: TeacherOutput,
              num_queries: jax.Array, *, first: bool):
        """Store the round's labels, update the reward model, relabel the buffer (and after
        the first round reset the critic). Returns (rs, scalar metrics)."""
        buf, ms = rs.replay, rs.method
        keys = _round_keys(rs)
        window = self.recent_episodes(buf)
        keep = out.valid & pairs.mask
        prefs = preferences.add(ms.prefs, preferences.PreferenceBatch(
            pairs.obs1, pairs.act1, pairs.obs2, pairs.act2, out.labels), keep)
        # a stream folded off the query key: PEBBLE's own draws stay what they were
        ms = self.after_labels(ms.replace(prefs=prefs), window, num_queries,
                               jax.random.fold_in(keys.query, 1))
        ms, rmetrics = self._train_reward(rs, ms, keys.reward)
        reward = relabel_rewards(ms.reward, buf.obs, buf.action, buf.reward, buf.size,
                                 reward_cfg=self.reward_cfg)
        buf = buf.replace(reward=reward)
        rs = rs.replace(replay=buf, method=ms, key=keys.next)
        if first:
            rs = rs.replace(sac=self._reset_critic_and_update(rs, keys.reset))
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
        return rs, metrics

    def human_queries(self, rs: RunState, num_queries: jax.Array, *, first: bool,
                      queries: int) -> tuple[SegmentPairs, dict]:
        """A person's round, first half: the pairs `propose` draws, and what a person is
        shown of them: the judged steps' physics states ("physics1"/"physics2": {field:
        [Q, H, ...]}) and true rewards ("true_reward1"/"true_reward2" [Q, H], kept beside
        the answers to tell later how a person's labels differ from the true reward's)."""
        pairs, _ = self.propose(rs, num_queries, first=first, queries=queries)
        window = self.recent_episodes(rs.replay)
        judged = self.judged_steps
        o = pairs.origin
        cut = lambda x, side: cut_segments(x, o[:, 2 * side - 2], o[:, 2 * side - 1],
                                           self.stored_segment_len)[:, judged]
        r1, r2 = self.teacher_rewards(pairs)
        shown = {"physics1": jax.tree.map(lambda x: cut(x, 1), window.physics),
                 "physics2": jax.tree.map(lambda x: cut(x, 2), window.physics),
                 "true_reward1": r1, "true_reward2": r2}
        return pairs, shown

    def human_learn(self, rs: RunState, pairs: SegmentPairs, labels: jax.Array,
                    valid: jax.Array, num_queries: jax.Array, *, first: bool):
        """A person's round, second half: B-Pref labels [Q] (0 left, 1 right, -1 equal) and
        `valid` (False: skipped) -> `learn`. Its "mistakes" count the answers that disagree
        with the true reward's order (the oracle's label)."""
        oracle = teacher_labels(_round_keys(rs).teacher, *self.teacher_rewards(pairs))
        equal = labels == -1
        out = TeacherOutput(labels=labels, valid=valid, equal=equal,
                            mistake=(labels != oracle.labels) & ~equal)
        return self.learn(rs, pairs, out, num_queries, first=first)

    def recent_episodes(self, buf) -> EpisodeWindow:
        """The last `trajectory_episodes` complete episodes, straight from the replay buffer
        (which holds whole episodes in order from row 0)."""
        last, count = episodes.last_episodes(buf.size, buf.capacity, self.kit.env.episode_length,
                                             self.pcfg.trajectory_episodes)
        return EpisodeWindow(last(buf.obs), last(buf.action), last(buf.true_reward), count,
                             jax.tree.map(last, buf.physics))

    def teacher_rewards(self, pairs) -> tuple[jax.Array, jax.Array]:
        """The true per-step rewards the teacher judges each segment of a pair by."""
        return pairs.true_r1[:, self.judged_steps], pairs.true_r2[:, self.judged_steps]

    def after_labels(self, ms: PebbleState, window: EpisodeWindow, num_queries: jax.Array,
                     key: jax.Array) -> PebbleState:
        """After the round's labels are stored, before the reward update (SURF draws its
        unlabelled pairs here). PEBBLE: nothing."""
        return ms

    def _train_reward(self, rs: RunState, ms: PebbleState, key: jax.Array):
        """The reward-ensemble update of a round on every stored pair (`ms.prefs`), with the
        extension's terms. -> (ms with the new reward params and optimiser state, scalar
        metrics: `reward/` and each term's unweighted loss under its name)."""
        terms, ms = self.ext.reward_terms(rs, ms)
        params, opt, m = train_reward(ms.reward, ms.reward_opt, ms.prefs, key,
                                      tx=self.reward_tx, reward_cfg=self.reward_cfg,
                                      cfg=self.pref_cfg, terms=terms)
        ms = ms.replace(reward=params, reward_opt=opt)
        m = {k: (v.astype(jnp.float32) if k == "reward/epochs" else v) for k, v in m.items()
             if k != "reward/train_acc_member"}
        return ms, {**m, **self.ext.round_metrics(ms, self.reward_cfg)}

    def _reset_critic_and_update(self, rs: RunState, key):
        """BPref `reset_critic` + `update_after_reset`: target EMA when index % 2 == 0. The
        agent's reward is the extension's, at the global step of the first round (RUNE's β)."""
        k_init, k_updates = jax.random.split(key)
        sac_state = self.kit.sac.reset_critic(rs.sac, k_init)
        step = jnp.asarray(self.first_round_step, jnp.int32)

        def body(state, i):
            k_sample, k_update = jax.random.split(jax.random.fold_in(k_updates, i))
            batch = replay.sample(rs.replay, k_sample, self.kit.sac.cfg.batch_size)
            reward, _, _ = self.ext.agent_reward(rs, batch, step)
            return self.kit.sac.update(state, batch._replace(reward=reward), k_update, i)[0], None

        return jax.lax.scan(body, sac_state, jnp.arange(self.pcfg.reset_update))[0]

    # -- host side -------------------------------------------------------------------------
    def run_event(self, rs: RunState, step: int):
        metrics = {}
        if step in self.ext.event_steps():  # e.g. PRIOR's world model, before the round
            rs, metrics = self.ext.run_event(rs, step)
        rounds = dict(self.rounds())
        if step in rounds:
            first = step == self.first_round_step
            n = np.int32(rounds[step])
            if self.asks_person:
                rs, round_metrics = self._human_round(rs, step, n, first)
            else:
                name, fn = self._round_program(first)
                rs, round_metrics = self.kit.compile(name, fn, rs, n)(rs, n)
            metrics = {**metrics, **round_metrics}
        return rs, metrics

    def programs(self, rs: RunState):
        n = np.int32(self.pcfg.queries_per_round)
        later = len(self.rounds()) > 1  # the first round always fits (checked at build)
        rounds = [(*self._round_program(first), (rs, n))
                  for first in (True, False) if first or later]
        ext = self.ext.programs(rs)  # its first event comes before the first round (PRIOR's)
        return ext[:1] + rounds[:1] + ext[1:] + rounds[1:]

    def _round_program(self, first: bool):
        """(name, fn) of a round's program: the whole scripted round, or the first half of
        a person's (the second compiles while the person answers)."""
        suffix = "/first" if first else ""
        if self.asks_person:
            return f"human_queries{suffix}", self.kit.per_seed(
                partial(self.human_queries, first=first, queries=self.pcfg.queries_per_round),
                (0, None))
        return f"feedback_round{suffix}", self.kit.per_seed(
            partial(self.feedback_round, first=first, queries=self.pcfg.queries_per_round),
            (0, None), donate_argnums=0)

    def _human_round(self, rs: RunState, step: int, n: np.int32, first: bool):
        """Propose (compiled), ask the person (host, may wait for hours or stop the run),
        learn from the answers (compiled)."""
        suffix = "/first" if first else ""
        name, propose = self._round_program(first)
        pairs, shown = self.kit.compile(name, propose, rs, n)(rs, n)
        number = [s for s, _ in self.rounds()].index(step) + 1
        labels, valid = self.kit.person.ask(number, step, fetch(shown), int(n))
        labels, valid = self.kit.place(labels), self.kit.place(valid)
        learn = self.kit.per_seed(partial(self.human_learn, first=first),
                                  (0, 0, 0, 0, None), donate_argnums=0)
        args = (rs, pairs, labels, valid, n)
        return self.kit.compile(f"human_learn{suffix}", learn, *args)(*args)


class RoundKeys(NamedTuple):
    next: jax.Array  # the run's key after the round
    query: jax.Array
    teacher: jax.Array
    reward: jax.Array
    reset: jax.Array


def _round_keys(rs: RunState) -> RoundKeys:
    """A round's streams, split off the run key it starts with (so both halves of a person's
    round, and the scripted round, draw the same)."""
    return RoundKeys(*jax.random.split(rs.key, 5))


def masked_correlation(x: jax.Array, y: jax.Array, n: jax.Array) -> jax.Array:
    """Pearson correlation of x[:n] and y[:n] (a diagnostic: learned vs true reward)."""
    w = (jnp.arange(x.shape[0]) < n).astype(jnp.float32)
    m = jnp.maximum(w.sum(), 1.0)
    xc = (x - jnp.sum(w * x) / m) * w
    yc = (y - jnp.sum(w * y) / m) * w
    return jnp.sum(xc * yc) / jnp.sqrt(jnp.sum(xc**2) * jnp.sum(yc**2) + 1e-12)


def spec(name: str) -> MethodSpec:
    return MethodSpec(name=name, build=Pebble, sections={"pebble": PebbleConfig},
                      preset=pebble_preset)
