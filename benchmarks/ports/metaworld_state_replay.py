"""One step of metaworld from the port's own states: is a SAC run's odd step the port's doing?

    python -m benchmarks.ports.metaworld_state_replay [--task sweep_into] [--jump 0.03]
        [--random-steps 200] [--dataset NPZ] [--out CSV]

Reads a reward-lab dataset built with the physics states of its training steps
(`hprior reward-lab --task T --dataset-only --physics`: a SAC run of the port, 50k steps).
For every step where the port's hand moved more than `--jump` metres, and for
`--random-steps` steps drawn at random as a baseline, metaworld's own env (C MuJoCo) is set to
the recorded state (qpos, qvel, mocap) and given the recorded action through its own `step`;
its next hand and object positions are compared with the port's recorded next observation.
If metaworld makes the same step, the step comes from the state and the action (the policy),
not from the port's scene. Also checked first: the recorded state, loaded into metaworld,
gives the recorded observation (hand and object), so states and observations line up.

Caveat: states are stored in float32 (MJX), and C MuJoCo integrates in float64, so even a
faithful port differs by rounding, which contacts can amplify within one step (5 substeps).
Rows go to `benchmarks/results/ports/metaworld_state_replay.csv`; a run replaces its task's rows.
"""
from __future__ import annotations

import tasks  # noqa: F401  (sets XLA_FLAGS before jax)

import argparse
import os
from pathlib import Path

import mujoco
import numpy as np

from benchmarks._timing import read_rows, write_rows
from benchmarks.ports.metaworld_parity import policy_env
from hprior_jax.lab.dataset import Dataset, dataset_path
from tasks.metaworld.reference import metaworld_version

RESULTS = os.path.join(os.path.dirname(os.path.dirname(__file__)), "results", "ports",
                       "metaworld_state_replay.csv")
HAND, OBJ = slice(0, 3), slice(4, 7)  # metaworld's observation: hand (tcp) and first object


def load_state(env, physics: dict, e: int, t: int) -> None:
    """metaworld's env set to the port's recorded state of episode e, step t."""
    d = env.data
    d.qpos[:] = physics["qpos"][e, t]
    d.qvel[:] = physics["qvel"][e, t]
    d.mocap_pos[:] = physics["mocap_pos"][e, t]
    d.mocap_quat[:] = physics["mocap_quat"][e, t]
    mujoco.mj_forward(env.model, d)


def replay(env, data: Dataset, e: int, t: int) -> dict:
    """metaworld from the port's state (e, t) with its action -> the comparison row."""
    env.reset()
    load_state(env, data.train_physics, e, t)
    obs_now = env._get_obs()
    mocap_ahead = float(np.linalg.norm(env.data.mocap_pos[0] - obs_now[HAND]))
    env.curr_path_length = 0  # one step from here: metaworld's 500-step limit is not near
    obs_next, *_ = env.step(data.train_act[e, t].astype(np.float64))
    port_now, port_next = data.train_obs[e, t], data.train_obs[e, t + 1]
    dist = lambda a, b: float(np.linalg.norm(np.asarray(a) - np.asarray(b)))
    return dict(episode=e, t=t,
                state_hand_err=dist(obs_now[HAND], port_now[HAND]),
                state_obj_err=dist(obs_now[OBJ], port_now[OBJ]),
                mocap_ahead=mocap_ahead,
                port_hand_step=dist(port_next[HAND], port_now[HAND]),
                metaworld_hand_step=dist(obs_next[HAND], obs_now[HAND]),
                next_hand_diff=dist(obs_next[HAND], port_next[HAND]),
                next_obj_diff=dist(obs_next[OBJ], port_next[OBJ]))


def hand_steps(data: Dataset) -> np.ndarray:
    """[E, L-1] distance the port's hand moved in each step of the training episodes."""
    hand = data.train_obs[..., HAND]
    return np.linalg.norm(hand[:, 1:] - hand[:, :-1], axis=-1)


def main(argv=None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--task", default="sweep_into")
    parser.add_argument("--dataset", default=None,
                        help="default: the task's cached physics dataset (seed 0, 50k, reduced)")
    parser.add_argument("--jump", type=float, default=0.03, help="metres in one step")
    parser.add_argument("--random-steps", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=RESULTS)
    args = parser.parse_args(argv)
    path = args.dataset or dataset_path(args.task, 0, 50_000, "reduced", physics=True)
    data = Dataset.load(path)
    if data.train_physics is None:
        parser.error(f"{path} has no physics states: build it with --physics")
    steps = hand_steps(data)
    jumps = np.argwhere(steps > args.jump)
    rng = np.random.default_rng(args.seed)
    flat = rng.choice(steps.size, args.random_steps, replace=False)
    randoms = np.stack(np.unravel_index(flat, steps.shape), 1)
    print(f"{path}: {steps.shape[0]} episodes; hand step 99.9th percentile "
          f"{np.percentile(steps, 99.9):.4f} m, max {steps.max():.4f} m; "
          f"{len(jumps)} steps over {args.jump} m in {len(set(jumps[:, 0]))} episodes")
    env = policy_env(args.task, 0)
    rows = []
    for kind, picks in (("jump", jumps), ("random", randoms)):
        for e, t in picks:
            rows.append(dict(task=args.task, kind=kind, metaworld=metaworld_version(),
                             **replay(env, data, int(e), int(t))))
    for kind in ("jump", "random"):
        sel = [r for r in rows if r["kind"] == kind]
        if not sel:
            continue
        col = lambda k: np.asarray([r[k] for r in sel])
        print(f"{kind} ({len(sel)} steps): state error hand max {col('state_hand_err').max():.2e} m; "
              f"next hand port vs metaworld median {np.median(col('next_hand_diff')):.2e}, "
              f"max {col('next_hand_diff').max():.2e} m; next object max "
              f"{col('next_obj_diff').max():.2e} m; hand step port/metaworld median "
              f"{np.median(col('port_hand_step') / np.maximum(col('metaworld_hand_step'), 1e-9)):.3f}")
    for r in rows:
        if r["kind"] == "jump":
            print(f"  episode {r['episode']} step {r['t']}: port {r['port_hand_step']:.4f} m, "
                  f"metaworld {r['metaworld_hand_step']:.4f} m, mocap {r['mocap_ahead']:.3f} m "
                  f"ahead, next hand differs by {r['next_hand_diff']:.2e} m")
    out = Path(args.out)
    write_rows(rows, out, keep=[r for r in read_rows(out) if r["task"] != args.task])
    return rows


if __name__ == "__main__":
    main()
