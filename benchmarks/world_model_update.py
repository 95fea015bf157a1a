"""One world-model dynamics update (Transformer-XL, appendix C / Table 5): time and roofline.

    python -m benchmarks.world_model_update [--sizes reduced paper] [--seeds 1 5] [--updates 3]

One update = `hprior_jax.prior.world_model.update_dynamics` (the function PRIOR's schedule runs:
every j = 2000 env steps, `wm_update_steps` of these) on a batch of random segments
(cheetah sizes: obs 17, action 6; segment 50), under `jit(vmap(scan(...)))` over seeds;
compile timed apart. Sizes: `paper` = the appendix/TWM defaults (10 layers x 256, batch 100),
`reduced` = the CPU preset (hprior_jax/presets.py). There is no PyTorch reference yet (TWM's
Transformer-XL would have to be written out here); the roofline columns say how close the update
runs to what the device sustains on large matmuls. Writes benchmarks/results/world_model_update.csv.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import tasks  # noqa: F401  (sets XLA_FLAGS before jax is imported)
from benchmarks._timing import (best_seconds, machine, matmul_gflops_s, roofline,
                                select_device, write_rows, xla_gflop)

RESULTS = Path(__file__).resolve().parent / "results" / "world_model_update.csv"
OBS, ACT, SEGMENT = 17, 6, 50


def world_model_config(size: str):
    from hprior_jax.presets import prior_config

    return prior_config("cheetah_run", size).world_model(OBS, ACT, SEGMENT)


def jax_update_ms(size: str, n_seeds: int, n_updates: int, repeats: int) -> dict:
    import jax

    from hprior_jax.prior import world_model as wm

    cfg = world_model_config(size)
    shape = (cfg.batch_size, SEGMENT)

    def run(state, key):
        def body(st, k):
            k_obs, k_act, k_drop = jax.random.split(k, 3)
            obs = jax.random.normal(k_obs, shape + (OBS,))
            act = jax.random.uniform(k_act, shape + (ACT,), minval=-1, maxval=1)
            st, m = wm.update_dynamics(st, obs, act, k_drop, cfg)
            return st, m["prior/wm_dyn_grad_norm"]
        return jax.lax.scan(body, state, jax.random.split(key, n_updates))

    keys = jax.random.split(jax.random.key(0), n_seeds)
    states = jax.jit(jax.vmap(lambda k: wm.init(k, cfg)))(keys)
    t0 = time.perf_counter()
    fn = jax.jit(jax.vmap(run)).lower(states, keys).compile()
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(fn(states, keys))
    best = best_seconds(lambda: fn(states, keys), repeats, jax.block_until_ready)
    one = jax.tree.map(lambda x: x[0], states)
    obs = jax.numpy.zeros(shape + (OBS,))
    act = jax.numpy.zeros(shape + (ACT,))
    gflop = xla_gflop(jax.jit(lambda s, o, a, k: wm.update_dynamics(s, o, a, k, cfg)),
                      one, obs, act, keys[0])
    return {"ms_per_update": 1e3 * best / n_updates, "compile_s": compile_s, "gflop": gflop,
            "device": jax.devices()[0].device_kind,
            "layers": cfg.num_layers, "embed": cfg.embed_dim, "batch": cfg.batch_size}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--sizes", nargs="+", default=["reduced", "paper"], choices=["reduced", "paper"])
    p.add_argument("--seeds", nargs="+", type=int, default=[1, 5])
    p.add_argument("--updates", type=int, default=3, help="updates per timed run")
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--device", default="cpu", choices=["cpu", "gpu"])
    p.add_argument("--out", type=Path, default=RESULTS)
    args = p.parse_args(argv)
    if any(s < 1 for s in args.seeds) or args.updates < 1 or args.repeats < 1:
        p.error("--seeds, --updates and --repeats must be >= 1")
    select_device(args.device)
    peak = matmul_gflops_s(args.repeats)
    rows = []
    for size in args.sizes:
        for n_seeds in args.seeds:
            res = jax_update_ms(size, n_seeds, args.updates, args.repeats)
            per_seed = res["ms_per_update"] / n_seeds
            row = {"sizes": size, "layers": res["layers"], "embed": res["embed"],
                   "batch": res["batch"], "seeds": n_seeds, "device": res["device"],
                   "jax_ms_per_update": round(res["ms_per_update"], 1),
                   "jax_ms_per_seed": round(per_seed, 1), "jax_compile_s": round(res["compile_s"], 1),
                   **roofline(res["gflop"], per_seed, None, peak),
                   "machine": machine()}
            rows.append(row)
            print("  ".join(f"{k}={v}" for k, v in row.items() if k != "machine"), flush=True)
    write_rows(rows, args.out)


if __name__ == "__main__":
    main()
