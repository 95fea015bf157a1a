"""One reward-ensemble minibatch step: our JAX PEBBLE reward learner against BPref's, same script.

    pip install -e ".[bench]" -c requirements.lock        # torch (CPU), benchmarks only
    python -m benchmarks.updates.reward_update [--sizes dmc metaworld] [--seeds 1 5] [--pairs 1024]

One step = every member of the ensemble (3 x 3x256, LeakyReLU, tanh) on its own minibatch of
128 labelled segment pairs (segment length 50), the Bradley-Terry cross-entropy on summed
segment rewards, one backward and one Adam step over all members (BPref
`RewardModel.train_reward`). Timed over one epoch of `--pairs` stored pairs.

- JAX: `hprior_jax.pbrl.preference.train_epoch`, the function training runs, under
  `jit(vmap(...))` over `--seeds`; compile timed apart; `--device gpu` on a GPU.
- PyTorch: BPref's loop written out here (nn.Sequential members, one Adam over all of them,
  per-member index permutations), one seed, torch's default threads.

Writes benchmarks/results/updates/reward_update.csv (an "update" in its columns = one minibatch
step): ms per step and per seed, `speedup` (PyTorch ms / JAX ms per seed), the step's FLOPs by
XLA's cost analysis and the GFLOP/s each side reaches.
"""
from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import tasks  # noqa: F401  (sets XLA_FLAGS before jax is imported)
from benchmarks._timing import (torch_wait, against_torch, best_seconds, machine, matmul_gflops_s,
                                select_device, torch_reference, write_rows, xla_gflop)

RESULTS = Path(__file__).resolve().parents[1] / "results" / "updates" / "reward_update.csv"
SIZES = {"dmc": (17, 6), "metaworld": (39, 4)}  # (obs, action): cheetah, MetaWorld
SEGMENT, BATCH, MEMBERS, HIDDEN = 50, 128, 3, (256, 256, 256)


def _random_store(key, n_pairs: int, obs: int, act: int):
    import jax
    import jax.numpy as jnp

    from hprior_jax.buffers.preferences import PreferenceStore

    k = jax.random.split(key, 5)
    shape = (n_pairs, SEGMENT)
    return PreferenceStore(
        obs1=jax.random.normal(k[0], shape + (obs,)), act1=jax.random.uniform(k[1], shape + (act,)),
        obs2=jax.random.normal(k[2], shape + (obs,)), act2=jax.random.uniform(k[3], shape + (act,)),
        labels=jax.random.bernoulli(k[4], 0.5, (n_pairs,)).astype(jnp.int32),
        ptr=jnp.int32(0), count=jnp.int32(n_pairs))


def epoch_program(size: str, n_seeds: int, n_pairs: int):
    """One epoch of `train_epoch` over `n_pairs` random stored pairs, `jit(vmap(...))` over
    `n_seeds` seeds, not yet compiled. -> (program, (params, opt_state, store, keys), epoch of
    one seed)."""
    import jax

    from hprior_jax.networks.reward_ensemble import RewardConfig, init_reward_ensemble
    from hprior_jax.pbrl.preference import PreferenceConfig, make_optimizer, train_epoch

    obs, act = SIZES[size]
    rcfg, pcfg = RewardConfig(hidden_sizes=HIDDEN, ensemble_size=MEMBERS), PreferenceConfig()
    tx = make_optimizer(pcfg)

    def init(key):
        params = init_reward_ensemble(key, obs, act, rcfg)
        return params, tx.init(params), _random_store(jax.random.fold_in(key, 1), n_pairs, obs, act)

    def epoch(params, opt_state, store, key):
        return train_epoch(params, opt_state, store, key, tx=tx, reward_cfg=rcfg, cfg=pcfg)

    keys = jax.random.split(jax.random.key(0), n_seeds)
    return jax.jit(jax.vmap(epoch)), (*jax.jit(jax.vmap(init))(keys), keys), epoch


def jax_step_ms(size: str, n_seeds: int, n_pairs: int, repeats: int) -> dict:
    import jax
    import jax.numpy as jnp

    program, (params, opt_state, store, keys), epoch = epoch_program(size, n_seeds, n_pairs)
    obs, act = SIZES[size]
    t0 = time.perf_counter()
    fn = program.lower(params, opt_state, store, keys).compile()
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(fn(params, opt_state, store, keys))
    best = best_seconds(lambda: fn(params, opt_state, store, keys), repeats,
                        jax.block_until_ready)
    loss = fn(params, opt_state, store, keys)[2]["loss"]
    if not bool(jnp.all(jnp.isfinite(loss))):
        raise RuntimeError("JAX reward training produced a non-finite loss")
    steps = math.ceil(n_pairs / BATCH)
    # FLOPs of one minibatch step = an epoch over exactly one batch of pairs, one seed
    one = jax.tree.map(lambda x: x[0], (params, opt_state))
    small = _random_store(keys[0], BATCH, obs, act)
    return {"ms_per_step": 1e3 * best / steps, "compile_s": compile_s,
            "gflop_per_step": xla_gflop(jax.jit(epoch), *one, small, keys[0]),
            "device": jax.devices()[0].device_kind}


def torch_step_ms(size: str, n_pairs: int, repeats: int) -> dict:
    """BPref `RewardModel.train_reward` for one epoch of `n_pairs` pairs (one seed)."""
    import numpy as np
    import torch
    from torch import nn

    torch.manual_seed(0)
    obs, act = SIZES[size]

    def member():
        layers, width = [], obs + act
        for h in HIDDEN:
            layers += [nn.Linear(width, h), nn.LeakyReLU()]
            width = h
        return nn.Sequential(*layers, nn.Linear(width, 1), nn.Tanh())

    ensemble = [member() for _ in range(MEMBERS)]
    opt = torch.optim.Adam([p for m in ensemble for p in m.parameters()], lr=3e-4)
    seg1 = np.random.randn(n_pairs, SEGMENT, obs + act).astype(np.float32)
    seg2 = np.random.randn(n_pairs, SEGMENT, obs + act).astype(np.float32)
    labels = np.random.randint(0, 2, n_pairs)
    ce = nn.CrossEntropyLoss()

    def epoch():
        perms = [np.random.permutation(n_pairs) for _ in range(MEMBERS)]
        for start in range(0, n_pairs, BATCH):
            opt.zero_grad()
            loss = 0.0
            for m, perm in zip(ensemble, perms):
                idx = perm[start:start + BATCH]
                r1 = m(torch.as_tensor(seg1[idx])).sum(1)
                r2 = m(torch.as_tensor(seg2[idx])).sum(1)
                logits = torch.cat([r1, r2], -1)
                loss = loss + ce(logits, torch.as_tensor(labels[idx]))
            loss.backward()
            opt.step()
        return loss

    epoch()  # warm-up
    best = best_seconds(epoch, repeats, torch_wait)
    return {"ms_per_step": 1e3 * best / math.ceil(n_pairs / BATCH),
            "threads": torch.get_num_threads(), "version": torch.__version__}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--sizes", nargs="+", default=list(SIZES), choices=list(SIZES))
    p.add_argument("--seeds", nargs="+", type=int, default=[1, 5])
    p.add_argument("--pairs", type=int, default=1024, help="labelled pairs in the store")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--no-torch", action="store_true", help="skip the PyTorch reference")
    p.add_argument("--device", default="cpu", choices=["cpu", "gpu"], help="for the JAX side")
    p.add_argument("--out", type=Path, default=RESULTS)
    args = p.parse_args(argv)
    if any(s < 1 for s in args.seeds) or args.pairs < 1 or args.repeats < 1:
        p.error("--seeds, --pairs and --repeats must be >= 1")
    select_device(args.device)
    peak = matmul_gflops_s(args.repeats)
    rows = []
    for size in args.sizes:
        ref = None if args.no_torch else torch_reference(p, torch_step_ms, size, args.pairs,
                                                         args.repeats)
        for n_seeds in args.seeds:
            res = jax_step_ms(size, n_seeds, args.pairs, args.repeats)
            row = {"sizes": size, "seeds": n_seeds, "device": res["device"],
                   **against_torch(res["ms_per_step"], n_seeds, res["compile_s"],
                                   ref["ms_per_step"] if ref else None, res["gflop_per_step"],
                                   peak),
                   "pairs": args.pairs, "machine": machine()}
            rows.append(row)
            print("  ".join(f"{k}={v}" for k, v in row.items() if k != "machine"), flush=True)
    write_rows(rows, args.out)


if __name__ == "__main__":
    main()
