"""Parity of a DM Control port against dm_control itself (C MuJoCo): the helpers of
`python -m benchmarks.ports.dm_control_parity` and tests/tasks/test_dm_control_tasks.py.

  same_data    our observation and reward on dm_control's own MjData (`obs_reward_check`);
  same_state   C `mj_forward` and `mjx.forward` on the same state (`same_state_check`), the
               reset observation (`reset_check`), quadruped's reset height
               (`quadruped_height_check`);
  trajectory   the same actions from dm_control's reset states (`trajectory_check`);
  policy       episode returns of random and zero actions (`policy_returns`).
Each port names the suite task it reproduces (its class's `suite`). Imported only by tests
and benchmarks.
"""
from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np

import tasks
from tasks.base import TaskState
from tasks.dm_control.common import DMControlTask
from tasks.physics import mjx

HORIZONS = (20, 100, 1000)


def ports() -> list[str]:
    """The registered DM Control ports, by name (not the model-less tasks that tests
    register under the dm_control domain)."""
    return [n for n in tasks.names() if tasks.info(n).domain == "dm_control"
            and issubclass(tasks.task_class(n), DMControlTask)]


# -- dm_control side --------------------------------------------------------------------
def reference_env(name: str, seed: int):
    from dm_control import suite

    domain, task = tasks.task_class(name).suite
    return suite.load(domain, task, task_kwargs={"random": seed})


def flatten_obs(obs) -> np.ndarray:
    """dmc2gym's `_flatten_obs`: scalars as 1-vectors, arrays raveled, dict order."""
    return np.concatenate([np.array([v]) if np.isscalar(v) else np.asarray(v).ravel()
                           for v in obs.values()])


def to_ctrl(env, action: np.ndarray) -> np.ndarray:
    """dmc2gym's rescaling of [-1, 1] actions to the action spec's bounds."""
    spec = env.action_spec()
    return spec.minimum + (np.asarray(action, np.float64) + 1.0) / 2.0 * (spec.maximum - spec.minimum)


def reference_rollout(env, actions: np.ndarray):
    """Steps `env` (already reset) with [-1, 1] actions: obs, rewards, qpos per step."""
    obs, rew, qpos = [], [], []
    for a in actions:
        ts = env.step(to_ctrl(env, a))
        obs.append(flatten_obs(ts.observation))
        rew.append(ts.reward)
        qpos.append(env.physics.data.qpos.copy())
    return np.asarray(obs), np.asarray(rew), np.asarray(qpos)


def reference_forward(env, qpos, qvel, act, ctrl):
    """dm_control observation and reward after `mj_forward` on the given state."""
    physics = env.physics
    physics.data.qpos[:], physics.data.qvel[:] = qpos, qvel
    physics.data.act[:], physics.data.ctrl[:] = act, ctrl
    physics.forward()
    return flatten_obs(env.task.get_observation(physics)), float(env.task.get_reward(physics))


# -- MJX side ---------------------------------------------------------------------------
def data_like(task, template: mjx.Data, **fields) -> mjx.Data:
    """A fresh MJX data with the dtypes of `template` and the given fields set."""
    data = mjx.make_data(task.model)
    data = data.replace(**{k: jnp.asarray(v, getattr(data, k).dtype) for k, v in fields.items()})
    return jax.tree.map(lambda x, t: x.astype(t.dtype) if hasattr(x, "dtype") else x,
                        data, template)


def state_from_physics(task, physics) -> TaskState:
    """TaskState holding a copy of dm_control's full MuJoCo data (dtypes as in our resets)."""
    template = mjx.make_data(task.model)
    data = mjx.put_data(task.mj_model, physics.data)
    data = jax.tree.map(lambda x, t: jnp.asarray(x, t.dtype), data, template)
    zero = jnp.zeros((), jnp.float32)
    return TaskState(data=data, obs=task._observation(data), true_reward=zero, success=zero,
                     terminated=jnp.zeros((), bool))


def make_rollout(task):
    """jit(vmap(scan(step))): (states[B], actions[B, T, A]) -> (obs, reward, qpos)[B, T]."""

    def rollout(state, actions):
        def body(s, a):
            s = task.step(s, a)
            return s, (s.obs, s.true_reward, s.data.qpos)
        return jax.lax.scan(body, state, actions)[1]

    return jax.jit(jax.vmap(rollout))


def make_forward_obs(task):
    """jit(vmap): (qpos, qvel, act, ctrl) -> (obs, reward) after `mjx.forward`."""
    template = mjx.make_data(task.model)

    def f(qpos, qvel, act, ctrl):
        data = data_like(task, template, qpos=qpos, qvel=qvel, act=act, ctrl=ctrl)
        data = task.forward(data)
        return task._observation(data), task._reward(data)

    return jax.jit(jax.vmap(f))


def stack(trees):
    # through numpy: eager jnp.stack returns *committed* arrays, and jit keys its cache on
    # that, so the stacked states would recompile a rollout already compiled for resets
    return jax.tree.map(lambda *x: jnp.asarray(np.stack([np.asarray(a) for a in x])), *trees)


# -- checks -----------------------------------------------------------------------------
def same_state_check(task, name, n_states=20, seed=0, forward_obs=None):
    """Max |obs| and |reward| differences of C vs MJX forward on states along a trajectory."""
    env = reference_env(name, seed)
    env.reset()
    rng = np.random.RandomState(seed)
    states = []
    for _ in range(n_states):
        env.step(to_ctrl(env, rng.uniform(-1, 1, task.action_size)))
        d = env.physics.data
        states.append((d.qpos.copy(), d.qvel.copy(), d.act.copy(), d.ctrl.copy()))
    ref = [reference_forward(env, *s) for s in states]
    forward_obs = forward_obs or make_forward_obs(task)
    obs, rew = forward_obs(*[jnp.asarray(np.stack(x), jnp.float32) for x in zip(*states)])
    obs_err = np.abs(np.asarray(obs) - np.stack([r[0] for r in ref]))
    rew_err = np.abs(np.asarray(rew) - np.array([r[1] for r in ref]))
    return obs_err.max(), rew_err.max(), obs_err.max(0)


def obs_reward_check(task, name, n_states=20, seed=0):
    """Our obs/reward functions on dm_control's own MuJoCo data (copied with put_data) vs
    dm_control's observation and reward: checks layout, sensor selection and reward shapes
    without compiling any MJX physics. States: the reset state, then a random trajectory."""
    env = reference_env(name, seed)
    ts = env.reset()
    rng = np.random.RandomState(seed)
    f = jax.jit(lambda d: (task._observation(d), task._reward(d)))
    obs_err, rew_err = 0.0, 0.0
    for i in range(n_states):
        if i:
            ts = env.step(to_ctrl(env, rng.uniform(-1, 1, task.action_size)))
        obs, rew = f(state_from_physics(task, env.physics).data)
        obs_err = max(obs_err, np.abs(np.asarray(obs) - flatten_obs(ts.observation)).max())
        if i:
            rew_err = max(rew_err, abs(float(rew) - ts.reward))
    return obs_err, rew_err


def reset_check(task, name, seeds=range(5)):
    """Max |obs diff| of dm_control's reset obs vs our reset forward on the same state."""
    errs = []
    fwd = jax.jit(lambda qpos, qvel, act: task._observation(task.reset_forward(
        mjx.make_data(task.model).replace(qpos=qpos, qvel=qvel, act=act))))
    for seed in seeds:
        env = reference_env(name, seed)
        ts = env.reset()
        d = env.physics.data
        obs = fwd(*[jnp.asarray(x, jnp.float32) for x in (d.qpos, d.qvel, d.act)])
        errs.append(np.abs(np.asarray(obs) - flatten_obs(ts.observation)).max())
    return max(errs)


def quadruped_height_check(task, n=200, seed=0):
    """Closed-form reset height vs dm_control's `_find_non_contacting_height` search."""
    from dm_control.suite import quadruped

    env = reference_env("quadruped_walk", seed)
    rng = np.random.RandomState(seed)
    quats = rng.randn(n, 4)
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    ref = []
    for q in quats:
        quadruped._find_non_contacting_height(env.physics, q)
        ref.append(env.physics.data.qpos[2])
    ours = jax.jit(jax.vmap(task.non_contacting_height))(jnp.asarray(quats, jnp.float32))
    steps = np.round((np.asarray(ours) - np.asarray(ref)) / 0.01)
    return int(np.sum(steps != 0)), float(np.abs(np.asarray(ours) - np.asarray(ref)).max())


def trajectory_check(task, name, n_episodes, horizon, seed=0, rollout=None):
    """Same actions from dm_control's reset states; per-horizon drift and return difference."""
    envs = [reference_env(name, seed + i) for i in range(n_episodes)]
    for env in envs:
        env.reset()
    states = stack([state_from_physics(task, env.physics) for env in envs])
    rng = np.random.RandomState(seed)
    actions = rng.uniform(-1, 1, (n_episodes, horizon, task.action_size)).astype(np.float32)
    rollout = rollout or make_rollout(task)
    t0 = time.perf_counter()
    obs, rew, qpos = jax.block_until_ready(rollout(states, jnp.asarray(actions)))
    mjx_s = time.perf_counter() - t0
    refs = [reference_rollout(env, a) for env, a in zip(envs, actions)]
    obs, rew, qpos = map(np.asarray, (obs, rew, qpos))
    out = {}
    for h in HORIZONS:
        if h > horizon:
            continue
        obs_err = max(np.abs(obs[i, :h] - refs[i][0][:h]).max() for i in range(n_episodes))
        qpos_err = max(np.abs(qpos[i, :h] - refs[i][2][:h]).max() for i in range(n_episodes))
        rew_err = max(np.abs(rew[i, :h] - refs[i][1][:h]).max() for i in range(n_episodes))
        ret_diff = np.array([rew[i, :h].sum() - refs[i][1][:h].sum() for i in range(n_episodes)])
        ret_ref = np.array([refs[i][1][:h].sum() for i in range(n_episodes)])
        out[h] = dict(obs_max_abs=obs_err, qpos_max_abs=qpos_err, reward_max_abs=rew_err,
                      return_diff_max_abs=np.abs(ret_diff).max(),
                      return_diff_mean=ret_diff.mean(), return_ref_mean=ret_ref.mean())
    return out, mjx_s


def policy_returns(task, name, n_episodes, policy, seed=0, rollout=None):
    """Episode returns of a random or zero policy, MJX (own resets) and dm_control."""
    T, A = task.episode_length, task.action_size
    rng = np.random.RandomState(seed + 1000)
    if policy == "random":
        actions = rng.uniform(-1, 1, (n_episodes, T, A)).astype(np.float32)
    else:
        actions = np.zeros((n_episodes, T, A), np.float32)
    keys = jax.random.split(jax.random.key(seed), n_episodes)
    states = jax.jit(jax.vmap(task.reset))(keys)
    rollout = rollout or make_rollout(task)
    _, rew, _ = rollout(states, jnp.asarray(actions))
    ours = np.asarray(rew).sum(1)
    theirs = []
    for i in range(n_episodes):
        env = reference_env(name, seed + 100 + i)
        env.reset()
        theirs.append(reference_rollout(env, actions[i])[1].sum())
    return ours, np.asarray(theirs)
