"""The Python entry points: train a configured run, step and render a task's environments in
a notebook, evaluate a policy (e.g. one exported by `hprior export`, `load_policy`)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import jax
import numpy as np

from hprior_jax.config import RunConfig
from hprior_jax.envs import VecEnv, make_env as make_vec_env
from hprior_jax.evaluate import evaluate_policy as evaluate_batch
from hprior_jax.render import render_frames
from hprior_jax.runs.build import train as train_run
from hprior_jax.runs.run_dir import prepare_run_dir


@dataclass(frozen=True)
class Evaluation:
    """What a training callback gets after each evaluation: per seed of the run, the mean
    true return (and success rate where the task has one) over its evaluation episodes."""

    step: int
    seeds: tuple[int, ...]
    returns: np.ndarray  # [seeds]
    successes: np.ndarray | None  # [seeds], None for a task without success


def train(config: RunConfig, callbacks: tuple[Callable[[Evaluation], bool | None], ...] = (),
          progress: bool = True) -> Path:
    """Trains `config` (e.g. `hprior_jax.presets.train_preset(task, algo, preset, out=...)`)
    into a new run directory and returns its path. Each callback
    gets an `Evaluation` after every evaluation; one returning True stops the run there,
    checkpointed (`hprior train --resume DIR` continues it)."""
    run_dir = prepare_run_dir(config)
    seeds = tuple(config.seeds)

    def on_evaluation(step, returns, successes) -> bool:
        evaluation = Evaluation(step, seeds, np.asarray(returns),
                                None if successes is None else np.asarray(successes))
        return any([bool(callback(evaluation)) for callback in callbacks])

    train_run(config, run_dir, progress=progress,
              on_evaluation=on_evaluation if callbacks else None)
    return run_dir


class Env:
    """`num_envs` environments of `task` for interactive use: `reset()` -> obs [N, obs];
    `step(action [N, act])` -> (obs, reward [N], done [N], info) with every environment reset
    together at the time limit (`done` then true; info: success, episode_return);
    `render(index)` -> an RGB frame of environment `index`. Steps are jitted (the first call
    compiles)."""

    def __init__(self, task: str, num_envs: int = 1, seed: int = 0, **task_options):
        self.env: VecEnv = make_vec_env(task, num_envs, **task_options)
        self.task = self.env.task
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
        self._key, key = jax.random.split(self._key)
        self.state, tr = self._step(self.state, jax.numpy.asarray(action, jax.numpy.float32),
                                    jax.numpy.int32(self.t), key)
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
    `policy` (obs [N, obs] -> action [N, act], a JAX function: e.g. `load_policy(path)`),
    run side by side from `seed`'s starts."""
    env = make_vec_env(task, episodes, **task_options)
    returns, successes = jax.jit(lambda key: evaluate_batch(env, policy, key))(
        jax.random.PRNGKey(seed))
    return np.asarray(returns), np.asarray(successes)
