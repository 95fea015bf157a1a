"""RunState, chunk functions and the host loop (DESIGN §4).

Every leaf of `RunState` has a leading seed axis. The schedule (random seed steps, then SAC
steps) is decided on the host from the global step, which is the same for every seed; a
chunk is a `lax.scan` over env steps compiled once per length as
`jit(vmap(chunk, in_axes=(0, None)), donate_argnums=0)`. The global step enters unbatched,
so per-step decisions derived from it (target-network EMA, episode ends) stay scalar.
"""
from __future__ import annotations

import contextlib
import dataclasses
import json
import sys
import time
from functools import partial
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from hprior_jax.agents.sac import SAC, SACState
from hprior_jax.buffers import replay
from hprior_jax.config import TrainConfig
from hprior_jax.envs import EnvState, make_env
from hprior_jax.evaluate import evaluate_policy

RANDOM, SAC_PHASE = "random", "sac"


@struct.dataclass
class RunState:
    sac: SACState
    replay: replay.ReplayState
    env: EnvState
    key: jax.Array  # raw uint32[2] key (checkpoint-friendly)
    extra: Any = None  # algorithm-specific state (PEBBLE: reward model, preferences, ...)


SAC_METRICS = ("train/critic_loss", "train/q", "train/actor_loss", "train/alpha_loss",
               "train/alpha", "train/entropy")


class Trainer:
    """The static half of a run: env, agent, compiled chunks. Holds no mutable run state.

    Algorithms extend it (see `hprior_jax.pebble.trainer`) through four hooks: the phases and
    their per-step functions (`phases`, `phase_starts`, `_phase_steps`), the reward stored
    with each new transition (`_stored_reward`), extra state (`_init_extra`), and host-side
    events between chunks (`event_steps`, `run_event`)."""

    def __init__(self, cfg: TrainConfig):
        self.cfg = cfg
        self.env = make_env(cfg.task, num_envs=1)
        self.eval_env = make_env(cfg.task, num_envs=cfg.num_eval_episodes)
        self.task = self.env.task
        self.sac = SAC(self.env.obs_size, self.env.action_size, cfg.sac)
        self._compiled: dict = {}
        self.compile_seconds: dict[str, float] = {}

    # -- schedule (host side, the same for every seed) ---------------------------------------
    @property
    def phases(self) -> tuple[str, ...]:
        return (RANDOM, SAC_PHASE)

    def phase_starts(self) -> tuple[int, ...]:
        """First global step of each phase after the first."""
        return (self.cfg.num_seed_steps,)

    def phase_at(self, step: int) -> str:
        return self.phases[sum(step >= b for b in self.phase_starts())]

    def phase_metrics(self, phase: str) -> tuple[str, ...]:
        """The `train/` metrics that are meaningful in `phase` (others are placeholders)."""
        return () if phase == RANDOM else SAC_METRICS

    def event_steps(self) -> list[int]:
        """Global steps before which `run_event` runs (PEBBLE: feedback rounds)."""
        return []

    def run_event(self, rs: RunState, step: int):
        raise NotImplementedError

    def chunk_plan(self, step: int) -> tuple[str, int]:
        """Phase and length of the next chunk: never crosses a phase change, event,
        evaluation, checkpoint or the end of training."""
        cfg = self.cfg
        bounds = [cfg.steps, _next_multiple(step, cfg.chunk_steps),
                  _next_multiple(step, cfg.eval_every), _next_multiple(step, cfg.checkpoint_every)]
        bounds += [b for b in (*self.phase_starts(), *self.event_steps()) if b > step]
        return self.phase_at(step), min(bounds) - step

    # -- pure functions (per seed) --------------------------------------------------------
    def init(self, seed_key: jax.Array, capacity: int | None = None) -> RunState:
        k_sac, k_env, k_run, k_extra = jax.random.split(seed_key, 4)
        capacity = capacity or self.cfg.capacity
        return RunState(
            sac=self.sac.init(k_sac),
            replay=replay.init(capacity, self.env.obs_size, self.env.action_size),
            env=self.env.reset(k_env), key=k_run, extra=self._init_extra(k_extra))

    def _init_extra(self, key: jax.Array):
        return None

    def _stored_reward(self, rs: RunState, obs, action, true_reward):
        """The reward written with a new transition: SAC on the true reward stores it."""
        return true_reward

    def _random_step(self, rs: RunState, obs, step, keys):
        action = jax.random.uniform(keys[0], (self.env.action_size,), minval=-1.0, maxval=1.0)
        return action, rs, {}

    def _sac_step(self, rs: RunState, obs, step, keys, reward_fn=None):
        """BPref order: act with the current policy, update, then (the caller) steps the env.
        `reward_fn(rs, batch) -> (reward, rs)` replaces the buffer's reward (pre-training)."""
        action = self.sac.act(rs.sac.actor, obs, keys[0])
        batch = replay.sample(rs.replay, keys[1], self.sac.cfg.batch_size)
        metrics = {}
        if reward_fn is not None:
            reward, rs, metrics = reward_fn(rs, batch)
            batch = batch._replace(reward=reward)
        sac_state, sac_metrics = self.sac.update(rs.sac, batch, keys[2], step)
        return action, rs.replace(sac=sac_state), {**metrics, **sac_metrics}

    def _phase_steps(self) -> dict:
        """Per-step function of each phase: (rs, obs, step, keys) -> (action, rs, metrics)."""
        return {RANDOM: self._random_step, SAC_PHASE: self._sac_step}

    def chunk(self, rs: RunState, step0: jax.Array, *, length: int):
        """`length` env steps from global step `step0`. A chunk never crosses a phase change,
        so the phase is an unbatched `lax.switch` index: a real branch under vmap, and one
        compiled program for every phase."""
        steps = self._phase_steps()
        branches = [steps[p] for p in self.phases]
        phase = sum((step0 >= b).astype(jnp.int32) for b in self.phase_starts())
        metric_keys = sorted({k for p in self.phases for k in self.phase_metrics(p)})

        def padded(fn):
            def run(*args):
                action, rs, m = fn(*args)
                return action, rs, {k: m.get(k, jnp.zeros((), jnp.float32)) for k in metric_keys}
            return run

        def body(rs: RunState, i):
            step = step0 + i
            key, k_act, k_sample, k_update, k_reset = jax.random.split(rs.key, 5)
            obs = rs.env.task.obs[0]
            action, rs, metrics = jax.lax.switch(phase, [padded(b) for b in branches], rs, obs,
                                                 step, (k_act, k_sample, k_update))
            env_state, tr = self.env.step(rs.env, action[None], step, k_reset)
            reward = self._stored_reward(rs, tr.obs[0], tr.action[0], tr.true_reward[0])
            buf = replay.add(rs.replay, tr.obs[0], tr.action[0], reward, tr.next_obs[0],
                             1.0 - tr.terminated[0].astype(jnp.float32), tr.true_reward[0])
            metrics = dict(metrics)
            metrics.update({
                "episode/done": jnp.logical_or(tr.terminated[0], tr.truncated[0]),
                "episode/true_return": tr.episode_return[0],
                "episode/success": tr.episode_success[0],
            })
            return rs.replace(replay=buf, env=env_state, key=key), metrics

        return jax.lax.scan(body, rs, jnp.arange(length, dtype=jnp.int32))

    def evaluate(self, actor_params, key: jax.Array):
        policy = lambda obs: self.sac.act(actor_params, obs, key, deterministic=True)
        return evaluate_policy(self.eval_env, policy, key)

    # -- compiled, vmapped over seeds ---------------------------------------------------------
    def _aot(self, name: str, fn, *args):
        """Compiles ahead of time so compile time is measured apart from run time."""
        if name not in self._compiled:
            t0 = time.perf_counter()
            self._compiled[name] = fn.lower(*args).compile()
            self.compile_seconds[name] = time.perf_counter() - t0
        return self._compiled[name]

    def init_seeds(self, seeds, capacity: int | None = None) -> RunState:
        keys = jnp.stack([jax.random.PRNGKey(s) for s in seeds])
        return jax.jit(jax.vmap(partial(self.init, capacity=capacity)))(keys)

    def run_chunk(self, rs: RunState, step0: int, length: int):
        fn = jax.jit(jax.vmap(partial(self.chunk, length=length), in_axes=(0, None)),
                     donate_argnums=0)
        step0 = np.int32(step0)
        return self._aot(f"chunk/{length}", fn, rs, step0)(rs, step0)

    def run_eval(self, rs: RunState, seeds, step: int):
        # keys derived from (seed, step) only: evaluation never touches the training stream
        keys = jnp.stack([jax.random.fold_in(jax.random.PRNGKey(s), 0x5EED0000 + step)
                          for s in seeds])
        fn = jax.jit(jax.vmap(self.evaluate))
        return self._aot("eval", fn, rs.sac.actor, keys)(rs.sac.actor, keys)


def make_trainer(cfg: TrainConfig) -> Trainer:
    if cfg.algo == "sac":
        return Trainer(cfg)
    if cfg.algo == "pebble":
        from hprior_jax.pebble.trainer import PebbleTrainer

        return PebbleTrainer(cfg)
    if cfg.algo == "prior":
        from hprior_jax.prior.trainer import PriorTrainer

        return PriorTrainer(cfg)
    raise ValueError(f"unknown algorithm {cfg.algo!r}")


def _next_multiple(step: int, every: int) -> int:
    return (step // every + 1) * every


# ---------------------------------------------------------------------------------------------
# host loop
# ---------------------------------------------------------------------------------------------
class TrainingDiverged(RuntimeError):
    pass


def _finite_or_raise(metrics: dict, step0: int, step1: int, seeds, run_dir, last_ckpt):
    for name, value in metrics.items():
        if name.startswith(("train/", "reward/", "prior/")):
            bad = ~np.all(np.isfinite(np.asarray(value)), axis=tuple(range(1, np.ndim(value))))
            if bad.any():
                which = [s for s, b in zip(seeds, bad) if b]
                msg = (f"non-finite {name} between steps {step0} and {step1} for seed(s) "
                       f"{which}. Nothing after step {last_ckpt} was saved; the run directory "
                       f"{run_dir} keeps the checkpoint at step {last_ckpt} and all metrics up "
                       "to it. Lower the learning rate (--sac.lr) or use other seeds, then "
                       f"continue with `hprior train --resume {run_dir}` or start a new run.")
                (Path(run_dir) / "error.txt").write_text(msg + "\n")
                raise TrainingDiverged(msg)


def prepare_run_dir(cfg: TrainConfig) -> Path:
    """Creates the run directory; refuses to write into a non-empty one."""
    out = Path(cfg.out) if cfg.out else Path("runs") / (
        f"{cfg.task}_{cfg.algo}_{time.strftime('%Y%m%d-%H%M%S')}")
    if out.exists() and any(out.iterdir()):
        raise FileExistsError(
            f"output directory {out} exists and is not empty; continue it with "
            f"`hprior train --resume {out}` or choose another --out")
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.json").write_text(cfg.to_json() + "\n")
    return out


def load_run_config(run_dir: Path) -> TrainConfig:
    path = Path(run_dir) / "config.json"
    if not path.exists():
        raise FileNotFoundError(f"{path} not found: --resume needs a run directory written "
                                "by `hprior train`")
    return TrainConfig.from_dict(json.loads(path.read_text()))


def extend_run(run_dir: Path, steps: int) -> tuple[TrainConfig, int]:
    """Raises the step budget of an existing run; returns the new config and the replay
    capacity its checkpoints were written with."""
    old = load_run_config(run_dir)
    if steps < old.steps:
        raise ValueError(f"--steps {steps} is below the run's budget {old.steps}; a resumed "
                         "run can only be extended")
    new = dataclasses.replace(old, steps=steps)
    (Path(run_dir) / f"config.steps{old.steps}.json").write_text(old.to_json() + "\n")
    (Path(run_dir) / "config.json").write_text(new.to_json() + "\n")
    return new, old.capacity


def run(cfg: TrainConfig, run_dir: Path, resume: bool = False, progress: bool = True,
        max_chunks: int | None = None, saved_capacity: int | None = None) -> RunState:
    """Trains `cfg` into `run_dir` (made by `prepare_run_dir`, or an existing run to resume).

    `max_chunks` stops early after that many chunks (used by tests to simulate an
    interruption); the state is checkpointed at the stop. `saved_capacity` is the replay
    capacity of the checkpoints when a resumed run's budget was extended."""
    from hprior_jax.checkpoint import Checkpointer
    from hprior_jax.plotting import plot_learning_curve
    from hprior_jax.run_log import RunLog

    run_dir = Path(run_dir)
    trainer = make_trainer(cfg)
    seeds = list(cfg.seeds)
    ckpt = Checkpointer(run_dir / "checkpoints")
    step = 0
    rs = trainer.init_seeds(seeds, capacity=saved_capacity if resume else None)
    if resume and ckpt.latest_step() is not None:
        step, rs = ckpt.restore(rs)
    if rs.replay.capacity != cfg.capacity:
        if replay.has_wrapped(rs.replay):
            raise ValueError("the replay buffer of this run has wrapped around; it cannot be "
                             "extended with --steps (start a new run instead)")
        rs = rs.replace(replay=jax.vmap(partial(replay.grow, capacity=cfg.capacity))(rs.replay))
    log = RunLog(run_dir, seeds, resume_step=step if resume else None)
    has_success = trainer.task.has_success
    last_ckpt = step
    bar = _progress_bar(cfg.steps, step, progress)
    chunks = 0
    events = set(trainer.event_steps())
    try:
        while step < cfg.steps and (max_chunks is None or chunks < max_chunks):
            compiled_before = set(trainer.compile_seconds)
            timer = _WallTimer(trainer.compile_seconds)  # wall time per part, compiles apart
            if step in events:  # e.g. a PEBBLE feedback round: before this step's update
                with timer("event_s"):
                    rs, event_metrics = trainer.run_event(rs, step)
                    event_metrics = jax.device_get(event_metrics)
                _finite_or_raise(event_metrics, step, step, seeds, run_dir, last_ckpt)
                for i, s in enumerate(seeds):
                    log.log(step, s, {k: np.asarray(v)[i] for k, v in event_metrics.items()})
            phase, length = trainer.chunk_plan(step)
            with timer("chunk_s"):  # env steps and agent updates: one fused program
                rs, metrics = trainer.run_chunk(rs, step, length)
                metrics = jax.device_get(metrics)
            keep = trainer.phase_metrics(phase)  # drop placeholders of other phases
            metrics = {k: v for k, v in metrics.items()
                       if not k.startswith("train/") or k in keep}
            _finite_or_raise(metrics, step, step + length, seeds, run_dir, last_ckpt)
            _log_chunk(log, seeds, step, metrics, has_success)
            step += length
            chunks += 1
            if step % cfg.eval_every == 0 or step == cfg.steps:
                with timer("eval_s"):
                    returns, successes = jax.device_get(trainer.run_eval(rs, seeds, step))
                for i, s in enumerate(seeds):
                    log.log_eval(step, s, float(np.mean(returns[i])),
                                 float(np.mean(successes[i])) if has_success else None)
                bar.set_postfix_str(f"eval return {np.mean(returns):.1f}")
            if step % cfg.checkpoint_every == 0 or step == cfg.steps or (
                    max_chunks is not None and chunks == max_chunks):
                log.flush()
                with timer("checkpoint_s"):
                    ckpt.save(step, rs)
                last_ckpt = step
            perf = {"perf/env_steps_per_s": length * len(seeds) / max(timer.seconds["chunk_s"],
                                                                      1e-9)}
            perf.update({f"perf/{k}": v for k, v in timer.seconds.items() if v or k == "chunk_s"})
            for s in seeds:
                log.log(step, s, perf)
            log.flush()  # a crash or kill loses at most the chunk in flight
            for name in sorted(set(trainer.compile_seconds) - compiled_before):
                bar.write(f"compiled {name} in {trainer.compile_seconds[name]:.1f} s "
                          "(once per shape; not counted in env steps/s)", file=sys.stdout)
                sys.stdout.flush()
            bar.update(length)
            bar.set_description(f"{perf['perf/env_steps_per_s']:.0f} env steps/s")
    finally:
        bar.close()
        log.close()
        ckpt.close()
    if (run_dir / "eval.csv").exists():
        plot_learning_curve(run_dir / "eval.csv", run_dir / "learning_curve.png",
                            title=f"{cfg.algo} on {cfg.task}")
    return rs


class _WallTimer:
    """Wall seconds per named part of one loop iteration, less any compile that happened
    inside it (`compile_seconds` is the trainer's dict of program -> compile time, which
    grows when a new program is compiled); compile time is summed under `compile_s`."""

    def __init__(self, compile_seconds: dict):
        self.compile_seconds = compile_seconds
        self.seconds = {"compile_s": 0.0}

    @contextlib.contextmanager
    def __call__(self, part: str):
        before, t0 = set(self.compile_seconds), time.perf_counter()
        yield
        compiled = sum(v for k, v in self.compile_seconds.items() if k not in before)
        self.seconds["compile_s"] += compiled
        self.seconds[part] = self.seconds.get(part, 0.0) + time.perf_counter() - t0 - compiled


def _log_chunk(log, seeds, step0: int, metrics: dict, has_success: bool) -> None:
    """Train-episode returns where episodes ended, mean losses per chunk."""
    done = metrics["episode/done"]  # [S, T]
    for i, s in enumerate(seeds):
        for t in np.flatnonzero(done[i]):
            ep = {"train/true_episode_return": metrics["episode/true_return"][i, t]}
            if has_success:
                ep["train/true_episode_success"] = metrics["episode/success"][i, t]
            log.log(step0 + int(t) + 1, s, ep)
        losses = {k: float(np.mean(v[i])) for k, v in metrics.items() if k.startswith("train/")}
        if losses:
            log.log(step0 + done.shape[1], s, losses)


def _progress_bar(total: int, initial: int, enabled: bool):
    from tqdm.auto import tqdm

    return tqdm(total=total, initial=initial, unit="step", disable=not enabled,
                dynamic_ncols=True, mininterval=1.0)
