"""`hprior train`: a new run or a resumed one; the SIGINT handler is in place before the
configuration is checked or the engine built."""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

from hprior_jax.methods import registry


def train(argv: list[str]) -> int:
    argv = _expand_aliases(argv)
    pre = argparse.ArgumentParser(add_help=False)
    for name in ("--task", "--algo", "--preset", "--resume", "--teacher", "--eval-budget"):
        pre.add_argument(name, default=None)
    pre.add_argument("--no-progress", action="store_true")
    pre.add_argument("--no-compile-ahead", action="store_true")
    pre.add_argument("--compile-ahead", default="after-first",
                     choices=["after-first", "first-phase-apart", "at-start", "off"])
    pre.add_argument("--devices", type=int, default=None)
    for name, kind in LABEL_OPTIONS.items():
        pre.add_argument(name, type=kind, default=None)
    known, rest = pre.parse_known_args(argv)
    help_asked = "-h" in rest or "--help" in rest

    from hprior_jax.loop.stopping import StopRequest  # before any checking or compiling

    # Ctrl-C from here on is a request, never an exception inside JAX's callbacks: before
    # anything is written it ends the command; after, the run checkpoints and stops
    stop, locks = StopRequest(), []
    try:
        return _train_run(argv, known, rest, help_asked, stop, locks)
    finally:
        for lock in locks:
            lock.release()
        stop.restore()


def _train_run(argv, known, rest, help_asked, stop, locks: list) -> int:
    """`hprior train` after the SIGINT handler is in place; the run directory's lock, once
    held, goes into `locks` (released by the caller whatever happens)."""
    from hprior_jax import dir_lock, presets, provenance
    from hprior_jax.config import DEFAULT_PRESET
    from hprior_jax.loop import devices, host, run_files
    from hprior_jax.runs import run_dir as run_dirs
    from hprior_jax.runs.build import build_engine, train
    from hprior_jax.setup_jax import enable_compilation_cache

    # before anything touches a device: with several processes the mesh spans them all
    several = not help_asked and devices.initialize_distributed()
    labelling = None if help_asked else _ask_options(known)  # checked before anything is written

    if known.resume and not help_asked:
        # the flags over the run's own config: resume_config refuses what may not change
        # (--task, --algo and --preset included: they are config fields too)
        run_dir = Path(known.resume)
        if "--out" in rest or any(a.startswith("--out=") for a in rest):
            raise ValueError("--resume continues the run in its own directory: drop --out "
                             f"(or copy {run_dir} there and resume the copy)")
        if devices.is_primary():
            run_dirs.load_run_config(run_dir)  # a run directory at all, before locking it
            locks.append(dir_lock.hold(run_dir))  # before anything in it changes
        note = run_files.settle_extension(run_dir, run_files.latest_checkpoint_step(run_dir))
        if note:
            print(note, file=sys.stderr, flush=True)
        saved = run_dirs.load_run_config(run_dir)
        default = (saved if known.teacher is None
                   else presets.with_teacher(saved, known.teacher))
        if known.eval_budget is not None:
            default = presets.with_eval_budget(default, known.eval_budget)
        requested = parse_config(default, _tyro_args(argv))
        cfg, saved_capacity = run_dirs.resume_config(run_dir, requested)
        made = False
        enable_compilation_cache()
        engine = build_engine(cfg, known.devices)
    else:
        task, algo = known.task or "cheetah_run", known.algo or registry.DEFAULT
        default = presets.train_preset(task, algo, known.preset or DEFAULT_PRESET)
        if known.teacher is not None:
            default = presets.with_teacher(default, known.teacher)
        if known.eval_budget is not None:
            default = presets.with_eval_budget(default, known.eval_budget)
        cfg = parse_config(default, rest if help_asked else _tyro_args(argv),
                            description=_train_description(algo))
        if several and not cfg.out:
            raise ValueError("a run of several processes needs --out: every process must "
                             "name the same run directory")
        cfg = dataclasses.replace(cfg, out=str(run_dirs.run_dir_path(cfg)))
        run_dirs.check_out_dir(Path(cfg.out))  # in every process: all refuse a bad --out
        enable_compilation_cache()
        # every configuration check runs before anything is written
        engine = build_engine(cfg, known.devices)
        devices.barrier("run directory checked")
        made = not Path(cfg.out).exists()
        if devices.is_primary():
            run_dirs.prepare_run_dir(cfg, provenance.run_info(["train", *argv]))
            locks.append(dir_lock.hold(Path(cfg.out)))
        devices.barrier("run directory made")
        run_dir, saved_capacity = Path(cfg.out), None
    if stop.requested:  # during the checks and compiles above: nothing was trained
        return _interrupted_before_training(None if known.resume else run_dir, made)
    print(f"run directory: {run_dir}", flush=True)
    try:
        train(cfg, run_dir, resume=bool(known.resume), progress=not known.no_progress,
                 saved_capacity=saved_capacity, engine=engine, labelling=labelling,
                 interrupt=stop,
                 compile_ahead="off" if known.no_compile_ahead
                 else known.compile_ahead.replace("-", "_"))
    except host.Interrupted as e:
        print(f"\n{e}. Continue with:\n  hprior train --resume {run_dir}", file=sys.stderr,
              flush=True)
        return 130
    _print_results(run_dir)
    return 0


def _interrupted_before_training(fresh: Path | None, made: bool) -> int:
    """Ctrl-C before the first chunk: a fresh run's directory is removed (or emptied, if
    --out existed), so the command line can be typed again; a resumed run is untouched."""
    from hprior_jax.loop import devices
    from hprior_jax.runs import run_dir as run_dirs

    if fresh is not None and devices.is_primary():
        run_dirs.discard_unstarted(fresh, made)
    print("interrupted", file=sys.stderr)
    return 130


def _print_results(run_dir: Path) -> None:
    """What a finished run learned (the evaluations, one line each) and where its files are."""
    from hprior_jax.plotting import returns_summary

    if (run_dir / "eval.csv").exists():
        print("evaluation (deterministic policy, true reward):",
              returns_summary(run_dir / "eval.csv"), sep="\n")
    print(f"done. results in {run_dir}: eval.csv, metrics.jsonl, learning_curve.png, "
          "tb/ (TensorBoard), checkpoints/", flush=True)


def parse_config(default, args: list[str], **kw):
    """tyro over `default`'s class; a configuration check that fails (a ValueError in a
    config's __post_init__) is raised as that ValueError, so it prints as one line."""
    import tyro

    try:  # tyro 1.0 calls this hook before it draws its error box and exits
        from tyro._errors import InstantiationFailure, on_parse_error
    except ImportError:  # pragma: no cover - another tyro: its own box
        return tyro.cli(type(default), default=default, args=args, prog="hprior train", **kw)

    def raise_value_error(event):
        if isinstance(event, InstantiationFailure):
            flag = getattr(event.argument, "display_name", None)
            # a value of the wrong type ("abc" for --steps): name the flag it was given to
            raise ValueError(f"{flag()}: {event.message}" if flag else event.message)

    with on_parse_error(raise_value_error):
        return tyro.cli(type(default), default=default, args=args, prog="hprior train", **kw)


def _train_description(algo: str) -> str:
    from hprior_jax.config import CHANGEABLE_ON_RESUME
    from hprior_jax.envs import task_names
    from hprior_jax.pbrl.teacher import PRESETS as TEACHERS

    return (f"Train an agent on an MJX task (--algo {algo}). Also: --task "
            f"{{{','.join(task_names())}}}; --algo {{{','.join(registry.names())}}}; "
            "--preset {paper,reduced,smoke}; --teacher "
            f"{{{','.join(sorted(TEACHERS))}}} (a B-Pref teacher); --eval-budget {{paper,cpu}} "
            "(cpu: 5 evaluation episodes every 10k steps; see README); --no-progress (no progress "
            "bar); --resume DIR continues an interrupted run, where only "
            f"{', '.join('--' + k.replace('_', '-') for k in CHANGEABLE_ON_RESUME)} may "
            "change. Ctrl-C once finishes the "
            "chunk in flight and saves a checkpoint; twice stops at once. --devices N splits "
            "the seeds over N devices (default: as many as divide the seeds evenly; a run may "
            "resume on another count); several hosts: README, 'Many devices and hosts'. "
            "--teacher human: you answer each feedback round's queries in a browser (the run "
            "prints the address and waits); --label-host H, --label-port P (default "
            "127.0.0.1:8765; another host needs --label-token, made up if not given), "
            "--label-timeout S (stop with a checkpoint after S seconds without an answer; "
            "default 3600). --compile-ahead after-first|first-phase-apart|at-start|off: when to "
            "start compiling the later programs (evaluation, feedback rounds, ...) in a "
            "background thread: once the first chunk's program is compiled (default; the "
            "background thread meanwhile compiles the programs of the episodes' first "
            "states and the initial run state); the "
            "same with the random phase's chunks run by a program of their own, quicker to "
            "compile (first-phase-apart); before the first chunk's compile (at-start); or "
            "never (each when first needed; for a one-core machine, where the background "
            "compile competes with training); --no-compile-ahead is --compile-ahead off.")


# `hprior train` options of the labelling page a human teacher's run serves (not config:
# a resumed run may serve elsewhere)
LABEL_OPTIONS = {"--label-host": str, "--label-port": int, "--label-token": str,
                 "--label-timeout": float}


def _ask_options(known):
    from hprior_jax.labelling.server import ServerOptions
    from hprior_jax.labelling.teacher import AskOptions

    default = ServerOptions()
    server = ServerOptions(known.label_host or default.host,
                           default.port if known.label_port is None else known.label_port,
                           known.label_token).check("--label-host", "--label-port")
    timeout = AskOptions().timeout_s if known.label_timeout is None else known.label_timeout
    return AskOptions(server=server, timeout_s=timeout)


def _tyro_args(argv: list[str]) -> list[str]:
    """argv less the options the pre-parser owns (tyro knows --task/--algo/--preset as
    config fields, but not these)."""
    out = [a for a in argv if a not in ("--no-progress", "--no-compile-ahead")]
    for name in ("--teacher", "--resume", "--eval-budget", "--devices", "--compile-ahead",
                 *LABEL_OPTIONS):
        out = _drop_option(out, name)
    return out


# short spellings of nested options (issue texts and the paper use these names)
ALIASES = {"--feedback": "--pebble.max-feedback",
           "--queries-per-round": "--pebble.queries-per-round"}


def _expand_aliases(argv: list[str]) -> list[str]:
    out = []
    for a in argv:
        name, eq, value = a.partition("=")
        out.append(ALIASES.get(name, name) + eq + value if name in ALIASES else a)
    return out


def _drop_option(argv: list[str], name: str) -> list[str]:
    out, skip = [], False
    for a in argv:
        if skip:
            skip = False
        elif a == name:
            skip = True
        elif not a.startswith(name + "="):
            out.append(a)
    return out
