"""A tiny pure-JAX task (1-D point mass, no MJX) so loop tests compile in seconds."""
import jax
import jax.numpy as jnp

import tasks
from tasks.base import Task, TaskState

NAME = "toy_point"


class ToyPoint(Task):
    name = NAME
    obs_size = 2
    action_size = 1
    episode_length = 20
    control_timestep = 0.1
    has_success = True
    domain = "dm_control"

    def __init__(self, contacts: str = "floor"):
        # the DM Control physics option, which configs of runs made before it existed restore
        # as "all" (tests/fixtures/format1_prior); a point mass has no contacts to choose
        self.contacts = contacts

    def reset(self, key):
        pos = jax.random.uniform(key, (), minval=-1.0, maxval=1.0)
        data = {"pos": pos, "vel": jnp.zeros(()), "resets": jnp.ones((), jnp.int32)}
        return TaskState(data=data, obs=self._obs(data), true_reward=jnp.zeros(()),
                         success=jnp.zeros(()), terminated=jnp.zeros((), bool))

    def step(self, state, action):
        a = jnp.clip(action[0], -1.0, 1.0)
        vel = 0.9 * state.data["vel"] + 0.1 * a
        pos = state.data["pos"] + 0.1 * vel
        data = dict(state.data, pos=pos, vel=vel)
        reward = -jnp.abs(pos - 0.5)
        return state.replace(data=data, obs=self._obs(data), true_reward=reward,
                             success=(jnp.abs(pos - 0.5) < 0.05).astype(jnp.float32))

    def render_state(self, data):
        # what a person's labels record of a state (no model to render: the test answers)
        return {"qpos": data["pos"][None], "qvel": data["vel"][None]}

    @staticmethod
    def _obs(data):
        return jnp.stack([data["pos"], data["vel"]]).astype(jnp.float32)


class ToyNaN(ToyPoint):
    """Returns a NaN reward: the training loop must stop with a clear error."""

    name = "toy_nan"

    def step(self, state, action):
        state = super().step(state, action)
        return state.replace(true_reward=state.true_reward * jnp.nan)


class ToyScaled(ToyPoint):
    """ToyPoint with the true reward scaled by 3: an oracle teacher gives the same labels, so
    a PbRL run that never lets the true reward reach the agent must not change at all."""

    name = "toy_scaled"

    def step(self, state, action):
        state = super().step(state, action)
        return state.replace(true_reward=3.0 * state.true_reward)


# the model-less tasks the tests register beside the ports
TOYS = (ToyPoint, ToyNaN, ToyScaled)


def ensure_registered():
    for cls in TOYS:
        if cls.name not in tasks.names():
            tasks.register(cls.name, cls)
