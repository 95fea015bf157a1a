"""Parity of the MJX MetaWorld ports against the installed metaworld package (C MuJoCo).

    python -m benchmarks.ports.metaworld_parity [--tasks drawer_open ...] [--episodes 50]

For each task, writes rows to benchmarks/results/ports/metaworld_parity.csv:
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

import numpy as np

from tasks.metaworld.parity import drift, reward_parity, scripted_success
from tasks.metaworld.reference import (explore_action, metaworld_version, policy_env, ports,
                                      scripted_policy)

RESULTS = os.path.join(os.path.dirname(os.path.dirname(__file__)), "results", "ports",
                       "metaworld_parity.csv")


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
            action = explore_action(policy, obs, rng, noise, random_ep)
            obs, reward, _, _, info = env.step(action)
            rows.append(dict(state=snapshot(env), obs=obs.copy(), action=action.astype(np.float32),
                             reward=float(reward), success=float(info["success"])))
    return env, rows


def snapshot(env):
    return dict(qpos=env.data.qpos.copy(), qvel=env.data.qvel.copy(),
                mocap_pos=env.data.mocap_pos.copy(), mocap_quat=env.data.mocap_quat.copy(),
                hand_pos=env.data.body("hand").xpos.copy(), hand_quat=env.data.body("hand").xquat.copy(),
                ctrl=env.data.ctrl.copy(), info=None)


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--tasks", nargs="*", default=None)
    p.add_argument("--episodes", type=int, default=50)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default=RESULTS)
    args = p.parse_args()
    names = args.tasks or ports()
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
