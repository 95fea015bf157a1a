"""The Python entry points: train a configured run, step and render a task's environments in
a notebook, evaluate a policy (e.g. one exported by `hprior export`, `load_policy`)."""
from __future__ import annotations

import contextlib
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from hprior_jax import dir_lock, provenance
from hprior_jax.config import RunConfig
from hprior_jax.envs import VecEnv, make_env as make_vec_env
from hprior_jax.evaluate import evaluate_policy as evaluate_batch
from hprior_jax.loop.run_files import latest_checkpoint_step, settle_extension
from hprior_jax.render import render_frames
from hprior_jax.runs.build import build_engine, train as train_run
from hprior_jax.runs.run_dir import (PYTHON, check_out_dir, load_run_config, prepare_run_dir,
                                     resume_config, run_dir_path)


@dataclass(frozen=True)
class Evaluation:
    """What a training callback gets after each evaluation: per seed of the run, the mean
    true return (and success rate where the task has one) over its evaluation episodes."""

    step: int
    seeds: tuple[int, ...]
    returns: np.ndarray  # [seeds]
    successes: np.ndarray | None  # [seeds], None for a task without success


def train(config: RunConfig, callbacks: tuple[Callable[[Evaluation], bool | None], ...] = (),
          progress: bool = True, resume: bool = False) -> Path:
    """Trains `config` (e.g. `hprior_jax.presets.train_preset(task, algo, preset, out=...)`)
    into a new run directory and returns its path, as `hprior train` does: the directory is
    locked while it trains and its config.json records what produced it (`run_info`). Each
    callback gets an `Evaluation` after every evaluation; one returning True stops the run
    there, checkpointed. `resume=True` continues the run in `config.out` from its latest
    checkpoint (as `hprior train --resume`): `config` may differ from the run's only in the
    budget and the cadences (`hprior_jax.config.CHANGEABLE_ON_RESUME`)."""
    seeds = tuple(config.seeds)

    def on_evaluation(step, returns, successes) -> bool:
        evaluation = Evaluation(step, seeds, np.asarray(returns),
                                None if successes is None else np.asarray(successes))
        return any([bool(callback(evaluation)) for callback in callbacks])

    run = _resumed if resume else _started
    with run(config) as (cfg, run_dir, options):
        train_run(cfg, run_dir, progress=progress,
                  on_evaluation=on_evaluation if callbacks else None, **options)
    return run_dir


@contextlib.contextmanager
def _started(config: RunConfig):
    """A new run directory, locked: checked and its engine built before anything is
    written."""
    check_out_dir(run_dir_path(config), PYTHON)
    engine = build_engine(config)
    run_dir = prepare_run_dir(config, provenance.run_info(), PYTHON)
    with dir_lock.DirLock(run_dir):
        yield config, run_dir, dict(engine=engine)


@contextlib.contextmanager
def _resumed(config: RunConfig):
    """The run in `config.out`, locked, with the changes `config` may make to it."""
    if not config.out:
        raise ValueError("resume=True continues the run in config.out: set it to the run's "
                         "directory")
    run_dir = Path(config.out)
    load_run_config(run_dir)  # a run directory at all, before locking it
    with dir_lock.DirLock(run_dir):
        note = settle_extension(run_dir, latest_checkpoint_step(run_dir))
        if note:
            print(note, file=sys.stderr, flush=True)
        cfg, saved_capacity = resume_config(run_dir, config, PYTHON)
        yield cfg, run_dir, dict(resume=True, saved_capacity=saved_capacity)


class Env:
    """`num_envs` environments of `task` for interactive use (`obs_size`, `action_size`):
    `reset()` -> obs [N, obs]; `step(action [N, act])` -> (obs, reward [N], done [N], info) with every environment reset
    together at the time limit (`done` then true; info: success, episode_return);
    `render(index)` -> an RGB frame of environment `index`. Steps are jitted (the first call
    compiles)."""

    def __init__(self, task: str, num_envs: int = 1, seed: int = 0, **task_options):
        self.env: VecEnv = make_vec_env(task, num_envs, **task_options)
        self.task = self.env.task
        self.num_envs, self.obs_size, self.action_size = (num_envs, self.env.obs_size,
                                                          self.env.action_size)
        self._key = jax.random.PRNGKey(seed)
        self._reset = jax.jit(self.env.reset)
        self._step = jax.jit(self.env.step)
        self.state, self.t = None, 0

    def reset(self) -> np.ndarray:
        self._key, key = jax.random.split(self._key)
        self.state, self.t = self._reset(key), 0
        return np.asarray(self.state.task.obs)

    def step(self, action) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
        if self.state is None:
            raise RuntimeError("call reset() before step()")
        action = jnp.asarray(action, jnp.float32)
        _check_actions(action.shape, self.env, self.task.name)
        self._key, key = jax.random.split(self._key)
        self.state, tr = self._step(self.state, action, jnp.int32(self.t), key)
        self.t = (self.t + 1) % self.env.episode_length
        done = np.asarray(tr.truncated | tr.terminated)
        info = {"success": np.asarray(tr.success), "episode_return": np.asarray(tr.episode_return)}
        return np.asarray(self.state.task.obs), np.asarray(tr.true_reward), done, info

    def render(self, index: int = 0, width: int = 320, height: int = 240) -> np.ndarray:
        """uint8[height, width, 3] of environment `index` in its current state."""
        if self.state is None:
            raise RuntimeError("call reset() before render()")
        fields = self.task.render_states(self.state.task.data)
        one = {k: np.asarray(v)[index][None] for k, v in fields.items()}
        return render_frames(self.task.mj_model, one, width, height)[0]


def make_env(task: str, num_envs: int = 1, seed: int = 0, **task_options) -> Env:
    """`Env` of `task` (`hprior tasks` lists them)."""
    return Env(task, num_envs, seed, **task_options)


def evaluate_policy(policy: Callable, task: str, episodes: int = 10, seed: int = 0,
                    **task_options) -> tuple[np.ndarray, np.ndarray]:
    """(true return [episodes], success [episodes]) of whole episodes of `task` under
    `policy` (obs [N, obs] -> action [N, act]), run side by side from `seed`'s starts. A JAX
    function (e.g. `load_policy(path)`) runs compiled with the episodes; any other (NumPy,
    PyTorch, one that keeps state between calls) is called once per step on the host."""
    env = make_vec_env(task, episodes, **task_options)
    key = jax.random.PRNGKey(seed)
    if _is_jax_function(policy, env, task):
        returns, successes = jax.jit(lambda key: evaluate_batch(env, policy, key))(key)
    else:
        returns, successes = _evaluate_on_host(policy, env, task, key)
    return np.asarray(returns), np.asarray(successes)


def _is_jax_function(policy: Callable, env: VecEnv, task: str) -> bool:
    """Traces `policy` once: True when it maps a traced batch of observations to traced
    actions (of the task's shape). NumPy code fails on a traced input, or returns a constant
    that compiling would freeze into every step: False."""
    obs = jax.ShapeDtypeStruct((env.num_envs, env.obs_size), jnp.float32)
    traced = []

    def probe(o):
        out = policy(o)
        traced.append(isinstance(out, jax.core.Tracer))
        return jnp.asarray(out)

    try:
        actions = jax.eval_shape(probe, obs)
    except Exception:  # noqa: BLE001 - not traceable: the host calls it (and names its error)
        return False
    if traced[0]:
        _check_actions(actions.shape, env, task)
    return traced[0]


def _evaluate_on_host(policy: Callable, env: VecEnv, task: str, key: jax.Array):
    state = jax.jit(env.reset)(key)
    advance = jax.jit(env.advance)
    for t in range(env.episode_length):
        obs = np.asarray(state.task.obs)
        try:
            action = np.asarray(policy(obs), np.float32)
        except Exception as e:  # noqa: BLE001 - the user's policy: its own error, named
            reason = (str(e).strip().splitlines() or [""])[0][:200]
            raise ValueError(f"the policy fails on observations of {task} (shape "
                             f"{obs.shape}): {type(e).__name__}: {reason}") from e
        _check_actions(action.shape, env, task)
        state, _ = advance(state, action, np.int32(t))
    return state.episode_return, state.episode_success


def _check_actions(shape: tuple, env, task: str) -> None:
    expected = (env.num_envs, env.action_size)
    if tuple(shape) != expected:
        raise ValueError(f"expected actions of shape {expected} ({env.num_envs} environments "
                         f"of {task}, {env.action_size} action dimensions), got "
                         f"{tuple(shape)}")
