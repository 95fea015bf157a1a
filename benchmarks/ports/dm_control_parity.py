"""Parity of the MJX DM Control ports against dm_control itself.

    python -m benchmarks.ports.dm_control_parity [--tasks ...] [--episodes 10] [--x64]

Three checks per task, written to benchmarks/results/ports/dm_control_parity.csv:
  same_state  C `mj_forward` and `mjx.forward` on the same (qpos, qvel, act, ctrl), taken
              along a random-action dm_control trajectory -> max |obs diff|, max |reward diff|;
              plus the reset observation (dm_control's reset state, actuation-free forward)
              and, for quadruped, the closed-form reset height vs dm_control's search;
  trajectory  from dm_control's reset state (copied with `mjx.put_data`), the same uniform
              random actions on both sides -> max |obs|, |qpos| and |reward| differences and
              the difference of summed reward over the first 20/100/1000 steps (per episode,
              then max and mean over episodes);
  policy      whole-episode returns of the random (uniform in [-1, 1]) and zero-action
              policies from each side's own resets: mean, std, min, max over `--episodes`.
`--x64` runs the trajectory check with jax_enable_x64 (float64 MJX) instead of float32, to
separate precision from modelling differences; its rows are tagged dtype=float64 and kept
in the CSV next to the float32 rows.
The helpers are tasks/dm_control/reference.py's (tests/tasks/test_dm_control_tasks.py uses them).
"""
from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import tasks  # noqa: F401  (sets XLA_FLAGS before jax is imported)

import jax
import numpy as np

from tasks.dm_control.reference import (  # noqa: F401  (flatten_obs, reference_env: env_profile)
    flatten_obs, make_rollout, obs_reward_check, policy_returns, ports,
    quadruped_height_check, reference_env, reset_check, same_state_check, trajectory_check)

RESULTS = Path(__file__).resolve().parents[1] / "results" / "ports" / "dm_control_parity.csv"


def _fmt(x):
    return float(f"{float(x):.6g}")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--tasks", nargs="+", default=ports())
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--x64", action="store_true", help="float64 MJX trajectory check only")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    if args.x64:
        jax.config.update("jax_enable_x64", True)
    dtype = "float64" if args.x64 else "float32"

    rows = []

    def add(task, check, metric, mjx_value, ref_value="", note=""):
        rows.append(dict(task=task, dtype=dtype, check=check, metric=metric,
                         mjx=_fmt(mjx_value), dm_control=ref_value if ref_value == "" else _fmt(ref_value),
                         note=note))
        print(rows[-1], flush=True)

    for name in args.tasks:
        task = tasks.make(name)
        rollout = make_rollout(task)
        if not args.x64:
            obs_err, rew_err = obs_reward_check(task, name)
            add(name, "same_data", "obs_max_abs", obs_err,
                note="20 states: our obs on dm_control's MjData vs its observation")
            add(name, "same_data", "reward_max_abs", rew_err,
                note="20 states: our reward on dm_control's MjData vs its reward")
            obs_err, rew_err, _ = same_state_check(task, name)
            add(name, "same_state", "obs_max_abs", obs_err, note="20 states, C vs MJX forward")
            add(name, "same_state", "reward_max_abs", rew_err, note="20 states, C vs MJX forward")
            add(name, "reset", "obs_max_abs", reset_check(task, name),
                note="dm_control reset qpos/qvel/act, actuation-free forward, 5 seeds")
            if name == "quadruped_walk":
                n_off, err = quadruped_height_check(task)
                add(name, "reset", "height_mismatch_count", n_off, note="of 200 orientations")
                add(name, "reset", "height_max_abs", err, note="of 200 orientations")
        traj, mjx_s = trajectory_check(task, name, args.episodes, task.episode_length,
                                       rollout=rollout)
        for h, metrics in traj.items():
            for k, v in metrics.items():
                if k == "return_ref_mean":
                    continue
                add(name, f"trajectory_{h}", k, v,
                    metrics["return_ref_mean"] if k.startswith("return") else "",
                    note=f"{args.episodes} episodes, random actions from dm_control's reset state"
                    + ("; dm_control column: its mean return" if k.startswith("return") else ""))
        print(f"{name}: {args.episodes}x{task.episode_length} MJX rollout incl. compile {mjx_s:.1f}s")
        if args.x64:
            continue
        for policy in ("random", "zero"):
            ours, theirs = policy_returns(task, name, args.episodes, policy, rollout=rollout)
            for stat in ("mean", "std", "min", "max"):
                f = getattr(np, stat)
                add(name, f"{policy}_policy_return", stat, f(ours), f(theirs),
                    note=f"{args.episodes} episodes x {task.episode_length} steps, own resets")

    # keep rows of the other dtype/tasks from earlier runs
    keep = []
    if args.out.exists():
        with open(args.out) as fh:
            keep = [r for r in csv.DictReader(fh)
                    if not (r["dtype"] == dtype and r["task"] in args.tasks)]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with open(args.out, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(keep + rows)
    print(f"wrote {args.out} ({' '.join(sys.argv[1:])})")


if __name__ == "__main__":
    main()
