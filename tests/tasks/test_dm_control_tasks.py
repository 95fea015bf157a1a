"""DM Control MJX ports (cheetah_run, walker_walk, quadruped_walk) against dm_control.

Fast tests compile two physics programs per task (a vmapped reset and one
jit(vmap(scan(step))) rollout shared by the shape and parity tests); `-m slow` adds MJX
forward parity on dm_control states, reset-observation parity and longer horizons.
Tolerances are float32 MJX vs float64 MuJoCo (helpers: tasks/dm_control/reference.py;
numbers: docs/ports/dm_control.md; in float64 MJX the quadruped stays within 1e-7 of
dm_control's qpos over 100 steps).
"""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tasks
from tasks.dm_control import reference as parity
from tasks.dm_control.reference import ports
from tasks.physics import mjx

B, T = 2, 20  # shared rollout shape: one compile per task

# Tolerances (float32 MJX vs float64 C): the first, or a port's own wider one. Quadruped's
# observation contains arcsinh(contact force) and the accelerometer, which amplify solver
# round-off.
SAME_STATE_OBS_TOL = (1e-4, {"quadruped_walk": 5e-3})
RESET_OBS_TOL = (1e-4, {"quadruped_walk": 5e-3})
TRAJ20_QPOS_TOL = (1e-4, {"walker_walk": 1e-3, "quadruped_walk": 1e-3})
TRAJ20_OBS_TOL = (1e-3, {"walker_walk": 5e-3, "quadruped_walk": 0.05})
TRAJ20_REWARD_TOL = 1e-3


def tol(tolerances, name: str) -> float:
    default, wider = tolerances
    return wider.get(name, default)


class Bundle:
    def __init__(self, name):
        self.name = name
        self.task = tasks.make(name)
        self.reset = jax.jit(jax.vmap(self.task.reset))
        self.rollout = parity.make_rollout(self.task)


# quadruped's rollout compiles for ~2 min on 2 cores: `-m slow` (its reset height stays fast)
@pytest.fixture(scope="module", params=[
    t if t != "quadruped_walk" else pytest.param(t, marks=pytest.mark.slow) for t in ports()])
def bundle(request):
    return Bundle(request.param)


def test_registry_and_attributes(bundle):
    task = bundle.task
    assert type(task).name == bundle.name and task.goal_text
    env = parity.reference_env(bundle.name, 0)
    assert task.action_size == env.action_spec().shape[0]
    assert task.obs_size == parity.flatten_obs(env.reset().observation).size
    assert task.control_timestep == pytest.approx(env.control_timestep())
    # dm_control's episode: its time limit over its control timestep
    assert task.episode_length == tasks.info(bundle.name).episode_length == round(env._step_limit)


def test_reset_and_step_under_jit_and_vmap(bundle):
    task = bundle.task
    states = bundle.reset(jax.random.split(jax.random.key(0), B))
    assert states.obs.shape == (B, task.obs_size) and states.obs.dtype == jnp.float32
    assert np.isfinite(np.asarray(states.obs)).all()
    # different keys give different initial states
    assert not np.allclose(states.data.qpos[0], states.data.qpos[1])
    actions = jax.random.uniform(jax.random.key(1), (B, T, task.action_size), minval=-1, maxval=1)
    obs, rew, qpos = bundle.rollout(states, actions)
    assert obs.shape == (B, T, task.obs_size) and rew.shape == (B, T)
    assert qpos.shape == (B, T, task.mj_model.nq)
    assert np.isfinite(np.asarray(obs)).all() and np.isfinite(np.asarray(rew)).all()
    assert (np.asarray(rew) >= 0).all() and (np.asarray(rew) <= 1).all()
    assert not np.allclose(qpos[:, -1], states.data.qpos)  # the physics moved


def test_same_state_obs_and_reward_parity(bundle):
    """Our observation and reward functions on dm_control's own MjData (reset state and 9
    states along a random trajectory) give dm_control's observation and reward."""
    obs_err, rew_err = parity.obs_reward_check(bundle.task, bundle.name, n_states=10)
    assert obs_err < 1e-5
    assert rew_err < 1e-6


def test_action_sequence_parity_20_steps(bundle):
    out, _ = parity.trajectory_check(bundle.task, bundle.name, n_episodes=B, horizon=T,
                                     rollout=bundle.rollout)
    m = out[T]
    assert m["qpos_max_abs"] < tol(TRAJ20_QPOS_TOL, bundle.name), m
    assert m["obs_max_abs"] < tol(TRAJ20_OBS_TOL, bundle.name), m
    assert m["reward_max_abs"] < TRAJ20_REWARD_TOL, m
    assert m["return_diff_max_abs"] < T * TRAJ20_REWARD_TOL, m


def test_quadruped_reset_height_matches_dm_control_search():
    """Closed-form reset height == dm_control's 1 cm contact search, and at that height no
    geom is below the floor while the lowest one is within one 1 cm step of it."""
    task = tasks.make("quadruped_walk")
    mismatches, max_err = parity.quadruped_height_check(task, n=100)
    assert mismatches == 0, max_err
    assert max_err < 1e-6

    def gap(q):  # lowest point over body geoms at the reset pose
        z = task.non_contacting_height(q)
        data = mjx.make_data(task.model)
        qpos = data.qpos.at[0:3].set(jnp.stack([0.0, 0.0, z])).at[3:7].set(q)
        return -task._floor_penetration(mjx.kinematics(task.model, data.replace(qpos=qpos)))

    quats = jax.random.normal(jax.random.key(3), (16, 4))
    quats = quats / jnp.linalg.norm(quats, axis=1, keepdims=True)
    gaps = np.asarray(jax.jit(jax.vmap(gap))(quats))
    assert (gaps > 0).all() and (gaps <= 0.01 + 1e-6).all(), gaps


# -- slow: MJX forward on dm_control states, longer horizons ------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("name", ports())
def test_same_state_mjx_forward_parity(name):
    """C mj_forward and mjx.forward on the same (qpos, qvel, act, ctrl): all sensors."""
    obs_err, rew_err, per_dim = parity.same_state_check(tasks.make(name), name, n_states=6)
    assert obs_err < tol(SAME_STATE_OBS_TOL, name), per_dim
    assert rew_err < 1e-5


@pytest.mark.slow
@pytest.mark.parametrize("name", ports())
def test_reset_observation_parity(name):
    """dm_control's reset state through our actuation-free reset forward."""
    assert parity.reset_check(tasks.make(name), name, seeds=range(2)) < tol(RESET_OBS_TOL, name)


@pytest.mark.slow
@pytest.mark.parametrize("name", ports())
def test_trajectory_parity_100_steps(name):
    task = tasks.make(name)
    out, _ = parity.trajectory_check(task, name, n_episodes=2, horizon=100)
    # 100-step returns agree to 1% of the episode length even where chaos separates states
    assert out[100]["return_diff_max_abs"] < 1.0, out[100]
    assert out[20]["reward_max_abs"] < TRAJ20_REWARD_TOL, out[20]


@pytest.mark.slow
@pytest.mark.parametrize("name", ports())
def test_policy_returns_match_dm_control_distribution(name):
    task = tasks.make(name)
    for policy in ("random", "zero"):
        ours, theirs = parity.policy_returns(task, name, 6, policy)
        spread = max(ours.std(), theirs.std(), 1.0)
        assert abs(ours.mean() - theirs.mean()) < 3 * spread, (policy, ours, theirs)


@pytest.mark.parametrize("domain", ["cheetah", "walker"])
def test_suite_model_files_are_what_dm_control_loads(domain):
    """The ports read dm_control's files without importing its suite: the same XML and
    assets as the domain's own `get_model_and_assets()`."""
    import importlib

    from tasks.dm_control.common import suite_model_files

    xml, assets = importlib.import_module(f"dm_control.suite.{domain}").get_model_and_assets()
    assert suite_model_files(domain) == (xml, assets)
