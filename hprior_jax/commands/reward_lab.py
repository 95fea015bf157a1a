"""`hprior reward-lab`: reward learning on a fixed dataset, every rule from the same labels;
`hprior reward-lab report`: a lab's report rebuilt from its results.csv, or several labs'
merged."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from hprior_jax.lab import rules as lab_rules
from hprior_jax.methods import registry

REPORT = "report"  # `hprior reward-lab report ...`; the lab itself takes no positional argument
REPORT_HINT = (f"hprior reward-lab {REPORT} RESULTS_CSV... OUT_DIR rebuilds a lab's report from "
               f"its results.csv, or merges several labs' (hprior reward-lab {REPORT} --help).")


def reward_lab(argv: list[str]) -> int:
    if argv[:1] == [REPORT]:
        report(argv[1:])
        return 0
    return _lab(argv)


def _lab(argv: list[str]) -> int:
    from hprior_jax.lab import dataset as datasets

    parser = _parser(datasets, lab_rules.default_rules(), lab_rules.rules())
    args = parser.parse_args(argv)
    from hprior_jax.lab.contrasts import Contrast
    from hprior_jax.lab.sweep import check_arguments, lab_config, run_lab

    try:
        contrasts = [Contrast.parse(c) for c in args.contrasts]
    except ValueError as e:
        raise ValueError(f"--contrasts: {e}") from None
    # every argument before the dataset (a build takes minutes) and before --out is touched
    if args.dataset_steps < 1:
        raise ValueError(f"--dataset-steps {args.dataset_steps}: give a positive step count")
    check_arguments(args.task, args.preset, args.rules, args.seeds, args.budgets, args.teacher,
                    args.prior_set, args.queries_per_round)
    from hprior_jax.setup_jax import enable_compilation_cache

    enable_compilation_cache()
    given = None

    def of_task(data, source: str):
        if data.task != args.task:
            parser.error(f"{source} is of {data.task}, not --task {args.task}")
        return data

    if args.labels:
        from hprior_jax.lab.human_labels import given_labels

        path, given, unanswered = given_labels(Path(args.labels))
        data = of_task(datasets.Dataset.load(path), f"--labels {args.labels}")
        if unanswered:
            print(f"{unanswered} queries of {args.labels} are not answered: training on the "
                  f"{len(given)} that are", file=sys.stderr)
        args.budgets, args.one_shot = [len(given)], True
    elif args.dataset:
        path = Path(args.dataset)
        data = of_task(datasets.Dataset.load(path), f"--dataset {args.dataset}")
    elif args.dataset_from_run:
        data = of_task(datasets.from_run(args.dataset_from_run, args.dataset_seed),
                       f"--dataset-from-run {args.dataset_from_run}")
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
        print(f"warning: {args.seeds} seeds; the lab's comparisons want 10 or more (the seed "
              f"shards of one lab merge: `hprior reward-lab report`)", file=sys.stderr)
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    cfg = lab_config(data, args.preset, args.rules, seeds, args.budgets,
                     args.queries_per_round, args.feed, args.teacher, args.one_shot, args.lam,
                     args.prior_set, args.tag)
    out = args.out or f"runs/reward_lab/{args.task}"
    from hprior_jax.dir_lock import DirInUse
    from hprior_jax.lab.resume import StateMismatch

    try:
        info = run_lab(data, cfg, out, progress=lambda line: print(line, flush=True),
                       given=given, reuse_world_models=not args.no_world_model_cache,
                       contrasts=contrasts, resume=args.resume)
    except (FileExistsError, StateMismatch, DirInUse) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"stopped: the same command with --resume goes on from the last state kept in "
              f"{out} (the rounds since then run again)", file=sys.stderr)
        return 130
    if info["world_model_cache"]:
        cache = info["world_model_cache"]
        print(f"world models {'loaded from' if cache['loaded'] else 'kept in'} {cache['path']}")
    print(f"{info['wall_seconds']} s, peak RSS {info['peak_rss_gib']} GiB; report in {out}")
    return 0


def _parser(datasets, default_rules: list[str], all_rules) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="hprior reward-lab",
        description="Reward learning decoupled from RL: every rule trains reward models from "
                    "the same kind of labels on a fixed dataset of the task (built once by a "
                    "SAC run on the true reward, cached in $HPRIOR_LAB_CACHE), seeds and rules "
                    "vmapped in one program; reports held-out accuracy and correlation with the "
                    "true reward, with CIs and paired tests against "
                    f"{lab_rules.REFERENCE}.",
        epilog=REPORT_HINT)
    parser.add_argument("--task", required=True)
    parser.add_argument("--preset", default="reduced", choices=("paper", "reduced", "smoke"),
                        help="the RL preset whose reward, schedule and world-model settings "
                             "the lab uses (and the dataset's SAC)")
    parser.add_argument("--dataset-steps", type=int, default=datasets.DEFAULT_STEPS)
    parser.add_argument("--dataset-seed", type=int, default=None,
                        help="default 0 (with --dataset-from-run: the run's first seed)")
    parser.add_argument("--dataset", default=None, metavar="FILE",
                        help="learn from this dataset file (a lab's .npz) instead of the "
                             "cached or built one: one lab run on several machines (seed "
                             "shards) must share it, as another machine's SAC run may build "
                             "other episodes")
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
                        help=f"default: {' '.join(default_rules)}; also PRIOR's ablations and "
                             "the credits learned from labels "
                             f"({' '.join(r for r in all_rules if r not in default_rules)}); "
                             "RULE@LAMBDA gives a rule its own λ (prior@1 prior@25: a λ sweep in "
                             "one program); RULE~shift the target α·(R̂ + T) − 1 (oracle~shift)")
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--first-seed", type=int, default=0,
                        help="the lab's seeds are FIRST_SEED .. FIRST_SEED + SEEDS - 1: a "
                             "seed's cells do not depend on the others', so a lab too long for "
                             "one sitting runs as seed shards (--seeds 5 --first-seed 5, ...) "
                             "merged by `hprior reward-lab report A/results.csv "
                             "B/results.csv OUT`")
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
                             "of several labs with `hprior reward-lab report "
                             "A/results.csv B/results.csv OUT`")
    parser.add_argument("--no-world-model-cache", action="store_true",
                        help="train the seeds' world models even when a lab of the same "
                             "dataset, seeds and world-model settings left them in "
                             "$HPRIOR_LAB_CACHE/world_models (and do not keep them)")
    parser.add_argument("--contrasts", nargs="+", default=(), metavar="A:B[@MARGIN]",
                        help="pre-registered contrasts A − B, reported first with Holm's "
                             "correction (MARGIN: a number or C:D/K, adds a TOST equivalence "
                             "test; C:D/K also A − B's share of C − D), e.g. oracle~shift:rvar "
                             "prior~shift:positional~shift@oracle~shift:rvar/2")
    parser.add_argument("--out", default=None, help="default runs/reward_lab/<task>")
    parser.add_argument("--resume", action="store_true",
                        help="go on from where a lab stopped in --out (Ctrl-C, a kill): "
                             "the same command plus --resume; its state is kept between "
                             "rounds (at least every 10 min and at every budget)")
    return parser


def report(argv: list[str]) -> Path:
    """`hprior reward-lab report`: write the report of one or more results.csv; its path."""
    from hprior_jax.lab.report import merge_results, write_report
    from hprior_jax.lab.report_notes import merged_notes

    parser = _report_parser()
    args = parser.parse_args(argv)
    pairs = [tuple(p.split(":")) for p in args.pairs]
    if any(len(p) != 2 for p in pairs):
        parser.error("write each pair as A:B")
    if len(args.paths) < 2:
        parser.error("give one or more results.csv and then the output folder")
    try:
        rows, differing = merge_results(args.paths[:-1], args.tags)
    except ValueError as e:  # --tags not one per results.csv
        parser.error(f"--tags: {e} ('' for none)")
    if args.only:
        missing = set(args.only) - {row["rule"] for row in rows}
        if missing:
            parser.error(f"--only: no rows of {sorted(missing)}")
        rows = [row for row in rows if row["rule"] in args.only]
    if differing:
        print(f"{differing} rows found in several files differ in a metric: the first "
              "file's are kept", file=sys.stderr)
    notes = merged_notes(args.paths[:-1], args.paths[-1])
    path = write_report(rows, args.paths[-1], args.title, pairs, args.contrasts, notes,
                        figures=not args.no_figures)
    print(path)
    return path


def _report_parser() -> argparse.ArgumentParser:
    from hprior_jax.lab.report import DEFAULT_TITLE

    parser = argparse.ArgumentParser(
        prog=f"hprior reward-lab {REPORT}",
        description="Rebuild a reward-learning lab report from its raw results.csv, or merge "
                    "the results.csv of several labs into one report: labs of the same dataset "
                    "and seeds (their rules side by side) or the seed shards of one lab "
                    "(`hprior reward-lab --first-seed`; their world-model diagnostics "
                    "and ceiling notes are merged from the files beside each results.csv).")
    parser.add_argument("paths", type=Path, nargs="+", metavar="RESULTS_CSV... OUT_DIR")
    parser.add_argument("--title", default=DEFAULT_TITLE)
    parser.add_argument("--pairs", nargs="+", default=(), metavar="A:B",
                        help="also compare rule A with rule B (A − B, paired by seed), e.g. "
                             "prior:positional prior:rvar")
    parser.add_argument("--contrasts", nargs="+", default=(), metavar="A:B[@MARGIN]",
                        help="pre-registered contrasts A − B (Holm over all of a metric; "
                             "MARGIN, a number or C:D/K, adds an equivalence test), e.g. "
                             "oracle~shift:rvar prior~shift:positional~shift@oracle~shift:rvar/2")
    parser.add_argument("--tags", nargs="+", default=None, metavar="TAG",
                        help="one per RESULTS_CSV: that lab's rules are reported as RULE[TAG] "
                             "('' keeps the names), e.g. '' one-shot for a lab and its "
                             "--one-shot copy, compared by --pairs rvar[one-shot]:rvar")
    parser.add_argument("--only", nargs="+", default=None, metavar="RULE",
                        help="report only these rules (names after --tags), e.g. pebble rvar "
                             "pebble[one-shot] rvar[one-shot]")
    parser.add_argument("--no-figures", action="store_true",
                        help="tables only: no PNGs, and report.md links none")
    return parser
