"""One place for JAX process settings (compilation cache)."""
from __future__ import annotations

import os
from pathlib import Path

import jax

from tasks._xla_flags import FLAG as FUSION_FLAG

# programs that compile in less time are not written to the cache (a test lowers it)
MIN_COMPILE_SECS = 1.0
DEFAULT_CACHE = Path(os.environ.get("HPRIOR_JAX_CACHE", Path.home() / ".cache" / "hprior_jax" / "xla"))


def enable_compilation_cache(path: str | os.PathLike | None = None) -> Path:
    """Persistent XLA compilation cache: MJX + SAC programs take 10-60 s to compile on CPU,
    and the cache makes the second run of the same shapes start in seconds."""
    cache = Path(path) if path is not None else DEFAULT_CACHE
    cache.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(cache))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_SECS)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return cache


LEVEL_OPTION = "xla_backend_optimization_level"
# XLA's default CPU emitters for a program without physics: MJX needs them off
# (tasks/_xla_flags.py sets that for the whole process), other programs need not
PHYSICS_FREE = {"xla_cpu_use_fusion_emitters": True}


def compiler_options(compile_level: str, task_level: int | None) -> dict:
    """XLA options of a run's programs for `--compile-level` (RunConfig.compile_level):
    "task" the task's level (`tasks.TaskInfo.compile_level`) on CPU unless XLA_FLAGS names one
    (the test suite's -O0, a user's choice), "xla" none (XLA's own level or XLA_FLAGS'), "0"-"3"
    that level whatever XLA_FLAGS says."""
    if compile_level == "xla":
        return {}
    if compile_level == "task":
        # the tasks' levels were measured on CPU; on a GPU "task" keeps XLA's own
        if (task_level is None or LEVEL_OPTION in os.environ.get("XLA_FLAGS", "")
                or jax.default_backend() != "cpu"):
            return {}
        return {LEVEL_OPTION: task_level}
    return {LEVEL_OPTION: int(compile_level)}


def program_options(options: dict, physics_free: bool) -> dict:
    """A program's XLA options: the run's `options`, plus XLA's default fusion emitters on CPU
    for a program that steps no MJX (the world-model update: 1.12-1.17x faster, outputs
    within 2e-6; `python -m benchmarks.updates.fusion_emitters`)."""
    # only where the process turned them off (jaxlibs from 0.11 have no such flag)
    if (physics_free and jax.default_backend() == "cpu"
            and FUSION_FLAG in os.environ.get("XLA_FLAGS", "")):
        return {**options, **PHYSICS_FREE}
    return options
