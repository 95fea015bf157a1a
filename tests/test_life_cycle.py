"""A run's life cycle as a user meets it (toy task): Ctrl-C and resume, torn logs, what a
resume may change, the compilation cache across a resume, eval, export, provenance, and the
command line's messages for bad input."""
import contextlib
import csv
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest

import hprior_jax
from hprior_jax import cli
from hprior_jax.loop import host
from hprior_jax.loop.progress import ProgressBar
from hprior_jax.runs.build import train
from hprior_jax.runs.restore import restore_run
from hprior_jax.runs.run_dir import load_run_config

ROOT = Path(__file__).resolve().parent.parent
TOY = ["--task", "toy_point", "--preset", "smoke", "--num-seed-steps", "20", "--chunk-steps",
       "20", "--eval-every", "40", "--num-eval-episodes", "2", "--sac.hidden-dim", "16",
       "--sac.hidden-depth", "1", "--sac.batch-size", "8"]


def _train(*args) -> int:
    return cli.main(["train", *TOY, "--no-progress", *args])


def _rows(path):
    return list(csv.reader(open(path, newline="")))


def _records(run_dir):
    """metrics.jsonl less wall-clock timings."""
    return [{k: v for k, v in json.loads(line).items() if not k.startswith("perf/")}
            for line in (run_dir / "metrics.jsonl").read_text().splitlines()]


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """A complete two-seed SAC run of 80 steps, made by the command line."""
    out = tmp_path_factory.mktemp("life") / "run"
    assert _train("--steps", "80", "--checkpoint-every", "40", "--seeds", "1", "2",
                  "--out", str(out)) == 0
    return out


@contextlib.contextmanager
def _cache_events():
    """Names of the persistent-compilation-cache events while inside, every program cached
    (no minimum compile time)."""
    from jax._src import monitoring

    from hprior_jax import setup_jax

    events = []
    listener = lambda name, **kw: events.append(name) if "compilation_cache" in name else None
    monitoring.register_event_listener(listener)
    before = jax.config.jax_persistent_cache_min_compile_time_secs, setup_jax.MIN_COMPILE_SECS
    # (the CLI enables the cache again with its own minimum: at the suite's -O0 the
    # evaluation compiles in under a second)
    setup_jax.MIN_COMPILE_SECS = 0.0
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    try:
        yield events
    finally:
        jax.config.update("jax_persistent_cache_min_compile_time_secs", before[0])
        setup_jax.MIN_COMPILE_SECS = before[1]
        monitoring.unregister_event_listener(listener)


# -- interrupt and resume ---------------------------------------------------------------------

def test_ctrl_c_saves_a_checkpoint_prints_the_resume_command_and_resumes_exactly(tmp_path):
    """SIGINT to a running `hprior train`: exit 130 after the chunk in flight, a checkpoint
    at the step it reached, the resume command on stderr; resumed to 40 more steps, the run
    equals an uninterrupted one of that budget (eval.csv and final state)."""
    out = tmp_path / "interrupted"
    # a budget it cannot finish before the signal; a fixed buffer so the resumed budget
    # (lower) keeps the same replay capacity
    args = [*TOY, "--steps", "400000", "--replay-capacity", "4000", "--checkpoint-every",
            "400000", "--seeds", "1", "2", "--out", str(out), "--no-progress"]
    code = ("import sys; from tests.toy_task import ensure_registered; ensure_registered(); "
            "from hprior_jax import cli; sys.exit(cli.main(sys.argv[1:]))")
    proc = subprocess.Popen([sys.executable, "-c", code, "train", *args], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONPATH": str(ROOT)})
    deadline = time.time() + 240
    while time.time() < deadline and proc.poll() is None:
        if (out / "eval.csv").exists() and len(_rows(out / "eval.csv")) >= 3:
            break  # compiled and trained past the first evaluation
        time.sleep(0.2)
    assert proc.poll() is None, proc.communicate()
    proc.send_signal(signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 130, stderr
    assert f"hprior train --resume {out}" in stderr and "Traceback" not in stderr
    step = int(stderr.split("interrupted at step ")[1].split(";")[0])
    assert 40 <= step < 400000 and (out / "checkpoints" / str(step)).exists()
    target = (step // 40 + 1) * 40
    assert _train("--resume", str(out), "--steps", str(target)) == 0
    resumed_state = restore_run(out).state
    # the same run, uninterrupted
    full = tmp_path / "full"
    assert _train("--steps", str(target), "--replay-capacity", "4000", "--checkpoint-every",
                  "400000", "--seeds", "1", "2", "--out", str(full)) == 0
    assert _rows(out / "eval.csv") == _rows(full / "eval.csv")
    full_state = restore_run(full).state
    for a, b in zip(jax.tree.leaves(resumed_state), jax.tree.leaves(full_state)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_a_torn_last_log_line_is_dropped_with_a_warning_and_resume_leaves_no_duplicates(
        tmp_path):
    out = tmp_path / "torn"
    assert _train("--steps", "80", "--checkpoint-every", "40", "--out", str(out)) == 0
    complete = _records(out)
    # as a kill after the checkpoint at 40 would leave it: the logs run past the checkpoint
    # and end in half a line
    (out / "checkpoints" / "80").rename(tmp_path / "gone")
    with open(out / "metrics.jsonl", "a") as f:
        f.write('{"step": 80, "seed": 12345, "train/cri')
    with open(out / "eval.csv", "a") as f:
        f.write("80,12")
    with pytest.warns(UserWarning, match=re.escape(str(out / "metrics.jsonl"))):
        train(load_run_config(out), out, resume=True, progress=False)
    assert _records(out) == complete  # the records after step 40 once, none torn
    assert [r[0] for r in _rows(out / "eval.csv")] == ["step", "40", "80"]


def test_a_resume_hits_the_compilation_cache(tmp_path):
    """Restored arrays are committed to their device; programs lowered from them differed
    from a fresh run's and missed the persistent cache (53-88 s of compiling per resume)."""
    out = tmp_path / "cached"
    with _cache_events() as events:
        assert _train("--steps", "80", "--checkpoint-every", "40", "--out", str(out)) == 0
        (out / "checkpoints" / "80").rename(tmp_path / "gone")
        events.clear()
        train(load_run_config(out), out, resume=True, progress=False)
    assert events.count("/jax/compilation_cache/cache_hits") >= 2  # the chunk and eval
    assert "/jax/compilation_cache/cache_misses" not in events


def test_resume_applies_budget_and_cadences_and_refuses_the_rest(finished, capsys):
    before = (finished / "config.json").read_text()
    for flags, named in ((["--algo", "pebble"], "--algo ('sac' -> 'pebble')"),
                         (["--sac.lr", "0.1"], "--sac.lr (0.0003 -> 0.1)"),
                         (["--seeds", "3"], "--seeds"),
                         (["--steps", "20"], "below step 80")):
        assert cli.main(["train", "--resume", str(finished), *flags]) == 2
        err = capsys.readouterr().err
        assert named in err and err.count("\n") == 1, err
    assert (finished / "config.json").read_text() == before  # nothing written
    # the budget and the cadences may change (80 -> 120 steps, evaluations every 20)
    assert cli.main(["train", "--resume", str(finished), "--steps", "120", "--eval-every",
                     "20", "--no-progress"]) == 0
    cfg = load_run_config(finished)
    assert (cfg.steps, cfg.eval_every, cfg.sac.lr) == (120, 20, 3e-4)
    assert [int(r[0]) for r in _rows(finished / "eval.csv")[1:]][-4:] == [100, 100, 120, 120]
    assert json.loads((finished / "config.json").read_text())["run_info"]["command"].startswith(
        "hprior train")


# -- what a run records --------------------------------------------------------------------

def test_run_records_its_provenance_and_plain_line_endings(finished, capsys):
    info = json.loads((finished / "config.json").read_text())["run_info"]
    assert info["command"].startswith("hprior train --task toy_point")
    assert info["versions"]["jax"] == jax.__version__ and "cpu" in info["device"]
    assert info["git_commit"] is None or len(info["git_commit"]) >= 40
    assert b"\r" not in (finished / "eval.csv").read_bytes()
    assert cli.main(["--version"]) == 0
    assert capsys.readouterr().out.startswith(f"hprior_jax {hprior_jax.__version__}")


def test_tensorboard_reads_the_logs(finished):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(finished / "tb" / "seed_1"))
    acc.Reload()
    tags = acc.Tags()["scalars"]
    assert "eval/true_return" in tags and "train/critic_loss" in tags
    assert [e.step for e in acc.Scalars("eval/true_return")][:2] == [40, 80]


def test_learning_curve_shows_success_beside_return(finished):
    import matplotlib.image

    width = matplotlib.image.imread(finished / "learning_curve.png").shape[1]
    assert width >= 2 * 6 * 120 * 0.95  # two 6-inch panels at 120 dpi: the toy has success


# -- eval and export -------------------------------------------------------------------------

def test_eval_of_a_checkpoint_repeats_its_evaluation(finished, capsys):
    """With the run's episode count, `hprior eval` runs the episodes of eval.csv's row."""
    assert cli.main(["eval", "--run", str(finished), "--step", "80", "--episodes", "2"]) == 0
    printed = capsys.readouterr().out
    logged = {int(r[1]): float(r[2]) for r in _rows(finished / "eval.csv")[1:] if r[0] == "80"}
    rows = list(csv.DictReader(open(finished / "eval_step80_2ep.csv")))
    assert {int(r["seed"]): float(r["true_return"]) for r in rows} == pytest.approx(logged,
                                                                                     rel=1e-5)
    assert "seed 1: true return" in printed and "success" in printed
    assert cli.main(["eval", "--run", str(finished), "--step", "7"]) == 2
    assert "keeps checkpoints at steps" in capsys.readouterr().err


def test_export_loads_a_pure_policy_without_the_run(finished, tmp_path):
    from hprior_jax.runs.restore import restore_run

    assert cli.main(["export", "--run", str(finished), "--seed", "2",
                     "--out", str(tmp_path / "exp")]) == 0
    policy = hprior_jax.load_policy(tmp_path / "exp")
    restored = restore_run(finished)
    obs = np.random.default_rng(0).normal(size=(5, 2)).astype(np.float32)
    expect = restored.engine.sac.act(restored.of_seed(2).sac.actor, obs, None,
                                     deterministic=True)
    np.testing.assert_allclose(np.asarray(jax.jit(policy)(obs)), np.asarray(expect), rtol=1e-6)
    with pytest.raises(ValueError, match="learns no reward"):
        hprior_jax.load_reward(tmp_path / "exp")


def test_render_frames_and_video(tmp_path):
    """Offscreen rendering of a real task (OSMesa, installed by .ci/setup) to an MP4."""
    import imageio.v3 as iio
    import mujoco

    import tasks
    from hprior_jax.render import render_frames, write_video

    model = tasks.make("cheetah_run").mj_model
    data = mujoco.MjData(model)
    qpos = np.stack([data.qpos.copy(), data.qpos + 0.3])
    frames = render_frames(model, {"qpos": qpos}, width=64, height=48)
    assert frames.shape == (2, 48, 64, 3) and frames.std() > 10
    assert np.abs(frames[0].astype(int) - frames[1]).mean() > 1  # the pose shows
    path = write_video(np.repeat(frames, 4, axis=0), tmp_path / "v.mp4", fps=20)
    assert iio.imread(path).shape[:1] == (8,)


# -- the command line ------------------------------------------------------------------------

def test_progress_bar_has_one_rate_and_an_eta(capsys, monkeypatch):
    def one_evaluation():
        bar = ProgressBar(total=1000, initial=0, enabled=True, num_seeds=2, has_success=True)
        bar.evaluated(-3.0, 0.5, seconds=0.1)
        bar.advance(100, 0.5)  # 100 steps per seed in 0.5 s of training, 0.1 s evaluating
        bar.close()
        return capsys.readouterr()

    # a log file (capsys: not a terminal): one plain line per evaluation, no \r frames
    logged = one_evaluation()
    assert "\r" not in logged.out + logged.err
    line = logged.out.strip().splitlines()[-1]
    assert line.startswith("step 100/1000: 400 env steps/s, ETA 0:00:04"), line
    assert "success 50%" in line and "evaluation 20% of the time" in line, line
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)  # a terminal: the bar
    line = one_evaluation().err.strip().splitlines()[-1].split("\r")[-1]
    assert "400 env steps/s, ETA 0:00:04" in line and line.count("/s") == 1, line
    assert "success 50%" in line and "evaluation 20% of the time" in line, line


def test_eval_budget_cpu_halves_episodes_and_cadence(tmp_path, monkeypatch, capsys):
    runs = []
    monkeypatch.setattr(host, "run", lambda engine, run_dir, **kw: runs.append(engine.cfg))
    base = ["train", "--task", "toy_point", "--preset", "reduced", "--algo", "sac"]
    assert cli.main([*base, "--out", str(tmp_path / "a")]) == 0
    assert cli.main([*base, "--eval-budget", "cpu", "--out", str(tmp_path / "b")]) == 0
    assert cli.main([*base, "--eval-budget=cpu", "--num-eval-episodes", "3",
                     "--out", str(tmp_path / "c")]) == 0  # an explicit flag still wins
    paper, cpu, explicit = runs
    assert paper.num_eval_episodes == 10 and paper.eval_every != 10_000
    assert (cpu.num_eval_episodes, cpu.eval_every) == (5, 10_000)
    assert (explicit.num_eval_episodes, explicit.eval_every) == (3, 10_000)
    assert cli.main([*base, "--eval-budget", "tiny", "--out", str(tmp_path / "d")]) == 2
    assert "unknown evaluation budget 'tiny'" in capsys.readouterr().err


def test_cli_accepts_flag_equals_value_and_lists_its_options(tmp_path, capsys, monkeypatch):
    runs = []
    monkeypatch.setattr(host, "run", lambda engine, run_dir, **kw: runs.append(engine.cfg))
    assert cli.main(["train", "--task=toy_point", "--preset=smoke", "--algo=pebble",
                     "--feedback=20", "--steps=200", "--num-eval-episodes=2",
                     f"--out={tmp_path / 'eq'}", "--teacher=mistake"]) == 0
    cfg = runs[0]
    assert (cfg.task, cfg.algo, cfg.steps, cfg.pebble.max_feedback) == ("toy_point", "pebble",
                                                                        200, 20)
    assert cfg.pebble.teacher.eps_mistake == 0.1
    with pytest.raises(SystemExit):
        cli.main(["train", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    for word in ("--resume", "--no-progress", "--teacher", "cheetah_run", "drawer_open",
                 "prior_nrp", "bisim"):
        assert word in text


def test_grid_passes_eval_budget_and_contacts_as_overrides(tmp_path, monkeypatch):
    from hprior_jax.experiments import grid

    seen = []
    monkeypatch.setattr(grid, "run_grid", lambda out, tasks, algos, seeds, preset, overrides,
                        **k: seen.append(overrides))
    assert cli.main(["grid", "--tasks", "toy_point", "--out", str(tmp_path)]) == 0
    assert cli.main(["grid", "--tasks", "toy_point", "--eval-budget", "cpu", "--contacts",
                     "all", "--contact-cap", "none", "--eval-every", "3000",
                     "--capture-video", "4", "--out", str(tmp_path)]) == 0
    assert seen == [{"contacts": "floor", "contact_cap": "task", "hand": "arm",
                     "wrist": "task", "capture_video": 0},
                    {"contacts": "all", "contact_cap": "none", "hand": "arm", "wrist": "task",
                     "num_eval_episodes": 5, "eval_every": 3000, "capture_video": 4}]
    # each physics option reaches only the tasks of its domain
    physics = {"contacts": "all", "contact_cap": "none", "hand": "free"}
    cfg = grid.run_config(tmp_path, "drawer_open", "sac", (1,), "smoke", physics)
    assert (cfg.contacts, cfg.contact_cap, cfg.hand) == ("floor", "none", "free")
    cfg = grid.run_config(tmp_path, "cheetah_run", "sac", (1,), "smoke", physics)
    assert (cfg.contacts, cfg.contact_cap, cfg.hand) == ("all", "none", "arm")
    physics = {"contact_cap": "none", "wrist": "box"}
    cfg = grid.run_config(tmp_path, "button_press", "sac", (1,), "smoke", physics)
    assert (cfg.contact_cap, cfg.wrist) == ("none", "box")
    # the box wrist is an option of button_press alone (the others' registered wrist)
    for task in ("cheetah_run", "drawer_open"):
        assert grid.run_config(tmp_path, task, "sac", (1,), "smoke", physics).wrist == "task"
    with pytest.raises(ValueError, match="--hand free"):
        grid.run_config(tmp_path, "button_press", "sac", (1,), "smoke", {**physics, "hand": "free"})


def test_grid_and_train_share_the_preset_flag_and_default(tmp_path, monkeypatch):
    from hprior_jax.experiments import grid

    seen = []
    monkeypatch.setattr(grid, "run_grid", lambda out, tasks, algos, seeds, preset, *a, **k:
                        seen.append(preset))
    assert cli.main(["grid", "--tasks", "toy_point", "--out", str(tmp_path)]) == 0
    assert cli.main(["grid", "--tasks", "toy_point", "--preset=smoke", "--out", str(tmp_path)]) == 0
    assert cli.main(["grid", "--tasks", "toy_point", "--budget", "reduced",
                     "--out", str(tmp_path)]) == 0
    from hprior_jax.config import DEFAULT_PRESET

    assert seen == [DEFAULT_PRESET, "smoke", "reduced"]
    runs = []
    monkeypatch.setattr(host, "run", lambda engine, run_dir, **kw: runs.append(engine.cfg))
    assert cli.main(["train", "--task", "toy_point", "--out", str(tmp_path / "t")]) == 0
    assert runs[0].preset == DEFAULT_PRESET


@pytest.mark.parametrize("argv, says", [
    # train: the run directory
    (["train", *TOY, "--out", "{file}"], "is a file, not a directory"),
    (["train", *TOY, "--out", "{file}/run"], "is a file, so no directory can be made"),
    (["train", *TOY, "--out", "{busy}"], "not a run directory (no config.json)"),
    (["train", *TOY, "--out", "{run}"], "hprior train --resume"),
    # train: the configuration, before anything is written
    (["train", *TOY, "--algo", "pebble", "--pebble.segment-len", "5000", "--out", "{new}"],
     "must be shorter than the episode"),
    (["train", "--task", "nope", "--out", "{new}"], "available tasks"),
    (["train", *TOY, "--algo", "ppo", "--out", "{new}"], "unknown"),
    (["train", *TOY, "--preset", "huge", "--out", "{new}"], "unknown preset"),
    (["train", *TOY, "--seeds", "1", "1", "--out", "{new}"], "duplicates"),
    (["train", *TOY, "--steps", "0", "--out", "{new}"], "--steps must be positive"),
    (["train", *TOY, "--num-seed-steps", "999", "--steps", "100", "--out", "{new}"],
     "--num-seed-steps"),
    (["train", *TOY, "--teacher", "grumpy", "--algo", "pebble", "--out", "{new}"],
     "unknown teacher"),
    (["train", *TOY, "--teacher", "oracle", "--out", "{new}"], "asks no teacher"),
    (["train", *TOY, "--prior.lam", "-1", "--algo", "prior", "--out", "{new}"], "--prior.lam"),
    # resume
    (["train", "--resume", "{missing}"], "is not a run directory"),
    (["train", "--resume", "{busy}"], "is not a run directory"),
    (["train", "--resume", "{run}", "--task", "cheetah_run"],
     "--task ('toy_point' -> 'cheetah_run')"),
    (["train", "--resume", "{run}", "--sac.batch-size", "4"], "these cannot change"),
    # the other commands
    (["eval", "--run", "{missing}"], "is not a run directory"),
    (["eval", "--run", "{run}", "--episodes", "0"], "--episodes must be positive"),
    (["export", "--run", "{run}", "--out", "{busy}"], "not a run directory"),
    (["export", "--run", "{run}", "--seed", "99", "--out", "{new}"], "--seed 99 is not in"),
    (["attention", "--run", "{missing}"], "is not a run directory"),
    (["attention", "--run", "{run}"], "attention maps need a method with a world model"),
    (["report", "{missing}"], "is not a directory"),
    (["report", "{busy}"], "no run directories with eval.csv under"),
    (["grid", "--tasks", "toy_point", "--algos", "ppo", "--out", "{new}"], "unknown algorithm"),
    (["grid", "--tasks", "toy_point", "--algos", "sac", "--out", "{run}"],
     "is a run directory of `hprior train`, not a grid's results folder"),
    (["frobnicate"], "unknown command"),
])
def test_bad_input_ends_with_one_clear_line(argv, says, finished, tmp_path, capsys):
    """Exit 2, one line on stderr that says what is wrong, no traceback, nothing written."""
    (tmp_path / "file").write_text("x")
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "notes.txt").write_text("mine")
    paths = dict(file=tmp_path / "file", busy=tmp_path / "busy", run=finished,
                 new=tmp_path / "new", missing=tmp_path / "missing")
    argv = [a.format(**paths) for a in argv]
    listing = sorted(p.name for p in tmp_path.rglob("*"))
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert says in err and "Traceback" not in err, err
    assert len(err.strip().splitlines()) == 1 or err.startswith("unknown command"), err
    assert sorted(p.name for p in tmp_path.rglob("*")) == listing  # nothing written


def test_an_out_without_write_permission_is_refused_by_name(tmp_path, monkeypatch):
    """(Root ignores permissions, so the check's answer is faked, not the folder's mode.)"""
    from hprior_jax.runs import run_dir

    monkeypatch.setattr(run_dir.os, "access", lambda path, mode: path != tmp_path)
    with pytest.raises(run_dir.RunDirError, match=f"no permission to write in {tmp_path}"):
        run_dir.check_out_dir(tmp_path / "a" / "b")
