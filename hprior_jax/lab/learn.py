"""Reward learning on fixed data, every (seed, rule) cell in one compiled program (SURF in
one of its own): a cell trains one reward ensemble the way the RL loop's feedback rounds do
(`lab.rounds`), with CE + λ·L_prior where its rule decides the credit α (`lab.config`).

Budgets are checkpoints of one run per cell: rounds of `queries_per_round`, clipped so the
label count lands on every budget (25 and 100 at 10 per round: 10, 10, 5, then 10 ... 10, 5).
The world model is trained once per seed before any round and fixed after
(`lab.seed_world_model`), so each pair's α is computed once, when the pair is stored.
Cells are [seed, rule]: rules vmapped inside seeds (a seed's world model is shared, not
copied); seeds vmapped on accelerators, one after the other on CPU (`_over_cells`). All rules
share the seed's random streams (initial weights, queries, minibatch order), so a paired
comparison between rules of one seed removes that variance.
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from hprior_jax.lab import resume, seed_world_model, world_model_cache
from hprior_jax.lab.config import (CREDITS, NO_PRIOR, Episodes, GivenLabels,
                                   LabConfig, RuleArgs)
from hprior_jax.lab.dataset import Dataset
from hprior_jax.lab.rounds import Cell, CellRounds, minibatch_size
from hprior_jax.lab.seed_world_model import SeedContext, held_out_segments
from hprior_jax.pbrl.preference import make_optimizer
from hprior_jax.prior import world_model as wm
from hprior_jax.prior.diagnostics import world_model_diagnostics
from hprior_jax.prior.loss import target_shift


class Lab(CellRounds):
    def __init__(self, cfg: LabConfig, data: Dataset, given: GivenLabels | None = None,
                 world_model_cache: Path | None = None):
        """`world_model_cache`: an .npz (`lab.world_model_cache.cache_path`) the seeds' world
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
        self.wall_before = 0.0  # seconds the lab ran before it was resumed

    # -- per seed -----------------------------------------------------------------------
    def seed_context(self, key: jax.Array, train: Episodes) -> SeedContext:
        return seed_world_model.train_seed_context(self.cfg, self.T, key, train)

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

    def run(self, progress=print, on_budget=None,
            checkpoints: resume.Checkpoints | None = None) -> list[dict]:
        """Every cell through every budget. -> rows (seed, rule, budget, the held-out
        predictions [E, L] as `prediction`, and the budget's last round's metrics).
        `on_budget(rows)`, if given, gets each budget's rows as soon as it is reached (and,
        when the lab resumes, the rows reached before it stopped, first).
        `checkpoints`: where the lab's state is kept between rounds (`lab.resume`); a state
        found there is resumed."""
        cfg = self.cfg
        t0 = time.perf_counter()
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
        state = self._resumed(checkpoints, progress, on_budget, schedule)
        rows = list(state.rows) if state else []
        last_save = time.perf_counter()
        for run, rounds in enumerate(schedule):
            if state is not None and run < state.schedule:
                continue
            groups = self._groups(keys, capacity=rounds[-1][1])
            start = 0
            if state is not None and run == state.schedule and state.next_round > 0:
                for group, leaves in zip(groups, state.cells, strict=True):
                    group.cells = resume.restore(group.cells, leaves)
                start = state.next_round
            queries = rounds[-1][1] if cfg.one_shot else cfg.queries_per_round
            labels_after = np.cumsum([n for n, _ in rounds])  # labels stored after each round
            for i, (n, budget) in enumerate(rounds[start:], start):
                reached = self._round(groups, ctx, n, i == 0, queries, labels_after[i], budget)
                rows += reached
                after = (run, i + 1) if i + 1 < len(rounds) else (run + 1, 0)
                if checkpoints is not None and after[0] < len(schedule) and (
                        reached or time.perf_counter() - last_save >= checkpoints.every_s):
                    # written before the budget's rows leave, so they are never lost
                    checkpoints.save(resume.LabState(
                        *after, cells=[jax.tree.leaves(jax.device_get(g.cells)) for g in groups]
                        if after[0] == run else [], rows=rows, adam_steps=self.adam_steps,
                        seconds=self.seconds, wall_seconds=self.wall_seconds(t0)))
                    last_save = time.perf_counter()
                if not reached:  # a line a round: a lab's budgets can be hours apart
                    progress(f"round {i + 1} of {len(rounds)}: {labels_after[i]} labels, "
                             f"{self.wall_seconds(t0):.0f} s")
                    continue
                if on_budget is not None:
                    on_budget(reached)
                progress(f"{budget} labels: {len(cfg.seeds)} seeds x {len(cfg.rules)} rules, "
                         f"{self.adam_steps} Adam steps, {sum(self.seconds.values()):.0f} s "
                         f"+ {sum(self.compile_seconds.values()):.0f} s compiling")
        return rows

    def _round(self, groups, ctx, n, first, queries, labels, budget) -> list[dict]:
        """One round of every group's cells (updated in place) -> the rows of the budget it
        reaches ([] when it reaches none)."""
        by_rule = {}  # rule -> (predictions [S, ...], metrics {name: [S]})
        for group in groups:
            group.cells, m = group.step(group.cells, ctx, n, first, queries, labels)
            if budget is not None:
                pred = self.predict_cells(group.cells, f"{group.name}/predict")
                by_rule |= {r: (pred[:, ri], {k: v[:, ri] for k, v in m.items()})
                            for ri, r in enumerate(group.rules)}
        if budget is None:
            return []
        return [dict(seed=seed, rule=rule, budget=budget, prediction=by_rule[rule][0][si],
                     **{k: v[si].item() for k, v in by_rule[rule][1].items()})
                for si, seed in enumerate(self.cfg.seeds) for rule in self.cfg.rules]

    def _resumed(self, checkpoints, progress, on_budget, schedule) -> resume.LabState | None:
        """The state `checkpoints` keeps (None: none), its counters taken over and its rows
        handed to `on_budget`."""
        state = checkpoints.load() if checkpoints is not None else None
        if state is None:
            return None
        self.adam_steps, self.wall_before = state.adam_steps, state.wall_seconds
        self.seconds = {k: state.seconds.get(k, 0.0) + self.seconds.get(k, 0.0)
                        for k in {**state.seconds, **self.seconds}}
        progress(f"resuming at round {state.next_round + 1} of "
                 f"{len(schedule[state.schedule])} with {len(state.rows)} rows reached")
        if state.rows and on_budget is not None:
            on_budget(list(state.rows))
        return state

    def wall_seconds(self, t0: float) -> float:
        """Seconds this lab has run since `t0`, the runs before a resume included."""
        return self.wall_before + time.perf_counter() - t0

    def _groups(self, keys: jax.Array, capacity: int) -> list[_Group]:
        """The program groups of a run whose stores hold `capacity` pairs: the shared
        program's rules, then each own-program rule, with their fresh cells."""
        cfg = self.cfg
        shared = [cfg.rules[i] for i in cfg.shared_rules]
        groups = ([_Group("shared", shared, self.init_cells(keys, capacity),
                          self._shared_step)] if shared else [])
        return groups + [_Group(name, [name], _broadcast_cells(partial(
            rule.init, capacity=capacity, obs_size=self.obs_size, act_size=self.act_size,
            lab=cfg), keys, 1), partial(self._own_step, name, rule))
            for name, rule in cfg.own_rules]

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
    mapped one after the other (`lax.map`) on CPU, where vmapping them too holds every cell's
    intermediates of a round at once (each cell's forward and backward pass over its
    minibatch of segment pairs), several times the memory, and a wider batch buys a CPU
    little (peak memory of both: docs/reward_lab.md, "Cost")."""
    cells = jax.vmap(fn, rule_axes)
    if jax.default_backend() != "cpu":
        return jax.vmap(cells, seed_axes)

    def mapped(*args):
        # lax.map slices the per-seed arguments; the shared ones ride as None (no leaves)
        per_seed = tuple(a if axis == 0 else None for a, axis in zip(args, seed_axes))
        return jax.lax.map(lambda sliced: cells(*[
            s if axis == 0 else a for a, s, axis in zip(args, sliced, seed_axes)]), per_seed)
    return mapped


# LabConfig fields that reach the programs as arguments or only the host schedule
_ARGUMENTS = ("rules", "credits", "lam", "clips", "shifts", "rule_lams", "bisim_lam", "seeds",
              "budgets")
_PROGRAMS: dict = {}  # compiled lab programs of this process (see Lab._compiled)
