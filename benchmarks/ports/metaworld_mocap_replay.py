"""Open-loop replay of metaworld's own mocap path on the port's scene (C MuJoCo).

    python -m benchmarks.ports.metaworld_mocap_replay [--tasks drawer_open ...] [--episodes 4]
        [--steps 500] [--variant arm|free] [--out CSV]

metaworld's scripted policy drives metaworld's env closed loop; every step we record the
mocap target, the gripper control, the hand's position and the object joint. The port's
scene (tasks/metaworld/sawyer.py) then starts from metaworld's state after reset (copied
with `data_from_metaworld`) and is driven by exactly that mocap path and control, in C
MuJoCo (no MJX: this isolates the scene). With the same inputs, any gap is the scene's:
how far the port's hand is from metaworld's, how far its object joint is from metaworld's,
and the hand-mocap lag on both sides, in the first 60 steps (reaching, no contact) and
over the episode. Each task runs twice: with metaworld's compiled constraint weights (the
registered scene) and with the simplified scene's own (`metaworld_invweights=False`).
`--variant` picks the scene as in benchmarks/ports/metaworld_dynamics.py (`arm`, the registered
one, or `free`, the first ports' free hand); rows are keyed by (task, scene, invweights).
"""
from __future__ import annotations

import tasks  # noqa: F401  (sets XLA_FLAGS before jax)

import argparse
import copy
import os
import warnings
from pathlib import Path

import mujoco
import numpy as np

from benchmarks._timing import read_rows, write_rows
from benchmarks.ports.metaworld_dynamics import make_task, object_joint
from benchmarks.ports.metaworld_parity import policy_env
from tasks.metaworld.reference import metaworld_version, ports, scripted_policy

RESULTS = os.path.join(os.path.dirname(os.path.dirname(__file__)), "results", "ports",
                       "metaworld_mocap_replay.csv")
REACH_STEPS = 60  # the scripted policies reach for the object first: no contact before this


def record_metaworld(name: str, episodes: int, seed: int, steps: int, task) -> list[dict]:
    """metaworld's scripted episodes: the port's initial state and the per-step path."""
    env = policy_env(name, seed)
    policy = scripted_policy(name)
    m, d = env.model, env.data
    jid = object_joint(m, name)
    qadr = int(m.jnt_qposadr[jid]) if jid is not None else None
    out = []
    for _ in range(episodes):
        obs, _ = env.reset()
        start = task.data_from_metaworld(env)
        ep = dict(qpos=np.asarray(start.qpos, np.float64), qvel=np.asarray(start.qvel, np.float64),
                  mocap_quat=d.mocap_quat[0].copy(), ctrl0=d.ctrl.copy(),
                  placement=task.info_from_metaworld(env).get("placement"),
                  mocap=[], ctrl=[], hand=[], obj=[])
        for _ in range(steps):
            obs, *_ = env.step(np.clip(policy.get_action(obs), -1, 1))
            ep["mocap"].append(d.mocap_pos[0].copy())
            ep["ctrl"].append(d.ctrl.copy())
            ep["hand"].append(d.body("hand").xpos.copy())
            ep["obj"].append(d.qpos[qadr] if qadr is not None else np.nan)
        out.append({k: np.asarray(v) if isinstance(v, list) else v for k, v in ep.items()})
    return out


def replay(task, name: str, episodes: list[dict]) -> list[dict]:
    """The recorded mocap paths on the port's scene: its hand and object joint per step."""
    m = copy.copy(task.mj_model)
    d = mujoco.MjData(m)
    jid = object_joint(m, name)
    qadr = int(m.jnt_qposadr[jid]) if jid is not None else None
    hand, mocap = m.body("hand").id, task._hand_mocap
    out = []
    for ep in episodes:
        mujoco.mj_resetData(m, d)
        if task._placed_body is not None:
            m.body_pos[task._placed_body] = ep["placement"]
        d.qpos[:], d.qvel[:] = ep["qpos"], ep["qvel"]
        d.mocap_quat[mocap], d.ctrl[:] = ep["mocap_quat"], ep["ctrl0"]
        hands, objs = [], []
        for target, ctrl in zip(ep["mocap"], ep["ctrl"]):
            d.mocap_pos[mocap], d.ctrl[:] = target, ctrl
            for _ in range(5):  # FRAME_SKIP
                mujoco.mj_step(m, d)
            mujoco.mj_kinematics(m, d)
            hands.append(d.xpos[hand].copy())
            objs.append(d.qpos[qadr] if qadr is not None else np.nan)
        out.append(dict(hand=np.asarray(hands), obj=np.asarray(objs)))
    return out


def compare(episodes: list[dict], replays: list[dict]) -> dict:
    mean = lambda f: float(np.mean([f(e, r) for e, r in zip(episodes, replays)]))
    dist = lambda a, b, sl=slice(None): np.linalg.norm(a[sl] - b[sl], axis=1).mean()
    reach = slice(0, REACH_STEPS)
    return dict(
        hand_error=mean(lambda e, r: dist(r["hand"], e["hand"])),
        lag_metaworld=mean(lambda e, r: dist(e["hand"], e["mocap"])),
        lag_port=mean(lambda e, r: dist(r["hand"], e["mocap"])),
        reach_lag_metaworld=mean(lambda e, r: dist(e["hand"], e["mocap"], reach)),
        reach_lag_port=mean(lambda e, r: dist(r["hand"], e["mocap"], reach)),
        object_error=mean(lambda e, r: np.abs(r["obj"] - e["obj"]).mean()),
        object_min_metaworld=float(min(e["obj"].min() for e in episodes)),
        object_min_port=float(min(r["obj"].min() for r in replays)),
        object_max_metaworld=float(max(e["obj"].max() for e in episodes)),
        object_max_port=float(max(r["obj"].max() for r in replays)),
    )


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--tasks", nargs="*", default=ports())
    p.add_argument("--episodes", type=int, default=4)
    p.add_argument("--steps", type=int, default=500)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--variant", default="arm", choices=["arm", "free"])
    p.add_argument("--out", default=RESULTS)
    args = p.parse_args()
    warnings.filterwarnings("ignore", message="Constant")  # metaworld policies' p warnings
    rows = []
    for name in args.tasks:
        scene = make_task(name, args.variant)
        episodes = record_metaworld(name, args.episodes, args.seed, args.steps, scene)
        for weights, task in (("metaworld", scene),
                              ("own", make_task(name, args.variant, metaworld_invweights=False))):
            row = dict(task=name, scene=args.variant, invweights=weights,
                       episodes=args.episodes, steps=args.steps,
                       **compare(episodes, replay(task, name, episodes)),
                       metaworld=metaworld_version(), mujoco=mujoco.__version__, seed=args.seed)
            print({k: round(v, 4) if isinstance(v, float) else v for k, v in row.items()},
                  flush=True)
            rows.append(row)
    key = lambda r: (r["task"], r.get("scene"), r["invweights"])
    rerun = {key(r) for r in rows}
    keep = [r for r in read_rows(Path(args.out)) if key(r) not in rerun]
    write_rows(rows, Path(args.out), keep=keep)


if __name__ == "__main__":
    main()
