"""Reward learning on fixed data, every (seed, rule) cell in one compiled program (SURF in
one of its own).

A cell trains one reward ensemble the way the RL loop's feedback rounds do (queries from the
training episodes, the first round uniform, then `feed_type`; the teacher; `train_reward` with
its epochs and 0.97 early stop, on every stored pair), with CE + λ·L_prior where the rule
decides the credit α of each stored pair:

  none           PEBBLE: cross-entropy only (λ = 0)
  attention      PRIOR: the world model's attention credit (the RL loop's α)
  attention_nrp  PRIOR-NRP: the same α min-max normalised and softmaxed (appendix eq. 9)
  attention_no_own_step  ablation: attention α without the query's own (last) step
  bisimulation   BISIM: no α (λ = 0); its bisimulation term instead (weight `bisim_lam`), on
                 transitions drawn from the training episodes, as the RL loop draws them from
                 the replay buffer
  uniform        RVAR: 1/|σ|
  positional     control: the mean attention α at each position, the same for every segment
                 (what is left of α without state information)
  oracle         control: each step's share of the segment's true return, r_t / Σ r (an upper
                 bound for any credit rule; the only rule that reads true rewards)

A rule may also take the shifted target form α_t·(R̂ + T·c) − c instead of the paper's α_t·R̂
(`shifts`, the rule named RULE~shift; prior/loss.py), clip its targets to the reward's range,
fit the prior on unlabelled
training segments too (`unlabelled`: prior/unlabelled.py) and have its own λ (`clips`,
`rule_lams`): PRIOR's ablations and a λ sweep then run side by side, as rules of one program.
A method whose update has other shapes (SURF: longer stored segments, an unlabelled pool)
runs in a program of its own (`OWN_PROGRAM`, its `MethodSpec.lab_rule`), one cell per seed,
with the same seeds' initial weights, on the same schedule; its rows join the others'.

Budgets are checkpoints of one run per cell: rounds of `queries_per_round`, clipped so the
label count lands on every budget (for budgets 25 and 100 at 10 per round: 10, 10, 5, then 10
... 10, 5); a separate run per budget would differ only in those round boundaries. The world
model is trained once per seed on the training episodes, before any round, and is fixed
after (the RL loop keeps training it; here the data does not change), so each pair's α is
computed once, when the pair is stored.

Cells are [seed, rule]: rules vmapped inside seeds, so the world model of a seed is shared by
its rules, not copied; seeds vmapped too on accelerators, one after the other on CPU
(`_over_cells`). All rules share the seed's random streams (initial reward weights, queries,
minibatch order), so a paired comparison between rules of one seed removes that variance; with
`feed_type="uniform"` every rule of a seed also gets exactly the same labels.
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import struct

from hprior_jax.buffers import preferences
from hprior_jax.lab import world_model_cache
from hprior_jax.lab.dataset import Dataset
from hprior_jax.networks.reward_ensemble import RewardConfig, init_reward_ensemble, mean_reward
from hprior_jax.pbrl.bisim import BisimTransitions, bisim_term
from hprior_jax.pbrl.preference import PreferenceConfig, make_optimizer, train_reward
from hprior_jax.pbrl.query import pairs_at, round_queries
from hprior_jax.pbrl.teacher import (TeacherConfig, TeacherOutput, compute_thresholds,
                                     teacher_labels)
from hprior_jax.prior import world_model as wm
from hprior_jax.prior.attention import (credit_from_attention, segment_attention,
                                        segment_credit)
from hprior_jax.prior.diagnostics import unreachable_targets, world_model_diagnostics
from hprior_jax.prior.loss import PairCredit, nrp_alpha, prior_term, rvar_alpha, target_shift
from hprior_jax.prior.unlabelled import STREAM as UNLABELLED_STREAM
from hprior_jax.prior.unlabelled import UnlabelledSegments, rows_of_pool, unlabelled_prior_term

CREDITS = ("none", "attention", "attention_nrp", "uniform", "positional", "oracle",
           "attention_no_own_step", "bisimulation")
OWN_PROGRAM = "own_program"  # a method's rule that runs in a program of its own (its lab_rule)
WORLD_MODEL_CREDITS = ("attention", "attention_nrp", "attention_no_own_step", "positional")
NO_PRIOR = ("none", "bisimulation")  # credits whose rule trains no prior term (λ = 0)
BISIM_STREAM = 0xB151  # folded off a round's key: the transitions leave the other draws alone
CONTROLS = {"positional": "positional", "oracle": "oracle"}  # lab rules that are no method
# lab rules asked for by name: (credit, targets clipped, prior also on unlabelled segments).
# The prior_* ones are `--algo prior` with a flag; the other two are prior_unlabelled's
# controls, the same unlabelled segments under uniform credit (`--algo rvar
# --rvar.unlabelled-segments N`) or positional credit (no method).
ABLATIONS = {"prior_no_own_step": ("attention_no_own_step", False, False),  # exclude-own-step
             "prior_clipped": ("attention", True, False),  # --prior.clip-targets
             "prior_unlabelled": ("attention", False, True),  # --prior.unlabelled-segments N
             "rvar_unlabelled": ("uniform", False, True),  # --rvar.unlabelled-segments N
             "positional_unlabelled": ("positional", False, True)}
UNLABELLED_SEGMENTS = 64  # the prior_unlabelled rule's N unless --prior-set sets it


@dataclass(frozen=True)
class LabConfig:
    rules: tuple[str, ...]  # rule names, in report order
    credits: tuple[str, ...]  # the credit of each rule (CREDITS)
    lam: float  # λ of every rule with a credit (the RL presets': 5 DMC, 1000 MetaWorld)
    clips: tuple[bool, ...] = ()  # per rule: targets clipped to [-1, 1] (empty: none)
    shifts: tuple[bool, ...] = ()  # per rule: the shifted target form (empty: all raw)
    unlabelled: tuple[bool, ...] = ()  # per rule: the prior also on unlabelled segments
    unlabelled_segments: int = UNLABELLED_SEGMENTS  # drawn afresh each round (prior.unlabelled)
    rule_lams: tuple[float | None, ...] = ()  # per rule: its own λ instead of `lam` (None: lam)
    bisim_lam: float = 0.5  # λ_bisim of the bisim rule (BISIM's default)
    bisim_transitions: int = 4  # transitions per stored-pair row (BISIM's default)
    discount: float = 0.99  # γ of the bisimulation target (SAC's, as in BISIM)
    own_rules: tuple = ()  # (rule, its method's lab rule object) of every OWN_PROGRAM rule
    budgets: tuple[int, ...] = (25, 100, 400)
    queries_per_round: int = 10
    feed_type: str = "disagreement"
    large_batch: int = 10
    one_shot: bool = False
    """Train once on all of a budget's labels (uniform queries) instead of round by round."""
    seeds: tuple[int, ...] = tuple(range(20))
    reward: RewardConfig = field(default_factory=RewardConfig)
    preference: PreferenceConfig = field(default_factory=PreferenceConfig)
    teacher: TeacherConfig = field(default_factory=TeacherConfig)
    world_model: wm.WorldModelConfig | None = None
    wm_pretrain_steps: int = 300
    wm_steps: int = 600  # dynamics-only steps after the pre-training
    wm_order: str = "joint"  # the pre-training's order (wm.pretrain)
    wm_normalize_obs: bool = False  # standardised world-model inputs (an ablation)
    attention_query: str = "action"
    profile_segments: int = 256  # training segments the positional profile averages

    def __post_init__(self):
        if len(self.rules) != len(self.credits) or not self.rules:
            raise ValueError("give one credit per rule")
        own = [r for r, c in zip(self.rules, self.credits) if c == OWN_PROGRAM]
        if own != [r for r, _ in self.own_rules]:
            raise ValueError(f"give the lab rule object of every own-program rule {own}")
        for name in ("clips", "shifts", "rule_lams", "unlabelled"):
            if len(getattr(self, name)) not in (0, len(self.rules)):
                raise ValueError(f"give one of {name} per rule, or none")
        bad = set(self.credits) - set(CREDITS) - {OWN_PROGRAM}
        if bad:
            raise ValueError(f"unknown credit {sorted(bad)}; available: {', '.join(CREDITS)}")
        if list(self.budgets) != sorted(set(self.budgets)) or self.budgets[0] < 1:
            raise ValueError(f"budgets must be increasing positive label counts: {self.budgets}")
        if self.needs_world_model and self.world_model is None:
            raise ValueError("a rule with attention or positional credit needs a world model")
        if self.needs_bisim and not self.reward.next_embedding_head:
            raise ValueError("the bisim rule needs RewardConfig(next_embedding_head=True)")

    @property
    def shared_rules(self) -> list[int]:
        """Indices of the rules that share the main program (all but OWN_PROGRAM ones)."""
        return [i for i, c in enumerate(self.credits) if c != OWN_PROGRAM]

    @property
    def needs_bisim(self) -> bool:
        return "bisimulation" in self.credits

    @property
    def needs_unlabelled(self) -> bool:
        return any(self.unlabelled)

    @property
    def needs_world_model(self) -> bool:
        return bool(set(WORLD_MODEL_CREDITS) & set(self.credits))

    def rounds(self) -> list[tuple[int, int | None]]:
        """(queries, budget reached after it or None) of every round, round by round."""
        out, labels = [], 0
        for budget in self.budgets:
            while labels < budget:
                n = min(self.queries_per_round, budget - labels)
                labels += n
                out.append((n, budget if labels == budget else None))
        return out


@struct.dataclass
class GivenLabels:
    """Labels given beforehand instead of the teacher's (a person's: `hprior label
    --from-lab`): pairs of the training episodes at `pair_index` [N, 4] (episode, start of
    each segment), B-Pref labels [N] (0 first, 1 second, -1 equal) and `valid` [N] (False:
    can't tell). Every cell trains once on all of them (one-shot)."""

    pair_index: np.ndarray
    labels: np.ndarray
    valid: np.ndarray

    def __len__(self) -> int:
        return len(self.labels)


@struct.dataclass
class RuleArgs:
    """What tells one rule from another inside the program (arrays, vmapped over rules):
    its credit (an index into CREDITS), λ of the prior term, whether its targets are clipped,
    their form's shift c (prior.loss.prior_targets: 0 raw), the weight of the bisimulation
    term and whether its prior also fits unlabelled segments."""

    credit: jax.Array
    lam: jax.Array
    clip: jax.Array
    shift: jax.Array
    bisim_lam: jax.Array
    unlabelled: jax.Array


@struct.dataclass
class Cell:
    """One (seed, rule): its reward ensemble and the labelled pairs with their credit."""

    reward: dict
    opt: optax.OptState
    prefs: preferences.PreferenceStore
    credit: PairCredit
    key: jax.Array


@struct.dataclass
class Episodes:
    """obs[E, L, ds], act[E, L, da], reward[E, L] (true rewards: the teacher's and the
    oracle credit's only)."""

    obs: jax.Array
    act: jax.Array
    reward: jax.Array


@struct.dataclass
class SeedContext:
    """What a seed's rules share: the world model, its mean α per position and the
    standardisation of its observations (None: raw, the paper's)."""

    wm_params: wm.WorldModelParams | None
    profile: jax.Array  # [T]
    obs_scaler: wm.ObsScaler | None = None


class Lab:
    def __init__(self, cfg: LabConfig, data: Dataset, given: GivenLabels | None = None,
                 world_model_cache: Path | None = None):
        """`world_model_cache`: an .npz (`world_model_cache.cache_path`) the seeds' world
        models are loaded from when it holds them, else trained and written to."""
        if given is not None and not (cfg.one_shot and cfg.budgets == (len(given),)):
            raise ValueError(f"given labels train once on all {len(given)}: one_shot=True "
                             f"and budgets=({len(given)},)")
        self.cfg, self.data = cfg, data
        # arguments of the round program, as the data: labs of the same shapes share it
        self.given = None if given is None else GivenLabels(
            jnp.asarray(given.pair_index, jnp.int32), jnp.asarray(given.labels, jnp.int32),
            jnp.asarray(given.valid, bool))
        self.obs_size = data.train_obs.shape[-1]
        self.act_size = data.train_act.shape[-1]
        self.T = data.segment_len
        self.tx = make_optimizer(cfg.preference)
        if given is not None and cfg.own_rules:
            raise ValueError("given labels train the rules of the shared program only, not "
                             f"{[r for r, _ in cfg.own_rules]}")
        pick = lambda values, default: [(values or (default,) * len(cfg.rules))[i]
                                        for i in cfg.shared_rules]
        credits = pick(cfg.credits, None)
        self.rule_args = RuleArgs(
            credit=jnp.asarray([CREDITS.index(c) for c in credits], jnp.int32),
            lam=jnp.asarray([0.0 if c in NO_PRIOR else cfg.lam if lam is None else lam
                             for c, lam in zip(credits, pick(cfg.rule_lams, None))], jnp.float32),
            clip=jnp.asarray(pick(cfg.clips, False), bool),
            shift=jnp.asarray([target_shift("shifted" if shifted else "raw",
                                            cfg.reward.output_activation)
                               for shifted in pick(cfg.shifts, False)], jnp.float32),
            bisim_lam=jnp.asarray([cfg.bisim_lam if c == "bisimulation" else 0.0
                                   for c in credits], jnp.float32),
            unlabelled=jnp.asarray(pick(cfg.unlabelled, False), bool))
        d = data
        # passed to the programs as arguments (not baked in as constants), so labs on data
        # of the same shapes share compiled programs
        self.train = Episodes(obs=jnp.asarray(d.train_obs), act=jnp.asarray(d.train_act),
                              reward=jnp.asarray(d.train_reward))
        self.test = Episodes(obs=jnp.asarray(d.test_obs), act=jnp.asarray(d.test_act),
                             reward=jnp.zeros(d.test_reward.shape, jnp.float32))  # not read
        # the teacher's margin: BPref's mean return of recent episodes; here of the data
        self.mean_return = jnp.float32(d.train_reward.sum(1).mean())
        self.seconds: dict[str, float] = {}
        self.compile_seconds: dict[str, float] = {}
        self.adam_steps = 0  # reward-ensemble minibatch steps run, of any minibatch size
        self.diagnostics: list[dict] = []  # per seed, when a rule needs the world model
        self.world_model_cache = world_model_cache if cfg.needs_world_model else None
        self.world_model_loaded = False  # True: from world_model_cache, not trained here

    # -- per seed -----------------------------------------------------------------------
    def seed_context(self, key: jax.Array, train: Episodes) -> SeedContext:
        cfg = self.cfg
        if not cfg.needs_world_model:
            return SeedContext(wm_params=None, profile=jnp.full((self.T,), 1.0 / self.T))
        k_init, k_pre, k_dyn, k_seg = jax.random.split(jax.random.fold_in(key, wm.RANDOM_STREAM), 4)
        obs, act = train.obs, train.act
        flat = lambda x: x.reshape((-1,) + x.shape[2:])
        size = jnp.int32(obs.shape[0] * obs.shape[1])
        scaler = wm.fit_obs_scaler(flat(obs), size) if cfg.wm_normalize_obs else None
        data = dict(obs_buf=flat(obs), act_buf=flat(act), size=size, cfg=cfg.world_model,
                    episode_len=obs.shape[1], obs_scaler=scaler)
        state = wm.init(k_init, cfg.world_model)
        state, _ = wm.pretrain(state, k_pre, num_steps=cfg.wm_pretrain_steps,
                               order=cfg.wm_order, **data)
        if cfg.wm_steps:
            state, _ = wm.train(state, k_dyn, num_steps=cfg.wm_steps, observation_model=False,
                                dynamics_model=True, **data)
        seg_obs, seg_act = wm.sample_segments(
            k_seg, flat(obs), flat(act), size, episode_len=obs.shape[1],
            batch_size=cfg.profile_segments, segment_len=self.T)
        alpha = segment_credit(state.params, wm.scaled(scaler, seg_obs), seg_act,
                               cfg.world_model, query=cfg.attention_query)
        return SeedContext(wm_params=state.params, profile=alpha.mean(0), obs_scaler=scaler)

    def seed_contexts(self, keys: jax.Array) -> SeedContext:
        """Every seed's context [S, ...]: from `world_model_cache` when it holds it, else
        trained (and written there)."""
        fn = jax.vmap(self.seed_context, (0, None))
        path = self.world_model_cache
        if path is not None:
            ctx = world_model_cache.load(path, jax.eval_shape(fn, keys, self.train))
            if ctx is not None:
                self.world_model_loaded = True
                return ctx
        ctx = self._timed("world_model", self._compiled("world_model", fn, keys, self.train),
                          keys, self.train)
        if path is not None:
            world_model_cache.save(path, ctx)
        return ctx

    def init_cell(self, key: jax.Array, capacity: int) -> Cell:
        params = init_reward_ensemble(key, self.obs_size, self.act_size, self.cfg.reward)
        return Cell(reward=params, opt=self.tx.init(params),
                    prefs=preferences.init(self.T, self.obs_size, self.act_size, capacity),
                    credit=PairCredit.uniform(capacity, self.T), key=key)

    # -- per cell -----------------------------------------------------------------------
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
                   "attention_no_own_step": no_own_step, "bisimulation": uniform}
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
        if cfg.needs_unlabelled:
            metrics |= {"unlabelled_prior_loss": m["prior/unlabelled_loss"]}
        if cfg.needs_bisim:
            metrics |= {"bisim_loss": m["bisim/loss"],
                        "bisim_grad_ratio": m["bisim/loss/grad_ratio"]}
        return Cell(reward=params, opt=opt, prefs=prefs, credit=credit, key=key), metrics

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

    # -- compiled over cells [S, R] -----------------------------------------------------
    def _compiled(self, name: str, fn, *args, donate=()):
        """jit(fn) compiled ahead of time once per process for every lab with the same
        settings and argument shapes (compile time measured apart)."""
        static = tuple(getattr(self.cfg, f.name) for f in dataclasses.fields(self.cfg)
                       if f.name not in _ARGUMENTS)
        key = (name, static, self.cfg.needs_world_model, self.T, self.data.episode_length, jax.tree.structure(args),
               tuple((x.shape, x.dtype) for x in jax.tree.leaves(args)))
        if key not in _PROGRAMS:
            t0 = time.perf_counter()
            _PROGRAMS[key] = jax.jit(fn, donate_argnums=donate).lower(*args).compile()
            self.compile_seconds[name] = time.perf_counter() - t0
        return _PROGRAMS[key]

    def _timed(self, name, fn, *args):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - t0
        return out

    def init_cells(self, keys: jax.Array, capacity: int) -> Cell:
        """[S, R] cells: every rule of a seed starts from the same weights and key."""
        return _broadcast_cells(partial(self.init_cell, capacity=capacity), keys,
                                len(self.cfg.shared_rules))

    def _world_model_diagnostics(self, ctx: SeedContext, num_segments: int = 256) -> list[dict]:
        """prior.diagnostics of each seed's world model on fixed held-out segments (the same
        for every seed; they read the held-out true rewards, as the metrics do). -> one dict
        per seed."""
        diagnose = partial(world_model_diagnostics, cfg=self.cfg.world_model,
                           query=self.cfg.attention_query)
        fn = jax.vmap(lambda params, scaler, obs, *rest: diagnose(
            params, wm.scaled(scaler, obs), *rest), (0, 0, None, None, None, None))
        args = (ctx.wm_params, ctx.obs_scaler,
                *held_out_segments(self.data, self.T, num_segments))
        out = jax.device_get(self._timed("diagnostics", self._compiled("diagnostics", fn, *args),
                                         *args))
        return [dict(seed=seed, **{k: float(v[i]) for k, v in out.items()})
                for i, seed in enumerate(self.cfg.seeds)]

    def run(self, progress=print, on_budget=None) -> list[dict]:
        """Every cell through every budget. -> rows (seed, rule, budget, the held-out
        predictions [E, L] as `prediction`, and the budget's last round's metrics).
        `on_budget(rows)`, if given, gets each budget's rows as soon as it is reached."""
        cfg = self.cfg
        keys = jnp.stack([jax.random.PRNGKey(s) for s in cfg.seeds])
        ctx = self.seed_contexts(keys)
        if cfg.needs_world_model:
            self.diagnostics = self._world_model_diagnostics(ctx)
            progress("world model, mean over seeds: " + ", ".join(
                f"{k} {np.mean([d[k] for d in self.diagnostics]):.3g}"
                for k in self.diagnostics[0] if k != "seed"))
        if cfg.one_shot:  # a fresh run per budget: one round of all its labels, uniform
            schedule = [[(b, b)] for b in cfg.budgets]
        else:
            schedule = [cfg.rounds()]
        rows = []
        for rounds in schedule:
            capacity = rounds[-1][1]
            shared = [cfg.rules[i] for i in cfg.shared_rules]
            groups = ([_Group("shared", shared, self.init_cells(keys, capacity),
                              self._shared_step)] if shared else [])
            groups += [_Group(name, [name], _broadcast_cells(partial(
                rule.init, capacity=capacity, obs_size=self.obs_size, act_size=self.act_size,
                lab=cfg), keys, 1), partial(self._own_step, name, rule))
                for name, rule in cfg.own_rules]
            queries = capacity if cfg.one_shot else cfg.queries_per_round
            labels_after = np.cumsum([n for n, _ in rounds])  # labels stored after each round
            for i, (n, budget) in enumerate(rounds):
                by_rule = {}  # rule -> (predictions [S, ...], metrics {name: [S]})
                for group in groups:
                    group.cells, m = group.step(group.cells, ctx, n, i == 0, queries,
                                                labels_after[i])
                    if budget is not None:
                        pred = self.predict_cells(group.cells, f"{group.name}/predict")
                        by_rule |= {r: (pred[:, ri], {k: v[:, ri] for k, v in m.items()})
                                    for ri, r in enumerate(group.rules)}
                if budget is None:
                    continue
                reached = []
                for si, seed in enumerate(cfg.seeds):
                    for rule in cfg.rules:
                        pred, m = by_rule[rule]
                        reached.append(dict(seed=seed, rule=rule, budget=budget,
                                            prediction=pred[si],
                                            **{k: v[si].item() for k, v in m.items()}))
                rows += reached
                if on_budget is not None:
                    on_budget(reached)
                progress(f"{budget} labels: {len(cfg.seeds)} seeds x {len(cfg.rules)} rules, "
                         f"{self.adam_steps} Adam steps, {sum(self.seconds.values()):.0f} s "
                         f"+ {sum(self.compile_seconds.values()):.0f} s compiling")
        return rows

    @property
    def _feed(self) -> str:
        # one-shot runs have only a first round: no candidate pool for the uncertainty rules
        return "uniform" if self.cfg.one_shot else self.cfg.feed_type

    def _shared_step(self, cells, ctx, n, first, queries, labels):
        """One round of the shared program's cells [S, R] -> (cells, metrics [S, R])."""
        cfg = self.cfg
        batch = minibatch_size(labels, cfg.preference.batch_size)
        # rules vmapped inside seeds, so a seed's world model is not copied
        fn = _over_cells(partial(self.round, queries=queries, batch_size=batch, feed=self._feed),
                         (0, 0, None) + (None,) * 5, (0, None, 0) + (None,) * 5)
        args = (cells, ctx, self.rule_args, jnp.int32(n), jnp.asarray(first), self.train,
                self.mean_return, self.given)
        fn = self._compiled(f"round/{queries}/batch{batch}", fn, *args, donate=0)
        cells, m = self._timed("rounds", fn, *args)  # the old cells are donated
        m = jax.device_get(m)
        # vmapped, a round runs until its slowest cell stops: that is what it costs
        self.adam_steps += int(np.max(m["epochs"])) * -(-int(np.max(m["labels"])) // batch)
        return cells, m

    def _own_step(self, name, rule, cells, ctx, n, first, queries, labels):
        """One round of an own-program rule's cells [S, 1] -> (cells, metrics [S, 1])."""
        fn = _over_cells(partial(rule.round, lab=self.cfg, queries=queries, feed=self._feed,
                                 episode_length=self.data.episode_length),
                         (0,) + (None,) * 4, (0,) + (None,) * 4)
        args = (cells, jnp.int32(n), jnp.asarray(first), self.train, self.mean_return)
        fn = self._compiled(f"{name}/round/{queries}", fn, *args, donate=0)
        cells, m = self._timed("rounds", fn, *args)
        m = jax.device_get(m)
        self.adam_steps += int(np.max(m["epochs"]))  # its iterations are Adam steps
        return cells, m

    def predict_cells(self, cells, name: str) -> np.ndarray:
        """r̂ of every held-out state under every cell: [S, R, E, L] (any cells whose
        `reward` field holds the ensemble: an own-program rule's too)."""
        fn = _over_cells(self.predict, (0, None), (0, None))
        fn = self._compiled(name, fn, cells, self.test)
        return np.asarray(self._timed("predict", fn, cells, self.test))


@dataclass
class _Group:
    """Rules that train in one program: its name, the rules, their cells [S, len(rules)] and
    the round step."""

    name: str
    rules: list[str]
    cells: object
    step: object  # (cells, ctx, n, first, queries, labels) -> (cells, metrics)


def _broadcast_cells(init, keys: jax.Array, rules: int):
    """[S, rules] cells: every rule of a seed starts from `init(key)` of that seed."""
    one = lambda k: jax.tree.map(lambda x: jnp.broadcast_to(x, (rules,) + x.shape), init(k))
    return jax.jit(jax.vmap(one))(keys)


def _over_cells(fn, seed_axes, rule_axes):
    """`fn` of one cell over [seed, rule] cells (`*_axes`: 0 where an argument has that axis,
    None where it is shared). Rules are vmapped; seeds are vmapped on accelerators and
    mapped one after the other (`lax.map`) on CPU, where the vmapped round of 40 cells held
    19.2 GiB of intermediates (sweep_into, 10 seeds x 4 rules, minibatch 128: each cell's
    forward and backward pass over 128 x 2 segments of 50 steps) against 2.1 GiB mapped,
    and a wider batch buys a CPU little (the whole lab: peak RSS 21.0 -> 3.6 GiB)."""
    cells = jax.vmap(fn, rule_axes)
    if jax.default_backend() != "cpu":
        return jax.vmap(cells, seed_axes)

    def mapped(*args):
        # lax.map slices the per-seed arguments; the shared ones ride as None (no leaves)
        per_seed = tuple(a if axis == 0 else None for a, axis in zip(args, seed_axes))
        return jax.lax.map(lambda sliced: cells(*[
            s if axis == 0 else a for a, s, axis in zip(args, sliced, seed_axes)]), per_seed)
    return mapped


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


def held_out_segments(data: Dataset, segment_len: int, num: int, seed: int = 0):
    """`num` fixed segments of the held-out episodes and a random step order for each:
    (obs, act, true reward, perm), the inputs of prior.diagnostics."""
    rng = np.random.default_rng(seed)
    ep = rng.integers(0, data.test_obs.shape[0], num)
    start = rng.integers(0, data.episode_length - segment_len + 1, num)
    steps = start[:, None] + np.arange(segment_len)
    cut = lambda x: jnp.asarray(x[ep[:, None], steps])
    perm = jnp.asarray(np.stack([rng.permutation(segment_len) for _ in range(num)]))
    return cut(data.test_obs), cut(data.test_act), cut(data.test_reward), perm


def minibatch_size(labels: int, batch_size: int) -> int:
    """The smallest of 16, 32, 64, ... >= `labels`, at most `batch_size`. While every stored
    pair fits in one minibatch, an epoch is that one minibatch whatever its padding (padded
    rows are masked), so a smaller static batch computes the same update for less: at 25
    labels a 32-row batch costs a quarter of a 128-row one."""
    size = 16
    while size < min(labels, batch_size):
        size *= 2
    return min(size, batch_size)


# LabConfig fields that reach the programs as arguments or only the host schedule
_ARGUMENTS = ("rules", "credits", "lam", "clips", "shifts", "rule_lams", "bisim_lam", "seeds",
              "budgets")
_PROGRAMS: dict = {}  # compiled lab programs of this process (see Lab._compiled)
