"""`hprior eval`: a checkpoint's policy on fresh evaluation episodes, per seed, and
optionally a video of one episode per seed."""
from __future__ import annotations

import csv
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from hprior_jax.loop.engine import eval_key
from hprior_jax.render import render_frames, write_video
from hprior_jax.runs.restore import restore_run


def evaluate_run(run_dir: Path, step: int | None = None, episodes: int = 10,
                 video: bool = False) -> tuple[list[dict], list[Path]]:
    """Rows {seed, step, episodes, true_return, true_return_std, success} (success only
    where the task defines it), written to RUN/eval_step<N>_<K>ep.csv, and the video paths.

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


def episode_states(engine, actor_params, keys: jax.Array,
                   deterministic: bool = True) -> dict[str, np.ndarray]:
    """Whole episodes' physics states [N, T + 1, ...] (the first after reset), one per key
    in `keys` [N, 2], with the deterministic (tanh of the mean) or the sampling policy."""
    env = engine.env  # one env, with the run's task options

    def snapshot(state):
        return {k: v[0] for k, v in env.task.render_state(state.task.data).items()}

    def one(key):
        def body(state, t):
            action = engine.sac.act(actor_params, state.task.obs, jax.random.fold_in(key, t),
                                    deterministic=deterministic)
            state, _ = env.advance(state, action, t)
            return state, snapshot(state)

        first = env.reset(key)
        _, rest = jax.lax.scan(body, first, jnp.arange(env.episode_length))
        return jax.tree.map(lambda a, b: jnp.concatenate([a[None], b]), snapshot(first), rest)

    # at the run's XLA level: another level rounds differently and drifts from its episodes
    return jax.device_get(jax.jit(jax.vmap(one),
                                  compiler_options=engine.compiler_options or None)(keys))


def _video(engine, actor_params, seed: int, step: int, run_dir: Path) -> Path:

    key = eval_key(seed, step)
    states = jax.tree.map(lambda x: x[0], episode_states(engine, actor_params, key[None]))
    frames = render_frames(engine.task.mj_model, states)
    return write_video(frames, run_dir / "videos" / f"step{step}_seed{seed}.mp4",
                       fps=1.0 / engine.task.control_timestep)
