"""Where a task's physics substep spends its time, stage by stage, under `jit(vmap)`.

    python -m benchmarks.ports.env_profile [--tasks cheetah_run ...] [--batch 128]
                                           [--warm-steps 200]

One legacy substep (dm_control's `mj_step2` then `mj_step1`, as `tasks.physics` runs it) is
cut into MJX's own stages: actuation, smooth acceleration, constraint solve, acceleration
sensors, integration, kinematics, com_pos, crb, factor_m, collision, make_constraint,
transmission, the position and velocity sensors, com_vel, passive, rne. Each stage is jitted
alone as `vmap(stage)` over a batch of states taken from random-action rollouts (so contacts
are present) and timed on that batch (best of `--repeats`, after a warm-up call). The whole
substep is timed the same way, so `sum_over_whole` says how much the cut itself costs:
each stage alone also reads and writes the whole batched `Data` (about 1 ms at batch 128
on 2 cores), so a stage's time is an upper bound, and the ranking matters more than the
sum. Also printed: the contact and constraint-row counts MJX allocates and how many
contacts are active in the sample; and, as the reference in the same run, the substep and the solve traced with MJX's own line-search
loop (`tasks.physics.linesearch_loop("scan")`). Writes benchmarks/results/ports/env_profile.csv.

    python -m benchmarks.ports.env_profile --census [--episodes 20]

Contact census of the reference simulator instead: dm_control's own env in C MuJoCo, half
the episodes with uniform random actions and half bang-bang (each actuator at a random end
of its range, which drives the joints to their limits), counting the steps in which each
geom pair touches. Pairs without a world-body (floor) geom are the self contacts that the
ports' default `contacts="floor"` leaves out. Writes benchmarks/results/ports/contact_census.csv.

    python -m benchmarks.ports.env_profile --census-counts [--episodes 60]

How many contacts the same C env holds at once, after every substep (random, bang-bang and
bang-bang held for 50 steps, in turn), against each port's MJX contact cap
(`tasks.physics.with_max_contacts`). Writes benchmarks/results/ports/contact_count_census.csv.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import tasks  # noqa: F401  (sets XLA_FLAGS before jax is imported)

import jax
import mujoco
import numpy as np
from mujoco.mjx._src import collision_driver, constraint, forward, sensor, smooth

from benchmarks._timing import write_rows
from tasks import physics
from tasks.dm_control.reference import ports
from tasks.physics import mjx

RESULTS = Path(__file__).resolve().parents[1] / "results" / "ports" / "env_profile.csv"
CENSUS = Path(__file__).resolve().parents[1] / "results" / "ports" / "contact_census.csv"
COUNTS = Path(__file__).resolve().parents[1] / "results" / "ports" / "contact_count_census.csv"


def substep_stages(m: mjx.Model):
    """(name, fn(d) -> d) in the order `tasks.physics.legacy_substeps` runs them."""
    integrator = mujoco.mjtIntegrator(int(m.opt.integrator))
    integrate = forward.implicit if integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST else forward.euler
    stages = [
        ("actuation", forward.fwd_actuation),
        ("acceleration", forward.fwd_acceleration),
        ("solve", physics.solve),
        ("sensor_acc", sensor.sensor_acc),
        ("integrate", integrate),
        ("kinematics", smooth.kinematics),
        ("com_pos", smooth.com_pos),
        ("crb", smooth.crb),
        ("factor_m", smooth.factor_m),
        ("collision", collision_driver.collision),
        ("make_constraint", constraint.make_constraint),
        ("transmission", smooth.transmission),
        ("sensor_pos", sensor.sensor_pos),
        ("com_vel", smooth.com_vel),
        ("passive", forward.passive.passive),
        ("rne", smooth.rne),
        ("sensor_vel", sensor.sensor_vel),
    ]
    return [(name, (lambda fn: lambda d: fn(m, d))(fn)) for name, fn in stages]


def sample_states(task, batch: int, n_steps: int, seed: int = 0):
    """`batch` task states after `n_steps` random-action control steps."""

    def rollout(state, key):
        def body(state, k):
            action = jax.random.uniform(k, (batch, task.action_size), minval=-1, maxval=1)
            return jax.vmap(task.step)(state, action), None
        return jax.lax.scan(body, state, jax.random.split(key, n_steps))[0]

    key = jax.random.key(seed)
    state = jax.jit(jax.vmap(task.reset))(jax.random.split(key, batch))
    return jax.jit(rollout)(state, jax.random.fold_in(key, 1))


def time_batched(fn, data, repeats: int) -> tuple[float, float]:
    """(compile_s, best seconds) of `jit(vmap(fn))(data)`."""
    t0 = time.perf_counter()
    compiled = jax.jit(jax.vmap(fn)).lower(data).compile()
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(compiled(data))
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(data))
        best = min(best, time.perf_counter() - t0)
    return compile_s, best


def profile_task(name: str, batch: int, warm_steps: int, repeats: int) -> list[dict]:
    task = tasks.make(name)
    m = task.model
    data = sample_states(task, batch, warm_steps).data
    impl = data._impl
    ncon = int(impl.contact.dist.shape[-1]) if impl.contact.dist.ndim > 1 else 0
    active = float(np.mean(np.sum(np.asarray(impl.contact.dist) < 0, axis=-1))) if ncon else 0.0
    nefc = int(impl.efc_J.shape[-2]) if impl.efc_J.ndim > 2 else 0
    whole = lambda d: physics.legacy_substeps(m, d, 1)
    _, whole_s = time_batched(whole, data, repeats)
    rows = []
    for stage, fn in substep_stages(m):
        compile_s, best = time_batched(fn, data, repeats)
        rows.append(dict(task=name, batch=batch, stage=stage, ms=round(best * 1e3, 3),
                         share_of_whole=round(best / whole_s, 3), compile_s=round(compile_s, 2)))
    total = sum(r["ms"] for r in rows)
    with physics.linesearch_loop("scan"):  # the reference: MJX's own line-search loop
        _, scan_whole_s = time_batched(whole, data, repeats)
        _, scan_solve_s = time_batched(lambda d: physics.solve(m, d), data, repeats)
    for r in rows:
        r.update(whole_substep_ms=round(whole_s * 1e3, 3),
                 sum_over_whole=round(total / (whole_s * 1e3), 2),
                 ncon=ncon, contacts_active_mean=round(active, 2), nefc=nefc,
                 mjx_scan_whole_substep_ms=round(scan_whole_s * 1e3, 3),
                 mjx_scan_solve_ms=round(scan_solve_s * 1e3, 3),
                 opt_iterations=int(task.mj_model.opt.iterations),
                 opt_ls_iterations=int(task.mj_model.opt.ls_iterations),
                 solver=mujoco.mjtSolver(int(task.mj_model.opt.solver)).name)
    return rows


HOLD_STEPS = 50  # the `hold` policy keeps one bang-bang action this many control steps


def _census_plan(name: str, episodes: int, policies: tuple[str, ...], seed: int,
                 exported: tuple[Path, ...]):
    """dm_control's C env for `name` and an action function per census episode: `policies`
    in turn, then each `hprior export` policy of `exported` for `episodes` // 2 more."""
    from benchmarks.ports.dm_control_parity import flatten_obs, reference_env
    from hprior_jax.export import load_policy

    env = reference_env(name, seed)
    spec = env.action_spec()
    rng = np.random.RandomState(seed)
    bang = lambda: np.where(rng.rand(*spec.shape) < 0.5, spec.minimum, spec.maximum)
    held = [None]

    def hold(t):
        if t % HOLD_STEPS == 0:
            held[0] = bang()
        return held[0]

    acts = {"random": lambda t: rng.uniform(spec.minimum, spec.maximum),
            "bang_bang": lambda t: bang(), "hold": hold}
    observe = lambda: flatten_obs(env.task.get_observation(env.physics))
    for p in exported:  # agent actions live in [-1, 1]; the DMC ports' actuators do too
        policy = jax.jit(load_policy(p))
        acts[f"export:{p}"] = lambda t, f=policy: np.asarray(f(observe()))
    plan = [policies[e % len(policies)] for e in range(episodes)]
    plan += [f"export:{p}" for p in exported for _ in range(episodes // 2)]
    return env, [(policy, acts[policy]) for policy in plan]


def contact_census(name: str, episodes: int, seed: int = 0,
                   exported: tuple[Path, ...] = ()) -> list[dict]:
    """Steps with a contact per geom pair in dm_control's C env (see the module docstring);
    `exported`: policies written by `hprior export`, each run for `episodes` // 2 more."""
    env, plan = _census_plan(name, episodes, ("random", "bang_bang"), seed, exported)
    m, d = env.physics.model.ptr, env.physics.data.ptr
    counts, steps = {}, {}
    for policy, act in plan:
        ts, t = env.reset(), 0
        while not ts.last():
            ts, t = env.step(act(t)), t + 1
            steps[policy] = steps.get(policy, 0) + 1
            touching = {tuple(sorted((int(c.geom1), int(c.geom2)))) for c in d.contact[:d.ncon]}
            for pair in touching:
                counts[pair, policy] = counts.get((pair, policy), 0) + 1
    geom = lambda g: mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g) or str(g)
    rows = [dict(task=name, geom1=geom(g1), geom2=geom(g2), policy=policy, steps_touching=n,
                 steps=steps[policy], self_contact=bool(m.geom_bodyid[g1] and m.geom_bodyid[g2]))
            for ((g1, g2), policy), n in sorted(counts.items(), key=lambda kv: -kv[1])]
    selfs = sum(r["steps_touching"] for r in rows if r["self_contact"])
    print(f"{name}: {len({(r['geom1'], r['geom2']) for r in rows})} geom pairs touched in "
          f"{sum(steps.values())} steps ({', '.join(f'{p} {n}' for p, n in steps.items())}), "
          f"self-contact steps {selfs}")
    return rows


def contact_counts(name: str, episodes: int, seed: int = 0,
                   exported: tuple[Path, ...] = ()) -> list[dict]:
    """How many contacts C MuJoCo holds at once, counted after every substep of dm_control's
    env (random, bang-bang and held bang-bang actions in turn, then `exported` policies),
    against the port's MJX contact cap (`tasks.physics.with_max_contacts`): a substep with
    more contacts than the cap is one where the port would drop the shallowest ones."""
    task = tasks.make(name)
    candidates = int(mjx.make_data(tasks.make(name, max_contacts=None).model)
                     ._impl.contact.dist.shape[-1])
    env, plan = _census_plan(name, episodes, ("random", "bang_bang", "hold"), seed, exported)
    physics_, d = env.physics, env.physics.data.ptr
    hist = {}  # (policy, contacts at once) -> substeps
    for policy, act in plan:
        env.reset()
        for t in range(task.episode_length):
            physics_.set_control(act(t))  # what the tasks' `before_step` does
            for _ in range(task.n_sub_steps):  # dm_control's step, one substep at a time
                physics_.step()
                key = (policy, int(d.ncon))
                hist[key] = hist.get(key, 0) + 1
    rows = []
    for policy in dict.fromkeys(p for p, _ in plan):
        h = {n: c for (p, n), c in hist.items() if p == policy}
        rows.append(dict(task=name, policy=policy, episodes=sum(p == policy for p, _ in plan),
                         substeps=sum(h.values()), max_at_once=max(h),
                         substeps_over_cap=sum(c for n, c in h.items()
                                               if task.max_contacts and n > task.max_contacts),
                         cap=task.max_contacts, candidates=candidates,
                         histogram=" ".join(f"{n}:{h[n]}" for n in sorted(h))))
        print(rows[-1], flush=True)
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--tasks", nargs="+", default=ports())
    parser.add_argument("--batch", type=int, default=128)
    parser.add_argument("--warm-steps", type=int, default=200,
                        help="random-action control steps before the profiled states")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--census", action="store_true",
                        help="count the reference simulator's contacts per geom pair instead")
    parser.add_argument("--census-counts", action="store_true",
                        help="count the contacts the reference simulator holds at once, "
                             "after every substep, against the ports' contact caps")
    parser.add_argument("--episodes", type=int, default=20, help="census episodes per task")
    parser.add_argument("--exported", nargs="*", type=Path, default=[],
                        help="census: also run these `hprior export` policies (of the task)")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    if args.census_counts:
        write_rows([r for name in args.tasks for r in contact_counts(
            name, args.episodes, exported=tuple(args.exported))], args.out or COUNTS)
        return
    if args.census:
        write_rows([r for name in args.tasks for r in contact_census(name, args.episodes,
                                                                 exported=tuple(args.exported))],
               args.out or CENSUS)
        return
    rows = []
    for name in args.tasks:
        task_rows = profile_task(name, args.batch, args.warm_steps, args.repeats)
        rows += task_rows
        r0 = task_rows[0]
        print(f"\n{name} B={args.batch}: whole substep {r0['whole_substep_ms']} ms "
              f"(stages sum {r0['sum_over_whole']}x), ncon {r0['ncon']} "
              f"(active {r0['contacts_active_mean']}), nefc {r0['nefc']}, {r0['solver']} "
              f"(opt.iterations {r0['opt_iterations']}, ls {r0['opt_ls_iterations']}); with "
              f"MJX's scan line search: substep {r0['mjx_scan_whole_substep_ms']} ms, solve "
              f"{r0['mjx_scan_solve_ms']} ms")
        for r in sorted(task_rows, key=lambda r: -r["ms"]):
            print(f"  {r['stage']:>16} {r['ms']:9.3f} ms  {100 * r['share_of_whole']:5.1f}%")
    write_rows(rows, args.out or RESULTS)


if __name__ == "__main__":
    main()
