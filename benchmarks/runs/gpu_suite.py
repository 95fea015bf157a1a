"""The benchmark suite for a machine with a GPU.

    python -m benchmarks.runs.gpu_suite                 # on the GPU machine: the sizes below
    python -m benchmarks.runs.gpu_suite --scale tiny    # anywhere, in a few minutes (its test)

On an H200 (2026-12-04) the parts took env 321 s, sac 71 s, world_model 263 s, reward 28 s
and, in a second lease, end_to_end 206 s: more than one 10-minute command, so run them in
parts (`--parts env`, then the updates, then end_to_end); each part writes its CSV and
suite.csv as it ends. On a machine with its own jax and no registry, `python -m
benchmarks.tooling.gpu_carry` packs what it lacks (results/runs/gpu_suite/gpu_NVIDIA_H200/).

Each part calls the single-purpose benchmark that owns the measurement, on the default JAX
device (the GPU when JAX sees one):
- `env`: MJX env steps/s of cheetah_run and quadruped_walk at batch 1k, 4k and 16k
  (`env_throughput.mjx_throughput`: a scan of vmapped steps, compile timed apart), with the
  ports' contact caps (`--env-caps task none` adds the uncapped ports);
- `sac`, `reward`, `world_model`: update times at the appendix's sizes, vmapped over 1 and 5
  seeds, beside the same update in PyTorch on CUDA when torch sees a GPU (on its CPU
  otherwise; skipped without torch);
- `end_to_end`: one 5-seed PEBBLE run of the reduced preset on cheetah_run, cut to
  `--e2e-steps` steps (20k: three feedback rounds; an `hprior train` child with an empty
  compilation cache).
`--keep DIR` keeps the end-to-end run's folder and log (a lease can end mid-run). MJX-Warp
against MJX-JAX is `benchmarks/ports/mjx_warp.py`, apart (it needs warp-lang: `gpu_carry --warp`).
The rows carry the device's name; the CSVs go to benchmarks/results/runs/gpu_suite/<device>/
(or --out), with `suite.csv` holding every part's wall seconds.
"""
from __future__ import annotations

import argparse
import re
import sys
import tempfile
import time
from pathlib import Path

import tasks  # noqa: F401  (sets XLA_FLAGS before jax is imported)
from benchmarks._timing import write_rows

RESULTS = Path(__file__).resolve().parents[1] / "results" / "runs" / "gpu_suite"
SCALES = {  # what each part measures at each scale
    # the cheapest and the most expensive DMC port; PEBBLE's first feedback rounds fall at
    # steps 10k, 14k and 18k of the reduced preset
    "full": dict(env_tasks=("cheetah_run", "quadruped_walk"), env_batches=(1024, 4096, 16384),
                 env_steps=100, env_caps=("task",), repeats=2, seeds=(1, 5), sac_updates=20,
                 reward_pairs=1024, wm_sizes=("reduced", "paper"), wm_updates=3,
                 e2e_task="cheetah_run", e2e_algo="pebble", e2e_preset="reduced", e2e_seeds=5,
                 e2e_steps=20_000, e2e_args=()),
    # every code path once, at sizes a 2-core CPU runs in about two minutes
    "tiny": dict(env_tasks=("cheetah_run",), env_batches=(2,), env_steps=5, env_caps=("task",),
                 repeats=1, seeds=(1,), sac_updates=2, reward_pairs=64, wm_sizes=("reduced",),
                 wm_updates=1, e2e_task="cheetah_run", e2e_algo="sac", e2e_preset="smoke",
                 e2e_seeds=2, e2e_steps=20,
                 e2e_args=("--num-seed-steps", "10", "--sac.batch-size", "8", "--chunk-steps",
                           "10", "--eval-every", "20", "--num-eval-episodes", "1")),
}
PARTS = ("env", "sac", "reward", "world_model", "end_to_end")


def device_name() -> str:
    import jax

    d = jax.devices()[0]
    return f"{d.platform}:{d.device_kind}"


def torch_device() -> str | None:
    """"cuda" when torch sees a GPU (made the default device), "cpu" without one, None
    without torch."""
    try:
        import torch
    except ImportError:
        return None
    device = "cuda" if torch.cuda.is_available() else "cpu"
    torch.set_default_device(device)
    return device


def env_rows(s: dict) -> list[dict]:
    """Per task, contact cap ("task": the port's default; "none": a slot for every candidate
    contact) and batch."""
    import tasks as registry

    from benchmarks.ports.env_throughput import mjx_throughput

    rows = []
    for name, cap in ((n, c) for n in s["env_tasks"] for c in s["env_caps"]):
        task = registry.make(name, **({"max_contacts": None} if cap == "none" else {}))
        for batch in s["env_batches"]:
            compile_s, run_s = mjx_throughput(task, batch, s["env_steps"], s["repeats"])
            rows.append({"task": name, "contact_cap": task.max_contacts, "batch": batch,
                         "compile_s": compile_s,
                         "env_steps_per_s": batch * s["env_steps"] / run_s})
    return rows


def update_rows(part: str, s: dict, torch_on: str | None) -> list[dict]:
    """One row per (size, seeds): JAX ms per update (all seeds), PyTorch ms for one seed."""
    from benchmarks.updates import reward_update, sac_update, world_model_update

    if part == "sac":
        sizes = list(sac_update.SIZES)
        jax_ms = lambda size, n: sac_update.jax_update_ms(size, n, s["sac_updates"], s["repeats"])
        torch_ms = lambda size: sac_update.torch_update_ms(size, s["sac_updates"], s["repeats"])
    elif part == "reward":
        sizes = list(reward_update.SIZES)
        jax_ms = lambda size, n: reward_update.jax_step_ms(size, n, s["reward_pairs"],
                                                          s["repeats"])
        torch_ms = lambda size: reward_update.torch_step_ms(size, s["reward_pairs"],
                                                            s["repeats"])
    else:
        sizes = list(s["wm_sizes"])
        jax_ms = lambda size, n: world_model_update.jax_update_ms(size, n, s["wm_updates"],
                                                                  s["repeats"])
        torch_ms = lambda size: world_model_update.torch_update_ms(size, s["wm_updates"],
                                                                   s["repeats"])
    rows = []
    for size in sizes:
        reference = torch_ms(size) if torch_on else {}
        for n in s["seeds"]:
            measured = jax_ms(size, n)
            ms = next(v for k, v in measured.items() if k.startswith("ms_per"))
            row = {"size": size, "seeds": n, "jax_ms": ms,
                   "compile_s": measured.get("compile_s", "")}
            if reference:
                torch_ms_one = next(v for k, v in reference.items() if k.startswith("ms_per"))
                row.update(torch_device=torch_on, torch_ms_one_seed=torch_ms_one,
                           speedup_per_seed=torch_ms_one * n / ms)
            rows.append(row)
    return rows


def end_to_end_rows(s: dict, device: str, keep: Path | None) -> tuple[list[dict], list[dict]]:
    """(the run's totals, its `perf/*` rows chunk by chunk). `keep`: the run's folder and log
    stay there (a lease can end mid-run) instead of in a temporary folder."""
    from benchmarks.runs.end_to_end import SEEDS, one_run, perf_rows

    if keep:
        keep.mkdir(parents=True, exist_ok=True)
    name = f"{s['e2e_algo']}_{s['e2e_seeds']}"  # the run's folder (and log) in `work`
    with tempfile.TemporaryDirectory() as work:
        work = keep or Path(work)
        row = one_run(s["e2e_task"], s["e2e_algo"], s["e2e_seeds"], s["e2e_preset"],
                      s["e2e_steps"], work, device=device, extra_args=s["e2e_args"], name=name)
        chunks = perf_rows(work / name / "metrics.jsonl", SEEDS[0])
    return [row], chunks


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scale", default="full", choices=list(SCALES))
    p.add_argument("--parts", nargs="+", default=list(PARTS), choices=list(PARTS))
    p.add_argument("--e2e-steps", type=int, default=None, help="override the scale's")
    p.add_argument("--keep", type=Path, default=None,
                   help="folder for the end-to-end run's output (default: a temporary one)")
    for key, kind in (("env_tasks", str), ("env_batches", int), ("env_steps", int),
                      ("env_caps", str)):
        p.add_argument("--" + key.replace("_", "-"), nargs="+" if key != "env_steps" else None,
                       type=kind, default=None, help="override the scale's")
    p.add_argument("--out", type=Path, default=None,
                   help="folder for the CSVs (default benchmarks/results/runs/gpu_suite/<device>)")
    args = p.parse_args(argv)
    s = dict(SCALES[args.scale])
    s.update({k: v for k, v in vars(args).items()
              if v is not None and k in s and k != "scale"})
    import jax

    device = device_name()
    on_gpu = jax.default_backend() == "gpu"
    out = args.out or RESULTS / re.sub(r"[^A-Za-z0-9_.-]+", "_", device)
    torch_on = torch_device()
    print(f"device {device}; PyTorch reference: {torch_on or 'not installed'}", flush=True)
    seconds = []
    for part in args.parts:
        t0 = time.perf_counter()
        if part == "env":
            rows = env_rows(s)
        elif part == "end_to_end":
            rows, chunks = end_to_end_rows(s, "gpu" if on_gpu else "cpu", args.keep)
            write_rows(chunks, out / "end_to_end_chunks.csv")
        else:
            rows = update_rows(part, s, torch_on)
        elapsed = time.perf_counter() - t0
        # the device's name over end_to_end's own `device` column (its cpu/gpu flag)
        write_rows([{"device": device, "scale": args.scale, **{k: v for k, v in r.items()
                                                               if k != "device"}}
                    for r in rows], out / f"{part}.csv")
        seconds.append({"device": device, "scale": args.scale, "part": part,
                        "wall_s": elapsed})
        print(f"{part}: {elapsed:.0f} s", flush=True)
        write_rows(seconds, out / "suite.csv")  # after every part: a lease can end mid-suite
    return 0


if __name__ == "__main__":
    sys.exit(main())
