"""Throughput of the MJX MetaWorld ports next to metaworld's own C environment.

    python -m benchmarks.ports.metaworld_throughput [--tasks drawer_open ...] [--batch 64]
                                                    [--steps 20]

MJX: env steps/s (one env step = 5 physics substeps) of `jit(lax.scan(vmap(step)))` at the
given batch, random actions, best of `--repeats` timed runs after compile; compile time is
reported apart. C: metaworld's `env.step` (gymnasium, 5 x mj_step + obs + reward) on one
core, random actions. Writes benchmarks/results/ports/metaworld_throughput.csv.

`--variant arm|free` builds the port with that scene (tasks/metaworld/sawyer.py) instead of
the registered one and labels the rows with it (column `scene`). `--linesearch scan` traces
MJX's own line-search loop instead of the ports' while loop (tasks/physics.py; column
`linesearch`), the reference for that change. `--max-contacts K` builds the port with MJX's
contact cap (K slots per condim group, `tasks.physics.with_max_contacts`; label `capK`),
`--max-contacts none` without one (label `uncapped`). `--group G|none|auto` steps the batch as
vmapped groups of G in turn (`tasks.batching`; none: one vmap; auto, the default: what
`hprior_jax.envs.VecEnv` does on this backend; column `group`).
"""
from __future__ import annotations

import tasks  # noqa: F401  (sets XLA_FLAGS before jax)

import argparse
import os
import time
from pathlib import Path

import jax
import numpy as np

from benchmarks._timing import read_rows, write_rows
from tasks import batching, physics
from tasks.metaworld.reference import make_env, metaworld_version, ports

RESULTS = os.path.join(os.path.dirname(os.path.dirname(__file__)), "results", "ports",
                       "metaworld_throughput.csv")


def mjx_rate(task, batch: int, steps: int, repeats: int, group: int | None = None):
    step = batching.vmap_in_groups(task.step, group)

    @jax.jit
    def rollout(state, key):
        actions = jax.random.uniform(key, (steps, batch, task.action_size), minval=-1, maxval=1)
        state, rewards = jax.lax.scan(lambda s, a: (lambda n: (n, n.true_reward))(step(s, a)),
                                      state, actions)
        return state, rewards

    state = jax.jit(jax.vmap(task.reset))(jax.random.split(jax.random.key(0), batch))
    t0 = time.perf_counter()
    state, r = rollout(state, jax.random.key(1))
    jax.block_until_ready(r)
    compile_s = time.perf_counter() - t0
    best = float("inf")
    for i in range(repeats):
        t0 = time.perf_counter()
        state, r = rollout(state, jax.random.key(2 + i))
        jax.block_until_ready(r)
        best = min(best, time.perf_counter() - t0)
    assert np.isfinite(np.asarray(r)).all()
    return batch * steps / best, compile_s


def c_rate(name: str, steps: int = 500):
    env = make_env(name, seed=0)
    env.reset()
    rng = np.random.default_rng(0)
    acts = rng.uniform(-1, 1, (steps, 4))
    t0 = time.perf_counter()
    for a in acts:
        env.step(a)
    return steps / (time.perf_counter() - t0)


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--tasks", nargs="*", default=None)
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--out", default=RESULTS)
    p.add_argument("--variant", default=None, choices=["arm", "free"])
    p.add_argument("--wrist", default=None, help="box, a number of hull points or coacd:... (see metaworld_dynamics)")
    p.add_argument("--label", default=None, help="scene label (default: variant/registered)")
    p.add_argument("--no-c", action="store_true", help="skip metaworld's C env timing")
    p.add_argument("--linesearch", default="while", choices=["while", "scan"])
    p.add_argument("--max-contacts", default=None,
                   help="MJX contact cap per condim group (tasks.physics.with_max_contacts), "
                        "or none: every slot (label `uncapped`)")
    p.add_argument("--group", default="auto",
                   help="batching: a group size, none (one vmap) or auto (VecEnv's layout)")
    args = p.parse_args()
    from benchmarks.ports.metaworld_dynamics import contact_cap_option, make_task

    options, cap = contact_cap_option(args.max_contacts)
    label = (args.label or "-".join(x for x in (args.variant, args.wrist, cap) if x)
             or "registered")
    names = args.tasks or ports()
    rows = []
    for name in names:
        task = make_task(name, args.variant, args.wrist, **options)
        group = batching.group_from_option(args.group, task)
        m = task.mj_model
        with physics.linesearch_loop(args.linesearch):
            rate, compile_s = mjx_rate(task, args.batch, args.steps, args.repeats, group)
        row = dict(task=name, scene=label, linesearch=args.linesearch, batch=args.batch,
                   group=batching.group_size(args.batch, group) or args.batch,
                   scan_steps=args.steps,
                   mjx_env_steps_per_s=round(rate, 1), mjx_substeps_per_s=round(5 * rate, 1),
                   compile_s=round(compile_s, 1),
                   c_env_steps_per_s=None if args.no_c else round(c_rate(name), 1),
                   nq=m.nq, nv=m.nv, npair=m.npair, devices=str(jax.devices()[0]),
                   cpu_count=os.cpu_count(), metaworld=metaworld_version(),
                   jax=jax.__version__, mujoco=__import__("mujoco").__version__)
        print(row, flush=True)
        rows.append(row)
    measured = {(row["task"], str(row["group"])) for row in rows}
    rerun = lambda r: ((r["task"], r.get("group") or r["batch"]) in measured
                       and r["batch"] == str(args.batch)
                       and r.get("scene", "registered") == label
                       and (r.get("linesearch") or "scan") == args.linesearch)
    write_rows(rows, Path(args.out), keep=[r for r in read_rows(Path(args.out)) if not rerun(r)])


if __name__ == "__main__":
    main()
