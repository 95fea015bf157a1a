"""Env steps/s of the MJX task ports next to the reference simulator on C MuJoCo.

    python -m benchmarks.ports.env_throughput [--tasks walker_walk ...] [--batch 1 16 128]
                                              [--steps 50]

MJX: `jit(lax.scan(vmap(step)))` over `--steps` control steps with uniform random actions
drawn inside the scan, after a vmapped reset; the first call (compile) is timed apart and the
best of `--repeats` runs is reported. Reference: the same task in its own package (dm_control
`env.step` with random actions, one Python env on one core), via a per-domain function in
REFERENCES so other domains (MetaWorld) can add theirs. `c_over_mjx` = reference env-steps/s
divided by MJX env-steps/s summed over the batch (>1: MJX slower). `--variants
LOOP:CONTACTS[:CAP] ...` times each batch once per combination, in the same run: LOOP `while`
(the ports' line search, tasks/physics.py) or `scan` (MJX's own, the reference), CONTACTS
`floor` (the ports' default) or `all` (dm_control's self-collision pairs kept; DM Control
only), CAP `task` (the port's MJX contact cap, the default) or `none` (a slot for every
candidate contact; DM Control only). Default: the ports' defaults, `while:floor:task`.
`--groups none 16 ...` times each combination once per batching layout: `none` one vmap of the
whole batch, G the batch stepped as vmapped groups of G in turn (`tasks.batching`; `auto`:
the layout `hprior_jax.envs.VecEnv` picks on this backend, the default).
Writes benchmarks/results/ports/env_throughput.csv and prints a table.
"""
from __future__ import annotations

import argparse
import csv
import os
import platform
import time
from pathlib import Path
from typing import Callable

import tasks  # noqa: F401  (sets XLA_FLAGS before jax is imported)
from tasks import batching, physics
from tasks.dm_control.reference import ports, reference_env

import jax
import numpy as np

RESULTS = Path(__file__).resolve().parents[1] / "results" / "ports" / "env_throughput.csv"


# -- reference simulators, one function per domain ---------------------------------------
def dm_control_reference(task_name: str, n_steps: int, seed: int = 0) -> float:
    """Control steps/s of dm_control's own env (`env.step`, random actions, resets excluded)."""
    env = reference_env(task_name, seed)
    spec = env.action_spec()
    rng = np.random.RandomState(seed)
    actions = rng.uniform(spec.minimum, spec.maximum, (n_steps, spec.shape[0]))
    env.reset()
    elapsed, done = 0.0, 0
    while done < n_steps:
        t0 = time.perf_counter()
        ts = env.step(actions[done])
        elapsed += time.perf_counter() - t0
        done += 1
        if ts.last():
            env.reset()
    return n_steps / elapsed


REFERENCES: dict[str, Callable[[str, int, int], float]] = {
    "dm_control": dm_control_reference,
}


# -- MJX --------------------------------------------------------------------------------
def mjx_throughput(task, batch: int, n_steps: int, repeats: int, seed: int = 0,
                   group: int | None = None):
    """(compile_s, best run_s) of `n_steps` vmapped steps at `batch` (in groups of `group`:
    `tasks.batching.vmap_in_groups`)."""
    step = batching.vmap_in_groups(task.step, group)

    def rollout(state, key):
        def body(carry, _):
            state, key = carry
            key, sub = jax.random.split(key)
            action = jax.random.uniform(sub, (batch, task.action_size), minval=-1, maxval=1)
            state = step(state, action)
            return (state, key), state.true_reward
        (state, _), rewards = jax.lax.scan(body, (state, key), None, length=n_steps)
        return state, rewards

    key = jax.random.key(seed)
    state = jax.jit(jax.vmap(task.reset))(jax.random.split(key, batch))
    jax.block_until_ready(state)
    t0 = time.perf_counter()
    fn = jax.jit(rollout).lower(state, key).compile()
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(fn(state, key))  # warm-up (allocations), not timed
    times = []
    for r in range(repeats):
        t0 = time.perf_counter()
        out = fn(state, jax.random.fold_in(key, r))
        jax.block_until_ready(out)
        times.append(time.perf_counter() - t0)
    if not np.isfinite(np.asarray(out[1])).all():
        raise FloatingPointError(f"{task.name}: non-finite reward in the benchmark rollout")
    return compile_s, min(times)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    # default: the DM Control ports (building every registered task would also build the
    # MetaWorld scenes); any registered task whose domain has a REFERENCES entry works
    parser.add_argument("--tasks", nargs="+", default=ports())
    parser.add_argument("--batch", nargs="+", type=int, default=[1, 16, 128])
    parser.add_argument("--steps", type=int, default=50, help="control steps per timed rollout")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--ref-steps", type=int, default=2000)
    parser.add_argument("--variants", nargs="+", default=["while:floor:task"],
                        help="LOOP:CONTACTS[:CAP] to time: line-search loop while|scan "
                             "(tasks.physics.linesearch_loop), contacts floor|all and contact "
                             "cap task|none (DM Control)")
    parser.add_argument("--groups", nargs="+", default=["auto"],
                        help="batching layouts: none (one vmap), auto (VecEnv's on this "
                             "backend) or a group size (tasks.batching)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)

    device = f"{jax.devices()[0].platform}:{os.cpu_count()}cpu:{platform.processor() or platform.machine()}"
    rows = []
    for name in args.tasks:
        ref = REFERENCES[tasks.info(name).domain](name, args.ref_steps, 0)
        for batch, variant, layout in ((b, v, g) for b in args.batch for v in args.variants
                                       for g in args.groups):
            loop, contacts, cap = (variant.split(":") + ["task"])[:3]
            options = {}
            if tasks.info(name).domain == "dm_control":
                options = {"contacts": contacts} | ({"max_contacts": None} if cap == "none" else {})
            task = tasks.make(name, **options)
            group = batching.group_from_option(layout, task)
            with physics.linesearch_loop(loop):
                compile_s, run_s = mjx_throughput(task, batch, args.steps, args.repeats,
                                                  group=group)
            sps = batch * args.steps / run_s
            rows.append(dict(
                task=name, batch=batch, linesearch=loop, contacts=contacts,
                contact_cap=getattr(task, "max_contacts", None),
                group=batching.group_size(batch, group) or batch, steps=args.steps,
                n_sub_steps=task.n_sub_steps,
                compile_s=round(compile_s, 2), run_s=round(run_s, 4),
                mjx_env_steps_per_s=round(sps, 1),
                mjx_substeps_per_s=round(sps * task.n_sub_steps, 1),
                ref_env_steps_per_s=round(ref, 1), c_over_mjx=round(ref / sps, 2),
                device=device, jax=jax.__version__,
            ))
            print(rows[-1], flush=True)

    args.out.parent.mkdir(parents=True, exist_ok=True)
    with open(args.out, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    cols = ["task", "batch", "group", "linesearch", "contacts", "contact_cap", "compile_s",
            "mjx_env_steps_per_s", "ref_env_steps_per_s", "c_over_mjx"]
    print("\n" + " | ".join(f"{c:>20}" for c in cols))
    for r in rows:
        print(" | ".join(f"{str(r[c]):>20}" for c in cols))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
