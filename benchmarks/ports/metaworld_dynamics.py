"""Closed-loop dynamics parity of the MJX MetaWorld ports against metaworld 3.0.0.

    python -m benchmarks.ports.metaworld_dynamics [--tasks button_press ...] [--episodes 20]
        [--sides metaworld port_c port] [--variant arm|free] [--out CSV]

metaworld's own scripted policy (metaworld.policies) drives, closed loop, for 500 steps:
  * `metaworld`: metaworld's env (C MuJoCo, its full scene);
  * `port`: our MJX port (`jit(vmap(step))`, all episodes in one batch; the same policy code
    is fed the port's observations);
  * `port_c`: the port's simplified scene stepped by C MuJoCo (same mocap/ctrl/frame-skip
    logic, observation and reward from the port's JAX functions): separates what the scene
    changes from what MJX changes.
Each side draws its own resets (`--episodes` of them). Per task and side we report the mean
return, success at the last step, the first step with success (mean over episodes that
succeed), the object joint's lowest/highest value against its range (metaworld's joints are
soft: its own scripted episodes leave the range too) and the share of episodes that pass it
by more than the tolerance below, and the mean distance between the hand body and the mocap
target. `--variant` picks the port's scene (see tasks/metaworld/sawyer.py): `arm` keeps
metaworld's arm (the registered scene), `free` is the arm-less free hand of the first ports
(with the wrist box on every task, as they had it). `--max-contacts K` builds the port with
MJX's contact cap (K slots per condim group, `tasks.physics.with_max_contacts`; label
`capK`; `--max-contacts none`: uncapped, label `uncapped`); the port side also reports `contacts_active_max`, the most contacts of one condim
group active after any step, against `contact_slots`, and per group `contacts_by_condim`
("condim:most active/slots").

Targets, port vs metaworld: return ratio in [0.9, 1.1]; last-step success within
15 points; excursion beyond the range at most metaworld's + 1 cm (0.05 rad for hinges);
hand-mocap distance ratio in [0.7, 1.3]. `targets_met` lists which hold.
"""
from __future__ import annotations

import tasks  # noqa: F401  (sets XLA_FLAGS before jax)

import argparse
import os
import time
import warnings
from pathlib import Path

import mujoco

from benchmarks._timing import read_rows, write_rows
from tasks.metaworld.closed_loop import (make_task, object_joint,  # noqa: F401
                                         run_metaworld, run_port, run_port_c, targets)
from tasks.metaworld.reference import metaworld_version, ports

RESULTS = os.path.join(os.path.dirname(os.path.dirname(__file__)), "results", "ports",
                       "metaworld_dynamics.csv")


def contact_cap_option(value: str | None) -> tuple[dict, str | None]:
    """`--max-contacts` (K, "none" or unset) as the port's constructor options and a label
    part: `capK`, `uncapped` (MJX gives every candidate contact a slot) or None."""
    if value is None:
        return {}, None
    if value == "none":
        return {"max_contacts": None}, "uncapped"
    return {"max_contacts": int(value)}, f"cap{int(value)}"


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--tasks", nargs="*", default=ports())
    p.add_argument("--episodes", type=int, default=20)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--sides", nargs="*", default=["metaworld", "port"],
                   choices=["metaworld", "port_c", "port"])
    p.add_argument("--variant", default=None, choices=["arm", "free"],
                   help="scene of the port (default: the registered port)")
    p.add_argument("--wrist", default=None,
                   help="wrist collider: box, mesh (C only: port_c), a number of hull points, or "
                        "coacd:THRESHOLD:MAX_HULLS:POINTS[:KEPT] (convex pieces of the mesh)")
    p.add_argument("--keep-cylinders", action="store_true",
                   help="paired cylinders stay cylinders (C only: port_c)")
    p.add_argument("--max-contacts", default=None,
                   help="MJX contact cap per condim group (tasks.physics.with_max_contacts), "
                        "or none: every slot (label `uncapped`)")
    p.add_argument("--label", default=None, help="label of the port rows (default: variant)")
    p.add_argument("--out", default=RESULTS)
    args = p.parse_args()
    warnings.filterwarnings("ignore", message="Constant")  # metaworld policies' p warnings
    cap_options, cap = contact_cap_option(args.max_contacts)
    label = args.label or "-".join(x for x in (args.variant, args.wrist, args.keep_cylinders
                                                and "cylinders", cap) if x) or "registered"
    options = ({"keep_cylinders": True} if args.keep_cylinders else {}) | cap_options
    rows = []
    for name in args.tasks:
        task = (make_task(name, args.variant, args.wrist, **options)
                if set(args.sides) - {"metaworld"}
                else None)
        results = {}
        for side in args.sides:
            t0 = time.time()
            if side == "metaworld":
                res = run_metaworld(name, args.episodes, args.seed)
            elif side == "port_c":
                res = run_port_c(task, name, args.episodes, args.seed)
            else:
                res = run_port(task, name, args.episodes, args.seed)
            res.update(task=name, side=side, scene="metaworld" if side == "metaworld" else label,
                       wall_s=round(time.time() - t0, 1), metaworld=metaworld_version(),
                       mujoco=mujoco.__version__, seed=args.seed)
            if side != "metaworld" and task is not None:
                res["npair"] = task.mj_model.npair
                res["nv"] = task.mj_model.nv
            results[side] = res
        mw = results.get("metaworld")
        for side, res in results.items():
            if mw is not None and side != "metaworld":
                res.update(targets(res, mw))
            print({k: (round(v, 4) if isinstance(v, float) else v) for k, v in res.items()},
                  flush=True)
            rows.append(res)
    rerun = {(r["task"], r["side"], r["scene"]) for r in rows}
    keep = [r for r in read_rows(Path(args.out)) if (r["task"], r["side"], r["scene"]) not in rerun]
    write_rows(rows, Path(args.out), keep=keep)  # rows not rerun this time stay


if __name__ == "__main__":
    main()
