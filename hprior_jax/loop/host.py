"""The host loop: schedule chunks and events, guard against NaN, log, evaluate, checkpoint.

Everything here runs between compiled programs; it knows phases, events and metric groups
only as the engine and the method name them.
"""
from __future__ import annotations

import contextlib
import json
import sys
from functools import partial
from pathlib import Path

import jax
import numpy as np

from hprior_jax.buffers import replay
from hprior_jax.checkpoint import Checkpointer
from hprior_jax.labelling.teacher import AskOptions, HumanTeacher, LabellingStopped
from hprior_jax.loop import checkpoints, devices
from hprior_jax.loop.engine import Engine
from hprior_jax.loop.episodes import episode_video, recorder_program
from hprior_jax.loop.progress import ProgressBar, WallTimer, process_age
from hprior_jax.loop.state import RunState
from hprior_jax.loop.stopping import Interrupted, StopRequest, TrainingDiverged
from hprior_jax.plotting import plot_learning_curve
from hprior_jax.run_log import RunLog

UNCHECKED = ("episode/", "perf/")  # metric groups that may legitimately be non-finite or are ours
AHEAD_WHEN = ("after_first", "first_phase_apart", "at_start", "off")


def run(engine: Engine, run_dir: Path, resume: bool = False, progress: bool = True,
        max_chunks: int | None = None, saved_capacity: int | None = None,
        interrupt: StopRequest | None = None, labelling=None,
        compile_ahead: str = "after_first", on_evaluation=None) -> RunState:
    """Trains `engine.cfg` into `run_dir` (made by `prepare_run_dir`, or an existing run to
    resume).

    `max_chunks` stops early after that many chunks (tests simulate an interruption so); the
    state is checkpointed at the stop. `saved_capacity` is the replay capacity of the
    checkpoints when a resumed run's budget was extended. `interrupt`: a `StopRequest` shared
    by runs that train side by side in threads (the grid's), which the main thread's Ctrl-C
    sets. `labelling`: where and how long a method that asks a person waits for answers
    (`AskOptions`; default: 127.0.0.1:8765, an hour). `on_evaluation(step, returns[S],
    successes[S] or None)` after each evaluation (per seed, the mean over its episodes); a
    true result stops the run there, checkpointed, as if its budget ended (it resumes).
    `compile_ahead`: when to start compiling the later programs (evaluation, the method's
    events, other chunk lengths) in a background thread (`Engine.compile_run_ahead`):
    "after_first" (default) once the main thread has compiled the first chunk's program;
    "first_phase_apart" the same, but the first phase's chunks (random actions) run a
    program of that phase alone, quicker to compile; "at_start" before the first chunk's
    compile (the two share the cores); "off" (each program when first needed).
    Each chunk's perf records hold its wall time by part; the first chunk's also
    `perf/first_step_s` (process start to its first env step) and, in `perf/compile_s`, the
    compiles the run waited for before it.

    The first Ctrl-C lets the chunk in flight finish, writes a checkpoint and raises
    `Interrupted`; a second one stops the process at once (the default SIGINT action)."""
    if compile_ahead not in AHEAD_WHEN:
        raise ValueError(f"compile_ahead={compile_ahead!r}: one of {AHEAD_WHEN}")
    # a run cut short (tests) would compile programs it never runs
    ahead = compile_ahead if max_chunks is None else "off"
    loop = _Loop(engine, Path(run_dir), max_chunks, interrupt, ahead, on_evaluation)
    try:
        loop.start(resume, saved_capacity if resume else None, progress, labelling)
        while loop.step < engine.cfg.steps and not loop.cut_short() and not loop.told_to_stop:
            loop.iteration()
    finally:
        loop.close()
    if loop.primary and (loop.run_dir / "eval.csv").exists():
        plot_learning_curve(loop.run_dir / "eval.csv", loop.run_dir / "learning_curve.png",
                            title=f"{engine.cfg.algo} on {engine.cfg.task}")
    return loop.rs


class _Loop:
    """One run's loop state between compiled programs; `iteration` is one chunk with the
    event before it and the evaluation and checkpoint after it."""

    def __init__(self, engine: Engine, run_dir: Path, max_chunks, interrupt, ahead: str,
                 on_evaluation=None):
        self.engine, self.cfg, self.run_dir = engine, engine.cfg, run_dir
        self.seeds = list(self.cfg.seeds)
        self.max_chunks, self.ahead = max_chunks, ahead
        self.own_interrupt = interrupt is None
        self.interrupt = interrupt or StopRequest()
        self.keep = self.cfg.keep_checkpoints or None  # None: orbax keeps every one
        self.ckpt = Checkpointer(run_dir / "checkpoints", max_to_keep=self.keep)
        self.primary = devices.is_primary()  # with several processes, one writes the logs
        self.step = self.chunks = 0
        self.rs = self.log = self.bar = None
        self.warned_cap = False
        self.on_evaluation, self.told_to_stop = on_evaluation, False
        self.evaluations = 0  # by this process: --capture-video counts from the first
        engine.person = None
        engine.first_phase_apart = ahead == "first_phase_apart"

    def cut_short(self) -> bool:
        return self.max_chunks is not None and self.chunks >= self.max_chunks

    def start(self, resume: bool, capacity: int | None, progress: bool, labelling) -> None:
        """The initial or restored state on this run's devices, the log and the bar."""
        engine = self.engine
        if self.ahead in ("after_first", "first_phase_apart"):  # the first chunk's first
            engine.compile_start(self.seeds, (self.ckpt.latest_step() or 0) if resume else 0,
                                 capacity)
        rs = engine.init_seeds(self.seeds, capacity=capacity)
        # the first states, the first chunk's program: counted with the first chunk
        self.start_compile_s = sum(engine.compile_seconds.values())
        if resume:
            rs = self._restore(rs)
        if rs.replay.capacity != self.cfg.capacity:
            rs = self._grow_replay(rs)
        rs = engine.place(rs)  # a restored state: onto this run's devices, whatever wrote it
        # the chunk writes transition `t` at ring position t % capacity (unbatched, in place)
        if np.any(devices.fetch(rs.replay.index) != self.step % rs.replay.capacity):
            raise ValueError(f"{self.run_dir}: the replay buffer's write position does not "
                             f"match step {self.step}; the checkpoint is not from this run")
        self.rs, self.last_ckpt = rs, self.step
        self.log = (RunLog(self.run_dir, self.seeds, resume_step=self.step if resume else None)
                    if self.primary else _NoLog())
        self.has_success = engine.task.has_success
        self.bar = ProgressBar(self.cfg.steps, self.step, progress and self.primary,
                               len(self.seeds), self.has_success)
        self.events = set(engine.event_steps())
        engine.person = self._person(labelling) if self.primary else None
        if self.ahead == "at_start":
            self._compile_run_ahead(self.step)

    def _restore(self, rs: RunState) -> RunState:
        """The newest checkpoint that restores (none yet: the initial `rs`, step 0)."""
        broken = []
        if self.ckpt.latest_step() is not None:
            self.step, rs = checkpoints.restore_latest(
                self.ckpt, rs, on_unreadable=lambda bad, error: broken.append(
                    (bad, error, checkpoints.set_aside(self.run_dir, bad))))
        if broken:  # the manager lists the steps it found when it was opened
            self.ckpt.close()
            self.ckpt = Checkpointer(self.run_dir / "checkpoints", max_to_keep=self.keep)
        if self.primary:  # said once the step it resumes from is known
            for bad, error, dest in broken:
                print(checkpoints.set_aside_line(bad, error, dest, self.step), file=sys.stderr,
                      flush=True)
            print(f"resuming from step {self.step} of {self.cfg.steps}", flush=True)
        return rs

    def _grow_replay(self, rs: RunState) -> RunState:
        ring = rs.replay.replace(size=devices.fetch(rs.replay.size),
                                 index=devices.fetch(rs.replay.index))
        if replay.has_wrapped(ring):
            raise ValueError("the replay buffer of this run has wrapped around; it cannot be "
                             "extended with --steps (start a new run instead)")
        grow = self.engine.per_seed(partial(replay.grow, capacity=self.cfg.capacity))
        return rs.replace(replay=grow(self.engine.place(rs.replay)))

    def _person(self, options):
        """The human teacher a method that asks a person gets (`kit.person`), or None."""
        if not self.engine.method.asks_person:
            return None
        if jax.process_count() > 1:
            raise ValueError("--teacher human runs in one process (one labelling page)")
        return HumanTeacher(self.run_dir / "labels", self.engine.task, self.cfg.seeds,
                            options or AskOptions(),
                            should_stop=lambda: self.interrupt.requested, say=self.bar.write)

    def iteration(self) -> None:
        # the first chunk also reports the programs compiled before the loop
        compiled_before = set(self.engine.compile_seconds) if self.chunks else set()
        timer = WallTimer(self.engine.compile_seconds)  # wall time per part, compiles apart
        if self.chunks == 0:
            timer.seconds["compile_s"] += self.start_compile_s
        if self.step in self.events:  # e.g. a feedback round: before this step's update
            self._event(timer)
        length, first_step = self._chunk(timer)
        self.step += length
        self.chunks += 1
        if self.step % self.cfg.eval_every == 0 or self.step == self.cfg.steps:
            self._evaluate(timer)
        stop = self.interrupt.requested  # read once: a checkpoint is written for every stop
        if (self.step % self.cfg.checkpoint_every == 0 or self.step == self.cfg.steps or stop
                or self.cut_short() or self.told_to_stop):
            self.log.flush()
            with timer("checkpoint_s"):
                self._save()
        self._log_perf(timer, length, first_step)
        self._say_compiles(compiled_before)
        self.bar.advance(length, sum(v for k, v in timer.seconds.items()
                                     if k not in ("compile_s", "label_wait_s")))
        if stop and self.step < self.cfg.steps:
            raise Interrupted(self.run_dir, self.step)

    def _save(self) -> None:
        # the configuration rides with the checkpoint: an edited config.json is then named
        # by field on resume, not mistaken for a damaged checkpoint
        checkpoints.save(self.ckpt, self.step, self.rs, self.run_dir, self.bar.write,
                         config=json.loads(self.cfg.to_json()))
        self.last_ckpt = self.step

    def _event(self, timer: WallTimer) -> None:
        engine, step = self.engine, self.step
        if engine.method.asks_person and self.last_ckpt != step:
            self._save()  # a person may stop the run while the round waits: it resumes here
        waited = engine.person.waited_s if engine.person is not None else 0.0
        with timer("event_s"), stopped_waiting(self.run_dir, step):
            self.rs, metrics = engine.run_event(self.rs, step)
            metrics = devices.fetch(metrics)
        if engine.person is not None:  # a person's time is not the event's
            timer.move("event_s", "label_wait_s", engine.person.waited_s - waited)
        finite_or_raise(metrics, step, step, self.seeds, self.run_dir, self.last_ckpt)
        for i, s in enumerate(self.seeds):
            self.log.log(step, s, {k: np.asarray(v)[i] for k, v in metrics.items()})

    def _chunk(self, timer: WallTimer) -> tuple[int, float | None]:
        """Env steps and agent updates of one chunk: one fused program."""
        engine, step = self.engine, self.step
        phase, length = engine.chunk_plan(step)
        with timer("chunk_s"):
            program = engine.compiled_chunk(self.rs, step, length)
            first_step = process_age() if self.chunks == 0 else None
            if self.chunks == 0 and self.ahead in ("after_first", "first_phase_apart"):
                self._compile_run_ahead(step)  # before the chunk: it donates rs
            starts = engine.episode_starts(self.rs, step)
            self.rs, metrics = program(self.rs, np.int32(step), starts)
            metrics = devices.fetch(metrics)
        keep = engine.phase_metrics(phase)  # drop placeholders of other phases
        metrics = {k: v for k, v in metrics.items() if not k.startswith("train/") or k in keep}
        finite_or_raise(metrics, step, step + length, self.seeds, self.run_dir, self.last_ckpt)
        _log_chunk(self.log, self.seeds, step, metrics, self.has_success)
        at_cap = float(np.mean(metrics.get("physics/contacts_at_cap", 0.0)))
        if at_cap and not self.warned_cap:  # once per run: the share is in metrics.jsonl
            self.warned_cap = True
            self.bar.write(f"warning: MJX's contact cap was full at {at_cap:.1%} of steps "
                           f"{step}-{step + length}: contacts may have been dropped there "
                           "(physics/contacts_at_cap in metrics.jsonl; --contact-cap none "
                           "simulates every contact)")
        return length, first_step

    def _evaluate(self, timer: WallTimer) -> None:
        with timer("eval_s"):
            returns, successes = devices.fetch(self.engine.run_eval(self.rs, self.seeds,
                                                                    self.step))
        for i, s in enumerate(self.seeds):
            self.log.log_eval(self.step, s, float(np.mean(returns[i])),
                              float(np.mean(successes[i])) if self.has_success else None)
        every = self.cfg.capture_video
        if every and self.evaluations % every == 0:
            with timer("eval_s"):  # rendering is part of what evaluation costs
                self._videos()
        self.evaluations += 1
        self.bar.evaluated(np.mean(returns), np.mean(successes), timer.seconds["eval_s"])
        if self.on_evaluation is not None:
            self.told_to_stop = bool(self.on_evaluation(
                self.step, np.mean(returns, axis=1),
                np.mean(successes, axis=1) if self.has_success else None))

    def _compile_run_ahead(self, step: int) -> None:
        """The rest of the run's programs in the background, with the episode recorder's
        beside evaluation's where this process records videos."""
        videos = self.cfg.capture_video and self.primary
        self.engine.compile_run_ahead(
            self.rs, step, [recorder_program(self.engine, self.rs.sac.actor)] if videos else [])

    def _videos(self) -> None:
        """RUN/videos/step<N>_seed<S>.mp4 of each seed's first evaluation episode."""
        actors = devices.fetch(self.rs.sac.actor)  # in every process: seeds may span them
        if not self.primary:
            return
        for i, seed in enumerate(self.seeds):
            episode_video(self.engine, jax.tree.map(lambda x: x[i], actors), seed, self.step,
                          self.run_dir / "videos" / f"step{self.step}_seed{seed}.mp4",
                          self.cfg.video_steps)

    def _log_perf(self, timer: WallTimer, length: int, first_step: float | None) -> None:
        chunk_s = max(timer.seconds["chunk_s"], 1e-9)
        perf = {"perf/env_steps_per_s": length * len(self.seeds) / chunk_s}
        perf.update({f"perf/{k}": v for k, v in timer.seconds.items() if v or k == "chunk_s"})
        if first_step is not None:  # how long this process took to its first env step
            perf["perf/first_step_s"] = first_step
        for s in self.seeds:
            self.log.log(self.step, s, perf)
        self.log.flush()  # a crash or kill loses at most the chunk in flight

    def _say_compiles(self, compiled_before: set) -> None:
        engine = self.engine
        for name in sorted(set(engine.compile_seconds) - compiled_before):
            ahead, waited = engine.ahead_seconds.get(name), engine.compile_seconds[name]
            self.bar.write(f"compiled {name} in {waited:.1f} s" if ahead is None else
                           f"compiled {name} in the background in {ahead:.1f} s (the run "
                           f"waited {waited:.1f} s for it)")
        if self.chunks == 1:
            self.bar.write("  (compiles: once per shape, not counted in env steps/s; cached "
                           "in $HPRIOR_JAX_CACHE for the next start)")

    def close(self) -> None:
        if self.own_interrupt:
            self.interrupt.restore()
        if self.engine.person is not None:
            self.engine.person.close()
        self.engine.close()
        for part in (self.bar, self.log):
            if part is not None:
                part.close()
        self.ckpt.close()


@contextlib.contextmanager
def stopped_waiting(run_dir: Path, step: int):
    """A person's round that stops waiting (Ctrl-C, timeout) stops the run: the checkpoint
    before the round is its resume point."""
    try:
        yield
    except LabellingStopped as e:
        raise Interrupted(run_dir, step, str(e)) from None


def finite_or_raise(metrics: dict, step0: int, step1: int, seeds, run_dir, last_ckpt):
    """Raises TrainingDiverged (and writes RUN/error.txt) when a metric is not finite."""
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
