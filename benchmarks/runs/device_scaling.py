"""The cost of splitting seeds over devices: one run on 1, 2 and 4 devices, same script.

    python -m benchmarks.runs.device_scaling [--task cheetah_run] [--algo sac] [--steps 2000]
                                        [--devices 1 2 4] [--preset reduced]

Each is one `hprior train` child (`benchmarks.runs.end_to_end.one_run`, empty compilation cache)
with 4 seeds and `--devices N`. On a CPU the devices are XLA's forced host devices
(`--xla_force_host_platform_device_count=4`), which share the machine's cores: the rate should
stay flat, and any drop is the overhead of the sharded programs and the host's gathering.
On a machine with several GPUs the same command measures the real scaling. Writes
benchmarks/results/runs/device_scaling.csv: env steps/s over all seeds (compile excluded), the
chunk, event and evaluation seconds, compile seconds, and the ratio to one device.
"""
from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import tasks  # noqa: F401  (sets XLA_FLAGS before jax is imported)
from benchmarks._timing import machine, write_rows
from benchmarks.runs.end_to_end import one_run

RESULTS = Path(__file__).resolve().parents[1] / "results" / "runs" / "device_scaling.csv"


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--task", default="cheetah_run")
    p.add_argument("--algo", default="sac")
    p.add_argument("--preset", default="reduced")
    p.add_argument("--steps", type=int, default=2000)
    p.add_argument("--seeds", type=int, default=4)
    p.add_argument("--devices", nargs="+", type=int, default=[1, 2, 4])
    p.add_argument("--device", default="cpu", choices=["cpu", "gpu"])
    p.add_argument("--out", type=Path, default=RESULTS)
    args = p.parse_args(argv)
    import os

    flags = os.environ.get("XLA_FLAGS", "")
    env = ({"XLA_FLAGS": f"{flags} --xla_force_host_platform_device_count={max(args.devices)}"}
           if args.device == "cpu" else {})
    rows = []
    with tempfile.TemporaryDirectory(prefix="hprior_devices_") as tmp:
        for n in args.devices:
            row = one_run(args.task, args.algo, args.seeds, args.preset, args.steps, Path(tmp),
                          args.device, extra_args=("--devices", str(n)), extra_env=env,
                          name=f"{args.algo}_{n}dev")
            rows.append({"machine": machine(), "devices": n, **row})
            print(f"{n} device(s): {row['env_steps_per_s']:.0f} env steps/s, chunks "
                  f"{row['chunk_s']:.1f} s, compile {row['compile_s']:.1f} s", flush=True)
    one = next((r for r in rows if r["devices"] == 1), None)
    for r in rows:
        r["rate_vs_one_device"] = (round(r["env_steps_per_s"] / one["env_steps_per_s"], 3)
                                   if one else "")
    write_rows([{k: round(v, 3) if isinstance(v, float) else v for k, v in r.items()}
                for r in rows], args.out)


if __name__ == "__main__":
    main()
