"""Methods as plug-ins: the registry, per-method configuration, one compiled program for a λ
sweep, compiled-program counts, and run directories written before the plug-ins."""
import dataclasses
import json
import re
import shutil
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hprior_jax import presets
from hprior_jax.agents.sac import SACConfig
from hprior_jax.config import FORMAT, RunConfig
from hprior_jax.runs.build import build_engine, train
from hprior_jax.runs.run_dir import load_run_config, prepare_run_dir
from hprior_jax.methods import registry

PACKAGE = Path(__file__).resolve().parents[1] / "hprior_jax"
FIXTURES = Path(__file__).resolve().parent / "fixtures"
SMALL = dict(sac=SACConfig(hidden_dim=16, hidden_depth=1, batch_size=8), num_eval_episodes=2,
             seeds=(7,))


def _cfg(tmp_path, algo, name=None, **kw):
    cfg = presets.train_preset("toy_point", algo, "smoke", out=str(tmp_path / (name or algo)),
                               **{**SMALL, **kw})
    if hasattr(cfg, "prior"):  # a dynamics update every 60 steps after the pre-training at 40
        cfg = dataclasses.replace(cfg, prior=dataclasses.replace(cfg.prior, wm_every=60))
    return cfg


def test_method_names_live_only_in_the_registry_and_methods():
    """`grep` for quoted method names outside hprior_jax/methods/ finds nothing but the
    reward lab's rule table, which names the methods that are its rules (the methods know
    nothing of the lab; tests/test_reward_lab.py checks the table against the registry)."""
    names = "|".join(registry.names())
    quoted = re.compile(rf"[\"']({names})[\"']")
    found = [f"{path.relative_to(PACKAGE)}:{i}: {line.strip()}"
             for path in sorted(PACKAGE.rglob("*.py"))
             if "methods" not in path.parts and path != PACKAGE / "lab" / "rules.py"
             for i, line in enumerate(path.read_text().splitlines(), 1) if quoted.search(line)]
    assert found == []


@pytest.mark.parametrize("algo", registry.names())
def test_every_method_builds_and_records_only_its_sections(tmp_path, algo):
    cfg = _cfg(tmp_path, algo)
    spec = registry.get(algo)
    saved = json.loads(cfg.to_json())
    assert saved["algo"] == algo and saved["format"] == FORMAT
    sections = {k for k, v in saved.items() if isinstance(v, dict)} - {"sac"}
    assert sections == set(spec.sections)  # a SAC run records no max_feedback
    assert RunConfig.from_dict(saved) == cfg
    engine = build_engine(cfg)
    assert engine.phases[0].start == 0 and engine.phase_at(cfg.steps - 1)
    assert all(0 < s < cfg.steps for s in engine.event_steps())


def test_unknown_method_lists_the_registry():
    with pytest.raises(ValueError, match="available: " + ", ".join(registry.names())):
        registry.get("ppo")


def _drive(engine, rs, steps):
    """The host loop's schedule without its logs: events, then chunks, up to `steps`."""
    step, events = 0, set(engine.event_steps())
    while step < steps:
        if step in events:
            rs, _ = engine.run_event(rs, step)
        _, n = engine.chunk_plan(step)
        rs, _ = engine.run_chunk(rs, step, n)
        step += n
    return rs


LAMS, SEEDS = (0.0, 5.0, 50.0), (7, 8)


@pytest.fixture(scope="module")
def lambda_sweep(tmp_path_factory):
    """Three λ x two seeds = six cells on the leading axis of one run."""
    cfg = _cfg(tmp_path_factory.mktemp("sweep"), "prior", steps=100, seeds=SEEDS)
    engine = build_engine(cfg)
    rs = engine.init_seeds([s for _ in LAMS for s in SEEDS])
    lam = jnp.repeat(jnp.asarray(LAMS, jnp.float32), len(SEEDS))
    rs = rs.replace(method=rs.method.replace(ext=rs.method.ext.replace(lam=lam)))
    rs = _drive(engine, rs, cfg.steps)
    engine.run_eval(rs, list(SEEDS) * len(LAMS), cfg.steps)
    return cfg, engine, rs


def _flat(tree, i):
    return np.concatenate([np.ravel(np.asarray(x)[i]) for x in jax.tree.leaves(tree)])


def _gap(a, b):
    return float(np.abs(a - b).mean())


@pytest.mark.slow
def test_lambda_sweep_runs_vmapped_beside_the_seeds_in_one_program(lambda_sweep):
    """Every program of the run (chunks, world model, feedback rounds) compiles once for the
    six cells, and λ reaches each cell's reward model."""
    _, engine, rs = lambda_sweep
    # ahead-of-time compiles, one per name: more would mean a shape or a static value
    # changes between chunks or cells
    assert sorted(engine.compile_seconds) == [
        "chunk/20", "episode_keys", "episode_starts", "eval", "feedback_round",
        "feedback_round/first", "init", "world_model/pretrain", "world_model/update"]
    cell = lambda i: _flat(rs.method.reward, i)  # cells: (λ 0: 0, 1), (λ 5: 2, 3), (λ 50: 4, 5)
    # lanes of one program with the same inputs compute the same bits: a gap means λ arrived
    assert _gap(cell(0), cell(2)) > 1e-5 and _gap(cell(2), cell(4)) > 1e-5


@pytest.mark.slow
def test_a_lambda_sweep_cell_equals_a_run_of_that_lambda_alone(lambda_sweep):
    """The cell (λ = 50, seed 7) is a run of λ = 50 alone, up to the rounding of a vmapped
    program (which grows over 100 steps of training): far closer than the λ = 5 cell."""
    cfg, _, rs = lambda_sweep
    alone = build_engine(dataclasses.replace(cfg, seeds=(7,), prior=dataclasses.replace(cfg.prior,
                                                                                   lam=50.0)))
    one = _drive(alone, alone.init_seeds([7]), cfg.steps)
    cell = lambda i: _flat(rs.method.reward, i)
    rounding = _gap(_flat(one.method.reward, 0), cell(4))
    assert rounding < 1e-4, rounding
    assert _gap(cell(2), cell(4)) > 10 * rounding  # λ = 5 vs 50: λ reaches the reward model
    assert _gap(cell(0), cell(2)) > 10 * rounding  # λ = 0 vs 5


@pytest.mark.slow  # CI time (65 s)
@pytest.mark.parametrize("fixture, algo", [("format1_prior", "prior")])
def test_a_run_directory_of_format_1_still_resumes(tmp_path, fixture, algo):
    """A tiny PRIOR run interrupted at step 80 by the code before methods were plug-ins
    (config.json with every section, `variant`, state under `extra`): it resumes to the end."""
    run_dir = tmp_path / fixture
    shutil.copytree(FIXTURES / fixture, run_dir)
    old = json.loads((run_dir / "config.json").read_text())
    cfg = load_run_config(run_dir)
    assert cfg.algo == algo and cfg.prior.lam == old["prior"]["lam"]
    restored = train(cfg, run_dir, resume=True, progress=False, max_chunks=0)
    fresh = build_engine(cfg).init_seeds(list(cfg.seeds))
    assert int(np.asarray(restored.method.prefs.count)[0]) > 0  # labels came back
    assert int(np.asarray(restored.method.ext.wm.dyn_steps)[0]) > 0  # so did the world model
    assert float(np.asarray(restored.method.ext.lam)[0]) == old["prior"]["lam"]
    assert not np.allclose(np.asarray(jax.tree.leaves(restored.method.reward)[0]),
                           np.asarray(jax.tree.leaves(fresh.method.reward)[0]))
    done = train(cfg, run_dir, resume=True, progress=False)
    assert int(np.asarray(done.replay.size)[0]) == cfg.steps
    rows = (run_dir / "eval.csv").read_text().splitlines()
    assert rows[-1].startswith(f"{cfg.steps},")


def test_prior_nrp_and_rvar_are_methods_of_their_own(tmp_path):
    nrp = build_engine(_cfg(tmp_path, "prior_nrp", steps=100)).method
    assert nrp.ext.variant == "nrp" and nrp.ext.event_steps() == [40, 60]
    rvar = build_engine(_cfg(tmp_path, "rvar", steps=100)).method
    assert rvar.event_steps() == [40, 80]  # feedback rounds only: no world model
    assert registry.get("prior_nrp").has_world_model and not registry.get("rvar").has_world_model


def test_new_run_directory_round_trips(tmp_path):
    cfg = _cfg(tmp_path, "rvar")
    run_dir = prepare_run_dir(cfg)
    assert load_run_config(run_dir) == cfg
