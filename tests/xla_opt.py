"""The suite's XLA optimisation level, set before jax is imported (conftest imports this first).

The suite's programs are small and compile-bound: LLVM at -O0 halves its time (a PRIOR loop
test 82 -> 30 s, the fast suite 1247 -> ~500 s on 2 cores, 2026-12-03), and CI has 25
minutes. Runs, benchmarks and CI's first command compile as usual. A test whose claim is
that two programs compute the same bit for bit compiles them as runs do (`AS_RUNS`): -O0
rounds differently across differently built programs. HPRIOR_TESTS_OPTIMIZED=1 compiles the
whole suite as runs do.
"""
import os

FLAG = "--xla_backend_optimization_level=0"
# jax.jit(..., compiler_options=AS_RUNS): XLA's default level, whatever XLA_FLAGS says. Runs
# of a task with its own level (`--compile-level task`: 1 on cheetah_run and quadruped_walk)
# compile at that one; the tests that use AS_RUNS passed with level 1 here too (2026-12-04,
# test_prior_loss and test_world_model)
AS_RUNS = {"xla_backend_optimization_level": 3}

if os.environ.get("HPRIOR_TESTS_OPTIMIZED") != "1" and \
        "xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + FLAG).strip()


def env_as_runs(env: dict) -> dict:
    """`env` for a subprocess that compiles as runs do (the suite's -O0 removed)."""
    env = dict(env)
    env["XLA_FLAGS"] = " ".join(f for f in env.get("XLA_FLAGS", "").split() if f != FLAG)
    return env
