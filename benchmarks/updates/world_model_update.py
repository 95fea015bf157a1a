"""One world-model dynamics update (Transformer-XL, appendix C / Table 5): time and roofline.

    python -m benchmarks.updates.world_model_update [--sizes reduced paper] [--seeds 1 5]
        [--updates 3] [--dropout-rng rbg threefry]

One update = `hprior_jax.prior.world_model.update_dynamics` (the function PRIOR's schedule runs:
every j = 2000 env steps, `wm_update_steps` of these) on a batch of random segments
(cheetah sizes: obs 17, action 6; segment 50), under `jit(vmap(scan(...)))` over seeds;
compile timed apart. Sizes: `paper` = the appendix/TWM defaults (10 layers x 256, batch 100),
`reduced` = the CPU preset (hprior_jax/presets.py). The PyTorch reference
(`benchmarks/updates/_torch_world_model.py`) is the same update as TWM writes it (a Python loop over
layers, one seed at a time), started from the same weights: the script first checks that both
give the same deterministic loss and gradient norm, then times each. The roofline columns say how
close the update runs to what the device sustains on large matmuls. `--dropout-rng` times the
dropout bits the config offers (hash, the default; rbg; threefry). The credit rows time
`prior.attention.pair_credit` (α of both segments of every stored pair: what each feedback
round recomputes) for `--credit-pairs` stored pairs, one seed.
Writes benchmarks/results/updates/world_model_update.csv and world_model_credit.csv.
"""
from __future__ import annotations

import argparse
import dataclasses
import itertools
import time
from pathlib import Path

import tasks  # noqa: F401  (sets XLA_FLAGS before jax is imported)
from benchmarks._timing import (torch_wait, against_torch, available_memory_gib, best_seconds, machine,
                                matmul_gflops_s, read_rows, select_device, torch_reference,
                                write_rows, xla_gflop)

RESULTS = Path(__file__).resolve().parents[1] / "results" / "updates" / "world_model_update.csv"
CREDIT_RESULTS = RESULTS.with_name("world_model_credit.csv")
OBS, ACT, SEGMENT = 17, 6, 50


def world_model_config(size: str, dropout_rng: str | None = None):
    from hprior_jax.presets import train_preset

    cfg = train_preset("cheetah_run", "prior", size).prior.world_model(OBS, ACT, SEGMENT)
    return cfg if dropout_rng is None else dataclasses.replace(cfg, dropout_rng=dropout_rng)


def update_program(size: str, n_seeds: int, n_updates: int, dropout_rng: str | None = None):
    """`jit(vmap(scan(update_dynamics)))` over `n_seeds` seeds and `n_updates` updates on random
    segments, not yet compiled. -> (fn, states, keys, cfg); call fn(states, keys)."""
    import jax

    from hprior_jax.prior import world_model as wm

    cfg = world_model_config(size, dropout_rng)
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
    return jax.jit(jax.vmap(run)), states, keys, cfg


def jax_update_ms(size: str, n_seeds: int, n_updates: int, repeats: int,
                  dropout_rng: str | None = None) -> dict:
    import jax

    from hprior_jax.prior import world_model as wm

    program, states, keys, cfg = update_program(size, n_seeds, n_updates, dropout_rng)
    shape = (cfg.batch_size, SEGMENT)
    t0 = time.perf_counter()
    fn = program.lower(states, keys).compile()
    compile_s = time.perf_counter() - t0
    temp_gib = fn.memory_analysis().temp_size_in_bytes / 2**30
    free_gib = available_memory_gib()
    if free_gib is not None and temp_gib > free_gib - 2.0:
        # the kernel's OOM killer would end the process without a word; say why instead
        # (2 GiB: states, outputs and the runtime beside the temporaries)
        return {"skipped": f"needs {temp_gib:.1f} GiB of temporaries, {free_gib:.1f} GiB available: "
                           f"run it in a process of its own (--sizes {size} --seeds {n_seeds} "
                           "--no-torch --append) or on a larger machine"}
    jax.block_until_ready(fn(states, keys))
    best = best_seconds(lambda: fn(states, keys), repeats, jax.block_until_ready)
    one = jax.tree.map(lambda x: x[0], states)
    obs = jax.numpy.zeros(shape + (OBS,))
    act = jax.numpy.zeros(shape + (ACT,))
    # XLA's cost analysis counts the body of the layer loop once: count on unrolled layers
    unrolled = dataclasses.replace(cfg, unroll_layers=True)
    gflop = xla_gflop(jax.jit(lambda s, o, a, k: wm.update_dynamics(s, o, a, k, unrolled)),
                      one, obs, act, keys[0])
    return {"ms_per_update": 1e3 * best / n_updates, "compile_s": compile_s, "gflop": gflop,
            "temp_gib": temp_gib,
            "device": jax.devices()[0].device_kind, "dropout_rng": cfg.dropout_rng,
            "layers": cfg.num_layers, "embed": cfg.embed_dim, "batch": cfg.batch_size}


def credit_ms(size: str, pairs: int, repeats: int) -> float:
    """ms of `pair_credit` over a store holding `pairs` pairs of random segments (one seed)."""
    import jax

    from hprior_jax.buffers import preferences
    from hprior_jax.prior import world_model as wm
    from hprior_jax.prior.attention import pair_credit

    cfg = world_model_config(size)
    store = preferences.init(SEGMENT, OBS, ACT, capacity=pairs)
    k1, k2 = jax.random.split(jax.random.key(1))
    store = store.replace(obs1=jax.random.normal(k1, store.obs1.shape),
                          obs2=jax.random.normal(k2, store.obs2.shape),
                          count=jax.numpy.asarray(pairs, jax.numpy.int32))
    params = wm.init(jax.random.key(0), cfg).params
    fn = jax.jit(lambda p, s: pair_credit(p, s, cfg)).lower(params, store).compile()
    jax.block_until_ready(fn(params, store))
    return 1e3 * best_seconds(lambda: fn(params, store), repeats, jax.block_until_ready)


def torch_update_ms(size: str, n_updates: int, repeats: int) -> dict:
    """PyTorch update time, after checking it computes what the JAX update computes."""
    import jax
    import numpy as np
    import optax
    import torch

    from benchmarks.updates._torch_world_model import TorchDynamicsUpdate
    from hprior_jax.prior import world_model as wm

    cfg = world_model_config(size)
    state = wm.init(jax.random.key(0), cfg)
    rng = np.random.default_rng(0)
    obs = rng.standard_normal((cfg.batch_size, SEGMENT, OBS)).astype(np.float32)
    act = rng.uniform(-1, 1, (cfg.batch_size, SEGMENT, ACT)).astype(np.float32)
    (jax_loss, _), grads = jax.value_and_grad(wm.dynamics_loss, has_aux=True)(
        state.params.dyn, state.params.obs, obs, act, None, cfg, True)
    ref = TorchDynamicsUpdate(state, cfg)
    t_obs, t_act = torch.as_tensor(obs), torch.as_tensor(act)
    with torch.no_grad():
        torch_loss = float(ref.loss(t_obs, t_act, training=False))
    loss_gap = abs(torch_loss - float(jax_loss)) / abs(float(jax_loss))
    norm_gap = abs(ref.grad_norm(t_obs, t_act) / float(optax.global_norm(grads)) - 1)
    if loss_gap > 1e-4 or norm_gap > 1e-3:
        raise SystemExit(f"PyTorch reference disagrees with the JAX world model: loss rel. gap "
                         f"{loss_gap:.2e}, gradient-norm rel. gap {norm_gap:.2e}")

    def run():
        for _ in range(n_updates):
            loss = ref.step(torch.randn(cfg.batch_size, SEGMENT, OBS),
                            torch.rand(cfg.batch_size, SEGMENT, ACT) * 2 - 1)
        return loss

    run()  # warm-up
    best = best_seconds(run, repeats, torch_wait)
    return {"ms_per_update": 1e3 * best / n_updates, "threads": torch.get_num_threads(),
            "version": torch.__version__, "loss_rel_gap": loss_gap, "grad_norm_rel_gap": norm_gap}


def main(argv=None) -> None:
    from hprior_jax.prior.world_model import DROPOUT_RNGS

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--sizes", nargs="+", default=["reduced", "paper"], choices=["reduced", "paper"])
    p.add_argument("--seeds", nargs="*", type=int, default=[1, 5], help="(none: credit rows only)")
    p.add_argument("--updates", type=int, default=3, help="updates per timed run")
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--dropout-rng", nargs="+", default=[None], choices=DROPOUT_RNGS,
                   help="PRNG of the dropout masks (default: the config's)")
    p.add_argument("--credit-pairs", nargs="*", type=int, default=[100, 1000],
                   help="stored pairs whose α the credit rows time (none: skip)")
    p.add_argument("--device", default="cpu", choices=["cpu", "gpu"])
    p.add_argument("--no-torch", action="store_true", help="skip the PyTorch reference")
    p.add_argument("--out", type=Path, default=RESULTS)
    p.add_argument("--append", action="store_true",
                   help="keep the rows already in --out (same columns) and add these")
    args = p.parse_args(argv)
    if any(s < 1 for s in args.seeds) or args.updates < 1 or args.repeats < 1:
        p.error("--seeds, --updates and --repeats must be >= 1")
    select_device(args.device)
    peak = matmul_gflops_s(args.repeats)
    kept = read_rows(args.out) if args.append else []
    rows = []
    for size in args.sizes:
        ref = None if args.no_torch else torch_reference(p, torch_update_ms, size, args.updates,
                                                         args.repeats)
        if ref:
            print(f"{size}: pytorch {ref['version']} ({ref['threads']} threads) "
                  f"{ref['ms_per_update']:.1f} ms/update; same loss as JAX within "
                  f"{ref['loss_rel_gap']:.1e}, gradient norm within {ref['grad_norm_rel_gap']:.1e}")
        for dropout_rng, n_seeds in itertools.product(args.dropout_rng, args.seeds):
            res = jax_update_ms(size, n_seeds, args.updates, args.repeats, dropout_rng)
            if "skipped" in res:
                print(f"{size}, {n_seeds} seeds, dropout {dropout_rng or 'default'}: skipped, "
                      f"{res['skipped']}", flush=True)
                continue
            row = {"sizes": size, "layers": res["layers"], "embed": res["embed"],
                   "batch": res["batch"], "seeds": n_seeds, "dropout_rng": res["dropout_rng"],
                   "device": res["device"],
                   **against_torch(res["ms_per_update"], n_seeds, res["compile_s"],
                                   ref and ref["ms_per_update"], res["gflop"], peak),
                   "jax_temp_gib": round(res["temp_gib"], 2), "machine": machine()}
            rows.append(row)
            print("  ".join(f"{k}={v}" for k, v in row.items() if k != "machine"), flush=True)
            write_rows(rows, args.out, kept)  # after every row: a later crash loses nothing
        credit = [{"sizes": size, "pairs": n, "credit_ms": round(credit_ms(size, n, args.repeats), 1),
                   "machine": machine()} for n in args.credit_pairs]
        for row in credit:
            print(f"{size}: α of {row['pairs']} stored pairs in {row['credit_ms']} ms", flush=True)
        if credit:
            credit_out = args.out.with_name(CREDIT_RESULTS.name)
            write_rows(credit, credit_out, read_rows(credit_out) if args.append else [])


if __name__ == "__main__":
    main()
