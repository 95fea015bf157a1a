"""One lab round of one cell (seed, rule): query -> teacher -> credit of the new pairs ->
reward update on every stored pair, as the RL loop's feedback rounds do on fixed episodes. A
learned credit (`lab.learned_credit`) trains its model on the stored pairs first and credits
every stored pair afresh."""
from __future__ import annotations

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp
import optax
from flax import struct

from hprior_jax.buffers import preferences
from hprior_jax.lab.config import (BISIM_STREAM, CREDITS, LEARNED_CREDITS, Episodes, GivenLabels,
                                   RuleArgs)
from hprior_jax.lab.learned_credit import learned_credits
from hprior_jax.lab.seed_world_model import SeedContext
from hprior_jax.networks.reward_ensemble import init_reward_ensemble, mean_reward
from hprior_jax.pbrl.bisim import BisimTransitions, bisim_term
from hprior_jax.pbrl.preference import train_reward
from hprior_jax.pbrl.query import pairs_at, round_queries
from hprior_jax.pbrl.teacher import TeacherOutput, compute_thresholds, teacher_labels
from hprior_jax.prior import world_model as wm
from hprior_jax.prior.attention import credit_from_attention, segment_attention
from hprior_jax.prior.diagnostics import unreachable_targets
from hprior_jax.prior.loss import PairCredit, nrp_alpha, prior_term, rvar_alpha
from hprior_jax.prior.unlabelled import STREAM as UNLABELLED_STREAM
from hprior_jax.prior.unlabelled import UnlabelledSegments, rows_of_pool, unlabelled_prior_term

LEARNED_STREAM = 0x1EA2  # folded off a round's key: the credit models leave the other draws alone


@struct.dataclass
class Cell:
    """One (seed, rule): its reward ensemble and the labelled pairs with their credit."""

    reward: dict
    opt: optax.OptState
    prefs: preferences.PreferenceStore
    credit: PairCredit
    key: jax.Array


class CellRounds:
    """The per-cell functions of a lab (pure, vmapped over cells by `Lab`); they read the
    lab's `cfg`, segment length `T`, optimizer `tx`, sizes and `data.episode_length`."""

    def init_cell(self, key: jax.Array, capacity: int) -> Cell:
        params = init_reward_ensemble(key, self.obs_size, self.act_size, self.cfg.reward)
        return Cell(reward=params, opt=self.tx.init(params),
                    prefs=preferences.init(self.T, self.obs_size, self.act_size, capacity),
                    credit=PairCredit.uniform(capacity, self.T), key=key)

    def credit(self, ctx: SeedContext, credit_id, obs, act, true_r) -> jax.Array:
        """α[B, T] of segments under the rule `credit_id` (an index into CREDITS)."""
        uniform = rvar_alpha(true_r)  # 1/T at every step (RVAR's credit)
        if ctx.wm_params is None:
            attention = no_own_step = uniform
        else:
            attn = segment_attention(ctx.wm_params, wm.scaled(ctx.obs_scaler, obs), act,
                                     self.cfg.world_model)
            attention, no_own_step = (
                jax.vmap(partial(credit_from_attention, num_steps=self.T,
                                 query=self.cfg.attention_query, own_step=own))(attn)
                for own in (True, False))  # one pass of the world model for both
        share = jnp.maximum(true_r, 0.0)
        total = share.sum(-1, keepdims=True)
        oracle = jnp.where(total > 1e-8, share / jnp.maximum(total, 1e-8), uniform)
        options = {"none": uniform, "attention": attention,
                   "attention_nrp": nrp_alpha(attention), "uniform": uniform,
                   "positional": jnp.broadcast_to(ctx.profile, true_r.shape), "oracle": oracle,
                   "attention_no_own_step": no_own_step, "bisimulation": uniform,
                   # placeholders: a learned credit credits every stored pair each round
                   **{c: uniform for c in LEARNED_CREDITS}}
        return jnp.stack([options[c] for c in CREDITS])[credit_id]

    def round(self, cell: Cell, ctx: SeedContext, rule: RuleArgs, num_queries, first,
              train: Episodes, mean_return, given: GivenLabels | None, *, queries: int,
              batch_size: int, feed: str):
        """Query -> teacher -> credit of the new pairs -> reward update on every stored pair.
        The first round's queries are uniform (as in BPref), later ones `feed`: both are
        drawn and `first` (traced) picks, so every round runs one compiled program. With
        `given` labels (arrays), those pairs and labels replace the query and the teacher."""
        cfg = self.cfg
        key, k_query, k_teacher, k_train = jax.random.split(cell.key, 4)
        if given is not None:
            pairs, out = self._given(train, given)
        else:
            pairs = round_queries(
                k_query, cell.reward, train.obs, train.act, train.reward,
                jnp.int32(train.obs.shape[0]), first=first, feed=feed, mb_size=queries,
                segment_len=self.T, large_batch=cfg.large_batch, num_queries=num_queries,
                reward_cfg=cfg.reward)
            thresholds = compute_thresholds(cfg.teacher, mean_return, self.T,
                                            self.data.episode_length, first_round=first)
            out = teacher_labels(k_teacher, pairs.true_r1, pairs.true_r2, cfg.teacher,
                                 thresholds)
        keep = out.valid & pairs.mask
        both = lambda a, b: jnp.concatenate([a, b])
        alpha = self.credit(ctx, rule.credit, both(pairs.obs1, pairs.obs2),
                            both(pairs.act1, pairs.act2), both(pairs.true_r1, pairs.true_r2))
        slot = preferences.slots(cell.prefs, keep)
        credit = PairCredit(alpha1=preferences.put_rows(cell.credit.alpha1, alpha[:queries], slot),
                            alpha2=preferences.put_rows(cell.credit.alpha2, alpha[queries:], slot))
        prefs = preferences.add(cell.prefs, preferences.PreferenceBatch(
            pairs.obs1, pairs.act1, pairs.obs2, pairs.act2, out.labels), keep)
        learned = {}
        if cfg.learned_kinds:  # every rule trains them (used by the learned rules only)
            credit, learned = self.learned_credit(
                jax.random.fold_in(k_train, LEARNED_STREAM), train, prefs, credit, rule.credit)
        terms = (prior_term(rule.lam, credit, "raw", rule.clip, rule.shift),)
        if cfg.needs_unlabelled:  # every rule computes it (weight 0 but its rule's)
            terms += (unlabelled_prior_term(
                rule.lam * rule.unlabelled,
                self.unlabelled_segments(jax.random.fold_in(k_train, UNLABELLED_STREAM), ctx,
                                         train, prefs.capacity, rule.credit),
                reward_cfg=cfg.reward, clip=rule.clip, shift=rule.shift),)
        if cfg.needs_bisim:  # every rule computes it (weight 0 but the bisim rule's)
            transitions = episode_transitions(jax.random.fold_in(k_train, BISIM_STREAM), train,
                                              prefs.capacity, cfg.bisim_transitions)
            terms += (bisim_term(rule.bisim_lam, transitions, reward_cfg=cfg.reward,
                                 discount=cfg.discount),)
        params, opt, m = train_reward(cell.reward, cell.opt, prefs, k_train, tx=self.tx,
                                      reward_cfg=cfg.reward,
                                      cfg=dataclasses.replace(cfg.preference,
                                                              batch_size=batch_size),
                                      terms=terms)
        metrics = {"labels": prefs.count, "epochs": m["reward/epochs"],
                   "train_acc": m["reward/train_acc"], "ce": m["reward/loss"],
                   "prior_loss": m["prior/loss"],
                   # ‖∇ λ·L_prior‖ / ‖∇ CE‖ where the round's update starts
                   "prior_grad_ratio": m["prior/loss/grad_ratio"],
                   # of the rule's own credit (uniform for pebble, which does not use it)
                   "target_out_of_range": unreachable_targets(params, prefs, credit,
                                                              cfg.reward, shift=rule.shift)}
        metrics |= learned
        if cfg.needs_unlabelled:
            metrics |= {"unlabelled_prior_loss": m["prior/unlabelled_loss"]}
        if cfg.needs_bisim:
            metrics |= {"bisim_loss": m["bisim/loss"],
                        "bisim_grad_ratio": m["bisim/loss/grad_ratio"]}
        return Cell(reward=params, opt=opt, prefs=prefs, credit=credit, key=key), metrics

    def learned_credit(self, key, train: Episodes, prefs, credit: PairCredit, credit_id):
        """Every stored pair's credit under the rule `credit_id` when it is a learned one (a
        credit model trained now on `prefs`, or its positional profile), else `credit` as it
        is; and each credit model's BT accuracy on its last step (`credit_acc/KIND`)."""
        options, accuracy = {}, {}
        for i, kind in enumerate(self.cfg.learned_kinds):
            pairs, profile, accuracy[f"credit_acc/{kind}"] = learned_credits(
                kind, self.cfg.credit_model, jax.random.fold_in(key, i), prefs, train.obs,
                train.act, self.cfg.profile_segments)
            options |= {kind: pairs, f"{kind}_positional": profile}
        for name, option in options.items():
            pick = credit_id == CREDITS.index(name)
            credit = jax.tree.map(lambda a, b: jnp.where(pick, a, b), option, credit)
        return credit, accuracy

    def unlabelled_segments(self, key, ctx: SeedContext, train: Episodes, capacity: int,
                            credit_id) -> UnlabelledSegments:
        """`unlabelled_segments` training segments drawn afresh, with the rule's credit
        `credit_id` (an index into CREDITS), as rows of the preference store."""
        e, length = train.obs.shape[:2]
        flat = lambda x: x.reshape((e * length,) + x.shape[2:])
        obs, act = wm.sample_segments(key, flat(train.obs), flat(train.act), jnp.int32(e * length),
                                      episode_len=length, batch_size=self.cfg.unlabelled_segments,
                                      segment_len=self.T)
        # no true reward: the oracle credit would be uniform here (no rule asks for it)
        alpha = self.credit(ctx, credit_id, obs, act, jnp.zeros(obs.shape[:2]))
        return rows_of_pool(obs, act, alpha, capacity)

    def _given(self, train: Episodes, given: GivenLabels):
        """The given pairs and labels as the round's queries and teacher output."""
        pairs = pairs_at(train.obs, train.act, train.reward, given.pair_index, self.T)
        return pairs, TeacherOutput(labels=given.labels, valid=given.valid,
                                    equal=given.labels == -1,
                                    mistake=jnp.zeros(given.labels.shape, bool))

    def predict(self, cell, test: Episodes) -> jax.Array:
        """r̂ (the ensemble mean, what the agent trains on) of every held-out state [E, L]."""
        return mean_reward(cell.reward, test.obs, test.act, self.cfg.reward)


def episode_transitions(key: jax.Array, episodes: Episodes, capacity: int,
                        per_row: int) -> BisimTransitions:
    """BISIM's transitions from fixed episodes: `per_row` per stored-pair row, each a step
    drawn uniformly (with replacement) among the steps that are not their episode's last, and
    the step after it (what `pbrl.bisim.sample_transitions` draws from a replay buffer)."""
    e, length = episodes.obs.shape[:2]
    k_ep, k_step = jax.random.split(key)
    ep = jax.random.randint(k_ep, (capacity, per_row), 0, e)
    t = jax.random.randint(k_step, (capacity, per_row), 0, length - 1)
    return BisimTransitions(obs=episodes.obs[ep, t], act=episodes.act[ep, t],
                            next_obs=episodes.obs[ep, t + 1], next_act=episodes.act[ep, t + 1],
                            valid=jnp.ones((capacity, per_row), bool))


def minibatch_size(labels: int, batch_size: int) -> int:
    """The smallest of 16, 32, 64, ... >= `labels`, at most `batch_size`. While every stored
    pair fits in one minibatch, an epoch is that one minibatch whatever its padding (padded
    rows are masked), so a smaller static batch computes the same update for less: at 25
    labels a 32-row batch costs a quarter of a 128-row one."""
    size = 16
    while size < min(labels, batch_size):
        size *= 2
    return min(size, batch_size)
