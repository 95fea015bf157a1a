"""SURF, RUNE, MRN and BISIM on the training loop (toy task): each runs under jit and vmap over
two seeds, a seed's result does not depend on its slot, and a resumed run equals an
uninterrupted one; each method's footprint in the run state; and the two that change the
agent's update against PEBBLE from the same seeds (RUNE's bonus reaches the critic and nothing
else; MRN's meta steps replace SAC steps)."""
import dataclasses
import json
from pathlib import Path

import jax
import numpy as np
import pytest

from hprior_jax import presets
from hprior_jax.agents.sac import SACConfig
from hprior_jax.runs.build import build_engine, train
from hprior_jax.runs.run_dir import load_run_config, prepare_run_dir
from hprior_jax.networks.reward_ensemble import NEXT_EMBEDDING
from tests.assertions import assert_buffer_holds_learned_reward

BASELINES = ("surf", "rune", "mrn", "bisim")
SMALL = dict(sac=SACConfig(hidden_dim=16, hidden_depth=1, batch_size=8), num_eval_episodes=2,
             steps=100)


def _cfg(tmp, algo, name, seeds):
    return presets.train_preset("toy_point", algo, "smoke", out=str(tmp / name), seeds=seeds,
                                **SMALL)


# Every baseline's loop runs (resume-and-lane check, what each method leaves in the run, MRN's
# host-scheduled meta steps) are in -m slow (CI time: SURF's alone took 105-154 s, MRN's 109 s);
# the fast suite keeps each method's mechanism tests (test_surf.py, test_rune.py, test_mrn.py,
# test_bisim.py)
@pytest.fixture(scope="module")
def runs_of(tmp_path_factory):
    """runs_of(algo) -> (cfg, mid, resumed, full), each run once per module: seeds (8, 7)
    stopped after the first feedback round and one chunk (`mid`), checkpointed, restored and
    finished (`resumed`); `full(seeds)`: an uninterrupted run of the same config."""
    cache = {}

    def get(algo):
        if algo not in cache:
            tmp = tmp_path_factory.mktemp(algo)
            cfg = _cfg(tmp, algo, "split", (8, 7))
            run_dir = prepare_run_dir(cfg)
            mid = train(cfg, run_dir, progress=False, max_chunks=3)
            mid = jax.tree.map(np.asarray, mid)  # the resumed run donates its buffers
            resumed = train(load_run_config(run_dir), run_dir, resume=True, progress=False)

            def full(seeds):
                c = _cfg(tmp, algo, "full_" + "_".join(map(str, seeds)), seeds)
                return train(c, prepare_run_dir(c), progress=False)

            cache[algo] = (cfg, mid, resumed, full)
        return cache[algo]

    return get


@pytest.fixture(params=[pytest.param(a, marks=pytest.mark.slow) for a in BASELINES])
def runs(request, runs_of):
    return (request.param, *runs_of(request.param))


def _lane(rs, i):
    return [np.asarray(x)[i] for x in jax.tree.leaves(rs)]


@pytest.mark.slow
@pytest.mark.parametrize("algo", BASELINES)
def test_a_resumed_run_with_its_seeds_swapped_equals_the_uninterrupted_one(runs_of, algo):
    """Resume restores everything the method keeps, and a seed's result does not depend on its
    lane (one that read another lane's state or its position would differ). Lanes of one
    program compute the same values for the same inputs; the tolerance only allows for that
    not being guaranteed bit for bit."""
    _, _, resumed, full = runs_of(algo)
    full = full((7, 8))
    for lane_full, lane_resumed in ((0, 1), (1, 0)):
        for a, b in zip(_lane(full, lane_full), _lane(resumed, lane_resumed)):
            np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    assert not np.allclose(np.asarray(full.sac.log_alpha)[0], np.asarray(full.sac.log_alpha)[1])


def test_each_method_leaves_its_mark(runs):
    """What the method adds is in the run state and the log (a method built as plain PEBBLE
    by mistake fails here)."""
    algo, cfg, _, rs, _ = runs
    rows = [json.loads(l) for l in open(f"{cfg.out}/metrics.jsonl")]
    logged = {k for r in rows for k in r}
    method = build_engine(cfg).method
    if algo == "surf":
        h, w = cfg.pebble.segment_len, cfg.surf.window
        assert method.stored_segment_len == h + 2 * w and rs.method.prefs.obs1.shape[2] == h + 2 * w
        given = sum(q for _, q in method.rounds())
        assert np.asarray(rs.method.ext.pool.count).tolist() == [given * cfg.surf.inv_label_ratio] * 2
        assert {"surf/unlabelled_loss", "surf/confident", "reward/iterations"} <= logged
        assert "reward/epochs" not in logged  # no early-stopped epochs: fixed iterations
    elif algo == "rune":
        assert {"train/rune_bonus", "train/rune_beta"} <= logged
    elif algo == "mrn":
        assert "mrn/outer_loss" in logged and method.meta_steps()
    elif algo == "bisim":
        head = rs.method.reward["params"][NEXT_EMBEDDING]["kernel"]
        fresh = build_engine(cfg).init_seeds([8, 7]).method.reward["params"][NEXT_EMBEDDING]["kernel"]
        assert np.abs(np.asarray(head) - np.asarray(fresh)).max() > 1e-4  # the head trained
        assert "bisim/loss" in logged


def _flat(tree):
    return np.concatenate([np.ravel(np.asarray(x)) for x in jax.tree.leaves(tree)])


@pytest.mark.slow
def test_rune_bonus_reaches_the_critic_and_nothing_else(runs_of):
    """After the first round and one chunk (the reward model has seen the same data): RUNE's
    reward model is PEBBLE's, its buffer holds r̂ alone, and its critic (reset at the round,
    then trained with the bonus) is not PEBBLE's."""
    (_, pebble, _, _), (cfg, rune, _, _) = runs_of("pebble"), runs_of("rune")
    np.testing.assert_allclose(_flat(rune.method.reward), _flat(pebble.method.reward),
                               rtol=1e-5, atol=1e-6)
    assert_buffer_holds_learned_reward(rune, build_engine(cfg).method.reward_cfg)
    assert np.abs(_flat(rune.sac.critic) - _flat(pebble.sac.critic)).max() > 1e-4


@pytest.mark.slow
def test_rune_logs_beta_on_the_global_step(runs_of):
    """The chunk's mean β, logged at its end, is β_0 (1 − ρ)^t at its steps (20 steps move it
    2e-4 relative), and only after pre-training."""
    cfg = runs_of("rune")[0]
    rows = [json.loads(l) for l in open(f"{cfg.out}/metrics.jsonl")]
    logged = [r for r in rows if "train/rune_beta" in r]
    assert logged and min(r["step"] for r in logged) > 40
    beta0, rho = cfg.rune.beta_init, cfg.rune.beta_decay
    for r in logged:
        assert r["train/rune_beta"] == pytest.approx(beta0 * (1 - rho) ** (r["step"] - 1), rel=1e-3)
        assert r["train/rune_bonus"] > 0


def _critic_updates(rs):
    """Adam's step count of the critic (reset with the critic at the first round)."""
    return int(np.asarray(jax.tree.leaves(rs.sac.critic_opt)[0])[0])


@pytest.mark.slow  # CI time (109 s); MRN's meta step is checked fast in test_mrn.py
def test_mrn_meta_steps_replace_sac_steps(runs_of):
    """As many critic updates as PEBBLE (each meta step made one, in place of the SAC step's),
    the buffer relabelled after the last meta step, every meta step logged with its cost."""
    (_, _, pebble, _), (cfg, _, mrn, _) = runs_of("pebble"), runs_of("mrn")
    method = build_engine(cfg).method
    assert method.meta_steps() == [60, 80]  # rounds at 40 and 80: 20 labels < 40 at step 80
    assert _critic_updates(mrn) == _critic_updates(pebble) == (
        cfg.steps - 40 + cfg.pebble.reset_update)
    assert_buffer_holds_learned_reward(mrn, method.reward_cfg)
    rows = [json.loads(l) for l in open(f"{cfg.out}/metrics.jsonl")]
    meta = [r for r in rows if "mrn/outer_loss" in r]
    assert [r["step"] for r in meta] == [60, 60, 80, 80]  # two seeds
    assert all(r["perf/meta_step_s"] > 0 and np.isfinite(r["mrn/outer_loss"]) for r in meta)


@pytest.mark.slow
@pytest.mark.parametrize("algo", BASELINES)
def test_a_seed_alone_equals_its_slot(tmp_path, algo):
    both = train(_cfg(tmp_path, algo, "both", (7, 8)),
                    prepare_run_dir(_cfg(tmp_path, algo, "both", (7, 8))), progress=False)
    alone = train(_cfg(tmp_path, algo, "alone", (8,)),
                     prepare_run_dir(_cfg(tmp_path, algo, "alone", (8,))), progress=False)
    for a, b in zip(_lane(alone, 0), _lane(both, 1)):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5)


def test_surf_named_defaults_from_the_command_line():
    """`--surf.defaults mrn` gives MRN's copy of SURF's config where no flag set a value."""
    import tyro

    from hprior_jax.methods.surf import SurfConfig

    default = presets.train_preset("cheetah_run", "surf", "reduced")
    assert (default.surf.threshold_u, default.surf.mu, default.surf.inv_label_ratio) == (0.95, 1, 10)
    cfg = tyro.cli(type(default), default=default,
                   args=["--surf.defaults", "mrn", "--surf.mu", "2"])
    assert (cfg.surf.threshold_u, cfg.surf.mu, cfg.surf.inv_label_ratio) == (0.99, 2, 100)
    assert type(cfg).from_dict(json.loads(cfg.to_json())) == cfg  # config.json round trip
    with pytest.raises(ValueError, match="crop"):
        build_engine(dataclasses.replace(_cfg(Path("/tmp"), "surf", "x", (7,)),
                                   surf=SurfConfig(window=1, crop_range=3)))
