"""MJX's two implementations on the task ports' physics: JAX (what the ports run) vs Warp.

    python -m benchmarks.ports.mjx_warp [--tasks cheetah_run ...] [--batch 1 16 128] [--steps 20]

Needs `warp-lang` (not a project dependency: `pip install warp-lang`; MuJoCo Warp itself ships
inside mujoco-mjx). Both sides step the port's own MjModel (`task.mj_model`: its floor-only
contact pairs; MJX-JAX also reads its contact cap, Warp sizes its contact pool per world from
the same number of slots) with `mjx.step`, `n_sub_steps` per control step, uniform random
controls, a jitted scan of `--steps` vmapped control steps from the port's own reset states.
JAX runs the ports' while-loop line search (tasks/physics.py); the ports themselves step with
dm_control's legacy split (step2 then step1), which Warp does not expose, at one forward per
substep either way. Compile is timed apart; best of `--repeats`.

Parity (`--parity N`): N reset states, one and ten control steps with the same controls on C
MuJoCo (`mj_step`), MJX-JAX and MJX-Warp; the largest |qpos - C's qpos| of each side.
Rows go to benchmarks/results/ports/mjx_warp.csv (or --out): one per task, batch and impl, with C
MuJoCo's single-thread substeps/s measured in the same run.
"""
from __future__ import annotations

import argparse
import contextlib
import io
import os
import platform
import time
from pathlib import Path

import tasks  # noqa: F401  (sets XLA_FLAGS before jax is imported)
from benchmarks._timing import write_rows
from tasks import physics
from tasks.dm_control.reference import ports

import jax
import mujoco
import numpy as np

RESULTS = Path(__file__).resolve().parents[1] / "results" / "ports" / "mjx_warp.csv"
IMPLS = ("jax", "warp")


def warp_available() -> bool:
    with contextlib.redirect_stdout(io.StringIO()):
        try:
            import warp  # noqa: F401
        except ImportError:
            return False
    return True


def pool_sizes(mx: physics.mjx.Model) -> tuple[int, int]:
    """(contact slots, constraint rows) MJX-JAX allocates for its model `mx`: Warp gets the
    same."""
    d = physics.mjx.make_data(mx)
    return max(int(d._impl.contact.dist.shape[0]), 1), max(int(d._impl.efc_J.shape[0]), 1)


class Engine:
    """`mjx.step` on one MjModel with one implementation; batched data from qpos/qvel."""

    def __init__(self, m: mujoco.MjModel, impl: str):
        self.impl, self.mj_model = impl, m
        with contextlib.redirect_stdout(io.StringIO()):  # Warp's start-up banner
            self.model = (physics.put_model(m) if impl == "jax"
                          else physics.mjx.put_model(m, impl="warp"))
        self.naconmax, self.njmax = pool_sizes(self.model if impl == "jax"
                                               else physics.put_model(m))
        self._step = physics.step if impl == "jax" else physics.mjx.step

    def data(self, qpos: jax.Array, qvel: jax.Array):
        """Batched data at `qpos`/`qvel` ([B, nq], [B, nv]), forward run."""
        batch = qpos.shape[0]

        def one(q, v):
            if self.impl == "jax":
                d = physics.mjx.make_data(self.model)
            else:  # Warp's contact pool is shared by the batch (njmax is per world)
                d = physics.mjx.make_data(self.mj_model, impl="warp",
                                          naconmax=self.naconmax * batch, njmax=self.njmax)
            return d.replace(qpos=q, qvel=v)
        d = jax.vmap(one)(qpos, qvel)
        forward = physics.forward if self.impl == "jax" else physics.mjx.forward
        return jax.jit(jax.vmap(forward, in_axes=(None, 0)))(self.model, d)

    def control_steps(self, d, ctrls: jax.Array, n_sub: int):
        """Scan over ctrls [T, B, nu]: set ctrl, `n_sub` steps. Returns (data, qpos [T, B, nq])."""
        step = jax.vmap(self._step, in_axes=(None, 0))

        def body(d, ctrl):
            d = d.replace(ctrl=ctrl)
            d = jax.lax.fori_loop(0, n_sub, lambda _, d: step(self.model, d), d)
            return d, d.qpos
        return jax.lax.scan(body, d, ctrls)


def random_ctrls(m: mujoco.MjModel, key, steps: int, batch: int) -> jax.Array:
    lo, hi = m.actuator_ctrlrange[:, 0], m.actuator_ctrlrange[:, 1]
    return jax.random.uniform(key, (steps, batch, m.nu), minval=lo, maxval=hi)


def reset_states(task, batch: int, seed: int = 0) -> tuple[jax.Array, jax.Array]:
    state = jax.jit(jax.vmap(task.reset))(jax.random.split(jax.random.key(seed), batch))
    return state.data.qpos, state.data.qvel


def throughput(engine: Engine, qpos, qvel, n_sub: int, steps: int, repeats: int):
    """(compile s, best run s) of `steps` control steps of the whole batch."""
    d0 = engine.data(qpos, qvel)
    ctrls = random_ctrls(engine.mj_model, jax.random.key(1), steps, qpos.shape[0])
    run = jax.jit(lambda d, c: engine.control_steps(d, c, n_sub))
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(io.StringIO()):  # Warp prints a line per kernel module
        jax.block_until_ready(run(d0, ctrls))  # compile and first run: Warp builds here
    compile_s = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        _, qs = run(d0, ctrls)
        jax.block_until_ready(qs)
        times.append(time.perf_counter() - t0)
    if not np.isfinite(np.asarray(qs)).all():
        raise FloatingPointError(f"{engine.impl}: non-finite qpos in the benchmark rollout")
    return compile_s, min(times)


def c_substeps_per_s(m: mujoco.MjModel, qpos, ctrls, seconds: float = 2.0) -> float:
    d = mujoco.MjData(m)
    d.qpos[:] = qpos
    mujoco.mj_forward(m, d)
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        d.ctrl[:] = ctrls[n % len(ctrls)]
        mujoco.mj_step(m, d)
        n += 1
    return n / (time.perf_counter() - t0)


def c_rollout(m: mujoco.MjModel, qpos, qvel, ctrls, n_sub: int) -> np.ndarray:
    """C MuJoCo's qpos after each control step, [T, B, nq]."""
    out = np.zeros((ctrls.shape[0], qpos.shape[0], m.nq))
    for b in range(qpos.shape[0]):
        d = mujoco.MjData(m)
        d.qpos[:], d.qvel[:] = qpos[b], qvel[b]
        mujoco.mj_forward(m, d)
        for t in range(ctrls.shape[0]):
            d.ctrl[:] = ctrls[t, b]
            for _ in range(n_sub):
                mujoco.mj_step(m, d)
            out[t, b] = d.qpos
    return out


def parity(task, engines: dict[str, Engine], n_states: int) -> dict:
    """Largest |qpos - C MuJoCo's| after 1 and 10 control steps, per impl."""
    m = task.mj_model
    qpos, qvel = reset_states(task, n_states, seed=7)
    ctrls = random_ctrls(m, jax.random.key(2), 10, n_states)
    ref = c_rollout(m, np.asarray(qpos, np.float64), np.asarray(qvel, np.float64),
                    np.asarray(ctrls, np.float64), task.n_sub_steps)
    out = {}
    for impl, engine in engines.items():
        with contextlib.redirect_stdout(io.StringIO()):
            _, qs = jax.jit(lambda d, c: engine.control_steps(d, c, task.n_sub_steps))(
                engine.data(qpos, qvel), ctrls)
        err = np.abs(np.asarray(qs, np.float64) - ref).max(axis=(1, 2))
        out[f"{impl}_qpos_err_1"], out[f"{impl}_qpos_err_10"] = float(err[0]), float(err[-1])
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--tasks", nargs="+", default=ports())
    p.add_argument("--batch", nargs="+", type=int, default=[1, 16, 128])
    p.add_argument("--steps", type=int, default=20, help="control steps per timed rollout")
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--impls", nargs="+", default=list(IMPLS), choices=IMPLS)
    p.add_argument("--parity", type=int, default=8, help="reset states compared with C (0: none)")
    p.add_argument("--out", type=Path, default=RESULTS)
    args = p.parse_args(argv)
    impls = [i for i in args.impls if i != "warp" or warp_available()]
    if impls != args.impls:
        print("warp-lang is not installed: MJX-JAX only", flush=True)
    dev = jax.devices()[0]
    device = (f"{dev.platform}:{dev.device_kind}" if dev.platform == "gpu" else
              f"cpu:{os.cpu_count()}cpu:{platform.processor() or platform.machine()}")
    rows = []
    for name in args.tasks:
        task = tasks.make(name)
        m, n_sub = task.mj_model, task.n_sub_steps
        qpos1, _ = reset_states(task, 1)
        c_rate = c_substeps_per_s(m, np.asarray(qpos1[0], np.float64),
                                  np.asarray(random_ctrls(m, jax.random.key(3), 100, 1)[:, 0]))
        engines = {impl: Engine(m, impl) for impl in impls}
        checks = parity(task, engines, args.parity) if args.parity else {}
        for batch in args.batch:
            qpos, qvel = reset_states(task, batch)
            for impl in impls:
                compile_s, run_s = throughput(engines[impl], qpos, qvel, n_sub, args.steps,
                                              args.repeats)
                substeps = batch * args.steps * n_sub / run_s
                rows.append(dict(
                    task=name, batch=batch, impl=impl, steps=args.steps, n_sub_steps=n_sub,
                    contact_slots=engines[impl].naconmax, compile_s=round(compile_s, 2),
                    substeps_per_s=round(substeps, 1), env_steps_per_s=round(substeps / n_sub, 1),
                    c_substeps_per_s=round(c_rate, 1), c_over_mjx=round(c_rate / substeps, 3),
                    **{k: v for k, v in checks.items() if k.startswith(impl)},
                    device=device, jax=jax.__version__, mujoco=mujoco.__version__))
                print(rows[-1], flush=True)
                write_rows(rows, args.out)  # after every row: a lease can end mid-run
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
