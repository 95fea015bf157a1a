"""SURF, RUNE, MRN and BISIM on the training loop (toy task): each runs under jit and vmap over
two seeds, a seed's result does not depend on its slot, and a resumed run equals an
uninterrupted one; plus each method's footprint in the run state."""
import dataclasses
import json

import jax
import numpy as np
import pytest

from hprior_jax import presets
from hprior_jax.agents.sac import SACConfig
from hprior_jax.loop import host
from hprior_jax.loop.engine import Engine
from hprior_jax.loop.run_dir import load_run_config, prepare_run_dir
from hprior_jax.networks.reward_ensemble import NEXT_EMBEDDING

BASELINES = ("surf", "rune", "mrn", "bisim")
SMALL = dict(sac=SACConfig(hidden_dim=16, hidden_depth=1, batch_size=8), num_eval_episodes=2,
             steps=100)


def _cfg(tmp, algo, name, seeds):
    return presets.train_preset("toy_point", algo, "smoke", out=str(tmp / name), seeds=seeds,
                                **SMALL)


@pytest.fixture(scope="module", params=BASELINES)
def runs(request, tmp_path_factory):
    """Seeds (7, 8) and (8, 7) of one method: the same compiled programs, lanes swapped."""
    algo, tmp = request.param, tmp_path_factory.mktemp(request.param)
    out = {}
    for name, seeds in (("ab", (7, 8)), ("ba", (8, 7))):
        cfg = _cfg(tmp, algo, name, seeds)
        out[name] = (cfg, host.run(cfg, prepare_run_dir(cfg), progress=False))
    return algo, tmp, out


def _lane(rs, i):
    return [np.asarray(x)[i] for x in jax.tree.leaves(rs)]


def test_a_seed_does_not_depend_on_its_slot(runs):
    """Swapping the seeds' lanes swaps the results (a lane that read another lane's state, or
    its position, would not)."""
    _, _, out = runs
    (_, ab), (_, ba) = out["ab"], out["ba"]
    for a, b in zip(_lane(ab, 0), _lane(ba, 1)):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    assert not np.allclose(np.asarray(ab.sac.log_alpha)[0], np.asarray(ab.sac.log_alpha)[1])


def test_resume_equals_uninterrupted(runs):
    algo, tmp, out = runs
    cfg, full = out["ab"]
    split = dataclasses.replace(cfg, out=str(tmp / "split"))
    run_dir = prepare_run_dir(split)
    host.run(split, run_dir, progress=False, max_chunks=3)  # after the first round
    resumed = host.run(load_run_config(run_dir), run_dir, resume=True, progress=False)
    for a, b in zip(jax.tree.leaves(full), jax.tree.leaves(resumed)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_each_method_leaves_its_mark(runs):
    """What the method adds is in the run state and the log (a method built as plain PEBBLE
    by mistake fails here)."""
    algo, _, out = runs
    cfg, rs = out["ab"]
    rows = [json.loads(l) for l in open(f"{cfg.out}/metrics.jsonl")]
    logged = {k for r in rows for k in r}
    method = Engine(cfg).method
    if algo == "surf":
        h, w = cfg.pebble.segment_len, cfg.surf.window
        assert method.stored_segment_len == h + 2 * w and rs.method.prefs.obs1.shape[2] == h + 2 * w
        given = sum(q for _, q in method.rounds() if q and _ < cfg.steps)
        assert np.asarray(rs.method.ext.pool.count).tolist() == [given * cfg.surf.inv_label_ratio] * 2
        assert {"surf/unlabelled_loss", "surf/confident", "reward/iterations"} <= logged
        assert "reward/epochs" not in logged  # no early-stopped epochs: fixed iterations
    elif algo == "rune":
        assert {"train/rune_bonus", "train/rune_beta"} <= logged
    elif algo == "mrn":
        assert "mrn/outer_loss" in logged and method.meta_steps()
    elif algo == "bisim":
        head = rs.method.reward["params"][NEXT_EMBEDDING]["kernel"]
        fresh = Engine(cfg).init_seeds([7, 8]).method.reward["params"][NEXT_EMBEDDING]["kernel"]
        assert np.abs(np.asarray(head) - np.asarray(fresh)).max() > 1e-4  # the head trained
        assert "bisim/loss" in logged


@pytest.mark.slow
@pytest.mark.parametrize("algo", BASELINES)
def test_a_seed_alone_equals_its_slot(tmp_path, algo):
    both = host.run(_cfg(tmp_path, algo, "both", (7, 8)),
                    prepare_run_dir(_cfg(tmp_path, algo, "both", (7, 8))), progress=False)
    alone = host.run(_cfg(tmp_path, algo, "alone", (8,)),
                     prepare_run_dir(_cfg(tmp_path, algo, "alone", (8,))), progress=False)
    for a, b in zip(_lane(alone, 0), _lane(both, 1)):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5)
