"""`hprior label`: the labelling web page over a query folder (from a run, from a lab dataset)."""
from __future__ import annotations

import argparse
from pathlib import Path


def label(argv: list[str]) -> int:
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
    from hprior_jax.labelling.server import ServerOptions, serve
    from hprior_jax.labelling.store import QueryFolder

    # where it will serve, checked before any query is written
    options = ServerOptions(args.host, args.port, args.token).check().resolved()

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
    folder = QueryFolder(args.dir)
    from hprior_jax import dir_lock

    with dir_lock.DirLock(Path(args.dir)):  # one server answers into a folder
        print(f"labelling {args.dir}: open {options.url()} (Ctrl-C stops; answers are saved "
              "as given)", flush=True)
        serve(folder, options)
    return 0
