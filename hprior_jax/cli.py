"""`hprior` command line: parse, then call into the library (no JAX logic here).

    hprior train --task cheetah_run --algo sac --preset smoke
    hprior train --task cheetah_run --seeds 12345 23456 --steps 100000 --sac.lr 3e-4
    hprior train --resume runs/cheetah_run_sac_20261122-101500
    hprior eval --run runs/cheetah_run_sac_20261122-101500 --episodes 20 --video
    hprior export --run runs/cheetah_run_prior_20261122-101500 --seed 12345 --out my_reward
    hprior attention --run runs/cheetah_run_prior_20261122-101500 --pair 3
    hprior grid --tasks cheetah_run --algos sac pebble prior --preset reduced --out results
    hprior report results
    hprior reward-lab --task cheetah_run --seeds 20 --budgets 25 100 400
    hprior tasks
    hprior methods
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

from tasks import _xla_flags  # noqa: F401  (before anything imports jax)

from hprior_jax.config import DEFAULT_PRESET, PRESETS
from hprior_jax.methods import registry

USAGE = """usage: hprior COMMAND [ARGS]

commands:
  train      train an agent (hprior train --help for every option)
  eval       evaluate a run's checkpoint per seed (true return, success), optionally a video
  export     a seed's learned reward and policy as a standalone folder (hprior_jax.load_reward)
  label      label preference queries in a browser (a local web app)
  attention  world-model attention maps of a trained run of a method with a world model
  grid       every (task, algorithm) with its seeds; skips finished runs, resumes the rest
  report     Tables 6-7, paired t-tests, learning curves of a grid's results directory
  reward-lab which method learns the better reward from the same labels, on fixed data
  tasks      list the registered tasks
  methods    list the registered methods (--algo)
"""


def _train(argv: list[str]) -> int:
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

    from hprior_jax.loop.stopping import StopRequest  # light: before JAX's own imports

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
    from hprior_jax.loop import devices, host, run_files
    from hprior_jax.runs import run_dir as run_dirs
    from hprior_jax.runs.build import build_engine, train
    from hprior_jax.setup_jax import enable_compilation_cache

    # before anything touches a device: with several processes the mesh spans them all
    several = not help_asked and devices.initialize_distributed()

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
        requested = _parse_config(default, _tyro_args(argv))
        cfg, saved_capacity = run_dirs.resume_config(run_dir, requested)
        enable_compilation_cache()
        engine = build_engine(cfg, known.devices)
    else:
        task, algo = known.task or "cheetah_run", known.algo or registry.DEFAULT
        default = presets.train_preset(task, algo, known.preset or DEFAULT_PRESET)
        if known.teacher is not None:
            default = presets.with_teacher(default, known.teacher)
        if known.eval_budget is not None:
            default = presets.with_eval_budget(default, known.eval_budget)
        cfg = _parse_config(default, rest if help_asked else _tyro_args(argv),
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
        if devices.is_primary():
            run_dirs.prepare_run_dir(cfg, provenance.run_info(["train", *argv]))
            locks.append(dir_lock.hold(Path(cfg.out)))
        devices.barrier("run directory made")
        run_dir = Path(cfg.out)
        saved_capacity = None
    if stop.requested:  # during the checks and compiles above: nothing was trained
        print("interrupted", file=sys.stderr)
        return 130
    print(f"run directory: {run_dir}", flush=True)
    if known.resume:
        step = run_files.latest_checkpoint_step(run_dir)
        print(f"resuming from step {step or 0} of {cfg.steps}", flush=True)
    try:
        train(cfg, run_dir, resume=bool(known.resume), progress=not known.no_progress,
                 saved_capacity=saved_capacity, engine=engine, labelling=_ask_options(known),
                 interrupt=stop,
                 compile_ahead="off" if known.no_compile_ahead
                 else known.compile_ahead.replace("-", "_"))
    except host.Interrupted as e:
        print(f"\n{e}. Continue with:\n  hprior train --resume {run_dir}", file=sys.stderr,
              flush=True)
        return 130
    print(f"done. results in {run_dir}: eval.csv, metrics.jsonl, learning_curve.png, "
          "tb/ (TensorBoard), checkpoints/", flush=True)
    return 0


def _parse_config(default, args: list[str], **kw):
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
    from hprior_jax.envs import task_names
    from hprior_jax.pbrl.teacher import PRESETS as TEACHERS

    return (f"Train an agent on an MJX task (--algo {algo}). Also: --task "
            f"{{{','.join(task_names())}}}; --algo {{{','.join(registry.names())}}}; "
            "--preset {paper,reduced,smoke}; --teacher "
            f"{{{','.join(sorted(TEACHERS))}}} (a B-Pref teacher); --eval-budget {{paper,cpu}} "
            "(cpu: 5 evaluation episodes every 10k steps; see README); --no-progress (no progress "
            "bar); --resume DIR continues an interrupted run, where only --steps, --eval-every, "
            "--checkpoint-every and --num-eval-episodes may change. Ctrl-C once finishes the "
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
                           known.label_token)
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


def _eval(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(
        prog="hprior eval",
        description="Evaluate the policy of a run's checkpoint on fresh episodes, per seed: "
                    "true return (mean and std) and, for MetaWorld, success rate. Writes "
                    "RUN/eval_step<N>_<K>ep.csv; --video renders one episode per seed to "
                    "RUN/videos/ (needs OSMesa: apt-get install libosmesa6).")
    parser.add_argument("--run", required=True, help="a run directory of `hprior train`")
    parser.add_argument("--step", type=int, default=None,
                        help="which checkpoint (default: the newest readable one; a run keeps its "
                             "last --keep-checkpoints, 2 unless set)")
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--video", action="store_true")
    args = parser.parse_args(argv)
    from hprior_jax.experiments.evaluate_run import evaluate_run
    from hprior_jax.setup_jax import enable_compilation_cache

    enable_compilation_cache()
    rows, videos = evaluate_run(args.run, args.step, args.episodes, args.video)
    print(f"{args.run} at step {rows[0]['step']}, {args.episodes} episodes per seed:")
    for r in rows:
        extra = f", success {100 * r['success']:.0f}%" if "success" in r else ""
        print(f"  seed {r['seed']}: true return {r['true_return']:.1f} "
              f"± {r['true_return_std']:.1f}{extra}")
    for path in videos:
        print(path)
    return 0


def _export(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(
        prog="hprior export",
        description="Write one seed's learned reward ensemble and policy as a standalone "
                    "folder (orbax checkpoint + export.json); load them elsewhere with "
                    "hprior_jax.load_reward(FOLDER) and hprior_jax.load_policy(FOLDER).")
    parser.add_argument("--run", required=True, help="a run directory of `hprior train`")
    parser.add_argument("--out", required=True, help="a new folder")
    parser.add_argument("--seed", type=int, default=None, help="default: the run's first")
    parser.add_argument("--step", type=int, default=None, help="default: the latest")
    args = parser.parse_args(argv)
    from hprior_jax.export import export_seed

    print(f"exported to {export_seed(args.run, args.out, args.seed, args.step)}")
    return 0


def _label(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(
        prog="hprior label",
        description="Label preference queries in a browser: a local web app shows each "
                    "query's two clips side by side; answer with buttons or keys 1 (left), "
                    "2 (right), 3 (equally good), 0 (can't tell), u (undo). Answers are "
                    "appended to DIR/answers.jsonl.")
    parser.add_argument("--dir", required=True, help="the query folder")
    parser.add_argument("--from-run", default=None,
                        help="first write queries into --dir: segment pairs from fresh "
                             "episodes of this run's policy")
    parser.add_argument("--from-lab", default=None, metavar="DATASET",
                        help="first write queries into --dir: uniform segment pairs of a "
                             "reward-lab dataset built with --physics (then train the lab on "
                             "the answers: `hprior reward-lab --labels DIR`)")
    parser.add_argument("--pairs", type=int, default=10)
    parser.add_argument("--segment-len", type=int, default=50,
                        help="with --from-run (a lab dataset's segments have its own length)")
    parser.add_argument("--seed", type=int, default=None,
                        help="which seed's policy (--from-run); the draw of pairs (--from-lab)")
    parser.add_argument("--build-only", action="store_true", help="write the queries, stop")
    parser.add_argument("--host", default="127.0.0.1",
                        help="address to serve on; any other than loopback needs a token")
    parser.add_argument("--port", type=int, default=8765)
    parser.add_argument("--token", default=None,
                        help="access token (made up and printed when --host is not loopback)")
    args = parser.parse_args(argv)
    from hprior_jax.labelling.store import QueryFolder

    if args.from_run and args.from_lab:
        parser.error("give --from-run or --from-lab, not both")
    if args.from_run or args.from_lab:
        from hprior_jax.runs.run_dir import check_out_dir

        check_out_dir(Path(args.dir))
        if args.from_run:
            from hprior_jax.experiments.label_queries import queries_from_run
            from hprior_jax.setup_jax import enable_compilation_cache

            enable_compilation_cache()
            ids = queries_from_run(args.from_run, args.dir, args.pairs, args.segment_len,
                                   args.seed)
        else:
            from hprior_jax.lab.human_labels import queries_from_lab

            ids = queries_from_lab(args.from_lab, args.dir, args.pairs, args.seed or 0)
        print(f"wrote {len(ids)} queries to {args.dir}", flush=True)
        if args.build_only:
            return 0
    from hprior_jax.labelling.server import ServerOptions, serve

    folder = QueryFolder(args.dir)
    options = ServerOptions(args.host, args.port, args.token).resolved()
    from hprior_jax import dir_lock

    with dir_lock.DirLock(Path(args.dir)):  # one server answers into a folder
        print(f"labelling {args.dir}: open {options.url()} (Ctrl-C stops; answers are saved "
              "as given)", flush=True)
        serve(folder, options)
    return 0


def _attention(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(
        prog="hprior attention",
        description="Attention of the world model's final step over a stored preference "
                    "segment (layers x time, state and action tokens), as appendix Figure 8.")
    parser.add_argument("--run", required=True,
                        help="run directory of a method with a world model (e.g. --algo prior)")
    parser.add_argument("--pair", type=int, default=0, help="index of the stored labelled pair")
    parser.add_argument("--seed", type=int, default=None, help="which of the run's seeds")
    parser.add_argument("--out", default=None, help="folder for the PNGs (default RUN/attention)")
    args = parser.parse_args(argv)
    from hprior_jax.experiments.attention_map import attention_maps_for_run

    for path in attention_maps_for_run(args.run, pair=args.pair, seed=args.seed, out=args.out):
        print(path)
    return 0


def _grid(argv: list[str]) -> int:
    from hprior_jax.experiments.grid import PAPER_SEEDS

    parser = argparse.ArgumentParser(
        prog="hprior grid",
        description="Run every (task, algorithm) with its seeds vmapped in one process into "
                    "OUT/<task>/<algo>/. Re-running the same command skips complete runs and "
                    "resumes interrupted ones.")
    parser.add_argument("--tasks", nargs="+", required=True)
    parser.add_argument("--algos", nargs="+", default=list(registry.GRID_DEFAULT),
                        help=f"methods (default: {' '.join(registry.GRID_DEFAULT)}; all: "
                             f"{' '.join(registry.names())})")
    parser.add_argument("--seeds", nargs="+", type=int, default=list(PAPER_SEEDS))
    parser.add_argument("--preset", "--budget", dest="preset", default=DEFAULT_PRESET,
                        choices=PRESETS,
                        help="the preset of every run, as `hprior train --preset` (default "
                             "paper; see README: Presets). --budget is an older name")
    parser.add_argument("--steps", type=int, default=None, help="override the preset's steps")
    parser.add_argument("--eval-every", type=int, default=None)
    parser.add_argument("--eval-budget", default="paper", choices=("paper", "cpu"),
                        help="cpu: 5 evaluation episodes every 10k steps (see README)")
    parser.add_argument("--contacts", default="floor", choices=("floor", "all"),
                        help="DM Control physics, as `hprior train --contacts`; grids run "
                             "before 2026-12-02 were run with `all`")
    parser.add_argument("--contact-cap", default="task", choices=("task", "none"),
                        help="MJX contact cap of the DM Control and MetaWorld ports, as "
                             "`hprior train --contact-cap`; grids run before 2026-12-04 were "
                             "run with `none`")
    parser.add_argument("--hand", default="arm", choices=("arm", "free"),
                        help="MetaWorld scene, as `hprior train --hand`; grids run before "
                             "this option were run with `free`")
    parser.add_argument("--out", required=True, help="results directory")
    parser.add_argument("--devices", type=int, default=None,
                        help="devices to use (default: all); runs train side by side, each "
                             "over as many as split its seeds evenly")
    parser.add_argument("--estimate", action="store_true",
                        help="time one chunk per phase, the first events and an evaluation "
                             "of every run first, pack the runs by those times and print "
                             "the estimated wall time")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    from hprior_jax.experiments.grid import run_grid
    from hprior_jax.loop import host
    from hprior_jax.setup_jax import enable_compilation_cache

    from hprior_jax.presets import EVAL_BUDGETS

    overrides = dict(EVAL_BUDGETS[args.eval_budget], contacts=args.contacts,
                     contact_cap=args.contact_cap, hand=args.hand)
    overrides.update({k: v for k, v in (("steps", args.steps), ("eval_every", args.eval_every))
                      if v is not None})
    enable_compilation_cache()
    try:
        run_grid(args.out, args.tasks, args.algos, args.seeds, args.preset, overrides,
                 progress=not args.no_progress, devices=args.devices, estimate=args.estimate)
    except host.Interrupted as e:
        print(f"\n{e}. Continue the grid with the same command.", file=sys.stderr, flush=True)
        return 130
    print(f"grid complete in {args.out}; make the tables with `hprior report {args.out}`")
    return 0


def _report(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(
        prog="hprior report",
        description="Tables 6-7 (normalized scores), paired t-tests, learning curves, reward "
                    "correlation and attention maps of a results directory.")
    parser.add_argument("root", help="results directory of `hprior grid`")
    parser.add_argument("--out", default=None, help="report folder (default ROOT/report)")
    parser.add_argument("--normalize", default="mean-of-ratios",
                        choices=("mean-of-ratios", "ratio-of-means"))
    parser.add_argument("--min-reference", type=float, default=0.0,
                        help="leave out evaluation steps where SAC scores at most this")
    parser.add_argument("--pair-by-seed", action="store_true",
                        help="normalize each seed by the SAC run of the same seed")
    parser.add_argument("--t-test-over", default="task", choices=("task", "seed"),
                        help="t-test pairs: per-task means (appendix F) or (task, seed) scores")
    parser.add_argument("--no-attention", action="store_true",
                        help="skip the attention maps (they restore PRIOR checkpoints)")
    args = parser.parse_args(argv)
    from hprior_jax.experiments.report import make_report

    path = make_report(args.root, args.out, args.normalize, args.min_reference,
                       args.pair_by_seed, args.t_test_over, attention=not args.no_attention)
    print(path.read_text())
    print(f"report written to {path.parent}")
    return 0


def _reward_lab(argv: list[str]) -> int:
    from hprior_jax.lab import dataset as datasets
    from hprior_jax.lab.sweep import default_rules, rules

    parser = argparse.ArgumentParser(
        prog="hprior reward-lab",
        description="Reward learning decoupled from RL: every rule trains reward models from "
                    "the same kind of labels on a fixed dataset of the task (built once by a "
                    "SAC run on the true reward, cached in $HPRIOR_LAB_CACHE), seeds and rules "
                    "vmapped in one program; reports held-out accuracy and correlation with the "
                    "true reward, with CIs and paired tests against "
                    f"{registry.LAB_REFERENCE}.")
    parser.add_argument("--task", required=True)
    parser.add_argument("--preset", default="reduced", choices=("paper", "reduced", "smoke"),
                        help="the RL preset whose reward, schedule and world-model settings "
                             "the lab uses (and the dataset's SAC)")
    parser.add_argument("--dataset-steps", type=int, default=datasets.DEFAULT_STEPS)
    parser.add_argument("--dataset-seed", type=int, default=None,
                        help="default 0 (with --dataset-from-run: the run's first seed)")
    parser.add_argument("--dataset-from-run", default=None, metavar="RUN",
                        help="make the dataset from this finished `hprior train --algo "
                             f"{registry.REFERENCE}` run's replay buffer instead of a new run "
                             "(cached under the run's seed, steps and preset)")
    parser.add_argument("--dataset-only", action="store_true", help="build the dataset, stop")
    parser.add_argument("--physics", action="store_true",
                        help="the dataset also keeps the physics state of every training step "
                             "(a person can label its pairs: `hprior label --from-lab`)")
    parser.add_argument("--labels", default=None, metavar="DIR",
                        help="train every rule once on a person's answers in this query folder "
                             "(`hprior label --from-lab`) instead of the teacher's labels; "
                             "the dataset is the one the folder names")
    parser.add_argument("--rules", nargs="+", default=None,
                        help=f"default: {' '.join(default_rules())}; also PRIOR's ablations "
                             f"({' '.join(r for r in rules() if r not in default_rules())}); "
                             "RULE@LAMBDA gives a rule its own λ (prior@1 prior@25: a λ "
                             "sweep in one program); RULE~shift the shifted target form "
                             "α·(R̂ + T) − 1 (oracle~shift, prior~shift)")
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--budgets", nargs="+", type=int, default=[25, 100, 400])
    parser.add_argument("--queries-per-round", type=int, default=None,
                        help="default: the preset's (10 DMC, 20 MetaWorld at reduced)")
    parser.add_argument("--feed", default=None, choices=("uniform", "disagreement", "entropy"),
                        help="query selection after the first (uniform) round")
    parser.add_argument("--teacher", default="oracle", help="a B-Pref teacher preset")
    parser.add_argument("--one-shot", action="store_true",
                        help="train once on all of a budget's labels (uniform queries)")
    parser.add_argument("--lam", type=float, default=None, help="λ (default: the preset's)")
    parser.add_argument("--prior-set", nargs="+", default=None, metavar="FIELD=VALUE",
                        help="change the proposed method's settings for this lab, e.g. "
                             "wm_layers=2 or wm_update_steps=500 (a world-model ablation); "
                             "the rules that read the world model are then reported as "
                             "RULE[TAG]")
    parser.add_argument("--tag", default=None,
                        help="TAG of --prior-set (default: the settings); merge the reports "
                             "of several labs with `python -m hprior_jax.lab.report "
                             "A/results.csv B/results.csv OUT`")
    parser.add_argument("--no-world-model-cache", action="store_true",
                        help="train the seeds' world models even when a lab of the same "
                             "dataset, seeds and world-model settings left them in "
                             "$HPRIOR_LAB_CACHE/world_models (and do not keep them)")
    parser.add_argument("--contrasts", nargs="+", default=(), metavar="A:B[@MARGIN]",
                        help="pre-registered contrasts A − B, reported first with Holm's "
                             "correction (MARGIN: a number or C:D/K, adds a TOST equivalence "
                             "test), e.g. oracle~shift:rvar "
                             "prior~shift:positional~shift@oracle~shift:rvar/2")
    parser.add_argument("--out", default=None, help="default runs/reward_lab/<task>")
    args = parser.parse_args(argv)
    from hprior_jax.lab.contrasts import Contrast
    from hprior_jax.lab.sweep import lab_config, run_lab

    try:
        contrasts = [Contrast.parse(c) for c in args.contrasts]
    except ValueError as e:
        parser.error(f"--contrasts: {e}")
    from hprior_jax.setup_jax import enable_compilation_cache

    enable_compilation_cache()
    given = None
    if args.labels:
        from hprior_jax.lab.human_labels import given_labels

        path, given, unanswered = given_labels(Path(args.labels))
        data = datasets.Dataset.load(path)
        if data.task != args.task:
            parser.error(f"--labels {args.labels} are of {data.task}, not --task {args.task}")
        if unanswered:
            print(f"{unanswered} queries of {args.labels} are not answered: training on the "
                  f"{len(given)} that are", file=sys.stderr)
        args.budgets, args.one_shot = [len(given)], True
    elif args.dataset_from_run:
        data = datasets.from_run(args.dataset_from_run, args.dataset_seed)
        if data.task != args.task:
            parser.error(f"--dataset-from-run {args.dataset_from_run} is a {data.task} run, "
                         f"not --task {args.task}")
        info = data.info
        path = data.save(datasets.dataset_path(data.task, info["seed"], info["steps"],
                                               info["preset"]))
    else:
        data, path = datasets.load_or_build(args.task, args.dataset_seed or 0,
                                            args.dataset_steps, args.preset,
                                            physics=args.physics)
    print(f"dataset {path}: {data.info}", flush=True)
    if args.dataset_only:
        return 0
    if args.seeds < 10:
        print(f"warning: {args.seeds} seeds; the lab's comparisons want 10 or more",
              file=sys.stderr)
    cfg = lab_config(data, args.preset, args.rules, args.seeds, args.budgets,
                     args.queries_per_round, args.feed, args.teacher, args.one_shot, args.lam,
                     args.prior_set, args.tag)
    out = args.out or f"runs/reward_lab/{args.task}"
    info = run_lab(data, cfg, out, progress=lambda line: print(line, flush=True), given=given,
                   reuse_world_models=not args.no_world_model_cache, contrasts=contrasts)
    if info["world_model_cache"]:
        cache = info["world_model_cache"]
        print(f"world models {'loaded from' if cache['loaded'] else 'kept in'} {cache['path']}")
    print(f"{info['wall_seconds']} s, peak RSS {info['peak_rss_gib']} GiB; report in {out}")
    return 0


def _tasks(argv: list[str]) -> int:
    from hprior_jax.envs import task_names

    print("\n".join(task_names()))
    return 0


def _methods(argv: list[str]) -> int:
    print(registry.describe())
    return 0


def main(argv: list[str] | None = None) -> int:
    from hprior_jax.dir_lock import DirInUse

    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help"):
        print(USAGE, file=sys.stdout if argv else sys.stderr)  # bare `hprior`: a usage error
        return 0 if argv else 2
    if argv[0] in ("--version", "-V"):
        from hprior_jax.provenance import version_string

        print(version_string())
        return 0
    command, rest = argv[0], argv[1:]
    commands = {"train": _train, "eval": _eval, "export": _export, "label": _label,
                "attention": _attention, "grid": _grid, "report": _report,
                "reward-lab": _reward_lab, "tasks": _tasks, "methods": _methods}
    if command not in commands:
        print(f"unknown command {command!r}\n\n{USAGE}", file=sys.stderr)
        return 2
    try:
        return commands[command](rest)
    except (ValueError, FileExistsError, FileNotFoundError, NotADirectoryError,
            PermissionError, DirInUse) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # disk full, permission lost mid-run: the path and the cause
        where = f"{e.filename}: " if e.filename else ""
        print(f"error: {where}{e.strerror or e}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:  # before training started (a run saves on its own Ctrl-C)
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
