"""The task contract every MJX port implements.

A task is a small Python object that owns a (static) `mjx.Model` and two pure functions:

    reset(key) -> TaskState
    step(state, action) -> TaskState

Both are jit- and vmap-able. A task knows nothing about batching, time limits or
auto-reset (that is `hprior_jax.envs`), and nothing about learning. The true task reward is
returned as `true_reward`; only the scripted teacher, evaluation and logging may read it.
"""
from __future__ import annotations

import abc
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct


RENDER_FIELDS = ("qpos", "qvel", "mocap_pos", "mocap_quat")  # what positions a frame


@struct.dataclass
class TaskState:
    """State of one environment after `reset` or `step`.

    data:        the MJX physics state.
    obs:         float32[obs_size] observation the agent sees.
    true_reward: float32[] reward of the transition that produced this state (0 after reset).
    success:     float32[] 1.0 if the task's success criterion holds now (0 where undefined).
    terminated:  bool[] true terminal state (no bootstrapping). None of the paper's tasks
                 terminates early; episodes end only at the time limit (a truncation).
    info:        task-specific extras (e.g. MetaWorld's previous-frame observation).
    """

    data: Any
    obs: jax.Array
    true_reward: jax.Array
    success: jax.Array
    terminated: jax.Array
    info: dict = struct.field(default_factory=dict)


class Task(abc.ABC):
    """Base class of MJX task ports. Subclasses set the class attributes and the two methods."""

    name: str = ""
    obs_size: int = 0
    action_size: int = 0
    episode_length: int = 0  # control steps per episode (the time limit)
    control_timestep: float = 0.0  # seconds of simulated time per control step
    has_success: bool = False  # MetaWorld tasks define success; DM Control tasks do not
    domain: str = ""  # "dm_control" or "metaworld": selects per-domain presets
    goal_text: str = ""  # what the true reward pays for, in one line (the labelling page's)
    # on CPU, many envs of this task step as vmapped groups of this size (tasks/batching.py);
    # None: one vmap, where groups were measured to gain nothing
    cpu_group: int | None = None

    @abc.abstractmethod
    def reset(self, key: jax.Array) -> TaskState:
        """A new episode's first state, drawn from the task's initial-state distribution."""

    @abc.abstractmethod
    def step(self, state: TaskState, action: jax.Array) -> TaskState:
        """Apply `action` (in [-1, 1]^action_size, clipped) for one control step."""

    def contacts_at_cap(self, data) -> jax.Array:
        """bool[]: MJX's contact cap may have dropped contacts in `data` (see
        `tasks.physics.contacts_at_cap`); never for a task without one."""
        return jnp.zeros((), bool)

    def render_state(self, data) -> dict[str, jax.Array]:
        """What positions a rendered frame of one environment's physics state `data`: those
        of RENDER_FIELDS the model has (cheetah has no mocap bodies), traceable (the chunk
        records them for a person's labels). Batched data goes through `render_states`."""
        return {k: getattr(data, k) for k in RENDER_FIELDS if getattr(data, k).size}

    def render_states(self, data) -> dict[str, jax.Array]:
        """`render_state` of every environment of batched `data` (each leaf with a leading
        env axis): {field: [N, ...]}. Whoever holds an env's batched state renders it through
        here: `render_state` indexes bodies (`xpos[body]`) and is written for one env's data;
        on batched data it would index the env axis instead."""
        return jax.vmap(self.render_state)(data)

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(name={self.name!r}, obs_size={self.obs_size}, "
            f"action_size={self.action_size}, episode_length={self.episode_length})"
        )


def zeros_scalar(dtype=jnp.float32) -> jax.Array:
    return jnp.zeros((), dtype)
