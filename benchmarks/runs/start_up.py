"""Where a start's seconds go, up to its first env step: every trace, lowering and compile
jax reports, by program and thread, on the real `hprior train` path.

`python -m benchmarks.runs.start_up [--task cheetah_run] [--algo pebble] [--preset reduced]
[--caches cold warm] [--repeats 1] [--trees LABEL=DIR ...] [--out CSV]`: runs `hprior train`
(one seed, 12000 steps) as a child with a listener on jax's own compile events
(`jax.monitoring` time spans: tracing to a jaxpr, lowering to MLIR, the backend compile),
stops it once its first chunk has logged, and prints the timeline: seconds from process start
at which each span began and ended, on which thread, for which program. `cold` starts on an
empty compilation cache, `warm` on the one the cold run filled. `--trees before=DIR after=.`
runs the code of each checkout in turn (a `git worktree` of an earlier commit), alternating
their order, so a change is measured against its parent in the same run; a start's first env step
moves by several seconds from run to run on a 2-core machine, so compare repeats, not one run.
Rows (one per span, `--out`; default: print only) carry the run's own `perf/first_step_s`.
"""
from __future__ import annotations

import argparse
import csv
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

FIRST_STEP = "perf/first_step_s"
EVENTS = {"/jax/core/compile/jaxpr_trace_duration": "trace",
          "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
          "/jax/core/compile/backend_compile_duration": "compile"}


def child(spans_path: str, argv: list[str]) -> None:
    """Runs `hprior train argv` with every compile event written to `spans_path` (JSONL)."""
    import threading

    from hprior_jax.loop.progress import process_age

    t_process = time.time() - process_age()  # the process's start on jax's clock
    out = open(spans_path, "a", buffering=1)

    def on_span(event, start, end, **kw):
        if event in EVENTS:
            out.write(json.dumps({"kind": EVENTS[event], "program": kw.get("fun_name", ""),
                                  "thread": threading.current_thread().name,
                                  "start_s": start - t_process, "end_s": end - t_process})
                      + "\n")

    import jax.monitoring

    jax.monitoring.register_event_time_span_listener(on_span)
    from hprior_jax import cli

    sys.exit(cli.main(["train", *argv]))


def one_start(work: Path, label: str, cache: Path, argv: list[str],
              tree: Path) -> tuple[float, list]:
    """One child (the code of checkout `tree`) up to its first chunk's log; returns its first
    env step and its spans."""
    from benchmarks.runs.end_to_end import first_record  # here: the child imports nothing more

    run_dir, spans = work / label, work / f"{label}.jsonl"
    env = dict(os.environ, HPRIOR_JAX_CACHE=str(cache), JAX_PLATFORMS="cpu")
    # the listener is this file's; the code it runs is the tree's (first on the path)
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", str(spans), "--",
           *argv, "--out", str(run_dir), "--no-progress"]
    env["PYTHONPATH"] = os.pathsep.join([str(tree), env.get("PYTHONPATH", "")])
    with open(work / f"{label}.log", "w") as log:
        proc = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT, cwd=tree)
        metrics = run_dir / "metrics.jsonl"
        while not metrics.exists() or math.isnan(first := first_record(metrics, FIRST_STEP)):
            if proc.poll() is not None:
                raise RuntimeError(f"{cmd} ended first:\n{(work / f'{label}.log').read_text()}")
            time.sleep(0.5)
        proc.kill()
        proc.wait()
    rows = [json.loads(line) for line in spans.read_text().splitlines()]
    return first, sorted(rows, key=lambda r: r["start_s"])


def _print_spans(spans: list, first: float, min_s: float) -> list:
    """Prints the spans that began before the first env step (shorter ones summed by kind);
    returns the printed ones."""
    shown, short = [], {}
    for s in spans:
        if s["start_s"] > first:
            continue
        took = s["end_s"] - s["start_s"]
        if took < min_s:
            short[s["kind"]] = short.get(s["kind"], 0.0) + took
            continue
        print(f"  {s['start_s']:6.1f} -> {s['end_s']:6.1f}  {took:5.1f} s  "
              f"{s['kind']:7s} {s['program'][:50]:50s} {s['thread']}")
        shown.append(s)
    print("  shorter spans, summed: " + ", ".join(f"{k} {v:.1f} s" for k, v in short.items()))
    return shown


def main(argv=None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--child"]:
        return child(argv[1], argv[3:])
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--task", default="cheetah_run")
    p.add_argument("--algo", default="pebble")
    p.add_argument("--preset", default="reduced")
    p.add_argument("--caches", nargs="+", default=["cold", "warm"], choices=["cold", "warm"])
    p.add_argument("--repeats", type=int, default=1)
    p.add_argument("--trees", nargs="+", default=["this=."], metavar="LABEL=DIR",
                   help="checkouts whose code to run, in turn (default: this one)")
    p.add_argument("--min-s", type=float, default=0.05, help="spans shorter than this: summed")
    p.add_argument("--out", type=Path, default=None)
    p.add_argument("train_args", nargs="*", help="more `hprior train` arguments (after --)")
    args = p.parse_args(argv)
    train = ["--task", args.task, "--algo", args.algo, "--preset", args.preset, "--seeds",
             "12345", "--steps", "12000", *args.train_args]
    trees = {label: Path(d).resolve() for label, d in (t.split("=", 1) for t in args.trees)}
    rows, firsts = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        for r in range(args.repeats):
            # every other repeat the other way round: neither tree always runs first
            for label, tree in list(trees.items())[::1 if r % 2 == 0 else -1]:
                for cache in args.caches:
                    name = f"{label}_{r}_{cache}"
                    first, spans = one_start(work, name, work / f"cache_{label}_{r}", train,
                                             tree)
                    firsts.setdefault((label, cache), []).append(first)
                    print(f"\n{name}: first env step at {first:.1f} s (perf/first_step_s)")
                    rows += [{"tree": label, "repeat": r, "cache": cache,
                              "first_step_s": round(first, 2), **s}
                             for s in _print_spans(spans, first, args.min_s)]
    print("\nfirst env step, s: " + "; ".join(
        f"{label} {cache}: " + ", ".join(f"{v:.1f}" for v in values)
        + f" (mean {sum(values) / len(values):.1f})" for (label, cache), values in firsts.items()))
    if args.out:
        with open(args.out, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)


if __name__ == "__main__":
    main()
