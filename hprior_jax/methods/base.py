"""The hooks a method implements, and the agent steps methods compose their phases from.

The chunk engine (`hprior_jax.loop.engine`) runs env steps in compiled chunks and asks the
method, never naming it:
  phases()                    the schedule: which per-step function runs from which step
  init(key)                   the method's own state (a pytree; one per seed)
  stored_reward(rs, ...)      the reward written with each new transition
  event_steps(), run_event()  host-side events between chunks (feedback rounds, world model)
The default is SAC on the true reward. A method gets the engine's services (env sizes, the
SAC agent, ahead-of-time compilation) through a `Kit`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Protocol

import jax

from hprior_jax.agents.sac import SAC
from hprior_jax.buffers import replay
from hprior_jax.envs import VecEnv
from hprior_jax.loop.state import RunState

RANDOM, SAC_PHASE = "random", "sac"
SAC_METRICS = ("train/critic_loss", "train/q", "train/actor_loss", "train/alpha_loss",
               "train/alpha", "train/entropy")

# (rs, obs, step, keys) -> (action, rs, metrics); keys = (act, sample, update)
StepFn = Callable


@dataclass(frozen=True)
class Phase:
    name: str
    start: int  # first global step of the phase
    step: StepFn
    metrics: tuple[str, ...] = ()  # the `train/` metrics meaningful in this phase


class Kit(Protocol):
    """What the engine lends a method."""

    env: VecEnv  # the training env (obs_size, action_size, episode_length)
    sac: SAC

    def compile(self, name: str, fn, *args):
        """`fn.lower(*args).compile()` once per name, its compile time measured apart."""

    def per_seed(self, fn, in_axes=(0,), donate_argnums=(), physics_free=False):
        """`fn` of one seed as one jitted program over every seed (split over the devices):
        `in_axes[i]` is 0 for an argument with the seed axis, None for one all seeds share.
        `physics_free`: `fn` steps no MJX, so on CPU it may compile with XLA's default fusion
        emitters (`setup_jax.PHYSICS_FREE`)."""

    def place(self, tree):
        """Host arrays with a leading seed axis, split over the devices as programs expect."""

    person: object  # the human teacher the host attached (`labelling.teacher`), or None


def random_step(kit: Kit) -> StepFn:
    def step(rs: RunState, obs, t, keys):
        action = jax.random.uniform(keys[0], (kit.env.action_size,), minval=-1.0, maxval=1.0)
        return action, rs, {}

    return step


def sac_step(kit: Kit, reward_fn=None) -> StepFn:
    """BPref order: act with the current policy, update, then (the engine) steps the env.
    `reward_fn(rs, batch, t) -> (reward, rs, metrics)` replaces the buffer's reward in the
    update (PEBBLE's state-entropy pre-training; a bonus decayed with the global step `t`)."""
    def step(rs: RunState, obs, t, keys):
        action = kit.sac.act(rs.sac.actor, obs, keys[0])
        batch = replay.sample(rs.replay, keys[1], kit.sac.cfg.batch_size)
        metrics = {}
        if reward_fn is not None:
            reward, rs, metrics = reward_fn(rs, batch, t)
            batch = batch._replace(reward=reward)
        sac_state, sac_metrics = kit.sac.update(rs.sac, batch, keys[2], t)
        return action, rs.replace(sac=sac_state), {**metrics, **sac_metrics}

    return step


class Method:
    """SAC on the true reward; other methods override the hooks they change."""

    # True: a person labels (through `kit.person`): the replay buffer keeps each obs's
    # physics state for the clips, and the host checkpoints before each event (where the
    # person may stop the run)
    asks_person = False

    def __init__(self, cfg, kit: Kit):
        self.cfg, self.kit = cfg, kit

    def phases(self) -> tuple[Phase, ...]:
        return (Phase(RANDOM, 0, random_step(self.kit)),
                Phase(SAC_PHASE, self.cfg.num_seed_steps, sac_step(self.kit), SAC_METRICS))

    def init(self, key: jax.Array):
        return None

    def stored_reward(self, rs: RunState, obs, action, true_reward) -> jax.Array:
        return true_reward

    def event_steps(self) -> list[int]:
        return []

    def run_event(self, rs: RunState, step: int) -> tuple[RunState, dict]:
        """Host side: the compiled event(s) before global step `step`; (rs, metrics [S])."""
        raise NotImplementedError(f"{type(self).__name__} has no events")

    def programs(self, rs: RunState) -> list[tuple[str, object, tuple]]:
        """(name, jitted fn, example args) of the programs `run_event` will compile, in the
        order the events need them: the engine compiles them in the background while the
        run goes on (a name `run_event` does not ask for is compiled for nothing)."""
        return []
