"""Batched environments over the `tasks` registry: the only importer of `tasks`.

Episodes are synchronous: every task here ends only at its time limit (DM Control and
MetaWorld never terminate early), all environments start together, so every environment is
at the same step `t` of its episode. The caller passes `t` (a host-side counter, unbatched
even when seeds are vmapped), and the auto-reset is a real `lax.cond` on `t`, not a select:
under vmap a select would evaluate a full reset (200 physics steps for cheetah) on every
step.
"""
from __future__ import annotations

import dataclasses
from typing import Callable

import jax
import jax.numpy as jnp
from flax import struct

import tasks
from tasks import Task, TaskState
from tasks.batching import default_group, vmap_in_groups


@struct.dataclass
class EnvState:
    task: TaskState  # leaves batched over envs [N, ...]
    episode_return: jax.Array  # [N] true return of the running episode
    episode_success: jax.Array  # [N] 1 if success held at any step so far (BPref convention)


@struct.dataclass
class Transition:
    obs: jax.Array  # [N, obs]
    action: jax.Array  # [N, act]
    next_obs: jax.Array  # [N, obs] observation after the action (before any auto-reset)
    true_reward: jax.Array  # [N]
    terminated: jax.Array  # [N] bool, true terminal state: no bootstrapping
    truncated: jax.Array  # [N] bool, time limit: bootstrap through it
    success: jax.Array  # [N] success at next_obs
    episode_return: jax.Array  # [N] true return of the episode this step belongs to (so far)
    episode_success: jax.Array  # [N] any-step success of the episode so far


class VecEnv:
    """`num_envs` copies of a task stepped with vmap, with time limit and auto-reset. On CPU
    more envs than the task's `cpu_group` (DM Control: 16) step as vmapped groups of 8-16 in
    turn (`tasks.batching`: the same states up to rounding, 1.7-3.6x the env steps/s of one
    vmap at 128 envs)."""

    def __init__(self, task: Task, num_envs: int):
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        if getattr(task, "terminates_early", False):
            raise NotImplementedError(
                f"{task.name} can terminate before its time limit; VecEnv resets all envs "
                "together at the time limit and does not support early termination yet")
        self.task = task
        self.num_envs = num_envs
        self.obs_size = task.obs_size
        self.action_size = task.action_size
        self.episode_length = task.episode_length
        self._reset = jax.vmap(task.reset)
        self._step = vmap_in_groups(task.step, default_group(task))

    def reset(self, key: jax.Array) -> EnvState:
        return self.reset_many(key)

    def reset_many(self, keys: jax.Array) -> EnvState:
        """`reset` of every key in `keys` (typed keys [...], or raw ones [..., 2]): an
        EnvState [..., num_envs, ...], made by one vmap of the task's reset over all of them.
        Each batching level re-walks the reset's trace (cheetah: 2.9 s to lower one level,
        6.0 s three nested)."""
        typed = jax.dtypes.issubdtype(keys.dtype, jax.dtypes.prng_key)
        tail = () if typed else keys.shape[-1:]  # a raw key's own axis
        lead, n = keys.shape[:keys.ndim - len(tail)], self.num_envs
        env_keys = jax.vmap(lambda k: jax.random.split(k, n))(keys.reshape((-1,) + tail))
        ts = self._reset(env_keys.reshape((-1,) + tail))
        ts = jax.tree.map(lambda x: x.reshape(lead + (n,) + x.shape[1:]), ts)
        zeros = jnp.zeros(lead + (n,), jnp.float32)
        return EnvState(task=ts, episode_return=zeros, episode_success=ts.success)

    def advance(self, state: EnvState, action: jax.Array, t: jax.Array):
        """Step every env without auto-reset; `t` is the shared index of this step within
        the episode. Returns the running state and the transition."""
        ts = self._step(state.task, action)
        ep_return = state.episode_return + ts.true_reward
        ep_success = jnp.maximum(state.episode_success, ts.success)
        truncated = jnp.broadcast_to((t + 1) % self.episode_length == 0, (self.num_envs,))
        transition = Transition(
            obs=state.task.obs, action=action, next_obs=ts.obs, true_reward=ts.true_reward,
            terminated=ts.terminated, truncated=truncated, success=ts.success,
            episode_return=ep_return, episode_success=ep_success)
        return EnvState(task=ts, episode_return=ep_return, episode_success=ep_success), transition

    def step(self, state: EnvState, action: jax.Array, t: jax.Array, key: jax.Array):
        """`advance`, then a reset of every env if the episode just hit its time limit."""
        return self.step_or_start(state, action, t, lambda: self.reset(key))

    def step_or_start(self, state: EnvState, action: jax.Array, t: jax.Array,
                      start: Callable[[], EnvState]):
        """`advance`, then the state `start()` gives (a new episode's first, made by
        `reset`) if the episode just hit its time limit."""
        running, transition = self.advance(state, action, t)
        next_state = jax.lax.cond((t + 1) % self.episode_length == 0, start, lambda: running)
        return next_state, transition


def make_env(task_name: str, num_envs: int = 1, **task_options) -> VecEnv:
    return VecEnv(tasks.make(task_name, **task_options), num_envs)


@dataclasses.dataclass(frozen=True)
class PhysicsOption:
    """A run-config field that picks a port's physics, meaningful in some domains only."""

    domains: tuple[str, ...]
    default: str  # the ports' default build (what `tasks.make(name)` caches)
    before: str  # what runs written before the option existed were trained on
    port_options: Callable[[str], dict]  # a non-default value -> the port's keyword options
    refusal: str  # why another domain refuses a non-default value ({name}, {value}, {task})
    # whether a task of those domains offers a non-default value (None: every one does)
    offered: Callable[[str, str], bool] | None = None


PHYSICS_OPTIONS = {
    "contacts": PhysicsOption(
        ("dm_control",), "floor", "all", lambda value: {"contacts": value},
        "--{name} {value}: only the DM Control ports have self-collision pairs to keep "
        "({task} has explicit pairs)"),
    "contact_cap": PhysicsOption(
        ("dm_control", "metaworld"), "task", "none", lambda value: {"max_contacts": None},
        "--{name} {value}: only the DM Control and MetaWorld ports cap their MJX contacts"),
    # `free`: the free-hand ports' scene as it was, with the wrist box on every task
    "hand": PhysicsOption(
        ("metaworld",), "arm", "free", lambda value: {"arm": False, "wrist": "box"},
        "--{name} {value}: only the MetaWorld ports have a Sawyer hand"),
    "wrist": PhysicsOption(
        ("metaworld",), "task", "task", lambda value: {"wrist": value},
        "--{name} {value}: only a MetaWorld port whose registered wrist is not the box offers "
        "it (button_press); {task}'s wrist is its registered one",
        offered=lambda task, value: value in getattr(tasks.task_class(task), "wrist_caps", {})),
}


def option_applies(name: str, task: str, value: str) -> bool:
    """Whether task `task` offers value `value` of physics option `name`."""
    option = PHYSICS_OPTIONS[name]
    return value == option.default or (
        task_info(task).domain in option.domains
        and (option.offered is None or option.offered(task, value)))


def task_options(cfg) -> dict:
    """The port options a run configuration asks for beyond the ports' defaults (so the
    default build is the one `tasks.make(name)` caches): `contacts="all"` on DM Control,
    `arm=False` (`hand="free"`) and `wrist="box"` on MetaWorld, `max_contacts=None`
    (`contact_cap="none"`) on both."""
    options = {}
    for name, option in PHYSICS_OPTIONS.items():
        value = getattr(cfg, name)
        if value == option.default:
            continue
        if not option_applies(name, cfg.task, value):
            raise ValueError(option.refusal.format(name=name, value=value, task=cfg.task))
        options.update(option.port_options(value))
    return options


def task_names() -> list[str]:
    return tasks.names()


def get_task(task_name: str) -> Task:
    return tasks.make(task_name)


def task_info(task_name: str) -> tasks.TaskInfo:
    """Domain, episode length, success flag: no model is built."""
    return tasks.info(task_name)


def task_goal(task_name: str) -> str:
    """What the task's true reward pays for, in one line ("" where the task says nothing):
    no model is built."""
    return tasks.task_class(task_name).goal_text
