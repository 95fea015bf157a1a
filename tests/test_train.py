"""The training loop on the toy task (compiles in seconds): seeds, resume, run dirs, errors."""
import csv
import json

import jax
import numpy as np
import pytest

from hprior_jax import cli
from hprior_jax.loop import host
from hprior_jax.runs.build import build_engine, train
from hprior_jax.runs.run_dir import RunDirError, load_run_config, prepare_run_dir
from hprior_jax.agents.sac import SACConfig
from hprior_jax.config import RunConfig

TOY = dict(task="toy_point", steps=80, num_seed_steps=20, chunk_steps=20, eval_every=40,
           checkpoint_every=40, num_eval_episodes=2,
           sac=SACConfig(hidden_dim=16, hidden_depth=1, batch_size=8))


def _cfg(tmp_path, name="run", **kw):
    return RunConfig(**{**TOY, "out": str(tmp_path / name), **kw})


def _leaves(rs):
    return [np.asarray(x) for x in jax.tree.leaves(rs)]


def test_seed_alone_equals_its_slot_in_a_vmapped_batch(tmp_path):
    both = train(_cfg(tmp_path, "both", seeds=(12345, 23456)),
                     prepare_run_dir(_cfg(tmp_path, "both", seeds=(12345, 23456))),
                     progress=False)
    alone = train(_cfg(tmp_path, "alone", seeds=(12345,)),
                      prepare_run_dir(_cfg(tmp_path, "alone", seeds=(12345,))),
                      progress=False)
    for a, b in zip(_leaves(alone), _leaves(both)):
        np.testing.assert_allclose(a[0], b[0], rtol=1e-4, atol=1e-5)
    # and the two seeds really differ
    assert not np.allclose(np.asarray(both.sac.log_alpha)[0], np.asarray(both.sac.log_alpha)[1])


def test_episodes_start_from_the_resets_of_the_chunks_own_key_stream(tmp_path):
    """A chunk's new episodes begin from states made outside it (the episode-starts program):
    `env.reset` of the key the chunk's own step draws at each episode end, found here by
    walking the chunk's key stream by hand."""
    cfg = _cfg(tmp_path, seeds=(12345, 23456), chunk_steps=50)  # toy episodes: 20 steps
    engine = build_engine(cfg)
    assert engine.starts_per_chunk == 3
    rs = engine.init_seeds(cfg.seeds)
    step0, length = 5, 45  # episode ends at steps 19 and 39
    starts = engine.episode_starts(rs, step0)
    reset = jax.jit(engine.env.reset)
    keys = np.asarray(rs.key)
    done, _ = engine.run_chunk(rs, step0, length)
    for seed, key in enumerate(keys):
        firsts = []
        for step in range(step0, step0 + length):
            key, _, _, _, k_reset = jax.random.split(key, 5)
            if (step + 1) % 20 == 0:
                firsts.append(np.asarray(reset(k_reset).task.obs))
        assert len(firsts) == 2
        for j, first in enumerate(firsts):
            np.testing.assert_array_equal(np.asarray(starts.task.obs)[seed, j], first)
            # the chunk continued from it: the obs stored at the step after the j-th end
            np.testing.assert_array_equal(np.asarray(done.replay.obs)[seed, 20 * (j + 1)],
                                          first[0])
        assert not np.array_equal(firsts[0], firsts[1])


def test_resume_equals_uninterrupted(tmp_path):
    """2 chunks + checkpoint + restore + 2 chunks == 4 chunks."""
    cfg_full = _cfg(tmp_path, "full")
    full = train(cfg_full, prepare_run_dir(cfg_full), progress=False)
    cfg = _cfg(tmp_path, "split")
    run_dir = prepare_run_dir(cfg)
    train(cfg, run_dir, progress=False, max_chunks=2)
    assert (run_dir / "checkpoints").exists()
    resumed = train(load_run_config(run_dir), run_dir, resume=True, progress=False)
    for a, b in zip(_leaves(full), _leaves(resumed)):
        np.testing.assert_array_equal(a, b)
    rows = list(csv.DictReader(open(run_dir / "eval.csv")))
    assert [int(r["step"]) for r in rows] == [40, 80]  # no duplicates after the resume
    full_rows = list(csv.DictReader(open(tmp_path / "full" / "eval.csv")))
    assert rows == full_rows


def test_refuses_non_empty_output_dir_and_keeps_it(tmp_path):
    out = tmp_path / "busy"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    with pytest.raises(RunDirError, match="not empty"):
        prepare_run_dir(_cfg(tmp_path, "busy"))
    assert (out / "notes.txt").read_text() == "mine"


def test_nan_loss_stops_with_a_clear_error_and_keeps_the_checkpoint(tmp_path):
    cfg = _cfg(tmp_path, "nan", task="toy_nan", num_seed_steps=40)
    run_dir = prepare_run_dir(cfg)
    with pytest.raises(host.TrainingDiverged, match="--sac.lr.*--resume"):
        train(cfg, run_dir, progress=False)
    assert (run_dir / "error.txt").exists()
    assert (run_dir / "checkpoints" / "40").exists()  # the last good state is kept
    assert (run_dir / "config.json").exists()


@pytest.mark.parametrize("kw, match", [
    (dict(algo="ppo"), "unknown algorithm 'ppo'; available: sac"),
    (dict(seeds=(1, 1)), "duplicates"),
    (dict(steps=10, num_seed_steps=20), "--num-seed-steps"),
    (dict(chunk_steps=0), "--chunk-steps"),
    (dict(steps=4, num_seed_steps=0), "--sac.batch-size"),
])
def test_config_errors_name_the_fix(tmp_path, kw, match):
    with pytest.raises(ValueError, match=match):
        _cfg(tmp_path, **kw)


def test_cli_writes_a_complete_run_directory(tmp_path, capsys):
    out = tmp_path / "cli"
    rc = cli.main(["train", "--task", "toy_point", "--preset", "smoke", "--steps", "60",
                   "--num-seed-steps", "20", "--chunk-steps", "20", "--eval-every", "40",
                   "--checkpoint-every", "40", "--num-eval-episodes", "2", "--sac.hidden-dim",
                   "16", "--sac.batch-size", "8", "--seeds", "1", "2", "--out", str(out),
                   "--no-progress"])
    assert rc == 0
    cfg = json.loads((out / "config.json").read_text())
    assert cfg["seeds"] == [1, 2] and cfg["sac"]["hidden_dim"] == 16 and cfg["steps"] == 60
    rows = list(csv.DictReader(open(out / "eval.csv")))
    assert [(int(r["step"]), int(r["seed"])) for r in rows] == [(40, 1), (40, 2), (60, 1), (60, 2)]
    assert all(r["success"] != "" for r in rows)  # the toy task defines success
    records = [json.loads(l) for l in (out / "metrics.jsonl").read_text().splitlines()]
    assert any("train/critic_loss" in r for r in records)
    assert any("perf/env_steps_per_s" in r for r in records)
    # wall time by part: every chunk, evals at 40 and 60, checkpoints at 40 and 60; the first
    # chunk and the first eval compiled (their compile is counted apart, not in their part)
    perf = [r for r in records if r["seed"] == 1 and "perf/chunk_s" in r]
    assert [r["step"] for r in perf] == [20, 40, 60] and all(r["perf/chunk_s"] > 0 for r in perf)
    assert [r["step"] for r in perf if "perf/eval_s" in r] == [40, 60]
    assert [r["step"] for r in perf if "perf/checkpoint_s" in r] == [40, 60]
    assert perf[0]["perf/compile_s"] > 0 and "perf/event_s" not in perf[0]  # SAC: no events
    assert (out / "learning_curve.png").stat().st_size > 1000
    assert (out / "checkpoints" / "60").exists()
    assert list((out / "tb").glob("seed_1/events.out.tfevents.*"))
    assert str(out) in capsys.readouterr().out
    # a second run into the same directory is refused without touching it
    assert cli.main(["train", "--task", "toy_point", "--out", str(out)]) == 2
    assert "--resume" in capsys.readouterr().err
    # --resume with a longer budget continues the run
    assert cli.main(["train", "--resume", str(out), "--steps", "80", "--no-progress"]) == 0
    rows = list(csv.DictReader(open(out / "eval.csv")))
    assert [int(r["step"]) for r in rows][-2:] == [80, 80]


def test_a_full_contact_cap_is_logged_and_warned_once(tmp_path, capsys, monkeypatch):
    """A task whose MJX contact cap is full (stood in for by the toy task) gets the share of
    such steps per chunk in metrics.jsonl and one warning naming --contact-cap none."""
    import jax.numpy as jnp

    import tasks

    monkeypatch.setattr(type(tasks.make("toy_point")), "contacts_at_cap",
                        lambda self, data: data["pos"] > -jnp.inf)  # always, traced
    out = tmp_path / "capped"
    assert cli.main(["train", "--task", "toy_point", "--preset", "smoke", "--steps", "40",
                     "--num-seed-steps", "20", "--chunk-steps", "20", "--eval-every", "40",
                     "--num-eval-episodes", "1", "--sac.hidden-dim", "16", "--sac.batch-size",
                     "8", "--seeds", "1", "--out", str(out), "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert printed.count("warning: MJX's contact cap was full at 100.0% of steps 0-20") == 1
    assert "--contact-cap none" in printed
    records = [json.loads(l) for l in (out / "metrics.jsonl").read_text().splitlines()]
    assert [r["physics/contacts_at_cap"] for r in records if "physics/contacts_at_cap" in r
            ] == [1.0, 1.0]


def test_cli_unknown_task_lists_available(capsys):
    assert cli.main(["train", "--task", "nope", "--out", "/tmp/never"]) == 2
    assert "available tasks" in capsys.readouterr().err


def test_random_phase_collects_without_updating(tmp_path):
    cfg = _cfg(tmp_path, "seedphase", num_seed_steps=40)
    trainer = build_engine(cfg)
    rs0 = trainer.init_seeds(cfg.seeds)
    init_actor = [np.asarray(x) for x in jax.tree.leaves(rs0.sac.actor)]
    rs, metrics = trainer.run_chunk(rs0, 0, 20)
    for a, b in zip(init_actor, jax.tree.leaves(rs.sac.actor)):
        np.testing.assert_array_equal(a, np.asarray(b))
    assert int(np.asarray(rs.replay.size)[0]) == 20
    actions = np.asarray(rs.replay.action)[0, :20]
    assert actions.min() >= -1 and actions.max() <= 1 and actions.std() > 0.3  # uniform
    rs, _ = trainer.run_chunk(rs, 40, 20)  # learning phase (the step index decides)
    assert not np.array_equal(init_actor[0], np.asarray(jax.tree.leaves(rs.sac.actor)[0]))
