"""A run directory's checkpoint back in memory, for the tools that read trained runs
(`hprior eval`, `hprior export`, `hprior attention`)."""
from __future__ import annotations

import dataclasses
import sys
from dataclasses import dataclass
from pathlib import Path

import jax

from hprior_jax.checkpoint import Checkpointer
from hprior_jax.loop.checkpoints import (CheckpointMismatch, CheckpointUnreadable, first_line,
                                        restore_latest)
from hprior_jax.loop.state import RunState
from hprior_jax.runs.build import build_engine
from hprior_jax.runs.run_dir import load_run_config


@dataclass
class Restored:
    cfg: object  # the run's RunConfig (with any overrides)
    engine: object  # an Engine built for cfg
    step: int  # the checkpoint's step
    state: RunState  # every seed, leading seed axis

    def seed_index(self, seed: int | None) -> int:
        """Position of `seed` in the run (None: the first)."""
        seeds = list(self.cfg.seeds)
        if seed is None:
            return 0
        if seed not in seeds:
            raise ValueError(f"--seed {seed} is not in this run; its seeds are {seeds}")
        return seeds.index(seed)

    def of_seed(self, seed: int | None):
        i = self.seed_index(seed)
        return jax.tree.map(lambda x: x[i], self.state)


def restore_run(run_dir: Path, step: int | None = None, **overrides) -> Restored:
    """The checkpoint at `step` (default: the newest that restores; a newer damaged one is
    named in one line on stderr and skipped) of `run_dir`; `overrides` replace config fields
    that do not change the state's shapes (e.g. num_eval_episodes)."""
    run_dir = Path(run_dir)
    cfg = dataclasses.replace(load_run_config(run_dir), **overrides)
    ckpt = Checkpointer(run_dir / "checkpoints")
    try:
        steps = sorted(ckpt.all_steps())
        if not steps:
            raise FileNotFoundError(f"{run_dir}/checkpoints holds no checkpoint yet")
        if step is not None and step not in steps:
            raise ValueError(f"--step {step}: {run_dir} keeps checkpoints at steps "
                             f"{', '.join(map(str, steps))} only")
        engine = build_engine(cfg)
        candidates = [step] if step is not None else steps[::-1]
        initial = {}  # a real initial state per replay capacity: leaves a checkpoint lacks
        for i, candidate in enumerate(candidates):
            try:
                # the capacity the checkpoint was written with (a budget extended on resume
                # grew the buffer of later checkpoints only)
                capacity = ckpt.stored_shape(".replay.reward", candidate)[1]
                if capacity not in initial:
                    initial[capacity] = engine.init_seeds(list(cfg.seeds), capacity=capacity)
                found, state = restore_latest(ckpt, initial[capacity], candidate)
                break
            except CheckpointMismatch:
                raise  # config.json changed: an older checkpoint fits no better
            except Exception as e:  # a damaged checkpoint: metadata or data
                reason = first_line(e)
                if i + 1 == len(candidates):
                    raise CheckpointUnreadable(f"the checkpoint at step {candidate} in "
                                               f"{run_dir} cannot be restored: {reason}") from e
                print(f"the checkpoint at step {candidate} cannot be restored ({reason});"
                      f" using step {candidates[i + 1]}", file=sys.stderr, flush=True)
    finally:
        ckpt.close()
    return Restored(cfg, engine, found, state)
