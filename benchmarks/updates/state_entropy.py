"""PEBBLE's k-NN state entropy per SAC step: ours (JAX, seeds vmapped) against BPref's
`compute_state_entropy` written out in PyTorch, same script.

    python -m benchmarks.updates.state_entropy [--counts 1000 5000 10000] [--batch 256] [--seeds 5]

One call = the (k+1)-th nearest-neighbour distance of a SAC batch of states (`--batch`, the
`reduced` preset's 256) among the `count` states stored so far, in a buffer of `--capacity`
rows (50k: the reduced preset's run length), obs size 17 (cheetah: normal states, 8 at scale
1 and 9 at scale 10, as its positions and velocities), k = 5. It is what every
SAC update of PEBBLE's unsupervised phase computes first (steps 1000-10000), for each seed.
- JAX: `hprior_jax.pbrl.state_entropy.knn_distance`, jitted, vmapped over `--seeds` seeds
  (each its own buffer), as the training chunk runs it; ms per seed = call / seeds.
- PyTorch: BPref's loop (agent/sac.py `compute_state_entropy`: `torch.norm` of the
  differences to 500-row slices of the buffer, concatenated, `kthvalue(k + 1)`), one seed,
  torch's default intra-op threads.
`speedup` = PyTorch ms / JAX ms per seed (> 1: JAX faster); `max_abs_diff`: the two sides'
distances on the same data (the first seed's). Writes benchmarks/results/updates/state_entropy.csv.
"""
from __future__ import annotations

import argparse
from functools import partial
from pathlib import Path

import tasks  # noqa: F401  (sets XLA_FLAGS before jax is imported)
import jax
import jax.numpy as jnp
import numpy as np

from benchmarks._timing import best_seconds, write_rows
from hprior_jax.pbrl.state_entropy import knn_distance

RESULTS = Path(__file__).resolve().parents[1] / "results" / "updates" / "state_entropy.csv"
OBS = 17  # cheetah_run
K = 5


def bpref_knn(obs, full_obs, k: int):
    """BPref agent/sac.py `compute_state_entropy` (the distances it returns, before std
    normalisation)."""
    import torch

    with torch.no_grad():
        dists = []
        for idx in range(len(full_obs) // 500 + 1):
            dists.append(torch.norm(obs[:, None, :] - full_obs[None, idx * 500:(idx + 1) * 500, :],
                                    dim=-1, p=2))
        return torch.kthvalue(torch.cat(dists, dim=1), k=k + 1, dim=1).values


def measure(count: int, batch: int, capacity: int, n_seeds: int, repeats: int) -> dict:
    import torch

    rng = np.random.default_rng(count)
    scale = np.r_[np.ones(8), 10 * np.ones(OBS - 8)]  # cheetah: 8 positions, 9 velocities
    buffers = (rng.normal(size=(n_seeds, capacity, OBS)) * scale).astype(np.float32)
    picks = rng.integers(0, count, size=(n_seeds, batch))
    states = np.take_along_axis(buffers, picks[..., None], axis=1)  # batch states are stored

    fn = jax.jit(jax.vmap(partial(knn_distance, k=K), in_axes=(0, 0, None)))
    args = (jnp.asarray(states), jnp.asarray(buffers), jnp.asarray(count, jnp.int32))
    ours = np.asarray(fn(*args))
    jax_s = best_seconds(lambda: fn(*args), repeats, jax.block_until_ready)

    obs_t, full_t = torch.from_numpy(states[0]), torch.from_numpy(buffers[0, :count])
    theirs = bpref_knn(obs_t, full_t, K).numpy()
    torch_s = best_seconds(lambda: bpref_knn(obs_t, full_t, K), repeats)
    jax_ms = 1e3 * jax_s / n_seeds
    return {"count": count, "batch": batch, "capacity": capacity, "seeds": n_seeds,
            "jax_ms_per_seed": round(jax_ms, 3), "torch_ms": round(1e3 * torch_s, 3),
            "speedup": round(1e3 * torch_s / jax_ms, 2),
            "max_abs_diff": float(np.max(np.abs(ours[0] - theirs))),
            "max_rel_diff": float(np.max(np.abs(ours[0] - theirs) / theirs))}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--counts", type=int, nargs="+", default=[1000, 5000, 10000])
    p.add_argument("--batch", type=int, default=256)
    p.add_argument("--capacity", type=int, default=50_000)
    p.add_argument("--seeds", type=int, default=5)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--label", default="", help="a note kept in each row (e.g. the commit)")
    p.add_argument("--out", type=Path, default=RESULTS)
    args = p.parse_args(argv)
    rows = []
    for count in args.counts:
        rows.append({**measure(count, args.batch, args.capacity, args.seeds, args.repeats),
                     "label": args.label})
        print(rows[-1], flush=True)
    write_rows(rows, args.out)


if __name__ == "__main__":
    main()
