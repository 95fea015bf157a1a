"""Hindsight PRIOR on the training loop (toy task): schedule, λ = 0 is PEBBLE, logs, resume."""
import dataclasses
import json

import jax
import numpy as np
import pytest

from hprior_jax import presets
from hprior_jax.runs.build import build_engine, train
from hprior_jax.runs.run_dir import load_run_config, prepare_run_dir
from hprior_jax.agents.sac import SACConfig
from hprior_jax.methods.prior import PriorConfig

SMALL = dict(sac=SACConfig(hidden_dim=16, hidden_depth=1, batch_size=8), num_eval_episodes=2,
             steps=100, seeds=(7,))


def _cfg(tmp_path, name, algo="prior", lam=5.0, **kw):
    cfg = presets.train_preset("toy_point", algo, "smoke", out=str(tmp_path / name), **{**SMALL, **kw})
    # toy episodes are 20 steps: a dynamics update every 60 steps (after the pre-training at 40)
    if hasattr(cfg, "prior"):
        cfg = dataclasses.replace(cfg, prior=dataclasses.replace(cfg.prior, lam=lam, wm_every=60))
    return cfg


def _records(run_dir):
    return [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]


def _run(cfg, **kw):
    return train(cfg, prepare_run_dir(cfg), progress=False, **kw)


def test_world_model_schedule(tmp_path):
    method = build_engine(_cfg(tmp_path, "s", steps=200)).method
    # feedback rounds as PEBBLE; the world model pre-trains at the first round (seed + unsup
    # = 40), then the dynamics model trains at every multiple of j = 60 after it
    assert method.rounds() == [(40, 10), (80, 10), (120, 10), (160, 10)]
    assert method.ext.event_steps() == [40, 60, 120, 180]
    assert method.event_steps() == [40, 60, 80, 120, 160, 180]
    rvar = build_engine(_cfg(tmp_path, "r", algo="rvar", steps=200)).method
    assert rvar.event_steps() == [40, 80, 120, 160]  # uniform α: no world model to train


def test_the_ablation_flags_reach_the_credit_and_the_prior_term(tmp_path, monkeypatch):
    """--prior.exclude-own-step: every stored pair's α is 0 on its last step and still sums
    to 1; --prior.clip-targets: the round's prior term is built to clip (prior_term's clip
    itself is tested in test_prior_loss); --prior.target shifted: built with the tanh head's
    shift 1 (its algebra: test_prior_loss); --prior.wm-normalize-obs: the world model's
    training, its diagnostics and the credit all read standardised observations (what a
    scaler does: test_world_model); --prior.unlabelled-segments: a second prior term."""
    import hprior_jax.methods.prior as prior_method

    clips, shifts, scalers = [], [], []
    real_term = prior_method.prior_term

    def term(*a, clip=False, shift=0.0):
        clips.append(clip)
        shifts.append(shift)
        return real_term(*a, clip=clip, shift=shift)

    monkeypatch.setattr(prior_method, "prior_term", term)
    real_scaled = prior_method.wm.scaled
    monkeypatch.setattr(prior_method.wm, "scaled",
                        lambda scaler, obs: scalers.append(scaler) or real_scaled(scaler, obs))
    cfg = _cfg(tmp_path, "ablated")
    cfg = dataclasses.replace(cfg, prior=dataclasses.replace(
        cfg.prior, exclude_own_step=True, clip_targets=True, wm_normalize_obs=True,
        unlabelled_segments=8, target="shifted"))
    rs = _run(cfg)
    count = int(rs.method.prefs.count[0])
    assert count > 0 and clips and all(clips) and shifts == [1.0] * len(shifts)
    # traced: pre-training, a later update, the diagnostics of each, the credit of a round
    # and of its unlabelled segments
    assert len(scalers) >= 6 and all(isinstance(s, prior_method.wm.ObsScaler) for s in scalers)
    # --prior.unlabelled-segments: the round's update fits the prior on them too
    rounds = [m for m in _records(tmp_path / "ablated") if "prior/unlabelled_loss" in m]
    assert rounds and all(m["prior/unlabelled_loss"] > 0 for m in rounds)
    for alpha in (rs.method.ext.credit.alpha1[0, :count], rs.method.ext.credit.alpha2[0, :count]):
        np.testing.assert_array_equal(np.asarray(alpha[:, -1]), 0.0)
        np.testing.assert_allclose(np.asarray(alpha).sum(-1), 1.0, rtol=1e-5)


def test_rvar_fits_its_uniform_prior_on_unlabelled_segments_too(tmp_path, monkeypatch):
    """--rvar.unlabelled-segments N (the lab's rvar_unlabelled): each round's update also
    fits the prior on N replay segments of T steps (their credit is `rvar_alpha`'s 1/T,
    tested in test_prior_loss; here it is traced, so only its shape is checked)."""
    import hprior_jax.methods.rvar as rvar_method

    pools = []
    real_rows = rvar_method.rows_of_pool
    monkeypatch.setattr(rvar_method, "rows_of_pool",
                        lambda obs, act, alpha, capacity: pools.append((obs, alpha))
                        or real_rows(obs, act, alpha, capacity))
    cfg = _cfg(tmp_path, "rvar_unlabelled", algo="rvar")
    cfg = dataclasses.replace(cfg, rvar=dataclasses.replace(cfg.rvar, unlabelled_segments=8))
    _run(cfg)
    t = cfg.pebble.segment_len
    assert len(pools) == 2  # traced by the first round's program and the later rounds'
    assert all(obs.shape[:2] == (8, t) and alpha.shape == (8, t) for obs, alpha in pools)
    rounds = [m for m in _records(tmp_path / "rvar_unlabelled") if "prior/unlabelled_loss" in m]
    assert len(rounds) == 2 and all(m["prior/unlabelled_loss"] > 0 for m in rounds)
    with pytest.raises(ValueError, match="unlabelled-segments"):
        rvar_method.RvarConfig(unlabelled_segments=-1)


class _Runs(dict):
    """name -> (cfg, final state, run dir), each run on first use (the fast suite needs only
    PRIOR's)."""

    SPECS = {"pebble": ("pebble", 0.0), "prior_lam0": ("prior", 0.0), "prior": ("prior", 5.0)}

    def __init__(self, tmp):
        super().__init__()
        self.tmp = tmp

    def __missing__(self, name):
        algo, lam = self.SPECS[name]
        cfg = _cfg(self.tmp, name, algo=algo, lam=lam)
        self[name] = (cfg, _run(cfg), self.tmp / name)
        return self[name]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    return _Runs(tmp_path_factory.mktemp("prior"))


def _agent(rs):
    return jax.tree.leaves((rs.sac, rs.method.reward, rs.replay.reward))


@pytest.mark.slow
def test_lambda_zero_trains_exactly_pebbles_agent(runs):
    """Same seeds, λ = 0: the prior term adds exactly zero, and the world model draws its random
    numbers from a folded-off stream, so the agent and reward model match PEBBLE's (to float
    rounding of two differently compiled programs)."""
    (_, pebble, _), (_, lam0, _), (_, prior, _) = runs["pebble"], runs["prior_lam0"], runs["prior"]
    for a, b in zip(_agent(pebble), _agent(lam0)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-6)
    # λ = 5 changes the reward model (the prior loss reaches the ensemble)
    r_pebble, r_prior = (np.concatenate([np.ravel(x) for x in jax.tree.leaves(rs.method.reward)])
                         for rs in (pebble, prior))
    assert np.abs(r_pebble - r_prior).max() > 1e-3


def test_prior_logs_world_model_and_credit_diagnostics(runs):
    cfg, rs, run_dir = runs["prior"]
    records = _records(run_dir)
    rounds = [r for r in records if "feedback/queries" in r]
    assert [r["step"] for r in rounds] == [40, 80]
    for r in rounds:
        assert 0.0 < r["prior/attention_entropy"] <= 1.0 + 1e-6
        assert 0.0 <= r["prior/target_out_of_range"] <= 1.0
        assert r["prior/loss"] >= 0.0 and "reward/true_corr" in r
        assert r["prior/loss/grad_ratio"] > 0.0  # λ = 5: the prior pulls against the CE
    wm = [r for r in records if "prior/wm_dyn_loss" in r]
    assert [r["step"] for r in wm] == [40, 60]
    for r in wm:  # the world-model diagnostics after each update (prior.diagnostics)
        assert r["prior/wm/persistence_error"] > 0.0 and r["prior/wm/mean_state_error"] > 0.0
        np.testing.assert_allclose(r["prior/wm/skill_vs_persistence"], 1.0 - r[
            "prior/wm/next_obs_error"] / r["prior/wm/persistence_error"], rtol=1e-4)
        assert 0.0 <= r["prior/alpha/position_r2"] <= 1.0
        assert 0.0 <= r["prior/alpha/shuffle_tv_position"] <= 1.0
    assert "prior/wm_obs_loss" in wm[0] and "prior/wm_obs_loss" not in wm[1]  # dynamics only
    assert all(r["perf/world_model_s"] > 0 for r in wm)
    # the host loop times each event (rounds at 40, 80; world model at 40, 60) and logs it
    # with the perf record of the chunk that follows it
    seed = records[0]["seed"]
    timed = [r["step"] for r in records if r["seed"] == seed and "perf/event_s" in r]
    assert len(timed) == 3
    for event, logged in zip([40, 60, 80], timed):
        assert event < logged <= event + cfg.chunk_steps
    # the world model trained: its step counters are in the RunState
    assert int(np.asarray(rs.method.ext.wm.obs_steps)[0]) == cfg.prior.wm_pretrain_steps
    assert int(np.asarray(rs.method.ext.wm.dyn_steps)[0]) == (cfg.prior.wm_pretrain_steps
                                                         + cfg.prior.wm_update_steps)
    # α of every stored pair is a distribution over the segment
    count = int(np.asarray(rs.method.prefs.count)[0])
    alpha = np.asarray(rs.method.ext.credit.alpha1[0, :count])
    np.testing.assert_allclose(alpha.sum(-1), 1.0, atol=1e-5)
    assert (alpha >= 0).all()


def test_prior_resume_equals_uninterrupted(runs, tmp_path):
    cfg, full, _ = runs["prior"]
    cfg = dataclasses.replace(cfg, out=str(tmp_path / "split"))
    run_dir = prepare_run_dir(cfg)
    train(cfg, run_dir, progress=False, max_chunks=3)  # stops after the first round
    resumed = train(load_run_config(run_dir), run_dir, resume=True, progress=False)
    for a, b in zip(jax.tree.leaves(full), jax.tree.leaves(resumed)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_prior_config_errors(tmp_path):
    with pytest.raises(ValueError, match="--prior.lam"):
        PriorConfig(lam=-1.0)
    with pytest.raises(ValueError, match="--algo rvar"):
        PriorConfig(wm_pretrain_steps=0)
    with pytest.raises(ValueError, match="--prior.wm-order"):
        PriorConfig(wm_order="dynamics_first")
    cfg = presets.train_preset("cheetah_run", "prior", "paper")
    assert cfg.prior.lam == 5.0 and cfg.prior.wm_layers == 10 and cfg.prior.wm_every == 2000
    assert cfg.prior.wm_order == "joint"  # the appendix's pre-training; TWM's is a flag
    from hprior_jax.commands.train import parse_config as _parse_config

    assert _parse_config(cfg, ["--prior.wm-order", "observation_first"]
                         ).prior.wm_order == "observation_first"
    assert presets.train_preset("drawer_open", "prior", "paper").prior.lam == 1000.0


def test_attention_maps_from_a_trained_run(runs, tmp_path):
    from hprior_jax import cli
    from hprior_jax.experiments.attention_map import attention_maps_for_run

    _, _, run_dir = runs["prior"]
    out = tmp_path / "maps"
    assert cli.main(["attention", "--run", str(run_dir), "--pair", "3", "--out", str(out)]) == 0
    pngs = sorted(out.glob("*.png"))
    assert [p.name for p in pngs] == ["seed7_pair3_seg1.png", "seed7_pair3_seg2.png"]
    assert all(p.stat().st_size > 5000 for p in pngs)
    with pytest.raises(ValueError, match="choose 0..19"):
        attention_maps_for_run(run_dir, pair=20)
    # the true reward drawn beside α is the segment's: it orders every pair as the oracle did
    from hprior_jax.experiments.attention_map import segment_true_reward

    _, rs, _ = runs["prior"]
    seed0 = jax.tree.map(lambda x: np.asarray(x)[0], rs)
    prefs = seed0.method.prefs
    for i in range(int(prefs.count)):
        r1, r2 = (segment_true_reward(seed0.replay, o[i]) for o in (prefs.obs1, prefs.obs2))
        assert len(r1) == len(r2) == prefs.obs1.shape[1]
        assert int(prefs.labels[i]) == int(r1.sum() < r2.sum())
    with pytest.raises(ValueError, match="world model"):
        attention_maps_for_run(prepare_run_dir(_cfg(tmp_path, "pebble", algo="pebble")))
