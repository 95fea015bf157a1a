"""Stepping many envs at once: one vmap, or vmapped groups one after the other on CPU.

XLA on CPU steps a vmapped DM Control port more slowly per env at a wide batch than at a
narrow one. Batch 128, env steps/s, one vmap against 8 groups of 16 stepped in turn with
`lax.map` (this project's 2-core CPU, `python -m benchmarks.ports.env_throughput
--groups none 16`): walker 535 -> 1908, cheetah 9311 -> 15505, quadruped 1436 -> 2512
(benchmarks/results/ports/env_throughput_groups.csv). The MetaWorld ports, whose solver is already
capped at 5 iterations, gained nothing at batch 64 (0.70-1.42x across the six tasks, mostly
within run-to-run noise: `metaworld_throughput --group none|16`), so a task opts in with
`Task.cpu_group`. Each env runs the same operations either way (MJX's solver loops under
vmap leave a converged env unchanged until the rest of its batch is done), but XLA may
vectorise the two layouts differently: bit-identical states at XLA's default optimisation
level (one-off check, cheetah, 20 envs, 5 steps), up to float32 rounding at -O0
(`tests/tasks/test_batching.py`). On accelerators a wide batch is what they are for: one
vmap there.
"""
from __future__ import annotations

from typing import Callable

import jax

# the group that stepped fastest on this project's CPU (8 and 16 within 10% of each other,
# 32 no better than one vmap of 128)
CPU_GROUP = 16


def default_group(task) -> int | None:
    """`task.cpu_group` on a CPU backend, None (one vmap) on accelerators."""
    return getattr(task, "cpu_group", None) if jax.default_backend() == "cpu" else None


def group_from_option(text: str, task) -> int | None:
    """A benchmark's `--group(s)` value: "none" (one vmap), "auto" (`default_group(task)`)
    or a group size."""
    return None if text == "none" else default_group(task) if text == "auto" else int(text)


def group_size(batch: int, group: int | None) -> int | None:
    """The group `vmap_in_groups` steps `batch` envs in: the largest divisor of `batch` not
    above `group`, if it is at least half of `group`; None (one vmap) otherwise, or when
    `batch` fits one group."""
    if group is None or batch <= group:
        return None
    size = max(d for d in range(1, group + 1) if batch % d == 0)
    return size if 2 * size >= group else None


def vmap_in_groups(fn: Callable, group: int | None) -> Callable:
    """`jax.vmap(fn)` over the leading axis of every argument leaf, computed as
    `lax.map` over groups of `group_size(batch, group)` envs when there is one."""
    vmapped = jax.vmap(fn)

    def batched(*args):
        batch = jax.tree.leaves(args)[0].shape[0]
        size = group_size(batch, group)
        if size is None:
            return vmapped(*args)
        split = lambda x: x.reshape((batch // size, size) + x.shape[1:])
        out = jax.lax.map(lambda a: vmapped(*a), jax.tree.map(split, args))
        return jax.tree.map(lambda x: x.reshape((batch,) + x.shape[2:]), out)

    return batched
