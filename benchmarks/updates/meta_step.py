"""MRN's meta step against the SAC update it replaces, same script, same sizes.

    python -m benchmarks.updates.meta_step [--sizes dmc metaworld reduced] [--repeats 5]

One meta step = hprior_jax.pbrl.meta_reward.bilevel_update: the reward ensemble on the SAC
batch, one virtual critic step, the outer loss on `pairs` recent labelled pairs and its
second-order gradient into the ensemble, the ensemble's Adam step, then the real SAC update.
Reference = `SAC.update` on the same batch. Both jitted, one seed, best of `--repeats` after a
warm-up; compile timed apart. Sizes: the appendix's SAC (Table 2: DMC 2 x 1024, batch 512,
cheetah obs 17 / action 6; MetaWorld 3 x 256, batch 1024, obs 39 / action 4), BPref's reward
ensemble (3 x 256 x 3) and 100 pairs of 50 steps; `reduced` = the CPU preset's SAC (256 x 2,
batch 256) on cheetah with 10 pairs. Writes benchmarks/results/updates/meta_step.csv.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import tasks  # noqa: F401  (sets XLA_FLAGS before jax is imported)
from benchmarks._timing import best_seconds, machine, write_rows

RESULTS = Path(__file__).resolve().parents[1] / "results" / "updates" / "meta_step.csv"
SIZES = {  # name: (obs, action, hidden, depth, batch, pairs)
    "dmc": (17, 6, 1024, 2, 512, 100),
    "metaworld": (39, 4, 256, 3, 1024, 50),
    "reduced": (17, 6, 256, 2, 256, 10),
}
SEGMENT = 50


def measure(size: str, repeats: int) -> dict:
    import jax
    import jax.numpy as jnp

    from hprior_jax.agents.sac import SAC, Batch, SACConfig
    from hprior_jax.buffers.preferences import PreferenceBatch
    from hprior_jax.networks.reward_ensemble import RewardConfig, init_reward_ensemble
    from hprior_jax.pbrl.meta_reward import bilevel_update
    from hprior_jax.pbrl.preference import make_optimizer

    obs, act, hidden, depth, batch, n_pairs = SIZES[size]
    sac = SAC(obs, act, SACConfig(hidden_dim=hidden, hidden_depth=depth, batch_size=batch))
    reward_cfg = RewardConfig()
    tx = make_optimizer()
    k = jax.random.split(jax.random.key(0), 9)
    state = sac.init(k[0])
    phi = init_reward_ensemble(k[1], obs, act, reward_cfg)
    opt = tx.init(phi)
    data = Batch(obs=jax.random.normal(k[2], (batch, obs)),
                 action=jax.random.uniform(k[3], (batch, act), minval=-1, maxval=1),
                 reward=jnp.zeros((batch,)), next_obs=jax.random.normal(k[4], (batch, obs)),
                 not_done=jnp.ones((batch,)))
    segs = lambda key, d: jax.random.normal(key, (n_pairs, SEGMENT, d))
    pairs = PreferenceBatch(segs(k[5], obs), segs(k[6], act), segs(k[7], obs), segs(k[8], act),
                            labels=jnp.arange(n_pairs, dtype=jnp.int32) % 2)
    mask = jnp.ones((n_pairs,), bool)
    key, step = jax.random.key(1), jnp.int32(10)

    meta = jax.jit(lambda s, p, o: bilevel_update(sac, s, p, o, data, pairs, mask, key, step,
                                                  reward_tx=tx, reward_cfg=reward_cfg,
                                                  outer_weight=0.1))
    plain = jax.jit(lambda s: sac.update(s, data, key, step))
    out = {}
    for name, fn, args in (("meta_step", meta, (state, phi, opt)), ("sac_update", plain, (state,))):
        t0 = time.perf_counter()
        compiled = fn.lower(*args).compile()
        out[f"{name}_compile_s"] = time.perf_counter() - t0
        jax.block_until_ready(compiled(*args))
        out[f"{name}_ms"] = 1e3 * best_seconds(lambda: compiled(*args), repeats,
                                               wait=jax.block_until_ready)
    return {"size": size, "obs": obs, "action": act, "hidden": hidden, "depth": depth,
            "batch": batch, "pairs": n_pairs, **out,
            "meta_over_sac": out["meta_step_ms"] / out["sac_update_ms"], "machine": machine()}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--sizes", nargs="+", default=list(SIZES), choices=list(SIZES))
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--out", type=Path, default=RESULTS)
    args = p.parse_args(argv)
    rows = []
    for size in args.sizes:
        row = measure(size, args.repeats)
        rows.append(row)
        print(f"{size}: meta step {row['meta_step_ms']:.1f} ms, SAC update "
              f"{row['sac_update_ms']:.1f} ms, ratio {row['meta_over_sac']:.2f}", flush=True)
    write_rows([{k: round(v, 3) if isinstance(v, float) else v for k, v in r.items()}
                for r in rows], args.out)


if __name__ == "__main__":
    main()
