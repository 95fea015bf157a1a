"""Helpers every benchmark uses: best-of-N wall time, the CSV writer, FLOPs by XLA cost
analysis and the matmul rate a device sustains (the roofline an update is read against)."""
from __future__ import annotations

import csv
import math
import os
import platform
import time
from pathlib import Path
from typing import Callable


def best_seconds(run: Callable, repeats: int, wait: Callable = lambda out: out,
                 setup: Callable | None = None) -> float:
    """Best of `repeats` wall times of `run()`; `wait(out)` blocks until an asynchronous result
    is ready (jax.block_until_ready), so dispatch is not mistaken for work. With `setup`, each
    call is `run(setup())` and `setup` runs outside the timer (e.g. a fresh copy of an input
    the program donates)."""
    best = math.inf
    for _ in range(repeats):
        args = () if setup is None else (setup(),)
        t0 = time.perf_counter()
        wait(run(*args))
        best = min(best, time.perf_counter() - t0)
    return best


def torch_wait(out=None):
    """Waits for the PyTorch work queued on the default device (CUDA runs asynchronously, so
    a timer must stop after it, as `jax.block_until_ready` does for JAX). A no-op on CPU."""
    import torch

    if torch.get_default_device().type == "cuda":
        torch.cuda.synchronize()
    return out


def write_rows(rows: list[dict], path: Path, keep: list[dict] = ()) -> None:
    """Write `keep` (rows read earlier, e.g. by `read_rows` for --append) then `rows`."""
    rows = [*keep, *rows]
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        columns = list(dict.fromkeys(k for row in rows for k in row))  # kept rows may lack new ones
        writer = csv.DictWriter(f, fieldnames=columns, restval="")
        writer.writeheader()
        writer.writerows(rows)
    print(f"wrote {path}")


def read_rows(path: Path) -> list[dict]:
    """The rows of an earlier CSV ([] if there is none)."""
    if not path.exists():
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def available_memory_gib() -> float | None:
    """MemAvailable of /proc/meminfo in GiB (Linux), None elsewhere."""
    try:
        with open("/proc/meminfo") as f:
            kb = next(int(line.split()[1]) for line in f if line.startswith("MemAvailable:"))
    except (OSError, StopIteration):
        return None
    return kb / 2**20


def xla_gflop(fn, *args) -> float:
    """GFLOPs of one call `fn(*args)` by XLA's cost analysis of the compiled program.
    The analysis counts the body of a loop (lax.scan, nn.scan, while) once, not once per
    iteration: pass a loop-free function (unrolled), or the count is too low."""
    cost = fn.lower(*args).compile().cost_analysis()
    cost = cost[0] if isinstance(cost, list) else cost
    return cost["flops"] / 1e9


def matmul_gflops_s(repeats: int, n: int = 2048) -> float:
    """What this device sustains on large float32 matmuls: the ceiling for an update whose
    FLOPs are almost all dense layers."""
    import jax

    x = jax.random.normal(jax.random.key(0), (n, n))
    f = jax.jit(lambda a: (a @ a) @ a)
    jax.block_until_ready(f(x))
    best = best_seconds(lambda: f(x), repeats, jax.block_until_ready)
    return 2 * 2 * n**3 / best / 1e9


def select_device(name: str) -> None:
    """`--device cpu|gpu` for the JAX side (call before any JAX computation)."""
    import jax

    if name == "cpu":
        jax.config.update("jax_platforms", "cpu")
    elif not [d for d in jax.devices() if d.platform == "gpu"]:
        raise SystemExit('--device gpu: JAX sees no GPU; install CUDA jaxlib with '
                         'pip install -e ".[cuda]" -c requirements.lock')


def torch_reference(parser, measure: Callable, *args):
    """`measure(*args)` of a PyTorch reference, or stop with the command that installs it."""
    try:
        return measure(*args)
    except ImportError:
        parser.error('PyTorch is not installed: pip install -e ".[bench]" -c requirements.lock '
                     "(or pass --no-torch)")


def roofline(gflop: float, jax_ms: float, torch_ms: float | None, matmul_gflops: float) -> dict:
    """CSV columns: work per update and the rate each side reaches against the matmul ceiling."""
    return {"gflop_per_update": round(gflop, 2), "jax_gflops_s": round(gflop / jax_ms * 1e3, 1),
            "torch_gflops_s": round(gflop / torch_ms * 1e3, 1) if torch_ms else "",
            "matmul_gflops_s": round(matmul_gflops, 1)}


def against_torch(jax_ms: float, n_seeds: int, compile_s: float, torch_ms: float | None,
                  gflop: float, matmul_gflops: float) -> dict:
    """CSV columns of a JAX update (all `n_seeds` vmapped) next to one PyTorch seed:
    times, `speedup` = PyTorch ms / JAX ms per seed (> 1: JAX faster), and the roofline."""
    per_seed = jax_ms / n_seeds
    return {"jax_ms_per_update": round(jax_ms, 2), "jax_ms_per_seed": round(per_seed, 2),
            "jax_compile_s": round(compile_s, 1),
            "torch_ms_per_seed": round(torch_ms, 2) if torch_ms else "",
            "speedup": round(torch_ms / per_seed, 2) if torch_ms else "",
            **roofline(gflop, per_seed, torch_ms, matmul_gflops)}


def machine() -> str:
    return f"{platform.machine()} {os.cpu_count()} cpus"
