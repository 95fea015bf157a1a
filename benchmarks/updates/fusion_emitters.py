"""XLA's CPU fusion emitters per program: the physics-free update programs compiled with and
without them, in one process.

    python -m benchmarks.updates.fusion_emitters [--repeats 7]

MJX needs `--xla_cpu_use_fusion_emitters=false` (tasks/_xla_flags.py) and the project sets it
for the whole process; a program without physics can take XLA's default back through its own
`compiler_options` (`hprior_jax.setup_jax.PHYSICS_FREE`). Each program below is lowered once
and compiled both ways, run on the same inputs, its outputs compared (largest absolute
difference over every output leaf) and timed alternately (best of `--repeats` each):

- the world-model dynamics update (`prior.world_model.update_dynamics`, 3 updates under
  `jit(vmap(scan))`, `benchmarks.updates.world_model_update`), reduced and paper sizes;
- one epoch of the reward ensemble (`pbrl.preference.train_epoch`,
  `benchmarks.updates.reward_update`), on 128 and 1024 stored pairs.

Writes benchmarks/results/updates/fusion_emitters.csv: ms with the flag (`ms_flag`) and
without (`ms_default`), their ratio (`speedup` = ms_flag / ms_default) and the difference.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import tasks  # noqa: F401  (sets XLA_FLAGS before jax is imported)
from benchmarks._timing import machine, write_rows

RESULTS = Path(__file__).resolve().parents[1] / "results" / "updates" / "fusion_emitters.csv"


def world_model_case(size: str, n_seeds: int):
    from benchmarks.updates.world_model_update import update_program

    program, states, keys, _ = update_program(size, n_seeds, n_updates=3)
    return program, (states, keys)


def reward_case(n_pairs: int, n_seeds: int):
    from benchmarks.updates.reward_update import epoch_program

    program, args, _ = epoch_program("dmc", n_seeds, n_pairs)
    return program, args


def compare(program, args, repeats: int) -> dict:
    """The program compiled with the process's flag and with XLA's default emitters: ms of
    each (best of `repeats`, alternating), compile seconds, the outputs' largest difference."""
    import jax
    import numpy as np

    from hprior_jax.setup_jax import PHYSICS_FREE

    lowered = program.lower(*args)
    compiled, compile_s = {}, {}
    for name, options in (("flag", None), ("default", PHYSICS_FREE)):
        t0 = time.perf_counter()
        compiled[name] = lowered.compile(compiler_options=options)
        compile_s[name] = time.perf_counter() - t0
    outputs = {name: jax.block_until_ready(fn(*args)) for name, fn in compiled.items()}
    diff = max(float(np.max(np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64))))
               for a, b in zip(jax.tree.leaves(outputs["flag"]), jax.tree.leaves(outputs["default"]))
               if np.issubdtype(np.asarray(a).dtype, np.floating))
    best = {name: float("inf") for name in compiled}
    for _ in range(repeats):
        for name, fn in compiled.items():
            t0 = time.perf_counter()
            jax.block_until_ready(fn(*args))
            best[name] = min(best[name], time.perf_counter() - t0)
    return {"ms_flag": 1e3 * best["flag"], "ms_default": 1e3 * best["default"],
            "speedup": best["flag"] / best["default"], "max_abs_diff": diff,
            "compile_s_flag": compile_s["flag"], "compile_s_default": compile_s["default"]}


CASES = {
    "world_model_update reduced x1": lambda: world_model_case("reduced", 1),
    "world_model_update reduced x5": lambda: world_model_case("reduced", 5),
    "world_model_update paper x1": lambda: world_model_case("paper", 1),
    "reward_epoch 128 pairs x1": lambda: reward_case(128, 1),
    "reward_epoch 128 pairs x5": lambda: reward_case(128, 5),
    "reward_epoch 1024 pairs x1": lambda: reward_case(1024, 1),
}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    rows = []
    for case in args.cases:
        program, inputs = CASES[case]()
        row = {"program": case, **compare(program, inputs, args.repeats), "machine": machine()}
        print(f"{case}: {row['ms_flag']:.1f} ms with the flag, {row['ms_default']:.1f} ms "
              f"without (x{row['speedup']:.2f}); outputs differ by {row['max_abs_diff']:.2g}",
              flush=True)
        rows.append(row)
    write_rows(rows, args.out)


if __name__ == "__main__":
    main()
