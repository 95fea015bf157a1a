"""A run directory's checkpoint back in memory, for the tools that read trained runs
(`hprior eval`, `hprior export`, `hprior attention`)."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import jax

from hprior_jax.loop.state import RunState


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
    """The checkpoint at `step` (default: the latest) of `run_dir`; `overrides` replace
    config fields that do not change the state's shapes (e.g. num_eval_episodes)."""
    from hprior_jax.checkpoint import Checkpointer
    from hprior_jax.loop.engine import Engine
    from hprior_jax.loop.host import restore_latest
    from hprior_jax.loop.run_dir import load_run_config

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
        engine = Engine(cfg)
        # the replay capacity the checkpoint was written with (a budget extended on resume
        # grew the buffer of later checkpoints only)
        capacity = ckpt.stored_shape(".replay.reward", step)[1]
        # a real initial state, not shapes: leaves a checkpoint lacks keep its values
        like = engine.init_seeds(list(cfg.seeds), capacity=capacity)
        step, state = restore_latest(ckpt, like, step)
    finally:
        ckpt.close()
    return Restored(cfg, engine, step, state)
