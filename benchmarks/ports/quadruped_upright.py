"""Does quadruped_walk's reset distribution match dm_control's?
(python -m benchmarks.ports.quadruped_upright)

Whole-episode returns of quadruped are bimodal: a body that lands upright earns ~0.5 per step
with zero action, one that does not earns ~0. With 10 episodes per side
(benchmarks/ports/dm_control_parity.py) the means can differ 20x by chance, so this counts, over
many resets of each side, the share of zero-action episodes that end upright (reward > 0.4
at step `--steps`). Writes benchmarks/results/ports/quadruped_upright.csv.
"""
from __future__ import annotations

import argparse
import csv
from pathlib import Path

import tasks  # noqa: F401  (XLA flags before jax)
import jax
import jax.numpy as jnp
import numpy as np

from tasks.dm_control.reference import make_rollout, reference_env, reference_rollout

RESULTS = Path(__file__).resolve().parents[1] / "results" / "ports" / "quadruped_upright.csv"


def main(argv=None):
    parser = argparse.ArgumentParser()
    parser.add_argument("--resets", type=int, default=40)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--seed", type=int, default=5)
    args = parser.parse_args(argv)
    task = tasks.make("quadruped_walk")
    n, t = args.resets, args.steps
    states = jax.jit(jax.vmap(task.reset))(jax.random.split(jax.random.key(args.seed), n))
    _, rew, _ = make_rollout(task)(states, jnp.zeros((n, t, task.action_size)))
    ours = np.asarray(rew)[:, -1]
    theirs = []
    for i in range(n):
        env = reference_env("quadruped_walk", args.seed + 100 + i)
        env.reset()
        theirs.append(reference_rollout(env, np.zeros((t, task.action_size), np.float32))[1][-1])
    theirs = np.asarray(theirs)
    # binomial standard error of each share, to judge the gap
    rows = []
    for side, r in (("mjx", ours), ("dm_control", theirs)):
        p = float((r > 0.4).mean())
        rows.append(dict(side=side, resets=n, steps=t, upright_share=round(p, 4),
                         std_error=round(float(np.sqrt(p * (1 - p) / n)), 4),
                         final_reward_mean=round(float(r.mean()), 5)))
    RESULTS.parent.mkdir(exist_ok=True)
    with open(RESULTS, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    for r in rows:
        print(r)


if __name__ == "__main__":
    main()
