import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hprior_jax.envs import VecEnv, make_env
from hprior_jax.evaluate import evaluate_policy
from tests.toy_task import ToyPoint


def _rollout(env, steps, key=jax.random.PRNGKey(0)):
    state = env.reset(key)

    def body(state, t):
        action = jnp.full((env.num_envs, 1), 0.5)
        state, tr = env.step(state, action, t, jax.random.fold_in(key, t))
        return state, (tr, state)

    return jax.jit(lambda s: jax.lax.scan(body, s, jnp.arange(steps)))(state)


def test_time_limit_truncates_and_auto_resets():
    env = VecEnv(ToyPoint(), num_envs=3)
    L = env.episode_length
    _, (tr, states) = _rollout(env, 2 * L)
    truncated = np.asarray(tr.truncated)
    assert truncated.shape == (2 * L, 3)
    # truncation exactly at the last step of each episode, never termination
    expect = np.zeros(2 * L, bool)
    expect[[L - 1, 2 * L - 1]] = True
    np.testing.assert_array_equal(truncated[:, 0], expect)
    assert not np.asarray(tr.terminated).any()
    # next_obs of the last step is the final observation, while the state holds a new reset
    last_next_obs = np.asarray(tr.next_obs[L - 1])
    reset_obs = np.asarray(states.task.obs[L - 1])
    assert not np.allclose(last_next_obs, reset_obs)
    np.testing.assert_allclose(reset_obs[:, 1], 0.0)  # fresh episode: zero velocity
    # the obs of the transition after the reset is the reset observation
    np.testing.assert_allclose(np.asarray(tr.obs[L]), reset_obs)


def test_episode_statistics_accumulate_and_restart():
    env = VecEnv(ToyPoint(), num_envs=2)
    L = env.episode_length
    _, (tr, states) = _rollout(env, 2 * L)
    r = np.asarray(tr.true_reward)
    np.testing.assert_allclose(np.asarray(tr.episode_return[L - 1]), r[:L].sum(0), rtol=1e-5)
    np.testing.assert_allclose(np.asarray(tr.episode_return[2 * L - 1]), r[L:].sum(0),
                               rtol=1e-5)
    np.testing.assert_allclose(np.asarray(states.episode_return[L - 1]), 0.0)
    # any-step success is the running max of per-step success
    np.testing.assert_array_equal(np.asarray(tr.episode_success[L - 1]),
                                  np.asarray(tr.success[:L]).max(0))


def test_reset_is_a_branch_not_a_select_under_vmap():
    """Under vmap over seeds with an unbatched step index, the reset must only run at the
    time limit: the toy task counts resets in its data."""
    env = VecEnv(ToyPoint(), num_envs=1)

    def rollout(key):
        state = env.reset(key)

        def body(state, t):
            state, _ = env.step(state, jnp.zeros((1, 1)), t, key)
            return state, state.task.data["resets"]

        return jax.lax.scan(body, state, jnp.arange(5))[1]

    resets = jax.jit(jax.vmap(rollout))(jax.random.split(jax.random.PRNGKey(1), 4))
    np.testing.assert_array_equal(np.asarray(resets), 1)  # never re-reset mid-episode
    hlo = jax.jit(jax.vmap(rollout)).lower(jax.random.split(jax.random.PRNGKey(1), 4)).as_text()
    assert "conditional" in hlo or "case" in hlo


def test_evaluate_policy_returns_whole_episode_returns():
    env = VecEnv(ToyPoint(), num_envs=4)
    policy = lambda obs: jnp.full((obs.shape[0], 1), 0.5)  # the action _rollout takes
    returns, success = jax.jit(lambda k: evaluate_policy(env, policy, k))(jax.random.PRNGKey(3))
    _, (tr, _) = _rollout(env, env.episode_length, jax.random.PRNGKey(3))
    np.testing.assert_allclose(np.asarray(returns), np.asarray(tr.episode_return[-1]), rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(success), np.asarray(tr.episode_success[-1]))


def test_make_env_unknown_task_names_the_available_ones():
    with pytest.raises(ValueError, match="available tasks:.*cheetah_run"):
        make_env("cheetah_walk")
    with pytest.raises(ValueError, match="num_envs"):
        VecEnv(ToyPoint(), num_envs=0)


@pytest.mark.parametrize("name", ["toy_point", "cheetah_run", "drawer_open"])
def test_task_info_matches_the_built_task(name):
    """Presets read a task's domain and episode length without building it: those must be
    what the built task says."""
    import tasks

    info, task = tasks.info(name), tasks.make(name)
    assert (info.domain, info.episode_length, info.has_success) == (
        task.domain, task.episode_length, task.has_success)
