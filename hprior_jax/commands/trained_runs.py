"""The commands that read a trained run: `hprior eval`, `hprior export`, `hprior attention`."""
from __future__ import annotations

import argparse


def evaluate(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(
        prog="hprior eval",
        description="Evaluate the policy of a run's checkpoint on fresh episodes, per seed: "
                    "true return (mean and std) and, for MetaWorld, success rate. Writes "
                    "RUN/eval_step<N>_<K>ep.csv; --video renders one episode per seed to "
                    "RUN/videos/eval_step<N>_seed<S>.mp4 (needs OSMesa: apt-get install "
                    "libosmesa6).")
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


def export(argv: list[str]) -> int:
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


def attention(argv: list[str]) -> int:
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
