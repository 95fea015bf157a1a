"""XLA's backend optimisation level against start-up and run speed (issue 23).

`python -m benchmarks.runs.compile_level [--task T] [--levels default 1 0] [--repeats 1]
[--first-repeat N]` (`--first-repeat N` numbers the repeats from N and keeps the CSV's other
rows of the task): `hprior train --task T --algo pebble --preset reduced` (default cheetah_run)
on one seed for 12000 steps (5000 random steps, evaluations at 5000 and 10000, the first
feedback round at 10000), once per level with `--compile-level N` and an empty compilation
cache ("default": `--compile-level xla`, XLA's own level, the reference run of the same
script). The test suite compiles at -O0 (tests/xla_opt.py), where compiling is about half as
long; this measures what a level costs a run: seconds to the first env step, compile seconds
the main thread waited for, the env + SAC chunks and the evaluation (run speed), and the
whole wall. Writes benchmarks/results/runs/compile_level.csv.
"""
from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

from benchmarks._timing import read_rows, write_rows
from benchmarks.runs.end_to_end import one_run
from hprior_jax.setup_jax import LEVEL_OPTION

OUT = Path(__file__).resolve().parents[1] / "results" / "runs" / "compile_level.csv"
FIELDS = ["task", "level", "repeat", "first_step_s", "compile_s", "chunk_s", "eval_s",
          "event_s", "wall_s", "env_steps_per_s", "steps"]


def without_level_flag() -> dict:
    """XLA_FLAGS of this process without a level (`--compile-level` sets the child's)."""
    flags = os.environ.get("XLA_FLAGS", "").split()
    return {"XLA_FLAGS": " ".join(f for f in flags if LEVEL_OPTION not in f)}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--task", default="cheetah_run")
    p.add_argument("--levels", nargs="+", default=["default", "1", "0"])
    p.add_argument("--repeats", type=int, default=1)
    p.add_argument("--first-repeat", type=int, default=0,
                   help="number the repeats from here, keeping the CSV's other rows")
    p.add_argument("--preset", default="reduced", choices=["smoke", "reduced"])
    p.add_argument("--steps", type=int, default=12_000)
    p.add_argument("--out", type=Path, default=OUT)
    args = p.parse_args(argv)
    rows = []
    # rows of other repeats stay (`--first-repeat`: more repeats of an earlier run)
    keep = [row for row in read_rows(args.out) if row.get("task") != args.task
            or int(row["repeat"]) < args.first_repeat
            or int(row["repeat"]) >= args.first_repeat + args.repeats]
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.first_repeat, args.first_repeat + args.repeats):
            for level in args.levels:
                name = f"{args.task}_level_{level}_{r}"
                row = one_run(args.task, "pebble", 1, args.preset, args.steps, Path(tmp),
                              extra_args=("--compile-level",
                                          "xla" if level == "default" else level),
                              extra_env=without_level_flag(), name=name)
                row.update(level=level, repeat=r)
                rows.append(row)
                print(f"{name}: first env step {row['first_step_s']:.1f} s, compile waited "
                      f"{row['compile_s']:.1f} s, chunks {row['chunk_s']:.1f} s, eval "
                      f"{row['eval_s']:.1f} s, wall {row['wall_s']:.1f} s", flush=True)
                # after every run: a stopped benchmark keeps what it measured
                write_rows([{k: (round(x[k], 2) if isinstance(x[k], float) else x[k])
                             for k in FIELDS} for x in rows], args.out, keep=keep)


if __name__ == "__main__":
    main()
