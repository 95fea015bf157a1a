"""The seed axis over devices: one mesh axis, programs that never talk across it.

Seeds are independent, so a run's programs are `shard_map`s of the per-seed function over a
one-axis mesh: every device runs `vmap` over its own seeds with no collective at all, and
the run's state (replay buffers, env batches, networks) lives on its seed's device. The
host gathers metrics only. With several processes (`jax.distributed`, one per host) the
mesh spans every process's devices; each process holds its own seeds' state and all of them
run the same host loop, while one (the primary) writes the logs.
"""
from __future__ import annotations

import os

import jax
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

SEEDS = "seeds"


class DeviceCountError(ValueError):
    pass


def initialize_distributed() -> bool:
    """Joins a multi-process run when the environment describes one; returns whether it did.

    Standard variables: `JAX_COORDINATOR_ADDRESS` (host:port of process 0), `JAX_NUM_PROCESSES`,
    `JAX_PROCESS_ID`; or a SLURM job step with more than one task (`srun`), which JAX reads
    itself. Nothing set: a single process, as before."""
    if jax.distributed.is_initialized():
        return True
    address = os.environ.get("JAX_COORDINATOR_ADDRESS")
    if address:
        try:
            num, pid = int(os.environ["JAX_NUM_PROCESSES"]), int(os.environ["JAX_PROCESS_ID"])
        except KeyError as e:
            raise DeviceCountError(f"JAX_COORDINATOR_ADDRESS is set but {e.args[0]} is not; "
                                   "set JAX_NUM_PROCESSES and JAX_PROCESS_ID on every host")
        jax.distributed.initialize(address, num_processes=num, process_id=pid)
        return True
    if int(os.environ.get("SLURM_NTASKS", "1")) > 1 and "SLURM_STEP_ID" in os.environ:
        jax.distributed.initialize()  # SLURM's variables, detected by JAX
        return True
    return False


def checked_count(n: int, available) -> int:
    """`n`, refused with its reason unless this process sees that many devices."""
    if not 1 <= n <= len(available):
        raise DeviceCountError(f"--devices {n}: this process sees {len(available)} "
                               f"device(s) ({available[0].platform})")
    return n


def devices_per_run(num_seeds: int, num_devices: int) -> int:
    """The most devices (at most `num_devices`) that split `num_seeds` seeds evenly."""
    return max(d for d in range(1, num_devices + 1) if num_seeds % d == 0)


def is_primary() -> bool:
    return jax.process_index() == 0


def seed_mesh(num_seeds: int, devices=None) -> Mesh:
    """A mesh of `devices` devices (default: as many as divide the seeds evenly; a list of
    devices: exactly those) along the seed axis. Every device holds the same number of
    seeds."""
    if devices is not None and not isinstance(devices, int):
        if num_seeds % len(devices):
            raise DeviceCountError(f"{len(devices)} devices do not divide the {num_seeds} "
                                   "seeds; every device holds the same number of seeds")
        return Mesh(np.array(list(devices)), (SEEDS,))
    available = jax.devices()
    if jax.process_count() > 1:
        # every process runs the same programs, so every one must own some of the seeds
        n = len(available) if devices is None else devices
        if n != len(available) or num_seeds % n:
            raise DeviceCountError(
                f"{jax.process_count()} processes with {len(available)} devices in all: give a "
                f"multiple of {len(available)} seeds (got {num_seeds}) and use every device "
                f"(--devices {len(available)})")
        return Mesh(np.array(available), (SEEDS,))
    if devices is None:
        n = devices_per_run(num_seeds, len(available))
        if n < len(available) and n < num_seeds:
            print(f"{num_seeds} seeds on {len(available)} devices: using {n} (every device "
                  f"holds the same number of seeds; give a multiple of {len(available)} seeds "
                  "to use them all)", flush=True)
    else:
        n = checked_count(devices, available)
        if num_seeds % n:
            raise DeviceCountError(f"--devices {n} does not divide the {num_seeds} seeds; "
                                   f"every device holds the same number of seeds")
    return Mesh(np.array(available[:n]), (SEEDS,))


def over_seeds(mesh: Mesh, fn, in_axes, donate_argnums=(), compiler_options=None):
    """`jit` of `fn` (which maps over a leading seed axis: a vmap or lax.map) on the mesh.
    `in_axes[i]` is 0 for an argument with the seed axis (split over devices), None for one
    every seed shares (replicated). Every output has the seed axis. `compiler_options`:
    XLA's, for every compile of the program (called or lowered)."""
    split, shared = NamedSharding(mesh, P(SEEDS)), NamedSharding(mesh, P())
    # no collective inside, so the replication (vma) types that check them are not needed;
    # they would reject a scan whose carry starts shared (e.g. zeros) and ends per seed
    local = jax.shard_map(fn, mesh=mesh, in_specs=tuple(P(SEEDS) if a == 0 else P()
                                                         for a in in_axes),
                          out_specs=P(SEEDS), check_vma=False)
    return jax.jit(local, in_shardings=tuple(split if a == 0 else shared for a in in_axes),
                   out_shardings=split, donate_argnums=donate_argnums,
                   compiler_options=compiler_options or None)


def place(mesh: Mesh, tree):
    """Every leaf (leading seed axis) split over the mesh; host arrays, arrays on other
    devices or with another layout (a restored checkpoint, a grown buffer) alike. With
    several processes host values must be the same in every process (they are: every
    process builds them from the same config)."""
    split = NamedSharding(mesh, P(SEEDS))

    def one(x):
        if isinstance(x, jax.Array) and x.sharding == split:
            return x
        if isinstance(x, jax.Array) and not x.is_fully_addressable:
            return jax.jit(lambda y: y, out_shardings=split)(x)
        value = np.asarray(x)
        return jax.make_array_from_callback(value.shape, split, lambda index: value[index])

    return jax.tree.map(one, tree)


def fetch(tree):
    """Host numpy copies of `tree`'s leaves; across processes, the whole seed axis in every
    process. Host values (numpy, floats) pass through."""
    def one(x):
        if isinstance(x, jax.Array) and not x.is_fully_addressable:
            return np.asarray(multihost_utils.process_allgather(x, tiled=True))
        return np.asarray(jax.device_get(x))

    return jax.tree.map(one, tree)


def barrier(name: str) -> None:
    """Waits until every process gets here (a no-op with one process)."""
    if jax.process_count() > 1:
        multihost_utils.sync_global_devices(name)
