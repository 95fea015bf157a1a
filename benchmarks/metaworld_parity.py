"""Parity of the MJX MetaWorld ports against the installed metaworld package (C MuJoCo).

    python -m benchmarks.metaworld_parity [--tasks drawer_open ...] [--episodes 50]

For each task, writes rows to benchmarks/results/metaworld_parity.csv:
  * reward/success/obs on identical states: metaworld states visited by its scripted policy
    (with exploration noise, so successful and unsuccessful states both occur) and by random
    actions are loaded into the port (hand pose, fingers, object joints, mocap, placement);
    we compare the 18 current observation values, the dense reward and the success flag;
  * drift over one 500-step episode from the same start (the port starts from metaworld's
    reset state), for the scripted policy and for uniform random actions: max |hand pos|
    and |object pos| difference, and summed reward of both;
  * metaworld's scripted policy run on `--episodes` random resets of both simulators:
    any-step success rate of each (the BPref metric).
"""
from __future__ import annotations

import tasks  # noqa: F401  (sets XLA_FLAGS before jax)

import argparse
import csv
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

from tasks.metaworld.reference import make_env, metaworld_version, scripted_policy

TASKS = ("drawer_open", "button_press", "door_open", "window_open", "door_unlock", "sweep_into")
RESULTS = os.path.join(os.path.dirname(__file__), "results", "metaworld_parity.csv")
# scripted policies that steer by the goal slots obs[36:39] (metaworld runs its policies on
# goal-observable envs); with the default hidden goal they head for (0, 0, 0). For these the
# policy is given the goal: metaworld env built goal-observable, port obs filled from info.
POLICY_READS_GOAL = ("sweep_into",)


def policy_env(name: str, seed: int):
    """The metaworld env whose observations the scripted policy is run on."""
    return make_env(name, seed=seed, partially_observable=name not in POLICY_READS_GOAL)


def collect_metaworld_states(name: str, n_episodes: int, steps: int, seed: int, noise: float):
    """Runs metaworld (scripted policy + Gaussian noise, and pure random episodes) and
    records everything needed to rebuild each visited state in the port."""
    env = policy_env(name, seed)
    policy = scripted_policy(name)
    rng = np.random.default_rng(seed)
    rows = []
    for ep in range(n_episodes):
        obs, _ = env.reset()
        random_ep = ep % 2 == 1
        for t in range(steps):
            if random_ep:
                action = rng.uniform(-1, 1, 4)
            else:
                action = np.clip(policy.get_action(obs) + noise * rng.standard_normal(4), -1, 1)
            obs, reward, _, _, info = env.step(action)
            rows.append(dict(state=snapshot(env), obs=obs.copy(), action=action.astype(np.float32),
                             reward=float(reward), success=float(info["success"])))
    return env, rows


def snapshot(env):
    return dict(qpos=env.data.qpos.copy(), qvel=env.data.qvel.copy(),
                mocap_pos=env.data.mocap_pos.copy(), mocap_quat=env.data.mocap_quat.copy(),
                hand_pos=env.data.body("hand").xpos.copy(), hand_quat=env.data.body("hand").xquat.copy(),
                ctrl=env.data.ctrl.copy(), info=None)


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
            if random_ep:
                action = rng.uniform(-1, 1, 4)
            else:
                action = np.clip(policy.get_action(obs) + noise * rng.standard_normal(4), -1, 1)
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
    from tasks.base import TaskState
    from tasks.physics import mjx

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
            if name in POLICY_READS_GOAL:
                obs[:, 36:39] = np.asarray(st.info["target_pos"])
            act = np.stack([np.clip(policy.get_action(o), -1, 1) for o in obs]).astype(np.float32)
            st = step(st, jnp.asarray(act))
            succ = np.maximum(succ, np.asarray(st.success))
        port.extend(succ[:n].tolist())
    return dict(episodes=episodes, mw_success_rate=float(np.mean(mw)),
                port_success_rate=float(np.mean(port)))


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--tasks", nargs="*", default=None)
    p.add_argument("--episodes", type=int, default=50)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=RESULTS)
    args = p.parse_args()
    names = args.tasks or [n for n in TASKS if n in tasks.names()]
    rows = []
    for name in names:
        task = tasks.make(name)
        t0 = time.time()
        row = dict(task=name, metaworld=metaworld_version(), mujoco=__import__("mujoco").__version__)
        row.update(reward_parity(task, name, seed=args.seed))
        for mode in ("scripted", "random"):
            row.update({f"{mode}_{k}": v for k, v in drift(task, name, mode, seed=args.seed).items()})
        row.update(scripted_success(task, name, args.episodes, seed=args.seed))
        row["wall_s"] = round(time.time() - t0, 1)
        print(row, flush=True)
        rows.append(row)
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    existing = []
    if os.path.exists(args.out):  # keep rows of tasks not rerun this time
        with open(args.out) as f:
            existing = [r for r in csv.DictReader(f) if r["task"] not in names]
    keys = list(rows[0].keys())
    with open(args.out, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys, extrasaction="ignore")
        w.writeheader()
        for r in existing + rows:
            w.writerow(r)
    print("wrote", args.out)


if __name__ == "__main__":
    main()
