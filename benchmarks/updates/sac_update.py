"""One SAC update per second: our JAX SAC against a BPref-style PyTorch SAC, same script.

    pip install -e ".[bench]" -c requirements.lock        # torch (CPU), benchmarks only
    python -m benchmarks.updates.sac_update [--sizes dmc metaworld] [--seeds 1 5] [--updates 20]

One update = critic step, actor step, temperature step and the target EMA (every 2nd step),
on random data drawn inside the timed loop in both implementations (as a replay sample is).
Sizes are the appendix's (Table 2): DMC 2 x 1024 hidden, batch 512, obs 17 / action 6
(cheetah); MetaWorld 3 x 256, batch 1024, obs 39 / action 4.

- JAX: `hprior_jax.agents.sac.SAC.update`, the function training runs, inside
  `jit(vmap(lax.scan(update)))` over `--updates` steps and `--seeds` seeds; compile timed apart.
  Each XLA setting in `--eigen` runs in its own child process, because XLA reads XLA_FLAGS
  once at import: `single` = `--xla_cpu_multi_thread_eigen=false` (what every run uses, see
  tasks/_xla_flags.py), `multi` = Eigen's thread pool on.
- PyTorch: the BPref update written out here (nn.Linear MLPs, torch.optim.Adam, rsample
  through tanh), one seed at a time as BPref runs, torch's default intra-op threads.

Prints ms per update and per seed, `speedup` = PyTorch ms per seed / JAX ms per seed (> 1: JAX
faster), `seeds_cost_over_one` = time of the vmapped update over that of one seed, and a
roofline: the update's FLOPs by XLA's cost analysis, the GFLOP/s each side reaches with them,
and `matmul_gflops_s`, what the device sustains on 2048^2 float32 matmuls (measured in the same
child). Writes benchmarks/results/updates/sac_update.csv. `--device gpu` runs the JAX side
on the GPU (PyTorch stays on the CPU as the reference the users have).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import tasks  # noqa: F401  (sets XLA_FLAGS before jax is imported)
from benchmarks._timing import (torch_wait, against_torch, best_seconds, machine, matmul_gflops_s,
                                torch_reference, write_rows, xla_gflop)

RESULTS = Path(__file__).resolve().parents[1] / "results" / "updates" / "sac_update.csv"
SIZES = {  # name: (obs, action, hidden, depth, batch) from appendix Table 2
    "dmc": (17, 6, 1024, 2, 512),
    "metaworld": (39, 4, 256, 3, 1024),
}
EIGEN_FLAG = {"single": "--xla_cpu_multi_thread_eigen=false",
              "multi": "--xla_cpu_multi_thread_eigen=true"}


# -- JAX --------------------------------------------------------------------------------------
def jax_update_ms(size: str, n_seeds: int, n_updates: int, repeats: int) -> dict:
    """Best-of-`repeats` ms per update (all seeds together) of our SAC.update, and compile s."""
    import jax
    import jax.numpy as jnp

    from hprior_jax.agents.sac import SAC, Batch, SACConfig

    obs, act, hidden, depth, batch = SIZES[size]
    sac = SAC(obs, act, SACConfig(hidden_dim=hidden, hidden_depth=depth, batch_size=batch))

    def run(state, key):
        def body(carry, step):
            state, key = carry
            key, k_data, k_update = jax.random.split(key, 3)
            ko, ka, kr, kn = jax.random.split(k_data, 4)
            data = Batch(obs=jax.random.normal(ko, (batch, obs)),
                         action=jax.random.uniform(ka, (batch, act), minval=-1, maxval=1),
                         reward=jax.random.normal(kr, (batch,)),
                         next_obs=jax.random.normal(kn, (batch, obs)),
                         not_done=jnp.ones((batch,)))
            state, metrics = sac.update(state, data, k_update, step)
            return (state, key), metrics["train/critic_loss"]
        (state, _), losses = jax.lax.scan(body, (state, key), jnp.arange(n_updates))
        return state, losses

    keys = jax.random.split(jax.random.key(0), n_seeds)
    states = jax.jit(jax.vmap(sac.init))(keys)
    t0 = time.perf_counter()
    fn = jax.jit(jax.vmap(run)).lower(states, keys).compile()
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(fn(states, keys))  # warm-up
    best = best_seconds(lambda: fn(states, keys), repeats, jax.block_until_ready)
    _, losses = fn(states, keys)
    if not bool(jnp.all(jnp.isfinite(losses))):
        raise RuntimeError(f"JAX SAC produced non-finite losses at {size} sizes")
    one = jax.tree.map(lambda x: x[0], states)
    data = Batch(jnp.zeros((batch, obs)), jnp.zeros((batch, act)), jnp.zeros((batch,)),
                 jnp.zeros((batch, obs)), jnp.ones((batch,)))
    return {"ms_per_update": 1e3 * best / n_updates, "compile_s": compile_s,
            "device": jax.devices()[0].device_kind,
            "gflop_per_update": xla_gflop(jax.jit(sac.update), one, data, keys[0], 0),
            "matmul_gflops_s": matmul_gflops_s(repeats)}


def jax_in_child(size: str, n_seeds: int, n_updates: int, repeats: int, eigen: str,
                 device: str) -> dict:
    """Runs `jax_update_ms` in a fresh Python whose XLA_FLAGS carry the Eigen setting."""
    flags = " ".join(f for f in os.environ.get("XLA_FLAGS", "").split()
                     if "xla_cpu_multi_thread_eigen" not in f)
    env = dict(os.environ, XLA_FLAGS=f"{flags} {EIGEN_FLAG[eigen]}".strip())
    if device == "cpu":
        env["JAX_PLATFORMS"] = "cpu"
    cmd = [sys.executable, "-m", "benchmarks.updates.sac_update", "--child", size, str(n_seeds),
           str(n_updates), str(repeats)]
    out = subprocess.run(cmd, env=env, capture_output=True, text=True,
                         cwd=Path(__file__).resolve().parents[2])
    if out.returncode != 0:
        raise RuntimeError(f"JAX child failed ({' '.join(cmd)}):\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


# -- PyTorch, BPref style ---------------------------------------------------------------------
def torch_update_ms(size: str, n_updates: int, repeats: int) -> dict:
    """Best-of-`repeats` ms per update of BPref's SAC update (agent/sac.py) for one seed."""
    import torch
    import torch.nn.functional as F
    from torch import nn

    torch.manual_seed(0)
    obs, act, hidden, depth, batch = SIZES[size]

    def mlp(inp, out):
        layers, width = [], inp
        for _ in range(depth):
            layers += [nn.Linear(width, hidden), nn.ReLU(inplace=True)]
            width = hidden
        return nn.Sequential(*layers, nn.Linear(width, out))

    actor = mlp(obs, 2 * act)
    q1, q2 = mlp(obs + act, 1), mlp(obs + act, 1)
    q1_t, q2_t = mlp(obs + act, 1), mlp(obs + act, 1)
    q1_t.load_state_dict(q1.state_dict())
    q2_t.load_state_dict(q2.state_dict())
    critic_params = list(q1.parameters()) + list(q2.parameters())
    target_params = list(q1_t.parameters()) + list(q2_t.parameters())
    log_alpha = torch.tensor(math.log(0.1), requires_grad=True)
    actor_opt = torch.optim.Adam(actor.parameters(), lr=1e-3)
    critic_opt = torch.optim.Adam(critic_params, lr=1e-3)
    alpha_opt = torch.optim.Adam([log_alpha], lr=1e-4)
    target_entropy = -float(act)

    def sample(o):  # SquashedNormal.rsample and log_prob as in BPref agent/actor.py
        mu, log_std = actor(o).chunk(2, dim=-1)
        log_std = -5.0 + 0.5 * 7.0 * (torch.tanh(log_std) + 1)
        std = log_std.exp()
        u = mu + std * torch.randn_like(mu)
        log_prob = (-0.5 * ((u - mu) / std) ** 2 - log_std - 0.5 * math.log(2 * math.pi)
                    - 2.0 * (math.log(2.0) - u - F.softplus(-2.0 * u)))
        return torch.tanh(u), log_prob.sum(-1, keepdim=True)

    def update(step):
        o, n = torch.randn(batch, obs), torch.randn(batch, obs)
        a = torch.rand(batch, act) * 2 - 1
        r, not_done = torch.randn(batch, 1), torch.ones(batch, 1)
        with torch.no_grad():  # BPref builds this graph, then detaches: same values, more work
            na, nlp = sample(n)
            na_in = torch.cat([n, na], -1)
            tv = torch.min(q1_t(na_in), q2_t(na_in)) - log_alpha.exp() * nlp
            tq = r + not_done * 0.99 * tv
        oa = torch.cat([o, a], -1)
        critic_loss = F.mse_loss(q1(oa), tq) + F.mse_loss(q2(oa), tq)
        critic_opt.zero_grad()
        critic_loss.backward()
        critic_opt.step()

        pa, lp = sample(o)
        pa_in = torch.cat([o, pa], -1)
        actor_loss = (log_alpha.exp().detach() * lp - torch.min(q1(pa_in), q2(pa_in))).mean()
        actor_opt.zero_grad()
        actor_loss.backward()
        actor_opt.step()
        alpha_loss = (log_alpha.exp() * (-lp - target_entropy).detach()).mean()
        alpha_opt.zero_grad()
        alpha_loss.backward()
        alpha_opt.step()

        if step % 2 == 0:
            with torch.no_grad():
                for p, t in zip(critic_params, target_params):
                    t.data.mul_(1 - 5e-3).add_(p.data, alpha=5e-3)
        return critic_loss

    update(0)  # warm-up
    best = best_seconds(lambda: [update(step) for step in range(n_updates)], repeats, torch_wait)
    if not torch.isfinite(update(0)):
        raise RuntimeError("PyTorch SAC produced a non-finite loss")
    return {"ms_per_update": 1e3 * best / n_updates, "threads": torch.get_num_threads(),
            "version": torch.__version__}


# -- driver -----------------------------------------------------------------------------------
def main(argv=None) -> None:
    if argv is None and len(sys.argv) > 1 and sys.argv[1] == "--child":
        size, n_seeds, n_updates, repeats = sys.argv[2], *map(int, sys.argv[3:6])
        print(json.dumps(jax_update_ms(size, n_seeds, n_updates, repeats)))
        return
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--sizes", nargs="+", default=list(SIZES), choices=list(SIZES))
    p.add_argument("--seeds", nargs="+", type=int, default=[1, 5])
    p.add_argument("--updates", type=int, default=20, help="updates per timed run")
    p.add_argument("--repeats", type=int, default=3, help="timed runs; the best is kept")
    p.add_argument("--eigen", nargs="+", default=["single", "multi"], choices=list(EIGEN_FLAG),
                   help="XLA CPU Eigen threading settings to measure (each in a child process)")
    p.add_argument("--device", default="cpu", choices=["cpu", "gpu"])
    p.add_argument("--no-torch", action="store_true", help="skip the PyTorch reference")
    p.add_argument("--out", type=Path, default=RESULTS)
    args = p.parse_args(argv)
    if any(s < 1 for s in args.seeds) or args.updates < 1 or args.repeats < 1:
        p.error("--seeds, --updates and --repeats must be >= 1")
    eigen = args.eigen if args.device == "cpu" else ["single"]  # the flag is CPU-only

    rows = []
    for size in args.sizes:
        ref = None
        if not args.no_torch:
            ref = torch_reference(p, torch_update_ms, size, args.updates, args.repeats)
            print(f"{size}: pytorch {ref['version']} ({ref['threads']} threads) "
                  f"{ref['ms_per_update']:.1f} ms/update", flush=True)
        for setting in eigen:
            for n_seeds in args.seeds:
                res = jax_in_child(size, n_seeds, args.updates, args.repeats, setting,
                                   args.device)
                row = {"sizes": size, "seeds": n_seeds, "device": res["device"],
                       "xla_eigen": setting if args.device == "cpu" else "",
                       **against_torch(res["ms_per_update"], n_seeds, res["compile_s"],
                                       ref["ms_per_update"] if ref else None,
                                       res["gflop_per_update"], res["matmul_gflops_s"]),
                       "seeds_cost_over_one": "", "updates": args.updates, "machine": machine()}
                one = next((r for r in rows if r["sizes"] == size and r["seeds"] == 1
                            and r["xla_eigen"] == row["xla_eigen"]), None)
                if one is not None and n_seeds > 1:
                    row["seeds_cost_over_one"] = round(
                        row["jax_ms_per_update"] / one["jax_ms_per_update"], 2)
                rows.append(row)
                print("  " + "  ".join(f"{k}={v}" for k, v in row.items()
                                       if k not in ("sizes", "machine", "updates")), flush=True)

    write_rows(rows, args.out)


if __name__ == "__main__":
    main()
