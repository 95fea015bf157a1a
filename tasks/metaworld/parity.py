"""State and episode parity of a MetaWorld port against metaworld (C MuJoCo): the helpers of
`python -m benchmarks.ports.metaworld_parity` and tests/tasks/test_metaworld_tasks.py.

  * `reward_parity`: metaworld states (its scripted policy with noise, and random actions)
    loaded into the port: the 18 current observation values, the dense reward, success;
  * `drift`: one episode from metaworld's reset state, the same actions on both sides;
  * `scripted_success`: metaworld's scripted policy closed loop on both simulators' resets.
Imported only by tests and benchmarks (metaworld is not needed to run a port).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from tasks.base import TaskState
from tasks.metaworld.reference import explore_action, policy_env, scripted_policy
from tasks.physics import mjx


def port_eval_fn(task):
    """jit(vmap) of: (data, prev obs, action, info) -> (current obs 18, reward, success)."""

    def one(data, prev, action, info):
        data = task.kinematics(data, info)
        curr = task.current_obs(data)
        obs = task.observe(curr, prev, info["target_pos"])
        reward, success = task._reward(obs, action, data, info)
        return curr, reward, success

    return jax.jit(jax.vmap(one))


def reward_parity(task, name: str, n_episodes: int = 6, steps: int = 150, seed: int = 0,
                  noise: float = 0.3):
    """Max |difference| of obs[:18] and reward, and success agreement, on metaworld states."""
    env = policy_env(name, seed)
    policy = scripted_policy(name)
    rng = np.random.default_rng(seed)
    datas, prevs, actions, infos, mw = [], [], [], [], []
    for ep in range(n_episodes):
        obs, _ = env.reset()
        info = {k: jnp.asarray(v, jnp.float32) for k, v in task.info_from_metaworld(env).items()}
        random_ep = ep % 3 == 2
        for _ in range(steps):
            action = explore_action(policy, obs, rng, noise, random_ep)
            prev = obs[:18].copy()
            obs, reward, _, _, minfo = env.step(action)
            datas.append(task.data_from_metaworld(env))
            prevs.append(jnp.asarray(prev, jnp.float32))
            actions.append(jnp.asarray(action, jnp.float32))
            infos.append(info)
            mw.append((obs.copy(), float(reward), float(minfo["success"])))
    stack = lambda xs: jax.tree.map(lambda *a: jnp.stack(a), *xs)  # noqa: E731
    curr, reward, success = port_eval_fn(task)(stack(datas), stack(prevs), stack(actions),
                                               stack(infos))
    mw_obs = np.stack([m[0][:18] for m in mw])
    mw_r = np.array([m[1] for m in mw])
    mw_s = np.array([m[2] for m in mw])
    return dict(
        n_states=len(mw), n_success_states=int(mw_s.sum()),
        max_obs_err=float(np.abs(np.asarray(curr) - mw_obs).max()),
        max_reward_err=float(np.abs(np.asarray(reward) - mw_r).max()),
        success_mismatches=int((np.asarray(success) != mw_s).sum()),
    )


def state_from_metaworld(task, env, obs):
    """A port TaskState at exactly a (just reset) metaworld env's state."""
    info = {k: jnp.asarray(v, jnp.float32) for k, v in task.info_from_metaworld(env).items()}
    data = mjx.forward(task.model_for(info), task.data_from_metaworld(env))
    info["prev_obs"] = task.current_obs(data)
    zero = jnp.zeros((), jnp.float32)
    return TaskState(data=data, obs=jnp.asarray(obs, jnp.float32), true_reward=zero,
                     success=zero, terminated=jnp.zeros((), bool), info=info)


def drift(task, name: str, mode: str, seed: int = 0, steps: int = 500):
    """Same start, same actions: metaworld C vs port. `scripted` actions are computed from
    metaworld's observations and replayed on the port (open loop)."""
    env = policy_env(name, seed)
    obs, _ = env.reset()
    state = state_from_metaworld(task, env, obs)
    rng = np.random.default_rng(seed)
    policy = scripted_policy(name)
    actions, mw_hand, mw_obj, mw_r, mw_succ = [], [], [], 0.0, 0.0
    for _ in range(steps):
        a = (policy.get_action(obs) if mode == "scripted" else rng.uniform(-1, 1, 4))
        a = np.clip(a, -1, 1).astype(np.float32)
        obs, r, _, _, info = env.step(a)
        actions.append(a)
        mw_hand.append(obs[:3].copy())
        mw_obj.append(obs[4:7].copy())
        mw_r += float(r)
        mw_succ = max(mw_succ, float(info["success"]))

    def body(s, a):
        s = task.step(s, a)
        return s, (s.obs[:3], s.obs[4:7], s.true_reward, s.success)

    _, (hand, obj, r, succ) = jax.jit(lambda s, a: jax.lax.scan(body, s, a))(
        state, jnp.asarray(np.stack(actions)))
    hand_err = np.abs(np.asarray(hand) - np.stack(mw_hand)).max(axis=1)
    obj_err = np.abs(np.asarray(obj) - np.stack(mw_obj)).max(axis=1)
    return dict(
        hand_err_t50=float(hand_err[:50].max()), hand_err_max=float(hand_err.max()),
        obj_err_t50=float(obj_err[:50].max()), obj_err_max=float(obj_err.max()),
        mw_return=mw_r, port_return=float(np.asarray(r).sum()),
        mw_success=mw_succ, port_success=float(np.asarray(succ).max()),
    )


def scripted_success(task, name: str, episodes: int, seed: int = 0, batch: int = 25):
    """Any-step success rate of metaworld's scripted policy, closed loop, on `episodes`
    random resets of metaworld (C) and of the port (its own reset distribution)."""
    env = policy_env(name, seed)
    policy = scripted_policy(name)
    mw = []
    for _ in range(episodes):
        obs, _ = env.reset()
        s = 0.0
        for _ in range(task.episode_length):
            obs, _, _, _, info = env.step(np.clip(policy.get_action(obs), -1, 1))
            s = max(s, float(info["success"]))
        mw.append(s)
    batch = min(batch, episodes)
    reset = jax.jit(jax.vmap(task.reset))
    step = jax.jit(jax.vmap(task.step))
    port = []
    key = jax.random.key(seed)
    for start in range(0, episodes, batch):
        n = min(batch, episodes - start)
        key, sub = jax.random.split(key)
        st = reset(jax.random.split(sub, batch))
        succ = np.zeros(batch)
        for _ in range(task.episode_length):
            obs = np.asarray(st.obs, np.float64)
            if task.policy_reads_goal:
                obs[:, 36:39] = np.asarray(st.info["target_pos"])
            act = np.stack([np.clip(policy.get_action(o), -1, 1) for o in obs]).astype(np.float32)
            st = step(st, jnp.asarray(act))
            succ = np.maximum(succ, np.asarray(st.success))
        port.extend(succ[:n].tolist())
    return dict(episodes=episodes, mw_success_rate=float(np.mean(mw)),
                port_success_rate=float(np.mean(port)))
