"""Envs stepped as vmapped groups in turn (tasks.batching) reach the states one vmap does, up
to float32 rounding (XLA vectorises the two layouts differently)."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tasks
from hprior_jax.envs import VecEnv
from tasks.batching import CPU_GROUP, default_group, group_size


@pytest.mark.parametrize("batch, group, expected", [
    (128, 16, 16), (50, 16, 10), (24, 16, 12), (16, 16, None), (5, 16, None),
    (17, 16, None),  # prime: groups of 1 would be slower than one vmap
    (128, None, None),
])
def test_group_size(batch, group, expected):
    assert group_size(batch, group) == expected


def test_vecenv_in_groups_steps_like_one_vmap():
    """20 cheetah envs on CPU: VecEnv steps them as 2 groups of 10; one vmap of all 20 from
    the same states with the same actions gives the same states and rewards up to rounding,
    far inside the tolerances the port keeps against dm_control over 20 steps
    (test_dm_control_tasks.py: qpos 1e-4, obs 1e-3, reward 1e-3)."""
    task = tasks.make("cheetah_run")
    assert default_group(task) == CPU_GROUP and group_size(20, CPU_GROUP) == 10  # on CPU
    env = VecEnv(task, 20)
    state = jax.jit(env.reset)(jax.random.key(0))
    actions = jax.random.uniform(jax.random.key(1), (5, 20, task.action_size), minval=-1,
                                 maxval=1)

    def rollout(step, ts):
        def body(ts, a):
            ts = step(ts, a)
            return ts, (ts.data.qpos, ts.obs, ts.true_reward)
        return jax.lax.scan(body, ts, actions)[1]

    grouped = jax.jit(lambda ts: rollout(env._step, ts))(state.task)
    flat = jax.jit(lambda ts: rollout(jax.vmap(task.step), ts))(state.task)
    # measured over these 5 steps: qpos 1e-6, obs (velocities) 1.5e-5, reward below 1e-6
    for ours, theirs, tol in zip(grouped, flat, (1e-5, 1e-4, 1e-5)):
        np.testing.assert_allclose(np.asarray(ours), np.asarray(theirs), rtol=0, atol=tol)
    assert float(jnp.abs(grouped[0][-1] - grouped[0][0]).max()) > 1e-3  # the envs moved
