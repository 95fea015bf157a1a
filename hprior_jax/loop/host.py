"""The host loop: schedule chunks and events, guard against NaN, log, evaluate, checkpoint.

Everything here runs between compiled programs; it knows phases, events and metric groups
only as the engine and the method name them.
"""
from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
import time
from functools import partial
from pathlib import Path

import jax
import numpy as np

from hprior_jax.buffers import replay
from hprior_jax.labelling.teacher import LabellingStopped
from hprior_jax.loop import devices
from hprior_jax.loop.engine import Engine
from hprior_jax.loop.run_dir import commit_extension, legacy_checkpoint_name
from hprior_jax.loop.state import RunState

UNCHECKED = ("episode/", "perf/")  # metric groups that may legitimately be non-finite or are ours


class TrainingDiverged(RuntimeError):
    pass


class Interrupted(Exception):
    """The user pressed Ctrl-C (the chunk in flight finished), or a person's round stopped
    waiting for answers: a checkpoint of step `step` is in the run directory."""

    def __init__(self, run_dir: Path, step: int, why: str = ""):
        super().__init__(f"interrupted at step {step}{': ' + why if why else ''}; "
                         f"checkpoint saved in {run_dir}")
        self.run_dir, self.step = run_dir, step


AHEAD_WHEN = ("after_first", "first_phase_apart", "at_start", "off")


def run(cfg, run_dir: Path, resume: bool = False, progress: bool = True,
        max_chunks: int | None = None, saved_capacity: int | None = None,
        engine: Engine | None = None, interrupt: "StopRequest | None" = None,
        labelling=None, compile_ahead: str = "after_first") -> RunState:
    """Trains `cfg` into `run_dir` (made by `prepare_run_dir`, or an existing run to resume).

    `max_chunks` stops early after that many chunks (used by tests to simulate an
    interruption); the state is checkpointed at the stop. `saved_capacity` is the replay
    capacity of the checkpoints when a resumed run's budget was extended. `engine`: one
    already built for `cfg` (the CLI builds it before writing anything, so configuration
    errors leave no run directory behind). `interrupt`: a `StopRequest` shared by runs that
    train side by side in threads (the grid's), which the main thread's Ctrl-C sets.
    `labelling`: where and how long a method that asks a person waits for answers
    (`hprior_jax.labelling.teacher.AskOptions`; default: 127.0.0.1:8765, an hour).
    `compile_ahead`: when to start compiling the later programs (evaluation, the method's
    events, other chunk lengths) in a background thread (`Engine.compile_run_ahead`):
    "after_first" (default) once the main thread has compiled the first chunk's program
    (while the background thread compiles the episode-starts and initial-state programs,
    `Engine.compile_start`);
    "first_phase_apart" the same, but the first phase's chunks (random actions) run a
    program of that phase alone, quicker to compile (`Engine._chunk_name`); "at_start"
    before the first chunk's compile (the two compiles then share the cores and the first
    env step comes later); "off" (each program when first needed).
    Each chunk's perf records hold its wall time by part; the first chunk's also
    `perf/first_step_s` (process start to its first env step), and its `perf/compile_s`
    counts the compiles the run waited for before it (the episode starts, the initial
    state, its program).

    The first Ctrl-C lets the chunk in flight finish, writes a checkpoint and raises
    `Interrupted`; a second one stops the process at once (the default SIGINT action)."""
    from hprior_jax.checkpoint import Checkpointer
    from hprior_jax.run_log import RunLog

    run_dir = Path(run_dir)
    engine = engine or Engine(cfg)
    seeds = list(cfg.seeds)
    keep = cfg.keep_checkpoints or None  # None: orbax keeps every one
    ckpt = Checkpointer(run_dir / "checkpoints", max_to_keep=keep)
    step = 0
    if compile_ahead not in AHEAD_WHEN:
        raise ValueError(f"compile_ahead={compile_ahead!r}: one of {AHEAD_WHEN}")
    # a run cut short (tests) would compile programs it never runs
    ahead = compile_ahead if max_chunks is None else "off"
    engine.first_phase_apart = ahead == "first_phase_apart"
    capacity = saved_capacity if resume else None
    if ahead in ("after_first", "first_phase_apart"):  # the first chunk's program first
        engine.compile_start(seeds, (ckpt.latest_step() or 0) if resume else 0, capacity)
    rs = engine.init_seeds(seeds, capacity=capacity)
    # the first states, the first chunk's program: counted with the first chunk
    start_compile_s = sum(engine.compile_seconds.values())
    if resume and ckpt.latest_step() is not None:
        broken = []
        step, rs = restore_latest(ckpt, rs, on_unreadable=lambda bad, error: broken.append(
            _set_aside(run_dir, bad, error)))
        if broken:  # the manager lists the steps it found when it was opened
            ckpt.close()
            ckpt = Checkpointer(run_dir / "checkpoints", max_to_keep=keep)
    if rs.replay.capacity != cfg.capacity:
        ring = rs.replay.replace(size=devices.fetch(rs.replay.size),
                                 index=devices.fetch(rs.replay.index))
        if replay.has_wrapped(ring):
            raise ValueError("the replay buffer of this run has wrapped around; it cannot be "
                             "extended with --steps (start a new run instead)")
        grow = engine.per_seed(partial(replay.grow, capacity=cfg.capacity))
        rs = rs.replace(replay=grow(engine.place(rs.replay)))
    rs = engine.place(rs)  # a restored state: onto this run's devices, whatever wrote it
    # the chunk writes transition `t` at ring position t % capacity (unbatched, in place)
    if np.any(devices.fetch(rs.replay.index) != step % rs.replay.capacity):
        raise ValueError(f"{run_dir}: the replay buffer's write position does not match step "
                         f"{step}; the checkpoint is not from this run")
    primary = devices.is_primary()  # with several processes, one writes the logs
    log = RunLog(run_dir, seeds, resume_step=step if resume else None) if primary else _NoLog()
    has_success = engine.task.has_success
    last_ckpt = step
    bar = _ProgressBar(cfg.steps, step, progress and primary, len(seeds), has_success)
    chunks, warned_cap = 0, False
    events = set(engine.event_steps())
    own_interrupt = interrupt is None
    interrupt = interrupt or StopRequest()
    try:
        engine.person = _person(engine, run_dir, labelling, interrupt, bar) if primary else None
        if ahead == "at_start":
            engine.compile_run_ahead(rs, step)
        while step < cfg.steps and (max_chunks is None or chunks < max_chunks):
            # the first chunk also reports the programs compiled before the loop
            compiled_before = set(engine.compile_seconds) if chunks else set()
            timer = _WallTimer(engine.compile_seconds)  # wall time per part, compiles apart
            if chunks == 0:
                timer.seconds["compile_s"] += start_compile_s
            if step in events:  # e.g. a feedback round: before this step's update
                if engine.method.asks_person and last_ckpt != step:
                    # a person may stop the run while the round waits: it resumes from here
                    _save(ckpt, step, rs, run_dir, bar)
                    last_ckpt = step
                waited = engine.person.waited_s if engine.person is not None else 0.0
                with timer("event_s"), _stopped_waiting(run_dir, step):
                    rs, event_metrics = engine.run_event(rs, step)
                    event_metrics = devices.fetch(event_metrics)
                if engine.person is not None:  # a person's time is not the event's
                    timer.move("event_s", "label_wait_s", engine.person.waited_s - waited)
                _finite_or_raise(event_metrics, step, step, seeds, run_dir, last_ckpt)
                for i, s in enumerate(seeds):
                    log.log(step, s, {k: np.asarray(v)[i] for k, v in event_metrics.items()})
            phase, length = engine.chunk_plan(step)
            with timer("chunk_s"):  # env steps and agent updates: one fused program
                program = engine.compiled_chunk(rs, step, length)
                first_step = process_age() if chunks == 0 else None
                if chunks == 0 and ahead in ("after_first", "first_phase_apart"):
                    engine.compile_run_ahead(rs, step)  # before the chunk: it donates rs
                starts = engine.episode_starts(rs, step)
                rs, metrics = program(rs, np.int32(step), starts)
                metrics = devices.fetch(metrics)
            keep = engine.phase_metrics(phase)  # drop placeholders of other phases
            metrics = {k: v for k, v in metrics.items()
                       if not k.startswith("train/") or k in keep}
            _finite_or_raise(metrics, step, step + length, seeds, run_dir, last_ckpt)
            _log_chunk(log, seeds, step, metrics, has_success)
            at_cap = float(np.mean(metrics.get("physics/contacts_at_cap", 0.0)))
            if at_cap and not warned_cap:  # once per run: the share is in metrics.jsonl
                warned_cap = True
                bar.write(f"warning: MJX's contact cap was full at {at_cap:.1%} of steps "
                          f"{step}-{step + length}: contacts may have been dropped there "
                          "(physics/contacts_at_cap in metrics.jsonl; --contact-cap none "
                          "simulates every contact)")
            step += length
            chunks += 1
            if step % cfg.eval_every == 0 or step == cfg.steps:
                with timer("eval_s"):
                    returns, successes = devices.fetch(engine.run_eval(rs, seeds, step))
                for i, s in enumerate(seeds):
                    log.log_eval(step, s, float(np.mean(returns[i])),
                                 float(np.mean(successes[i])) if has_success else None)
                bar.evaluated(np.mean(returns), np.mean(successes), timer.seconds["eval_s"])
            stop = interrupt.requested  # read once: a checkpoint is written for every stop
            if step % cfg.checkpoint_every == 0 or step == cfg.steps or stop or (
                    max_chunks is not None and chunks == max_chunks):
                log.flush()
                with timer("checkpoint_s"):
                    _save(ckpt, step, rs, run_dir, bar)
                last_ckpt = step
            perf = {"perf/env_steps_per_s": length * len(seeds) / max(timer.seconds["chunk_s"],
                                                                      1e-9)}
            perf.update({f"perf/{k}": v for k, v in timer.seconds.items() if v or k == "chunk_s"})
            if first_step is not None:  # how long this process took to its first env step
                perf["perf/first_step_s"] = first_step
            for s in seeds:
                log.log(step, s, perf)
            log.flush()  # a crash or kill loses at most the chunk in flight
            for name in sorted(set(engine.compile_seconds) - compiled_before):
                ahead, waited = engine.ahead_seconds.get(name), engine.compile_seconds[name]
                bar.write(f"compiled {name} in {waited:.1f} s" if ahead is None else
                          f"compiled {name} in the background in {ahead:.1f} s (the run "
                          f"waited {waited:.1f} s for it)")
            if chunks == 1:
                bar.write("  (compiles: once per shape, not counted in env steps/s; cached in "
                          "$HPRIOR_JAX_CACHE for the next start)")
            bar.advance(length, sum(v for k, v in timer.seconds.items()
                                    if k not in ("compile_s", "label_wait_s")))
            if stop and step < cfg.steps:
                raise Interrupted(run_dir, step)
    finally:
        if own_interrupt:
            interrupt.restore()
        if engine.person is not None:
            engine.person.close()
        engine.close()
        bar.close()
        log.close()
        ckpt.close()
    if primary and (run_dir / "eval.csv").exists():
        from hprior_jax.plotting import plot_learning_curve  # matplotlib: ~1 s to import

        plot_learning_curve(run_dir / "eval.csv", run_dir / "learning_curve.png",
                            title=f"{cfg.algo} on {cfg.task}")
    return rs


def process_age() -> float:
    """Seconds since this process started (Linux: from /proc; elsewhere: since this module
    was imported, which misses the interpreter's start and the first imports)."""
    try:
        start_ticks = int(Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()[19])
        uptime = float(Path("/proc/uptime").read_text().split()[0])
        return uptime - start_ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return time.perf_counter() - _IMPORTED


_IMPORTED = time.perf_counter()


def _person(engine: Engine, run_dir: Path, options, interrupt: "StopRequest", bar):
    """The human teacher a method that asks a person gets (`kit.person`), or None."""
    if not engine.method.asks_person:
        return None
    from hprior_jax.labelling.teacher import AskOptions, HumanTeacher

    if jax.process_count() > 1:
        raise ValueError("--teacher human runs in one process (one labelling page)")
    return HumanTeacher(run_dir / "labels", engine.task, engine.cfg.seeds,
                        options or AskOptions(), should_stop=lambda: interrupt.requested,
                        say=bar.write)


@contextlib.contextmanager
def _stopped_waiting(run_dir: Path, step: int):
    """A person's round that stops waiting (Ctrl-C, timeout) stops the run: the checkpoint
    before the round is its resume point."""
    try:
        yield
    except LabellingStopped as e:
        raise Interrupted(run_dir, step, str(e)) from None


def _save(ckpt, step: int, rs: RunState, run_dir: Path, bar) -> None:
    """A checkpoint, then a pending extension of the run's budget becomes its config (it
    now has a checkpoint it can resume from)."""
    ckpt.save(step, rs)
    if devices.is_primary():
        note = commit_extension(run_dir)
        if note:
            bar.write(note)


class CheckpointUnreadable(ValueError):
    """No checkpoint of a run could be restored; the message names the newest and why."""


def restore_latest(ckpt, like: RunState, step: int | None = None, on_unreadable=None):
    """The checkpoint at `step`, or by default the newest one that restores (written by
    today's state layout or the first one). A newer one that does not (a truncated or
    missing file) is passed to `on_unreadable(step, error)` and the next older is tried;
    without `on_unreadable`, or when none restores, CheckpointUnreadable names it."""
    candidates = [step] if step is not None else sorted(ckpt.all_steps(), reverse=True)
    for i, candidate in enumerate(candidates):
        try:
            stored = ckpt.stored_names(candidate)
            legacy = any(name.startswith(".extra") for name in stored)
            return ckpt.restore(like, candidate,
                                rename=legacy_checkpoint_name if legacy else None)
        except Exception as e:  # orbax raises many kinds for a damaged checkpoint
            if on_unreadable is None or i + 1 == len(candidates):
                raise CheckpointUnreadable(
                    f"the checkpoint at step {candidate} in {ckpt.directory} cannot be "
                    f"restored: {first_line(e)}") from e
            on_unreadable(candidate, e)
    raise CheckpointUnreadable(f"{ckpt.directory} holds no checkpoint")


def first_line(error: BaseException) -> str:
    text = str(error).strip().splitlines()
    return f"{type(error).__name__}: {text[0] if text else ''}"[:300]


def _set_aside(run_dir: Path, step: int, error: BaseException) -> Path:
    """Moves the unreadable checkpoint of `step` to RUN/broken_checkpoints/ (kept for a
    post-mortem, out of the way of the next save at that step) and says so in one line."""
    src = Path(run_dir) / "checkpoints" / str(step)
    dest = Path(run_dir) / "broken_checkpoints" / str(step)
    n = 1
    while dest.exists():
        dest, n = Path(run_dir) / "broken_checkpoints" / f"{step}.{n}", n + 1
    dest.parent.mkdir(exist_ok=True)
    src.rename(dest)
    print(f"the checkpoint at step {step} cannot be restored ({first_line(error)}); moved "
          f"to {dest}, resuming from the newest readable one", file=sys.stderr, flush=True)
    return dest


def _finite_or_raise(metrics: dict, step0: int, step1: int, seeds, run_dir, last_ckpt):
    for name, value in metrics.items():
        if name.startswith(UNCHECKED):
            continue
        bad = ~np.all(np.isfinite(np.asarray(value)), axis=tuple(range(1, np.ndim(value))))
        if bad.any():
            which = [s for s, b in zip(seeds, bad) if b]
            msg = (f"non-finite {name} between steps {step0} and {step1} for seed(s) "
                   f"{which}. Nothing after step {last_ckpt} was saved; the run directory "
                   f"{run_dir} keeps the checkpoint at step {last_ckpt} and all metrics up "
                   "to it. Lower the learning rate (--sac.lr) or use other seeds, then "
                   f"continue with `hprior train --resume {run_dir}` or start a new run.")
            if devices.is_primary():
                (Path(run_dir) / "error.txt").write_text(msg + "\n")
            raise TrainingDiverged(msg)


class _NoLog:
    """The logs of a process that is not the primary: every process computes the same
    metrics (gathered over all seeds), one writes them."""

    def log(self, *args, **kwargs):
        pass

    log_eval = flush = close = log


class _WallTimer:
    """Wall seconds per named part of one loop iteration, less any compile that happened
    inside it (`compile_seconds` is the engine's dict of program -> compile time, which
    grows when a new program is compiled); compile time is summed under `compile_s`."""

    def __init__(self, compile_seconds: dict):
        self.compile_seconds = compile_seconds
        self.seconds = {"compile_s": 0.0}

    @contextlib.contextmanager
    def __call__(self, part: str):
        before, t0 = set(self.compile_seconds), time.perf_counter()
        yield
        compiled = sum(v for k, v in self.compile_seconds.items() if k not in before)
        self.seconds["compile_s"] += compiled
        self.seconds[part] = self.seconds.get(part, 0.0) + time.perf_counter() - t0 - compiled

    def move(self, source: str, part: str, seconds: float) -> None:
        """Counts `seconds` of `source` under `part` instead."""
        self.seconds[source] -= seconds
        self.seconds[part] = self.seconds.get(part, 0.0) + seconds


def _log_chunk(log, seeds, step0: int, metrics: dict, has_success: bool) -> None:
    """Train-episode returns where episodes ended, mean losses per chunk."""
    done = metrics["episode/done"]  # [S, T]
    for i, s in enumerate(seeds):
        for t in np.flatnonzero(done[i]):
            ep = {"train/true_episode_return": metrics["episode/true_return"][i, t]}
            if has_success:
                ep["train/true_episode_success"] = metrics["episode/success"][i, t]
            log.log(step0 + int(t) + 1, s, ep)
        losses = {k: float(np.mean(v[i])) for k, v in metrics.items()
                  if k.startswith(("train/", "physics/"))}
        if losses:
            log.log(step0 + done.shape[1], s, losses)


class StopRequest:
    """SIGINT handler for the run: the first Ctrl-C is a request to stop after the chunk in
    flight (XLA cannot be interrupted mid-program anyway), the second stops at once. Only
    the main thread can own signals; elsewhere Ctrl-C keeps its default behaviour."""

    def __init__(self):
        self.requested = False
        self._previous = None
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._handle)

    def _handle(self, signum, frame):
        self.requested = True
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        print("\nCtrl-C: stopping at the next safe point (once training has started: after "
              "the chunk in flight, with a checkpoint); press Ctrl-C again to stop at once "
              "and lose that chunk", file=sys.stderr, flush=True)

    def restore(self):
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)


class _ProgressBar:
    """tqdm with one rate, env steps per second over all seeds, from the wall time of the
    training parts only (compiles excluded), and the ETA from that rate; the latest
    evaluation (return, and success rate where the task has one) beside it, and the share
    of that wall time evaluation has taken so far (its cost: see `--num-eval-episodes`)."""

    def __init__(self, total: int, initial: int, enabled: bool, num_seeds: int,
                 has_success: bool):
        from tqdm.auto import tqdm

        self.total, self.done, self.num_seeds = total, initial, num_seeds
        self.has_success = has_success
        self.steps, self.seconds, self.eval_seconds = 0, 0.0, 0.0
        self._eval = ""
        # a log file gets a plain line per evaluation instead of the bar's \r frames
        self.lines = enabled and not sys.stderr.isatty()
        self._bar = tqdm(total=total, initial=initial, unit="step",
                         disable=not enabled or self.lines, dynamic_ncols=True,
                         mininterval=1.0,
                         bar_format="{l_bar}{bar}| {n_fmt}/{total_fmt} {postfix}")
        self._status = ""

    def advance(self, length: int, seconds: float) -> None:
        self.done += length
        self.steps += length
        self.seconds += seconds
        rate = self.steps / max(self.seconds, 1e-9)  # per seed
        eta = (self.total - self.done) / rate
        cost = (f" (evaluation {100 * self.eval_seconds / self.seconds:.0f}% of the time)"
                if self.eval_seconds else "")
        self._status = (f"{rate * self.num_seeds:.0f} env steps/s, ETA {_clock(eta)}"
                        f"{self._eval}{cost}")
        self._bar.set_postfix_str(self._status, refresh=False)
        self._bar.update(length)
        if self.lines and self._eval:  # once per evaluation
            self.write(f"step {self.done}/{self.total}: {self._status}")
            self._eval = ""

    def evaluated(self, mean_return: float, mean_success: float, seconds: float) -> None:
        self.eval_seconds += seconds
        self._eval = f", eval return {mean_return:.1f}"
        if self.has_success:
            self._eval += f", success {100 * mean_success:.0f}%"

    def write(self, line: str) -> None:
        self._bar.write(line, file=sys.stdout)
        sys.stdout.flush()

    def close(self) -> None:
        self._bar.close()


def _clock(seconds: float) -> str:
    seconds = int(seconds)
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"
