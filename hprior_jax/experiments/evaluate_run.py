"""`hprior eval`: a checkpoint's policy on fresh evaluation episodes, per seed, and
optionally a video of one episode per seed."""
from __future__ import annotations

import csv
from pathlib import Path

import jax
import numpy as np

from hprior_jax.loop.episodes import episode_video
from hprior_jax.runs.restore import restore_run


def evaluate_run(run_dir: Path, step: int | None = None, episodes: int = 10,
                 video: bool = False) -> tuple[list[dict], list[Path]]:
    """Rows {seed, step, episodes, true_return, true_return_std, success} (success only
    where the task defines it), written to RUN/eval_step<N>_<K>ep.csv, and the video paths
    (RUN/videos/eval_step<N>_seed<S>.mp4).

    The episodes use the evaluation keys of the run at that step, so with the run's own
    episode count they are the episodes of its eval.csv row at that step."""
    if episodes < 1:
        raise ValueError(f"--episodes must be positive, got {episodes}")
    run_dir = Path(run_dir)
    restored = restore_run(run_dir, step, num_eval_episodes=episodes)
    engine, seeds, step = restored.engine, list(restored.cfg.seeds), restored.step
    if video and not hasattr(engine.task, "mj_model"):
        raise ValueError(f"--video: task {restored.cfg.task} has no MuJoCo model to render")
    returns, successes = jax.device_get(engine.run_eval(restored.state, seeds, step))
    rows = []
    for i, seed in enumerate(seeds):
        row = dict(seed=seed, step=step, episodes=episodes,
                   true_return=float(np.mean(returns[i])),
                   true_return_std=float(np.std(returns[i])))
        if engine.task.has_success:
            row["success"] = float(np.mean(successes[i]))
        rows.append(row)
    path = run_dir / f"eval_step{step}_{episodes}ep.csv"
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]), lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
    videos = [_video(engine, restored.of_seed(s).sac.actor, s, step, run_dir)
              for s in seeds] if video else []
    return rows, videos


def _video(engine, actor_params, seed: int, step: int, run_dir: Path) -> Path:
    """RUN/videos/eval_step<N>_seed<S>.mp4: a name of its own, beside (never over) the
    step<N>_seed<S>.mp4 that training's --capture-video writes."""
    return episode_video(engine, actor_params, seed, step,
                         run_dir / "videos" / f"eval_step{step}_seed{seed}.mp4")
