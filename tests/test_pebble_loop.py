"""PEBBLE on the training loop (toy task): schedule, true-reward isolation, relabelling."""
import json

import jax
import numpy as np
import pytest

from hprior_jax import cli, presets
from hprior_jax.loop import host
from hprior_jax.runs.build import build_engine, train
from hprior_jax.runs.run_dir import prepare_run_dir
from hprior_jax.agents.sac import SACConfig
from hprior_jax.methods.pebble_family import PebbleConfig
from tests.assertions import assert_buffer_holds_learned_reward

SMALL = dict(sac=SACConfig(hidden_dim=16, hidden_depth=1, batch_size=8), num_eval_episodes=2)


def _cfg(tmp_path, name, task="toy_point", **kw):
    return presets.train_preset(task, "pebble", "smoke", out=str(tmp_path / name),
                                **{**SMALL, **kw})


def _records(run_dir):
    return [json.loads(l) for l in (run_dir / "metrics.jsonl").read_text().splitlines()]


def test_round_schedule_follows_bpref():
    cfg = presets.train_preset("toy_point", "pebble", "smoke", **SMALL)
    trainer = build_engine(cfg).method
    # 20 seed + 20 pre-training steps, then a round every 40 steps; 40 queries in rounds of 10
    assert trainer.rounds() == [(40, 10), (80, 10), (120, 10), (160, 10)]
    engine = build_engine(cfg)
    assert engine.phase_at(0) == "random" and engine.phase_at(20) == "unsup"
    assert engine.phase_at(40) == "sac"
    import dataclasses
    clipped = dataclasses.replace(cfg, pebble=dataclasses.replace(cfg.pebble, max_feedback=25))
    assert build_engine(clipped).method.rounds() == [(40, 10), (80, 10), (120, 5)]


class _ToyRuns(dict):
    """task -> (cfg, final state, run dir), each run on first use (toy_scaled only for the
    slow isolation test)."""

    def __init__(self, tmp):
        super().__init__()
        self.tmp = tmp

    def __missing__(self, task):
        cfg = _cfg(self.tmp, task, task=task, seeds=(7,))
        self[task] = (cfg, train(cfg, prepare_run_dir(cfg), progress=False), self.tmp / task)
        return self[task]


@pytest.fixture(scope="module")
def toy_runs(tmp_path_factory):
    return _ToyRuns(tmp_path_factory.mktemp("pebble"))


@pytest.mark.slow
def test_true_reward_never_reaches_agent_or_reward_model(toy_runs):
    """Scaling the true reward by 3 leaves an oracle teacher's labels unchanged; if nothing
    but the teacher (and logging) reads the true reward, training is the same. (Not bit for
    bit: the two tasks compile to different XLA programs, which round differently in the
    last ulp; a leak of a 3x reward would move everything by orders of magnitude more.)"""
    (_, a, _), (_, b, _) = toy_runs["toy_point"], toy_runs["toy_scaled"]
    for x, y in zip(jax.tree.leaves((a.sac, a.method.reward)), jax.tree.leaves((b.sac, b.method.reward))):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(np.asarray(a.replay.reward), np.asarray(b.replay.reward),
                               rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(3 * np.asarray(a.replay.true_reward), np.asarray(b.replay.true_reward),
                               rtol=1e-4, atol=1e-6)


def test_buffer_holds_learned_reward_for_every_transition(toy_runs):
    cfg, rs, run_dir = toy_runs["toy_point"]
    assert int(np.asarray(rs.replay.size)[0]) == cfg.steps
    assert_buffer_holds_learned_reward(rs, build_engine(cfg).method.reward_cfg)


def test_feedback_and_reward_logs(toy_runs):
    cfg, rs, run_dir = toy_runs["toy_point"]
    rounds = [r for r in _records(run_dir) if "feedback/queries" in r]
    assert [r["step"] for r in rounds] == [40, 80, 120, 160]
    assert [r["feedback/total_labeled"] for r in rounds] == [10, 20, 30, 40]
    assert all(r["feedback/skipped"] == 0 and r["feedback/mistakes"] == 0 for r in rounds)
    assert all(1 <= r["reward/epochs"] <= cfg.pebble.reward_epochs for r in rounds)
    # the learned reward tracks the true one on this easy task
    assert rounds[-1]["reward/true_corr"] > 0.8
    assert any("train/intrinsic_reward" in r for r in _records(run_dir))
    assert int(np.asarray(rs.method.prefs.count)[0]) == 40


def test_cli_pebble_with_short_flags(tmp_path, monkeypatch):
    """The short spellings and --teacher reach the run's config (the training itself is
    the other tests' job: host.run is replaced by a recorder)."""
    runs = []
    monkeypatch.setattr(host, "run", lambda engine, run_dir, **kw: runs.append(engine.cfg))
    out = tmp_path / "cli"
    rc = cli.main(["train", "--algo", "pebble", "--task", "toy_point", "--preset", "smoke",
                   "--feedback", "20", "--queries-per-round", "10", "--teacher", "mistake",
                   "--sac.hidden-dim", "16", "--sac.batch-size", "8", "--num-eval-episodes", "2",
                   "--steps", "100", "--out", str(out), "--no-progress"])
    assert rc == 0 and len(runs) == 1
    cfg = json.loads((out / "config.json").read_text())
    assert cfg["pebble"]["max_feedback"] == 20 and cfg["pebble"]["teacher"]["eps_mistake"] == 0.1
    assert cfg["pebble"]["queries_per_round"] == 10 and cfg["sac"]["hidden_dim"] == 16
    assert build_engine(runs[0]).method.rounds() == [(40, 10), (80, 10)]


def test_pebble_config_errors(tmp_path):
    with pytest.raises(ValueError, match="--queries-per-round"):
        _cfg(tmp_path, "x", pebble=PebbleConfig(max_feedback=5, queries_per_round=10))
    with pytest.raises(ValueError, match="shorter than the episode"):
        build_engine(_cfg(tmp_path, "y", pebble=PebbleConfig(segment_len=20)))
    with pytest.raises(ValueError, match="multiple of 20"):
        build_engine(_cfg(tmp_path, "z", steps=210))


def test_exported_reward_is_the_runs_learned_reward(toy_runs, tmp_path):
    """`hprior export` + `hprior_jax.load_reward`: a pure function equal to the mean of the
    run's ensemble (the reward its buffer holds), usable without the run directory."""
    import hprior_jax

    cfg, rs, run_dir = toy_runs["toy_point"]
    assert cli.main(["export", "--run", str(run_dir), "--out", str(tmp_path / "exp")]) == 0
    reward = jax.jit(hprior_jax.load_reward(tmp_path / "exp"))
    size = int(np.asarray(rs.replay.size)[0])
    np.testing.assert_allclose(np.asarray(reward(rs.replay.obs[0, :size],
                                                 rs.replay.action[0, :size])),
                               np.asarray(rs.replay.reward[0, :size]), rtol=2e-5, atol=2e-6)
    meta = json.loads((tmp_path / "exp" / "export.json").read_text())
    assert (meta["algo"], meta["seed"], meta["step"]) == ("pebble", 7, cfg.steps)


def test_a_chunk_of_the_first_phase_runs_the_same_in_its_own_program(tmp_path):
    """The random phase's own program (no switch over the phases, so it compiles sooner and
    the run starts while the full program compiles) gives the state and metrics of the
    full program's random branch, bit for bit."""
    cfg = _cfg(tmp_path, "x", seeds=(7, 8))
    engine = build_engine(cfg)
    assert engine._chunk_name(0, 20) == "chunk/20"  # one program unless asked
    engine.first_phase_apart = True
    assert engine._chunk_name(0, 20) == "chunk/20/random"
    assert engine._chunk_name(20, 20) == "chunk/20"
    rs = engine.init_seeds(cfg.seeds)
    runs = {}
    for name in ("chunk/20/random", "chunk/20"):
        fn, state, step0, _ = engine._chunk_program(rs, 0, 20, name)
        copy = jax.tree.map(lambda x: x.copy(), state)  # the program donates its state
        runs[name] = jax.device_get(fn(copy, step0, engine.episode_starts(rs, 0)))
    leaves = lambda name: jax.tree.leaves(runs[name])
    assert len(leaves("chunk/20/random")) == len(leaves("chunk/20"))
    for a, b in zip(leaves("chunk/20/random"), leaves("chunk/20")):
        np.testing.assert_array_equal(a, b)


def test_later_programs_compile_in_the_background_into_the_same_run(tmp_path):
    """At the start of a run the engine queues the compile of evaluation, the feedback rounds
    and the other chunk lengths on a background thread; a run whose programs all came from
    there is the run that compiles each when it first needs it."""
    ahead = _cfg(tmp_path, "ahead", seeds=(7,), steps=100, eval_every=60)
    engine = build_engine(ahead)
    rs = engine.init_seeds(ahead.seeds)
    engine.compile_run_ahead(rs, 0)
    # chunks of 20 (the main thread compiles their program first): random, pre-training,
    # the first round at 40, 20 to the eval at 60, the second round at 80, 20: queued in
    # the order the run needs them
    assert list(engine._pending) == ["feedback_round/first", "feedback_round", "eval"]
    for pending in engine._pending.values():
        pending.result()
    train(ahead, prepare_run_dir(ahead), progress=False, engine=engine)
    assert {"eval", "feedback_round/first", "feedback_round"} <= set(engine.ahead_seconds)

    inline = _cfg(tmp_path, "inline", seeds=(7,), steps=100, eval_every=60)
    engine = build_engine(inline)
    train(inline, prepare_run_dir(inline), progress=False, engine=engine, compile_ahead="off")
    assert not engine.ahead_seconds
    assert (tmp_path / "ahead" / "eval.csv").read_text() == (tmp_path / "inline" / "eval.csv").read_text()
    rounds = lambda run: [r for r in _records(tmp_path / run) if "reward/true_corr" in r]
    assert rounds("ahead") == rounds("inline") and len(rounds("ahead")) == 2


@pytest.mark.parametrize("when", ["after_first", "first_phase_apart", "at_start"])
def test_background_compiles_start_when_asked(tmp_path, when):
    """By default the background queue starts once the main thread has compiled the first
    chunk's program (the two compiles would share the cores and delay the first env step);
    `first_phase_apart` the same after the random phase's own program; `at_start` before."""
    cfg = _cfg(tmp_path, when, seeds=(7,), steps=60, eval_every=60)
    engine = build_engine(cfg)
    compiled_then = []
    queue = engine.compile_run_ahead
    engine.compile_run_ahead = lambda *args: (compiled_then.append(set(engine._compiled)),
                                              queue(*args))
    train(cfg, prepare_run_dir(cfg), progress=False, engine=engine, compile_ahead=when)
    first = {"after_first": {"chunk/20"}, "first_phase_apart": {"chunk/20/random"},
             "at_start": set()}[when]
    # the episode-starts and initial-state programs made the first run state (`init_seeds`);
    # with the first chunk's program first, they compiled in the background beside that one
    assert compiled_then == [first | {"episode_starts", "init"}]
    for name in ("episode_starts", "init"):
        assert (name in engine.ahead_seconds) == (when != "at_start")
    assert "eval" in engine.ahead_seconds
    if when == "first_phase_apart":  # the full program came from the background
        assert "chunk/20" in engine.ahead_seconds


def test_the_episode_recorder_compiles_in_the_background_in_a_run_that_records(tmp_path,
                                                                               monkeypatch):
    """--capture-video: the first clip's episode program comes from the background queue,
    as evaluation's does, and records the episodes the main thread's own compile records."""
    from hprior_jax.loop.engine import eval_key
    from hprior_jax.loop.episodes import episode_states

    recorded = {}

    def record(engine, actor, seed, step, path, max_steps=None):  # the toy has no scene
        if "episode_states/deterministic/1" in engine._pending:  # queued: its turn may not
            engine._pending["episode_states/deterministic/1"].result()  # have come yet
        recorded.setdefault(engine, []).append(
            episode_states(engine, actor, eval_key(seed, step)[None]))
        return path

    monkeypatch.setattr(host, "episode_video", record)
    engines = []
    for ahead in ("after_first", "off"):
        cfg = _cfg(tmp_path, ahead, seeds=(7, 8), steps=60, eval_every=60, capture_video=1)
        engines.append(build_engine(cfg))
        train(cfg, prepare_run_dir(cfg), progress=False, engine=engines[-1],
              compile_ahead=ahead)
    assert "episode_states/deterministic/1" in engines[0].ahead_seconds
    ahead, inline = (recorded[e] for e in engines)
    assert len(ahead) == len(inline) == 2  # 1 evaluation, 2 seeds
    for a, b in zip(ahead, inline):
        jax.tree.map(np.testing.assert_array_equal, a, b)
