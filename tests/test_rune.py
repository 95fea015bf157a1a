"""RUNE: the bonus is the members' std, β decays exponentially with the global step, and the
bonus reaches the critic's target and nothing else."""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hprior_jax import presets
from hprior_jax.agents.sac import SACConfig
from hprior_jax.loop import host
from hprior_jax.loop.run_dir import prepare_run_dir
from hprior_jax.methods.rune import RuneConfig, beta, disagreement_bonus
from hprior_jax.networks.reward_ensemble import (RewardConfig, RewardNet, init_reward_ensemble,
                                                 mean_reward)

SMALL = dict(sac=SACConfig(hidden_dim=16, hidden_depth=1, batch_size=8), num_eval_episodes=2,
             seeds=(7,))


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


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """RUNE and PEBBLE from the same seed, stopped after the first round (step 40) and one
    chunk of SAC updates after it: the reward model has seen the same data."""
    tmp = tmp_path_factory.mktemp("rune")
    out = {}
    for algo in ("pebble", "rune"):
        cfg = presets.train_preset("toy_point", algo, "smoke", out=str(tmp / algo), **SMALL)
        if algo == "rune":  # a β large enough to move the critic visibly
            cfg = dataclasses.replace(cfg, rune=RuneConfig(beta_init=5.0))
        out[algo] = (cfg, host.run(cfg, prepare_run_dir(cfg), progress=False, max_chunks=3))
    return out


def _flat(tree):
    return np.concatenate([np.ravel(np.asarray(x)) for x in jax.tree.leaves(tree)])


def test_bonus_reaches_the_critic_and_nothing_else(runs):
    (_, pebble), (cfg, rune) = runs["pebble"], runs["rune"]
    # the reward model and its labels are PEBBLE's (the bonus never enters reward learning)
    np.testing.assert_allclose(_flat(rune.method.reward), _flat(pebble.method.reward),
                               rtol=1e-5, atol=1e-6)
    # the buffer stores r̂ alone, no bonus
    size = int(np.asarray(rune.replay.size)[0])
    params = jax.tree.map(lambda x: x[0], rune.method.reward)
    r_hat = mean_reward(params, rune.replay.obs[0, :size], rune.replay.action[0, :size],
                        RewardConfig(hidden_sizes=(cfg.pebble.reward_hidden,) * cfg.pebble.reward_depth))
    np.testing.assert_allclose(np.asarray(rune.replay.reward[0, :size]), np.asarray(r_hat),
                               rtol=2e-5, atol=2e-6)
    # the critic (reset at the first round, then trained with the bonus) is not PEBBLE's
    assert np.abs(_flat(rune.sac.critic) - _flat(pebble.sac.critic)).max() > 1e-3


def test_beta_logged_is_the_schedule_at_the_logged_step(runs):
    """The chunk's mean β (logged at the chunk's end) is β at its steps: 20 steps move it 2e-4."""
    import json

    cfg, _ = runs["rune"]
    rows = [json.loads(l) for l in open(f"{cfg.out}/metrics.jsonl")]
    logged = [r for r in rows if "train/rune_beta" in r]
    assert logged and min(r["step"] for r in logged) > 40  # after pre-training only
    for r in logged:
        assert r["train/rune_beta"] == pytest.approx(5.0 * (1 - 1e-5) ** (r["step"] - 1), rel=1e-3)
        assert r["train/rune_bonus"] > 0
