"""The host loop: schedule chunks and events, guard against NaN, log, evaluate, checkpoint.

Everything here runs between compiled programs; it knows phases, events and metric groups
only as the engine and the method name them.
"""
from __future__ import annotations

import contextlib
import sys
import time
from functools import partial
from pathlib import Path

import jax
import numpy as np

from hprior_jax.buffers import replay
from hprior_jax.loop.engine import Engine
from hprior_jax.loop.run_dir import legacy_checkpoint_name
from hprior_jax.loop.state import RunState

UNCHECKED = ("episode/", "perf/")  # metric groups that may legitimately be non-finite or are ours


class TrainingDiverged(RuntimeError):
    pass


def run(cfg, run_dir: Path, resume: bool = False, progress: bool = True,
        max_chunks: int | None = None, saved_capacity: int | None = None) -> RunState:
    """Trains `cfg` into `run_dir` (made by `prepare_run_dir`, or an existing run to resume).

    `max_chunks` stops early after that many chunks (used by tests to simulate an
    interruption); the state is checkpointed at the stop. `saved_capacity` is the replay
    capacity of the checkpoints when a resumed run's budget was extended."""
    from hprior_jax.checkpoint import Checkpointer
    from hprior_jax.plotting import plot_learning_curve
    from hprior_jax.run_log import RunLog

    run_dir = Path(run_dir)
    engine = Engine(cfg)
    seeds = list(cfg.seeds)
    ckpt = Checkpointer(run_dir / "checkpoints")
    step = 0
    rs = engine.init_seeds(seeds, capacity=saved_capacity if resume else None)
    if resume and ckpt.latest_step() is not None:
        step, rs = restore_latest(ckpt, rs)
    if rs.replay.capacity != cfg.capacity:
        if replay.has_wrapped(rs.replay):
            raise ValueError("the replay buffer of this run has wrapped around; it cannot be "
                             "extended with --steps (start a new run instead)")
        rs = rs.replace(replay=jax.vmap(partial(replay.grow, capacity=cfg.capacity))(rs.replay))
    # the chunk writes transition `t` at ring position t % capacity (unbatched, in place)
    if np.any(np.asarray(rs.replay.index) != step % rs.replay.capacity):
        raise ValueError(f"{run_dir}: the replay buffer's write position does not match step "
                         f"{step}; the checkpoint is not from this run")
    log = RunLog(run_dir, seeds, resume_step=step if resume else None)
    has_success = engine.task.has_success
    last_ckpt = step
    bar = _progress_bar(cfg.steps, step, progress)
    chunks = 0
    events = set(engine.event_steps())
    try:
        while step < cfg.steps and (max_chunks is None or chunks < max_chunks):
            compiled_before = set(engine.compile_seconds)
            timer = _WallTimer(engine.compile_seconds)  # wall time per part, compiles apart
            if step in events:  # e.g. a feedback round: before this step's update
                with timer("event_s"):
                    rs, event_metrics = engine.run_event(rs, step)
                    event_metrics = jax.device_get(event_metrics)
                _finite_or_raise(event_metrics, step, step, seeds, run_dir, last_ckpt)
                for i, s in enumerate(seeds):
                    log.log(step, s, {k: np.asarray(v)[i] for k, v in event_metrics.items()})
            phase, length = engine.chunk_plan(step)
            with timer("chunk_s"):  # env steps and agent updates: one fused program
                rs, metrics = engine.run_chunk(rs, step, length)
                metrics = jax.device_get(metrics)
            keep = engine.phase_metrics(phase)  # drop placeholders of other phases
            metrics = {k: v for k, v in metrics.items()
                       if not k.startswith("train/") or k in keep}
            _finite_or_raise(metrics, step, step + length, seeds, run_dir, last_ckpt)
            _log_chunk(log, seeds, step, metrics, has_success)
            step += length
            chunks += 1
            if step % cfg.eval_every == 0 or step == cfg.steps:
                with timer("eval_s"):
                    returns, successes = jax.device_get(engine.run_eval(rs, seeds, step))
                for i, s in enumerate(seeds):
                    log.log_eval(step, s, float(np.mean(returns[i])),
                                 float(np.mean(successes[i])) if has_success else None)
                bar.set_postfix_str(f"eval return {np.mean(returns):.1f}")
            if step % cfg.checkpoint_every == 0 or step == cfg.steps or (
                    max_chunks is not None and chunks == max_chunks):
                log.flush()
                with timer("checkpoint_s"):
                    ckpt.save(step, rs)
                last_ckpt = step
            perf = {"perf/env_steps_per_s": length * len(seeds) / max(timer.seconds["chunk_s"],
                                                                      1e-9)}
            perf.update({f"perf/{k}": v for k, v in timer.seconds.items() if v or k == "chunk_s"})
            for s in seeds:
                log.log(step, s, perf)
            log.flush()  # a crash or kill loses at most the chunk in flight
            for name in sorted(set(engine.compile_seconds) - compiled_before):
                bar.write(f"compiled {name} in {engine.compile_seconds[name]:.1f} s "
                          "(once per shape; not counted in env steps/s)", file=sys.stdout)
                sys.stdout.flush()
            bar.update(length)
            bar.set_description(f"{perf['perf/env_steps_per_s']:.0f} env steps/s")
    finally:
        bar.close()
        log.close()
        ckpt.close()
    if (run_dir / "eval.csv").exists():
        plot_learning_curve(run_dir / "eval.csv", run_dir / "learning_curve.png",
                            title=f"{cfg.algo} on {cfg.task}")
    return rs


def restore_latest(ckpt, like: RunState):
    """The latest checkpoint, written by today's state layout or the first one."""
    stored = ckpt.stored_names()
    legacy = any(name.startswith(".extra") for name in stored)
    return ckpt.restore(like, rename=legacy_checkpoint_name if legacy else None)


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
            (Path(run_dir) / "error.txt").write_text(msg + "\n")
            raise TrainingDiverged(msg)


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


def _log_chunk(log, seeds, step0: int, metrics: dict, has_success: bool) -> None:
    """Train-episode returns where episodes ended, mean losses per chunk."""
    done = metrics["episode/done"]  # [S, T]
    for i, s in enumerate(seeds):
        for t in np.flatnonzero(done[i]):
            ep = {"train/true_episode_return": metrics["episode/true_return"][i, t]}
            if has_success:
                ep["train/true_episode_success"] = metrics["episode/success"][i, t]
            log.log(step0 + int(t) + 1, s, ep)
        losses = {k: float(np.mean(v[i])) for k, v in metrics.items() if k.startswith("train/")}
        if losses:
            log.log(step0 + done.shape[1], s, losses)


def _progress_bar(total: int, initial: int, enabled: bool):
    from tqdm.auto import tqdm

    return tqdm(total=total, initial=initial, unit="step", disable=not enabled,
                dynamic_ncols=True, mininterval=1.0)
