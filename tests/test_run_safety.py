"""A run directory is never left broken: an extension of the budget becomes the run's only
once it has a checkpoint (a stop before that rolls it back, one after it commits), one
writer per directory (two real processes), and a damaged newest checkpoint is skipped for
the newest readable one by resume and eval."""
import logging
import shutil
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest

from hprior_jax import cli, dir_lock
from hprior_jax.loop import checkpoints, host
from hprior_jax.runs.restore import restore_run
from hprior_jax.loop.run_files import EXTENDING
from hprior_jax.runs.run_dir import load_run_config
from tests.test_life_cycle import TOY, _rows, _train, finished as base  # noqa: F401

ROOT = Path(__file__).resolve().parent.parent


def _same_state(a: Path, b: Path):
    for x, y in zip(jax.tree.leaves(restore_run(a).state), jax.tree.leaves(restore_run(b).state),
                    strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_an_extension_stopped_before_its_checkpoint_rolls_back_and_one_after_commits(
        base, tmp_path, monkeypatch, capsys):
    clean, before, after = (tmp_path / n for n in ("clean", "before", "after"))
    for d in (clean, before, after):
        shutil.copytree(base, d)
    assert _train("--resume", str(clean), "--steps", "120") == 0  # the uninterrupted one

    # stopped while restoring: nothing of the extension was saved
    real_run = host.run

    def stopped(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(host, "run", stopped)
    assert _train("--resume", str(before), "--steps", "120") == 130
    monkeypatch.setattr(host, "run", real_run)
    assert load_run_config(before).steps == 80 and (before / EXTENDING).exists()
    capsys.readouterr()
    assert _train("--resume", str(before)) == 0  # as configured: nothing left to train
    assert "rolled back" in capsys.readouterr().err and not (before / EXTENDING).exists()
    assert _train("--resume", str(before), "--steps", "120") == 0

    # stopped (kill -9 alike) right after the extension's first checkpoint, before the commit
    real_commit = checkpoints.commit_extension
    monkeypatch.setattr(checkpoints, "commit_extension", lambda run_dir: (_ for _ in ()).throw(
        KeyboardInterrupt()))
    assert _train("--resume", str(after), "--steps", "120") == 130
    monkeypatch.setattr(checkpoints, "commit_extension", real_commit)
    assert load_run_config(after).steps == 80  # not yet the run's ...
    capsys.readouterr()
    assert _train("--resume", str(after)) == 0  # ... until the next start sees the checkpoint
    assert "had checkpointed" in capsys.readouterr().err
    assert load_run_config(after).steps == 120 and (after / "config.steps80.json").exists()

    for d in (before, after):
        assert _rows(d / "eval.csv") == _rows(clean / "eval.csv")
        _same_state(d, clean)


def _holder(directory: Path) -> subprocess.Popen:
    """Another real process that holds `directory`'s lock until killed."""
    code = ("import sys, time; from hprior_jax import dir_lock; "
            "dir_lock.hold(sys.argv[1]); print('held', flush=True); time.sleep(600)")
    proc = subprocess.Popen([sys.executable, "-c", code, str(directory)], cwd=ROOT,
                            stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "held"
    return proc


def test_a_directory_has_one_writer_and_a_dead_holders_lock_is_taken_over(base, tmp_path,
                                                                           capsys):
    run = tmp_path / "run"
    shutil.copytree(base, run)
    holder = _holder(run)
    try:
        before = (run / "eval.csv").read_text()
        assert _train("--resume", str(run), "--steps", "120") == 2
        err = capsys.readouterr().err
        assert f"{run} is in use by PID {holder.pid} (started " in err and err.count("\n") == 1
        assert (run / "eval.csv").read_text() == before and not (run / EXTENDING).exists()
        with pytest.raises(dir_lock.DirInUse):
            dir_lock.hold(run)
        grid_dir = tmp_path / "grid"
        grid_holder = _holder(grid_dir)
        assert cli.main(["grid", "--tasks", "toy_point", "--algos", "sac", "--out",
                         str(grid_dir)]) == 2
        assert "is in use by PID" in capsys.readouterr().err
        grid_holder.kill()
        folder = tmp_path / "queries"
        folder.mkdir()
        (folder / "queries.jsonl").write_text("")  # a query folder (empty)
        folder_holder = _holder(folder)
        assert cli.main(["label", "--dir", str(folder), "--port", "0"]) == 2
        assert "is in use by PID" in capsys.readouterr().err
        folder_holder.kill()
    finally:
        holder.kill()
        holder.wait()
    time.sleep(0.1)
    lock = dir_lock.hold(run)  # the holder is gone: its lock with it
    lock.release()
    assert _train("--resume", str(run), "--steps", "120") == 0


def _truncate_a_file_of(checkpoint: Path):
    files = sorted((p for p in checkpoint.rglob("*") if p.is_file() and p.stat().st_size > 64),
                   key=lambda p: -p.stat().st_size)
    with open(files[0], "r+b") as f:
        f.truncate(files[0].stat().st_size // 2)


def test_a_damaged_newest_checkpoint_is_skipped_by_eval_and_resume(base, tmp_path, capsys):
    run = tmp_path / "run"
    shutil.copytree(base, run)
    _truncate_a_file_of(run / "checkpoints" / "80")
    capsys.readouterr()
    assert cli.main(["eval", "--run", str(run), "--episodes", "2"]) == 0
    out = capsys.readouterr()
    assert "at step 40" in out.out and "step 80 cannot be restored" in out.err
    assert out.err.count("\n") == 1 and "Traceback" not in out.err
    assert _train("--resume", str(run)) == 0  # from step 40 back to 80
    out = capsys.readouterr()
    # one short line, naming the step it resumes from, before the run says it resumes there
    said = [line for line in out.err.splitlines() if "cannot be restored" in line]
    assert len(said) == 1 and said[0].endswith(
        f"; moved to {run / 'broken_checkpoints' / '80'}, resuming from step 40"), said
    assert len(said[0]) - len(str(run)) < 200, said
    assert "resuming from step 40 of 80" in out.out and "step 80 of" not in out.out
    assert (run / "broken_checkpoints" / "80").exists()
    assert _rows(run / "eval.csv") == _rows(base / "eval.csv")
    _same_state(run, base)


def test_an_unreadable_checkpoints_reason_is_one_short_line():
    """orbax and TensorStore errors carry object reprs and bracketed specs: not in a line."""
    error = ValueError("NOT_FOUND: Error opening \"zarr3\" driver: "
                       "<tensorstore_cc.KvStore object at 0x7f3a2c1b9e70> " + "x" * 300
                       + " [source locations='tensorstore/driver/zarr3/driver.cc:571']"
                       "\n[tensorstore_spec='{...}']")
    line = checkpoints.first_line(error)
    assert line.startswith("ValueError: NOT_FOUND: Error opening")
    assert len(line) <= 100 and "0x7f" not in line and "source locations" not in line


def test_keep_checkpoints_zero_keeps_every_one(tmp_path):
    out = tmp_path / "all"
    assert _train("--steps", "80", "--checkpoint-every", "20", "--keep-checkpoints", "0",
                  "--out", str(out)) == 0
    assert sorted(int(p.name) for p in (out / "checkpoints").iterdir()
                  if p.name.isdigit()) == [20, 40, 60, 80]


def _start_training(out: Path) -> subprocess.Popen:
    args = [*TOY, "--steps", "400000", "--replay-capacity", "4000", "--checkpoint-every",
            "400000", "--out", str(out), "--no-progress"]
    # the imports done, it leaves a mark (Python's own imports are not the command's: a
    # Ctrl-C there is Python's KeyboardInterrupt, however busy the machine makes them)
    code = ("import os, sys; from tests.toy_task import ensure_registered; ensure_registered(); "
            "from hprior_jax import cli; open(os.environ['IMPORTED_MARK'], 'w').close(); "
            "sys.exit(cli.main(sys.argv[1:]))")
    import os

    return subprocess.Popen([sys.executable, "-c", code, "train", *args], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONPATH": str(ROOT),
                                 "IMPORTED_MARK": str(out.parent / "imported")})


WHEN = {  # what must exist (or not) when the signal is sent
    # the command started: checking the configuration, building the engine
    "start-up": lambda out, started: (out.parent / "imported").exists(),
    # the run directory made, no chunk trained yet
    "compile": lambda out, started: (out / "config.json").exists(),
    "training": lambda out, started: ((out / "eval.csv").exists()
                                      and len(_rows(out / "eval.csv")) >= 3),
}


@pytest.mark.parametrize("when", ["start-up", "compile", "training"])
def test_ctrl_c_at_any_point_ends_130_with_a_resumable_directory_or_none(when, tmp_path,
                                                                         capsys):
    import signal

    out = tmp_path / "run"
    started = time.time()
    proc = _start_training(out)
    deadline = started + 240
    while time.time() < deadline and proc.poll() is None and not WHEN[when](out, started):
        time.sleep(0.05)
    assert proc.poll() is None, proc.communicate()
    proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=240)
    assert proc.returncode == 130, stderr
    assert "Traceback" not in stderr and "Exception ignored" not in stderr, stderr
    if not (out / "config.json").exists():
        assert not out.exists() or not any(out.iterdir())  # nothing left behind
        return
    step = (max((int(p.name) for p in (out / "checkpoints").iterdir() if p.name.isdigit()),
                default=0) if (out / "checkpoints").exists() else 0)
    assert _train("--resume", str(out), "--steps", str(step + 20)) == 0
    assert load_run_config(out).steps == step + 20


@pytest.mark.parametrize("site", ["log", "checkpoint"])
def test_an_io_error_ends_with_one_line_and_the_run_still_resumes(site, base, tmp_path,
                                                                   monkeypatch, capsys):
    """A full disk faked where a run writes (its logs; a checkpoint, leaving orbax's
    half-written folder): one line naming the path and the cause, rc 1, and the next
    resume continues from the last checkpoint as if nothing happened."""
    import errno

    from hprior_jax.checkpoint import Checkpointer
    from hprior_jax.run_log import RunLog

    run = tmp_path / "run"
    shutil.copytree(base, run)
    full = lambda path: OSError(errno.ENOSPC, "No space left on device", str(path))
    if site == "log":
        def write(self, *args, **kwargs):
            raise full(self.eval_csv_path)
        monkeypatch.setattr(RunLog, "log_eval", write)
    else:
        def write(self, step, state, metadata=None):
            (self.directory / f"{step}.orbax-checkpoint-tmp-1").mkdir()
            raise full(self.directory / f"{step}.orbax-checkpoint-tmp-1")
        monkeypatch.setattr(Checkpointer, "save", write)
    capsys.readouterr()
    assert _train("--resume", str(run), "--steps", "120") == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "No space left on device" in err[0] and str(run) in err[0], err
    monkeypatch.undo()
    clean = tmp_path / "clean"
    shutil.copytree(base, clean)
    assert _train("--resume", str(clean), "--steps", "120") == 0
    assert _train("--resume", str(run), "--steps", "120") == 0
    assert _rows(run / "eval.csv") == _rows(clean / "eval.csv")


def test_a_checkpoint_without_a_render_field_recorded_since_restores_with_zeros(tmp_path):
    """A replay buffer's recorded physics gained a field after the checkpoint was written
    (MetaWorld's object placement): the rest restores, the new field stays `like`'s."""
    from flax import struct

    from hprior_jax.checkpoint import Checkpointer
    from hprior_jax.loop.checkpoints import restore_latest

    @struct.dataclass
    class Replay:
        obs: jax.Array
        physics: dict

    @struct.dataclass
    class State:
        replay: Replay

    ckpt = Checkpointer(tmp_path / "checkpoints")
    ckpt.save(5, State(Replay(np.arange(3.0), {"qpos": np.ones((3, 2))})))
    like = State(Replay(np.zeros(3), {"qpos": np.zeros((3, 2)), "placement": np.zeros((3, 3))}))
    step, state = restore_latest(ckpt, like)
    ckpt.close()
    assert step == 5 and np.array_equal(state.replay.obs, np.arange(3.0))
    physics = state.replay.physics
    assert np.all(physics["qpos"] == 1) and np.all(physics["placement"] == 0)


def _run_as_hprior(tmp_path: Path, body: str, *args: str) -> subprocess.CompletedProcess:
    """A script named `hprior` (what the console script is called) running `body`."""
    import os

    script = tmp_path / "bin" / "hprior"
    script.parent.mkdir(exist_ok=True)
    script.write_text("import os, signal, sys\n" + body)
    return subprocess.run([sys.executable, str(script), *args], cwd=ROOT, text=True,
                          capture_output=True, timeout=240,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})


def test_ctrl_c_while_the_command_imports_is_one_line_and_130(tmp_path):
    body = ("import hprior_jax  # the console script's first import\n"
            "os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C while the rest imports\n"
            "from hprior_jax.cli import main\n"
            "sys.exit(main())\n")
    done = _run_as_hprior(tmp_path, body, "train", "--out", str(tmp_path / "run"))
    assert done.returncode == 130 and done.stderr == "interrupted\n", done.stderr
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("out_existed", [False, True])
def test_ctrl_c_before_the_first_chunk_leaves_no_half_made_run_directory(out_existed,
                                                                         tmp_path):
    """Ctrl-C once the engine is built, before the run directory is made: the command ends
    130 as if it had never run (an --out that existed empty stays empty), so the same
    command line can be typed again."""
    out = tmp_path / "run"
    if out_existed:
        out.mkdir()
    body = ("from tests.toy_task import ensure_registered; ensure_registered()\n"
            "from hprior_jax.cli import main\n"
            "from hprior_jax.runs import build\n"
            "built = build.build_engine\n"
            "def build_engine(*a, **k):\n"
            "    engine = built(*a, **k)\n"
            "    os.kill(os.getpid(), signal.SIGINT)\n"
            "    return engine\n"
            "build.build_engine = build_engine\n"
            "sys.exit(main())\n")
    done = _run_as_hprior(tmp_path, body, "train", *TOY, "--steps", "40", "--out", str(out),
                          "--no-progress")
    assert done.returncode == 130 and "Traceback" not in done.stderr, done.stderr
    assert done.stderr.strip().splitlines()[-1] == "interrupted", done.stderr
    assert (list(out.iterdir()) == []) if out_existed else not out.exists()


def test_orbaxs_notes_that_say_nothing_to_a_user_stay_off_the_terminal(caplog):
    """What orbax logs through absl about a slow previous save, an unfinished save's folder
    removed on resume, or item metadata it cannot read is not shown; its other warnings are."""
    from absl import logging as absl_logging

    import hprior_jax.checkpoint  # noqa: F401  (installs the filter)

    noise = ["Waiting for previous save to complete took 12.5 seconds. If this number is high,"
             " consider checkpointing less frequently.",
             "Attempted to create temporary directory /r/checkpoints/80.orbax-checkpoint-tmp-1"
             " which already exists. Removing existing directory since it is not finalized.",
             "Failed to get item metadata from directory /r/checkpoints/80/state. Either it was"
             " not present in the checkpoint, or the handler does not support it."]
    with caplog.at_level(logging.WARNING, logger="absl"):
        for line in noise + ["a warning a user should see"]:
            absl_logging.warning(line)
    assert [r.getMessage() for r in caplog.records] == ["a warning a user should see"]
