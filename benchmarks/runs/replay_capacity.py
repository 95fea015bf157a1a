"""Env steps/s at several replay capacities, per phase: the cost of a step must not grow with
the buffer (only a feedback round may touch every stored row, once per round).

    python -m benchmarks.runs.replay_capacity [--task cheetah_run]
        [--capacities 10000 100000 1000000] [--algos sac pebble] [--length 500] [--repeats 3]

For each (algorithm, capacity) one engine at smoke network sizes, one seed. The buffer is
filled with `n` random rows before each measurement, `n` being the phase's step (so the k-NN
reward of the unsupervised phase scans the same number of rows at every capacity); then one
compiled chunk of `--length` env steps runs from that step, best of `--repeats`. PEBBLE's
first feedback round (query, teacher, reward learning, relabel, critic reset) is timed once
after its compile. `ratio` = seconds per step / the smallest capacity's. Writes
benchmarks/results/runs/replay_capacity.csv.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import tasks  # noqa: F401  (sets XLA_FLAGS before jax is imported)
from benchmarks._timing import best_seconds, machine, write_rows
from hprior_jax.methods import registry

RESULTS = Path(__file__).resolve().parents[1] / "results" / "runs" / "replay_capacity.csv"
SEED_STEPS, UNSUP_STEPS = 2000, 3000
PHASE_STEP = {"random": 1000, "unsup": 3000, "sac": 6000}  # a step inside each phase


def make_engine(task: str, algo: str, capacity: int):
    import dataclasses

    from hprior_jax import presets
    from hprior_jax.runs.build import build_engine

    cfg = presets.train_preset(task, algo, "smoke", steps=capacity, num_seed_steps=SEED_STEPS)
    if hasattr(cfg, "pebble"):  # the PEBBLE family: a pre-training phase of UNSUP_STEPS
        cfg = dataclasses.replace(cfg, pebble=dataclasses.replace(
            cfg.pebble, num_unsup_steps=UNSUP_STEPS))
    return build_engine(cfg)


def filled(rs, n: int, key):
    """`rs` with the first `n` rows of its buffer random and the ring at position `n`."""
    import jax
    import jax.numpy as jnp

    buf = rs.replay
    valid = (jnp.arange(buf.capacity) < n)[None, :, None]
    noise = lambda k, x: jnp.where(valid, jax.random.normal(k, x.shape), 0.0)
    k1, k2, k3 = jax.random.split(key, 3)
    n_ = jnp.full_like(buf.size, n)
    buf = buf.replace(obs=noise(k1, buf.obs), next_obs=noise(k2, buf.next_obs),
                      action=jnp.tanh(noise(k3, buf.action)), index=n_, size=n_)
    return rs.replace(replay=buf)


def seconds(fn, rs_source, repeats: int) -> float:
    """Best wall time of `fn(copy of rs)`: the chunk donates its input, so each call gets a
    fresh copy made outside the timer."""
    import jax
    import jax.numpy as jnp

    copy = lambda: jax.block_until_ready(jax.tree.map(jnp.copy, rs_source))
    return best_seconds(fn, repeats, jax.block_until_ready, setup=copy)


def measure(task: str, algo: str, capacity: int, length: int, repeats: int) -> list[dict]:
    import jax

    engine = make_engine(task, algo, capacity)
    rs0 = engine.init_seeds([12345])
    rows = []
    for phase in (p.name for p in engine.phases):
        step = PHASE_STEP[phase]
        assert engine.phase_at(step) == phase
        rs = filled(rs0, step, jax.random.PRNGKey(step))
        engine.compiled_chunk(rs, step, length)  # compile outside the timer
        s = seconds(lambda r: engine.run_chunk(r, step, length), rs, repeats)
        rows.append({"algo": algo, "phase": phase, "capacity": capacity,
                     "ms_per_step": s / length * 1e3, "env_steps_per_s": length / s})
    if engine.event_steps():
        step = engine.event_steps()[0]
        rs = filled(rs0, step, jax.random.PRNGKey(step))
        seconds(lambda r: engine.run_event(r, step), rs, 1)  # compile
        s = seconds(lambda r: engine.run_event(r, step), rs, repeats)
        rows.append({"algo": algo, "phase": "feedback_round", "capacity": capacity,
                     "ms_per_step": "", "env_steps_per_s": "", "event_s": s})
    return rows


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--task", default="cheetah_run")
    p.add_argument("--algos", nargs="+", default=["sac", "pebble"], choices=registry.names())
    p.add_argument("--capacities", nargs="+", type=int, default=[10_000, 100_000, 1_000_000])
    p.add_argument("--length", type=int, default=500, help="env steps per timed chunk")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--out", type=Path, default=RESULTS)
    args = p.parse_args(argv)
    if min(args.capacities) <= PHASE_STEP["sac"] + args.length:
        p.error(f"capacities must exceed {PHASE_STEP['sac'] + args.length} (the last "
                "measured step)")

    rows = []
    for algo in args.algos:
        for cap in sorted(args.capacities):
            for row in measure(args.task, algo, cap, args.length, args.repeats):
                rows.append(row)
                print(row, flush=True)
    smallest = min(args.capacities)
    base = {(r["algo"], r["phase"]): r for r in rows if r["capacity"] == smallest}
    for r in rows:
        key = "event_s" if r["phase"] == "feedback_round" else "ms_per_step"
        r["ratio"] = round(r[key] / base[(r["algo"], r["phase"])][key], 3)
        r["machine"] = machine()
        for k, v in r.items():
            if isinstance(v, float):
                r[k] = round(v, 4)
    for r in rows:
        if r["capacity"] != smallest and r["phase"] != "feedback_round":
            verdict = "ok" if r["ratio"] <= 1.1 else "GROWS WITH CAPACITY"
            print(f"{r['algo']:7s} {r['phase']:7s} {r['capacity']:>8d}/{smallest}: "
                  f"x{r['ratio']:.2f} {verdict}")
    write_rows(rows, args.out)


if __name__ == "__main__":
    main()
