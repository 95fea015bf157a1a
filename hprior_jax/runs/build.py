"""A run's engine from its config (the method's hooks from the registry), and training it."""
from __future__ import annotations

from pathlib import Path

from hprior_jax.loop import host
from hprior_jax.loop.engine import Engine
from hprior_jax.loop.state import RunState
from hprior_jax.methods import registry


def build_engine(cfg, devices=None, records_physics: bool = False) -> Engine:
    """The engine of `cfg` with its method (`cfg.algo`); see `Engine` for the options."""
    return Engine(cfg, registry.get(cfg.algo).build, devices=devices,
                  records_physics=records_physics)


def train(cfg, run_dir: Path, engine: Engine | None = None, **options) -> RunState:
    """Trains `cfg` into `run_dir` (`host.run`'s options), building its engine unless one
    built for `cfg` is given (the CLI builds it before writing anything, so configuration
    errors leave no run directory behind)."""
    return host.run(engine or build_engine(cfg), run_dir, **options)
