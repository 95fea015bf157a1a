"""The chunk engine: env, SAC, the method's hooks, compiled `jit(vmap(chunk))` programs.

Every leaf of `RunState` has a leading seed axis, split over the devices of a one-axis mesh
(`hprior_jax.loop.devices`). The schedule (the method's phases and events) is decided on the
host from the global step, which is the same for every seed; a chunk is a `lax.scan` over
env steps compiled once per length as `vmap(chunk, in_axes=(0, None))` on every device's
seeds (`devices.over_seeds`, donating the state). The global step enters unbatched, so
per-step decisions derived from it (target-network EMA, episode ends, the replay ring
position) stay scalar. The engine holds no mutable run state and names no method.
"""
from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from hprior_jax.agents.sac import SAC
from hprior_jax.buffers import replay
from hprior_jax.envs import EnvState, make_env, task_info, task_options
from hprior_jax.evaluate import evaluate_policy
from hprior_jax.loop import devices as seed_devices
from hprior_jax.loop.state import RunState
from hprior_jax.loop.programs import ProgramCache, abstract, shapes, timed
from hprior_jax.setup_jax import compiler_options, program_options


STARTS = "episode_starts"  # the program of the states new episodes begin from
INIT = "init"  # the program of every seed's first run state


class Engine(ProgramCache):
    def __init__(self, cfg, build_method, devices=None, records_physics: bool = False):
        """`build_method(cfg, engine)`: the method's hooks (`methods.registry`'s `build`).
        `devices`: how many devices the seeds are split over (default: as many as divide
        the seeds evenly), or which (`hprior_jax.loop.devices.seed_mesh`).
        `records_physics`: the replay buffer keeps the physics state behind each obs (what a
        clip is rendered from), as it does anyway for a method that asks a person."""
        self.cfg = cfg
        self.mesh = seed_devices.seed_mesh(len(cfg.seeds), devices)
        options = task_options(cfg)
        self.env = make_env(cfg.task, num_envs=1, **options)
        self.eval_env = make_env(cfg.task, num_envs=cfg.num_eval_episodes, **options)
        self.task = self.env.task
        self.sac = SAC(self.env.obs_size, self.env.action_size, cfg.sac)
        # every program of the run compiles with these (XLA's optimisation level)
        self.compiler_options = compiler_options(cfg.compile_level,
                                                 task_info(cfg.task).compile_level)
        ProgramCache.__init__(self)
        self.first_phase_apart = False  # see _chunk_name; the host sets it
        self.person = None  # a human teacher, attached by the host loop when one is asked
        self.method = build_method(cfg, self)
        self.records_physics = records_physics or self.method.asks_person
        self.phases = self.method.phases()
        starts = [p.start for p in self.phases]
        assert starts[0] == 0 and starts == sorted(starts), "phases must start in order at 0"

    # -- schedule (host side, the same for every seed) ---------------------------------------
    def phase_at(self, step: int) -> str:
        return self.phases[self._phase_index(step)].name

    def _phase_index(self, step):
        """The phase of global step `step`: a Python int on the host, a traced int32 in the
        chunk (where it indexes the lax.switch)."""
        return sum((step >= p.start) * 1 for p in self.phases[1:])

    def phase_metrics(self, phase: str) -> tuple[str, ...]:
        """The `train/` metrics meaningful in `phase` (others are placeholders)."""
        return next(p.metrics for p in self.phases if p.name == phase)

    def event_steps(self) -> list[int]:
        return self.method.event_steps()

    def chunk_plan(self, step: int) -> tuple[str, int]:
        """Phase and length of the next chunk: never crosses a phase change, event,
        evaluation, checkpoint or the end of training."""
        cfg = self.cfg
        bounds = [cfg.steps, _next_multiple(step, cfg.chunk_steps),
                  _next_multiple(step, cfg.eval_every), _next_multiple(step, cfg.checkpoint_every)]
        bounds += [b for b in (*(p.start for p in self.phases), *self.event_steps()) if b > step]
        return self.phase_at(step), min(bounds) - step

    # -- pure functions (per seed) --------------------------------------------------------
    def init(self, seed_key: jax.Array, env: EnvState, capacity: int | None = None) -> RunState:
        """`env`: the first episode's state, `env.reset(env_key(seed_key))` (made by the
        episode-starts program, `init_seeds`)."""
        k_sac, _, k_run, k_method = jax.random.split(seed_key, 4)
        capacity = capacity or self.cfg.capacity
        return RunState(
            sac=self.sac.init(k_sac),
            replay=replay.init(capacity, self.env.obs_size, self.env.action_size,
                               physics=self.recorded_physics(env)),
            env=env, key=k_run, method=self.method.init(k_method))

    def recorded_physics(self, env_state):
        """The physics state behind the env's observation where it is recorded (a person
        labels clips rendered from it); None otherwise."""
        if not self.records_physics:
            return None
        return {k: v[0] for k, v in self.task.render_states(env_state.task.data).items()}

    # -- episode starts: made outside the chunk ------------------------------------------
    # A new episode's first state is made by a program of its own, not inside the chunk:
    # the reset is a second copy of the physics in the chunk's program (cheetah's 200
    # settling substeps), and without it the first chunk's program traced and compiled in
    # 30-40% of the time (benchmarks/README, "Start-up"). The states are the resets the
    # chunk made before: the same keys, drawn from the chunk's own key stream.
    @property
    def starts_per_chunk(self) -> int:
        """Episode ends a chunk can hold (a chunk is at most `chunk_steps` long)."""
        return -(-self.cfg.chunk_steps // self.env.episode_length)

    def episode_keys(self, key: jax.Array, step0: jax.Array) -> jax.Array:
        """[starts_per_chunk] reset keys of the episodes that start in the chunk from global
        step `step0` whose key stream starts at `key` (`rs.key`): slot j holds the key the
        chunk's step at the j-th episode end draws (`chunk`'s split); slots past the chunk's
        last episode end hold keys never used."""
        def draw(key, _):
            key, _, _, _, k_reset = jax.random.split(key, 5)
            return key, k_reset

        steps = self.cfg.chunk_steps
        _, k_resets = jax.lax.scan(draw, key, None, length=steps)
        ends = self.env.episode_length
        at = (ends - 1 - step0 % ends) + ends * jnp.arange(self.starts_per_chunk)
        return k_resets[jnp.minimum(at, steps - 1)]

    def episode_starts(self, rs: RunState, step0: int) -> EnvState:
        """The states the episodes that start in the chunk from `step0` begin from, stacked
        [seeds, starts_per_chunk, ...] (the chunk's `starts` input)."""
        keys = self.compile("episode_keys", self.per_seed(self.episode_keys, (0, None)),
                            rs.key, np.int32(step0))(rs.key, np.int32(step0))
        return self._reset_all(keys)

    def _reset_all(self, keys: jax.Array) -> EnvState:
        """`env.reset` of every key in [seeds, starts_per_chunk] keys (`STARTS`)."""
        return self.compile(STARTS, self._starts_program(), keys)(keys)

    def _starts_program(self):
        """The episode-starts program: one vmap over every seed and slot (`VecEnv.reset_many`;
        vmaps nested over seeds and slots took longer to lower)."""
        return self.over_seed_axis(self.env.reset_many)

    def chunk(self, rs: RunState, step0: jax.Array, starts: EnvState, *, length: int,
              only: int | None = None):
        """`length` env steps from global step `step0`. A chunk never crosses a phase change,
        so the phase is an unbatched `lax.switch` index: a real branch under vmap, and one
        compiled program for every phase. `only`: the program of that phase alone (no
        switch), for chunks the host knows to be in it (`_chunk_name`). `starts`: the first
        states of the episodes that start in the chunk (`episode_starts`)."""
        if length > self.cfg.chunk_steps:
            raise ValueError(f"a chunk of {length} steps: at most chunk_steps "
                             f"({self.cfg.chunk_steps}), whose episode starts it is given")
        phase = jnp.asarray(self._phase_index(step0), jnp.int32)
        ends = self.env.episode_length
        metric_keys = sorted({k for p in self.phases for k in p.metrics})

        def branch(fn):
            # The replay buffer enters the switch read-only and does not leave it, and the
            # insert position leaves it: XLA then orders the in-place insert after the switch's
            # reads of the buffer. Otherwise it may schedule the insert of values that do not
            # depend on the action (the stored obs) first, and copies the whole buffer on every
            # step to keep the switch's input intact (cost O(capacity) per env step).
            def run(rs, obs, step, keys):
                action, rs_out, m = fn(rs, obs, step, keys)
                return (action, rs_out.replace(replay=None), step % rs.replay.capacity,
                        {k: m.get(k, jnp.zeros((), jnp.float32)) for k in metric_keys})
            return run

        branches = [branch(p.step) for p in self.phases]

        def body(rs: RunState, i):
            step = step0 + i
            # k_reset: drawn so the stream stays the one `episode_keys` walks
            key, k_act, k_sample, k_update, k_reset = jax.random.split(rs.key, 5)
            obs = rs.env.task.obs[0]
            args = (rs, obs, step, (k_act, k_sample, k_update))
            action, rest, write_at, metrics = (jax.lax.switch(phase, branches, *args)
                                               if only is None else branches[only](*args))
            rs = rest.replace(replay=rs.replay)
            nth_start = step // ends - step0 // ends  # episode ends before this step
            env_state, tr = self.env.step_or_start(
                rs.env, action[None], step, lambda: jax.tree.map(lambda x: x[nth_start], starts))
            reward = self.method.stored_reward(rs, tr.obs[0], tr.action[0], tr.true_reward[0])
            # every seed has taken `step` steps, so the ring position is the same for all and
            # unbatched under vmap: a dynamic-update-slice, not a scatter
            buf = replay.add(rs.replay, tr.obs[0], tr.action[0], reward, tr.next_obs[0],
                             1.0 - tr.terminated[0].astype(jnp.float32), tr.true_reward[0],
                             index=write_at, physics=self.recorded_physics(rs.env))
            metrics = dict(metrics)
            metrics.update({
                "episode/done": jnp.logical_or(tr.terminated[0], tr.truncated[0]),
                "episode/true_return": tr.episode_return[0],
                "episode/success": tr.episode_success[0],
                # MJX's contact cap full at this step's end: contacts may have been dropped
                "physics/contacts_at_cap": jax.vmap(self.task.contacts_at_cap)(
                    env_state.task.data).any(),
            })
            return rs.replace(replay=buf, env=env_state, key=key), metrics

        return jax.lax.scan(body, rs, jnp.arange(length, dtype=jnp.int32))

    def evaluate(self, actor_params, key: jax.Array):
        policy = lambda obs: self.sac.act(actor_params, obs, key, deterministic=True)
        return evaluate_policy(self.eval_env, policy, key)

    # -- compiled, vmapped over seeds ---------------------------------------------------------
    def compile_start(self, seeds, step: int, capacity: int | None = None) -> None:
        """Compiles the programs a run's first env step waits for side by side: the
        episode-starts and initial-state programs on the background thread while this one
        compiles the first chunk's (from `step`). The chunk needs their shapes only, which
        lowering them gives, so on two cores the first env step waits for the longer
        compile, not all (`init_seeds(seeds, capacity)` then finds them ready)."""
        keys = self._env_keys(seeds)
        starts = self._starts_program().lower(*shapes((keys,)))
        self._in_background(STARTS, partial(timed, starts.compile))
        env = jax.tree.map(abstract, starts.out_info)
        seed_keys = jax.ShapeDtypeStruct((len(seeds), 2), np.uint32)
        name = self._init_name(capacity)
        init = self._init_program(capacity).lower(seed_keys, env)
        self._in_background(name, partial(timed, init.compile))
        if name == INIT:
            rs = jax.tree.map(abstract, init.out_info)
        else:  # a resumed run grows its buffer to this run's capacity before its first chunk
            rs = jax.eval_shape(self._init_program(None), seed_keys, env)
        self.compiled_chunk(rs, step, self.chunk_plan(step)[1])

    def compile_run_ahead(self, rs: RunState, step: int, with_eval=()) -> None:
        """Queues the background compile of every program the rest of the run will ask for
        after its first chunk, in the order it will ask for them (the host's chunk plan,
        evaluations and events from `step`): chunk programs, evaluation, the method's event
        programs (all of them at its first event, in their order). `with_eval`: (name,
        program, argument shapes) of programs the host runs at evaluations (the episode
        recorder), queued right after evaluation's."""
        cfg, events, order, at = self.cfg, set(self.event_steps()), [], step
        programs = None
        while at < cfg.steps:
            if at in events and programs is None:
                programs = {name: (fn, args) for name, fn, args in self.method.programs(rs)}
                order += list(programs)
            length = self.chunk_plan(at)[1]
            order.append(self._chunk_name(at, length))
            at += length
            if at % cfg.eval_every == 0 or at == cfg.steps:
                order.append("eval")
        first = order[0] if order else None
        for name in dict.fromkeys(order):  # first need of each, in order
            if name == first:
                continue  # the main thread's: compiled before or after this call
            if name == "eval":
                self.compile_ahead(name, *self._eval_program(rs, cfg.seeds, step))
                for other, fn, args in with_eval:
                    self.compile_ahead(other, fn, *args)
            elif name in (programs or {}):
                self.compile_ahead(name, programs[name][0], *programs[name][1])
            else:
                length = int(name.split("/")[1])
                self.compile_ahead(name, *self._chunk_program(rs, step, length, name))

    def per_seed(self, fn, in_axes=(0,), donate_argnums=(), physics_free=False):
        """`fn` of one seed as a jitted program over every seed, split over the mesh:
        `in_axes[i]` is 0 for an argument with the seed axis, None for one all seeds share.
        `physics_free`: `fn` steps no MJX (`setup_jax.program_options`)."""
        return self.over_seed_axis(jax.vmap(fn, in_axes=in_axes), in_axes, donate_argnums,
                                   physics_free)

    def over_seed_axis(self, fn, in_axes=(0,), donate_argnums=(), physics_free=False):
        """As `per_seed` for `fn` that maps over the seed axis itself (e.g. `lax.map`)."""
        return seed_devices.over_seeds(self.mesh, fn, in_axes, donate_argnums,
                                       program_options(self.compiler_options, physics_free))

    def place(self, tree):
        """`tree` (leading seed axis) split over the mesh as the compiled programs expect."""
        return seed_devices.place(self.mesh, tree)

    def init_seeds(self, seeds, capacity: int | None = None) -> RunState:
        keys = self.place(np.stack([np.asarray(jax.random.PRNGKey(s)) for s in seeds]))
        starts = self._reset_all(self._env_keys(seeds))
        program = self._init_program(capacity)
        return self.compile(self._init_name(capacity), program, keys, starts)(keys, starts)

    def _init_program(self, capacity: int | None):
        """The initial run states from the seeds' keys and their episode starts (every slot
        the first episode's state; slot 0 is taken in the program, not by an eager slice
        per leaf, each of which would compile a program of its own)."""
        def init(seed_key, starts):
            return self.init(seed_key, jax.tree.map(lambda x: x[0], starts), capacity)

        return self.per_seed(init, (0, 0))

    def _init_name(self, capacity: int | None) -> str:
        """One initial-state program per replay capacity (a resumed run restores into the
        capacity it saved, then grows it)."""
        return INIT if capacity in (None, self.cfg.capacity) else f"{INIT}/{capacity}"

    def _env_keys(self, seeds) -> jax.Array:
        """The first episode's keys as the episode-starts program takes them: [seeds,
        starts_per_chunk], every slot the seed's env key."""
        one = np.stack([np.asarray(env_key(jax.random.PRNGKey(s))) for s in seeds])
        return self.place(np.repeat(one[:, None], self.starts_per_chunk, axis=1))

    def compiled_chunk(self, rs: RunState, step0: int, length: int):
        """The compiled program of `length` env steps from `step0`: one per length for every
        phase, except in the first phase with `first_phase_apart` (`_chunk_name`)."""
        name = self._chunk_name(step0, length)
        return self.compile(name, *self._chunk_program(rs, step0, length, name))

    def _chunk_name(self, step0: int, length: int) -> str:
        """With `first_phase_apart`, chunks of the first phase (random actions: no network
        update) run a program of that phase alone, smaller to compile, so the run's first env
        steps need not wait for the program of every phase, which compiles in the background
        meanwhile. Measured, the run starts sooner but ends later, so it stays a flag
        (`--compile-ahead first-phase-apart`; benchmarks/README.md, "compile_ahead"). Both
        compute the same bits (tested). Without a background compile the split would only
        add one."""
        first = (self.first_phase_apart and self._phase_index(step0) == 0
                 and len(self.phases) > 1)
        return f"chunk/{length}/{self.phases[0].name}" if first else f"chunk/{length}"

    def _chunk_program(self, rs: RunState, step0: int, length: int, name: str | None = None):
        only = 0 if name is not None and name.count("/") == 2 else None
        fn = self.per_seed(partial(self.chunk, length=length, only=only), (0, None, 0),
                           donate_argnums=0)
        per_chunk = self.starts_per_chunk
        starts = jax.tree.map(lambda x: jax.ShapeDtypeStruct(
            (x.shape[0], per_chunk) + x.shape[1:], x.dtype), rs.env)
        return fn, rs, np.int32(step0), starts

    def run_chunk(self, rs: RunState, step0: int, length: int):
        program = self.compiled_chunk(rs, step0, length)
        return program(rs, np.int32(step0), self.episode_starts(rs, step0))

    def run_event(self, rs: RunState, step: int):
        return self.method.run_event(rs, step)

    def run_eval(self, rs: RunState, seeds, step: int):
        fn, actor, keys = self._eval_program(rs, seeds, step)
        return self.compile("eval", fn, actor, keys)(actor, keys)

    def _eval_program(self, rs: RunState, seeds, step: int):
        keys = self.place(np.stack([np.asarray(eval_key(s, step)) for s in seeds]))
        fn = self.over_seed_axis(partial(over_seeds, self.evaluate), (0, 0))
        return fn, rs.sac.actor, keys


def over_seeds(fn, *args):
    """`fn` for every seed (leading axis of `args`: a device's seeds): one seed after the
    other on CPU, where MJX gains nothing from a wider batch and loses cache locality (an
    evaluation of several cheetah seeds ran slower vmapped, or as one flat batch of their
    envs, than mapped); vmapped on accelerators."""
    if jax.default_backend() == "cpu":
        return jax.lax.map(lambda a: fn(*a), args)
    return jax.vmap(fn)(*args)


def eval_key(seed: int, step: int) -> jax.Array:
    """The evaluation key of `seed` at `step`: derived from (seed, step) only, so evaluation
    never touches the training stream and any tool can repeat a run's evaluation."""
    return jax.random.fold_in(jax.random.PRNGKey(seed), 0x5EED0000 + step)


def env_key(seed_key: jax.Array) -> jax.Array:
    """The key of a seed's first episode (`Engine.init`'s split)."""
    return jax.random.split(seed_key, 4)[1]


def _next_multiple(step: int, every: int) -> int:
    return (step // every + 1) * every
