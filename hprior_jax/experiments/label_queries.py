"""Queries from a trained run: segment pairs cut from fresh episodes of its policy."""
from __future__ import annotations

from pathlib import Path

import jax
import numpy as np

from hprior_jax.labelling.store import write_queries
from hprior_jax.loop.episodes import episode_states
from hprior_jax.runs.restore import restore_run


def queries_from_run(run_dir: Path, out: Path, pairs: int = 10, segment_len: int = 50,
                     seed: int | None = None, round_: int = 1, sample: bool = True) -> list[str]:
    """Writes `pairs` queries into the query folder `out`: each pair two segments of
    `segment_len` steps from two episodes of seed `seed`'s policy (sampling actions unless
    `sample` is False), at independent random starts. Returns the query ids."""
    if pairs < 1:
        raise ValueError(f"--pairs must be positive, got {pairs}")
    restored = restore_run(run_dir)
    engine = restored.engine
    if not hasattr(engine.task, "mj_model"):
        raise ValueError(f"task {restored.cfg.task} has no MuJoCo model to render")
    length = engine.env.episode_length
    if not 1 <= segment_len <= length:
        raise ValueError(f"--segment-len {segment_len}: choose 1..{length} (the episode)")
    seed = restored.cfg.seeds[0] if seed is None else seed
    actor = restored.of_seed(seed).sac.actor
    keys = jax.random.split(jax.random.PRNGKey(seed + 0x1AB), 2 * pairs)
    episodes = episode_states(engine, actor, keys, deterministic=not sample)
    starts = np.random.default_rng(seed).integers(0, length + 1 - segment_len, 2 * pairs)
    cut = [{k: v[e, s:s + segment_len] for k, v in episodes.items()}
           for e, s in enumerate(starts)]
    fps = 1.0 / engine.task.control_timestep
    return write_queries(out, restored.cfg.task, round_, list(zip(cut[::2], cut[1::2])), fps)
