"""`hprior grid` (every task x method with its seeds) and `hprior report` (its tables and tests)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from hprior_jax.methods import registry


def grid(argv: list[str]) -> int:
    from hprior_jax.config import DEFAULT_PRESET, PRESETS
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
                        help="DM Control physics, as `hprior train --contacts`")
    parser.add_argument("--contact-cap", default="task", choices=("task", "none"),
                        help="MJX contact cap of the DM Control and MetaWorld ports, as "
                             "`hprior train --contact-cap`")
    parser.add_argument("--hand", default="arm", choices=("arm", "free"),
                        help="MetaWorld scene, as `hprior train --hand`")
    parser.add_argument("--wrist", default="task", choices=("task", "box"),
                        help="MetaWorld wrist collider, as `hprior train --wrist`")
    parser.add_argument("--out", required=True, help="results directory")
    parser.add_argument("--devices", type=int, default=None,
                        help="devices to use (default: all); runs train side by side, each "
                             "over as many as split its seeds evenly")
    parser.add_argument("--estimate", action="store_true",
                        help="time one chunk per phase, the first events and an evaluation "
                             "of every run first, pack the runs by those times and print "
                             "the estimated wall time")
    parser.add_argument("--capture-video", type=int, default=0, metavar="K",
                        help="every K-th evaluation, an MP4 of each seed's first evaluation "
                             "episode in RUN/videos/ (0: none), as `hprior train "
                             "--capture-video`")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    if (Path(args.out) / "config.json").exists():
        raise ValueError(f"--out {args.out} is a run directory of `hprior train`, not a grid's "
                         "results folder (a grid keeps its runs in OUT/<task>/<algo>/); "
                         "choose another --out")
    from hprior_jax import provenance
    from hprior_jax.experiments.grid import run_grid
    from hprior_jax.loop import host
    from hprior_jax.setup_jax import enable_compilation_cache

    from hprior_jax.presets import EVAL_BUDGETS

    overrides = dict(EVAL_BUDGETS[args.eval_budget], contacts=args.contacts,
                     contact_cap=args.contact_cap, hand=args.hand, wrist=args.wrist,
                     capture_video=args.capture_video)
    overrides.update({k: v for k, v in (("steps", args.steps), ("eval_every", args.eval_every))
                      if v is not None})
    enable_compilation_cache()
    try:
        run_grid(args.out, args.tasks, args.algos, args.seeds, args.preset, overrides,
                 progress=not args.no_progress, devices=args.devices, estimate=args.estimate,
                 run_info=provenance.run_info(["grid", *argv]))
    except host.Interrupted as e:
        print(f"\n{e}. Continue the grid with the same command.", file=sys.stderr, flush=True)
        return 130
    print(f"grid complete in {args.out}; make the tables with `hprior report {args.out}`")
    return 0


def report(argv: list[str]) -> int:
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
