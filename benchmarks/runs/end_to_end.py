"""Whole training runs at a fixed small budget: env steps/s, wall time by part, peak memory.

    python -m benchmarks.runs.end_to_end [--algos pebble prior] [--seeds 1 5] [--task cheetah_run]
                                    [--preset smoke] [--steps N] [--device cpu|gpu]

Each (algorithm, seed count) is one `hprior train` in a child process with an empty
compilation cache (so compile time is real and reported apart) and `--no-progress`. Its
`metrics.jsonl` gives the wall seconds the host loop measured per part (`perf/chunk_s`: env
steps and agent updates, one fused program; `perf/event_s`: feedback rounds = teacher, reward
learning, relabelling, and for PRIOR the world model, of which `perf/world_model_s`;
`perf/eval_s`, `perf/checkpoint_s`, `perf/compile_s`); the rest of the child's wall time
(start-up, imports, building the task) is `other_s`. Peak resident memory is the child's
max RSS. `overhead_vs_pebble` = (method wall - PEBBLE wall) / method wall at the same seed
count, compile excluded, for every method run beside PEBBLE (`prior_overhead` in rows written
before 2026-12-01). `meta_step_s` is MRN's meta steps, inside `event_s` like the world model.
Writes benchmarks/results/runs/end_to_end.csv (or --out).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import tasks  # noqa: F401  (sets XLA_FLAGS before jax is imported)
from benchmarks._timing import write_rows
from hprior_jax.methods import registry

RESULTS = Path(__file__).resolve().parents[1] / "results" / "runs" / "end_to_end.csv"
PARTS = ("chunk_s", "event_s", "world_model_s", "meta_step_s", "eval_s", "checkpoint_s",
         "compile_s")
INSIDE_EVENTS = ("world_model_s", "meta_step_s")
SEEDS = (12345, 23456, 34567, 45678, 56789, 67890, 78901, 89012)


def perf_totals(metrics_file: Path, first_seed: int) -> dict:
    """Sum of every `perf/<part>` over the run (logged once per seed; read one seed)."""
    totals = defaultdict(float)
    steps = 0
    with open(metrics_file) as f:
        for line in f:
            rec = json.loads(line)
            if rec.get("seed") != first_seed:
                continue
            steps = max(steps, rec.get("step", 0))
            for part in PARTS:
                if f"perf/{part}" in rec:
                    totals[part] += float(rec[f"perf/{part}"])
    return {"steps": steps, **{p: totals[p] for p in PARTS}}


def perf_rows(metrics_file: Path, first_seed: int) -> list[dict]:
    """Every step's `perf/*` values (one seed's rows): where a run's time went, chunk by chunk."""
    rows = []
    with open(metrics_file) as f:
        for line in f:
            rec = json.loads(line)
            perf = {k.split("/", 1)[1]: v for k, v in rec.items() if k.startswith("perf/")}
            if rec.get("seed") == first_seed and perf:
                rows.append({"step": rec.get("step"), **perf})
    return rows


def first_record(metrics_file: Path, key: str) -> float:
    """The first value of `key` in the run's metrics (nan if never logged)."""
    with open(metrics_file) as f:
        for line in f:
            rec = json.loads(line)
            if key in rec:
                return float(rec[key])
    return float("nan")


def one_run(task: str, algo: str, n_seeds: int, preset: str, steps: int | None,
            work: Path, device: str = "cpu", extra_args: tuple[str, ...] = (),
            extra_env: dict | None = None, name: str | None = None,
            cache: str | None = None, tree: Path | None = None) -> dict:
    """One `hprior train` child; `extra_args` / `extra_env` go to it (e.g. `--devices 2` and
    the XLA flag that makes CPU devices), `name` labels its folder (default algo_seeds),
    `cache` its compilation cache's (default: the name, so a new name starts cold), `tree`
    the checkout whose code it runs (default: this one)."""
    name = name or f"{algo}_{n_seeds}"
    run_dir = work / name
    seeds = [str(s) for s in SEEDS[:n_seeds]]
    cmd = [sys.executable, "-m", "hprior_jax.cli", "train", "--task", task, "--algo", algo,
           "--preset", preset, "--seeds", *seeds, "--out", str(run_dir), "--no-progress",
           *extra_args]
    if steps is not None:
        cmd += ["--steps", str(steps)]
    env = dict(os.environ, HPRIOR_JAX_CACHE=str(work / f"cache_{cache or name}"),
               **(extra_env or {}))
    if device == "cpu":
        env["JAX_PLATFORMS"] = "cpu"
    log_path = work / f"{name}.log"
    t0 = time.perf_counter()
    with open(log_path, "w") as log:  # a file, not a pipe: nothing blocks while we wait4
        # `python -m` puts the working directory first on the path: the tree's code runs
        child = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT, cwd=tree)
        _, status, usage = os.wait4(child.pid, 0)  # this child's own peak RSS
    wall = time.perf_counter() - t0
    if os.waitstatus_to_exitcode(status) != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{log_path.read_text()[-4000:]}")
    peak_kb = usage.ru_maxrss  # KiB on Linux
    totals = perf_totals(run_dir / "metrics.jsonl", int(seeds[0]))
    totals["first_step_s"] = first_record(run_dir / "metrics.jsonl", "perf/first_step_s")
    measured = sum(totals[p] for p in PARTS if p not in INSIDE_EVENTS)
    return {"task": task, "algo": algo, "seeds": n_seeds, "preset": preset, "device": device,
            **totals,
            "other_s": wall - measured, "wall_s": wall,
            "env_steps_per_s": totals["steps"] * n_seeds / max(wall - totals["compile_s"], 1e-9),
            "peak_rss_gb": peak_kb / 2**20}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--task", default="cheetah_run")
    p.add_argument("--algos", nargs="+", default=["pebble", "prior"],
                   choices=registry.names())
    p.add_argument("--seeds", nargs="+", type=int, default=[1, 5])
    p.add_argument("--preset", default="smoke", choices=["smoke", "reduced", "paper"])
    p.add_argument("--steps", type=int, default=None, help="override the preset's steps")
    p.add_argument("--device", default="cpu", choices=["cpu", "gpu"],
                   help="gpu: the runs use JAX's default device (CUDA jaxlib installed)")
    p.add_argument("--out", type=Path, default=RESULTS)
    args = p.parse_args(argv)
    if any(not 1 <= s <= len(SEEDS) for s in args.seeds):
        p.error(f"--seeds counts must be between 1 and {len(SEEDS)}")

    rows = []
    with tempfile.TemporaryDirectory(prefix="hprior_e2e_") as tmp:
        for algo in args.algos:
            for n in sorted(args.seeds):
                row = one_run(args.task, algo, n, args.preset, args.steps, Path(tmp), args.device)
                rows.append(row)
                print("  ".join(f"{k}={v:.2f}" if isinstance(v, float) else f"{k}={v}"
                                for k, v in row.items()), flush=True)
    by = {(r["algo"], r["seeds"]): r for r in rows}
    for r in rows:
        peb = by.get(("pebble", r["seeds"]))
        r["overhead_vs_pebble"] = ""
        if r["algo"] != "pebble" and peb:
            own = r["wall_s"] - r["compile_s"]
            r["overhead_vs_pebble"] = round((own - peb["wall_s"] + peb["compile_s"]) / own, 3)
            print(f"{r['algo']} overhead over PEBBLE, {r['seeds']} seed(s), compile excluded: "
                  f"{100 * r['overhead_vs_pebble']:.0f}% of its wall time")
    write_rows([{k: round(v, 3) if isinstance(v, float) else v for k, v in r.items()}
                for r in rows], args.out)


if __name__ == "__main__":
    main()
