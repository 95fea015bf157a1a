"""RUNE: the bonus is the members' std and β decays exponentially with the global step (the
loop-level checks against PEBBLE are in test_baselines.py)."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hprior_jax.methods.rune import RuneConfig, beta, disagreement_bonus
from hprior_jax.networks.reward_ensemble import RewardConfig, RewardNet, init_reward_ensemble


def test_bonus_is_the_population_std_of_the_members():
    cfg = RewardConfig(hidden_sizes=(8, 8), ensemble_size=3)
    params = init_reward_ensemble(jax.random.PRNGKey(0), 3, 2, cfg)
    obs = jax.random.normal(jax.random.PRNGKey(1), (5, 3))
    act = jax.random.uniform(jax.random.PRNGKey(2), (5, 2), minval=-1, maxval=1)
    x = np.concatenate([obs, act], -1)
    members = np.stack([np.asarray(RewardNet(cfg).apply(jax.tree.map(lambda p: p[k], params), x))
                        for k in range(3)])
    got = np.asarray(disagreement_bonus(params, obs, act, cfg))
    np.testing.assert_allclose(got, members.std(0, ddof=0), rtol=1e-5, atol=1e-7)
    assert got.min() > 0


@pytest.mark.parametrize("t", [0, 10_000, 100_000, 500_000, 1_000_000])
def test_beta_decays_exponentially_with_the_global_step(t):
    expected = 0.05 * (1 - 1e-5) ** t  # rune: beta_init * (1 - beta_decay) ** step
    assert float(beta(RuneConfig(), jnp.int32(t))) == pytest.approx(expected, rel=1e-5)
    assert float(beta(RuneConfig(beta_schedule="constant"), jnp.int32(t))) == pytest.approx(0.05)
