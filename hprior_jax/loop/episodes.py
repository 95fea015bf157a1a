"""Whole episodes of a run's policy as physics states (what a frame is rendered from), and
the short videos a run writes at its evaluations (`--capture-video`)."""
from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from hprior_jax.loop.engine import Engine, eval_key
from hprior_jax.render import render_frames, write_video


def episode_states(engine: Engine, actor_params, keys: jax.Array,
                   deterministic: bool = True) -> dict[str, np.ndarray]:
    """Whole episodes' physics states [N, T + 1, ...] (the first after reset), one per key
    in `keys` [N, 2], with the deterministic (tanh of the mean) or the sampling policy."""
    name, fn = _program(engine, len(keys), deterministic)
    return jax.device_get(engine.compile(name, fn, actor_params, keys)(actor_params, keys))


def recorder_program(engine: Engine, actors) -> tuple[str, object, tuple]:
    """(name, program, argument shapes) of what `episode_video` runs (one seed's episode),
    for the background compile queue (`Engine.compile_run_ahead`), so a run's first
    `--capture-video` clip does not wait for it; `actors`: the run's actor parameters, with
    their seed axis."""
    one_seed = jax.tree.map(lambda x: jax.ShapeDtypeStruct(np.shape(x)[1:], x.dtype), actors)
    keys = jax.ShapeDtypeStruct((1, 2), np.uint32)  # eval_key(seed, step)[None]
    name, fn = _program(engine, 1)
    return name, fn, (one_seed, keys)


def _program(engine: Engine, episodes: int, deterministic: bool = True):
    """-> (its name, the jitted program of `episodes` whole episodes, one per key)."""
    env = engine.env  # one env, with the run's task options

    def snapshot(state):
        return {k: v[0] for k, v in env.task.render_states(state.task.data).items()}

    def one(params, key):
        def body(state, t):
            action = engine.sac.act(params, state.task.obs, jax.random.fold_in(key, t),
                                    deterministic=deterministic)
            state, _ = env.advance(state, action, t)
            return state, snapshot(state)

        first = env.reset(key)
        _, rest = jax.lax.scan(body, first, jnp.arange(env.episode_length))
        return jax.tree.map(lambda a, b: jnp.concatenate([a[None], b]), snapshot(first), rest)

    # at the run's XLA level: another level rounds differently and drifts from its episodes
    fn = jax.jit(jax.vmap(one, in_axes=(None, 0)),
                 compiler_options=engine.compiler_options or None)
    return f"episode_states/{'deterministic' if deterministic else 'sampled'}/{episodes}", fn


def episode_video(engine: Engine, actor_params, seed: int, step: int, path: Path,
                  max_steps: int | None = None) -> Path:
    """An MP4 at real time of the first evaluation episode of `seed` at `step` (the first
    `max_steps` env steps of it; None: all)."""
    key = eval_key(seed, step)
    states = jax.tree.map(lambda x: x[0], episode_states(engine, actor_params, key[None]))
    if max_steps is not None:
        states = {k: v[:max_steps + 1] for k, v in states.items()}
    frames = render_frames(engine.task.mj_model, states)
    return write_video(frames, path, fps=1.0 / engine.task.control_timestep)
