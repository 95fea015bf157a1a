"""prior.diagnostics against NumPy/scipy on hand-built inputs, and its wiring in the lab."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from hprior_jax.lab.learn import Lab
from hprior_jax.lab.seed_world_model import SeedContext, held_out_segments
from hprior_jax.prior import world_model as wm
from hprior_jax.prior.diagnostics import (credit_diagnostics, next_state_errors,
                                          world_model_diagnostics)

B, T = 6, 8
rng = np.random.default_rng(0)
PERM = np.stack([rng.permutation(T) for _ in range(B)])


def _dirichlet(shape):
    a = rng.gamma(1.0, size=shape)
    return a / a.sum(-1, keepdims=True)


def test_positional_credit_is_all_position_and_stays_put_when_shuffled():
    profile = _dirichlet(T)
    alpha = np.tile(profile, (B, 1))
    d = credit_diagnostics(jnp.asarray(alpha), jnp.asarray(alpha), jnp.asarray(PERM),
                           jnp.asarray(rng.normal(size=(B, T))))
    assert float(d["alpha/position_r2"]) == pytest.approx(1.0)
    assert float(d["alpha/shuffle_tv_position"]) == pytest.approx(0.0, abs=1e-7)
    content = np.take_along_axis(alpha, PERM, 1)
    assert float(d["alpha/shuffle_tv_content"]) == pytest.approx(
        0.5 * np.abs(alpha - content).sum(1).mean(), rel=1e-5)
    assert float(d["alpha/last_step"]) == pytest.approx(profile[-1], rel=1e-6)


def test_content_credit_follows_its_steps_and_matches_numpy():
    alpha = _dirichlet((B, T))
    shuffled = np.take_along_axis(alpha, PERM, 1)  # α moved with the steps it credits
    reward = rng.normal(size=(B, T))
    reward[0] = 1.0  # a constant-reward segment has no correlation: left out of the mean
    d = credit_diagnostics(jnp.asarray(alpha), jnp.asarray(shuffled), jnp.asarray(PERM),
                           jnp.asarray(reward))
    assert float(d["alpha/shuffle_tv_content"]) == pytest.approx(0.0, abs=1e-7)
    profile = alpha.mean(0)
    r2 = 1 - ((alpha - profile) ** 2).sum() / ((alpha - alpha.mean()) ** 2).sum()
    assert float(d["alpha/position_r2"]) == pytest.approx(r2, rel=1e-5)
    corr = np.mean([stats.pearsonr(alpha[b], reward[b])[0] for b in range(1, B)])
    assert float(d["alpha/reward_corr"]) == pytest.approx(corr, rel=1e-4)


CFG = wm.WorldModelConfig(obs_size=3, act_size=2, latent_dim=4, obs_hidden=(16,), embed_dim=16,
                          num_heads=2, head_dim=8, num_layers=1, ff_dim=32, head_hidden=(16,),
                          segment_len=T, memory_len=T, batch_size=8)


def test_next_state_errors_match_numpy_and_the_dynamics_loss():
    params = wm.init(jax.random.PRNGKey(0), CFG).params
    obs = jnp.asarray(rng.normal(size=(B, T, 3)), jnp.float32)
    act = jnp.asarray(rng.uniform(-1, 1, size=(B, T, 2)), jnp.float32)
    e = jax.jit(next_state_errors, static_argnums=3)(params, obs, act, CFG)
    o = np.asarray(obs)
    half_sq = lambda p: 0.5 * ((p - o[:, 1:]) ** 2).sum(-1).mean()
    assert float(e["wm/persistence_error"]) == pytest.approx(half_sq(o[:, :-1]), rel=1e-5)
    assert float(e["wm/mean_state_error"]) == pytest.approx(
        half_sq(o.reshape(-1, 3).mean(0)), rel=1e-5)
    _, m = jax.jit(wm.dynamics_loss, static_argnums=(5, 6))(params.dyn, params.obs, obs, act,
                                                            None, CFG, True)
    assert float(e["wm/next_obs_error"]) == pytest.approx(float(m["prior/wm_next_obs_loss"]),
                                                          rel=1e-5)
    assert float(e["wm/skill_vs_persistence"]) == pytest.approx(
        1 - float(e["wm/next_obs_error"]) / half_sq(o[:, :-1]), rel=1e-5)
    # in latent space: the dynamics loss's latent term against z_t, and the decoder's floor
    z = np.asarray(wm.encode(params.obs, obs, CFG))
    latent_persistence = 0.5 * ((z[:, :-1] - z[:, 1:]) ** 2).sum(-1).mean()
    assert float(e["wm/latent_error"]) == pytest.approx(float(m["prior/wm_latent_loss"]), rel=1e-5)
    assert float(e["wm/latent_skill_vs_persistence"]) == pytest.approx(
        1 - float(m["prior/wm_latent_loss"]) / latent_persistence, rel=1e-4)
    recon = np.asarray(wm.decode(params.obs, z[:, 1:], CFG))
    assert float(e["wm/reconstruction_error"]) == pytest.approx(half_sq(recon), rel=1e-5)


@pytest.mark.slow  # CI time (54 s: two compiles of the diagnostics); the lab runs it for real
def test_the_lab_reports_each_seeds_world_model_on_held_out_segments():
    """Per seed (seeds' models differ), on the same fixed held-out segments."""
    from tests.test_reward_lab import TINY_WM, confounded, tiny

    data = confounded()
    lab = Lab(tiny(seeds=(0, 1)), data)
    params = jax.vmap(lambda k: wm.init(k, TINY_WM).params)(jax.random.split(
        jax.random.PRNGKey(1), 2))
    rows = lab._world_model_diagnostics(SeedContext(wm_params=params, profile=None),
                                        num_segments=32)
    assert [r["seed"] for r in rows] == [0, 1]
    assert rows[0]["wm/next_obs_error"] != rows[1]["wm/next_obs_error"]
    assert rows[0]["wm/persistence_error"] == pytest.approx(rows[1]["wm/persistence_error"])
    alone = world_model_diagnostics(jax.tree.map(lambda x: x[1], params),
                                    *held_out_segments(data, lab.T, 32), cfg=TINY_WM)
    assert rows[1]["alpha/position_r2"] == pytest.approx(float(alone["alpha/position_r2"]),
                                                         rel=1e-4)


def test_unreachable_targets_counts_stored_pairs_only_and_matches_numpy():
    """|α_t·R̂_k| > 1 over the stored pairs' steps (not the empty slots), mean over members."""
    from hprior_jax.buffers import preferences
    from hprior_jax.networks.reward_ensemble import (RewardConfig, init_reward_ensemble,
                                                     member_rewards)
    from hprior_jax.prior.diagnostics import unreachable_targets
    from hprior_jax.prior.loss import PairCredit

    cfg = RewardConfig(hidden_sizes=(16,), ensemble_size=3)
    params = init_reward_ensemble(jax.random.PRNGKey(0), 3, 2, cfg)
    seg = lambda *s: jnp.asarray(rng.normal(size=s) * 3, jnp.float32)
    store = preferences.add(preferences.init(T, 3, 2, capacity=5), preferences.PreferenceBatch(
        seg(3, T, 3), seg(3, T, 2), seg(3, T, 3), seg(3, T, 2), jnp.zeros(3, jnp.int32)),
        jnp.ones(3, bool))
    a1, a2 = _dirichlet((5, T)) * 4, _dirichlet((5, T)) * 4  # scaled: some targets leave [-1, 1]
    credit = PairCredit(alpha1=jnp.asarray(a1, jnp.float32), alpha2=jnp.asarray(a2, jnp.float32))
    got = float(unreachable_targets(params, store, credit, cfg))
    share = []
    for obs, act, alpha in ((store.obs1, store.act1, a1), (store.obs2, store.act2, a2)):
        r = np.asarray(member_rewards(params, obs[:3], act[:3], cfg))  # [K, 3, T]
        share.append((np.abs(alpha[:3] * r.sum(-1, keepdims=True)) > 1).mean(-1))  # [K, 3]
    assert 0 < got < 1
    assert got == pytest.approx(np.concatenate(share, 1).mean(), rel=1e-5)
