"""Start-up with and without compiling ahead: the first env step, compile waits, wall time.

`python -m benchmarks.runs.compile_ahead [--repeats 2] [--modes off at-start ...]
[--out CSV]`: `hprior train --task cheetah_run --algo pebble --preset reduced` on one seed for
12000 steps (5000 random steps, evaluations at 5000 and 10000, the first feedback round at
10000). Per repeat, one run per `--compile-ahead` mode: `off` (every later program compiled
when first needed), `at-start` (everything after the first chunk's program compiled in a
background thread from the start, in the order the run needs it), `after-first` (the
same queue, started once the main thread has compiled the first chunk's program) and
`first-phase-apart` (as after-first, with the random phase's chunks run by a program of
that phase alone, so the first compile is smaller), each
with a fresh persistent compilation cache (cold), then all again on their now-filled
caches (warm). Writes benchmarks/results/runs/compile_ahead.csv: seconds from
process start to the first env step (perf/first_step_s), wall seconds of the whole run
(process start to exit), the compile seconds the main thread spent or waited for
(perf/compile_s), and the parts' seconds. `--trees before=DIR after=.` runs each mode with
the code of each checkout in turn (e.g. a `git worktree` of an earlier commit), so a change
is measured against its parent in the same run; column `tree`.
"""
from __future__ import annotations

import argparse
import csv
import subprocess
import tempfile
from pathlib import Path

from benchmarks.runs.end_to_end import one_run

OUT = Path(__file__).resolve().parents[1] / "results" / "runs" / "compile_ahead.csv"
MODES = ["off", "at-start", "after-first", "first-phase-apart"]


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--steps", type=int, default=12_000)
    p.add_argument("--modes", nargs="+", default=MODES, choices=MODES)
    p.add_argument("--out", type=Path, default=OUT)
    p.add_argument("--trees", nargs="+", default=["this=."], metavar="LABEL=DIR",
                   help="checkouts whose code to run, each mode in turn (default: this one)")
    args = p.parse_args(argv)
    trees = dict(t.split("=", 1) for t in args.trees)
    commits = {label: subprocess.run(["git", "-C", d, "rev-parse", "--short", "HEAD"],
                                     capture_output=True, text=True).stdout.strip()
               for label, d in trees.items()}
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.repeats):
            for cache in ("cold", "warm"):
                for mode in args.modes:
                    for label, tree in trees.items():
                        name = f"{mode}_{r}_{cache}_{label}"
                        row = one_run("cheetah_run", "pebble", 1, "reduced", args.steps,
                                      Path(tmp), extra_args=("--compile-ahead", mode), name=name,
                                      cache=f"{mode}_{r}_{label}", tree=Path(tree).resolve())
                        row.update(mode=mode, cache=cache, repeat=r, tree=label,
                                   commit=commits[label])
                        rows.append(row)
                        print(f"{name}: first env step {row['first_step_s']:.1f} s, wall "
                              f"{row['wall_s']:.1f} s, compile waited {row['compile_s']:.1f} s",
                              flush=True)
    keys = ["mode", "cache", "repeat", "tree", "commit", "first_step_s", "wall_s", "compile_s",
            "chunk_s", "eval_s", "event_s", "env_steps_per_s"]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with open(args.out, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys, extrasaction="ignore", lineterminator="\n")
        w.writeheader()
        w.writerows({k: (round(v, 2) if isinstance(v, float) else v) for k, v in row.items()}
                    for row in rows)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
