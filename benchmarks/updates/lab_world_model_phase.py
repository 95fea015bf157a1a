"""The reward lab's world-model phase alone: every seed's world model trained as `hprior
reward-lab` trains it (pre-training, then the dynamics updates of its budgets), vmapped over
seeds, compile timed apart, nothing cached.

    python -m benchmarks.updates.lab_world_model_phase --dataset PATH.npz [--seeds 10]
        [--budgets 25 100]

PATH: a lab dataset (`$HPRIOR_LAB_CACHE/<task>_sac-reduced_50000steps_seed0.npz`). Prints one
CSV row (and appends it to --out when given); run it once per code version, back to back on
an idle machine, to compare them.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import tasks  # noqa: F401  (sets XLA_FLAGS before jax is imported)
from benchmarks._timing import machine, read_rows, write_rows


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--dataset", type=Path, required=True)
    p.add_argument("--seeds", type=int, default=10)
    p.add_argument("--budgets", nargs="+", type=int, default=[25, 100])
    p.add_argument("--label", default="", help="names the code version in the row")
    p.add_argument("--out", type=Path, default=None)
    args = p.parse_args(argv)
    import jax
    import jax.numpy as jnp

    from hprior_jax.lab.dataset import Dataset
    from hprior_jax.lab.learn import Lab
    from hprior_jax.lab.sweep import lab_config

    data = Dataset.load(args.dataset)
    cfg = lab_config(data, rule_names=["prior"], seeds=args.seeds, budgets=tuple(args.budgets))
    lab = Lab(cfg, data, None, world_model_cache=None)
    keys = jnp.stack([jax.random.PRNGKey(s) for s in cfg.seeds])
    t0 = time.perf_counter()
    lab.seed_contexts(keys)
    row = {"label": args.label, "task": data.task, "seeds": args.seeds,
           "pretrain_steps": cfg.wm_pretrain_steps, "dynamics_steps": cfg.wm_steps,
           "run_s": round(lab.seconds["world_model"], 1),
           "compile_s": round(lab.compile_seconds["world_model"], 1),
           "wall_s": round(time.perf_counter() - t0, 1), "machine": machine()}
    print(",".join(map(str, row)), ",".join(map(str, row.values())), sep="\n")
    if args.out:
        write_rows([row], args.out, read_rows(args.out))


if __name__ == "__main__":
    main()
